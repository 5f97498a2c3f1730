"""The camera's tone curve from the edges of a chessboard (docs/frames.md, "The camera's tone curve").

A camera mixes light (its lens blurs it, each pixel sums it), then encodes it through a tone curve,

    v = 255 (L / 255)^gamma        (sRGB about 0.45; 1: linear),

so every sub-pixel edge measured in pixel values (marker corners, the object's outline) moves by a
fraction of the blur towards the dark side (gamma < 1) or the light one. Across a straight edge
between a dark and a light square the light is

    L(s) = b + (w - b) F(s - s0),    F the blur's step response, F(-t) = 1 - F(t) (a symmetric blur),

point-symmetric about (s0, (b + w) / 2): the level halfway between its ends is crossed where the
profile rises fastest. Through a tone curve it is not, and no symmetric edge fits it. So the
edges are fitted, each pixel value v_i at signed distance s_i from the edge's line (the pixels
themselves, no resampling: a slanted edge samples its own profile finely, as ISO 12233 does), by

    v_i = 255 ((b + (w - b) Phi((s_i - s0) / sigma)) / 255)^gamma,

Phi the normal CDF (a pixel's box convolved with a lens's blur is close to a Gaussian's step), each
edge's (b, w, s0, sigma) by Gauss-Newton, and gamma by minimizing the sum of squared residuals over
all the edges (``scipy.optimize.minimize_scalar`` over log gamma in [``GAMMA_MIN``, ``GAMMA_MAX``]).
Its standard error: sqrt(2 s^2 / C) in log gamma, with s^2 the residual variance per pixel and C the
cost's curvature at the minimum.

Edges: each grid segment between neighbouring inner corners of a chessboard parts a dark square from
a light one; its pixels within ``ALONG`` of its length of its middle and ``REACH`` to either side
are one edge. An edge whose dark and light pixels differ by less than ``MIN_CONTRAST`` grey levels,
or which saturates, is left out.
"""

from __future__ import annotations

import functools
import math
from typing import List, Sequence, Tuple

import cv2
import numpy as np
from scipy import optimize, special

from nao_core.robot_model import tone_curve

GAMMA_MIN, GAMMA_MAX = 0.25, 4.0
REACH = 0.3  # of a segment's length: the pixels this far to either side of it (well inside both squares)
ALONG = 0.2  # ... and this far along it from its middle (clear of the corners)
MIN_CONTRAST = 40.0  # grey levels between an edge's dark and light pixels (5th and 95th percentiles)
SATURATED = (2.0, 253.0)  # an edge reaching these levels is clipped, not curved
MIN_EDGES = 20


class ToneCurveError(ValueError):
    """The edges cannot tell the tone curve (the message says why)."""


@functools.lru_cache(maxsize=8)
def _inverse(gamma: float) -> np.ndarray:
    return tone_curve(1.0 / gamma)


def in_light(image: np.ndarray, gamma: float) -> np.ndarray:
    """A uint8 image as the light it shows: through the inverse of the tone curve ``gamma``
    (``cv2.LUT``); the image itself for a linear camera (gamma 1)."""
    return image if gamma == 1.0 else cv2.LUT(image, _inverse(gamma))


def chessboard_edges(gray: np.ndarray, corners: np.ndarray, pattern: Tuple[int, int]) -> List[Tuple[np.ndarray, np.ndarray]]:
    """The pixels about the middle of each grid segment between neighbouring inner ``corners`` of a
    chessboard (``pattern`` = (cols, rows), cv2 order), one (s, v) per usable edge: s each pixel
    centre's signed distance to the segment's line, oriented so that v (its value) rises with s
    (module docstring)."""
    grid = np.asarray(corners, np.float64).reshape(pattern[1], pattern[0], 2)
    starts = np.concatenate([grid[:, :-1].reshape(-1, 2), grid[:-1, :].reshape(-1, 2)])
    ends = np.concatenate([grid[:, 1:].reshape(-1, 2), grid[1:, :].reshape(-1, 2)])
    edges = []
    for a, b in zip(starts, ends):
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        n, m = np.array([-d[1], d[0]]), 0.5 * (a + b)
        r = REACH * length + 1.0
        x0, y0 = np.floor(m - r).astype(int)
        x1, y1 = np.ceil(m + r).astype(int) + 1
        if x0 < 0 or y0 < 0 or x1 > gray.shape[1] or y1 > gray.shape[0]:
            continue
        ys, xs = np.mgrid[y0:y1, x0:x1]
        offset = np.stack([xs - m[0], ys - m[1]], axis=-1).reshape(-1, 2)
        along, across = offset @ d, offset @ n
        keep = (np.abs(along) <= ALONG * length) & (np.abs(across) <= REACH * length)
        v = gray[y0:y1, x0:x1].reshape(-1).astype(np.float64)[keep]
        across = across[keep]
        if v[across > 0].mean() < v[across < 0].mean():
            across = -across
        if (np.percentile(v, 95) - np.percentile(v, 5) >= MIN_CONTRAST and v.min() > SATURATED[0]
                and v.max() < SATURATED[1]):
            edges.append((across, v))
    return edges


def _edge_model(s: np.ndarray, params: np.ndarray, gamma: float):
    """The symmetric edge through the tone curve at offsets ``s`` (N x K) for each edge's (b, w, s0,
    log sigma): (values, light, Phi, phi, z, sigma)."""
    b, w, s0, sigma = params[:, 0:1], params[:, 1:2], params[:, 2:3], np.exp(params[:, 3:4])
    z = (s - s0) / sigma
    F = special.ndtr(z)
    light = np.maximum(b + (w - b) * F, 1e-3)
    return 255.0 * (light / 255.0) ** gamma, light, F, np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi), z, sigma


def fit_cost(s: np.ndarray, v: np.ndarray, used: np.ndarray, gamma: float, iterations: int = 12) -> float:
    """Sum over the edges (N x K pixels: offsets ``s``, values ``v``, ``used``) of the squared residuals,
    in pixel values, of the symmetric edge through the tone curve ``gamma`` (module docstring), each
    edge's (b, w, s0, sigma) fitted by Gauss-Newton (all edges at once, Levenberg-damped)."""
    weight = used.astype(np.float64)
    v = np.clip(v, 1.0, 254.0)
    light = 255.0 * (v / 255.0) ** (1.0 / gamma)
    b = (light * weight * (s < 0)).sum(axis=1) / np.maximum((weight * (s < 0)).sum(axis=1), 1.0)
    w = (light * weight * (s > 0)).sum(axis=1) / np.maximum((weight * (s > 0)).sum(axis=1), 1.0)
    params = np.column_stack([b, w, np.zeros(len(v)), np.zeros(len(v))])  # s0 0, sigma 1 px
    for _ in range(iterations):
        model, L, F, phi, z, sigma = _edge_model(s, params, gamma)
        dv_dL = gamma * model / L
        contrast = params[:, 1:2] - params[:, 0:1]
        J = np.stack([dv_dL * (1.0 - F), dv_dL * F, -dv_dL * contrast * phi / sigma, -dv_dL * contrast * phi * z], axis=-1)
        J = J * weight[..., None]
        r = (v - model) * weight
        JtJ = np.einsum("nsi,nsj->nij", J, J)
        JtJ = JtJ + 1e-3 * JtJ * np.eye(4)[None] + 1e-9 * np.eye(4)[None]
        step = np.linalg.solve(JtJ, np.einsum("nsi,ns->ni", J, r)[..., None])[..., 0]
        params = params + step
        params[:, 3] = np.clip(params[:, 3], math.log(0.1), math.log(10.0))
    return float(np.sum(((v - _edge_model(s, params, gamma)[0]) * weight) ** 2))


def estimate_gamma(s: np.ndarray, v: np.ndarray, used: np.ndarray) -> Tuple[float, float]:
    """(gamma, its standard error) of the tone curve whose symmetric edges fit the chessboard's edges
    (N x K pixels, ``used`` False on padding) best; raises ``ToneCurveError`` with fewer than
    ``MIN_EDGES`` of them, or when the best fit is at the search's bound."""
    if len(v) < MIN_EDGES:
        raise ToneCurveError(f"{len(v)} usable chessboard edges, at least {MIN_EDGES} needed")

    def cost(log_gamma: float) -> float:
        return fit_cost(s, v, used, math.exp(log_gamma))

    found = optimize.minimize_scalar(cost, bounds=(math.log(GAMMA_MIN), math.log(GAMMA_MAX)), method="bounded",
                                     options={"xatol": 1e-3})
    x, h = float(found.x), 0.02
    if not GAMMA_MIN * 1.01 < math.exp(x) < GAMMA_MAX / 1.01:
        raise ToneCurveError(f"the edges fit best at the search's bound ({math.exp(x):.2f}): too sharp or too clipped to tell")
    curvature = (cost(x + h) - 2.0 * float(found.fun) + cost(x - h)) / (h * h)
    variance = float(found.fun) / max(int(used.sum()) - 4 * len(v), 1)  # of one pixel's residual
    log_std = math.sqrt(2.0 * variance / curvature) if curvature > 0.0 else math.inf
    return math.exp(x), math.exp(x) * log_std


def tone_gamma(grays: Sequence[np.ndarray], corner_sets: Sequence[np.ndarray],
               pattern: Tuple[int, int]) -> Tuple[float, float, int]:
    """(gamma, standard error, edges used) over several chessboard views; ``ToneCurveError`` when they cannot tell it."""
    edges = [edge for g, c in zip(grays, corner_sets) for edge in chessboard_edges(g, c, pattern)]
    k = max((len(v) for _, v in edges), default=0)
    s, v, used = np.zeros((len(edges), k)), np.zeros((len(edges), k)), np.zeros((len(edges), k), bool)
    for i, (across, values) in enumerate(edges):
        s[i, :len(values)], v[i, :len(values)], used[i, :len(values)] = across, values, True
    gamma, error = estimate_gamma(s, v, used)
    return gamma, error, len(edges)
