"""Landmark places refined with the keyframes' cameras (agent/map_refinement.py), on synthetic views of
the simulated room's ring of boards with its map measured off as a tape measures it."""

from __future__ import annotations

import math
from typing import List, Tuple

import cv2
import numpy as np

from agent.keyframe_pose import refine_camera_pose
from agent.map_refinement import KeyframeView, adjust
from nao_core.config import CONFIG_DIR
from nao_core.geometry import invert
from nao_core.landmark_map import Landmark, LandmarkMap, load_landmark_map
from nao_sim.layouts import measured
from tests.carving_scenes import look_at

K = np.array([[587.0, 0.0, 320.0], [0.0, 587.0, 240.0], [0.0, 0.0, 1.0]])
PIXEL_SIGMA = 0.3
ROTATION_SIGMA, POSITION_SIGMA = 0.004, 0.015  # the keyframes' priors: what a fused pose is worth
MAP_SIGMA, MAP_YAW_SIGMA = 0.005, math.radians(1.0)
OBJECT = np.array([[0.05 * math.cos(a), 0.05 * math.sin(a), z] for a in np.linspace(0.0, 2 * math.pi, 12, endpoint=False)
                   for z in (0.0, 0.12)])
RING = load_landmark_map(CONFIG_DIR / "landmarks" / "sim_room.yaml")


def _project(T_WC: np.ndarray, X: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    T = invert(T_WC)
    X_C = X @ T[:3, :3].T + T[:3, 3]
    return X_C[:, :2] / X_C[:, 2:3] * np.diag(K)[:2] + K[:2, 2], X_C[:, 2]


def _points(landmark: Landmark) -> np.ndarray:
    """A marker's four corners, or a ball's centre."""
    return landmark.aruco_corners() if landmark.kind == "aruco" else np.asarray(landmark.position, dtype=float)[None]


def _misalignment(T_WC: np.ndarray, truth: np.ndarray) -> float:
    """px: the object's largest image displacement between a camera pose and the true one."""
    return float(np.max(np.linalg.norm(_project(T_WC, OBJECT)[0] - _project(truth, OBJECT)[0], axis=1)))


def _rotated(T: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ cv2.Rodrigues(np.asarray(rotvec, dtype=float))[0]
    return out


def _walk(seed: int, truth: LandmarkMap = RING) -> Tuple[LandmarkMap, List[np.ndarray], List[KeyframeView]]:
    """A map measured off, the true cameras of 30 keyframes around the object (0.8 m, head aimed at it)
    and their views: the true corners' pixels with noise, the measured map's corners, a prior pose off."""
    rng = np.random.default_rng(seed)
    mapped = measured(truth, MAP_SIGMA, MAP_YAW_SIGMA, rng)
    cameras, views = [], []
    for k in range(30):
        a = 2 * math.pi * k / 30
        T = _rotated(look_at((0.8 * math.cos(a), 0.8 * math.sin(a), 0.5), (0.0, 0.0, 0.15)), rng.normal(0.0, 0.2) * np.array([0, 1.0, 0]))
        world, pixels, ids = [], [], []
        for true_lm, lm in zip(truth.landmarks, mapped.landmarks):
            uv, depth = _project(T, _points(true_lm))
            facing = lm.kind == "color" or np.dot(true_lm.normal[:2], T[:2, 3] - np.asarray(true_lm.position[:2])) > 0.0
            if facing and np.all(depth > 0.1) and np.all((uv > 2) & (uv < (638, 478))):
                world.append(_points(lm))
                pixels.append(uv + rng.normal(0.0, PIXEL_SIGMA, uv.shape))
                ids += [lm.id] * len(uv)
        prior = _rotated(T, rng.normal(0.0, ROTATION_SIGMA, 3))
        prior[:3, 3] += rng.normal(0.0, POSITION_SIGMA * 0.7, 3)
        cameras.append(T)
        views.append(KeyframeView(prior, np.vstack(world), np.vstack(pixels), tuple(ids), PIXEL_SIGMA, K))
    return mapped, cameras, views


def _each_refined(views: List[KeyframeView]) -> List[np.ndarray]:
    """Each keyframe refined alone against the measured map, its points weighed by the map's error at
    their depth (station/pilot.py): the poses before the adjustment."""
    poses = []
    for v in views:
        depth = float(np.median((v.world - v.T_WC[:3, 3]) @ v.T_WC[:3, 2]))
        sigma = math.hypot(PIXEL_SIGMA, K[0, 0] * MAP_SIGMA / depth)
        refined = refine_camera_pose(v.T_WC, v.world, v.pixels, K, sigma, ROTATION_SIGMA, POSITION_SIGMA, 50.0)
        poses.append(v.T_WC if refined is None else refined)
    return poses


def test_the_adjusted_keyframes_place_the_object_nearer_where_the_true_map_would():
    """Four walks, each with its own map error: the keyframes adjusted with the map misplace the object
    by about half what each refined alone does, and the landmarks move towards their true places."""
    alone, adjusted, exact, map_before, map_after = [], [], [], [], []
    for seed in range(4):
        mapped, cameras, views = _walk(seed)
        result = adjust(views, MAP_SIGMA, MAP_YAW_SIGMA, ROTATION_SIGMA, POSITION_SIGMA, 50.0)
        assert result is not None and all(T is not None for T in result.T_WC)
        alone += [_misalignment(T, truth) for T, truth in zip(_each_refined(views), cameras)]
        adjusted += [_misalignment(T, truth) for T, truth in zip(result.T_WC, cameras)]
        for true_lm, lm in zip(RING.landmarks, mapped.landmarks):
            if lm.id in result.displacement:
                d, psi = result.displacement[lm.id]
                map_before.append(np.subtract(true_lm.position, lm.position))
                map_after.append(np.subtract(true_lm.position, lm.position) - d)
        # the same walk with the exact map, each keyframe refined alone: what the adjustment aims at
        exact_views = [KeyframeView(v.T_WC, _exact(v), v.pixels, v.ids, v.pixel_sigma, K) for v in views]
        exact += [_misalignment(refine_camera_pose(v.T_WC, v.world, v.pixels, K, PIXEL_SIGMA, ROTATION_SIGMA, POSITION_SIGMA, 50.0),
                                truth) for v, truth in zip(exact_views, cameras)]
    assert np.median(adjusted) < 0.65 * np.median(alone), (np.median(adjusted), np.median(alone))
    assert np.median(adjusted) < 1.6 * np.median(exact), (np.median(adjusted), np.median(exact))
    before, after = np.array(map_before), np.array(map_after)
    after -= after.mean(axis=0)  # the map's overall shift is not seen by the images (module docstring)
    assert np.sqrt(np.mean(after ** 2)) < 0.6 * np.sqrt(np.mean(before ** 2))


def _exact(view: KeyframeView) -> np.ndarray:
    """The true corners of the landmarks a view's points belong to, in its point order."""
    true = {lm.id: _points(lm) for lm in RING.landmarks}
    ids = list(dict.fromkeys(view.ids))
    return np.vstack([true[i] for i in ids])


def test_an_exact_map_is_not_adjusted():
    _, _, views = _walk(0)
    assert adjust(views, 0.0, 0.0, ROTATION_SIGMA, POSITION_SIGMA, 50.0) is None


def test_a_view_that_cannot_be_used_is_left_out_and_a_misplaced_corner_pulls_no_further():
    """A view with a NaN pixel and one with a point behind its camera get no pose; one corner 40 px off
    (a misdetection the fit kept) leaves its keyframe as well placed as the clean walk's."""
    mapped, cameras, views = _walk(1)
    clean = adjust(views, MAP_SIGMA, MAP_YAW_SIGMA, ROTATION_SIGMA, POSITION_SIGMA, 50.0)
    nan_pixels = views[3].pixels.copy()
    nan_pixels[0, 0] = math.nan
    behind = views[5].world.copy()
    behind[0] = views[5].T_WC[:3, 3] - 0.5 * views[5].T_WC[:3, 2]
    outlier = views[8].pixels.copy()
    outlier[2] += (40.0, 0.0)
    hostile = list(views)
    hostile[3] = KeyframeView(views[3].T_WC, views[3].world, nan_pixels, views[3].ids, PIXEL_SIGMA, K)
    hostile[5] = KeyframeView(views[5].T_WC, behind, views[5].pixels, views[5].ids, PIXEL_SIGMA, K)
    hostile[8] = KeyframeView(views[8].T_WC, views[8].world, outlier, views[8].ids, PIXEL_SIGMA, K)
    result = adjust(hostile, MAP_SIGMA, MAP_YAW_SIGMA, ROTATION_SIGMA, POSITION_SIGMA, 50.0)
    assert result is not None and result.T_WC[3] is None and result.T_WC[5] is None
    assert math.isnan(result.rms_px[3]) and math.isnan(result.rms_px[5])
    assert _misalignment(result.T_WC[8], cameras[8]) < _misalignment(clean.T_WC[8], cameras[8]) + 1.0
    assert all(T is not None for k, T in enumerate(result.T_WC) if k not in (3, 5))


def test_a_landmark_seen_by_one_keyframe_stays_where_the_map_has_it():
    _, _, views = _walk(2)
    first = views[0].ids.count(views[0].ids[0])  # the points of the view's first landmark
    lone = KeyframeView(views[0].T_WC, views[0].world[:first], views[0].pixels[:first], ("lone",) * first, PIXEL_SIGMA, K)
    result = adjust(views + [lone], MAP_SIGMA, MAP_YAW_SIGMA, ROTATION_SIGMA, POSITION_SIGMA, 50.0)
    assert result is not None and "lone" not in result.displacement
    assert result.T_WC[-1] is not None
