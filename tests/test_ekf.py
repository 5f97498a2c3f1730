"""Object EKF against ground truth: Jacobians, image geometry, Monte-Carlo consistency, accuracy,
gating, observability, the planner's batched rollout, bad inputs and the paper's width slip."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from agent.camera import CameraModel, optical_axis_heading
from agent.ekf import (
    NOMINAL_R,
    FloorContact,
    ObjectEKF,
    floor_depression,
    load_ekf_params,
    measure,
    measurement_jacobian,
    pose_noise,
    position_std,
    rollout_covariance,
)
from nao_core.config import ConfigError
from nao_core.geometry import camera_in_world, wrap_angle
from nao_core.robot_model import load_robot_model
from tests.tangents import bearing_width_from_pixels
from tools.demo_estimation import PoseDrift, circling_cameras, circling_runs, first_views, simulate

PARAMS = load_ekf_params()
coord = st.floats(-3.0, 3.0)





def numeric_jacobian(x: np.ndarray, cam: np.ndarray, model: str, eps: float = 1e-6) -> np.ndarray:
    H = np.zeros((2, 3))
    for i in range(3):
        step = np.zeros(3)
        step[i] = eps
        hi, lo = measure(x + step, cam, model), measure(x - step, cam, model)
        H[0, i] = wrap_angle(hi[0] - lo[0]) / (2 * eps)
        H[1, i] = (hi[1] - lo[1]) / (2 * eps)
    return H


@settings(max_examples=200, deadline=None)
@given(coord, coord, st.floats(0.01, 0.5), coord, coord, st.floats(-math.pi, math.pi), st.sampled_from(["asin", "paper_atan"]))
def test_jacobian_equals_finite_differences(xo, yo, r, cx, cy, psi, model):
    x, cam = np.array([xo, yo, r]), np.array([cx, cy, psi])
    assume(math.hypot(xo - cx, yo - cy) > 1.2 * r + 0.05)  # away from the tangent singularity d = r
    np.testing.assert_allclose(measurement_jacobian(x, cam, model), numeric_jacobian(x, cam, model), rtol=1e-5, atol=1e-6)


def test_vectorized_functions_match_single_calls():
    rng = np.random.default_rng(3)
    x = np.array([0.3, -0.2, 0.1])
    cams = np.concatenate([rng.uniform(-2, 2, (4, 5, 2)), rng.uniform(-3, 3, (4, 5, 1))], axis=-1)
    z, H = measure(x, cams), measurement_jacobian(x, cams)
    assert z.shape == (4, 5, 2) and H.shape == (4, 5, 2, 3)
    for idx in np.ndindex(4, 5):
        np.testing.assert_allclose(z[idx], measure(x, cams[idx]))
        np.testing.assert_allclose(H[idx], measurement_jacobian(x, cams[idx]))


@pytest.mark.parametrize("dist", [np.zeros(5), np.array([-0.08, 0.02, 0.0, 0.0, 0.0])])
@pytest.mark.parametrize("yaw, pitch", [(0.0, 0.0), (0.4, 0.35), (-0.6, -0.3)])
def test_bearing_and_width_from_image_equal_analytic(dist, yaw, pitch):
    """Tangent points of a vertical cylinder, projected by a pitched camera, give exactly (phi, delta)."""
    robot = load_robot_model()
    intr = robot.camera.intrinsics("vga")
    camera = CameraModel(intr.K, dist, intr.width, intr.height)
    T_WC = camera_in_world((0.3, -0.2, 0.5), robot.camera_in_robot(yaw, pitch))
    cam = np.array([T_WC[0, 3], T_WC[1, 3], optical_axis_heading(T_WC)])
    # Object 1.3 m ahead along the optical-axis heading, slightly off-centre.
    aim = cam[2] + 0.12
    x = np.array([cam[0] + 1.3 * math.cos(aim), cam[1] + 1.3 * math.sin(aim), 0.09])
    d = math.hypot(x[0] - cam[0], x[1] - cam[1])
    alpha, leg = math.asin(x[2] / d), math.sqrt(d * d - x[2] ** 2)
    centre_az = math.atan2(x[1] - cam[1], x[0] - cam[0])
    # Tangent points at different heights: the azimuths do not depend on the height.
    heights = np.linspace(0.05, 0.45, 9)
    left = [[cam[0] + leg * math.cos(centre_az + alpha), cam[1] + leg * math.sin(centre_az + alpha), h] for h in heights]
    right = [[cam[0] + leg * math.cos(centre_az - alpha), cam[1] + leg * math.sin(centre_az - alpha), h] for h in heights]
    uv_l, front_l = camera.project_world(np.array(left), T_WC)
    uv_r, front_r = camera.project_world(np.array(right), T_WC)
    inside = lambda uv: (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)
    ok = front_l & front_r & inside(uv_l) & inside(uv_r)
    assert ok.sum() >= 2, "the test geometry must put tangent points in the image"
    expected = measure(x, cam)
    for i in np.flatnonzero(ok):
        _, phi, delta = bearing_width_from_pixels(camera, uv_l[i], uv_r[i][None], T_WC)
        assert abs(math.degrees(wrap_angle(phi - expected[0]))) < 0.01
        assert abs(math.degrees(delta - expected[1])) < 0.01


def test_monte_carlo_nees_and_nis_inside_chi_square_bands():
    """Model matched to the truth (radius drawn from the prior, static object): the filter is consistent."""
    params = dataclasses.replace(PARAMS, radius_prior_std=0.02, process_noise=(0.0, 0.0, 0.0))
    runs = 150
    traces = circling_runs(params, runs, 60, seed=11, radius_std=0.02)
    nees = np.array([t.nees for t in traces])  # (runs, views)
    nis = np.array([t.nis[1:] for t in traces])
    lo3, hi3 = chi2.ppf([0.025, 0.975], 3 * runs) / runs
    lo2, hi2 = chi2.ppf([0.025, 0.975], 2 * runs) / runs
    mean_nees, mean_nis = nees.mean(axis=0), nis.mean(axis=0)
    assert lo3 < mean_nees.mean() < hi3, mean_nees.mean()
    assert lo2 < mean_nis.mean() < hi2, mean_nis.mean()
    # Per view, the run-averaged NEES/NIS fall in their 95 % bands about as often as they should.
    assert np.mean((lo3 < mean_nees) & (mean_nees < hi3)) > 0.85
    assert np.mean((lo2 < mean_nis) & (mean_nis < hi2)) > 0.85


def test_one_circle_at_half_a_metre_is_accurate():
    traces = circling_runs(PARAMS, 60, 72, seed=5)
    err = np.array([t.x[-1] - t.truth for t in traces])
    assert np.median(np.hypot(err[:, 0], err[:, 1])) < 0.01
    assert np.median(np.abs(err[:, 2])) < 0.002
    assert all(t.accepted[1:].mean() > 0.95 for t in traces)


def test_gross_outliers_are_gated_and_the_estimate_stays_unbiased():
    traces = circling_runs(PARAMS, 60, 72, seed=8, outliers=0.10)
    outlier = np.concatenate([t.outlier[1:] for t in traces])
    accepted = np.concatenate([t.accepted[1:] for t in traces])
    assert 0.07 < outlier.mean() < 0.13
    assert np.mean(~accepted[outlier]) > 0.95  # outliers rejected
    assert np.mean(accepted[~outlier]) > 0.98  # inliers kept
    err = np.array([t.x[-1] - t.truth for t in traces])
    assert np.median(np.hypot(err[:, 0], err[:, 1])) < 0.01
    assert np.median(np.abs(err[:, 2])) < 0.002
    sem = err.std(axis=0) / math.sqrt(len(err))
    assert np.all(np.abs(err.mean(axis=0)) < 4 * sem + 1e-4), (err.mean(axis=0), sem)


def test_bearing_only_radial_motion_keeps_the_range_uncertain():
    truth = np.array([2.0, 0.0, 0.1])
    ekf = ObjectEKF(PARAMS)
    ekf.initialize((0.0, 0.0, 0.0), 0.0)
    range_sigma0 = math.sqrt(ekf.P[0, 0])
    assert range_sigma0 == pytest.approx(PARAMS.default_range_std)
    for cx in np.linspace(0.05, 1.0, 20):  # walk straight at the object
        cam = np.array([cx, 0.0, 0.0])
        ekf.predict(0.1)
        assert ekf.update(cam, measure(truth, cam)[0]).accepted
    assert math.sqrt(ekf.P[0, 0]) >= range_sigma0  # no information on the range: no false confidence
    assert abs(ekf.x[0] - truth[0]) < 3 * math.sqrt(ekf.P[0, 0])
    assert math.sqrt(ekf.P[1, 1]) < 0.01  # the lateral position is observed

    sideways = ObjectEKF(PARAMS)  # the same bearings from a lateral baseline do fix the range
    sideways.initialize((0.0, 0.0, 0.0), 0.0)
    for cy in np.linspace(0.05, 1.0, 20):
        cam = np.array([0.0, cy, 0.0])
        sideways.predict(0.1)
        sideways.update(cam, measure(truth, cam)[0])
    assert math.sqrt(sideways.P[0, 0]) < 0.1 * range_sigma0
    assert abs(sideways.x[0] - truth[0]) < 0.05


@settings(max_examples=100, deadline=None)
@given(coord, coord, st.floats(0.02, 0.3), coord, coord, st.floats(-math.pi, math.pi), st.floats(0.3, 0.7))
def test_floor_depression_jacobian_equals_finite_differences(xo, yo, r, cx, cy, psi, height):
    x, cam = np.array([xo, yo, r]), np.array([cx, cy, psi])
    assume(math.hypot(xo - r * math.cos(psi) - cx, yo - r * math.sin(psi) - cy) > 0.05)
    _, analytic = floor_depression(x, cam, height)
    numeric = [(floor_depression(x + e, cam, height)[0] - floor_depression(x - e, cam, height)[0]) / 2e-6 for e in np.eye(3) * 1e-6]
    np.testing.assert_allclose(analytic, numeric, atol=1e-6)


def floored_starts(params, views):
    """Each first view's start with its floor contact: its NEES and its centre error over the range."""
    nees, errors = [], []
    for view in views:
        ekf = ObjectEKF(params)
        assert ekf.initialize(view.cam, view.phi, view.delta, view.floor).accepted
        err = ekf.x - view.truth
        nees.append(err @ np.linalg.solve(ekf.P, err))
        errors.append(math.hypot(*err[:2]) / math.hypot(*view.truth[:2]))
    return np.array(nees), np.array(errors)


def test_a_floor_contact_starts_the_range_consistently():
    """Monte Carlo, the model matched to the truth (radius drawn from the prior, a cylinder: no shape
    term): a first view with its floor contact (phi, delta, depression with their noise) starts the
    filter at the right range with a covariance that says so (NEES in its chi-square band), where
    the radius prior alone leaves the range as uncertain as the radius."""
    params = dataclasses.replace(PARAMS, radius_prior_std=0.02, floor_shape_std=0.0)  # 5 sigma from r = 0
    views = first_views(params, 400, seed=7)
    nees, errors = floored_starts(params, views)
    unfloored = []
    for view in views:
        bare = ObjectEKF(params)
        bare.initialize(view.cam, view.phi, view.delta)
        unfloored.append(math.sqrt(np.linalg.eigvalsh(bare.P[:2, :2])[-1]) / math.hypot(*view.truth[:2]))
    lo, hi = chi2.ppf([0.025, 0.975], 3 * len(views)) / len(views)
    assert lo < np.mean(nees) < hi, np.mean(nees)
    assert np.median(errors) < 0.08  # measured 4.2 %: floor_angle_std (1.4 deg) is 5 % of the range at 0.6 m, 11 % at 2 m
    assert np.median(unfloored) > 0.15  # without it: the radius prior's 20 %


def test_a_thin_object_starts_from_its_floor_contact_where_the_radius_prior_would_put_it_metres_off():
    """A radius of 1.2-2.5 cm (a pen, a thin bottle) lies in the tail of the prior's inverse range
    (rho = s / r0, 100 % std): its contact fails the gate against that start, and the start is made
    from the width and the contact, the prior fused after them (agent/ekf.py ``_floor_start``). The
    centre within 8 % of the range (median; measured 4.4 %, 453 % from the prior's start), never
    metres off, with a covariance that does not claim more than it has (NEES not above its band)."""
    views = first_views(PARAMS, 400, seed=11, radii=(0.012, 0.025), ranges=(0.6, 1.6))
    nees, errors = floored_starts(PARAMS, views)
    assert np.median(errors) < 0.08 and max(errors) < 0.6, (np.median(errors), max(errors))
    assert np.mean(nees) < chi2.ppf(0.975, 3 * len(views)) / len(views), np.mean(nees)


def test_initial_covariance_is_the_propagated_measurement_and_prior_noise():
    """Sampling (phi, delta, r0) and mapping them through the initializer reproduces P0."""
    rng = np.random.default_rng(2)
    cam, phi, delta = np.array([0.2, 0.1, 0.4]), 0.1, 0.2
    params = dataclasses.replace(PARAMS, radius_prior_std=0.01)  # keep the map close to linear
    ekf = ObjectEKF(params)
    ekf.initialize(cam, phi, delta)
    samples = []
    for _ in range(4000):
        other = ObjectEKF(dataclasses.replace(params, radius_prior=params.radius_prior + params.radius_prior_std * rng.standard_normal()))
        other.initialize(cam, phi + params.sigma_phi * rng.standard_normal(), delta + params.sigma_delta * rng.standard_normal())
        samples.append(other.x)
    np.testing.assert_allclose(np.cov(np.array(samples).T), ekf.P, rtol=0.1, atol=1e-7)


def test_rollout_equals_a_loop_of_filter_updates():
    rng = np.random.default_rng(4)
    ekf = ObjectEKF(PARAMS)
    ekf.initialize((0.0, 0.0, 0.0), 0.05, 0.15)
    K, D, dt = 6, 8, 0.2
    ang = rng.uniform(-math.pi, math.pi, (K, D))
    rad = rng.uniform(0.4, 1.5, (K, D))
    cams = np.stack([ekf.x[0] + rad * np.cos(ang), ekf.x[1] + rad * np.sin(ang), ang + math.pi + rng.uniform(-0.3, 0.3, (K, D))], -1)
    cams[0, 3, :2] = ekf.x[:2]  # a camera inside the object is skipped, as the filter rejects it
    visible = rng.random((K, D)) < 0.7
    batched = rollout_covariance(ekf.x, ekf.P, cams, visible, PARAMS.Q(dt), R=PARAMS.R)
    assert batched.shape == (K, 3, 3)
    for k in range(K):
        f = ekf.copy()
        for j in range(D):
            f.predict(dt)
            if visible[k, j]:
                f.update(cams[k, j], *measure(f.x, cams[k, j]))
        np.testing.assert_allclose(f.x, ekf.x)  # noise-free synthesized measurements: the mean stays
        np.testing.assert_allclose(batched[k], f.P, rtol=1e-6, atol=1e-12)
    per_candidate = rollout_covariance(ekf.x, np.broadcast_to(ekf.P, (K, 3, 3)), cams, visible, PARAMS.Q(dt), R=PARAMS.R)
    np.testing.assert_allclose(per_candidate, batched)
    nothing_seen = rollout_covariance(ekf.x, ekf.P, cams, np.zeros((K, D), bool), PARAMS.Q(dt))
    np.testing.assert_allclose(nothing_seen, np.broadcast_to(ekf.P + D * PARAMS.Q(dt), (K, 3, 3)))


@pytest.mark.parametrize(
    "cam, phi, delta, reason",
    [
        ((0.0, 0.0, 0.0), float("nan"), 0.2, "bearing must be a finite number"),
        ((0.0, 0.0, 0.0), 0.1, float("nan"), "width must be finite"),
        ((0.0, 0.0, 0.0), None, 0.2, "bearing must be a finite number"),
        ((0.0, 0.0, 0.0), 0.1, "wide", "width must be finite"),
        ((0.0, 0.0, 0.0), 0.1, -0.2, "width must be finite and in (0"),
        ((0.0, float("inf"), 0.0), 0.1, 0.2, "camera pose must be 3 finite numbers"),
        ((0.0, 0.0), 0.1, 0.2, "camera pose must be 3 finite numbers"),
        (("a", "b", "c"), 0.1, 0.2, "camera pose must be 3 finite numbers"),
        ((1.0, 0.0, 0.0), 0.1, 0.2, "camera inside the estimated object"),
    ],
)
def test_bad_inputs_are_rejected_with_a_reason_and_change_nothing(cam, phi, delta, reason):
    ekf = ObjectEKF(PARAMS)
    ekf.initialize((0.0, 0.0, 0.0), 0.0, 2 * math.asin(0.1 / 1.0))  # x = (1, 0, 0.1)
    before = ekf.copy()
    result = ekf.update(cam, phi, delta)
    assert not result.accepted and reason in result.reason and result.nis is None
    np.testing.assert_array_equal(ekf.x, before.x)
    np.testing.assert_array_equal(ekf.P, before.P)
    assert ekf.stats.invalid == 1


def test_uninitialized_filter_and_bad_first_observation_are_rejected():
    ekf = ObjectEKF(PARAMS)
    assert ekf.update((0.0, 0.0, 0.0), 0.1, 0.2).reason == "filter not initialized"
    result = ekf.initialize((0.0, 0.0, 0.0), float("nan"), 0.2)
    assert not result.accepted and "bearing" in result.reason and not ekf.initialized
    with pytest.raises(ValueError, match="dt"):
        ekf.predict(-0.1)
    for floor in (FloorContact(float("nan"), 0.5), FloorContact(-0.1, 0.5), FloorContact(0.4, 0.0), (0.4, 0.5)):
        result = ekf.initialize((0.0, 0.0, 0.0), 0.1, 0.2, floor)
        assert not result.accepted and "floor contact" in result.reason and not ekf.initialized


def test_bearing_innovation_is_wrapped_across_pi():
    """Object behind the optical axis: measured pi - e against predicted -pi + e is a -2e innovation."""
    ekf = ObjectEKF(PARAMS)
    ekf.initialize((0.0, 0.0, 0.0), -math.pi + 0.02, 2 * math.asin(0.1 / 1.0))  # estimate near (-1, -0.02)
    cam = np.array([0.0, -0.01, 0.0])
    predicted = measure(ekf.x, cam)[0]
    truth = np.array([-1.0, 0.0, 0.1])
    phi, delta = measure(truth, cam)
    assert predicted < -3.1 and phi > 3.1  # on both sides of the cut
    before = ekf.x.copy()
    result = ekf.update(cam, phi, delta)
    assert result.accepted and result.innovation[0] == pytest.approx(wrap_angle(phi - predicted)) and abs(result.innovation[0]) < 0.05
    # the bearing moves towards the truth (prior and view weigh the same); a 1 cm baseline leaves the range
    assert abs(ekf.x[1] - truth[1]) < 0.75 * abs(before[1] - truth[1])
    assert math.hypot(*ekf.x[:2]) == pytest.approx(math.hypot(*before[:2]), abs=1e-3)


def test_gate_counts_rejections():
    ekf = ObjectEKF(PARAMS)
    ekf.initialize((0.0, 0.0, 0.0), 0.0, 2 * math.asin(0.1 / 1.0))
    result = ekf.update((0.0, 0.0, 0.0), math.radians(10.0), 2 * math.asin(0.1 / 1.0))
    assert not result.accepted and result.nis > ekf.gate(2) and ekf.stats.gated == 1
    assert ekf.snapshot()["stats"] == {"accepted": 1, "gated": 1, "invalid": 0, "rejected_in_a_row": 1, "width_gated": 0, "reinitialized": 0}


def test_a_lost_estimate_restarts_from_the_view_after_consecutive_gated_views():
    """A wrong first view (bearing off by 0.5 rad) makes the true views inconsistent; after
    ``reinitialize_after`` of them in a row the filter restarts from the current view, says why,
    counts it, and then converges on the true object."""
    truth = np.array([1.0, 0.0, 0.08])
    cams = circling_cameras(truth[:2], 0.6, 40, start=math.pi)
    ekf = ObjectEKF(PARAMS)
    ekf.initialize(cams[0], *(measure(truth, cams[0]) + [0.5, 0.0]))
    results = [ekf.update(cam, *measure(truth, cam)) for cam in cams[1:]]
    restarts = [k for k, r in enumerate(results) if r.reason.startswith("re-initialized after")]
    assert len(restarts) == 1 and ekf.stats.reinitialized == 1
    k = restarts[0]
    assert not any(r.accepted for r in results[k - PARAMS.reinitialize_after + 1 : k])
    assert all(r.accepted and r.reason == "ok" for r in results[k + 1 :])
    np.testing.assert_allclose(ekf.x, truth, atol=1e-3)


def test_five_bad_views_do_not_erase_an_estimate_built_from_hundreds():
    """Issue 12: 300 views of the object, then views of a phantom 2 m away (a cut silhouette read as
    a far object) that agree with each other. Five, or any streak shorter than
    reinitialize_fraction x 300, leave the estimate untouched; a longer one (the object really
    moved) restarts it from the phantom's views."""
    truth, phantom = np.array([1.0, 0.0, 0.05]), np.array([3.0, 1.5, 0.05])
    cams = circling_cameras(truth[:2], 0.6, 300)
    ekf = ObjectEKF(PARAMS)
    z = measure(truth, cams)
    ekf.initialize(cams[0], *z[0])
    assert all(ekf.update(cam, *obs).accepted for cam, obs in zip(cams[1:], z[1:]))
    built = ekf.copy()
    needed = ekf.restart_views
    assert needed == math.ceil(PARAMS.reinitialize_fraction * 300) > 5  # proportionate to the 300 views fused
    bad_cams = circling_cameras(truth[:2], 0.6, needed, start=1.0)
    bad = [ekf.update(cam, *measure(phantom, cam)) for cam in bad_cams[:needed - 1]]
    assert not any(r.accepted for r in bad) and ekf.stats.reinitialized == 0
    np.testing.assert_array_equal(ekf.x, built.x)
    assert ekf.update(cams[7], *z[7]).accepted  # a good view ends the streak and drops the alternative
    assert ekf.restart_views == math.ceil(PARAMS.reinitialize_fraction * 301)
    for cam in circling_cameras(truth[:2], 0.6, ekf.restart_views, start=1.0):
        result = ekf.update(cam, *measure(phantom, cam))
    assert result.accepted and result.reason.startswith("re-initialized after") and ekf.stats.reinitialized == 1
    assert np.hypot(*(ekf.x[:2] - phantom[:2])) < np.hypot(*(built.x[:2] - phantom[:2]))  # now on the phantom's side


def test_views_without_parallax_never_restart_however_many():
    """Issue 12 (matrix seed 27): the robot turning in place sees something else, consistently.
    From one spot its views fix a bearing, not a range, so the alternative they build is not
    located and never replaces the estimate; the same views from a walk restart it."""
    truth, phantom = np.array([1.0, 0.0, 0.05]), np.array([0.2, 1.2, 0.05])
    ekf = ObjectEKF(PARAMS)
    cams = circling_cameras(truth[:2], 0.6, 20)
    ekf.initialize(cams[0], *measure(truth, cams[0]))
    assert all(ekf.update(cam, *measure(truth, cam)).accepted for cam in cams[1:])
    built = ekf.copy()
    spot = cams[-1][:2]
    turning = [np.array([*spot, psi]) for psi in np.linspace(1.2, 1.8, 40)]  # phantom in view, head still
    for cam in turning:
        ekf.update(cam, *measure(phantom, cam))
    assert ekf.stats.gated == 40 and ekf.stats.reinitialized == 0
    np.testing.assert_array_equal(ekf.x, built.x)
    walk = [np.array([spot[0] + 0.02 * k, spot[1], 1.5]) for k in range(40)]  # 0.8 m sideways
    results = [ekf.update(cam, *measure(phantom, cam)) for cam in walk]
    assert ekf.stats.reinitialized == 1 and any(r.reason.startswith("re-initialized after") for r in results)
    np.testing.assert_allclose(ekf.x[:2], phantom[:2], atol=0.02)


def test_inconsistent_views_that_disagree_with_each_other_never_restart():
    """Random gross outliers (no consistent alternative) never replace an estimate, however many."""
    truth = np.array([1.0, 0.0, 0.05])
    cams = circling_cameras(truth[:2], 0.6, 40)
    ekf = ObjectEKF(PARAMS)
    z = measure(truth, cams)
    ekf.initialize(cams[0], *z[0])
    for cam, obs in zip(cams[1:], z[1:]):
        ekf.update(cam, *obs)
    rng = np.random.default_rng(1)
    for cam in circling_cameras(truth[:2], 0.6, 60):
        ekf.update(cam, rng.uniform(-0.5, 0.5), rng.uniform(0.05, 0.4))
    assert ekf.stats.reinitialized == 0
    np.testing.assert_allclose(ekf.x, truth, atol=2e-3)


@pytest.mark.parametrize("name", ["can", "remote", "figure", "mug"])
def test_objects_that_are_not_cylinders_keep_a_consistent_centre(name, robot):
    """Issue 13: rendered frames of a box, a figure and a mug (and the can) from 48 views around a
    0.8 m ring, measured by perception: the centre stays within 1.5 cm (issue 12's target for other
    shapes) of the footprint's centroid (convex hull of the object on the floor), its error is
    inside the 99.7 % ellipse of P (2-dof NEES), and the width variability c2 is learned for the
    non-cylinders (so their widths are fused, not gated) while the can keeps c2 = 0."""
    from agent.perception import PerceptionParams, extract_silhouette, measure_object
    from nao_core.config import CONFIG_DIR, load
    from nao_core.geometry import planar_transform
    from nao_sim.world import SimWorld

    try:
        world = SimWorld(name, robot, "vga", seed=2)
    except KeyError as exc:  # the mug arrives with the simulator engineer's scenarios
        pytest.skip(str(exc))
    perception = load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")
    camera = CameraModel.from_intrinsics(robot.camera.intrinsics("vga"))
    scenario = world.scenario
    hull = cv2.convexHull(scenario.world_points()[:, :2].astype(np.float32))
    m = cv2.moments(hull)
    centroid = np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])
    ekf = ObjectEKF(PARAMS)
    rng = np.random.default_rng(0)
    for k, a in enumerate(np.linspace(0.0, 2.0 * math.pi, 48, endpoint=False)):
        pose = (scenario.position[0] + 0.8 * math.cos(a), scenario.position[1] + 0.8 * math.sin(a), a + math.pi + rng.uniform(-0.2, 0.2))
        T_WC = planar_transform(*pose) @ robot.camera_in_robot(*robot.look_at(pose, (*scenario.position, 0.5 * scenario.height)))
        z = measure_object(extract_silhouette(world.renderer.render(T_WC, k + 1), perception), camera, T_WC, perception)
        assert z.cut == () and z.delta is not None  # whole silhouettes: the test is about the shape, not the border
        cam = (T_WC[0, 3], T_WC[1, 3], optical_axis_heading(T_WC))
        (ekf.update if ekf.initialized else ekf.initialize)(cam, z.phi, z.delta)
    error = ekf.x[:2] - centroid
    assert np.hypot(*error) < 0.015
    assert error @ np.linalg.solve(ekf.P[:2, :2], error) < chi2.ppf(0.997, 2)
    assert ekf.stats.gated == 0 and ekf.stats.reinitialized == 0
    if scenario.kind == "cylinder":
        assert ekf.width.c2 == 0.0 and ekf.stats.width_gated == 0
    else:
        assert ekf.width.c2 > 0.0 and ekf.stats.width_gated <= 0.1 * 48


@pytest.mark.parametrize("seed, omnidirectional", [(13, False), (23, False), (15, True), (35, True)])
def test_planner_seeds_that_used_to_diverge_converge(seed, omnidirectional):
    """Regression (nao_sim.sim2d): from these starts the first update after a one-view initialization used
    to jump 1 to 2.9 m off with a centimetre covariance, or clamp r at its minimum, and the gate then
    rejected every view. With the inverse-range start the estimate converges; 60 steps (12 s) suffice."""
    from agent.planner import load_planner_params
    from nao_sim.sim2d import random_scenario, simulate
    from tools.plan_sim import sim_robot

    planner = dataclasses.replace(load_planner_params(), omnidirectional=omnidirectional)
    result = simulate(*random_scenario(seed), planner, PARAMS, sim_robot(), seed, max_steps=60)
    seen = np.isfinite(result.measurements[:, 0])
    assert seen.sum() > 30
    centre_error, radius_error = result.final_errors()
    std = position_std(result.covariances[-1])
    assert centre_error < 0.02 and radius_error < 0.01, (centre_error, radius_error)
    assert centre_error < 4 * std + 1e-3  # and the covariance covers the error


def test_paper_width_form_misreads_true_widths_as_a_doubled_radius():
    """docs/estimation.md, "The paper's slips": slip 1: atan(r/d) fits the measured full angle only with r about twice too large."""
    paper = dataclasses.replace(PARAMS, width_model="paper_atan")
    truth = np.array([0.0, 0.0, 0.08])
    cams = circling_cameras(truth[:2], 0.6, 72, aim_offset=0.1)
    rng = np.random.default_rng(9)
    true_widths = simulate(ObjectEKF(PARAMS), truth, cams, rng)  # widths generated with asin
    ekf = ObjectEKF(paper)
    z = measure(truth, cams)
    ekf.initialize(cams[0], *z[0])
    for cam, obs in zip(cams[1:], z[1:]):
        ekf.update(cam, *obs)
    assert abs(true_widths.x[-1, 2] - truth[2]) < 0.002
    assert 1.9 < ekf.x[2] / truth[2] < 2.2
    # With widths that follow its own model, the paper form is consistent with itself.
    own = simulate(ObjectEKF(paper), truth, cams, rng)
    assert abs(own.x[-1, 2] - truth[2]) < 0.003


def test_config_defaults_and_errors(tmp_path):
    np.testing.assert_allclose(PARAMS.R, NOMINAL_R, rtol=1e-5)
    assert PARAMS.width_model == "asin"
    bad = tmp_path / "ekf.yaml"
    bad.write_text("ekf:\n  width_model: atan\n")
    with pytest.raises(ConfigError, match=r"ekf.width_model: expected one of \['asin', 'paper_atan'\]"):
        load_ekf_params([bad])


def test_demo_writes_its_figures(tmp_path, capsys):
    from tools.demo_estimation import main

    assert main(["--out", str(tmp_path / "demo")]) == 0
    printed = capsys.readouterr().out
    for name in ("estimation_topview.png", "estimation_errors.png"):
        path = tmp_path / "demo" / name
        assert path.stat().st_size > 10_000 and f"wrote {path}" in printed


@pytest.mark.parametrize("floored", [False, True])
@pytest.mark.parametrize("offset, bias", [((0.0, 0.02), -0.02), ((0.0, 0.02), 0.02), ((0.02, 0.0), 0.015), ((0.01, 0.018), -0.01)])
def test_a_standing_robot_with_a_biased_bearing_does_not_move_the_range(offset, bias, floored):
    """Seen from 2 cm beside its first view (the head turning on a standing robot), a bearing biased
    by a shape (a figure's silhouette cut at the top) must not carry the range away: before
    min_parallax the same 30 views put a 1.5 m object 351 m away (a stress-matrix mission, seed 100).
    A start whose floor contact knows the range to 6 % keeps it as well (it stays on inverse range)."""
    truth = np.array([0.0, 0.0, 0.09])
    anchor = np.array([1.3, 0.7, math.atan2(-0.7, -1.3)])
    ekf = ObjectEKF(PARAMS)
    floor = FloorContact(floor_depression(truth, anchor, 0.5)[0], 0.5) if floored else None
    ekf.initialize(anchor, *measure(truth, anchor), floor)
    start = math.hypot(*(ekf.x[:2] - anchor[:2]))
    cam = np.array([anchor[0] + offset[0], anchor[1] + offset[1], anchor[2] - 0.3])
    phi = measure(truth, cam)[0] + bias
    for _ in range(30):
        ekf.predict(0.07)
        assert ekf.update(cam, phi).accepted
    assert math.hypot(*(ekf.x[:2] - anchor[:2])) == pytest.approx(start, rel=0.02)
    assert math.isfinite(position_std(ekf.P)) and position_std(ekf.P) < 2.0 * start



@pytest.mark.parametrize("radius", [0.033, 0.1])
def test_a_start_without_a_width_restarts_from_the_first_view_with_one_and_its_floor_contact(radius):
    """A first view cut at the bottom gives a bearing alone: the start is at the default range. Width
    views from the standing robot then carried the range to radius prior / sin(delta / 2), however
    wrong (one-wall world 507: a 21 cm-wide remote 1 m away put at 0.5 m with a 7 cm std, then lost):
    a Cartesian start has no range to leave alone. Now the first view with a width restarts the filter
    with its floor contact, and the range stays right."""
    truth = np.array([1.0, -0.3, radius])
    start = np.array([0.06, 0.0, 0.0])
    ekf = ObjectEKF(PARAMS)
    ekf.initialize(start, measure(truth, start)[0])
    for k in range(30):  # the head turns: the camera moves by 2 cm
        cam = np.array([0.06 + 0.01 * math.sin(k), -0.02 * (k % 2), -0.25])
        floor = FloorContact(floor_depression(truth, cam, 0.5)[0], 0.5)
        ekf.predict(0.07)
        result = ekf.update(cam, *measure(truth, cam), floor=floor)
        assert result.accepted and (k > 0 or result.reason == "restarted from the first view with a width")
    distance = math.hypot(*(truth[:2] - start[:2]))
    assert math.hypot(*(ekf.x[:2] - truth[:2])) < 0.08 * distance
    assert abs(ekf.x[2] - radius) < 0.3 * radius


@settings(max_examples=100, deadline=None)
@given(coord, coord, st.floats(0.02, 0.3), coord, coord, st.floats(-math.pi, math.pi))
def test_pose_noise_is_the_camera_covariance_through_the_camera_jacobian(xo, yo, r, cx, cy, psi):
    """Hc C Hc^T with Hc = dh/dcam: equal to central differences of ``measure`` in the camera pose."""
    x, cam = np.array([xo, yo, r]), np.array([cx, cy, psi])
    assume(math.hypot(xo - cx, yo - cy) > r + 0.05)
    Hc = np.zeros((2, 3))
    for i in range(3):
        step = np.zeros(3)
        step[i] = 1e-6
        hi, lo = measure(x, cam + step), measure(x, cam - step)
        Hc[:, i] = (wrap_angle(hi[0] - lo[0]) / 2e-6, (hi[1] - lo[1]) / 2e-6)
    C = np.diag([0.02, 0.03, 0.01]) ** 2 + 1e-4 * np.ones((3, 3))
    np.testing.assert_allclose(pose_noise(x, cam, C), Hc @ C @ Hc.T, rtol=1e-4, atol=1e-12)


def test_views_from_a_pose_as_uncertain_as_its_covariance_says_neither_gate_nor_restart():
    """300 views from exact poses, then 120 from a pose that has drifted 4 cm sideways (the views
    are of the true object, the filter is told the drifted camera). Told nothing of the drift they
    are gated and, consistent with each other, restart the estimate centimetres off; told the pose
    covariance (3 cm std), every view is fused at its weight and the estimate stays within 1 cm."""
    truth = np.array([1.0, 0.0, 0.05])
    cams = circling_cameras(truth[:2], 0.6, 300)
    drift = np.array([0.0, 0.04, 0.0])
    drifted = circling_cameras(truth[:2], 0.6, 120, start=1.0)
    C = np.diag([0.03, 0.03, 0.002]) ** 2
    ends = {}
    for told in (False, True):
        ekf = ObjectEKF(PARAMS)
        z = measure(truth, cams)
        ekf.initialize(cams[0], *z[0])
        assert all(ekf.update(cam, *obs).accepted for cam, obs in zip(cams[1:], z[1:]))
        results = [ekf.update(cam, *measure(truth, cam + drift), C if told else None) for cam in drifted]
        ends[told] = (ekf.x.copy(), sum(r.accepted for r in results), ekf.stats.reinitialized)
    x, accepted, restarts = ends[True]
    assert accepted == 120 and restarts == 0 and math.dist(x[:2], truth[:2]) < 0.01
    x, accepted, restarts = ends[False]
    assert restarts == 1 and math.dist(x[:2], truth[:2]) > 0.02


def test_a_malformed_pose_covariance_is_rejected_and_changes_nothing():
    ekf = ObjectEKF(PARAMS)
    ekf.initialize((0.0, 0.0, 0.0), 0.0, 2 * math.asin(0.1 / 1.0))
    before = ekf.copy()
    for bad in (np.eye(2), np.full((3, 3), np.nan), -np.eye(3), [["a"] * 3] * 3):
        result = ekf.update((0.0, 0.1, 0.0), -0.1, 0.2, bad)
        assert not result.accepted and "camera pose covariance" in result.reason
    np.testing.assert_array_equal(ekf.x, before.x)
    assert ekf.stats.invalid == 4


def test_weighing_drifting_poses_by_their_covariance_restarts_less_and_errs_less():
    """Monte Carlo (tools/demo_estimation.py ``PoseDrift``): camera poses off as a localizer leaves
    them between fixes. The same runs, the poses taken as exact, restart most estimates and end
    centimetres off; weighed by their covariance, few restart and the centre error drops."""
    drift = PoseDrift(step=0.004, heading_step=0.003, fix=0.005, heading_fix=0.003, fix_every=12)
    runs = {weigh: circling_runs(PARAMS, 40, 72, seed=5, drift=drift, weigh_pose=weigh) for weigh in (False, True)}
    restarted = {weigh: sum(t.restarts > 0 for t in traces) for weigh, traces in runs.items()}
    error = {weigh: np.median([math.dist(t.x[-1, :2], t.truth[:2]) for t in traces]) for weigh, traces in runs.items()}
    assert restarted[False] >= 15 and restarted[True] <= 3
    assert error[True] < 0.75 * error[False]
