"""The NAO's model: camera intrinsics, head and walk limits, head kinematics, frame conventions.

Frames (see docs/frames.md):

* Robot frame B = NAOqi FRAME_ROBOT: origin on the floor between the feet, x forward, y left, z up.
* NAO camera frame (what ``ALMotion.getTransform("CameraTop", 2, True)`` reports): x forward
  (optical axis), y left, z up.
* Optical camera frame C (OpenCV): x right, y down, z forward.

The conversion NAO camera frame -> optical frame happens once, here (:func:`nao_to_optical`), at
the bridge, where the transform is read from NAOqi or from the simulator. Everything on the wire
and everything in ``agent`` uses the optical convention: ``T_BC`` maps optical-frame points to the
robot frame, ``p_B = T_BC @ p_C``.

Head kinematics (used by the simulator and the NAOqi stand-in; the real robot reports its own
transform)::

    T_B,cam(yaw, pitch) = Trans(0, 0, neck_height) Rz(yaw) Ry(pitch) Trans(camera_offset) Ry(camera_tilt)

The yaw-dependent pitch limits are Aldebaran's head anti-collision table, linearly interpolated.
"""

from __future__ import annotations

import dataclasses

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple, Union

import numpy as np

from nao_core.config import CONFIG_DIR, bounds, load
from nao_core.geometry import Pose, invert, planar_transform, rot_y, rot_z

# Columns are the optical axes (x right, y down, z forward) expressed in the NAO camera frame
# (x forward, y left, z up): x_opt = -y_nao, y_opt = -z_nao, z_opt = x_nao.
R_NAO_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def nao_to_optical(T_B_nao_cam: np.ndarray) -> np.ndarray:
    """Camera pose in the NAO camera convention -> the same pose in the optical convention."""
    T = np.asarray(T_B_nao_cam, dtype=float).reshape(4, 4).copy()
    T[:3, :3] = T[:3, :3] @ R_NAO_OPTICAL
    return T


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics and OpenCV distortion (k1, k2, p1, p2, k3) at one resolution."""

    width: int = field(metadata=bounds(16, 8192))
    height: int = field(metadata=bounds(16, 8192))
    fx: float = field(metadata=bounds(1.0, 1e5))
    fy: float = field(metadata=bounds(1.0, 1e5))
    cx: float = field(metadata=bounds(0.0, 8192.0))
    cy: float = field(metadata=bounds(0.0, 8192.0))
    dist: Tuple[float, float, float, float, float] = field(metadata=bounds(-10.0, 10.0))

    def __post_init__(self) -> None:
        if not (0 < self.cx < self.width and 0 < self.cy < self.height):
            raise ValueError(f"principal point ({self.cx}, {self.cy}) outside a {self.width}x{self.height} image")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class CameraSpec:
    """The top camera: a name, intrinsics per resolution ('qvga', 'vga', ...) and its mounting."""

    sensor: str
    resolutions: Dict[str, CameraIntrinsics]
    offset: Tuple[float, float, float] = field(metadata=bounds(-0.5, 0.5))  # from the head pitch joint, m
    tilt: float = field(metadata=bounds(-1.0, 1.0))  # extra pitch of the optical axis, rad (down > 0)
    # the tone curve: a pixel reads 255 (L / 255)^gamma of its light L (docs/frames.md); 1: linear
    response_gamma: float = field(metadata=bounds(0.2, 3.0))

    def intrinsics(self, resolution: str) -> CameraIntrinsics:
        if resolution not in self.resolutions:
            raise KeyError(f"camera {self.sensor!r} has no resolution {resolution!r}; known: {sorted(self.resolutions)}")
        return self.resolutions[resolution]


def tone_curve(gamma: float, dtype: type = np.uint8) -> np.ndarray:
    """The 256-entry table v -> 255 (v / 255)^gamma (``cv2.LUT``): a camera's tone curve with the
    gamma of its response (docs/frames.md, "The camera's tone curve"), its inverse with 1 / gamma."""
    table = 255.0 * (np.arange(256) / 255.0) ** gamma
    return np.round(table).astype(np.uint8) if dtype is np.uint8 else table.astype(dtype)


def head_at(head: Tuple[float, float], target: Tuple[float, float], tolerance: float) -> bool:
    """Are the head angles (yaw, pitch) within ``tolerance`` rad of ``target`` on both joints (a NaN angle is not)?"""
    return abs(head[0] - target[0]) <= tolerance and abs(head[1] - target[1]) <= tolerance


@dataclass(frozen=True)
class HeadLimits:
    """Joint limits (rad) and speed (rad/s); pitch limits interpolated in ``pitch_by_yaw`` rows."""

    yaw: Tuple[float, float] = field(metadata=bounds(-3.2, 3.2))
    max_speed: float = field(metadata=bounds(0.01, 10.0))
    pitch_by_yaw: Tuple[Tuple[float, float, float], ...] = field(metadata=bounds(-3.2, 3.2))

    def __post_init__(self) -> None:
        yaws = [row[0] for row in self.pitch_by_yaw]
        if len(yaws) < 2 or any(b <= a for a, b in zip(yaws, yaws[1:])):
            raise ValueError("pitch_by_yaw needs at least two rows with strictly increasing yaw")
        if self.yaw[0] >= self.yaw[1]:
            raise ValueError(f"yaw limits {self.yaw} are not increasing")

    def pitch_range(self, yaw: float) -> Tuple[float, float]:
        table = np.asarray(self.pitch_by_yaw)
        return float(np.interp(yaw, table[:, 0], table[:, 1])), float(np.interp(yaw, table[:, 0], table[:, 2]))

    def clamp(self, yaw: float, pitch: float) -> Tuple[float, float]:
        yaw = min(max(yaw, self.yaw[0]), self.yaw[1])
        lo, hi = self.pitch_range(yaw)
        return yaw, min(max(pitch, lo), hi)


@dataclass(frozen=True)
class WalkLimits:
    """Velocity limits for ALMotion.move (m/s, m/s, rad/s)."""

    v_max: float = field(metadata=bounds(0.0, 1.0))
    v_min: float = field(metadata=bounds(-1.0, 0.0))
    vy_max: float = field(metadata=bounds(0.0, 1.0))
    omega_max: float = field(metadata=bounds(0.0, 5.0))

    def clamp(self, v: float, vy: float, omega: float) -> Tuple[float, float, float]:
        return (
            min(max(v, self.v_min), self.v_max),
            min(max(vy, -self.vy_max), self.vy_max),
            min(max(omega, -self.omega_max), self.omega_max),
        )


@dataclass(frozen=True)
class RobotModel:
    """Everything the software needs to know about one NAO version."""

    name: str
    neck_height: float = field(metadata=bounds(0.1, 2.0))  # floor to the head joints, m
    camera: CameraSpec
    head: HeadLimits
    walk: WalkLimits

    def with_lens(self, dist: Sequence[float]) -> "RobotModel":
        """The same robot with the lens distortion ``dist`` (k1, k2, p1, p2, k3) at every resolution."""
        resolutions = {name: dataclasses.replace(intr, dist=tuple(dist)) for name, intr in self.camera.resolutions.items()}
        return dataclasses.replace(self, camera=dataclasses.replace(self.camera, resolutions=resolutions))

    def camera_in_robot(self, yaw: float, pitch: float) -> np.ndarray:
        """T_BC (optical convention) for the given head angles: the kinematic chain of the docstring."""
        return nao_to_optical(self.camera_in_robot_nao(yaw, pitch))

    def look_at(self, pose: Pose, target_W: Sequence[float], iterations: int = 8) -> Tuple[float, float]:
        """Head (yaw, pitch) that put the world point ``target_W`` on the optical axis, clamped to the limits.

        Fixed-point iteration on the target's direction in the optical frame (x right, y down, z forward)::

            (x, y, z) = T_BC(yaw, pitch)^-1 T_WB(pose)^-1 t,   yaw <- yaw - atan2(x, z),   pitch <- pitch + atan2(y, z)

        then ``head.clamp`` (pitch limits shrink at large yaw). Several iterations, because the
        camera's offset from the neck makes one step slightly short.
        """
        target_B = invert(planar_transform(*(float(p) for p in pose))) @ np.append(np.asarray(target_W, dtype=float)[:3], 1.0)
        yaw = pitch = 0.0
        for _ in range(iterations):
            x, y, z = (invert(self.camera_in_robot(yaw, pitch)) @ target_B)[:3]
            yaw, pitch = self.head.clamp(yaw - math.atan2(x, z), pitch + math.atan2(y, z))
        return yaw, pitch

    def camera_in_robot_nao(self, yaw: float, pitch: float) -> np.ndarray:
        """The same pose in NAO's camera convention, as ALMotion.getTransform reports it."""
        T = np.eye(4)
        T[2, 3] = self.neck_height
        T = T @ rot_z(yaw) @ rot_y(pitch)
        offset = np.eye(4)
        offset[:3, 3] = self.camera.offset
        return T @ offset @ rot_y(self.camera.tilt)




def load_robot_model(
    files: Sequence[Union[str, Path]] = (), default: Optional[Path] = None
) -> RobotModel:
    """The ``robot`` section of the default model file (NAO V6) merged with ``files``."""
    base = default or CONFIG_DIR / "robots" / "nao_v6.yaml"
    return load(RobotModel, [base, *files], section="robot")
