"""Robot motion over a planning horizon and the planar camera poses it implies.

Walk model (SI). The robot walks at a constant body-frame velocity (v, v_y) and holds the angular
velocity omega_k for one control period tau. Integrated exactly along the arc::

    theta_{k+1}  = theta_k + omega_k tau
    p_{k+1}      = p_k + tau sinc(omega_k tau / 2) R(theta_k + omega_k tau / 2) [v, v_y]^T

with p = (x, y), R(a) the planar rotation and sinc(a) = sin(a) / a. The unicycle is v_y = 0.

Head-yaw policy. The head turns toward the estimated object centre o, within the yaw limits::

    yaw = clip(wrap(atan2(o_y - y, o_x - x) - theta), yaw_min, yaw_max),   psi = theta + yaw

psi is the optical-axis heading. The camera sits a distance b ahead of the yaw axis *on* its
optical axis (NAO's CameraTop offset), so its planar pose is::

    c = p + b [cos psi, sin psi],   camera pose = (c_x, c_y, psi)

and whenever the yaw is not clipped the optical axis passes exactly through o (bearing phi = 0).

Visibility. A camera sees the whole object (and so measures both phi and delta) when its
silhouette is inside the horizontal field of view and the centre is within the usable range::

    |phi| + delta / 2 <= hfov / 2,   r < d <= d_max
"""

from __future__ import annotations

from typing import Tuple

import numpy as np

from agent.ekf import measure
from nao_core.geometry import wrap_angle


def rollout_poses(
    pose: np.ndarray, omegas: np.ndarray, speed: float, period: float, lateral_speed: float = 0.0
) -> np.ndarray:
    """Robot poses (x, y, theta) after each step of each omega sequence: (..., D) -> (..., D, 3)."""
    x0, y0, theta0 = np.asarray(pose, dtype=float)
    omegas = np.asarray(omegas, dtype=float)
    turn = omegas * period
    theta_after = theta0 + np.cumsum(turn, axis=-1)
    mid = theta_after - 0.5 * turn
    chord = period * np.sinc(turn / (2.0 * np.pi))  # np.sinc(t) = sin(pi t) / (pi t)
    c, s = np.cos(mid), np.sin(mid)
    dx = chord * (c * speed - s * lateral_speed)
    dy = chord * (s * speed + c * lateral_speed)
    return np.stack([x0 + np.cumsum(dx, axis=-1), y0 + np.cumsum(dy, axis=-1), wrap_angle(theta_after)], axis=-1)


def head_yaw_toward(poses: np.ndarray, target: np.ndarray, yaw_limits: Tuple[float, float]) -> np.ndarray:
    """Head yaw (...,) turning each robot pose (..., 3) toward the planar target, clipped to the limits."""
    poses = np.asarray(poses, dtype=float)
    bearing = np.arctan2(target[1] - poses[..., 1], target[0] - poses[..., 0])
    return np.clip(wrap_angle(bearing - poses[..., 2]), yaw_limits[0], yaw_limits[1])


def camera_poses(
    poses: np.ndarray, target: np.ndarray, yaw_limits: Tuple[float, float], camera_offset: float
) -> np.ndarray:
    """Planar camera poses (c_x, c_y, psi) (..., 3) of robot poses (..., 3) under the head-yaw policy."""
    poses = np.asarray(poses, dtype=float)
    psi = wrap_angle(poses[..., 2] + head_yaw_toward(poses, target, yaw_limits))
    cx = poses[..., 0] + camera_offset * np.cos(psi)
    cy = poses[..., 1] + camera_offset * np.sin(psi)
    return np.stack([cx, cy, psi], axis=-1)


def object_in_view(x: np.ndarray, cams: np.ndarray, hfov: float, max_range: float) -> np.ndarray:
    """Whether cameras (..., 3) see the whole cylinder x = (xo, yo, r) within ``max_range``: (...,) bool."""
    cams = np.asarray(cams, dtype=float)
    phi, delta = np.moveaxis(measure(x, cams), -1, 0)
    d = np.hypot(x[0] - cams[..., 0], x[1] - cams[..., 1])
    return (np.abs(phi) + 0.5 * delta <= 0.5 * hfov) & (d > x[2]) & (d <= max_range)
