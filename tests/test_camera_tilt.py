"""The camera's tilt on its mount (agent/camera_tilt.py): the body-frame map, its learning from standing
fixes against ground truth on rendered frames, and Monte-Carlo consistency of the estimate."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from agent.camera import CameraModel
from agent.camera_tilt import CameraTilt, body_tilt_map
from agent.localization import LocalizationParams, PlanarModel, RobotLocalizer
from agent.perception import PerceptionParams
from nao_core.config import CONFIG_DIR, load
from nao_core.geometry import rot_x, rot_y
from nao_core.landmark_map import LandmarkMap
from nao_sim.scenarios import load_sim_config
from nao_sim.world import SimWorld


@pytest.fixture(scope="module")
def params() -> LocalizationParams:
    return load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization")


def _apply(T_BC: np.ndarray, b) -> np.ndarray:
    """The camera turned by the tilt b = (roll, pitch) in its own (optical) frame."""
    tilt = CameraTilt((1e-3, 1e-3), 1e-4)
    tilt.estimate = np.asarray(b, dtype=float)
    return tilt.correct(T_BC)


@pytest.mark.parametrize("head", [(0.0, 0.0), (0.0, 0.4), (1.2, -0.1), (-0.8, 0.3)])
def test_a_camera_tilt_is_the_body_tilt_A_b_to_first_order(robot, head):
    """The camera turned in its own frame by b is the body turned by R_BC omega_C: its roll and pitch
    components are A b (to 2 % at 0.6 deg), whatever the head's yaw and pitch."""
    T_BC = robot.camera_in_robot(*head)
    b = np.array([0.01, -0.008])
    R = _apply(T_BC, b)[:3, :3] @ T_BC[:3, :3].T
    omega = cv2.Rodrigues(R)[0].ravel()
    np.testing.assert_allclose(omega[:2], body_tilt_map(T_BC) @ b, rtol=0.02, atol=2e-4)


def test_standing_fixes_learn_the_camera_tilt_on_rendered_frames(params, robot):
    """A standing robot whose camera sits 0.5 deg rolled and 0.7 deg pitched up on its mount
    (unreported: the simulator renders it, T_BC omits it) looks round a room of wall markers at
    several heights, 3 m ahead. Its fixes learn the tilt to 0.1 deg, and the fixes after that are
    within 1 cm of the truth. (Markers at several heights also hold a fit whose tilt prior is zero:
    the mission this matters in is a sparse layout's, docs/landmarks.md.)"""
    truth_tilt = (math.radians(0.5), math.radians(-0.7))
    base = load_sim_config()
    config = dataclasses.replace(base.with_layout("landmarks/walls.yaml", 2.0), noise=dataclasses.replace(base.noise, mount_error=truth_tilt))
    world = SimWorld("can", robot, "vga", seed=3, config=config)
    camera = CameraModel.from_intrinsics(robot.camera.intrinsics("vga"))
    perception = load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")
    learning = RobotLocalizer(params, world.landmarks, camera, perception)
    pose = (-1.0, 0.3, 0.1)  # markers 3 m ahead
    errors = []
    for k, yaw in enumerate(np.tile(np.linspace(-0.9, 0.9, 7), 3)):
        world.teleport(pose, (float(yaw), 0.05))
        frame = world.render()
        learning.reset()  # every frame a cold fix: the errors are the frames', not the fusion's
        fix = learning.on_frame(frame.image, frame.T_BC, (0.0, 0.0, 0.0), 0.1 * k)
        if fix is not None and k >= 7:
            errors.append(math.hypot(fix.pose[0] - pose[0], fix.pose[1] - pose[1]))
    # the principal point is exact here, so the learnt tilt is the mount's
    np.testing.assert_allclose(learning.tilt.estimate, truth_tilt, atol=math.radians(0.1))
    assert np.all(learning.tilt.std < math.radians(0.1))
    assert len(errors) >= 10 and max(errors) <= 0.01


def test_the_learnt_tilt_is_consistent_monte_carlo(params, robot):
    """Monte Carlo, 200 robots: a true tilt drawn from the prior (0.6 deg per axis), six standing
    frames each at a random head yaw of synthetic markers at several heights, every frame with
    its own torso roll and pitch drawn from the standing priors and 0.15 px of corner noise (a frame
whose pitch is beyond the 3-sigma gate gives no fix: at most 1 %). The
    estimate's NEES against the true tilt (no floor on its covariance) averages 2 (chi-square,
    2 dof: 99 % of means within 1.6-2.4 for 200 runs; the first-order model allowed for: 1.5-2.6)."""
    camera = CameraModel.from_fov(640, 480, math.radians(57.0))
    rng = np.random.default_rng(11)
    square = np.array([[0.0, -0.065, -0.065], [0.0, 0.065, -0.065], [0.0, 0.065, 0.065], [0.0, -0.065, 0.065]])
    X = np.concatenate([square + (2.0, y, z) for y, z in ((-1.2, 0.25), (-0.4, 0.7), (0.4, 0.35), (1.2, 0.6))])
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    sigma = np.asarray(params.camera_tilt_sigma)
    unfloored = dataclasses.replace(params, camera_tilt_floor=1e-6)  # the floor's margin is a choice, not the model
    nees, missed = [], 0
    for _ in range(200):
        b = rng.normal(0.0, sigma)
        localizer = RobotLocalizer(unfloored, LandmarkMap(()), camera)
        frames = {}

        def measure(image, T_BC, prior=None, roll_sigma=None, camera_rate=None, prior_covariance=None):
            return localizer.fit(X, frames["pixels"], T_BC, prior, roll_sigma=roll_sigma, prior_covariance=prior_covariance)

        localizer.measure = measure
        for k in range(6):
            T_BC = robot.camera_in_robot(rng.uniform(-0.4, 0.4), 0.05)
            sway = rot_x(rng.normal(0.0, params.roll_sigma_still)) @ rot_y(rng.normal(0.0, params.pitch_sigma))
            seen_by = PlanarModel(camera, sway @ _apply(T_BC, b))
            frames["pixels"] = seen_by.project(np.zeros(3), X)[0] + rng.normal(0.0, params.pixel_sigma, (len(X), 2))
            localizer.reset()
            missed += localizer.on_frame(image, T_BC, (0.0, 0.0, 0.0), 0.1 * k) is None  # a 3-sigma pitch is no fix
        e = localizer.tilt.estimate - b
        nees.append(e @ np.linalg.solve(localizer.tilt.covariance, e))
    assert 1.5 < np.mean(nees) < 2.6
    assert missed <= 12  # of 1200 frames
