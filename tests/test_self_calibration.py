"""Self-calibration (agent/self_calibration.py) against ground truth: landmark corners of a user's
wall layout projected by a camera whose intrinsics differ from the configured ones by a known error,
from poses around an object, with the torso roll and pixel noise of a standing NAO's fixes (the
only ones it stores)."""

from __future__ import annotations

import dataclasses
import math
from typing import List, Optional, Tuple

import numpy as np
import pytest

from agent.camera import CameraModel
from agent.localization import LocalizationParams, RobotLocalizer
from agent.self_calibration import SelfCalibration, SelfCalibrationParams, corrected
from nao_core.config import CONFIG_DIR, load
from nao_core.geometry import Pose, camera_in_world, rot_x
from nao_core.landmark_map import load_landmark_map
from nao_core.robot_model import load_robot_model

ROBOT = load_robot_model()
CAMERA = CameraModel.from_intrinsics(ROBOT.camera.intrinsics("vga"))
MAP = load_landmark_map(CONFIG_DIR / "landmarks" / "walls.yaml")
LOCALIZATION = load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization")
PARAMS = load(SelfCalibrationParams, [CONFIG_DIR / "self_calibration.yaml"], section="self_calibration")
PIXEL_NOISE = 0.2  # px per axis, about the corner refinement's
ROLL = LOCALIZATION.roll_sigma_still  # rad, the torso roll T_BC misses, standing


def observe(rng: np.random.Generator, true_camera: CameraModel) -> Optional[Tuple[Pose, np.ndarray, np.ndarray, np.ndarray]]:
    """A pose 0.6-1.1 m from the room's centre with the head somewhere in its range, and the corners
    of the markers wholly in view as ``true_camera`` sees them: (pose, T_BC, world N x 3, pixels N x 2)."""
    d, az = rng.uniform(0.6, 1.1), rng.uniform(-math.pi, math.pi)
    pose = (d * math.cos(az), d * math.sin(az), rng.uniform(-math.pi, math.pi))
    T_BC = ROBOT.camera_in_robot(rng.uniform(-1.5, 1.5), rng.uniform(-0.1, 0.3))
    T_WC = camera_in_world(pose, rot_x(rng.normal(0.0, ROLL)) @ T_BC)
    world, pixels = [], []
    for marker in MAP.of_kind("aruco"):
        corners = marker.aruco_corners()
        uv, front = true_camera.project_world(corners, T_WC)
        facing = np.dot(marker.normal, T_WC[:3, 3] - corners.mean(axis=0)) > 0
        inside = np.all((uv >= 3) & (uv <= np.array([CAMERA.width, CAMERA.height]) - 3))
        if front.all() and facing and inside:
            world.append(corners)
            pixels.append(uv)
    if len(world) < 2:
        return None
    return pose, T_BC, np.vstack(world), np.vstack(pixels) + rng.normal(0.0, PIXEL_NOISE, (4 * len(world), 2))


def first_view(seed: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T_BC, world points, pixels) of the first pose drawn from ``seed`` that shows two markers, exact camera."""
    rng = np.random.default_rng(seed)
    while (seen := observe(rng, CAMERA)) is None:
        pass
    return seen[1:]


def mission(error: np.ndarray, frames: int, params: SelfCalibrationParams = PARAMS, seed: int = 0):
    """Fixes as a mission makes them (the localizer on the calibration's current camera), fed to a
    SelfCalibration: (it, [(position error m, applied) per fix])."""
    rng = np.random.default_rng(seed)
    true_camera = corrected(CAMERA, error)
    calibration = SelfCalibration(params, CAMERA)
    localizer = RobotLocalizer(LOCALIZATION, MAP, CAMERA)
    errors: List[Tuple[float, bool]] = []
    t = 0.0
    while len(errors) < frames:
        seen = observe(rng, true_camera)
        if seen is None:
            continue
        pose, T_BC, world, pixels = seen
        localizer.camera = calibration.camera
        fix = localizer.fit(world, pixels, T_BC, roll_sigma=ROLL)
        if fix is None:
            continue
        errors.append((math.hypot(fix.pose[0] - pose[0], fix.pose[1] - pose[1]), calibration.applied is not None))
        t += 1.0
        calibration.add(fix, t)
    return calibration, errors


def test_a_calibration_off_by_half_a_percent_and_a_pixel_is_found_and_the_fixes_recover():
    error = np.array([0.005, -0.005, 1.0, -1.0])  # the matrix's randomized calibration error (config/sim.yaml)
    calibration, errors = mission(error, 120)
    applied = calibration.applied
    assert applied is not None
    std = np.sqrt(np.diag(applied.covariance))
    # the focal scales and the vertical principal point are observed: within 3 sigma and 0.1 % / 0.2 px
    assert np.all(np.abs(applied.c[[0, 1, 3]] - error[[0, 1, 3]]) <= np.maximum(3.0 * std[[0, 1, 3]], [0.001, 0.001, 0.2])), (applied.c, std)
    # a horizontal principal point shift is nearly a turn of the robot: its prior holds it, within that prior
    assert abs(applied.c[2] - error[2]) <= PARAMS.principal_sigma
    before = [e for e, calibrated in errors if not calibrated]
    after = [e for e, calibrated in errors if calibrated]
    assert len(before) >= PARAMS.min_frames
    # the error was common to every fix (a bias); corrected, the fixes are within noise: 3 x better
    assert np.median(after) < np.median(before) / 3.0, (np.median(before), np.median(after))


def test_an_exact_calibration_stays_exact():
    calibration, errors = mission(np.zeros(4), 60)
    assert calibration.applied is not None
    assert np.all(np.abs(calibration.applied.c[[0, 1]]) <= 0.001) and abs(calibration.applied.c[3]) <= 0.2, calibration.applied.c
    assert np.median([e for e, _ in errors]) < 0.005


def test_a_wrongly_associated_fix_is_dropped_not_believed():
    calibration, _ = mission(np.zeros(4), 30)
    good = calibration.solve()
    fix = calibration.fixes[-1]
    shifted = dataclasses.replace(fix, u=fix.u + np.array([15.0, 0.0]) * np.sign(fix.u[:, :1] - CAMERA.K[0, 2]))
    calibration.fixes[-1] = shifted  # one fix's points spread 15 px: a wrong marker identity
    estimate = calibration.solve()
    assert estimate is not None and estimate.frames == good.frames - 1
    assert np.allclose(estimate.c[[0, 1]], good.c[[0, 1]], atol=5e-4)


def test_disabled_it_never_changes_the_camera():
    calibration, _ = mission(np.array([0.01, 0.01, 0.0, 0.0]), 30, dataclasses.replace(PARAMS, enabled=False))
    assert calibration.applied is None and calibration.camera is CAMERA


@pytest.mark.parametrize("points", [0, 4])
def test_fixes_with_too_few_points_are_not_stored(points):
    calibration = SelfCalibration(PARAMS, CAMERA)
    localizer = RobotLocalizer(LOCALIZATION, MAP, CAMERA)
    T_BC, world, pixels = first_view(3)
    fix = localizer.fit(world, pixels, T_BC, roll_sigma=ROLL)
    assert fix is not None
    few = dataclasses.replace(fix, inliers=(world[:points], pixels[:points]))
    assert not calibration.add(few, 1.0) and not calibration.fixes


def test_walking_fixes_are_not_stored():
    """Walking, the sway the kinematics miss would pass for a calibration error: the localizer's
    walking roll prior marks such a fix, and it is left out."""
    calibration = SelfCalibration(PARAMS, CAMERA)
    localizer = RobotLocalizer(LOCALIZATION, MAP, CAMERA)
    T_BC, world, pixels = first_view(4)
    walking = localizer.fit(world, pixels, T_BC, roll_sigma=LOCALIZATION.roll_sigma)
    standing = localizer.fit(world, pixels, T_BC, roll_sigma=LOCALIZATION.roll_sigma_still)
    assert walking is not None and standing is not None
    calibration.add(walking, 1.0)
    assert not calibration.fixes
    calibration.add(standing, 2.0)
    assert len(calibration.fixes) == 1
