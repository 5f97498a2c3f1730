"""Markers tracked under motion smear (agent/marker_tracking.py): the image motion of a turning
camera against finite differences, the smear kernel's moments, and rendered frames of a room drawn
as users lay markers out, smeared by the simulator's shutter, with known poses."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from agent.camera import CameraModel
from agent.localization import LocalizationParams, RobotLocalizer, camera_in_world, landmarks_in_image
from agent.marker_tracking import SMEAR_FACTORS, marker_texture, rotation_flow, smear_kernel, track_marker
from agent.perception import PerceptionParams
from nao_core.config import CONFIG_DIR, load
from nao_core.robot_model import load_robot_model
from nao_sim.layouts import layout_file, sample_layout
from nao_sim.randomize import load_randomizer
from nao_sim.scenarios import load_sim_config
from nao_sim.world import SimWorld, orbit_pose

SMEAR_PX = 8.0  # a NAO's torso pitching at 0.25 rad/s over a 30 ms exposure (docs/landmarks.md "Markers under smear")


def test_rotation_flow_is_the_image_motion_of_a_turning_camera():
    """Points projected half a small turn before and after (R(t) = exp(t [w])) move by flow dt."""
    camera = CameraModel.from_fov(640, 480, math.radians(57))
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-1, 1, 20), rng.uniform(-0.7, 0.7, 20), rng.uniform(1, 3, 20)])
    rate, dt = np.array([0.3, -0.5, 0.8]), 1e-4
    before = camera.project(X @ cv2.Rodrigues(-rate * dt / 2)[0])  # X_C(t) = R(t)^T X: rows times R(t)
    after = camera.project(X @ cv2.Rodrigues(rate * dt / 2)[0])
    flow = rotation_flow(X[:, :2] / X[:, 2:], rate, (camera.K[0, 0], camera.K[1, 1]))
    assert (after - before) / dt == pytest.approx(flow, rel=1e-3, abs=1e-2)


@pytest.mark.parametrize("smear", [(7.0, 0.0), (0.0, 4.3), (6.0, -8.0)])
def test_smear_kernel_is_a_centred_line_of_the_smear_length(smear):
    """Sum 1, centroid on the middle pixel, second moment L^2 / 12 along the smear (a uniform line)
    plus the bilinear taps' and the sampled ends' spread, and under a pixel's across it."""
    kernel = smear_kernel(np.array(smear))
    assert kernel.sum() == pytest.approx(1.0)
    ys, xs = np.indices(kernel.shape)
    centre = (kernel.shape[1] - 1) / 2
    d = np.stack([xs - centre, ys - centre], axis=-1)
    assert (kernel[..., None] * d).sum(axis=(0, 1)) == pytest.approx([0.0, 0.0], abs=1e-6)
    direction = np.array(smear) / np.hypot(*smear)
    along, across = d @ direction, d @ np.array([-direction[1], direction[0]])
    length = float(np.hypot(*smear))
    assert length**2 / 12 <= (kernel * along**2).sum() <= 1.1 * length**2 / 12 + 0.25
    assert (kernel * across**2).sum() < 0.35
    assert smear_kernel(np.array([0.5, 0.5])) is None


@pytest.fixture(scope="module")
def smeared_views():
    """Frames of a drawn ArUco room (the robot on the orbit round the can, the head aimed at the
    markers nearest its heading), each rendered still and smeared by SMEAR_PX of camera pitch: (world,
    camera, list of (true pose, T_BC, T_WC mid-exposure, still image, smeared image, camera rate))."""
    robot = load_robot_model()
    drawn = sample_layout("aruco", load_randomizer().drawn_layout)
    config = load_sim_config().with_layout(str(layout_file(drawn)), drawn.half_size)
    world = SimWorld("can", robot, "vga", seed=5, config=config)
    camera = CameraModel.from_intrinsics(robot.camera.intrinsics("vga"))
    params = load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization")
    rng = np.random.default_rng(5)
    views = []
    for index in range(12):
        pose = orbit_pose(rng, world.scenario.position)
        world.teleport(pose, (float(rng.uniform(-0.5, 0.5)), 0.0))
        frame = world.render()
        T_WC = np.asarray(world.truth()["camera"]["T_WC"])
        w = np.array([SMEAR_PX / camera.K[1, 1], 0.0, 0.0])  # about the camera's x: a vertical smear
        smeared = world.renderer.render(T_WC, 1000 + index, T_WC[:3, :3] @ cv2.Rodrigues(w)[0])
        middle = T_WC.copy()
        middle[:3, :3] = T_WC[:3, :3] @ cv2.Rodrigues(0.5 * w)[0]  # the smear's centre: the mid-exposure camera
        views.append((pose, frame.T_BC, middle, frame.image, smeared, w / params.exposure))
    return world, camera, views


@pytest.fixture(scope="module")
def localization() -> tuple[LocalizationParams, PerceptionParams]:
    """The configured localization with tracking on (it is off by default, agent/marker_tracking.py)."""
    params = load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization")
    return (dataclasses.replace(params, track_smear_factors=SMEAR_FACTORS),
            load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception"))


def test_smeared_markers_the_detector_misses_are_tracked_to_their_centres(smeared_views, localization):
    """The detector finds under a fifth of the markers predicted in the smeared frames (>= 8 px side);
    tracking from a prior 1 cm / 0.3 deg off finds most of the rest, each centre within 1.5 px of
    where the mid-exposure camera sees it (0.5 px median)."""
    world, camera, views = smeared_views
    params, perception = localization
    localizer = RobotLocalizer(params, world.landmarks, camera, perception)
    detector = localizer.detector
    rng = np.random.default_rng(1)
    predicted = detected = 0
    errors = []
    for pose, T_BC, middle, _, smeared, rate in views:
        gray = cv2.cvtColor(smeared, cv2.COLOR_BGR2GRAY)
        prior = tuple(np.array(pose) + rng.normal(0.0, [0.01, 0.01, 0.005]))
        T_prior = camera_in_world(prior, T_BC)
        found = detector.aruco_points(gray, detector.predicted_boxes(camera, T_prior))
        tracked = detector.tracked_points(gray, camera, T_prior, found.ids, rate, params.exposure)
        for landmark in world.landmarks.of_kind("aruco"):
            marker_id, corners = int(landmark.id), landmark.aruco_corners()
            uv, in_front = camera.project_world(corners, middle)
            side = np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1).min()
            inside = np.all((uv >= 20) & (uv <= [camera.width - 21, camera.height - 21]))
            facing = np.dot(landmark.normal, middle[:3, 3] - corners.mean(axis=0)) > 0
            if not (in_front.all() and inside and facing and side >= params.track_min_side_px):
                continue
            predicted += 1
            detected += marker_id in found.ids
            if marker_id in tracked.ids:
                centre, _ = camera.project_world(corners.mean(axis=0)[None], middle)
                errors.append(float(np.linalg.norm(tracked.u[tracked.ids.index(marker_id)] - centre[0])))
    assert predicted >= 20
    assert detected < 0.2 * predicted
    assert detected + len(errors) >= 0.7 * predicted
    assert max(errors) <= 1.5 and np.median(errors) <= 0.5


def test_smeared_frames_give_fixes_with_tracking_and_none_confirms_a_wrong_prior(smeared_views, localization):
    """From a prior 1 cm off, >= 80 % of the smeared frames showing three markers or more give a fix,
    within 1 cm (median) and 3 cm (each), where the detector alone gives almost none. From a prior
    20 cm off, tracking finds nothing it could pull a fix towards the prior with: every fix is within
    3 cm of the truth."""
    world, camera, views = smeared_views
    params, perception = localization
    tracking = RobotLocalizer(params, world.landmarks, camera, perception)
    alone = RobotLocalizer(dataclasses.replace(params, track_smear_factors=()), world.landmarks, camera, perception)
    rng = np.random.default_rng(2)
    errors, untracked, wrong_prior, showing = [], 0, [], 0
    for pose, T_BC, middle, _, smeared, rate in views:
        showing += landmarks_in_image(camera, world.landmarks, middle) >= 3
        prior = tuple(np.array(pose) + rng.normal(0.0, [0.01, 0.01, 0.005]))
        fix = tracking.measure(smeared, T_BC, prior, camera_rate=rate)
        if fix is not None:
            errors.append(math.dist(fix.pose[:2], pose[:2]))
        untracked += alone.measure(smeared, T_BC, prior, camera_rate=rate) is not None
        off = np.array(pose) + np.array([0.2 * math.cos(pose[2] + 1.0), 0.2 * math.sin(pose[2] + 1.0), 0.0])
        far = tracking.measure(smeared, T_BC, tuple(off), camera_rate=rate)
        if far is not None:
            wrong_prior.append(math.dist(far.pose[:2], pose[:2]))
    assert showing >= 6 and len(errors) >= 0.8 * showing and untracked <= 0.25 * showing
    assert np.median(errors) <= 0.01 and max(errors) <= 0.03
    assert all(e <= 0.03 for e in wrong_prior)


@pytest.mark.parametrize("quad", [
    [[300, 200]] * 4,                                    # a point
    [[300, 200], [340, 200], [380, 200], [420, 200]],    # a line
    [[-30, 200], [10, 200], [10, 240], [-30, 240]],      # across the border
    [[300, 200], [260, 200], [260, 240], [300, 240]],    # seen from behind (mirrored)
])
def test_hostile_predictions_and_flat_images_track_nothing(quad):
    """A predicted quad that is a point, a line, across the image border or mirrored, in a flat or a
    noisy image: no match (None, or a correlation under the configured 0.8), and nothing raises."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    texture, corners = marker_texture(dictionary, 3)
    rng = np.random.default_rng(0)
    for gray in (np.full((480, 640), 128, np.uint8), rng.integers(0, 256, (480, 640), dtype=np.uint8)):
        found = track_marker(gray, texture, corners, np.array(quad, float), np.array([0.0, 6.0]), (0.6, 0.3, 0.0), 1.0, 16.0)
        assert found is None or found.correlation < 0.8
