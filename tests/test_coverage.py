"""Coverage bins on the cylinder against hand-worked geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.coverage import Coverage, CoverageParams, bin_angles, bins_seen, seen_count
from nao_core.geometry import wrap_angle

UNIT = np.array([0.0, 0.0, 0.1])  # object at the origin, radius 10 cm
WIDE = CoverageParams(bins=4, facing_angle=math.radians(60), distance_range=(0.2, 3.0))


def test_bin_angles_are_centred_in_equal_sectors():
    np.testing.assert_allclose(np.degrees(bin_angles(4)), [45, 135, 225, 315])


def test_camera_on_the_x_axis_sees_the_two_bins_facing_it():
    # Bin at 45 deg: q = (0.0707, 0.0707); camera at (1, 0): c - q = (0.9293, -0.0707), |c - q| = 0.9320,
    # n . (c - q) = 0.7071 (0.9293 - 0.0707) = 0.6071 -> angle acos(0.6071 / 0.9320) = 49.3 deg.
    cam = np.array([1.0, 0.0, math.pi])
    np.testing.assert_array_equal(bins_seen(UNIT, cam, WIDE, hfov=1.0), [True, False, False, True])
    narrow = CoverageParams(bins=4, facing_angle=math.radians(49.0), distance_range=(0.2, 3.0))
    np.testing.assert_array_equal(bins_seen(UNIT, cam, narrow, hfov=1.0), [False] * 4)
    just = CoverageParams(bins=4, facing_angle=math.radians(49.5), distance_range=(0.2, 3.0))
    np.testing.assert_array_equal(bins_seen(UNIT, cam, just, hfov=1.0), [True, False, False, True])


def test_field_of_view_and_range_gate_the_bins():
    # The bins at +-45 deg are 0.076 rad off the optical axis when the camera looks at the centre.
    assert not bins_seen(UNIT, np.array([1.0, 0.0, 0.0]), WIDE, hfov=1.0).any()  # looking away
    assert not bins_seen(UNIT, np.array([1.0, 0.0, math.pi]), WIDE, hfov=0.15).any()  # 0.075 < 0.076
    assert bins_seen(UNIT, np.array([1.0, 0.0, math.pi]), WIDE, hfov=0.16).sum() == 2
    assert not bins_seen(UNIT, np.array([3.5, 0.0, math.pi]), WIDE, hfov=1.0).any()  # beyond d_hi
    assert not bins_seen(UNIT, np.array([0.25, 0.0, math.pi]), WIDE, hfov=3.0).any()  # q closer than d_lo


def test_far_camera_sees_the_bins_within_the_facing_angle():
    # From far away c - q is parallel to the x axis: bin i is seen iff |a_i| <= 60 deg: 6 bins each side.
    params = CoverageParams(bins=36, facing_angle=math.radians(60), distance_range=(0.0, 1e4))
    seen = bins_seen(UNIT, np.array([1000.0, 0.0, math.pi]), params, hfov=1.0)
    np.testing.assert_array_equal(seen, np.abs(np.degrees(wrap_angle(bin_angles(36)))) <= 60)
    assert seen.sum() == 12


def test_bins_move_with_the_estimate():
    cam = np.array([1.0, 0.0, math.pi])
    shifted = np.array([0.0, 5.0, 0.1])  # object moved out of sight and out of range
    assert bins_seen(UNIT, cam, WIDE, 1.0).any() and not bins_seen(shifted, cam, WIDE, 1.0).any()


def test_seen_count_is_the_union_over_the_sequence_and_the_past_vectorized():
    params = CoverageParams(bins=36, facing_angle=math.radians(60), distance_range=(0.0, 1e4))
    east, west = np.array([1000.0, 0.0, math.pi]), np.array([-1000.0, 0.0, 0.0])
    cams = np.stack([np.stack([east, east]), np.stack([east, west])])  # (K=2, D=2, 3)
    none = np.zeros(36, dtype=bool)
    np.testing.assert_array_equal(seen_count(UNIT, cams, none, params, 1.0), [12, 24])
    north = np.zeros(36, dtype=bool)
    north[9] = True  # the bin at 95 deg, seen by neither camera
    np.testing.assert_array_equal(seen_count(UNIT, cams, north, params, 1.0), [13, 25])


def test_coverage_accumulates_the_executed_path():
    params = CoverageParams(bins=36, facing_angle=math.radians(60), distance_range=(0.0, 1e4))
    cov = Coverage(params, hfov=1.0)
    assert cov.fraction(UNIT) == 0.0 and cov.cameras.shape == (0, 3)
    for azimuth in np.radians([0, 120, 240]):
        cov.add(1000.0 * np.array([math.cos(azimuth), math.sin(azimuth), 0.0]) + [0, 0, azimuth + math.pi])
    assert cov.fraction(UNIT) == 1.0


def test_coverage_rejects_bad_input():
    cov = Coverage(WIDE, hfov=1.0)
    with pytest.raises(ValueError, match="finite"):
        cov.add([0.0, float("nan"), 0.0])
    with pytest.raises(ValueError, match="distance_range"):
        CoverageParams(bins=4, facing_angle=1.0, distance_range=(2.0, 1.0))


def test_termination_margin_drops_bins_seen_only_at_the_facing_limit():
    cov = Coverage(WIDE, hfov=1.0)
    cov.add([1.0, 0.0, math.pi])  # the +-45 deg bins are seen at 49.3 deg from their normals
    assert cov.fraction(UNIT) == 0.5
    assert cov.fraction(UNIT, margin=math.radians(10.0)) == 0.5  # 50 deg limit: still seen
    assert cov.fraction(UNIT, margin=math.radians(11.0)) == 0.0  # 49 deg limit: not any more
