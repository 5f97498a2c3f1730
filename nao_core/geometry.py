"""Rigid-body geometry shared by every package: SE(2) poses on the floor and SE(3) transforms.

Conventions (docs/frames.md): ``T_AB`` is a 4x4 homogeneous transform mapping points of frame B
into frame A, ``p_A = T_AB @ p_B``. The world W has z up and the floor at z = 0; a robot pose on
the floor is ``Pose = (x, y, theta)`` with theta the yaw of its x axis.

SE(2) composition and relative pose (a (+) b and (-a) (+) b)::

    compose(a, b)  = (a_x + c b_x - s b_y,  a_y + s b_x + c b_y,  wrap(a_t + b_t)),   c, s = cos a_t, sin a_t
    relative(a, b) = ( c dx + s dy,  -s dx + c dy,  wrap(b_t - a_t)),                  (dx, dy) = b_xy - a_xy

Rigid inverse: T^-1 = [R^T, -R^T t; 0, 1].
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np

Pose = Tuple[float, float, float]


def wrap_angle(a):
    """Wrap angles to (-pi, pi]; works on floats and arrays."""
    w = np.mod(np.asarray(a, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    w = np.where(w == -np.pi, np.pi, w)
    return float(w) if np.ndim(w) == 0 else w


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def rot_x(a: float) -> np.ndarray:
    """4x4 rotation by ``a`` about x."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0, 0.0], [0.0, c, -s, 0.0], [0.0, s, c, 0.0], [0.0, 0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    """4x4 rotation by ``a`` about y."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s, 0.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 0.0], [0.0, 0.0, 0.0, 1.0]])


def rot2(a: float) -> np.ndarray:
    """2x2 rotation by ``a``."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def planar_transform(x: float, y: float, theta: float) -> np.ndarray:
    """T_WB of a robot at (x, y, theta) on the floor (a rotation about z by theta, then the translation)."""
    T = np.eye(4)
    T[:2, :2] = rot2(theta)
    T[0, 3], T[1, 3] = x, y
    return T


def rot_z(a: float) -> np.ndarray:
    """4x4 rotation by ``a`` about z."""
    return planar_transform(0.0, 0.0, a)


def planar_pose(T_WB: np.ndarray) -> Pose:
    """(x, y, theta) of a transform: translation on the floor and yaw of its x axis."""
    return float(T_WB[0, 3]), float(T_WB[1, 3]), math.atan2(T_WB[1, 0], T_WB[0, 0])


def camera_in_world(robot_pose: Pose, T_BC: np.ndarray) -> np.ndarray:
    """T_WC = T_WB(x, y, theta) @ T_BC."""
    return planar_transform(*robot_pose) @ np.asarray(T_BC, dtype=float)


def compose(a: Pose, b: Pose) -> Pose:
    """a (+) b: pose b expressed in frame a, as a pose in a's parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2])


def relative(a: Pose, b: Pose) -> Pose:
    """(-a) (+) b: pose b seen from pose a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[2] - a[2])
