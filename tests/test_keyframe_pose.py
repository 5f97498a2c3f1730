"""Keyframe camera pose refined against the frame's landmarks (agent/keyframe_pose.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from agent.camera import CameraModel
from agent.carving import load_carving_params
from agent.keyframe_pose import refine_camera_pose
from agent.localization import LocalizationParams, RobotLocalizer
from agent.perception import PerceptionParams
from nao_core.config import CONFIG_DIR, load
from nao_core.geometry import camera_in_world, invert, wrap_angle
from nao_core.robot_model import load_robot_model
from nao_sim.world import SimWorld
from tests.carving_scenes import look_at

CARVING = load_carving_params()
LOCALIZATION = load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization")
K = np.array([[587.0, 0.0, 320.0], [0.0, 587.0, 240.0], [0.0, 0.0, 1.0]])
OBJECT = np.array([[0.8 + 0.05 * math.cos(a), 0.05 * math.sin(a), z]
                   for a in np.linspace(0.0, 2 * math.pi, 12, endpoint=False) for z in (0.0, 0.12)])


def _project(T_WC: np.ndarray, X: np.ndarray) -> np.ndarray:
    T = invert(T_WC)
    X_C = X @ T[:3, :3].T + T[:3, 3]
    return X_C[:, :2] / X_C[:, 2:3] * np.diag(K)[:2] + K[:2, 2]


def _object_error(T_WC: np.ndarray, truth: np.ndarray) -> float:
    """Mean image displacement, px, of the object's rim between a camera pose and the true one."""
    return float(np.mean(np.linalg.norm(_project(T_WC, OBJECT) - _project(truth, OBJECT), axis=1)))


def _perturbed(T_WC: np.ndarray, rng: np.random.Generator, degrees: float, metres: float) -> np.ndarray:
    T = T_WC.copy()
    T[:3, :3] = T_WC[:3, :3] @ cv2.Rodrigues(rng.normal(0.0, math.radians(degrees), 3))[0]
    T[:3, 3] += rng.normal(0.0, metres, 3)
    return T


def _marker_corners(centre: np.ndarray, normal_yaw: float, side: float = 0.13) -> np.ndarray:
    tangent = np.array([-math.sin(normal_yaw), math.cos(normal_yaw), 0.0])
    return np.array([centre + side / 2 * (a * tangent + b * np.array([0.0, 0.0, 1.0])) for a, b in ((-1, 1), (1, 1), (1, -1), (-1, -1))])


def _refine(T_prior: np.ndarray, X: np.ndarray, u: np.ndarray):
    return refine_camera_pose(T_prior, X, u, K, 0.3, CARVING.keyframe_rotation_sigma, CARVING.keyframe_position_sigma,
                              LOCALIZATION.max_reprojection_px)


def test_markers_spread_in_view_bring_a_kinematics_skewed_camera_back_to_the_truth():
    # 100 keyframes: a camera 0.5 m up aiming at an object 0.8 m ahead, three wall markers 1.6-2.4 m away
    # seen with 0.3 px noise; the prior (the fused pose) is off by 0.4 deg per axis and 8 mm per axis,
    # as walking kinematics leave it. The refined poses misplace the object's image 4x less.
    rng = np.random.default_rng(3)
    before, after = [], []
    for _ in range(100):
        truth = look_at((0.0, rng.uniform(-0.1, 0.1), 0.5), (0.8, 0.0, 0.06))
        X = np.vstack([_marker_corners(np.array([d, y, h]), math.pi) for d, y, h in
                       zip(rng.uniform(1.6, 2.4, 3), (-0.6, 0.05, 0.6), rng.uniform(0.25, 0.6, 3))])
        u = _project(truth, X) + rng.normal(0.0, 0.3, (len(X), 2))
        prior = _perturbed(truth, rng, 0.4, 0.008)
        refined = _refine(prior, X, u)
        assert refined is not None
        before.append(_object_error(prior, truth))
        after.append(_object_error(refined, truth))
    assert np.median(before) > 3.0
    assert np.median(after) < np.median(before) / 4


def test_one_far_marker_does_not_make_an_honest_prior_worse():
    # One 13 cm marker 2.5 m away cannot tell a sideways step from a turn that keeps it in place: along
    # that direction the prior holds the pose. With the prior off by what its std says (the config's),
    # the refined poses misplace the object's image less than the prior on the whole.
    rng = np.random.default_rng(4)
    before, after = [], []
    for _ in range(40):
        truth = look_at((0.0, 0.0, 0.5), (0.8, 0.0, 0.06))
        X = _marker_corners(np.array([2.5, rng.uniform(-0.5, 0.5), 0.4]), math.pi)
        u = _project(truth, X) + rng.normal(0.0, 0.3, (4, 2))
        prior = _perturbed(truth, rng, math.degrees(CARVING.keyframe_rotation_sigma), CARVING.keyframe_position_sigma)
        refined = _refine(prior, X, u)
        assert refined is not None
        before.append(_object_error(prior, truth))
        after.append(_object_error(refined, truth))
    assert np.mean(after) < np.mean(before)


def test_points_that_no_pose_explains_or_too_few_leave_the_pose_alone():
    truth = look_at((0.0, 0.0, 0.5), (0.8, 0.0, 0.06))
    X = np.vstack([_marker_corners(np.array([2.0, y, 0.4]), math.pi) for y in (-0.5, 0.5)])
    u = _project(truth, X)
    wrong = u.copy()
    wrong[:4] += 25.0  # one marker mis-associated: no camera pose reprojects it within the gate
    assert _refine(truth, X, wrong) is None
    assert _refine(truth, X[:2], u[:2]) is None
    assert _refine(truth, X, np.full_like(u, np.nan)) is None
    behind = truth.copy()
    behind[:3, :3] = truth[:3, :3] @ cv2.Rodrigues(np.array([0.0, math.pi, 0.0]))[0]  # turned away from the markers
    assert _refine(behind, X, u) is None


def test_rendered_frames_with_skewed_kinematics_get_the_true_camera_back():
    # Rendered VGA frames of the project's room; the camera pose from the true robot pose and a T_BC
    # off by 0.3 deg about each axis (torso sway and joint lag the kinematics missed) misplaces the
    # object's image by pixels; refined against the frame's landmark fix, by a third of that at most.
    robot = load_robot_model()
    camera = CameraModel.from_intrinsics(robot.camera.intrinsics("vga"))
    world = SimWorld("can", robot, "vga", seed=2)
    perception = load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")
    localizer = RobotLocalizer(LOCALIZATION, world.landmarks, camera, perception)
    ox, oy = world.scenario.position
    rng = np.random.default_rng(5)
    before, after = [], []
    for az in np.linspace(0.0, 2 * math.pi, 6, endpoint=False):
        d = rng.uniform(0.6, 0.9)
        pose = (ox + d * math.cos(az), oy + d * math.sin(az), wrap_angle(az + math.pi + rng.normal(0.0, 0.1)))
        world.teleport(pose, robot.look_at(pose, (ox, oy, 0.06)))
        frame = world.render()
        truth = np.array(world.truth()["camera"]["T_WC"])
        skew = cv2.Rodrigues(np.radians(rng.choice([-0.3, 0.3], 3)))[0]
        T_BC = frame.T_BC.copy()
        T_BC[:3, :3] = skew @ T_BC[:3, :3]
        fix = localizer.measure(frame.image, frame.T_BC, pose)
        assert fix is not None, localizer.no_fix_reason
        fused = camera_in_world(pose, T_BC)  # the right robot pose with the kinematics' error
        refined = refine_camera_pose(fused, *fix.inliers, camera.K, max(LOCALIZATION.pixel_sigma, fix.rms_px),
                                     CARVING.keyframe_rotation_sigma, CARVING.keyframe_position_sigma,
                                     LOCALIZATION.max_reprojection_px)
        assert refined is not None
        rim = OBJECT - [0.8, 0.0, 0.0] + [ox, oy, 0.0]
        before.append(np.mean(np.linalg.norm(_project(fused, rim) - _project(truth, rim), axis=1)))
        after.append(np.mean(np.linalg.norm(_project(refined, rim) - _project(truth, rim), axis=1)))
    assert np.median(before) > 2.0
    assert np.median(after) < np.median(before) / 3
