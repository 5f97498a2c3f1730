"""Triangle meshes for simulated objects: procedural shapes, mesh files, and the exact inside test.

A mesh is ``(vertices (V x 3), faces (F x 3 int))``, outward-oriented (counter-clockwise seen from
outside), made of one or more closed components that may overlap. Procedural shapes are unions
of UV ellipsoids (``n_u`` longitudes x ``n_v`` latitudes; the two poles are single vertices).
A mesh file (STL, OBJ, PLY, GLB, ...) is read with trimesh, imported only when a file is asked for.

Inside test: the generalized winding number (Jacobson et al. 2013), the sum over triangles of the
signed solid angle at p (Van Oosterom and Strackee 1983) over 4 pi::

    tan(Omega / 2) = a . (b x c) / (|a||b||c| + (a . b)|c| + (a . c)|b| + (b . c)|a|),   a, b, c = vertices - p
    w(p) = sum Omega / (4 pi)

w counts the closed components that hold p (0 outside), so ``w >= 1/2`` is exact on the triangles
themselves: the renderer draws the same triangles, the truth is the same solid.

For a closed mesh (every edge in exactly two faces) w is also the signed count of the triangles a
vertical ray from p crosses above it: +1 for a face whose outward normal points up (leaving a
component), -1 for one pointing down (entering it). Many points share a column (x, y) (a voxel
grid), so ``contains`` intersects each column with every triangle once, by 2-D edge functions
e_k(q) = (v_{k+1} - v_k) x (q - v_k) of the projected triangle (q inside when all three share the
sign of the projected area), z by the barycentric weights e_k / area; and counts per point the
crossings above it: O(columns x faces) instead of O(points x faces), the same answer (a column
is moved by 1e-9 m so that it never runs exactly along an edge).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Dict, Sequence, Tuple, Union

import numpy as np

Mesh = Tuple[np.ndarray, np.ndarray]
PROCEDURAL_PREFIX = "procedural:"


def ellipsoid(centre: Sequence[float], radii: Sequence[float], n_u: int = 16, n_v: int = 10) -> Mesh:
    """A closed UV ellipsoid: poles at +-z, ``n_v - 1`` rings of ``n_u`` vertices, outward faces."""
    u = np.linspace(0.0, 2.0 * math.pi, n_u, endpoint=False)
    v = np.linspace(0.0, math.pi, n_v + 1)[1:-1]  # ring latitudes from the top
    ring = np.stack([np.outer(np.sin(v), np.cos(u)), np.outer(np.sin(v), np.sin(u)), np.outer(np.cos(v), np.ones(n_u))], axis=-1)
    unit = np.vstack([[0.0, 0.0, 1.0], ring.reshape(-1, 3), [0.0, 0.0, -1.0]])
    vertices = unit * np.asarray(radii, dtype=float) + np.asarray(centre, dtype=float)
    faces = []
    top, bottom, rings = 0, len(unit) - 1, n_v - 1
    for j in range(n_u):
        k = (j + 1) % n_u
        faces.append((top, 1 + j, 1 + k))
        for r in range(rings - 1):
            a, b = 1 + r * n_u + j, 1 + r * n_u + k
            c, d = a + n_u, b + n_u
            faces += [(a, c, d), (a, d, b)]
        last = 1 + (rings - 1) * n_u
        faces.append((bottom, last + k, last + j))
    return vertices, np.array(faces, dtype=np.int64)


def union(*meshes: Mesh) -> Mesh:
    """The components side by side (overlaps allowed: the winding number counts them)."""
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
    return np.vstack([v for v, _ in meshes]), np.vstack([f + o for (_, f), o in zip(meshes, offsets)])


def bunny() -> Mesh:
    """A crouching rabbit about 12 x 5 x 13 cm: body, head, two ears, tail (scaled to the part's size)."""
    return union(
        ellipsoid((0.0, 0.0, 0.045), (0.055, 0.035, 0.045)),  # body
        ellipsoid((0.045, 0.0, 0.085), (0.028, 0.024, 0.026)),  # head
        ellipsoid((0.038, 0.011, 0.122), (0.008, 0.005, 0.03), n_u=10, n_v=8),  # ears
        ellipsoid((0.038, -0.011, 0.122), (0.008, 0.005, 0.03), n_u=10, n_v=8),
        ellipsoid((-0.055, 0.0, 0.04), (0.012, 0.012, 0.012), n_u=10, n_v=6),  # tail
    )


def duck() -> Mesh:
    """A sitting duck: a long body, a head on top at one end, a flat beak."""
    return union(
        ellipsoid((0.0, 0.0, 0.035), (0.06, 0.035, 0.035)),
        ellipsoid((0.04, 0.0, 0.085), (0.022, 0.022, 0.024)),
        ellipsoid((0.068, 0.0, 0.082), (0.016, 0.01, 0.005), n_u=10, n_v=6),
    )


PROCEDURAL: Dict[str, Callable[[], Mesh]] = {"bunny": bunny, "duck": duck}


def load_mesh(source: Union[str, Path]) -> Mesh:
    """``procedural:NAME`` (one of ``PROCEDURAL``) or a mesh file read with trimesh."""
    text = str(source)
    if text.startswith(PROCEDURAL_PREFIX):
        name = text[len(PROCEDURAL_PREFIX):]
        if name not in PROCEDURAL:
            raise ValueError(f"unknown procedural mesh {name!r}; known: {sorted(PROCEDURAL)}")
        return PROCEDURAL[name]()
    path = Path(source)
    if not path.is_file():
        raise ValueError(f"mesh file {path} does not exist")
    import trimesh  # only for mesh files: the procedural shapes need NumPy alone

    mesh = trimesh.load(path, force="mesh")
    if len(mesh.faces) == 0:
        raise ValueError(f"mesh file {path} has no triangles")
    return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)


def fit_box(mesh: Mesh, centre: Sequence[float], size: Sequence[float]) -> Mesh:
    """The mesh scaled per axis and moved so that its bounding box is ``size`` centred at ``centre``."""
    vertices, faces = mesh
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    if np.any(hi - lo <= 0.0):
        raise ValueError("a mesh with a zero-size bounding box cannot be fitted to a part's size")
    unit = (vertices - 0.5 * (lo + hi)) / (hi - lo)
    return unit * np.asarray(size, dtype=float) + np.asarray(centre, dtype=float), faces


def winding_numbers(mesh: Mesh, points: np.ndarray, chunk: int = 1 << 22) -> np.ndarray:
    """Generalized winding number of each point (module docstring); chunks bound the memory."""
    vertices, faces = mesh
    triangles = vertices[faces]  # F x 3 x 3
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.empty(len(points))
    step = max(1, chunk // max(len(faces), 1))
    for s in range(0, len(points), step):
        p = points[s : s + step, None, None, :]
        a, b, c = (triangles[None, :, k, :] - p[:, :, 0, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        numerator = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        denominator = la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", a, c) * lb \
            + np.einsum("pfi,pfi->pf", b, c) * la
        out[s : s + step] = np.arctan2(numerator, denominator).sum(axis=1) / (2.0 * math.pi)
    return out


def is_closed(mesh: Mesh) -> bool:
    """Every edge in exactly two faces."""
    faces = mesh[1]
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def ray_winding_numbers(mesh: Mesh, points: np.ndarray, chunk: int = 1 << 22) -> np.ndarray:
    """w of each point of a closed mesh by signed vertical-ray crossings (module docstring)."""
    vertices, faces = mesh
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])  # 2 x projected, signed
    upright = area != 0.0  # vertical faces: no crossing
    a, b, c, area = a[upright], b[upright], c[upright], area[upright]
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    columns, column_of = np.unique(points[:, :2], axis=0, return_inverse=True)
    q = columns + np.array([1.0e-9, 1.7e-9])  # off every edge
    order = np.argsort(column_of.ravel(), kind="stable")  # the points of column j: order[first[j]:first[j + 1]]
    first = np.searchsorted(column_of.ravel()[order], np.arange(len(columns) + 1))
    sign = np.sign(area)  # projected counter-clockwise: outward normal up
    out = np.zeros(len(points))
    step = max(1, chunk // max(len(area), 1))
    for s in range(0, len(q), step):
        qs = q[s : s + step, None, :]
        weights = [((v[None, :, 0] - u[None, :, 0]) * (qs[..., 1] - u[None, :, 1])
                    - (v[None, :, 1] - u[None, :, 1]) * (qs[..., 0] - u[None, :, 0])) / area for u, v in ((b, c), (c, a), (a, b))]
        crossed = (weights[0] >= 0.0) & (weights[1] >= 0.0) & (weights[2] >= 0.0)  # weights of a, b, c: inside
        z = weights[0] * a[:, 2] + weights[1] * b[:, 2] + weights[2] * c[:, 2]
        for i in range(len(qs)):
            mine = order[first[s + i]:first[s + i + 1]]
            hits = crossed[i]
            out[mine] = ((z[i, hits][None, :] > points[mine, 2, None]) * sign[hits]).sum(axis=1)
    return out


def contains(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Bool per point: inside the mesh (winding number >= 1/2), tested only inside its bounding box;
    by vertical rays when the mesh is closed (module docstring)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    lo, hi = mesh[0].min(axis=0), mesh[0].max(axis=0)
    candidate = np.all((points >= lo) & (points <= hi), axis=1)
    inside = np.zeros(len(points), dtype=bool)
    if candidate.any():
        winding = ray_winding_numbers if is_closed(mesh) else winding_numbers
        inside[candidate] = winding(mesh, points[candidate]) >= 0.5
    return inside
