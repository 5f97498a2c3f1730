"""The records a robot backend produces: one camera frame with its capture-time kinematics, one state sample.

Times are the bridge machine's clock (seconds); camera poses are in the optical convention
(``nao_core.robot_model``, docs/frames.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np


@dataclass(frozen=True)
class CameraFrame:
    """One top-camera image with everything measured at its capture time."""

    image: np.ndarray  # H x W x 3 uint8, BGR
    stamp: float  # capture time, bridge clock, s
    head_yaw: float  # rad
    head_pitch: float  # rad
    T_BC: np.ndarray  # 4 x 4 camera-in-robot at capture, optical convention
    odom: Tuple[float, float, float]  # odometry pose (x, y, theta) at capture
    stamp_std: float = 0.0  # s, how far the stamp may be from the instant the image shows (docs/frames.md)


@dataclass(frozen=True)
class RobotState:
    stamp: float
    odom: Tuple[float, float, float]
    head_yaw: float
    head_pitch: float
    walking: bool
    fallen: bool
    battery: Optional[float]  # charge fraction in [0, 1], None when the robot does not report it
