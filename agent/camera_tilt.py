"""The camera's tilt on its mount, learnt from standing landmark fixes (docs/landmarks.md, "Camera tilt").

``ALMotion.getTransform("CameraTop")`` is the nominal kinematic chain. A real camera sits on its
mount a few tenths of a degree off, and the head pitch joint reads its angle with an offset: the
true camera is the reported one turned by a small constant rotation in its own frame,
b = (gamma, beta), gamma about the optical axis (roll) and beta about the image's x axis (pitch,
down > 0 as the robot model's camera tilt): the rotation vector (-beta, 0, gamma) in optical axes.
A turn about the image's y axis turns the robot's heading with it and is absorbed by theta. Half a
degree of roll puts a marker at the image's edge 2 m away 1.7 cm off; held by the standing robot's
tight torso-roll prior it throws a fix decimetres off (measured: a sparse layout, a mission lost).

Body-frame tilt. The localizer's fit (agent/localization.py) turns the camera by the torso's
unmodelled roll delta and pitch epsilon, T_BC' = Rx(delta) Ry(epsilon) T_BC. To first order a
rotation omega_C in the camera frame is the rotation R_BC omega_C in the body frame, so

    t = (delta, epsilon) = A b,   A = [R_BC[0:2, 2]  -R_BC[0:2, 0]]   (columns: optical z, minus optical x),

det A = cos(the optical axis' depression): with the head turned, the camera's pitch is the
torso's roll.

Estimate. b ~ N(b_hat, P), P_0 = diag(``sigma``)^2. Every frame's T_BC is corrected by b_hat,

    T_BC <- T_BC Rot(-beta, 0, gamma)   (a rotation vector in optical axes),

and its fit holds t by the prior N(0, Sigma_f + A P A^T), Sigma_f the frame's own torso roll and
pitch (the sway). A standing fix (Sigma_f the standing one) is a measurement of A (b - b_hat): its
data alone (the fit's normal matrix without the prior, the pose eliminated by the Schur complement)
give the information I_d on t and the vector I_d t_d, and in information form

    M = (I + I_d Sigma_f)^-1 I_d,   P <- (P^-1 + A^T M A)^-1,   b_hat <- b_hat + P A^T (I + I_d Sigma_f)^-1 I_d t_d,

which holds when I_d is singular (markers all at one height say nothing of the roll). P is kept
above ``floor``^2 on every axis: the frames of one standing view share the map's and the
intrinsics' errors, which more frames do not average.
"""

from __future__ import annotations

from typing import Tuple

import cv2
import numpy as np


def body_tilt_map(T_BC: np.ndarray) -> np.ndarray:
    """A (2 x 2): the torso (roll, pitch) that a camera-frame (roll, pitch) amounts to at ``T_BC``."""
    R = np.asarray(T_BC, dtype=float)[:3, :3]
    return np.column_stack([R[:2, 2], -R[:2, 0]])


class CameraTilt:
    """The estimate b_hat and its covariance P of the camera's (roll, pitch) on its mount, rad."""

    def __init__(self, sigma: Tuple[float, float], floor: float):
        self.floor = float(floor)
        self.estimate = np.zeros(2)
        self.covariance = np.diag(np.square(np.asarray(sigma, dtype=float)))
        self.fixes = 0  # standing fixes learnt from

    def correct(self, T_BC: np.ndarray) -> np.ndarray:
        """The reported camera transform turned by the estimate."""
        gamma, beta = self.estimate
        T = np.array(T_BC, dtype=float)
        T[:3, :3] = T[:3, :3] @ cv2.Rodrigues(np.array([-beta, 0.0, gamma]))[0]
        return T

    def body_covariance(self, T_BC: np.ndarray) -> np.ndarray:
        """A P A^T: what the estimate's uncertainty adds to a fit's prior on the torso (roll, pitch)."""
        A = body_tilt_map(T_BC)
        return A @ self.covariance @ A.T

    def update(self, T_BC: np.ndarray, information: np.ndarray, evidence: np.ndarray, frame_covariance: np.ndarray) -> None:
        """Learn from a standing fix at the corrected ``T_BC``: the information I_d of its data on the
        torso (roll, pitch), the vector I_d t_d, and Sigma_f (module docstring)."""
        A = body_tilt_map(T_BC)
        if abs(np.linalg.det(A)) < 1e-3:  # the camera looking straight down: roll is yaw
            return
        scale = np.linalg.inv(np.eye(2) + information @ frame_covariance)
        M = scale @ information
        P = np.linalg.inv(np.linalg.inv(self.covariance) + A.T @ (0.5 * (M + M.T)) @ A)
        self.estimate = self.estimate + P @ A.T @ scale @ evidence
        w, V = np.linalg.eigh(0.5 * (P + P.T))
        self.covariance = V @ np.diag(np.maximum(w, self.floor**2)) @ V.T
        self.fixes += 1

    @property
    def std(self) -> np.ndarray:
        """rad, the estimate's standard deviations (roll, pitch)."""
        return np.sqrt(np.diag(self.covariance))
