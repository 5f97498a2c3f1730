"""Smoothed frame poses (agent/pose_smoother.py) against the true walk: synthetic odometry and fixes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.pose_smoother import TrackPoint, smooth_track
from nao_core.geometry import compose, relative, wrap_angle

K_T, K_R = 0.03, 0.03  # the filter's odometry noise (config/localization.yaml)
FIX_STD = (0.005, 0.004)  # m, rad


def walk(rng: np.random.Generator, seconds: float = 60.0, rate: float = 10.0):
    """A robot orbiting a point 0.6 m away at 0.1 m/s, standing 2 s every 8 s; its true poses, its
    odometry (reporting 95 % of the turn, a heading random walk of k_r) and a fix on every standing frame."""
    n = int(seconds * rate)
    true, odom = [(0.6, 0.0, math.pi / 2)], [(0.0, 0.0, 0.0)]
    standing = [True]
    for j in range(1, n):
        stand = (j / rate) % 8.0 < 2.0
        v = 0.0 if stand else 0.1 / rate
        w = v / 0.6
        true.append(compose(true[-1], (v, 0.0, w)))
        length = abs(v)
        noise = rng.normal(0.0, 1.0, 3) * [K_T * math.sqrt(length), K_T * math.sqrt(length), K_R * math.sqrt(length + abs(w))]
        odom.append(compose(odom[-1], (v + noise[0], noise[1], 0.95 * w + noise[2])))
        standing.append(stand)
    fixes = [tuple(np.array(p) + rng.normal(0.0, 1.0, 3) * [FIX_STD[0], FIX_STD[0], FIX_STD[1]]) if s else None
             for p, s in zip(true, standing)]
    return np.array(true), odom, fixes


def dead_reckoned(odom, fixes):
    """The filter's pose between fixes: the last fix carried forward by odometry."""
    poses, anchor = [], None
    for o, z in zip(odom, fixes):
        if z is not None:
            anchor = (z, o)
        poses.append(compose(anchor[0], relative(anchor[1], o)))
    return poses


def track_of(odom, fixes, poses, segment=0):
    R = np.diag([FIX_STD[0] ** 2, FIX_STD[0] ** 2, FIX_STD[1] ** 2])
    return [TrackPoint(float(j), o, p, segment, z, None if z is None else R) for j, (o, z, p) in enumerate(zip(odom, fixes, poses))]


def heading_errors(poses, true) -> np.ndarray:
    return np.abs([wrap_angle(p[2] - t[2]) for p, t in zip(poses, true)])


def test_smoothing_cuts_the_error_between_fixes():
    """Between fixes the filter's heading error grows like a random walk's, sigma sqrt(t); the smoother's
    is a Brownian bridge's, sigma sqrt(t (T - t) / T): over an interval their means are 2/3 and pi/8
    of sigma sqrt(T), a ratio of 0.59. Pooled over five walks, the medians must show it."""
    before, after, position_before, position_after, at_fixes = [], [], [], [], []
    for seed in range(5):
        true, odom, fixes = walk(np.random.default_rng(seed))
        filtered = dead_reckoned(odom, fixes)
        smoothed = smooth_track(track_of(odom, fixes, filtered), (1.0, 1.0, 1 / 0.95), K_T, K_R)
        walking = np.array([z is None for z in fixes])
        before += list(heading_errors(filtered, true)[walking])
        after += list(heading_errors(smoothed, true)[walking])
        position_before += list(np.hypot(*(np.array(filtered)[:, :2] - true[:, :2]).T)[walking])
        position_after += list(np.hypot(*(smoothed[:, :2] - true[:, :2]).T)[walking])
        at_fixes += list(heading_errors(smoothed, true)[~walking])
    assert np.median(after) < 0.65 * np.median(before), (np.median(before), np.median(after))
    assert np.median(position_after) < 0.75 * np.median(position_before), (np.median(position_before), np.median(position_after))
    assert np.percentile(at_fixes, 95) < 3.0 * FIX_STD[1]  # where the fixes are, the smoothed poses stay within their noise


def test_a_wrong_fix_moves_its_neighbours_little():
    true, odom, fixes = walk(np.random.default_rng(3))
    clean = smooth_track(track_of(odom, fixes, dead_reckoned(odom, fixes)), (1.0, 1.0, 1.0), K_T, K_R)
    standing = [j for j, z in enumerate(fixes) if z is not None]
    bad = standing[len(standing) // 2]
    fixes[bad] = (fixes[bad][0] + 0.5, fixes[bad][1], fixes[bad][2] + 0.3)  # a wrong association that passed the gate
    smoothed = smooth_track(track_of(odom, fixes, dead_reckoned(odom, fixes)), (1.0, 1.0, 1.0), K_T, K_R)
    others = np.ones(len(fixes), dtype=bool)
    others[bad] = False
    shift = np.hypot(*(smoothed[others, :2] - clean[others, :2]).T)
    assert np.max(shift) < 0.03, np.max(shift)  # it would drag a quadratic cost's neighbours by decimetres


def test_segments_are_smoothed_apart_and_one_without_a_fix_keeps_its_poses():
    true, odom, fixes = walk(np.random.default_rng(4), seconds=20.0)
    filtered = dead_reckoned(odom, fixes)
    half = len(odom) // 2
    first = track_of(odom[:half], fixes[:half], filtered[:half], segment=0)
    second = track_of(odom[half:], [None] * (len(odom) - half), filtered[half:], segment=1)  # after a reset: no fix yet
    smoothed = smooth_track(first + second, (1.0, 1.0, 1.0), K_T, K_R)
    np.testing.assert_array_equal(smoothed[half:], np.array(filtered[half:]))
    alone = smooth_track(first, (1.0, 1.0, 1.0), K_T, K_R)
    np.testing.assert_allclose(smoothed[:half], alone)

