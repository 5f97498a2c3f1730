"""Keyframe camera pose: the full 6-DOF camera pose refined against the frame's own landmark points.

The localizer fits the robot's planar pose (x, y, theta) with the torso roll and camera pitch T_BC
missed, and fuses the fix with odometry (agent/localization.py, docs/landmarks.md); the pilot's
camera pose is then T_WB(fused pose) T_BC, the kinematics' orientation again. The carve needs only
the camera pose, and the kinematics' errors (torso sway and joint lag left after capture-time
interpolation: a few tenths of a degree, 3 px at 587 px focal length for 0.3 deg) move every
silhouette: measured on a walking flat box mission, the fused camera pose was off by 5-15 mm at its
keyframes, and the carve removed the true object's rim where the silhouettes were misplaced
(docs/carving.md, "Keyframe poses").

A keyframe whose frame gave a landmark fix gets the maximum a posteriori camera pose given that
fix's inlier points (world X_i, pinhole pixels u_i) and the fused pose (R_0, C_0) as prior:

    R = R_0 Exp(omega),  C = C_0 + c,   u_i' = pi(K, R^T (X_i - C))
    min_{omega, c}  sum_i ||u_i' - u_i||^2 / s^2 + ||omega||^2 / sigma_rot^2 + ||c||^2 / sigma_pos^2

with s = max(``pixel_sigma``, the fix's reprojection RMS) (with a map measured sigma_p off, the pilot
adds f sigma_p / z at the points' median depth: agent/localization.py, Map error), sigma_rot = ``keyframe_rotation_sigma``
(what the kinematics' orientation is worth) and sigma_pos = ``keyframe_position_sigma`` (what the
fused position is worth at a keyframe; the fused covariance does not know the kinematics' error).
With several markers spread in the image the points fix all six degrees of freedom and the prior
hardly matters; with one or two markers the poorly seen directions stay near the prior. Solved by
Levenberg-Marquardt (``scipy.optimize.least_squares``) from omega = c = 0; the refined pose is kept
when its reprojection RMS is at most ``max_rms`` px, else the fused pose stands.

The priors are what the fused pose is worth, not looser: the posterior mean is the best estimate
only when they are honest. One far marker cannot tell a sideways step from a turn that keeps it in
place; there the prior alone holds the pose, and a prior looser than the pose's real error would let
the corners' noise move the camera along that direction and misplace the nearer object by pixels
(tests/test_keyframe_pose.py).
"""

from __future__ import annotations

from typing import Optional

import cv2
import numpy as np
from scipy.optimize import least_squares

MIN_DEPTH = 0.05  # m: a landmark point nearer than this to the camera plane gives no refinement


def refine_camera_pose(T_WC: np.ndarray, world: np.ndarray, pixels: np.ndarray, K: np.ndarray, pixel_sigma: float,
                       rotation_sigma: float, position_sigma: float, max_rms: float) -> Optional[np.ndarray]:
    """The MAP camera pose (4 x 4 T_WC) from landmark points and the prior ``T_WC`` (module docstring), or
    None when the points cannot refine it (fewer than three, behind the camera, not finite, or a refined
    reprojection RMS above ``max_rms`` px)."""
    X = np.asarray(world, dtype=float).reshape(-1, 3)
    u = np.asarray(pixels, dtype=float).reshape(-1, 2)
    T_WC = np.asarray(T_WC, dtype=float)
    if len(X) < 3 or len(u) != len(X) or not (np.all(np.isfinite(X)) and np.all(np.isfinite(u)) and np.all(np.isfinite(T_WC))):
        return None
    R0, C0 = T_WC[:3, :3], T_WC[:3, 3]
    f, c = np.array([K[0, 0], K[1, 1]]), K[:2, 2]

    def pose(v: np.ndarray) -> tuple:
        return R0 @ cv2.Rodrigues(v[:3])[0], C0 + v[3:]

    def project(v: np.ndarray) -> tuple:
        R, C = pose(v)
        X_C = (X - C) @ R
        return X_C[:, :2] / X_C[:, 2:3] * f + c, X_C[:, 2]

    if np.any(project(np.zeros(6))[1] < MIN_DEPTH):
        return None

    def residuals(v: np.ndarray) -> np.ndarray:
        uv, depth = project(v)
        uv = np.where(depth[:, None] > MIN_DEPTH, uv, u + 1e6)  # a point crossing behind the camera: a huge residual
        return np.concatenate([(uv - u).ravel() / pixel_sigma, v[:3] / rotation_sigma, v[3:] / position_sigma])

    solution = least_squares(residuals, np.zeros(6), method="lm")
    uv, depth = project(solution.x)
    rms = float(np.sqrt(np.mean(np.sum((uv - u) ** 2, axis=1))))
    if not (solution.success and np.all(depth > MIN_DEPTH) and rms <= max_rms):
        return None
    R, C = pose(solution.x)
    refined = np.eye(4)
    refined[:3, :3], refined[:3, 3] = R, C
    return refined
