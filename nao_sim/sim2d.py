"""A 2-D simulation of the active loop (no images): true cylinder, noisy measurements, EKF, planner.

Each control period k:

1. camera pose c_k from the robot pose and the head-yaw policy toward the current estimate
   (toward the straight-ahead direction before the object is first seen; :mod:`agent.motion`);
2. if the true cylinder is in view (:func:`agent.motion.object_in_view`), measure
   (phi, delta) = h(x_true, c_k) + n,  n ~ N(0, diag(sigma_phi^2, sigma_delta^2)), and initialize or
   predict(tau) + update the EKF;
3. record c_k for coverage, check termination (:func:`agent.planner.termination_reason`);
4. pick the command (v, v_y, omega_k): the planner (active) or a circle-following law around the first
   estimate (passive), clamp it to the walk limits, walk one period.

Passive circle law (a vector field converging to the circle of radius d_min around the centre g,
travelled counter-clockwise)::

    heading* = atan2(g - p) - pi/2 + atan(k (d - d_min) / d_min)
    omega    = clip(v / d + wrap(heading* - theta) / tau, -omega_max, omega_max)   (v / d: the circle's own turn)

Deterministic for a seed: the noise and the planner's sampler draw from generators seeded with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Literal, Optional, Tuple

import numpy as np

from agent.coverage import Coverage, bins_seen
from agent.ekf import EKFParams, ObjectEKF, measure
from agent.keep_in import KeepIn
from agent.landmark_reach import LandmarkReach
from agent.motion import camera_poses, object_in_view, rollout_poses
from agent.planner import Planner, PlannerParams, termination_reason
from nao_core.geometry import wrap_angle
from nao_core.robot_model import WalkLimits

Policy = Literal["planner", "circle"]
CIRCLE_GAIN = 2.0


@dataclass(frozen=True)
class SimRobot:
    """What the simulation needs to know about the robot."""

    walk: WalkLimits
    hfov: float
    head_yaw_limits: Tuple[float, float]
    camera_offset: float


@dataclass
class SimResult:
    """Per-step histories (k = 0 .. K-1) and the outcome of one run."""

    truth: np.ndarray  # (3,) true (xo, yo, r)
    poses: np.ndarray  # (K, 3) robot poses where each period started
    cameras: np.ndarray  # (K, 3) camera poses
    estimates: np.ndarray  # (K, 3) x after the step's update (NaN before initialization)
    covariances: np.ndarray  # (K, 3, 3)
    commands: np.ndarray  # (K, 3) (v, vy, omega) sent
    measurements: np.ndarray  # (K, 2) noisy (phi, delta), NaN where the object was not in view
    true_coverage: np.ndarray  # (K,) fraction of the true cylinder's bins seen so far
    reason: str
    first_estimate: Optional[np.ndarray] = None
    plan_terms: List[dict] = field(default_factory=list)

    @property
    def path_length(self) -> np.ndarray:
        """Distance walked before each step, (K,)."""
        steps = np.hypot(*np.diff(self.poses[:, :2], axis=0).T)
        return np.concatenate([[0.0], np.cumsum(steps)])

    def steps_to_full_coverage(self) -> Optional[int]:
        full = np.flatnonzero(self.true_coverage >= 1.0)
        return int(full[0]) if full.size else None

    def final_errors(self) -> Tuple[float, float]:
        """(centre error, |radius error|) of the last estimate, m."""
        x = self.estimates[-1]
        return float(np.hypot(*(x[:2] - self.truth[:2]))), float(abs(x[2] - self.truth[2]))


def random_scenario(seed: int) -> Tuple[np.ndarray, np.ndarray]:
    """A true cylinder near the origin (r in 5..20 cm) and a start 1.5..2.5 m away, roughly facing it."""
    rng = np.random.default_rng(1000 + seed)
    azimuth, distance = rng.uniform(-math.pi, math.pi), rng.uniform(1.5, 2.5)
    heading = azimuth + math.pi + rng.uniform(-0.3, 0.3)
    start = np.array([distance * math.cos(azimuth), distance * math.sin(azimuth), wrap_angle(heading)])
    truth = np.array([*rng.uniform(-0.2, 0.2, 2), rng.uniform(0.05, 0.2)])
    return truth, start


def circle_omega(
    pose: np.ndarray, centre: np.ndarray, radius: float, speed: float, period: float, omega_max: float
) -> float:
    """The passive law of the module docstring."""
    d = math.hypot(centre[0] - pose[0], centre[1] - pose[1])
    heading = math.atan2(centre[1] - pose[1], centre[0] - pose[0]) - 0.5 * math.pi
    heading += math.atan(CIRCLE_GAIN * (d - radius) / radius)
    return float(np.clip(speed / d + wrap_angle(heading - pose[2]) / period, -omega_max, omega_max))


def simulate(
    truth: np.ndarray,
    start: np.ndarray,
    planner_params: PlannerParams,
    ekf_params: EKFParams,
    robot: SimRobot,
    seed: int,
    policy: Policy = "planner",
    max_steps: Optional[int] = None,
    keep_in: Optional[KeepIn] = None,
    landmarks: Optional[LandmarkReach] = None,
) -> SimResult:
    """Run one episode from robot pose ``start`` toward the cylinder ``truth`` = (xo, yo, r); the
    planner keeps off the walls of ``keep_in`` and keeps ``landmarks`` within the head's reach (c_m) if given."""
    truth = np.asarray(truth, dtype=float)
    pose = np.asarray(start, dtype=float).copy()
    p = planner_params
    rng = np.random.default_rng(seed)
    noise_std = np.array([ekf_params.sigma_phi, ekf_params.sigma_delta])
    planner = Planner(p, robot.walk, robot.hfov, robot.head_yaw_limits, robot.camera_offset, ekf_params, seed=seed)
    ekf = ObjectEKF(ekf_params)
    coverage = Coverage(p.coverage, robot.hfov)
    true_seen = np.zeros(p.coverage.bins, dtype=bool)
    steps = max_steps if max_steps is not None else int(math.ceil(p.termination.time_limit / p.period))
    hist = {k: [] for k in ("poses", "cameras", "estimates", "covariances", "commands", "measurements", "coverage")}
    first_estimate, terms, reason = None, [], "step_limit"
    for k in range(steps):
        target = ekf.x[:2] if ekf.initialized else pose[:2] + np.array([math.cos(pose[2]), math.sin(pose[2])])
        cam = camera_poses(pose, target, robot.head_yaw_limits, robot.camera_offset)
        seen = bool(object_in_view(truth, cam, robot.hfov, p.max_range))
        phi, delta = measure(truth, cam) + noise_std * rng.standard_normal(2) if seen else (np.nan, np.nan)
        if seen:
            if ekf.initialized:
                ekf.predict(p.period)
                ekf.update(cam, float(phi), float(delta))
            else:
                ekf.initialize(cam, float(phi), float(delta))
                first_estimate = ekf.x.copy()
        elif ekf.initialized:
            ekf.predict(p.period)
        coverage.add(cam)
        true_seen |= bins_seen(truth, cam, p.coverage, robot.hfov)
        hist["poses"].append(pose.copy())
        hist["cameras"].append(cam)
        hist["estimates"].append(ekf.x.copy() if ekf.initialized else np.full(3, np.nan))
        hist["covariances"].append(ekf.P.copy() if ekf.initialized else np.full((3, 3), np.nan))
        hist["measurements"].append((phi, delta))
        hist["coverage"].append(true_seen.mean())
        if ekf.initialized:
            reachable = None if keep_in is None else planner.reachable_bins(ekf.x, keep_in)
            covered = coverage.fraction(ekf.x, p.termination.facing_margin, reachable)
            done = termination_reason(covered, ekf.P, k * p.period, p.termination)
            if done is not None:
                reason = done
                hist["commands"].append(np.zeros(3))
                break
        if not ekf.initialized:
            command = robot.walk.clamp(p.speed, 0.0, 0.0)
        elif policy == "circle":
            omega = circle_omega(pose, first_estimate, p.d_min, p.speed, p.period, robot.walk.omega_max)
            command = robot.walk.clamp(p.speed, 0.0, omega)
        else:
            plan = planner.plan(pose, ekf.x, ekf.P, coverage, keep_in=keep_in, landmarks=landmarks)
            terms.append(plan.terms)
            command = plan.command  # already clamped to the walk limits by the planner
        command = np.array(command)
        hist["commands"].append(command)
        pose = rollout_poses(pose, command[2:], command[0], p.period, command[1])[0]
    return SimResult(
        truth=truth,
        poses=np.array(hist["poses"]),
        cameras=np.array(hist["cameras"]),
        estimates=np.array(hist["estimates"]),
        covariances=np.array(hist["covariances"]),
        commands=np.array(hist["commands"]),
        measurements=np.array(hist["measurements"]),
        true_coverage=np.array(hist["coverage"]),
        reason=reason,
        first_estimate=first_estimate,
        plan_terms=terms,
    )

