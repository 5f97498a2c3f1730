"""Motion model, cost terms against hand-computed values, the planner, and the closed loop in 2-D simulation."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from agent.coverage import Coverage
from agent.ekf import load_ekf_params, measure
from agent.keep_in import KeepIn
from agent.landmark_reach import LandmarkReach
from agent.localization import LocalizationParams
from agent.motion import camera_poses, head_yaw_toward, object_in_view, rollout_poses
from agent.planner import (
    VerticalView,
    vertical_view_cost,
    CLEARANCE_WEIGHT,
    Planner,
    clearance_cost,
    clearance_margin,
    coverage_cost,
    distance_cost,
    effort_cost,
    load_planner_params,
    termination_reason,
    uncertainty_cost,
    view_cost,
)
from nao_core.config import CONFIG_DIR, load
from nao_core.landmark_map import Landmark, LandmarkMap, load_landmark_map
from nao_core.robot_model import load_robot_model
from nao_sim.sim2d import SimRobot, circle_omega, random_scenario, simulate

ROBOT_MODEL = load_robot_model()
PARAMS = load_planner_params()
EKF = load_ekf_params()
FOCAL = ROBOT_MODEL.camera.intrinsics("vga").fx
MIN_PX = load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization").aruco_min_side_px  # c_m's q_min
HFOV = 2.0 * math.atan(0.5 * 640 / FOCAL)
ROBOT = SimRobot(ROBOT_MODEL.walk, HFOV, ROBOT_MODEL.head.yaw, ROBOT_MODEL.camera.offset[0])


# --- motion ---------------------------------------------------------------------------------------


def test_straight_walk_advances_v_tau_per_step():
    poses = rollout_poses(np.array([1.0, 2.0, math.pi / 2]), np.zeros(3), speed=0.1, period=2.0)
    np.testing.assert_allclose(poses, [[1.0, 2.2, math.pi / 2], [1.0, 2.4, math.pi / 2], [1.0, 2.6, math.pi / 2]], atol=1e-12)


def test_constant_turn_walks_the_exact_circle_of_radius_v_over_omega():
    v, omega, tau = 0.08, 0.2, 1.0
    n = 70  # more than two full turns
    poses = rollout_poses(np.zeros(3), np.full(n, omega), v, tau)
    centre = np.array([0.0, v / omega])  # turning left from the origin heading +x
    np.testing.assert_allclose(np.hypot(*(poses[:, :2] - centre).T), v / omega, atol=1e-12)
    np.testing.assert_allclose(poses[:, 2], np.angle(np.exp(1j * omega * tau * np.arange(1, n + 1))), atol=1e-9)


def test_lateral_walk_moves_left_of_the_heading():
    pose = rollout_poses(np.zeros(3), np.zeros(1), speed=0.0, period=1.0, lateral_speed=0.05)[0]
    np.testing.assert_allclose(pose, [0.0, 0.05, 0.0], atol=1e-12)


def test_head_yaw_points_the_camera_at_the_target_within_limits():
    target = np.array([1.0, 1.0, 0.1])
    robot = np.array([0.0, 0.0, 0.0])
    assert head_yaw_toward(robot, target, (-2.0, 2.0)) == pytest.approx(math.pi / 4)
    cam = camera_poses(robot, target, (-2.0, 2.0), camera_offset=0.06)
    np.testing.assert_allclose(cam, [0.06 * math.cos(math.pi / 4), 0.06 * math.sin(math.pi / 4), math.pi / 4])
    assert measure(target, cam)[0] == pytest.approx(0.0, abs=1e-12)  # the offset lies on the optical axis
    behind = np.array([-1.0, -0.01, 0.1])
    assert head_yaw_toward(robot, behind, (-2.0, 2.0)) == pytest.approx(-2.0)  # clipped at the limit
    assert not object_in_view(behind, camera_poses(robot, behind, (-2.0, 2.0), 0.06), hfov=1.0, max_range=5.0)
    assert object_in_view(target, cam, hfov=1.0, max_range=5.0)
    assert not object_in_view(target, cam, hfov=1.0, max_range=1.0)  # beyond range


# --- cost terms -----------------------------------------------------------------------------------


def test_uncertainty_cost_relative_and_paper():
    P = np.diag([0.01, 0.02, 0.04]) ** 2  # det = 6.4e-11, cbrt = 4e-4
    assert uncertainty_cost(P, 0.1, "paper") == pytest.approx(6.4e-11)
    assert uncertainty_cost(P, 0.1, "relative") == pytest.approx(4e-4 / 0.01)
    # Scaling the world by s leaves the relative form unchanged: comparable across object sizes.
    assert uncertainty_cost(P * 25.0, 0.5, "relative") == pytest.approx(0.04)


def test_view_cost_paper_and_reachable():
    """The paper's form is the end's bearing squared; the reachable form sums the squared excesses over
    the horizon, so a turn that passes the object behind the robot's back costs even when it ends
    with the object in reach (one-wall world 502)."""
    reach = (-2.58, 2.58)
    assert view_cost(np.array([3.0, 0.5]), reach, "paper") == pytest.approx(0.25)
    np.testing.assert_allclose(view_cost(np.array([[2.5], [-2.5], [3.0], [-3.1]]), reach, "reachable"), [0, 0, 0.42**2, 0.52**2])
    through_the_back = np.array([1.5, 2.5, 3.0, -3.1, -2.0])
    assert view_cost(through_the_back, reach, "reachable") == pytest.approx(0.42**2 + 0.52**2)


def test_coverage_cost_corrected_and_paper():
    assert coverage_cost(9, 36, "corrected") == pytest.approx(0.75)
    assert coverage_cost(9, 36, "paper") == pytest.approx(0.25)


def test_distance_cost_standoff_and_paper():
    assert distance_cost(1.2, 0.8, "standoff") == pytest.approx(0.25)
    assert distance_cost(0.8, 0.8, "standoff") == 0.0
    assert distance_cost(1.2, 0.8, "paper") == pytest.approx(2 / 3)


def test_effort_and_clearance_costs():
    assert effort_cost(np.array([0.1, -0.2])) == pytest.approx(0.05)
    # r + clearance = 0.35: only the 0.30 m step violates, by 0.05 m.
    assert clearance_cost(np.array([1.0, 0.30]), 0.1, 0.25) == pytest.approx(CLEARANCE_WEIGHT * 0.05**2)
    assert clearance_cost(np.array([1.0, 0.36]), 0.1, 0.25) == 0.0


def test_clearance_margin_is_k_sigma_of_the_distance_to_the_surface():
    P = np.diag([0.1, 0.2, 0.05]) ** 2
    robot = np.array([[0.0, 0.0], [1.0, -1.0]])  # object at (1, 0): seen along +x, then along +y
    x = np.array([1.0, 0.0, 0.1])
    margin = clearance_margin(robot, x, P, sigmas=3.0, cap=10.0)
    np.testing.assert_allclose(margin, 3.0 * np.sqrt([0.1**2 + 0.05**2, 0.2**2 + 0.05**2]))
    # Centre and radius errors that move the surface together cancel: s = d - r barely changes.
    correlated = P.copy()
    correlated[0, 2] = correlated[2, 0] = 0.9 * 0.1 * 0.05
    assert clearance_margin(robot[:1], x, correlated, 3.0, 10.0)[0] == pytest.approx(3.0 * math.sqrt(0.01 + 0.0025 - 0.009))
    assert clearance_margin(robot, x, P, 3.0, cap=0.4).tolist() == [pytest.approx(0.3354, abs=1e-4), 0.4]
    # The margin adds to the clearance: r + clearance + m = 0.5 m here, the 0.45 m step violates by 0.05 m.
    assert clearance_cost(np.array([1.0, 0.45]), 0.1, 0.25, np.array([0.15, 0.15])) == pytest.approx(CLEARANCE_WEIGHT * 0.05**2)


def test_termination_reasons():
    small = np.diag([0.001, 0.001, 0.001]) ** 2
    params = PARAMS.termination
    assert termination_reason(1.0, small, 10.0, params).startswith("complete")
    assert termination_reason(0.9, small, 10.0, params) is None
    assert termination_reason(1.0, small * 100, 10.0, params) is None  # 1 cm std is not precise enough
    assert termination_reason(0.5, small, params.time_limit, params).startswith("time_limit")


# --- planner --------------------------------------------------------------------------------------


def make_planner(**changes) -> Planner:
    """A planner of the config with ``changes``; a unicycle unless asked (the tests roll out v_y = 0)."""
    changes = {"omnidirectional": False, **changes}
    return Planner(dataclasses.replace(PARAMS, **changes), ROBOT.walk, HFOV, ROBOT.head_yaw_limits, ROBOT.camera_offset, EKF)


def test_plan_terms_add_up_and_the_command_is_within_limits():
    planner = make_planner()
    x, P = np.array([2.0, 0.0, 0.1]), np.diag([0.02, 0.5, 0.05]) ** 2
    plan = planner.plan(np.zeros(3), x, P, Coverage(PARAMS.coverage, HFOV))
    assert plan.cost == pytest.approx(sum(plan.terms.values()))
    assert set(plan.terms) == {"uncertainty", "view", "coverage", "distance", "vertical", "landmarks", "effort", "clearance", "wall"}
    assert plan.omegas.shape == (PARAMS.horizon,) and np.all(np.abs(plan.omegas) <= ROBOT.walk.omega_max)
    v, vy, omega = plan.command
    assert (v, vy) == (PARAMS.speed, 0.0) and omega == plan.omegas[0]
    # From 2 m with d_min 0.8 m the plan approaches the object.
    end = rollout_poses(np.zeros(3), plan.omegas, PARAMS.speed, PARAMS.period)[-1]
    assert math.hypot(*(x[:2] - end[:2])) < 2.0 - 0.5 * PARAMS.horizon * PARAMS.speed


def test_plan_turns_away_rather_than_break_the_clearance():
    planner = make_planner()
    r = 0.1
    x, P = np.array([r + PARAMS.clearance + 0.25, 0.0, r]), np.diag([0.005, 0.005, 0.005]) ** 2  # boundary 0.25 m ahead
    plan = planner.plan(np.zeros(3), x, P, Coverage(PARAMS.coverage, HFOV))
    path = rollout_poses(np.zeros(3), plan.omegas, PARAMS.speed, PARAMS.period)
    assert np.min(np.hypot(*(x[:2] - path[:, :2]).T)) >= x[2] + PARAMS.clearance
    assert plan.terms["clearance"] == 0.0


def test_a_poor_estimate_keeps_the_uncertainty_margin():
    # An estimate 1.2 m ahead with 15 cm position and 5 cm radius std: 3 sigma along the line of sight is
    # about 0.47 m, so the plan must stay r + clearance + 0.47 = 0.82 m from the estimated centre, although
    # d_min (0.5 m) and the uncertainty term pull it in. Without the margin it does go closer.
    x, P = np.array([1.2, 0.0, 0.1]), np.diag([0.15, 0.15, 0.05]) ** 2
    coverage = Coverage(PARAMS.coverage, HFOV)
    closest = {}
    for sigmas in (3.0, 0.0):
        plan = make_planner(d_min=0.5, clearance_sigmas=sigmas).plan(np.zeros(3), x, P, coverage)
        path = rollout_poses(np.zeros(3), plan.omegas, PARAMS.speed, PARAMS.period)
        margin = clearance_margin(path, x, P, sigmas, PARAMS.clearance_margin_max)
        assert np.all(np.hypot(*(x[:2] - path[:, :2]).T) >= x[2] + PARAMS.clearance + margin - 1e-3)
        closest[sigmas] = np.min(np.hypot(*(x[:2] - path[:, :2]).T))
    assert plan.clearance_margin == 0.0
    assert closest[3.0] >= 0.1 + 0.25 + 0.47 and closest[0.0] < 0.1 + 0.25 + 0.3


def test_omnidirectional_plan_chooses_a_lateral_speed_within_limits():
    planner = make_planner(omnidirectional=True)
    x, P = np.array([0.4, 0.5, 0.1]), np.diag([0.01, 0.01, 0.01]) ** 2  # object ahead to the left, 0.64 m away
    evaluate = planner.cost_function(np.zeros(3), x, P, np.zeros(PARAMS.coverage.bins, dtype=bool))
    toward, away = np.zeros((2, PARAMS.horizon + 1))
    toward[-1], away[-1] = ROBOT.walk.vy_max, -ROBOT.walk.vy_max
    clearance = evaluate(np.stack([toward, away]))[1]["clearance"]
    assert clearance[0] > 0.0 and clearance[1] == 0.0  # the lateral speed moves the predicted robot
    plan = planner.plan(np.zeros(3), x, P, Coverage(PARAMS.coverage, HFOV))
    v, vy, omega = plan.command
    assert plan.omegas.shape == (PARAMS.horizon,) and vy == plan.lateral_speed and abs(vy) <= ROBOT.walk.vy_max
    path = rollout_poses(np.zeros(3), plan.omegas, v, PARAMS.period, vy)
    assert np.min(np.hypot(*(x[:2] - path[:, :2]).T)) >= x[2] + PARAMS.clearance
    assert make_planner(omnidirectional=False).plan(np.zeros(3), x, P, Coverage(PARAMS.coverage, HFOV)).command[1] == 0.0


def test_nelder_mead_and_cem_optimize_the_same_cost():
    x, P = np.array([1.5, 0.3, 0.1]), np.diag([0.02, 0.3, 0.05]) ** 2
    coverage = Coverage(PARAMS.coverage, HFOV)
    cem = make_planner(horizon=5).plan(np.zeros(3), x, P, coverage)
    nm = make_planner(horizon=5, optimizer="nelder_mead").plan(np.zeros(3), x, P, coverage)
    zero = make_planner(horizon=5).cost_function(np.zeros(3), x, P, coverage.seen(x))(np.zeros((1, 5)))[0][0]
    assert nm.cost < zero and cem.cost < zero  # both improve on walking straight
    assert cem.cost <= nm.cost * 1.02


def test_warm_start_is_the_previous_solution_shifted():
    planner = make_planner(horizon=4, cem=dataclasses.replace(PARAMS.cem, iterations=1))
    x, P = np.array([1.5, 0.3, 0.1]), np.diag([0.02, 0.3, 0.05]) ** 2
    first = planner.plan(np.zeros(3), x, P, Coverage(PARAMS.coverage, HFOV))
    np.testing.assert_array_equal(planner._warm_start(), np.append(first.omegas[1:], first.omegas[-1]))
    planner.reset()
    np.testing.assert_array_equal(planner._warm_start(), np.zeros(4))


@pytest.mark.parametrize(
    "args, message",
    [
        ((np.zeros(2), np.array([1.0, 0.0, 0.1]), np.eye(3)), "robot_pose"),
        ((np.zeros(3), np.array([1.0, np.nan, 0.1]), np.eye(3)), "x: expected finite"),
        ((np.zeros(3), np.array([1.0, 0.0, -0.1]), np.eye(3)), "radius must be positive"),
        ((np.zeros(3), np.array([1.0, 0.0, 0.1]), "eye"), "P: expected finite"),
    ],
)
def test_bad_input_is_named(args, message):
    with pytest.raises(ValueError, match=message):
        make_planner().plan(*args, Coverage(PARAMS.coverage, HFOV))


def test_speed_beyond_the_walk_limit_is_refused():
    with pytest.raises(ValueError, match="v_max"):
        make_planner(speed=0.5)


def marked_wall(x: float = 1.8, ys=(-1.2, -0.4, 0.4, 1.2), size: float = 0.15) -> LandmarkMap:
    """Markers on one wall at ``x``, facing the origin."""
    return LandmarkMap(tuple(Landmark(id=i, kind="aruco", dictionary="DICT_4X4_50", size=size, position=(x, y, 0.3), yaw=math.pi)
                             for i, y in enumerate(ys)))


def test_landmarks_count_where_the_head_can_turn_the_camera_to_them():
    """agent/landmark_reach.py: a marker ahead counts 1, straight behind (beyond the head's reach) 0,
    seen from behind its wall 0, too far to keep its width 0; a ball counts from any side; the count
    fades continuously at the reach's edge."""
    planner = make_planner()
    lo, hi = planner.reach
    one = LandmarkReach.from_map(marked_wall(ys=(0.0,)), FOCAL, MIN_PX)
    assert one.counts(np.zeros(3), planner.reach) == pytest.approx(1.0)
    assert one.counts(np.array([0.0, 0.0, math.pi]), planner.reach) == 0.0
    assert one.counts(np.array([2.5, 0.0, math.pi]), planner.reach) == 0.0  # behind the wall: the marker faces away
    far = FOCAL * 0.15 / MIN_PX  # its width is the least kept from there
    assert one.counts(np.array([1.8 - far, 0.0, 0.0]), planner.reach) == 0.0
    assert one.counts(np.array([1.8 - 0.5 * far, 0.0, 0.0]), planner.reach) == pytest.approx(1.0)
    ball = LandmarkReach.from_map(LandmarkMap((Landmark(id="b", kind="color", color="green", diameter=0.12, position=(1.8, 0.0, 0.3)),)),
                                  FOCAL, MIN_PX)
    assert ball.counts(np.array([2.5, 0.0, math.pi]), planner.reach) == pytest.approx(1.0)
    edge = np.array([[0.0, 0.0, -hi + d] for d in np.linspace(-0.3, 0.3, 61)])  # the marker at bearing hi - d
    counts = one.counts(edge, planner.reach)
    assert counts[0] == 0.0 and counts[-1] == pytest.approx(1.0)
    assert np.all(np.diff(counts) >= 0.0) and np.max(np.diff(counts)) < 0.1


def test_a_room_marked_all_round_leaves_the_plan_as_it_was():
    """The ring of config/landmarks/sim_room.yaml keeps two landmarks and more within reach from every
    pose round the object: c_m is zero and the plan the same as without it."""
    reach = LandmarkReach.from_map(load_landmark_map(CONFIG_DIR / "landmarks" / "sim_room.yaml"), FOCAL, MIN_PX)
    x, P = np.array([0.0, 0.0, 0.05]), np.diag([0.01, 0.01, 0.005]) ** 2
    for start in (np.array([0.8, 0.0, math.pi / 2]), np.array([0.0, -0.9, 0.3]), np.array([-0.6, 0.6, -2.0])):
        plans = [make_planner(omnidirectional=True).plan(start, x, P, Coverage(PARAMS.coverage, HFOV), landmarks=lm)
                 for lm in (None, reach)]
        assert plans[1].terms["landmarks"] == 0.0
        np.testing.assert_array_equal(plans[0].omegas, plans[1].omegas)


# --- closed loop in simulation ----------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(10))
def test_active_loop_localizes_and_covers_within_limits(seed):
    truth, start = random_scenario(seed)
    result = simulate(truth, start, dataclasses.replace(PARAMS, omnidirectional=False), EKF, ROBOT, seed)  # the unicycle
    assert result.reason.startswith("complete")
    centre_error, radius_error = result.final_errors()
    assert centre_error < 0.01 and radius_error < 0.005
    distance = np.hypot(*(result.poses[:, :2] - truth[:2]).T)
    assert np.min(distance - truth[2]) >= PARAMS.clearance - 0.02  # never inside the clearance (2 cm estimate slack)
    settled = np.median(distance[len(distance) // 2 :])
    full = result.steps_to_full_coverage()
    assert full is not None and result.path_length[full] <= 1.3 * 2 * math.pi * settled
    v, vy, omega = result.commands.T
    assert np.all(v <= ROBOT.walk.v_max) and np.all(np.abs(vy) <= ROBOT.walk.vy_max)
    assert np.all(np.abs(omega) <= ROBOT.walk.omega_max)


@pytest.mark.parametrize("seed", range(2))
def test_omnidirectional_loop_localizes_and_covers_within_limits(seed):
    truth, start = random_scenario(seed)
    result = simulate(truth, start, dataclasses.replace(PARAMS, omnidirectional=True), EKF, ROBOT, seed)
    assert result.reason.startswith("complete") and result.final_errors()[0] < 0.01
    assert np.min(np.hypot(*(result.poses[:, :2] - truth[:2]).T) - truth[2]) >= PARAMS.clearance - 0.02
    vy = result.commands[:, 1]
    assert np.all(np.abs(vy) <= ROBOT.walk.vy_max) and np.any(np.abs(vy) > 0.01)  # it does walk sideways


def test_with_one_marked_wall_the_orbit_keeps_its_markers_within_the_head_s_reach():
    """Markers on one wall 1.8 m from the object (the closed loop, omnidirectional, the planner kept off
    that wall): with c_m the share of poses with fewer than ``landmarks_needed`` markers within the
    head's reach falls to at most 0.7 of it without (measured 0.142 -> 0.079 over seven scenarios),
    and the missions complete as precisely and in as many steps within 10 %."""
    wall = marked_wall()
    reach = LandmarkReach.from_map(wall, FOCAL, MIN_PX)
    params = dataclasses.replace(PARAMS, omnidirectional=True)
    planner = make_planner(omnidirectional=True)
    short, steps = {False: [], True: []}, {False: 0, True: 0}
    for seed in (0, 2, 3, 5, 6, 7, 8):
        truth, start = random_scenario(seed)
        start[:2] *= 0.5  # inside the room
        for with_reach in (False, True):
            result = simulate(truth, start, params, EKF, ROBOT, seed, keep_in=KeepIn(wall), landmarks=reach if with_reach else None)
            assert result.reason.startswith("complete") and result.final_errors()[0] < 0.01
            short[with_reach].extend(reach.counts(result.poses, planner.reach) < PARAMS.landmarks_needed)
            steps[with_reach] += len(result.poses)
    assert np.mean(short[True]) <= 0.7 * np.mean(short[False])
    assert steps[True] <= 1.1 * steps[False]


def test_simulation_is_deterministic_for_a_seed():
    truth, start = random_scenario(3)
    a, b = (simulate(truth, start, PARAMS, EKF, ROBOT, seed=7, max_steps=15) for _ in range(2))
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.estimates, b.estimates)
    c = simulate(truth, start, PARAMS, EKF, ROBOT, seed=8, max_steps=15)
    assert not np.array_equal(a.estimates, c.estimates)


def test_passive_circle_law_converges_to_the_circle():
    pose = np.array([2.0, 0.0, math.pi])
    for _ in range(150):
        omega = circle_omega(pose, np.zeros(2), 0.8, 0.08, 1.0, ROBOT.walk.omega_max)
        pose = rollout_poses(pose, np.array([omega]), 0.08, 1.0)[0]
    assert math.hypot(pose[0], pose[1]) == pytest.approx(0.8, abs=0.03)


def test_vertical_view_cost_vanishes_where_the_base_and_top_fit_the_reachable_view():
    view = VerticalView.for_robot(ROBOT_MODEL, "qvga")
    r, height, margin = 0.055, 0.2, PARAMS.vertical_margin
    for yaw in (0.0, 1.5):  # body facing the object / head turned to the side (lower pitch limit)
        p_hi = ROBOT_MODEL.head.pitch_range(yaw)[1]
        # the base's near edge enters the reachable view at d0 = r + h_c / tan(p_hi + h_v - m)
        d0 = r + view.camera_height / math.tan(p_hi + view.half_vfov - margin)
        near, far = (vertical_view_cost(np.array([d]), np.array([yaw]), r, height, view, margin) for d in (0.9 * d0, 1.05 * d0))
        assert near > 0.0 and far == 0.0
        expected = math.atan2(view.camera_height, 0.9 * d0 - r) + margin - p_hi - view.half_vfov
        assert near == pytest.approx(expected**2)
    # turning the head to the side lowers the pitch limit, so the orbit must be wider
    assert ROBOT_MODEL.head.pitch_range(1.5)[1] < ROBOT_MODEL.head.pitch_range(0.0)[1]
    # an object taller than the view at that range costs by how much it overflows the vertical FOV
    tall = vertical_view_cost(np.array([0.6]), np.array([0.0]), r, 2.0, view, margin)
    assert tall > 0.0


def test_planner_without_robot_geometry_has_no_vertical_term():
    x, P = np.array([1.0, 0.0, 0.1]), np.diag([0.01, 0.01, 0.01]) ** 2
    plan = make_planner().plan(np.zeros(3), x, P, Coverage(PARAMS.coverage, HFOV))
    assert plan.terms["vertical"] == 0.0
    robot = Planner.for_robot(PARAMS, ROBOT_MODEL, "qvga", EKF)
    near = robot.plan(np.array([0.45, 0.0, math.pi / 2]), x, P, Coverage(PARAMS.coverage, HFOV), object_height=0.2)
    assert near.terms["vertical"] > 0.0  # 0.45 m from a 0.1 m can with the head turned: the base is cut
    with pytest.raises(ValueError, match="object_height"):
        robot.plan(np.zeros(3), x, P, Coverage(PARAMS.coverage, HFOV), object_height=-1.0)
