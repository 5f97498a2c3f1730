"""Head visual servoing: yaw and pitch that keep the object centred in the top camera.

Aim height. The object stands on the floor (z = 0), so its vertical middle is H / 2 with H its top.
Each silhouette whose top row v_t is not cut by the image border bounds H: the ray of row v_t - 1/2
through the object's centre column, d = R_WC K^-1 (u, v_t - 1/2, 1), meets the object's top edge at the
horizontal range s = |o - C| + r when it descends (the far rim of a top seen from above) and
|o - C| - r when it rises, so H = C_z + s d_z / hypot(d_x, d_y). :class:`ObjectHeight` keeps the
median of the last estimates; until there is one, ``aim_height`` of the configuration is used.

Model-based target: the point t = (x_o, y_o, h_aim) (the estimated centre at the object's
middle height) is put on the optical axis by fixed-point iteration on its direction in the camera frame
(optical: x right, y down, z forward), with the kinematics T_BC(yaw, pitch) of the robot model
(``RobotModel.look_at``)::

    (x, y, z) = T_BC(yaw, pitch)^-1 T_WB(pose)^-1 t,   yaw <- yaw - atan2(x, z),   pitch <- pitch + atan2(y, z)

Measured correction: when the object's silhouette centroid (u, v) was seen with the head at
(yaw_c, pitch_c), centring it asks for (yaw_c - atan2(x_n, 1), pitch_c + atan2(y_n, 1)) with
(x_n, y_n) its undistorted normalized coordinates. The target is the blend
(1 - g) model + g measured, g = ``servo_gain``, for the yaw only: the pitch follows the model's
mid-height, since a silhouette cut by the image's bottom border has its centroid above the middle
and would pull the base further out of view. Then ``robot.head.clamp`` (pitch limits shrink at
large yaw).

Before an estimate. A silhouette cut by the image's side gives no bearing the filter may use
(docs/perception.md), so no estimate starts from it; the head then centres the measured centroid,
(yaw_c - atan2(x_n, 1), pitch_c + atan2(y_n, 1)), which brings the cut side into view (the centroid
of a cut blob lies inside the object's image, on the way to its middle).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Deque, Optional, Sequence, Tuple, Union

import numpy as np

from agent.camera import CameraModel
from agent.perception import object_pixel_direction
from nao_core.config import CONFIG_DIR, bounds, load
from nao_core.robot_model import RobotModel


@dataclass(frozen=True)
class HeadServoParams:
    """Head servo settings (config/head_servo.yaml, section ``head_servo``)."""

    aim_height: float = field(metadata=bounds(0.0, 2.0))  # m, aim height until the silhouettes bound the top
    servo_gain: float = field(metadata=bounds(0.0, 1.0))  # g: weight of the measured centroid in the yaw target
    search_pitch: float = field(metadata=bounds(-1.0, 1.0))  # rad, head pitch when there is no estimate yet


def load_head_servo_params(overrides: Sequence[Union[str, Path]] = ()) -> HeadServoParams:
    """HeadServoParams from config/head_servo.yaml merged with ``overrides``."""
    return load(HeadServoParams, [CONFIG_DIR / "head_servo.yaml", *overrides], section="head_servo")


def object_top(top_row: int, column: float, camera: CameraModel, T_WC: np.ndarray, x: Sequence[float]) -> Optional[float]:
    """H from a silhouette's top row and centre column (module docstring); None when the ray is level."""
    ray = np.asarray(T_WC, dtype=float)[:3, :3] @ np.linalg.solve(camera.K, np.array([column, top_row - 0.5, 1.0]))
    centre = np.asarray(T_WC, dtype=float)[:3, 3]
    across = math.hypot(ray[0], ray[1])
    if across < 1e-9 or abs(ray[2]) < 1e-9 * across:
        return None
    reach = math.hypot(x[0] - centre[0], x[1] - centre[1]) + (x[2] if ray[2] < 0.0 else -x[2])
    return float(centre[2] + max(reach, 0.0) * ray[2] / across)


class ObjectHeight:
    """The object's top H above the floor: median of the last ``window`` bounds from uncut silhouettes."""

    def __init__(self, window: int = 15):
        self._tops: Deque[float] = deque(maxlen=window)

    def update(self, top_row: int, column: float, touches_top: bool, camera: CameraModel, T_WC: np.ndarray,
               x: Optional[Sequence[float]]) -> None:
        """Add the bound of one silhouette (ignored when its top is cut or there is no estimate)."""
        if touches_top or x is None:
            return
        top = object_top(top_row, column, camera, T_WC, x)
        if top is not None and top > 0.0:
            self._tops.append(top)

    @property
    def top(self) -> Optional[float]:
        """H, m, or None before any uncut silhouette."""
        return float(np.median(self._tops)) if self._tops else None

    @property
    def aim(self) -> Optional[float]:
        """The aim height H / 2, m, or None."""
        return None if self.top is None else 0.5 * self.top


def head_target(
    robot_model: RobotModel,
    pose: Optional[Sequence[float]],
    object_x: Optional[Sequence[float]],
    params: HeadServoParams,
    centroid_uv: Optional[Tuple[float, float]] = None,
    camera: Optional[CameraModel] = None,
    head_at_capture: Optional[Tuple[float, float]] = None,
    aim_height: Optional[float] = None,
) -> Tuple[float, float]:
    """(yaw, pitch) that centre the object (x_o, y_o, r), within the head's joint limits.

    Without a pose or an estimate the head centres a measured ``centroid_uv`` or else looks straight
    ahead at ``params.search_pitch``. A measured ``centroid_uv`` (with the ``camera`` and the ``head_at_capture`` angles of its frame)
    pulls the yaw towards centring it, by ``params.servo_gain``. ``aim_height`` (m; e.g.
    :attr:`ObjectHeight.aim`) replaces the configured ``params.aim_height``.
    """
    seen = centroid_uv is not None and camera is not None and head_at_capture is not None
    if pose is None or object_x is None:
        if not seen:
            return robot_model.head.clamp(0.0, params.search_pitch)
        horizontal, vertical = object_pixel_direction(camera, centroid_uv)
        return robot_model.head.clamp(head_at_capture[0] - horizontal, head_at_capture[1] + vertical)
    aim = params.aim_height if aim_height is None else aim_height
    yaw, pitch = robot_model.look_at(pose, (float(object_x[0]), float(object_x[1]), aim))
    if seen and params.servo_gain > 0.0:
        horizontal, _ = object_pixel_direction(camera, centroid_uv)
        g = params.servo_gain
        yaw = (1.0 - g) * yaw + g * (head_at_capture[0] - horizontal)
    return robot_model.head.clamp(yaw, pitch)
