"""Landmarks within the head's reach: how many a robot pose lets the camera turn to (docs/planner.md).

The planner's landmark term c_m (agent/planner.py) keeps the robot where the lookout (station/pilot.py,
docs/landmarks.md "Active localization") can find landmarks: a NAO's head turns the camera through
[yaw_min - hfov/2, yaw_max + hfov/2] about the body's heading (the planner's ``reach``), so a wall of
markers straight behind the robot is out of sight whatever the head does, and a walk that turns its
back on the only marked wall carries the pose on odometry alone.

For the robot at (p, theta) and landmark m at p_m (floor coordinates), d = p_m - p, rho = |d|, the
bearing b = wrap(atan2(d) - theta), and its soft count in [0, 1] is the product of two ramps:

    angle  v_a = clip(min(b - lo, hi - b) / ANGLE_RAMP, 0, 1)        [lo, hi] the reach
    size   v_s = clip((q_m - q_min) / (SIZE_RAMP q_min), 0, 1),   q_m = f s_m c_m / rho

q_m is the landmark's width in the image (px): f the camera's focal length, s_m a marker's side or a
ball's diameter, c_m = max(0, n_m . (-d) / rho) the cosine of a marker's viewing angle (n_m its
horizontal normal; a ball faces every way, c_m = 1), q_min the least width the detector keeps
(localization ``aruco_min_side_px``, the localizer's own rule for a predicted marker). The ramps make the count continuous, so the planner's gradient polish sees
it: n(p, theta) = sum_m v_a v_s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Tuple

import numpy as np

from nao_core.geometry import wrap_angle
from nao_core.landmark_map import LandmarkMap

ANGLE_RAMP = 0.2  # rad inside the reach's edge over which a landmark fades out
SIZE_RAMP = 0.5  # a landmark counts wholly from 1.5 times the least width the detector keeps


@dataclass(frozen=True)
class LandmarkReach:
    """The map's landmarks on the floor: positions (M, 2), horizontal normals (M, 2; zero for a ball,
    which faces every way) and widths (M,): f s_m, px at 1 m; and q_min, px."""

    positions: np.ndarray
    normals: np.ndarray
    widths: np.ndarray
    min_px: float

    @classmethod
    def from_map(cls, landmarks: LandmarkMap, focal_px: float, min_px: float) -> "LandmarkReach":
        """From a landmark map, the camera's focal length and the least image width kept (px)."""
        if not (math.isfinite(focal_px) and focal_px > 0.0 and math.isfinite(min_px) and min_px > 0.0):
            raise ValueError(f"focal_px and min_px must be positive, got {focal_px!r} and {min_px!r}")
        items = landmarks.landmarks
        positions = np.array([lm.position[:2] for lm in items], dtype=float).reshape(-1, 2)
        normals = np.array([lm.normal[:2] if lm.kind == "aruco" else (0.0, 0.0) for lm in items], dtype=float).reshape(-1, 2)
        sizes = np.array([lm.size if lm.kind == "aruco" else lm.diameter for lm in items], dtype=float)
        return cls(positions, normals, focal_px * sizes, float(min_px))

    def counts(self, poses: np.ndarray, reach: Tuple[float, float]) -> np.ndarray:
        """Soft counts n (...) of the landmarks the camera can turn to from robot poses (..., 3)
        (module docstring), ``reach`` the camera's (lo, hi) bearings about the heading, rad."""
        poses = np.asarray(poses, dtype=float)
        if len(self.positions) == 0:
            return np.zeros(poses.shape[:-1])
        d = self.positions - poses[..., None, :2]  # (..., M, 2)
        rho = np.maximum(np.hypot(d[..., 0], d[..., 1]), 1e-9)
        bearing = wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - poses[..., 2:3])
        angle = np.clip(np.minimum(bearing - reach[0], reach[1] - bearing) / ANGLE_RAMP, 0.0, 1.0)
        ball = ~np.any(self.normals != 0.0, axis=1)
        cosine = np.where(ball, 1.0, np.maximum(-np.einsum("...mk,mk->...m", d, self.normals) / rho, 0.0))
        width = self.widths * cosine / rho
        size = np.clip((width - self.min_px) / (SIZE_RAMP * self.min_px), 0.0, 1.0)
        return np.sum(angle * size, axis=-1)
