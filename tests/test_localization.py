"""Robot localization against ground truth: simulator frames with known poses, drawn colour
landmarks with known projections, odometry composition and covariance growth, gates, garbage."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from agent.camera import CameraModel
from agent.localization import LocalizationParams, RobotLocalizer
from agent.perception import ImageError, PerceptionParams
from nao_core.config import CONFIG_DIR, load
from nao_core.geometry import compose, planar_transform, relative, wrap_angle
from nao_core.landmark_map import Landmark, LandmarkMap, load_landmark_map
from nao_sim.render import COLOURS_BGR
from nao_sim.world import SimWorld


@pytest.fixture(scope="module")
def params() -> LocalizationParams:
    return load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization")


@pytest.fixture(scope="module")
def perception() -> PerceptionParams:
    return load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")


@pytest.fixture(scope="module")
def room() -> LandmarkMap:
    return load_landmark_map(CONFIG_DIR / "landmarks" / "sim_room.yaml")


def camera_of(robot, resolution: str) -> CameraModel:
    intr = robot.camera.intrinsics(resolution)
    return CameraModel.from_intrinsics(intr)


def pose_error(pose, truth):
    return math.hypot(pose[0] - truth[0], pose[1] - truth[1]), abs(wrap_angle(pose[2] - truth[2]))


def test_aruco_fix_within_1cm_and_half_a_degree_at_2m(params, perception, robot, room):
    """Sim VGA frames, the robot 0.5 m from the centre looking out at the markers on the 1.5 m ring."""
    world = SimWorld("can", robot, "vga", seed=5)
    camera = camera_of(robot, "vga")
    for azimuth in np.linspace(-math.pi, math.pi, 8, endpoint=False):
        pose = (-0.5 * math.cos(azimuth), -0.5 * math.sin(azimuth), azimuth + 0.1)
        target = (1.5 * math.cos(azimuth), 1.5 * math.sin(azimuth), 0.085)
        world.teleport(pose, robot.look_at(pose, target))
        frame = world.render()
        localizer = RobotLocalizer(params, room, camera, perception)
        fix = localizer.on_frame(frame.image, frame.T_BC, frame.odom, frame.stamp)
        assert fix is not None and len(fix.landmark_ids) >= 2
        distance, angle = pose_error(fix.pose, world.truth()["robot_pose"])
        assert distance < 0.01 and angle < math.radians(0.5)
        assert localizer.pose == pytest.approx(fix.pose)
        assert np.all(np.sqrt(np.diag(fix.covariance)) < [0.02, 0.02, 0.02])


def test_too_few_landmarks_gives_no_fix(params, perception, robot, room):
    camera = camera_of(robot, "qvga")
    localizer = RobotLocalizer(params, room, camera, perception)
    T_BC = robot.camera_in_robot(0.0, 0.3)
    assert localizer.on_frame(np.full((240, 320, 3), 128, np.uint8), T_BC, (0.0, 0.0, 0.0), 0.0) is None
    assert localizer.pose is None
    # One colour disc only (3 points short of a fix), drawn where the map says.
    lm = next(lm for lm in room.of_kind("color") if lm.id == "green-1")
    pose = (0.5, 0.3, 0.0)
    uv, _ = camera.project_world(np.array([lm.position]), planar_transform(*pose) @ T_BC)
    image = np.full((240, 320, 3), 128, np.uint8)
    cv2.circle(image, tuple(int(round(c)) for c in uv[0]), 6, COLOURS_BGR["green"], -1)
    assert localizer.on_frame(image, T_BC, (0.0, 0.0, 0.0), 1.0) is None and localizer.pose is None


def colour_scene(camera: CameraModel, T_WC: np.ndarray, landmarks) -> np.ndarray:
    image = np.full((camera.height, camera.width, 3), 128, np.uint8)
    uv, _ = camera.project_world(np.array([lm.position for lm in landmarks]), T_WC)
    for lm, p in zip(landmarks, uv):
        cv2.circle(image, (int(round(p[0] * 16)), int(round(p[1] * 16))), 6 * 16, COLOURS_BGR[lm.color], -1, cv2.LINE_AA, 4)
    return image


def test_repeated_colours_are_associated_by_the_prior(params, perception, robot):
    """Three green and three yellow discs on a wall 2 m ahead; a prior 5 cm / 2 deg off."""
    landmarks = tuple(
        Landmark(id=f"{color}-{i}", kind="color", color=color, position=(2.0, y, z))
        for i, (color, y, z) in enumerate(
            [("green", -0.6, 0.3), ("green", 0.0, 0.6), ("green", 0.6, 0.3), ("yellow", -0.3, 0.6), ("yellow", 0.3, 0.2), ("yellow", 0.5, 0.7)]
        )
    )
    camera = camera_of(robot, "vga")
    T_BC = robot.camera_in_robot(0.0, 0.0)
    truth = (0.0, 0.0, 0.02)
    image = colour_scene(camera, planar_transform(*truth) @ T_BC, landmarks)
    localizer = RobotLocalizer(params, LandmarkMap(landmarks), camera, perception)
    assert localizer.on_frame(image, T_BC, (0.0, 0.0, 0.0), 0.0) is None  # no prior: colours repeat, no fix
    localizer._correction, localizer.covariance = (0.05, -0.03, 0.02 + math.radians(2)), np.diag([0.05, 0.05, 0.05]) ** 2
    fix = localizer.on_frame(image, T_BC, (0.0, 0.0, 0.0), 1.0)
    assert fix is not None and sorted(fix.landmark_ids) == sorted(lm.id for lm in landmarks)
    distance, angle = pose_error(fix.pose, truth)
    assert distance < 0.02 and angle < math.radians(0.5)


def test_ambiguous_colour_blobs_are_dropped(params, perception, robot):
    """Two green discs 4 cm apart at 2 m: both within the gate of both predictions -> neither used."""
    landmarks = (
        Landmark(id="g1", kind="color", color="green", position=(2.0, 0.0, 0.5)),
        Landmark(id="g2", kind="color", color="green", position=(2.0, 0.04, 0.5)),
    )
    camera = camera_of(robot, "vga")
    localizer = RobotLocalizer(params, LandmarkMap(landmarks), camera, perception)
    T_WC = robot.camera_in_robot(0.0, 0.0)
    image = colour_scene(camera, T_WC, landmarks)
    assert localizer.detector.color_points(image, camera, T_WC) == ([], [], [])


def test_odometry_carries_the_pose_and_grows_the_covariance(params, perception, robot, room):
    world = SimWorld("can", robot, "vga", seed=2)
    camera = camera_of(robot, "vga")
    pose = (-0.5, 0.0, 0.0)
    world.teleport(pose, robot.look_at(pose, (1.5, 0.0, 0.085)))
    frame = world.render()
    localizer = RobotLocalizer(params, room, camera, perception)
    localizer.on_odometry((1.0, 2.0, 0.5), frame.stamp - 0.1)
    fix = localizer.on_frame(frame.image, frame.T_BC, (1.0, 2.0, 0.5), frame.stamp)
    assert fix is not None
    previous = np.trace(localizer.covariance)
    step = (0.1, 0.02, 0.05)
    odom = (1.0, 2.0, 0.5)
    for k in range(10):
        odom = compose(odom, step)
        localizer.on_odometry(odom, frame.stamp + k + 1)
        assert np.trace(localizer.covariance) > previous
        previous = np.trace(localizer.covariance)
    expected = fix.pose
    for _ in range(10):
        expected = compose(expected, step)
    assert localizer.pose == pytest.approx(expected, abs=1e-9)
    localizer.on_odometry((9.0, 9.0, 0.0), frame.stamp)  # older than the last reading: ignored
    assert localizer.pose == pytest.approx(expected, abs=1e-9)
    assert relative(fix.pose, compose(fix.pose, step)) == pytest.approx(step)


def test_a_jump_is_rejected_until_it_repeats(params, perception, robot, room):
    world = SimWorld("can", robot, "vga", seed=4)
    camera = camera_of(robot, "vga")
    pose = (-0.5, 0.0, 0.0)
    world.teleport(pose, robot.look_at(pose, (1.5, 0.0, 0.085)))
    frame = world.render()
    localizer = RobotLocalizer(params, room, camera, perception)
    localizer._correction, localizer.covariance = (0.5, 0.4, 0.0), np.diag([0.01, 0.01, 0.01]) ** 2  # a wrong prior
    localizer._odom = (0.0, 0.0, 0.0)
    for k in range(params.max_rejected_jumps - 1):
        assert localizer.on_frame(frame.image, frame.T_BC, (0.0, 0.0, 0.0), float(k)) is None
        assert localizer.pose == pytest.approx((0.5, 0.4, 0.0))
    fix = localizer.on_frame(frame.image, frame.T_BC, (0.0, 0.0, 0.0), 10.0)
    assert fix is not None and pose_error(localizer.pose, world.truth()["robot_pose"])[0] < 0.01


@pytest.mark.parametrize(
    "image, error",
    [
        (None, ImageError),
        (np.zeros((480, 640, 3), np.uint8), ImageError),  # wrong size for the QVGA camera
        (np.zeros((240, 320, 3), np.int16), ImageError),
        (np.zeros((240, 320), np.uint8), ImageError),
    ],
)
def test_garbage_frames_raise_a_clear_value_error(params, perception, robot, room, image, error):
    localizer = RobotLocalizer(params, room, camera_of(robot, "qvga"), perception)
    with pytest.raises(error):
        localizer.on_frame(image, robot.camera_in_robot(0, 0), (0, 0, 0), 0.0)


def test_bad_transform_or_odometry_raise_value_error(params, robot, room):
    localizer = RobotLocalizer(params, room, camera_of(robot, "qvga"))
    image = np.zeros((240, 320, 3), np.uint8)
    with pytest.raises(ValueError, match="T_BC"):
        localizer.on_frame(image, np.eye(3), (0, 0, 0), 0.0)
    with pytest.raises(ValueError, match="odom"):
        localizer.on_frame(image, np.eye(4), (0, math.nan, 0), 0.0)
    with pytest.raises(ValueError, match="odom"):
        localizer.on_odometry("abc", 0.0)


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_walking_fixes_and_odometry_track_the_true_pose(params, perception, robot, room):
    """Sim: 12 s circling the object (speed-scale error, slip, sway), 5 frames/s at QVGA, states in
    between: after the first fixes the pose stays within 3 cm of the truth; dead reckoning drifts."""
    clock = _Clock()
    world = SimWorld("can", robot, "qvga", seed=3, clock=clock)
    localizer = RobotLocalizer(params, room, camera_of(robot, "qvga"), perception)
    obj = (*world.scenario.position, 0.1)
    world.walk(0.08, 0.0, 0.08)
    errors, fixes = [], 0
    for _ in range(60):
        clock.t += 0.1
        world.set_head(*robot.look_at(world.truth()["robot_pose"], obj), 1.0)
        state = world.state()
        localizer.on_odometry(state.odom, state.stamp)
        clock.t += 0.1
        frame = world.render()
        fixes += localizer.on_frame(frame.image, frame.T_BC, frame.odom, frame.stamp) is not None
        errors.append(pose_error(localizer.pose, world.truth()["robot_pose"]))
    errors = np.array(errors[5:])
    assert fixes >= 55
    assert errors[:, 0].max() < 0.03 and errors[:, 0].mean() < 0.015 and errors[:, 1].max() < math.radians(1.5)
    truth = world.truth()
    dead_reckoning = compose(tuple(truth["odom_origin"]), tuple(truth["odom"]))
    assert pose_error(dead_reckoning, truth["robot_pose"])[0] > 3 * errors[-1, 0]


def test_fix_covariance_is_not_overconfident(params, perception, robot, room):
    """NEES of single-frame fixes over random orbit views: below the chi-square(3) 99 % bound."""
    world = SimWorld("can", robot, "qvga", seed=7)
    camera = camera_of(robot, "qvga")
    rng = np.random.default_rng(1)
    ox, oy = world.scenario.position
    nees = []
    for _ in range(20):
        d, az = rng.uniform(0.6, 1.2), rng.uniform(-math.pi, math.pi)
        pose = (ox + d * math.cos(az), oy + d * math.sin(az), az + math.pi)
        world.teleport(pose, robot.look_at(pose, (ox, oy, 0.1)))
        frame = world.render()
        fix = RobotLocalizer(params, room, camera, perception).on_frame(frame.image, frame.T_BC, frame.odom, frame.stamp)
        truth = world.truth()["robot_pose"]
        e = np.array([fix.pose[0] - truth[0], fix.pose[1] - truth[1], wrap_angle(fix.pose[2] - truth[2])])
        nees.append(e @ np.linalg.solve(fix.covariance, e))
    assert np.max(nees) < 11.34 and np.mean(nees) < 3.0


def test_markers_searched_around_the_prior_give_the_full_search_fix(params, perception, robot, room):
    """VGA orbit views: with a prior 3 cm / 1.5 deg off, the boxes around the predicted markers
    (a fraction of the frame) give the same markers and pose as searching the whole frame; with a
    prior 1 m and 90 deg off, the boxes find too few corners and the whole frame is searched."""
    world = SimWorld("can", robot, "vga", seed=2)
    camera = camera_of(robot, "vga")
    localizer = RobotLocalizer(params, room, camera, perception)
    ox, oy = world.scenario.position
    for azimuth in (0.3, 2.2, -1.9):
        truth = (ox + 0.9 * math.cos(azimuth), oy + 0.9 * math.sin(azimuth), azimuth + math.pi)
        world.teleport(truth, robot.look_at(truth, (ox, oy, 0.1)))
        frame = world.render()
        near = (truth[0] + 0.03, truth[1] - 0.02, truth[2] + math.radians(1.5))
        boxes = localizer.detector.predicted_boxes(camera, planar_transform(*near) @ frame.T_BC)
        assert 0 < sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in boxes) < 0.5 * camera.width * camera.height
        full = localizer.measure(frame.image, frame.T_BC)
        for prior in (near, (truth[0] + 1.0, truth[1], truth[2] + math.pi / 2)):
            fix = localizer.measure(frame.image, frame.T_BC, prior)
            assert sorted(fix.landmark_ids) == sorted(full.landmark_ids)
            assert fix.pose == pytest.approx(full.pose, abs=1e-6)
            distance, angle = pose_error(fix.pose, truth)
            assert distance < 0.01 and angle < math.radians(0.5)
