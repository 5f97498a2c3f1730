"""Head visual servoing: yaw and pitch that keep the object centred in the top camera.

Model-based target: the point t = (x_o, y_o, h_aim) (the estimated centre at the object's visible
middle) is put on the optical axis by fixed-point iteration on its direction in the camera frame
(optical: x right, y down, z forward), with the kinematics T_BC(yaw, pitch) of the robot model
(``RobotModel.look_at``)::

    (x, y, z) = T_BC(yaw, pitch)^-1 T_WB(pose)^-1 t,   yaw <- yaw - atan2(x, z),   pitch <- pitch + atan2(y, z)

Measured correction: when the object's silhouette centroid (u, v) was seen with the head at
(yaw_c, pitch_c), centring it asks for (yaw_c - atan2(x_n, 1), pitch_c + atan2(y_n, 1)) with
(x_n, y_n) its undistorted normalized coordinates. The target is the blend
(1 - g) model + g measured, g = ``servo_gain``, then ``robot.head.clamp`` (pitch limits shrink at
large yaw).
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

from agent.camera import CameraModel
from agent.perception import PerceptionParams, object_pixel_direction
from nao_core.robot_model import RobotModel


def head_target(
    robot_model: RobotModel,
    pose: Optional[Sequence[float]],
    object_x: Optional[Sequence[float]],
    params: PerceptionParams,
    centroid_uv: Optional[Tuple[float, float]] = None,
    camera: Optional[CameraModel] = None,
    head_at_capture: Optional[Tuple[float, float]] = None,
) -> Tuple[float, float]:
    """(yaw, pitch) that centre the object (x_o, y_o, r), within the head's joint limits.

    Without a pose or an estimate the head looks straight ahead at ``params.search_pitch``. A
    measured ``centroid_uv`` (with the ``camera`` and the ``head_at_capture`` angles of its frame)
    pulls the target towards centring it, by ``params.servo_gain``.
    """
    if pose is None or object_x is None:
        return robot_model.head.clamp(0.0, params.search_pitch)
    yaw, pitch = robot_model.look_at(pose, (float(object_x[0]), float(object_x[1]), params.aim_height))
    if centroid_uv is not None and camera is not None and head_at_capture is not None and params.servo_gain > 0.0:
        horizontal, vertical = object_pixel_direction(camera, centroid_uv)
        g = params.servo_gain
        yaw = (1.0 - g) * yaw + g * (head_at_capture[0] - horizontal)
        pitch = (1.0 - g) * pitch + g * (head_at_capture[1] + vertical)
    return robot_model.head.clamp(yaw, pitch)
