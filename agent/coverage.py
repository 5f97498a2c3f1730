"""Coverage of the object's surface: N0 bins on the cylinder around the estimated object.

Bin i (i = 0 .. N0-1) sits at azimuth a_i = 2 pi (i + 1/2) / N0 around the estimated centre o with
radius r: point q_i = o + r n_i, outward normal n_i = (cos a_i, sin a_i). A camera at c with
optical-axis heading psi and horizontal field of view hfov sees bin i when all three hold::

    facing:   n_i . (c - q_i) >= |c - q_i| cos(alpha_max)           (normal within alpha_max of the camera)
    in view:  |wrap(atan2(q_i - c) - psi)| <= hfov / 2                (inside the horizontal field of view)
    range:    d_lo <= |c - q_i| <= d_hi                               (usable distance)

alpha_max <= pi/2, so a facing bin is never hidden by the (convex) cylinder itself. The coverage
after a path is the union over its cameras, N_v = |U_t seen(c_t)|, re-evaluated against the
current estimate (the bins move with it) from the executed camera poses, plus the predicted ones.
Termination asks for coverage within alpha_max - margin, so that a bin seen right at the facing
limit of the estimate is not missing for the true object.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np

from nao_core.config import bounds


@dataclass(frozen=True)
class CoverageParams:
    """Bins on the cylinder and when a bin counts as seen (angles in rad, distances in m)."""

    bins: int = field(metadata=bounds(4, 3600))
    facing_angle: float = field(metadata=bounds(0.01, math.pi / 2))
    distance_range: Tuple[float, float] = field(metadata=bounds(0.0, 100.0))

    def __post_init__(self) -> None:
        if self.distance_range[0] >= self.distance_range[1]:
            raise ValueError(f"distance_range {self.distance_range} is not increasing")


def bin_angles(n_bins: int) -> np.ndarray:
    """Azimuths a_i of the bin centres, (N0,)."""
    return 2.0 * np.pi * (np.arange(n_bins) + 0.5) / n_bins


def bins_seen(x: np.ndarray, cams: np.ndarray, params: CoverageParams, hfov: float) -> np.ndarray:
    """Which bins of the cylinder x = (xo, yo, r) each camera (..., 3) sees: (..., N0) bool.

    Both angle tests are done on dot products (hfov < pi): no arctan in the planner's inner loop.
    """
    return _seen_at(x, np.asarray(cams, dtype=float), bin_angles(params.bins), params, hfov)


def _seen_at(x: np.ndarray, cams: np.ndarray, a: np.ndarray, params: CoverageParams, hfov: float) -> np.ndarray:
    nx, ny = np.cos(a), np.sin(a)
    vx = cams[..., 0, None] - (x[0] + x[2] * nx)  # c - q_i
    vy = cams[..., 1, None] - (x[1] + x[2] * ny)
    dist = np.hypot(vx, vy)
    facing = nx * vx + ny * vy >= dist * math.cos(params.facing_angle)
    axis_x, axis_y = np.cos(cams[..., 2, None]), np.sin(cams[..., 2, None])
    in_view = -(axis_x * vx + axis_y * vy) >= dist * math.cos(0.5 * hfov)
    in_range = (dist >= params.distance_range[0]) & (dist <= params.distance_range[1])
    return facing & in_view & in_range


def seen_count(x: np.ndarray, cams: np.ndarray, already: np.ndarray, params: CoverageParams, hfov: float) -> np.ndarray:
    """N_v for camera sequences (..., D, 3) added to the bins ``already`` seen (N0,): (...,) int.

    Only the bins not seen yet are tested.
    """
    unseen = bin_angles(params.bins)[~np.asarray(already, dtype=bool)]
    fresh = _seen_at(x, np.asarray(cams, dtype=float), unseen, params, hfov).any(axis=-2).sum(axis=-1)
    return int(np.count_nonzero(already)) + fresh


class Coverage:
    """The executed camera poses; the bins they have seen, evaluated against any estimate."""

    def __init__(self, params: CoverageParams, hfov: float):
        self.params = params
        self.hfov = hfov
        self._cams: List[Tuple[float, float, float]] = []

    def add(self, cam: np.ndarray) -> None:
        """Record the planar pose (c_x, c_y, psi) of a camera that captured a frame."""
        cam = np.asarray(cam, dtype=float).reshape(3)
        if not np.all(np.isfinite(cam)):
            raise ValueError(f"camera pose must be finite, got {cam.tolist()}")
        self._cams.append(tuple(cam))

    @property
    def cameras(self) -> np.ndarray:
        return np.asarray(self._cams, dtype=float).reshape(-1, 3)

    def seen(self, x: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Bins (N0,) seen from the executed path for the estimate x, within facing_angle - margin."""
        params = self.params
        if margin:
            params = dataclasses.replace(params, facing_angle=max(params.facing_angle - margin, 0.0))
        return bins_seen(np.asarray(x, dtype=float), self.cameras, params, self.hfov).any(axis=0)

    def fraction(self, x: np.ndarray, margin: float = 0.0, within: Optional[np.ndarray] = None) -> float:
        """N_v / N_0 of the executed path (``margin``: see :meth:`seen`); of the bins ``within`` (N0,) bool
        if given (those the walls leave reachable, agent/keep_in.py)."""
        return seen_fraction(self.seen(x, margin), within)


def seen_fraction(seen: np.ndarray, within: Optional[np.ndarray] = None) -> float:
    """The share of bins seen (N0,) bool, of those ``within`` if given (0 when none is)."""
    if within is None:
        return float(seen.mean())
    return float(seen[within].mean()) if within.any() else 0.0
