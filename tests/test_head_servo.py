"""Head servo: the target centres the object's aim point, respects the yaw-dependent pitch limits,
and follows a measured centroid."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from agent.camera import CameraModel
from agent.head_servo import HeadServoParams, ObjectHeight, head_target, load_head_servo_params
from agent.head_servo import object_top
from nao_core.geometry import planar_transform


@pytest.fixture(scope="module")
def params() -> HeadServoParams:
    return load_head_servo_params()


@pytest.fixture(scope="module")
def camera(robot) -> CameraModel:
    intr = robot.camera.intrinsics("vga")
    return CameraModel.from_intrinsics(intr)


def aim_pixel(robot, camera, pose, obj, params, head):
    T_WC = planar_transform(*pose) @ robot.camera_in_robot(*head)
    uv, in_front = camera.project_world(np.array([[obj[0], obj[1], params.aim_height]]), T_WC)
    assert in_front[0]
    return uv[0]


@pytest.mark.parametrize("bearing, distance", [(0.0, 1.0), (0.6, 1.2), (-0.9, 1.5), (0.3, 2.0)])
def test_target_puts_the_aim_point_on_the_optical_axis(params, robot, camera, bearing, distance):
    pose = (0.3, -0.2, 0.4)
    obj = (pose[0] + distance * math.cos(pose[2] + bearing), pose[1] + distance * math.sin(pose[2] + bearing), 0.05)
    head = head_target(robot, pose, obj, params)
    assert aim_pixel(robot, camera, pose, obj, params, head) == pytest.approx(camera.K[:2, 2], abs=0.5)


def test_target_is_clamped_and_pitch_limits_shrink_at_large_yaw(params, robot):
    pose = (0.0, 0.0, 0.0)
    behind = head_target(robot, pose, (-1.0, 0.05, 0.05), params)
    assert behind[0] == pytest.approx(robot.head.yaw[1])
    close_side = head_target(robot, pose, (0.05, 0.4, 0.05), params)  # beside the feet: steep pitch
    lo, hi = robot.head.pitch_range(close_side[0])
    assert lo <= close_side[1] <= hi and close_side[1] == pytest.approx(hi)
    assert hi < robot.head.pitch_range(0.0)[1]


def test_measured_centroid_pulls_the_target(params, robot, camera):
    pose, obj = (0.0, 0.0, 0.0), (1.0, 0.0, 0.05)
    model = head_target(robot, pose, obj, params)
    # The object was seen 40 px right of the centre with the head at the model target: turn right.
    seen = (camera.K[0, 2] + 40.0, camera.K[1, 2])
    pulled = head_target(robot, pose, obj, params, centroid_uv=seen, camera=camera, head_at_capture=model)
    expected = model[0] - params.servo_gain * math.atan2(40.0, camera.K[0, 0])
    assert pulled[0] == pytest.approx(expected, abs=1e-9) and pulled[1] == pytest.approx(model[1], abs=1e-9)
    pure_model = dataclasses.replace(params, servo_gain=0.0)
    assert head_target(robot, pose, obj, pure_model, centroid_uv=seen, camera=camera, head_at_capture=model) == pytest.approx(model)


def test_without_an_estimate_the_head_searches(params, robot):
    assert head_target(robot, None, (1.0, 0.0, 0.1), params) == robot.head.clamp(0.0, params.search_pitch)
    assert head_target(robot, (0.0, 0.0, 0.0), None, params) == robot.head.clamp(0.0, params.search_pitch)


def test_object_top_inverts_the_projection_of_the_far_rim(robot, camera):
    # A can of radius r and top H seen from above: its top silhouette row is the far rim's image,
    # so the row's upper edge (v_t - 1/2) must give H back exactly, from any range and head angle.
    r, H = 0.05, 0.2
    for distance, head in ((0.8, (0.0, 0.3)), (1.2, (0.4, 0.2))):
        pose = (0.0, 0.0, 0.0)
        T_WC = planar_transform(*pose) @ robot.camera_in_robot(*head)
        centre = T_WC[:3, 3]
        obj = (centre[0] + distance, centre[1] + 0.02, r)
        away = np.array([obj[0] - centre[0], obj[1] - centre[1]]) / math.hypot(obj[0] - centre[0], obj[1] - centre[1])
        rim = np.array([[obj[0] + r * away[0], obj[1] + r * away[1], H]])
        uv, in_front = camera.project_world(rim, T_WC)
        assert in_front[0]
        assert object_top(uv[0, 1] + 0.5, uv[0, 0], camera, T_WC, obj) == pytest.approx(H, abs=1e-9)


def test_object_height_ignores_cut_tops_and_aims_at_the_middle(robot, camera):
    height = ObjectHeight(window=3)
    T_WC = robot.camera_in_robot(0.0, 0.3)
    assert height.aim is None
    height.update(10, 320.0, True, camera, T_WC, (1.0, 0.0, 0.05))  # top cut by the image border: no bound
    height.update(10, 320.0, False, camera, T_WC, None)  # no estimate yet: no bound
    assert height.top is None
    height.update(200, 320.0, False, camera, T_WC, (1.0, 0.0, 0.05))
    assert height.aim == pytest.approx(0.5 * object_top(200, 320.0, camera, T_WC, (1.0, 0.0, 0.05)))


def test_pitch_follows_the_aim_height_not_a_cut_centroid(params, robot, camera):
    pose, obj = (0.0, 0.0, 0.0), (1.0, 0.0, 0.05)
    low, high = head_target(robot, pose, obj, params, aim_height=0.02), head_target(robot, pose, obj, params, aim_height=0.15)
    assert low[1] > high[1]  # aiming lower pitches the head further down (NAO pitch is positive down)
    seen_high = (camera.K[0, 2], camera.K[1, 2] - 60.0)  # a centroid high in the image (base cut off)
    assert head_target(robot, pose, obj, params, seen_high, camera, low, aim_height=0.02)[1] == pytest.approx(low[1])


def test_before_an_estimate_the_head_centres_a_silhouette_cut_by_the_side(params, robot, camera):
    """A blob cut by the right border gives no bearing, so no estimate starts; the head must turn right
    towards it (it once stayed straight ahead for a whole mission, the object half out of view)."""
    pose, head = (0.0, 0.0, 0.0), (0.0, 0.25)
    cut = (camera.width - 20.0, camera.K[1, 2] + 30.0)  # near the right edge, below the centre
    yaw, pitch = head_target(robot, pose, None, params, centroid_uv=cut, camera=camera, head_at_capture=head)
    horizontal, vertical = math.atan2(cut[0] - camera.K[0, 2], camera.K[0, 0]), math.atan2(30.0, camera.K[1, 1])
    assert yaw == pytest.approx(-horizontal, abs=1e-3) and yaw < -0.3  # turned right (NAO yaw: left positive)
    assert pitch == pytest.approx(min(head[1] + vertical, robot.head.pitch_range(yaw)[1]), abs=1e-3)
    assert head_target(robot, pose, None, params) == robot.head.clamp(0.0, params.search_pitch)  # nothing seen
