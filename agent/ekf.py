"""Extended Kalman filter on an unknown vertical cylinder: centre (xo, yo) and radius r on the floor.

State and camera (world frame W, SI units)::

    x = (xo, yo, r),   cam = (cx, cy, psi)      cam: camera centre on the floor, optical-axis heading

Measurement (docs/estimation.md; the paper's slip is kept behind ``width_model``)::

    dx = xo - cx,  dy = yo - cy,  d = sqrt(dx^2 + dy^2)
    phi   = wrap(atan2(dy, dx) - psi)           bearing of the centre
    delta = 2 asin(r / d)  ("asin")   or   atan(r / d)  ("paper_atan")

Analytic Jacobian H = dh/dx (rows phi, delta)::

    dphi/d(xo, yo, r)   = (-dy / d^2,  dx / d^2,  0)
    asin:  ddelta/d(xo, yo, r) = (-2 r dx, -2 r dy, 2 d^2) / (d^2 sqrt(d^2 - r^2))
    atan:  ddelta/d(xo, yo, r) = (-r dx / d, -r dy / d, d) / (d^2 + r^2)

The camera pose is an estimate too: with its covariance C (3x3, of (cx, cy, psi)) a view's noise is

    R = diag(sigma_phi^2, sigma_delta^2) + Hc C Hc^T,   Hc = dh/dcam = (-H[:, 0], -H[:, 1], (-1, 0))

(dh/d(cx, cy) = -dh/d(xo, yo); the bearing is measured from psi). A view from a pose known to a
few centimetres weighs less, and is gated and restarts the estimate less readily, than one taken
just after a landmark fix (docs/estimation.md, "Pose uncertainty").

Prediction: x- = x, P- = P + Q dt, Q = diag(q_x^2, q_y^2, q_r^2) (the object is static).

Two parametrisations of the same estimate, each a small immutable state class
(docs/estimation.md, "Initialization"):

* :class:`InverseRangeState`, from a first view with a width, anchored at that camera a::

      y = (beta, rho, s):   x(y) = (ax + cos(beta) / rho, ay + sin(beta) / rho, s / rho)
      h(y, cam) = h(u, origin),   u = (rho (ax - cx) + cos beta, rho (ay - cy) + sin beta, s)

  (h is homogeneous of degree 0 in (xo - cx, yo - cy, r)); published as x(y), J P_y J^T, and
  Q mapped by J^-1, J = dx/dy. Once std(rho) < inverse_range_switch * rho it becomes a
* :class:`CartesianState` on (x, P) directly (also the start from a bearing-only first view).

A view from (nearly) the anchor holds no range: its baseline subtends alpha = rho |a - c| at the
object, and a bearing biased by eps (a shape that is not a cylinder, a silhouette cut at the top)
moves rho by about eps / |a - c|, the same way from every frame of a standing robot. Below
``min_parallax`` the view's update leaves rho alone (a Schmidt, or consider, update: the gain's
rho row is zero; its innovation covariance still holds rho's variance, and the Joseph form is
exact for that gain); beta and s are updated as usual.

The start's floor contact (docs/estimation.md, "Floor contact"): with the object's base in view,
the silhouette's lowest row meets the floor at the base's point nearest the camera along its
optical axis, seen from the camera's height h under the depression theta below the horizontal::

    p = (xo, yo) - r (cos psi, sin psi),  v = p - (cx, cy),  theta = atan2(h, |v|)
    dtheta/dx = g (v_x / |v|, v_y / |v|, -(cos psi v_x + sin psi v_y) / |v|),  g = -h / (h^2 + |v|^2)
    R = floor_angle_std^2 + (g floor_shape_std r)^2

fused into the first view's state only (through x(y) and J on inverse range), which stays on
inverse range until a view with parallax: the floor fixes the range a radius prior leaves 100 %
uncertain, and views without parallax still leave rho alone.

One pure update for both, :func:`iterated_update` (IEKF, Gauss-Newton on the MAP cost)::

    H_i = H(m_i),  r_i = wrap(z - h(m_i)) - H_i (m- - m_i),  S_i = H_i P- H_i^T + R,
    K_i = P- H_i^T S_i^-1 (rows of considered components zeroed),  m_i+1 = m- + K_i r_i,
    NIS = r_i^T S_i^-1 r_i (last i),  P+ = (I - K H) P- (I - K H)^T + K R K^T  (Joseph)

accepted iff NIS <= chi2.ppf(gate_probability, dof).

View-dependent width (objects that are not cylinders: a box, a mug, a figure). The width noise is
R_dd = sigma_delta^2 + c2 delta^2, with the relative width variability c2 estimated online from
the width innovations nu_d of views whose bearing is consistent::

    v = (nu_d^2 - (H P H^T)_dd - sigma_delta^2) / delta^2,   w = delta^4 / (2 S_dd^2)  (1 / Var v under c2 = 0)
    c2 = max(0, sum(l^k w v) / sum(l^k w) - k_sig / sqrt(sum(l^k w))),   l = 1 - 1 / width_shape_window

(v clipped at width_shape_max^2): only a significant excess inflates it, so a cylinder keeps
c2 = 0. A view whose width fails the gate but whose bearing passes updates the bearing alone.

Restart only on proportionate evidence: a view whose bearing is inconsistent with the estimate
starts (or extends) an alternative hypothesis filtered from those views alone; an alternative
that gates one of them restarts from it. The estimate is replaced by the alternative when it has
been consistent over n_restart views in a row, with n the views fused since the last start::

    n_restart = clip(ceil(reinitialize_fraction * n), reinitialize_after, reinitialize_max)

and when those views have located it: its centre's largest std is at most inverse_range_switch
times its range from the camera (the filter's own test for leaving inverse range). Views without
parallax (the robot turning in place) fix a bearing, not a range, and never restart.

Expected covariance for the planner: K candidate camera sequences of D steps rolled forward with
noise-free observations at the mean (zero innovation: only the covariance evolves)::

    P_k,j = P_k,j-1 + Q_step;   if visible[k, j]: P_k,j -= K S K^T with H(x, cam_k,j)

in closed form on float64 scalars in a numba-compiled loop (:func:`rollout_covariance`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from numbers import Real
from pathlib import Path
from typing import Callable, Literal, Optional, Sequence, Tuple, Union

import numpy as np
from numba import njit
from scipy.special import chdtri  # inverse chi-square survival: chi2.ppf(p, k) = chdtri(k, 1 - p)

from nao_core.config import CONFIG_DIR, bounds, load
from nao_core.geometry import wrap_angle

WidthModel = Literal["asin", "paper_atan"]

# The nominal measurement noise of the spec (0.5 deg, 0.3 deg), the defaults of config/ekf.yaml
# (a test keeps the two equal). Used by rollout_covariance when the caller passes no R.
NOMINAL_R = np.diag([math.radians(0.5), math.radians(0.3)]) ** 2


@dataclass(frozen=True)
class EKFParams:
    """Noise, priors and gate of the object filter (config/ekf.yaml, section ``ekf``)."""

    sigma_phi: float = field(metadata=bounds(1e-6, 0.5))  # bearing noise std, rad
    sigma_delta: float = field(metadata=bounds(1e-6, 0.5))  # width noise std, rad
    process_noise: Tuple[float, float, float] = field(metadata=bounds(0.0, 1.0))  # std per sqrt(s) of xo, yo, r
    radius_prior: float = field(metadata=bounds(1e-3, 10.0))  # m
    radius_prior_std: float = field(metadata=bounds(1e-4, 10.0))  # m
    default_range: float = field(metadata=bounds(0.05, 100.0))  # m, bearing-only first observation
    default_range_std: float = field(metadata=bounds(1e-3, 100.0))  # m
    gate_probability: float = field(metadata=bounds(0.5, 1.0 - 1e-12))
    min_radius: float = field(metadata=bounds(0.0, 10.0))  # m
    iterations: int = field(metadata=bounds(1, 50))  # Gauss-Newton steps per update; 1 = plain EKF
    inverse_range_switch: float = field(metadata=bounds(0.0, 1.0))  # rho std / rho below which x, P take over
    min_parallax: float = field(metadata=bounds(0.0, 1.0))  # rad, a view's baseline to the anchor below which rho is kept
    reinitialize_after: int = field(metadata=bounds(1, 100000))  # fewest consistent-alternative views that restart
    reinitialize_fraction: float = field(metadata=bounds(0.0, 10.0))  # restart views per view fused since the start
    reinitialize_max: int = field(metadata=bounds(1, 100000))  # most views a restart ever needs
    width_shape_window: float = field(metadata=bounds(1.0, 1e6))  # views: forgetting of the width-variability estimate
    width_shape_significance: float = field(metadata=bounds(0.0, 100.0))  # sigmas of excess before inflating
    width_shape_max: float = field(metadata=bounds(0.0, 10.0))  # largest relative width std c
    floor_angle_std: float = field(metadata=bounds(1e-6, 0.5))  # rad, depression of the base's floor contact
    floor_shape_std: float = field(metadata=bounds(0.0, 2.0))  # the contact's distance std from the shape, times r
    width_model: WidthModel

    def __post_init__(self) -> None:
        if self.reinitialize_max < self.reinitialize_after:
            raise ValueError(f"reinitialize_max ({self.reinitialize_max}) must be >= reinitialize_after ({self.reinitialize_after})")

    @property
    def R(self) -> np.ndarray:
        """Nominal measurement noise covariance of (phi, delta)."""
        return np.diag([self.sigma_phi, self.sigma_delta]) ** 2

    def Q(self, dt: float) -> np.ndarray:
        """Process noise accumulated over ``dt`` seconds."""
        return np.diag(np.square(self.process_noise)) * dt


def load_ekf_params(files: Sequence[Union[str, Path]] = ()) -> EKFParams:
    """The ``ekf`` section of config/ekf.yaml merged with override ``files``."""
    return load(EKFParams, [CONFIG_DIR / "ekf.yaml", *files], section="ekf")


@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one observation. ``nis``/``innovation`` are None when the input was invalid."""

    accepted: bool
    nis: Optional[float]
    dof: int  # components fused (1 when only the bearing was)
    innovation: Optional[np.ndarray]
    reason: str  # "ok", or why the observation was rejected or only partly used


@dataclass
class FilterStats:
    """Counters the station logs: observations accepted, rejected by the gate, rejected as invalid,
    rejections since the last accepted one, widths gated while the bearing was fused, restarts."""

    accepted: int = 0
    gated: int = 0
    invalid: int = 0
    rejected_in_a_row: int = 0
    width_gated: int = 0
    reinitialized: int = 0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def position_std(P: np.ndarray) -> float:
    """Largest standard deviation of the estimated centre (xo, yo): sqrt of the largest eigenvalue of P[:2, :2], m."""
    return math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(P)[:2, :2])[-1]), 0.0))


def _geometry(x: np.ndarray, cams: np.ndarray) -> Tuple[np.ndarray, ...]:
    """(dx, dy, d^2, r, psi) of states and cameras, broadcast against each other."""
    x = np.asarray(x, dtype=float)
    cams = np.asarray(cams, dtype=float)
    dx = x[..., 0] - cams[..., 0]
    dy = x[..., 1] - cams[..., 1]
    return dx, dy, dx * dx + dy * dy, x[..., 2], cams[..., 2]


def measure(x: np.ndarray, cams: np.ndarray, width_model: WidthModel = "asin") -> np.ndarray:
    """Predicted (phi, delta) of state ``x`` (3,) or (..., 3) from cameras ``cams`` (..., 3) -> (..., 2).

    A camera inside the cylinder (d <= r) sees it fill half the world: delta saturates at pi (asin).
    """
    dx, dy, d2, r, psi = _geometry(x, cams)
    out = np.empty(np.broadcast_shapes(dx.shape, r.shape) + (2,))
    out[..., 0] = wrap_angle(np.arctan2(dy, dx) - psi)
    d = np.sqrt(d2)
    if width_model == "asin":
        out[..., 1] = 2.0 * np.arcsin(np.clip(r / np.maximum(d, 1e-12), 0.0, 1.0))
    else:
        out[..., 1] = np.arctan2(r, d)
    return out


def measurement_jacobian(x: np.ndarray, cams: np.ndarray, width_model: WidthModel = "asin") -> np.ndarray:
    """H = d(phi, delta)/d(xo, yo, r) for state ``x`` and cameras ``cams`` (..., 3) -> (..., 2, 3).

    Inside the cylinder (d <= r) the asin width row is not defined, at its centre (d = 0) neither is
    the bearing row; they are set to zero there.
    """
    dx, dy, d2, r, _ = _geometry(x, cams)
    H = np.zeros(np.broadcast_shapes(dx.shape, r.shape) + (2, 3))
    bearing_d2 = np.where(d2 > 0.0, d2, np.inf)  # a camera at the centre: no bearing row
    H[..., 0, 0] = -dy / bearing_d2
    H[..., 0, 1] = dx / bearing_d2
    if width_model == "asin":
        slack = d2 - r * r
        outside = slack > 0.0
        scale = np.where(outside, 2.0 / np.where(outside, d2 * np.sqrt(np.maximum(slack, 0.0)), 1.0), 0.0)
        H[..., 1, 0] = -r * dx * scale
        H[..., 1, 1] = -r * dy * scale
        H[..., 1, 2] = d2 * scale
    else:
        scale = 1.0 / (d2 + r * r)
        H[..., 1, 0] = -r * dx * scale / np.sqrt(bearing_d2)
        H[..., 1, 1] = -r * dy * scale / np.sqrt(bearing_d2)
        H[..., 1, 2] = np.sqrt(d2) * scale
    return H


def pose_noise(x: np.ndarray, cam: np.ndarray, cam_cov: np.ndarray, width_model: WidthModel = "asin") -> np.ndarray:
    """Hc C Hc^T: the (phi, delta) covariance a camera pose covariance ``cam_cov`` (3x3) adds (module docstring)."""
    H = measurement_jacobian(x, cam, width_model)
    Hc = np.column_stack([-H[:, 0], -H[:, 1], [-1.0, 0.0]])
    return Hc @ np.asarray(cam_cov, dtype=float) @ Hc.T


@dataclass(frozen=True)
class FloorContact:
    """Where the silhouette's lowest row meets the floor (agent/clearance.py), seen from a camera
    ``height`` m above the floor: that ray's ``depression`` below the horizontal, rad."""

    depression: float
    height: float

    @property
    def distance(self) -> float:
        """m: where that ray meets the floor, horizontally from the camera (h / tan(depression))."""
        return self.height / math.tan(self.depression)

    def valid(self) -> bool:
        return math.isfinite(self.depression) and 0.0 < self.depression < 0.5 * math.pi and math.isfinite(self.height) and self.height > 0.0


def floor_depression(x: np.ndarray, cam: np.ndarray, height: float) -> Tuple[float, np.ndarray]:
    """Predicted depression of the floor contact of state ``x`` seen from ``cam``, and d/dx (module docstring)."""
    c, s = math.cos(cam[2]), math.sin(cam[2])
    v = np.array([x[0] - x[2] * c - cam[0], x[1] - x[2] * s - cam[1]])
    d = max(math.hypot(*v), 1e-9)
    g = -height / (height * height + d * d)  # d theta / d |v|
    return math.atan2(height, d), g * np.array([v[0] / d, v[1] / d, -(c * v[0] + s * v[1]) / d])


def _inverse_spd(S: np.ndarray) -> np.ndarray:
    """Closed-form inverse of (..., 1, 1) or (..., 2, 2) innovation covariances."""
    if S.shape[-1] == 1:
        return 1.0 / S
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    inv = np.empty_like(S)
    inv[..., 0, 0] = S[..., 1, 1]
    inv[..., 1, 1] = S[..., 0, 0]
    inv[..., 0, 1] = -S[..., 0, 1]
    inv[..., 1, 0] = -S[..., 1, 0]
    return inv / det[..., None, None]


def rollout_covariance(
    x: np.ndarray,
    P: np.ndarray,
    cams: np.ndarray,
    visible: Optional[np.ndarray] = None,
    Q_step: Optional[np.ndarray] = None,
    *,
    R: Optional[np.ndarray] = None,
    width_model: WidthModel = "asin",
) -> np.ndarray:
    """Covariance after rolling the filter along each of K camera sequences ``cams`` (K, D, 3) -> (K, 3, 3).

    Each step adds ``Q_step`` (3x3, default none) and, where ``visible[k, j]`` (K, D bool, default
    all) and the camera is outside the estimated cylinder, applies a noise-free update at the
    mean ``x`` with measurement noise ``R`` (2x2, default :data:`NOMINAL_R`; pass ``params.R``).
    ``P`` is (3, 3) or one per candidate (K, 3, 3).

    Closed form in a compiled loop (numba) on float64 scalars, no matrix calls: with the rows
    a = H[0] (a_r = 0), b = H[1], u = P a, w = P b, S = [[a.u, a.w], [a.w, b.w]] + R,
    P - K S K^T = P - (S11 u u^T - S01 (u w^T + w u^T) + S00 w w^T) / det S.
    """
    x = np.asarray(x, dtype=float)
    cams = np.asarray(cams, dtype=float)
    if cams.ndim != 3 or cams.shape[-1] != 3:
        raise ValueError(f"cams must have shape (K, D, 3), got {cams.shape}")
    n_cand, n_steps = cams.shape[:2]
    R = NOMINAL_R if R is None else np.asarray(R, dtype=float)
    Q_step = np.zeros((3, 3)) if Q_step is None else np.asarray(Q_step, dtype=float)
    mask = np.ones((n_cand, n_steps), dtype=bool) if visible is None else np.asarray(visible, dtype=bool)
    if mask.shape != (n_cand, n_steps):
        raise ValueError(f"visible must have shape {(n_cand, n_steps)}, got {mask.shape}")
    _, _, d2, r, _ = _geometry(x, cams)
    mask = mask & (d2 > r * r)
    H = np.where(mask[..., None, None], measurement_jacobian(x, cams, width_model), 0.0)  # zero rows: no update
    P = np.broadcast_to(np.asarray(P, dtype=float), (n_cand, 3, 3))
    return _rollout_kernel(np.ascontiguousarray(0.5 * (P + P.swapaxes(-1, -2))), np.ascontiguousarray(H),
                           np.ascontiguousarray(Q_step), np.ascontiguousarray(R))


# typed: compiled (or loaded from the cache) at import, not in the mission's first replan (300-650 ms)
@njit("float64[:, :, ::1](float64[:, :, ::1], float64[:, :, :, ::1], float64[:, ::1], float64[:, ::1])", cache=True)
def _rollout_kernel(P0: np.ndarray, H: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The loop of :func:`rollout_covariance` on scalars: P0 (K, 3, 3), H (K, D, 2, 3) -> (K, 3, 3)."""
    n_cand, n_steps = H.shape[0], H.shape[1]
    out = np.empty((n_cand, 3, 3))
    for k in range(n_cand):
        p00, p01, p02, p11, p12, p22 = P0[k, 0, 0], P0[k, 0, 1], P0[k, 0, 2], P0[k, 1, 1], P0[k, 1, 2], P0[k, 2, 2]
        for j in range(n_steps):
            p00 += Q[0, 0]
            p01 += Q[0, 1]
            p02 += Q[0, 2]
            p11 += Q[1, 1]
            p12 += Q[1, 2]
            p22 += Q[2, 2]
            a0, a1 = H[k, j, 0, 0], H[k, j, 0, 1]
            b0, b1, b2 = H[k, j, 1, 0], H[k, j, 1, 1], H[k, j, 1, 2]
            u0 = p00 * a0 + p01 * a1
            u1 = p01 * a0 + p11 * a1
            u2 = p02 * a0 + p12 * a1
            w0 = p00 * b0 + p01 * b1 + p02 * b2
            w1 = p01 * b0 + p11 * b1 + p12 * b2
            w2 = p02 * b0 + p12 * b1 + p22 * b2
            s00 = a0 * u0 + a1 * u1 + R[0, 0]
            s01 = a0 * w0 + a1 * w1 + R[0, 1]
            s11 = b0 * w0 + b1 * w1 + b2 * w2 + R[1, 1]
            scale = 1.0 / (s00 * s11 - s01 * s01)
            cu, cx, cw = s11 * scale, -s01 * scale, s00 * scale  # P -= cu u u^T + cx (u w^T + w u^T) + cw w w^T
            p00 -= cu * u0 * u0 + 2.0 * cx * u0 * w0 + cw * w0 * w0
            p01 -= cu * u0 * u1 + cx * (u0 * w1 + w0 * u1) + cw * w0 * w1
            p02 -= cu * u0 * u2 + cx * (u0 * w2 + w0 * u2) + cw * w0 * w2
            p11 -= cu * u1 * u1 + 2.0 * cx * u1 * w1 + cw * w1 * w1
            p12 -= cu * u1 * u2 + cx * (u1 * w2 + w1 * u2) + cw * w1 * w2
            p22 -= cu * u2 * u2 + 2.0 * cx * u2 * w2 + cw * w2 * w2
        out[k, 0, 0], out[k, 1, 1], out[k, 2, 2] = p00, p11, p22
        out[k, 0, 1] = out[k, 1, 0] = p01
        out[k, 0, 2] = out[k, 2, 0] = p02
        out[k, 1, 2] = out[k, 2, 1] = p12
    return out


# The two parametrisations -----------------------------------------------------------------------


def _outside(x: np.ndarray, cam: np.ndarray) -> bool:
    return math.hypot(x[0] - cam[0], x[1] - cam[1]) > x[2]


@dataclass(frozen=True)
class CartesianState:
    """Mean x = (xo, yo, r) and covariance P, the filter's state once the range is known."""

    mean: np.ndarray
    cov: np.ndarray

    def cartesian(self) -> Tuple[np.ndarray, np.ndarray]:
        return self.mean, self.cov

    @staticmethod
    def point(m: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """x(m) = m and dx/dm = I."""
        return m, np.eye(3)

    def model(self, m: np.ndarray, cam: np.ndarray, dof: int, width_model: WidthModel) -> Tuple[np.ndarray, np.ndarray]:
        """h(m, cam) and dh/dm, the first ``dof`` rows."""
        return measure(m, cam, width_model)[:dof], measurement_jacobian(m, cam, width_model)[:dof]

    def valid(self, m: np.ndarray, cam: np.ndarray) -> bool:
        return _outside(m, cam)

    def considered(self, cam: np.ndarray, params: EKFParams) -> Optional[np.ndarray]:
        """Components this view must not update: none, once the range is known."""
        return None

    def predicted(self, Q: np.ndarray) -> "CartesianState":
        return CartesianState(self.mean, self.cov + Q)

    def updated(self, m: np.ndarray, cov: np.ndarray, params: EKFParams, parallax: bool) -> "CartesianState":
        """The posterior, with the radius projected onto r >= min_radius."""
        m = m.copy()
        m[2] = max(m[2], params.min_radius)
        return CartesianState(m, cov)


@dataclass(frozen=True)
class InverseRangeState:
    """Mean y = (beta, rho, s) and covariance P_y anchored at the first camera a = (ax, ay)."""

    anchor: np.ndarray
    mean: np.ndarray
    cov: np.ndarray

    def point(self, m: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """x(m) and J = d(xo, yo, r) / d(beta, rho, s) at m."""
        beta, rho, size = m
        c, s = math.cos(beta), math.sin(beta)
        x = np.array([self.anchor[0] + c / rho, self.anchor[1] + s / rho, size / rho])
        return x, np.array([[-s / rho, -c / rho**2, 0.0], [c / rho, -s / rho**2, 0.0], [0.0, -size / rho**2, 1.0 / rho]])

    def cartesian(self) -> Tuple[np.ndarray, np.ndarray]:
        """x(y) and J P_y J^T (first order)."""
        x, J = self.point(self.mean)
        return x, J @ self.cov @ J.T

    def model(self, m: np.ndarray, cam: np.ndarray, dof: int, width_model: WidthModel) -> Tuple[np.ndarray, np.ndarray]:
        """h and dh/dy through u = (rho (ax - cx) + cos beta, rho (ay - cy) + sin beta, s) seen from the origin."""
        beta, rho, size = m
        offset = self.anchor - cam[:2]
        u = np.array([rho * offset[0] + math.cos(beta), rho * offset[1] + math.sin(beta), size])
        du_dy = np.array([[-math.sin(beta), offset[0], 0.0], [math.cos(beta), offset[1], 0.0], [0.0, 0.0, 1.0]])
        origin = np.array([0.0, 0.0, cam[2]])
        return measure(u, origin, width_model)[:dof], measurement_jacobian(u, origin, width_model)[:dof] @ du_dy

    def valid(self, m: np.ndarray, cam: np.ndarray) -> bool:
        """In front of the anchor at a finite range, a size in (0, 1), the camera outside the object."""
        beta, rho, size = m
        return rho > 0.0 and 0.0 < size < 1.0 and math.hypot(*(rho * (self.anchor - cam[:2]) + (math.cos(beta), math.sin(beta)))) > size

    def considered(self, cam: np.ndarray, params: EKFParams) -> Optional[np.ndarray]:
        """rho, when the view's baseline to the anchor subtends less than ``min_parallax`` (module docstring)."""
        if self.mean[1] * math.hypot(*(self.anchor - cam[:2])) < params.min_parallax:
            return np.array([False, True, False])
        return None

    def predicted(self, Q: np.ndarray) -> "InverseRangeState":
        J_inv = np.linalg.inv(self.point(self.mean)[1])
        return InverseRangeState(self.anchor, self.mean, self.cov + J_inv @ Q @ J_inv.T)

    def updated(self, m: np.ndarray, cov: np.ndarray, params: EKFParams, parallax: bool) -> Union["InverseRangeState", CartesianState]:
        """The posterior; on (x, P) once std(rho) < inverse_range_switch * rho after a view with
        ``parallax`` (one that updated rho: a floor contact alone does not end the considered updates)."""
        state = InverseRangeState(self.anchor, m, cov)
        if parallax and math.sqrt(cov[1, 1]) < params.inverse_range_switch * m[1]:
            return CartesianState(*state.cartesian())
        return state


State = Union[CartesianState, InverseRangeState]


def initial_state(params: EKFParams, cam: Sequence[float], phi: float, delta: Optional[float],
                  floor: Optional[FloorContact] = None) -> State:
    """The state from a first view (docs/estimation.md, "Initialization"); inputs already validated.

    With a width: inverse range, y0 = (psi + phi, s / r0, s), P_y0 = G diag(s_phi^2, s_delta^2,
    s_r0^2) G^T, G = dy0 / d(phi, delta, r0). Without: Cartesian, range ~ N(default_range, std^2).
    A ``floor`` contact is then fused into it (:func:`_with_floor`); when it fails the gate there
    and the view has a width, the start is made from the width and the contact, the prior fused
    after them (:func:`_floor_start`), unless the prior gates that one too.
    """
    cx, cy, psi = (float(v) for v in cam)
    heading = psi + phi
    p = params
    if delta is None:
        c, s = math.cos(heading), math.sin(heading)
        rng = p.default_range
        G = np.array([[-rng * s, c, 0.0], [rng * c, s, 0.0], [0.0, 0.0, 1.0]])  # d(xo, yo, r) / d(phi, range, r0)
        x = np.array([cx + rng * c, cy + rng * s, p.radius_prior])
        state: State = CartesianState(x, G @ np.diag([p.sigma_phi, p.default_range_std, p.radius_prior_std]) ** 2 @ G.T)
    else:
        if p.width_model == "asin":
            size, d_size = math.sin(0.5 * delta), 0.5 * math.cos(0.5 * delta)
        else:
            size, d_size = math.tan(delta), 1.0 / math.cos(delta) ** 2
        rho = size / p.radius_prior
        G = np.array([[1.0, 0.0, 0.0], [0.0, d_size / p.radius_prior, -rho / p.radius_prior], [0.0, d_size, 0.0]])
        P_y = G @ np.diag([p.sigma_phi, p.sigma_delta, p.radius_prior_std]) ** 2 @ G.T
        state = InverseRangeState(np.array([cx, cy]), np.array([heading, rho, size]), P_y)
    if floor is None:
        return state
    camera = np.array([cx, cy, psi])
    fused = _with_floor(state, camera, floor, params)
    if fused is state and delta is not None:
        return _floor_start(p, camera, phi, size, d_size, floor) or state
    return fused


def _contact_variance(floor: FloorContact, params: EKFParams, radius: float) -> float:
    """R of a floor contact's depression for an object of ``radius`` (docs/estimation.md, "Floor
    contact"): floor_angle_std^2 + (h / (h^2 + d_f^2) floor_shape_std r)^2, d_f = h / tan(theta)."""
    slope = floor.height / (floor.height**2 + floor.distance**2)
    return params.floor_angle_std**2 + (slope * params.floor_shape_std * radius) ** 2


def _floor_start(params: EKFParams, cam: np.ndarray, phi: float, size: float, d_size: float,
                 floor: FloorContact) -> Optional[State]:
    """The start from a width and its floor contact (docs/estimation.md, "Floor contact"), the radius
    prior then fused as a measurement of r = s / rho; None when the prior gates that radius. Taken
    when the contact fails the gate against the prior's start (``initial_state``).

    The contact p = (xo, yo) - r (cos psi, sin psi) lies at |p - c| = d k, k = sqrt(1 - 2 s cos phi
    + s^2), and at h / tan(theta) from the camera, so::

        y0 = (psi + phi, k tan(theta) / h, s),  P_y0 = G diag(s_phi^2, s_delta^2, R_theta) G^T,
        G = dy0 / d(phi, delta, theta),  R_theta: ``_contact_variance`` at r = s / rho.

    From the prior, the range is Gaussian in rho = s / r0 with a 100 % std, and a thin object's true
    rho lies in its tail: a 2 cm radius at 1 m is 4 std out, the contact fails the gate and the
    start was metres off. The prior, Gaussian in r, holds a 2 cm radius at 0.8 std. (Not the first
    choice: for a large near object the contact's shape term is wide, the prior the better start.)
    """
    h, theta = floor.height, floor.depression
    t, k = math.tan(theta), math.sqrt(1.0 - 2.0 * size * math.cos(phi) + size**2)
    rho = k * t / h
    R_theta = _contact_variance(floor, params, size / rho)
    G = np.array([[1.0, 0.0, 0.0],
                  [t / h * size * math.sin(phi) / k, t / h * (size - math.cos(phi)) / k * d_size, k / (h * math.cos(theta) ** 2)],
                  [0.0, d_size, 0.0]])
    P = G @ np.diag([params.sigma_phi**2, params.sigma_delta**2, R_theta]) @ G.T
    state = InverseRangeState(cam[:2].copy(), np.array([cam[2] + phi, rho, size]), P)
    if not state.valid(state.mean, cam):
        return None

    def radius(m: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        return np.array([m[2] / m[1]]), np.array([[0.0, -m[2] / m[1] ** 2, 1.0 / m[1]]])

    step = iterated_update(state.mean, state.cov, np.array([params.radius_prior]), np.array([[params.radius_prior_std**2]]),
                           radius, lambda m: state.valid(m, cam), params.iterations)
    if step is None or step.nis > chdtri(1, 1.0 - params.gate_probability):
        return None
    return state.updated(step.mean, step.cov, params, parallax=False)


def _with_floor(state: State, cam: np.ndarray, floor: FloorContact, params: EKFParams) -> State:
    """``state`` updated by the depression of its floor contact (docs/estimation.md, "Floor contact"),
    with R = floor_angle_std^2 + (|d theta / d d| floor_shape_std r)^2, r the radius the contact and
    the state's angular size give; ``state`` itself when the contact fails the gate."""
    x = state.cartesian()[0]
    size = x[2] / math.hypot(x[0] - cam[0], x[1] - cam[1])
    R = np.array([[_contact_variance(floor, params, size * floor.distance / (1.0 - size))]])

    def model(m: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        point, J = state.point(m)
        theta, d_theta = floor_depression(point, cam, floor.height)
        return np.array([theta]), (d_theta @ J)[None, :]

    step = iterated_update(state.mean, state.cov, np.array([floor.depression]), R, model, lambda m: state.valid(m, cam), params.iterations)
    if step is None or step.nis > chdtri(1, 1.0 - params.gate_probability):
        return state
    return state.updated(step.mean, step.cov, params, parallax=False)


# The update ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class IteratedStep:
    """Result of :func:`iterated_update`: posterior mean and covariance, and the gated statistic."""

    mean: np.ndarray
    cov: np.ndarray
    nis: float


def _wrapped(nu: np.ndarray) -> np.ndarray:
    nu = nu.copy()
    nu[0] = wrap_angle(nu[0])
    return nu


def iterated_update(
    mean: np.ndarray,
    cov: np.ndarray,
    z: np.ndarray,
    R: np.ndarray,
    model: Callable[[np.ndarray], Tuple[np.ndarray, np.ndarray]],
    valid: Callable[[np.ndarray], bool],
    iterations: int,
    considered: Optional[np.ndarray] = None,
) -> Optional[IteratedStep]:
    """Iterated EKF update of (mean, cov) by z (bearing first, wrapped) with noise R (module docstring).

    ``model(m)`` gives (h(m), dh/dm); an iterate that is not finite or not ``valid`` stops the
    iteration at the last good one. None when even the first is not, or the posterior is degenerate.
    The components where ``considered`` is True are not updated (their gain rows are zero).
    """
    step = None
    m_lin = mean
    for _ in range(iterations):
        h, H = model(m_lin)
        residual = _wrapped(z - h) - H @ (mean - m_lin)
        S_inv = _inverse_spd(H @ cov @ H.T + R)
        gain = cov @ H.T @ S_inv
        if considered is not None:
            gain[considered] = 0.0
        m_next = mean + gain @ residual
        if not (np.all(np.isfinite(m_next)) and valid(m_next)):
            break
        step = (m_next, H, gain, float(residual @ S_inv @ residual))
        if np.max(np.abs(m_next - m_lin)) < 1e-9:  # converged
            break
        m_lin = m_next
    if step is None:
        return None
    m, H, gain, nis = step
    A = np.eye(len(mean)) - gain @ H
    post = A @ cov @ A.T + gain @ R @ gain.T
    if not (math.isfinite(nis) and np.all(np.isfinite(post))):
        return None
    return IteratedStep(m, 0.5 * (post + post.T), nis)


@dataclass
class WidthVariability:
    """Online estimate of c2, the relative variance of the apparent width that the cylinder does
    not explain (module docstring): forgetting sums of w and w v."""

    params: EKFParams
    weight: float = 0.0
    weighted: float = 0.0

    @property
    def c2(self) -> float:
        if self.weight <= 0.0:
            return 0.0
        return max(0.0, self.weighted / self.weight - self.params.width_shape_significance / math.sqrt(self.weight))

    def add(self, nu_width: float, predicted_var: float, delta: float) -> None:
        """One width innovation nu_width with its predicted variance (H P H^T)_dd + sigma_delta^2."""
        if delta <= 0.0 or predicted_var <= 0.0:
            return
        v = min((nu_width**2 - predicted_var) / delta**2, self.params.width_shape_max**2)
        w = delta**4 / (2.0 * predicted_var**2)
        keep = 1.0 - 1.0 / self.params.width_shape_window
        self.weight = keep * self.weight + w
        self.weighted = keep * self.weighted + w * v


class ObjectEKF:
    """The object filter. ``x`` (3,) and ``P`` (3, 3) are None until :meth:`initialize` succeeds."""

    def __init__(self, params: EKFParams):
        self.params = params
        self.stats = FilterStats()
        self.width = WidthVariability(params)
        self._state: Optional[State] = None
        self._alternative: Optional[State] = None  # filtered from the current streak of inconsistent views
        self._streak = 0  # views in a row the alternative explains and the estimate does not
        self._fused = 0  # views fused since the last (re)start
        self._bearing_start: Optional[np.ndarray] = None  # the camera of a start without a width, until a view brings one
        self._gate = {dof: float(chdtri(dof, 1.0 - params.gate_probability)) for dof in (1, 2)}
        self._max_width = math.pi if params.width_model == "asin" else 0.5 * math.pi

    @classmethod
    def from_estimate(cls, params: EKFParams, x: np.ndarray, P: np.ndarray) -> "ObjectEKF":
        """A filter already running on the Cartesian estimate (x, P), as one fused view."""
        ekf = cls(params)
        ekf._state = CartesianState(np.array(x, dtype=float), np.array(P, dtype=float))
        ekf._fused = 1
        return ekf

    @property
    def initialized(self) -> bool:
        return self._state is not None

    @property
    def x(self) -> Optional[np.ndarray]:
        return None if self._state is None else self._state.cartesian()[0]

    @property
    def P(self) -> Optional[np.ndarray]:
        return None if self._state is None else self._state.cartesian()[1]

    @property
    def restart_views(self) -> int:
        """Consecutive consistent-alternative views that would restart the estimate now."""
        p = self.params
        return int(min(max(math.ceil(p.reinitialize_fraction * self._fused), p.reinitialize_after), p.reinitialize_max))

    def gate(self, dof: int) -> float:
        """NIS threshold for a measurement with ``dof`` components."""
        return self._gate[dof]

    def copy(self) -> "ObjectEKF":
        other = copy.copy(self)  # the states are immutable; params, gate thresholds shared
        other.stats = dataclasses.replace(self.stats)
        other.width = dataclasses.replace(self.width)
        return other

    def snapshot(self) -> dict:
        """Plain-Python state for logs: estimate, covariance, counters."""
        return {
            "x": None if self.x is None else self.x.tolist(),
            "P": None if self.P is None else self.P.tolist(),
            "stats": self.stats.as_dict(),
        }

    def _invalid(self, cam: Sequence[float], phi: float, delta: Optional[float], floor: Optional[FloorContact] = None) -> Optional[str]:
        try:
            cam_ok = np.shape(cam) == (3,) and bool(np.all(np.isfinite(np.asarray(cam, dtype=float))))
        except (TypeError, ValueError):
            cam_ok = False
        if not cam_ok:
            return f"camera pose must be 3 finite numbers (cx, cy, psi), got {cam!r}"
        if not (isinstance(phi, Real) and math.isfinite(phi)):
            return f"bearing must be a finite number, got {phi!r}"
        if delta is not None and not (isinstance(delta, Real) and math.isfinite(delta) and 0.0 < delta < self._max_width):
            return f"width must be finite and in (0, {self._max_width:.4f}) rad, got {delta!r}"
        if floor is not None and not (isinstance(floor, FloorContact) and floor.valid()):
            return f"floor contact must have a depression in (0, pi/2) rad and a height > 0 m, got {floor!r}"
        return None

    @staticmethod
    def _invalid_covariance(cam_cov: Optional[np.ndarray]) -> Optional[str]:
        if cam_cov is None:
            return None
        try:
            C = np.asarray(cam_cov, dtype=float)
        except (TypeError, ValueError):
            C = None
        if C is None or C.shape != (3, 3) or not np.all(np.isfinite(C)) or np.any(np.linalg.eigvalsh(0.5 * (C + C.T)) < -1e-12):
            return f"camera pose covariance must be a finite positive semi-definite 3 x 3 matrix, got {cam_cov!r}"
        return None

    def _reject_invalid(self, reason: str, dof: int) -> UpdateResult:
        self.stats.invalid += 1
        self.stats.rejected_in_a_row += 1
        return UpdateResult(False, None, dof, None, reason)

    def initialize(self, cam: Sequence[float], phi: float, delta: Optional[float] = None,
                   floor: Optional[FloorContact] = None) -> UpdateResult:
        """Set the estimate from a first observation (:func:`initial_state`); replaces any previous one."""
        dof = 1 if delta is None else 2
        reason = self._invalid(cam, phi, delta, floor)
        if reason is not None:
            return self._reject_invalid(reason, dof)
        self._state = initial_state(self.params, cam, phi, delta, floor)
        self._alternative, self._streak, self._fused = None, 0, 1
        self._bearing_start = np.asarray(cam, dtype=float) if delta is None else None
        self.stats.accepted += 1
        return UpdateResult(True, None, dof, None, "initialized")

    def predict(self, dt: float) -> None:
        """Add the process noise of ``dt`` seconds (the object is static)."""
        if not (math.isfinite(dt) and dt >= 0.0):
            raise ValueError(f"predict: dt must be finite and >= 0 s, got {dt!r}")
        if self._state is not None:
            self._state = self._state.predicted(self.params.Q(dt))

    def _fuse(self, state: State, cam: np.ndarray, z: np.ndarray, R: np.ndarray) -> Optional[IteratedStep]:
        dof = len(z)
        width_model = self.params.width_model
        return iterated_update(
            state.mean, state.cov, z, R, lambda m: state.model(m, cam, dof, width_model), lambda m: state.valid(m, cam), self.params.iterations,
            state.considered(cam, self.params),
        )

    def update(self, cam: Sequence[float], phi: float, delta: Optional[float] = None,
               cam_cov: Optional[np.ndarray] = None, floor: Optional[FloorContact] = None) -> UpdateResult:
        """Fuse one observation (bearing-only when ``delta`` is None); gated, never leaves a NaN.

        ``cam_cov``: covariance of the camera pose (cx, cy, psi), added to the noise through Hc
        (module docstring); None for a pose taken as exact. A filter started without a width
        restarts from the first view with one, with that view's ``floor`` contact, while no baseline
        has observed the range (docs/estimation.md, "A start without a width").
        """
        dof = 1 if delta is None else 2
        if self._state is None:
            return self._reject_invalid("filter not initialized", dof)
        reason = self._invalid(cam, phi, delta) or self._invalid_covariance(cam_cov)
        if reason is not None:
            return self._reject_invalid(reason, dof)
        cam = np.asarray(cam, dtype=float)
        state = self._state
        x = state.cartesian()[0]
        if delta is not None and self._bearing_start is not None:
            start = self._bearing_start
            if math.hypot(*(cam[:2] - start[:2])) < self.params.min_parallax * math.hypot(*(x[:2] - start[:2])):
                result = self.initialize(cam, phi, delta, floor)
                return result if not result.accepted else dataclasses.replace(result, reason="restarted from the first view with a width")
            self._bearing_start = None  # a baseline has observed the range since
        if not _outside(x, cam):
            return self._reject_invalid("camera inside the estimated object (d <= r)", dof)
        z = np.array([phi, 0.0 if delta is None else delta])[:dof]
        h, H = state.model(state.mean, cam, dof, self.params.width_model)
        nu = _wrapped(z - h)
        R = self.params.R.copy()
        if cam_cov is not None:
            R += pose_noise(x, cam, cam_cov, self.params.width_model)
        R = R[:dof, :dof]
        predicted = H @ state.cov @ H.T + R
        bearing_ok = nu[0] ** 2 <= self._gate[1] * predicted[0, 0]
        if dof == 2:
            if bearing_ok:
                self.width.add(float(nu[1]), float(predicted[1, 1]), float(h[1]))
            R[1, 1] += self.width.c2 * h[1] ** 2
        step = self._fuse(state, cam, z, R)
        note = "ok"
        if dof == 2 and (step is None or step.nis > self._gate[2]) and bearing_ok:
            step = self._fuse(state, cam, z[:1], R[:1, :1])  # the width disagrees, the bearing does not
            note = f"width inconsistent with the estimate (innovation {nu[1]:.4f} rad): bearing only"
            dof = 1
        if step is None:
            return self._inconsistent(cam, z, R, None, nu, "update would put the camera inside the object or is degenerate")
        if step.nis > self._gate[dof]:
            return self._inconsistent(cam, z, R, step.nis, nu, f"NIS {step.nis:.1f} above gate {self._gate[dof]:.1f}")
        self._state = state.updated(step.mean, step.cov, self.params, state.considered(cam, self.params) is None)
        self._alternative, self._streak = None, 0
        self._fused += 1
        self.stats.accepted += 1
        self.stats.width_gated += note != "ok"
        self.stats.rejected_in_a_row = 0
        return UpdateResult(True, step.nis, dof, nu, note)

    def _located(self, state: State, cam: np.ndarray) -> bool:
        """The centre's largest std is at most ``inverse_range_switch`` times its range from ``cam``."""
        x, P = state.cartesian()
        return position_std(P) <= self.params.inverse_range_switch * math.hypot(x[0] - cam[0], x[1] - cam[1])

    def _inconsistent(
        self, cam: np.ndarray, z: np.ndarray, R: np.ndarray, nis: Optional[float], nu: np.ndarray, reason: str
    ) -> UpdateResult:
        """A valid view the estimate cannot explain: it extends the alternative hypothesis (or starts
        a new one if the alternative cannot explain it either); once the alternative has explained
        ``restart_views`` in a row and is located (:meth:`_located`), it replaces the estimate."""
        if nis is None:
            self.stats.invalid += 1
        else:
            self.stats.gated += 1
        step = None if self._alternative is None else self._fuse(self._alternative, cam, z, R)
        if step is not None and step.nis <= self._gate[len(z)]:
            self._alternative = self._alternative.updated(step.mean, step.cov, self.params,
                                                          self._alternative.considered(cam, self.params) is None)
            self._streak += 1
        else:
            self._alternative = initial_state(self.params, cam, float(z[0]), float(z[1]) if len(z) == 2 else None)
            self._streak = 1
        needed = self.restart_views
        if self._streak < needed or not self._located(self._alternative, cam):
            self.stats.rejected_in_a_row += 1
            return UpdateResult(False, nis, nu.size, nu if nis is not None else None, reason)
        self._state, self._alternative, self._bearing_start = self._alternative, None, None
        self._fused, self._streak = self._streak, 0
        self.stats.reinitialized += 1
        self.stats.rejected_in_a_row = 0
        return UpdateResult(
            True, nis, nu.size, nu,
            f"re-initialized after {needed} consecutive views inconsistent with the estimate and consistent with each other ({reason})",
        )
