"""Reconstruction-oriented receding-horizon planner (the paper's Sec. III-B, corrected, and fast).

Decision: the angular velocities w = (omega_{t+1}, ..., omega_{t+D}), |omega_k| <= omega_max, walked
at constant speed v for one period tau each (:mod:`agent.motion`). With ``omnidirectional`` on, w also
holds one lateral speed v_y, |v_y| <= vy_max, walked over the whole horizon (NAO walks sideways). Expected cost (docs/estimation.md, "Rollout for the planner":
the filter is rolled forward D steps with noise-free observations at the mean, so x stays and only
the covariance shrinks, :func:`agent.ekf.rollout_covariance`)::

    c(w) = l_l c_l + l_v c_v + l_r c_r + l_d c_d + l_h c_h + l_m c_m + mu |w|^2 + c_clear + c_wall

evaluated at t + D (robot p, heading theta, object estimate o, r, covariance P_{t+D}):

    c_l  uncertainty   "relative": det(P_{t+D})^(1/3) / r^2   (geometric-mean variance over r^2:
                       dimensionless, so one weight serves a 5 cm can and a 50 cm box)
                       "paper":    det(P_{t+D})
    c_v  view          "reachable": sum over the horizon of e_k^2, e_k = excess of the bearing
                       b_k = wrap(atan2(o - p_k) - theta_k) beyond the reachable field of view
                       [yaw_min - hfov/2, yaw_max + hfov/2] (0 inside): at t + D alone, a plan could
                       turn the robot round through the object behind its back (one-wall world 502)
                       "paper":    b^2 at t + D (the paper's theta_o read as the robot heading)
    c_r  coverage      "corrected": 1 - N_v / N_0;   "paper": N_v / N_0 (minimizing it avoids coverage)
                       N_v: bins seen over the executed path and the horizon (:mod:`agent.coverage`)
    c_d  distance      "standoff": ((d - d_min) / d_min)^2;   "paper": d_min / d,   d = |o - p_{t+D}|
    c_h  vertical view (not in the paper): mean over the horizon of e_k^2, the angle (rad) by which the
                       object's vertical extent, base z = 0 to top H, misses the vertical field of view
                       reachable with the head pitch limits at the head yaw used (pitch_by_yaw). With the
                       camera at height h_c and distance d_k from the centre (pitch and angles positive down):
                       base depression a_b = atan2(h_c, d_k - r) (near edge), top a_t = atan2(h_c - H, d_k + r)
                       (far edge), m a margin, vfov/2 = h_v, [p_lo, p_hi] the pitch limits at yaw_k:
                       e_k = max(0, a_b + m - p_hi - h_v) + max(0, p_lo - h_v - a_t + m)
                             + max(0, a_b - a_t + 2 m - 2 h_v)
                       (base below the reachable view, top above it, extent taller than the view). It
                       pushes the orbit out when the head is turned far (small p_hi) or, walking
                       omnidirectionally, turns the body toward the object (small yaw, larger p_hi).
    c_m  landmarks     (not in the paper): mean over the horizon of max(0, N - n_k)^2, n_k the soft count
                       of the map's landmarks the head can turn the camera to from the robot's pose k
                       (:mod:`agent.landmark_reach`: within the reach, large enough to detect), N
                       ``landmarks_needed``: the robot keeps where the lookout finds landmarks (a wall
                       of markers is not left straight behind it). Zero in a room marked all round.
    c_clear            hard clearance: W_clear sum_k max(0, r + clearance + m_k - |o - p_k|)^2 over the
                       horizon, W_clear = 1e6, so any sequence keeping the clearance beats any that
                       breaks it, and when none can, the least violating one wins. m_k is the
                       uncertainty margin: k sigma of the distance to the surface s = |o - p| - r,
                       m_k = min(k sqrt(g_k^T P g_k), m_max), g_k = ds/d(o, r) = (u_k, -1),
                       u_k = (o - p_k) / |o - p_k| (current P: where the true object may be now).
    c_wall             hard keep-in (given a :class:`agent.keep_in.KeepIn`): W_clear sum_k sum_j
                       max(0, m_wall - s_j(p_k))^2, s_j the distance in front of wall j, m_wall
                       ``wall_clearance``: the robot keeps off the walls the landmark map shows.

Optimizers (same cost, warm-started with the previous solution shifted by one step):

* ``nelder_mead``: scipy.optimize.minimize(method="Nelder-Mead"), one candidate per call, as the paper.
* ``cem``: the cross-entropy method vectorized over K candidate sequences per iteration (one batched
  rollout each): sample w = clip(m + s * (B z)), z ~ N(0, I) on a few knots and B their linear
  interpolation over the D steps (smooth perturbations: fewer samples explore long horizons), keep
  the E best, refit m, s; the batch also holds m itself and the best so far.
  The first batch also holds the warm start and the constant-turn sequences, so circling in either
  direction is always considered. Then a polish: scipy's truncated Newton (TNC, bounds +-omega_max)
  from the CEM's best for a few iterates, each iterate's cost and forward-difference gradient
  g_i = (c(w) - c(w - h e_i)) / h costed in one batch of D + 1 candidates (h = 1e-6 rad/s); kept
  only if it lowers the cost. CEM finds the basin, the polish its floor (where Nelder-Mead ends).

Termination: coverage N_v/N_0 >= target and position and radius standard deviations below their
thresholds ("complete"), or the elapsed time beyond the limit ("time_limit").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Dict, Literal, Optional, Tuple

import numpy as np
from scipy.optimize import minimize

from agent.camera import CameraModel
from agent.coverage import Coverage, CoverageParams, seen_count
from agent.ekf import EKFParams, position_std, rollout_covariance
from agent.keep_in import KeepIn, reachable_bins
from agent.landmark_reach import LandmarkReach
from agent.motion import camera_poses, object_in_view, rollout_poses
from nao_core.config import CONFIG_DIR, bounds, load
from nao_core.geometry import wrap_angle
from nao_core.robot_model import RobotModel, WalkLimits

CLEARANCE_WEIGHT = 1e6
REACH_SLACK = 0.05  # m beyond the object clearance a bin's view must leave: the clearance margin of a converged estimate
FD_STEP = 1e-6  # rad/s, finite-difference step of the polish's gradient


@dataclass(frozen=True)
class Weights:
    """lambda_l, lambda_v, lambda_r, lambda_d, lambda_h, lambda_m and mu of the cost."""

    uncertainty: float = field(metadata=bounds(0.0, 1e9))
    view: float = field(metadata=bounds(0.0, 1e9))
    coverage: float = field(metadata=bounds(0.0, 1e9))
    distance: float = field(metadata=bounds(0.0, 1e9))
    vertical: float = field(metadata=bounds(0.0, 1e9))  # lambda_h
    landmarks: float = field(metadata=bounds(0.0, 1e9))  # lambda_m
    effort: float = field(metadata=bounds(0.0, 1e9))


@dataclass(frozen=True)
class CEMParams:
    """Cross-entropy method: candidates per iteration, elites kept, iterations, initial and floor std (rad/s);
    then a gradient polish of at most ``polish_calls`` batched calls (0: none)."""

    samples: int = field(metadata=bounds(4, 100000))
    elites: int = field(metadata=bounds(1, 100000))
    iterations: int = field(metadata=bounds(1, 1000))
    initial_std: float = field(metadata=bounds(1e-4, 10.0))
    min_std: float = field(metadata=bounds(0.0, 10.0))
    knots: int = field(metadata=bounds(2, 1000))  # perturbations are linear between this many knots
    polish_calls: int = field(metadata=bounds(0, 1000))  # batched cost+gradient calls of the final TNC polish

    def __post_init__(self) -> None:
        if self.elites >= self.samples:
            raise ValueError(f"cem.elites ({self.elites}) must be fewer than cem.samples ({self.samples})")


@dataclass(frozen=True)
class TerminationParams:
    """Stop when coverage >= coverage and the position/radius std are below the thresholds, or after time_limit s.

    The coverage for termination counts bins within the facing angle minus ``facing_margin`` (rad).
    With walls hiding part of the object, of the bins they leave reachable (``Planner.reachable_bins``),
    and those count as covered once no new one was seen for ``stall`` s (station/pilot.py).
    """

    coverage: float = field(metadata=bounds(0.0, 1.0))
    facing_margin: float = field(metadata=bounds(0.0, 1.0))
    stall: float = field(metadata=bounds(1.0, 1e4))  # s without a new reachable bin, walls hiding some, that ends the coverage
    position_std: float = field(metadata=bounds(0.0, 10.0))
    radius_std: float = field(metadata=bounds(0.0, 10.0))
    time_limit: float = field(metadata=bounds(0.0, 1e6))


@dataclass(frozen=True)
class PlannerParams:
    """config/planner.yaml, section ``planner`` (SI units)."""

    speed: float = field(metadata=bounds(0.0, 1.0))  # v, m/s
    period: float = field(metadata=bounds(0.01, 10.0))  # tau, s
    horizon: int = field(metadata=bounds(1, 200))  # D steps
    d_min: float = field(metadata=bounds(0.05, 20.0))  # comfortable distance to the centre, m
    clearance: float = field(metadata=bounds(0.0, 10.0))  # never closer to the estimated surface, m
    clearance_sigmas: float = field(metadata=bounds(0.0, 100.0))  # k: margin of k sigma of the surface distance
    clearance_margin_max: float = field(metadata=bounds(0.0, 10.0))  # m_max: the margin's cap, m
    wall_clearance: float = field(metadata=bounds(0.0, 10.0))  # m_wall: the robot's centre keeps this far off a wall, m
    omnidirectional: bool  # also choose a lateral speed v_y per plan (unicycle when false)
    max_range: float = field(metadata=bounds(0.1, 100.0))  # the object is measurable up to this distance, m
    uncertainty_form: Literal["relative", "paper"]
    view_form: Literal["reachable", "paper"]
    coverage_form: Literal["corrected", "paper"]
    distance_form: Literal["standoff", "paper"]
    weights: Weights
    vertical_margin: float = field(metadata=bounds(0.0, 0.5))  # m of c_h: rad kept between the object and the image border
    object_height: float = field(metadata=bounds(0.01, 5.0))  # H assumed until the silhouettes bound the top, m
    landmarks_needed: float = field(metadata=bounds(0.0, 100.0))  # N of c_m: landmarks the head should be able to turn to
    coverage: CoverageParams
    optimizer: Literal["cem", "nelder_mead"]
    cem: CEMParams
    termination: TerminationParams


def load_planner_params(files=()) -> PlannerParams:
    """The ``planner`` section of config/planner.yaml merged with override ``files``."""
    return load(PlannerParams, [CONFIG_DIR / "planner.yaml", *files], section="planner")


# --- cost terms --------------------------------------------------------------------------------


def uncertainty_cost(P: np.ndarray, radius: float, form: str = "relative") -> np.ndarray:
    """c_l of covariances (..., 3, 3): det(P)^(1/3) / r^2 ("relative") or det(P) ("paper")."""
    det = np.linalg.det(P)
    if form == "paper":
        return det
    return np.cbrt(np.maximum(det, 0.0)) / radius**2


def view_cost(bearing: np.ndarray, reach: Tuple[float, float], form: str = "reachable") -> np.ndarray:
    """c_v of the object's bearings (..., D) from the robot heading over the horizon: b_D^2 ("paper") or
    the sum of the squared excesses beyond reach."""
    if form == "paper":
        return np.square(bearing[..., -1])
    excess = np.maximum(bearing - reach[1], 0.0) + np.maximum(reach[0] - bearing, 0.0)
    return np.sum(np.square(excess), axis=-1)


def coverage_cost(n_seen: np.ndarray, n_bins: int, form: str = "corrected") -> np.ndarray:
    """c_r: 1 - N_v / N_0 ("corrected") or N_v / N_0 ("paper")."""
    fraction = np.asarray(n_seen, dtype=float) / n_bins
    return fraction if form == "paper" else 1.0 - fraction


def distance_cost(d: np.ndarray, d_min: float, form: str = "standoff") -> np.ndarray:
    """c_d: ((d - d_min) / d_min)^2 ("standoff") or d_min / d ("paper")."""
    d = np.asarray(d, dtype=float)
    return d_min / d if form == "paper" else np.square((d - d_min) / d_min)


@dataclass(frozen=True)
class VerticalView:
    """What c_h needs of the robot: camera height h_c (m), vfov/2 h_v (rad), the pitch_by_yaw table."""

    camera_height: float
    half_vfov: float
    pitch_by_yaw: np.ndarray  # rows (yaw, pitch_min, pitch_max), rad

    @classmethod
    def for_robot(cls, robot: RobotModel, resolution: str) -> "VerticalView":
        camera = CameraModel.from_intrinsics(robot.camera.intrinsics(resolution))
        half_vfov = math.atan2(camera.height / 2.0, float(camera.K[1, 1]))
        return cls(robot.neck_height + robot.camera.offset[2], half_vfov, np.asarray(robot.head.pitch_by_yaw, dtype=float))


def vertical_view_cost(
    distance: np.ndarray, yaw: np.ndarray, radius: float, height: float, view: VerticalView, margin: float
) -> np.ndarray:
    """c_h: mean over the horizon (last axis) of e_k^2 for camera-to-centre distances and head yaws (..., D)."""
    table = view.pitch_by_yaw
    p_lo, p_hi = np.interp(yaw, table[:, 0], table[:, 1]), np.interp(yaw, table[:, 0], table[:, 2])
    h_c, h_v = view.camera_height, view.half_vfov
    base = np.arctan2(h_c, np.maximum(distance - radius, 1e-3))
    top = np.arctan2(h_c - height, distance + radius)
    excess = (
        np.maximum(base + margin - p_hi - h_v, 0.0)
        + np.maximum(p_lo - h_v - top + margin, 0.0)
        + np.maximum(base - top + 2.0 * margin - 2.0 * h_v, 0.0)
    )
    return np.mean(np.square(excess), axis=-1)


def landmark_cost(counts: np.ndarray, needed: float) -> np.ndarray:
    """c_m: mean over the horizon (last axis) of max(0, N - n_k)^2 of the landmarks' soft counts."""
    return np.mean(np.square(np.maximum(needed - counts, 0.0)), axis=-1)


def effort_cost(omegas: np.ndarray) -> np.ndarray:
    """|w|^2 = sum_k omega_k^2 over the horizon (last axis)."""
    return np.sum(np.square(omegas), axis=-1)


def clearance_margin(
    positions: np.ndarray, x: np.ndarray, P: np.ndarray, sigmas: float, cap: float
) -> np.ndarray:
    """m = min(k sqrt(g^T P g), m_max) for robot positions (..., 2), g = (u, -1), u the unit vector to o."""
    dx, dy = x[0] - positions[..., 0], x[1] - positions[..., 1]
    d = np.maximum(np.hypot(dx, dy), 1e-9)
    ux, uy = dx / d, dy / d
    variance = (
        ux * ux * P[0, 0] + 2.0 * ux * uy * P[0, 1] + uy * uy * P[1, 1] - 2.0 * (ux * P[0, 2] + uy * P[1, 2]) + P[2, 2]
    )
    return np.minimum(sigmas * np.sqrt(np.maximum(variance, 0.0)), cap)


def clearance_cost(distances: np.ndarray, radius: float, clearance: float, margin=0.0) -> np.ndarray:
    """W_clear sum_k max(0, r + clearance + m_k - d_k)^2 over the horizon (last axis)."""
    return CLEARANCE_WEIGHT * np.sum(np.square(np.maximum(radius + clearance + margin - distances, 0.0)), axis=-1)


def wall_cost(distances: np.ndarray, wall_clearance: float) -> np.ndarray:
    """W_clear sum_k sum_j max(0, m_wall - s_jk)^2 of distances (K, D, J) in front of the walls."""
    return CLEARANCE_WEIGHT * np.sum(np.square(np.maximum(wall_clearance - distances, 0.0)), axis=(-2, -1))


# --- planner ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plan:
    """One replan: the chosen sequence, the command to send now, the cost and its weighted terms."""

    omegas: np.ndarray  # (D,) rad/s
    command: Tuple[float, float, float]  # (v, vy, omega) within the walk limits
    cost: float
    terms: Dict[str, float]  # weighted: uncertainty, view, coverage, distance, effort, vertical, landmarks, clearance, wall
    evaluations: int  # candidate sequences whose cost was computed
    lateral_speed: float = 0.0  # v_y over the horizon, m/s (0 unless omnidirectional)
    clearance_margin: float = 0.0  # the uncertainty margin m at the robot's next position, m


def termination_reason(
    coverage_fraction: float, P: np.ndarray, elapsed: float, params: TerminationParams
) -> Optional[str]:
    """Why the mission is over ("complete: ...", "time_limit: ..."), or None to go on."""
    centre_std = position_std(P)
    radius_std = math.sqrt(max(P[2, 2], 0.0))
    if coverage_fraction >= params.coverage and centre_std <= params.position_std and radius_std <= params.radius_std:
        return (
            f"complete: coverage {coverage_fraction:.2f}, position std {1000 * centre_std:.1f} mm, "
            f"radius std {1000 * radius_std:.1f} mm"
        )
    if elapsed >= params.time_limit:
        return f"time_limit: {elapsed:.0f} s elapsed (limit {params.time_limit:.0f} s)"
    return None


class Planner:
    """Receding-horizon controller: call :meth:`plan` once per control period."""

    def __init__(
        self,
        params: PlannerParams,
        walk_limits: WalkLimits,
        camera_hfov: float,
        head_yaw_limits: Tuple[float, float],
        camera_offset: float = 0.0,
        ekf: Optional[EKFParams] = None,
        seed: int = 0,
        vertical_view: Optional[VerticalView] = None,
    ):
        if params.speed > walk_limits.v_max:
            raise ValueError(f"planner.speed {params.speed} m/s exceeds the robot's v_max {walk_limits.v_max} m/s")
        if not 0.0 < camera_hfov < math.pi:
            raise ValueError(f"camera_hfov must be in (0, pi) rad, got {camera_hfov}")
        self.params = params
        self.walk_limits = walk_limits
        self.hfov = camera_hfov
        self.head_yaw_limits = (float(head_yaw_limits[0]), float(head_yaw_limits[1]))
        self.camera_offset = camera_offset
        self.vertical_view = vertical_view  # None: c_h is not evaluated (no robot geometry given)
        self.reach = (self.head_yaw_limits[0] - 0.5 * camera_hfov, self.head_yaw_limits[1] + 0.5 * camera_hfov)
        self._R = None if ekf is None else ekf.R
        self._Q_step = None if ekf is None else ekf.Q(params.period)
        self._rng = np.random.default_rng(seed)
        self._previous: Optional[np.ndarray] = None
        # bounds of the decision w = (omega_1 .. omega_D[, v_y])
        self._limits = np.full(params.horizon, walk_limits.omega_max)
        if params.omnidirectional:
            self._limits = np.append(self._limits, walk_limits.vy_max)

    @classmethod
    def for_robot(
        cls, params: PlannerParams, robot: RobotModel, resolution: str, ekf: Optional[EKFParams] = None, seed: int = 0
    ) -> "Planner":
        """A planner with the walk limits, field of view, head yaw limits and camera offset of ``robot``."""
        hfov = CameraModel.from_intrinsics(robot.camera.intrinsics(resolution)).hfov
        vertical = VerticalView.for_robot(robot, resolution)
        return cls(params, robot.walk, hfov, robot.head.yaw, robot.camera.offset[0], ekf, seed, vertical)

    @property
    def omega_max(self) -> float:
        return self.walk_limits.omega_max

    def reset(self) -> None:
        """Forget the warm start (a new mission)."""
        self._previous = None

    def cost_function(
        self, robot_pose: np.ndarray, x: np.ndarray, P: np.ndarray, seen: np.ndarray, height: Optional[float] = None,
        keep_in: Optional[KeepIn] = None, landmarks: Optional[LandmarkReach] = None,
    ) -> Callable[[np.ndarray], Tuple[np.ndarray, Dict[str, np.ndarray]]]:
        """The batched cost of decisions (K, D[+1]) -> (total (K,), weighted terms) for this replan's belief;
        ``keep_in``: the walls to keep off, ``landmarks``: the map's landmarks for c_m (robot_pose in the
        landmark map's frame)."""
        p, w = self.params, self.params.weights
        target = x[:2]
        height = p.object_height if height is None else height
        walls = None if keep_in is None else keep_in.walls(x)

        def evaluate(decisions: np.ndarray) -> Tuple[np.ndarray, Dict[str, np.ndarray]]:
            omegas, lateral = self._split(decisions)
            poses = rollout_poses(robot_pose, omegas, p.speed, p.period, lateral[:, None])  # (K, D, 3)
            cams = camera_poses(poses, target, self.head_yaw_limits, self.camera_offset)
            visible = object_in_view(x, cams, self.hfov, p.max_range)
            P_end = rollout_covariance(x, P, cams, visible, self._Q_step, R=self._R)
            dist = np.hypot(target[0] - poses[..., 0], target[1] - poses[..., 1])  # (K, D)
            bearing = wrap_angle(np.arctan2(target[1] - poses[..., 1], target[0] - poses[..., 0]) - poses[..., 2])  # (K, D)
            n_seen = seen_count(x, cams, seen, p.coverage, self.hfov)
            terms = {
                "uncertainty": w.uncertainty * uncertainty_cost(P_end, x[2], p.uncertainty_form),
                "view": w.view * view_cost(bearing, self.reach, p.view_form),
                "coverage": w.coverage * coverage_cost(n_seen, p.coverage.bins, p.coverage_form),
                "distance": w.distance * distance_cost(dist[:, -1], p.d_min, p.distance_form),
                "effort": w.effort * effort_cost(omegas),
                "vertical": self._vertical(poses, cams, x, height),
                "landmarks": (np.zeros(len(poses)) if landmarks is None or w.landmarks == 0.0
                              else w.landmarks * landmark_cost(landmarks.counts(poses, self.reach), p.landmarks_needed)),
                "clearance": clearance_cost(
                    dist, x[2], p.clearance, clearance_margin(poses, x, P, p.clearance_sigmas, p.clearance_margin_max)
                ),
                "wall": (np.zeros(len(poses)) if walls is None
                         else wall_cost(keep_in.distances(poses[..., :2], walls), p.wall_clearance)),
            }
            return sum(terms.values()), terms

        return evaluate

    def _vertical(self, poses: np.ndarray, cams: np.ndarray, x: np.ndarray, height: float) -> np.ndarray:
        """l_h c_h of the predicted robot and camera poses (K, D, 3); zeros without the robot's geometry."""
        if self.vertical_view is None or self.params.weights.vertical == 0.0:
            return np.zeros(len(poses))
        distance = np.hypot(x[0] - cams[..., 0], x[1] - cams[..., 1])
        yaw = wrap_angle(cams[..., 2] - poses[..., 2])
        cost = vertical_view_cost(distance, yaw, float(x[2]), height, self.vertical_view, self.params.vertical_margin)
        return self.params.weights.vertical * cost

    def plan(self, robot_pose, x, P, coverage: Coverage, object_height: Optional[float] = None,
             keep_in: Optional[KeepIn] = None, landmarks: Optional[LandmarkReach] = None) -> Plan:
        """Choose the next D angular velocities (and v_y) for the robot at ``robot_pose`` and the belief (x, P).

        ``object_height``: the object's top above the floor, m, when the silhouettes bound it (else the
        configured ``object_height``). ``keep_in``: the walls to keep off (c_wall), ``landmarks``: the
        map's landmarks (c_m), the pose in their frame."""
        robot_pose = _checked("robot_pose", robot_pose, (3,))
        x = _checked("x", x, (3,))
        P = _checked("P", P, (3, 3))
        if x[2] <= 0.0:
            raise ValueError(f"x: object radius must be positive, got {x[2]}")
        if object_height is not None and not (math.isfinite(object_height) and object_height > 0.0):
            raise ValueError(f"object_height: expected a positive height in m, got {object_height}")
        evaluate = self.cost_function(robot_pose, x, P, coverage.seen(x), object_height, keep_in, landmarks)
        optimize = self._cem if self.params.optimizer == "cem" else self._nelder_mead
        best, evaluations = optimize(evaluate, self._warm_start())
        total, terms = evaluate(best[None])
        self._previous = best
        omegas, lateral = self._split(best[None])
        v, vy, omega = self.walk_limits.clamp(self.params.speed, float(lateral[0]), float(omegas[0, 0]))
        first = rollout_poses(robot_pose, omegas[:, :1], v, self.params.period, vy)[0, 0]
        p = self.params
        return Plan(
            omegas=omegas[0],
            command=(v, vy, omega),
            cost=float(total[0]),
            terms={k: float(t[0]) for k, t in terms.items()},
            evaluations=evaluations,
            lateral_speed=vy,
            clearance_margin=float(clearance_margin(first, x, P, p.clearance_sigmas, p.clearance_margin_max)),
        )

    def reachable_bins(self, x: np.ndarray, keep_in: KeepIn) -> np.ndarray:
        """Coverage bins (N0,) of the estimate x seen from where the walk can go and turn back: off the
        object's surface by clearance + ``REACH_SLACK`` and off the walls by wall_clearance plus the
        turn radius v / omega_max, within the termination's facing margin (agent/keep_in.py)."""
        p = self.params
        return reachable_bins(keep_in, x, p.coverage, p.clearance + REACH_SLACK, p.wall_clearance + p.speed / self.omega_max,
                              p.termination.facing_margin)

    def _split(self, decisions: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Decisions (K, D[+1]) -> omegas (K, D) and lateral speeds (K,)."""
        D = self.params.horizon
        lateral = decisions[:, D] if self.params.omnidirectional else np.zeros(len(decisions))
        return decisions[:, :D], lateral

    def _warm_start(self) -> np.ndarray:
        if self._previous is None or self._previous.shape != self._limits.shape:
            return np.zeros_like(self._limits)
        D = self.params.horizon
        return np.concatenate([self._previous[1:D], self._previous[D - 1 :]])  # shifted, last omega repeated

    def _cem(self, evaluate, warm: np.ndarray) -> Tuple[np.ndarray, int]:
        c, D, limits = self.params.cem, self.params.horizon, self._limits
        knots = np.linspace(0.0, D - 1.0, min(D, c.knots))
        basis = np.stack([np.interp(np.arange(D), knots, row) for row in np.eye(len(knots))])  # (knots, D)
        if self.params.omnidirectional:  # v_y: one more independent coordinate
            basis = np.block([[basis, np.zeros((len(knots), 1))], [np.zeros((1, D)), np.ones((1, 1))]])
        scale = limits / self.omega_max  # std in the units of each coordinate
        turns = np.zeros((5, len(limits)))
        turns[:, :D] = np.linspace(-self.omega_max, self.omega_max, 5)[:, None]
        mean, std = warm.copy(), c.initial_std * scale
        best, best_cost, evaluations = warm, math.inf, 0
        for iteration in range(c.iterations):
            noise = self._rng.standard_normal((c.samples, len(basis))) @ basis  # smooth in time
            samples = np.clip(mean + std * noise, -limits, limits)
            samples[0] = mean
            if iteration == 0:
                samples[1 : 1 + len(turns)] = turns
            else:
                samples[1] = best
            costs, _ = evaluate(samples)
            evaluations += len(samples)
            order = np.argsort(costs)
            if costs[order[0]] < best_cost:
                best, best_cost = samples[order[0]].copy(), costs[order[0]]
            elites = samples[order[: c.elites]]
            mean, std = elites.mean(axis=0), np.maximum(elites.std(axis=0), c.min_std * scale)
        if c.polish_calls == 0:
            return best, evaluations
        return self._polish(evaluate, best, best_cost, evaluations)

    def _polish(self, evaluate, best: np.ndarray, best_cost: float, evaluations: int) -> Tuple[np.ndarray, int]:
        """Polish the CEM's ``best`` with scipy's truncated Newton (TNC, within the bounds), each iterate's
        cost and forward-difference gradient costed in one batch of len(w) + 1 candidates."""
        limits, n = self._limits, len(best)
        probes = FD_STEP * np.vstack([np.zeros(n), -np.eye(n)])
        calls = 0

        def cost_and_gradient(w: np.ndarray) -> Tuple[float, np.ndarray]:
            nonlocal calls
            calls += 1
            costs, _ = evaluate(np.clip(w, -limits, limits) + probes)
            return float(costs[0]), (costs[0] - costs[1:]) / FD_STEP

        result = minimize(
            cost_and_gradient,
            best,
            jac=True,
            method="TNC",
            bounds=list(zip(-limits, limits)),
            options={"maxfun": self.params.cem.polish_calls},
        )
        evaluations += calls * (n + 1)
        return (np.clip(result.x, -limits, limits), evaluations) if result.fun < best_cost else (best, evaluations)

    def _nelder_mead(self, evaluate, warm: np.ndarray) -> Tuple[np.ndarray, int]:
        limits = self._limits
        step = 0.25 * limits * np.where(warm > 0.0, -1.0, 1.0)  # initial simplex edges pointing inward
        simplex = np.vstack([warm, warm + np.diag(step)])
        result = minimize(
            lambda w: float(evaluate(np.asarray(w)[None])[0][0]),
            warm,
            method="Nelder-Mead",
            bounds=list(zip(-limits, limits)),
            options={"initial_simplex": simplex},
        )
        return np.clip(result.x, -limits, limits), int(result.nfev)


def _checked(name: str, value, shape: Tuple[int, ...]) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        array = np.full(1, np.nan)
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: expected finite numbers of shape {shape}, got {np.asarray(value).tolist()!r}")
    return array
