"""Marker corners from the lines of the marker's edges, free of the corner detector's bias
(docs/landmarks.md, "Marker corners").

An ArUco marker's outer corners are convex L-corners (a dark square on a light board). Blurred (the
lens, the pixels, the renderer's anti-aliasing), the tip of such a corner is rounded, and
``cv2.cornerSubPix`` (every gradient g_p in a window orthogonal to p - q) pulls q into the rounding:
inward, by a fixed fraction of a pixel. Measured on rendered VGA frames of the wall layout (markers
of 12-30 px, the renderer's fill exact): -0.23 px along the diagonal, which shrinks a 16 px marker
by 2 % and scales its range or the camera's self-calibrated focal length alike (edge lines:
+0.00 px). The straight parts of the edges are not biased: with a symmetric blur the intensity
across a straight edge rises fastest on the edge itself.

For each edge k from corner c_k to c_{k+1} (outward unit normal n_k), at samples
m_j = c_k + t_j (c_{k+1} - c_k), t_j in [a, 1 - a] (a keeps the samples off both corners' rounding),
the profile I_j(s) = I(m_j + s n_k), s in [-r, r] (bicubic: bilinear sampling locks the peak to
the pixel grid), gives the edge point

    e_j = m_j + s_j n_k,   s_j = argmax_s dI_j/ds   (a parabola through the three samples at the peak),

with r within the marker's black border (``BORDER_FRACTION`` of a cell): the edge between the
border and a white bit has the opposite sign and its tail barely moves the peak (the mid-level
between the profile's ends, tried first, is pulled outwards by it: +0.1 px with a 1 px blur). A
line l_k (a unit normal and an offset) is fitted to the e_j by total least squares
(``cv2.fitLine``), and corner k is the intersection of l_{k-1} and l_k. Lens distortion bends
an edge by far less than the edge noise over a marker's 12-40 px and is not modelled.

Measured (tests/test_marker_corners.py, a marker of 14-40 px drawn area-exact, blurred by a
Gaussian of 0.5-1.3 px): cornerSubPix -0.16 to -0.40 px along the diagonal, the edge lines within
+-0.03 px except markers under 18 px at 1 px of blur or more (+0.04 to +0.11 px).

A marker whose edges do not all give ``MIN_EDGE_POINTS`` points of contrast ``MIN_CONTRAST`` grey
levels or more, or whose refined corners move more than ``MAX_SHIFT`` px, keeps its corners.

The edge shift. A camera whose tone curve the station is not told (docs/frames.md), or a blur the
refinement does not see symmetric, moves every dark-to-light edge by the same e px along its outward
normal (measured on rendered VGA frames at gamma 0.45: e = -0.22 px with the anti-aliasing alone, on
markers of 12 and of 40-100 px alike; -0.76 px with a 1 px blur; linear: +0.00). Both lines through
corner k move by e, so the corner moves by e d_k, where

    [n_a; n_b] d_k = (1, 1)^T,   n_a, n_b the outward unit normals of the edges to c_{k-1} and c_{k+1}

(``edge_shift_jacobian``). A marker's size then reads 2 e px off while the distances between markers
do not: e is told apart from the focal length and the range in a view of two markers or more, and
agent/self_calibration.py estimates it with the intrinsics.
"""

from __future__ import annotations

import cv2
import numpy as np

BORDER_FRACTION = 0.6  # of a cell: how far the profile reaches into the marker's black border
MAX_REACH = 3.0  # px, the profile's half-length at most
MIN_REACH = 1.0  # px, ... and at least (below that the marker is too small to refine)
STEP = 0.25  # px between two profile samples
SAMPLE_SPACING = 0.5  # px between two profiles along an edge
MIN_EDGE_POINTS = 3
MIN_CONTRAST = 20.0  # grey levels between the two ends of a profile
MAX_SHIFT = 1.5  # px: a refinement that moves a corner further is not trusted


def refine_corners(gray: np.ndarray, corners: np.ndarray, cells: int) -> np.ndarray:
    """The 4 x 2 corners of one marker (cv2.aruco order, full-size pixels) re-estimated as the
    intersections of its edge lines (module docstring); ``cells`` is the marker's side in cells
    (bits plus the two border cells). Returns ``corners`` unchanged when the edges are not clear."""
    corners = np.asarray(corners, dtype=np.float64)
    side = float(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1).min())
    reach = min(MAX_REACH, BORDER_FRACTION * side / cells)
    if reach < MIN_REACH:
        return corners
    centre = corners.mean(axis=0)
    s = np.arange(-reach, reach + 1e-9, STEP)  # profile offsets across an edge
    points, normals = [], []  # per edge: the samples m_j, the outward unit normal n_k
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        n = np.array([d[1], -d[0]])
        if np.dot(n, 0.5 * (a + b) - centre) < 0:
            n = -n  # outward
        margin = min(0.4, (reach + 1.0) / length)
        t = np.linspace(margin, 1.0 - margin, max(MIN_EDGE_POINTS, int((1.0 - 2.0 * margin) * length / SAMPLE_SPACING)))
        points.append(a + t[:, None] * (b - a))
        normals.append(np.broadcast_to(n, points[-1].shape))
    samples, outward = np.concatenate(points), np.concatenate(normals)
    grid = samples[:, None, :] + s[None, :, None] * outward[:, None, :]  # samples of all four edges x steps x 2
    profile = cv2.remap(gray, grid[..., 0].astype(np.float32), grid[..., 1].astype(np.float32),
                        cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    e = samples + _steepest(profile, s)[:, None] * outward  # e_j
    lines = []
    for edge in np.split(e, np.cumsum([len(p) for p in points])[:-1]):
        edge = edge[np.isfinite(edge[:, 0])]
        if len(edge) < MIN_EDGE_POINTS:
            return corners
        vx, vy, x0, y0 = cv2.fitLine(edge.astype(np.float32), cv2.DIST_L2, 0, 0.01, 0.01).ravel()
        normal = np.array([-vy, vx], dtype=np.float64)
        lines.append((normal, float(normal @ np.array([x0, y0]))))
    refined = np.empty_like(corners)
    for k in range(4):
        (n1, o1), (n2, o2) = lines[k - 1], lines[k]
        A = np.array([n1, n2])
        if abs(np.linalg.det(A)) < 1e-3:
            return corners
        refined[k] = np.linalg.solve(A, [o1, o2])
    if np.linalg.norm(refined - corners, axis=1).max() > MAX_SHIFT:
        return corners
    return refined


def _steepest(profile: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Per row, the s where the profile rises fastest from dark (s < 0) to light, to a fraction of a
    step; NaN for a row without ``MIN_CONTRAST`` or whose steepest rise is at either end."""
    slope = np.gradient(profile, s, axis=1)
    k = np.argmax(slope, axis=1)
    rows = np.arange(len(profile))
    inner = np.clip(k, 1, len(s) - 2)
    before, at, after = slope[rows, inner - 1], slope[rows, inner], slope[rows, inner + 1]
    curvature = before - 2.0 * at + after
    offset = np.where(curvature < 0, 0.5 * (before - after) / np.where(curvature < 0, curvature, -1.0), 0.0)
    edge = s[inner] + np.clip(offset, -1.0, 1.0) * (s[1] - s[0])
    valid = (profile[:, -1] - profile[:, 0] >= MIN_CONTRAST) & (k > 0) & (k < len(s) - 1)
    return np.where(valid, edge, np.nan)


def edge_shift_jacobian(u: np.ndarray, group: np.ndarray) -> np.ndarray:
    """d u / d e (N x 2): each corner's move when every marker edge moves by e px along its outward
    normal (module docstring, the edge shift), for points ``u`` (N x 2) grouped by ``group``: a group of
    four is a marker's corners in cv2.aruco (cyclic) order; any other point (a colour blob) does not move."""
    u = np.asarray(u, dtype=np.float64)
    D = np.zeros_like(u)
    order = np.argsort(np.asarray(group), kind="stable")  # each group's points together, in their order
    _, starts, counts = np.unique(np.asarray(group)[order], return_index=True, return_counts=True)
    rows = order[starts[counts == 4][:, None] + np.arange(4)]  # M x 4: the markers' corners
    if not len(rows):
        return D
    quads = u[rows]
    edges = np.roll(quads, -1, axis=1) - quads  # edge k: corner k to k + 1
    n = np.stack([edges[..., 1], -edges[..., 0]], axis=-1) / np.maximum(np.linalg.norm(edges, axis=-1, keepdims=True), 1e-9)
    outward = np.einsum("mki,mki->mk", n, 0.5 * (quads + np.roll(quads, -1, axis=1)) - quads.mean(axis=1, keepdims=True))
    n = np.where(outward[..., None] >= 0.0, n, -n)
    a, b = np.roll(n, 1, axis=1), n  # at corner k: the edges to k - 1 and to k + 1
    det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    safe = np.abs(det) > 1e-3  # a degenerate quad's corner does not move
    inverse_ones = np.stack([b[..., 1] - a[..., 1], a[..., 0] - b[..., 0]], axis=-1) / np.where(safe, det, 1.0)[..., None]
    D[rows] = np.where(safe[..., None], inverse_ones, 0.0)  # [a; b] d = (1, 1)
    return D
