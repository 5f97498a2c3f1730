"""Extended Kalman filter on an unknown vertical cylinder: centre (xo, yo) and radius r on the floor.

State and camera (world frame W, SI units)::

    x = (xo, yo, r),   cam = (cx, cy, psi)

``cam`` is the camera centre projected on the floor and the heading of its optical axis
(:func:`agent.camera.optical_axis_heading`) at the frame's capture time.

Measurement (DESIGN.md slip 1 corrected; the paper's form is kept behind ``width_model``)::

    dx = xo - cx,  dy = yo - cy,  d = sqrt(dx^2 + dy^2)
    phi   = wrap(atan2(dy, dx) - psi)                     bearing of the centre
    delta = 2 asin(r / d)           ("asin", exact: the angle between the two tangent planes)
    delta = atan(r / d)             ("paper_atan", as printed; with real widths r comes out ~2x)

Analytic Jacobian H = dh/dx (rows phi, delta)::

    dphi/d(xo, yo, r)   = (-dy / d^2,  dx / d^2,  0)
    asin:  ddelta/d(xo, yo, r) = (-2 r dx, -2 r dy, 2 d^2) / (d^2 sqrt(d^2 - r^2))
    atan:  ddelta/d(xo, yo, r) = (-r dx / d, -r dy / d, d) / (d^2 + r^2)

Prediction (the object is static; a random walk keeps the filter from overconfidence)::

    x- = x,   P- = P + Q dt,   Q = diag(q_x^2, q_y^2, q_r^2)

Update (Joseph form, wrapped bearing innovation, chi-square gate on the NIS)::

    nu = (wrap(phi_m - phi(x-)), delta_m - delta(x-)),   S = H P- H^T + R,   R = diag(s_phi^2, s_delta^2)
    NIS = nu^T S^-1 nu;  accept iff NIS <= chi2.ppf(gate_probability, dof)
    K = P- H^T S^-1,   x+ = x- + K nu,   P+ = (I - K H) P- (I - K H)^T + K R K^T

The update is iterated (IEKF, Gauss-Newton on the MAP cost; ``iterations`` = 1 is the plain EKF):
relinearize at the iterate x_i, H_i = H(x_i), K_i = P- H_i^T (H_i P- H_i^T + R)^-1,
x_i+1 = x- + K_i (z - h(x_i) - H_i (x- - x_i)), and P+ uses the last K_i, H_i. From the first
views the range is as uncertain as the radius prior (100 %), and a single linearization there
overshoots and can lock the gate out for good; a few iterations remove that (docs/estimation.md).
The gate tests the minimum of the MAP cost, which is the NIS of the last linearization,
r_i^T S_i^-1 r_i with r_i = z - h(x_i) - H_i (x- - x_i) and S_i = H_i P- H_i^T + R (the plain NIS
when iterations = 1): with a wide prior, the NIS linearized at the prior mean is inflated by the
curvature of h and would reject good first views of an object whose size differs from the prior.

Without a width (``delta is None``) only the bearing row is used (dof 1). An update whose camera
lies inside the estimated cylinder (d <= r), or whose inputs are not finite, is rejected with a
reason; the state never becomes NaN. After an update the radius is projected onto r >= min_radius.

Initialization from a first observation with a width, u = (phi, delta, r0), radius prior
r0 ~ N(radius_prior, radius_prior_std^2). One view fixes the bearing and the angular size
s = r / d = sin(delta/2) (asin; tan(delta) for paper_atan) but not the scale: the range is as
uncertain as the radius (100 % with the default prior). Gaussian in (xo, yo, r) such a prior puts
mass at r <= 0 and d <= 0, and the bearing parallax of the next views is hyperbolic in d: the
MAP then lands near the camera with r -> 0 or 1 to 3 m off with a centimetre covariance, and the
gate locks out (planner seeds 13, 23, 15, 35). So the filter starts in inverse-range coordinates
anchored at the first camera a = (ax, ay) (Civera, Davison, Montiel 2008)::

    y = (beta, rho, s):   x(y) = (ax + cos(beta) / rho, ay + sin(beta) / rho, s / rho)
    y0 = (psi + phi, s / r0, s),   P_y0 = G diag(s_phi^2, s_delta^2, s_r0^2) G^T,   G = dy0/du

(the radius prior propagated to first order to the inverse radius). h is homogeneous of degree 0
in (xo - cx, yo - cy, r), so with u = rho (xo - cx, yo - cy, r) = (rho (ax - cx) + cos beta,
rho (ay - cy) + sin beta, s), h(y) = h(u seen from the origin): smooth through rho = 0, near-linear
in rho, never r < 0. Updates run on y (the same iterated, gated update, valid iff rho > 0,
0 < s < 1 and the camera outside); x, P are published as x(y), J P_y J^T (J = dx/dy), and Q is
mapped by J^-1. Once std(rho) < inverse_range_switch * rho the filter continues on (x, P).
Without a width, u = (phi, d, r0) with d ~ N(default_range, default_range_std^2), independent of
r0, in (xo, yo, r) directly: x0 = (cx + d cos(psi + phi), cy + d sin(psi + phi), r0).

Lost estimate: a valid view that is gated, or whose update would leave the state's domain, is
inconsistent with the estimate; after ``reinitialize_after`` of them in a row the filter restarts
from the current view (``stats.reinitialized``, and the result's reason says why).

Expected covariance for the planner (DESIGN.md item 7): K candidate camera sequences of D steps are
rolled forward with synthesized noise-free observations at the predicted mean, so the innovation
is zero, the mean stays and only the covariance evolves::

    P_k,j = P_k,j-1 + Q_step;   if visible[k, j]: P_k,j -= K S K^T with H(x, cam_k,j)

(with the optimal gain this equals the filter's Joseph-form update; a test checks the two agree)

in closed form on float64 scalars in a numba-compiled loop (:func:`rollout_covariance`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from numbers import Real
from pathlib import Path
from typing import Literal, Optional, Sequence, Tuple, Union

import numpy as np
from numba import njit
from scipy.stats import chi2

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
    reinitialize_after: int = field(metadata=bounds(1, 100000))  # consecutive gated views that restart the filter
    width_model: WidthModel

    @property
    def R(self) -> np.ndarray:
        """Measurement noise covariance of (phi, delta)."""
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
    dof: int
    innovation: Optional[np.ndarray]
    reason: str  # "ok", or why the observation was rejected


@dataclass
class FilterStats:
    """Counters the station logs: observations accepted, rejected by the gate, rejected as invalid,
    rejections since the last accepted one, and restarts from a view after ``reinitialize_after``
    consecutive gated views (the estimate was lost)."""

    accepted: int = 0
    gated: int = 0
    invalid: int = 0
    rejected_in_a_row: int = 0
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
    return _rollout_kernel(np.ascontiguousarray(0.5 * (P + P.swapaxes(-1, -2))), np.ascontiguousarray(H), Q_step, R)


@njit(cache=True)
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


def _size_from_width(delta: float, width_model: WidthModel) -> Tuple[float, float]:
    """Angular size s = r / d implied by the width delta, and ds/ddelta."""
    if width_model == "asin":
        return math.sin(0.5 * delta), 0.5 * math.cos(0.5 * delta)
    return math.tan(delta), 1.0 / math.cos(delta) ** 2


class ObjectEKF:
    """The object filter. ``x`` (3,) and ``P`` (3, 3) are None until :meth:`initialize` succeeds."""

    def __init__(self, params: EKFParams):
        self.params = params
        self.x: Optional[np.ndarray] = None
        self.P: Optional[np.ndarray] = None
        self.stats = FilterStats()
        # Inverse-range state (beta, rho, s) and its covariance while the range is poorly known,
        # anchored at the first camera; None once the filter runs on x, P directly.
        self._anchor: Optional[np.ndarray] = None
        self._y: Optional[np.ndarray] = None
        self._Py: Optional[np.ndarray] = None
        self._lost_in_a_row = 0
        self._R = params.R
        self._gate = {dof: float(chi2.ppf(params.gate_probability, dof)) for dof in (1, 2)}
        self._max_width = math.pi if params.width_model == "asin" else 0.5 * math.pi

    @property
    def initialized(self) -> bool:
        return self.x is not None

    def gate(self, dof: int) -> float:
        """NIS threshold for a measurement with ``dof`` components."""
        return self._gate[dof]

    def copy(self) -> "ObjectEKF":
        other = copy.copy(self)  # shares the immutable params, R and gate thresholds
        other.x = None if self.x is None else self.x.copy()
        other.P = None if self.P is None else self.P.copy()
        other._y = None if self._y is None else self._y.copy()
        other._Py = None if self._Py is None else self._Py.copy()
        other.stats = dataclasses.replace(self.stats)
        return other

    def snapshot(self) -> dict:
        """Plain-Python state for logs: estimate, covariance, counters."""
        return {
            "x": None if self.x is None else self.x.tolist(),
            "P": None if self.P is None else self.P.tolist(),
            "stats": self.stats.as_dict(),
        }

    def _invalid(self, cam: Sequence[float], phi: float, delta: Optional[float]) -> Optional[str]:
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
        return None

    def _reject_invalid(self, reason: str, dof: int) -> UpdateResult:
        self.stats.invalid += 1
        self.stats.rejected_in_a_row += 1
        return UpdateResult(False, None, dof, None, reason)

    def initialize(self, cam: Sequence[float], phi: float, delta: Optional[float] = None) -> UpdateResult:
        """Set the estimate from a first observation (see the module docstring); replaces any previous one."""
        p = self.params
        dof = 1 if delta is None else 2
        reason = self._invalid(cam, phi, delta)
        if reason is not None:
            return self._reject_invalid(reason, dof)
        cx, cy, psi = (float(v) for v in cam)
        heading = psi + phi
        self._anchor = self._y = self._Py = None
        self._lost_in_a_row = 0
        if delta is None:
            c, s = math.cos(heading), math.sin(heading)
            rng = p.default_range
            # G = d(xo, yo, r) / d(phi, range, r0)
            G = np.array([[-rng * s, c, 0.0], [rng * c, s, 0.0], [0.0, 0.0, 1.0]])
            self.x = np.array([cx + rng * c, cy + rng * s, p.radius_prior])
            self.P = G @ np.diag([p.sigma_phi, p.default_range_std, p.radius_prior_std]) ** 2 @ G.T
        else:
            size, d_size = _size_from_width(delta, p.width_model)
            rho = size / p.radius_prior
            # G = d(beta, rho, s) / d(phi, delta, r0)
            G = np.array([[1.0, 0.0, 0.0], [0.0, d_size / p.radius_prior, -rho / p.radius_prior], [0.0, d_size, 0.0]])
            self._anchor = np.array([cx, cy])
            self._y = np.array([heading, rho, size])
            self._Py = G @ np.diag([p.sigma_phi, p.sigma_delta, p.radius_prior_std]) ** 2 @ G.T
            self._publish()
        self.stats.accepted += 1
        return UpdateResult(True, None, dof, None, "initialized")

    def predict(self, dt: float) -> None:
        """Add the process noise of ``dt`` seconds (the object is static)."""
        if not (math.isfinite(dt) and dt >= 0.0):
            raise ValueError(f"predict: dt must be finite and >= 0 s, got {dt!r}")
        if self._y is not None:
            J_inv = np.linalg.inv(self._cartesian_jacobian(self._y))
            self._Py = self._Py + J_inv @ self.params.Q(dt) @ J_inv.T
            self._publish()
        elif self.P is not None:
            self.P = self.P + self.params.Q(dt)

    def update(self, cam: Sequence[float], phi: float, delta: Optional[float] = None) -> UpdateResult:
        """Fuse one observation (bearing-only when ``delta`` is None); gated, never leaves a NaN."""
        dof = 1 if delta is None else 2
        if self.x is None or self.P is None:
            return self._reject_invalid("filter not initialized", dof)
        reason = self._invalid(cam, phi, delta)
        if reason is not None:
            return self._reject_invalid(reason, dof)
        cam = np.asarray(cam, dtype=float)
        if not self._outside(self.x, cam):
            return self._reject_invalid("camera inside the estimated object (d <= r)", dof)
        z = np.array([phi, 0.0 if delta is None else delta])[:dof]
        R = self._R[:dof, :dof]
        inverse_range = self._y is not None
        mean, cov = (self._y, self._Py) if inverse_range else (self.x, self.P)
        model = self._inverse_range_model if inverse_range else self._cartesian_model
        h0, _ = model(mean, cam, dof)
        nu = self._wrapped(z - h0)
        # Iterated EKF: Gauss-Newton on the MAP cost; one iteration is the plain EKF update.
        step = None
        m_lin, residual = mean, nu
        for _ in range(self.params.iterations):
            h, H = model(m_lin, cam, dof)
            if m_lin is not mean:
                residual = self._wrapped(z - h) - H @ (mean - m_lin)
            S_inv = _inverse_spd(H @ cov @ H.T + R)
            gain = cov @ H.T @ S_inv
            m_next = mean + gain @ residual
            if not (np.all(np.isfinite(m_next)) and self._valid(m_next, cam, inverse_range)):
                break
            step = (m_next, H, S_inv, residual, gain)
            if np.max(np.abs(m_next - m_lin)) < 1e-9:  # converged
                break
            m_lin = m_next
        if step is None:
            return self._reject_inconsistent(cam, phi, delta, None, nu, "update would put the camera inside the object or is degenerate")
        m, H, S_inv, residual, gain = step
        nis = float(residual @ S_inv @ residual)  # = min MAP cost; the plain NIS when iterations = 1
        if not math.isfinite(nis):
            return self._reject_invalid("innovation covariance is degenerate", dof)
        if nis > self._gate[dof]:
            return self._reject_inconsistent(cam, phi, delta, nis, nu, f"NIS {nis:.1f} above gate {self._gate[dof]:.1f}")
        self._lost_in_a_row = 0
        A = np.eye(3) - gain @ H
        cov = A @ cov @ A.T + gain @ R @ gain.T
        if not np.all(np.isfinite(cov)):
            return self._reject_invalid("update produced a non-finite covariance", dof)
        cov = 0.5 * (cov + cov.T)
        if inverse_range:
            self._y, self._Py = m, cov
            self._publish()
            if math.sqrt(cov[1, 1]) < self.params.inverse_range_switch * m[1]:
                self._anchor = self._y = self._Py = None  # the range is known: continue on x, P
        else:
            self.x, self.P = m.copy(), cov
            self.x[2] = max(self.x[2], self.params.min_radius)
        self.stats.accepted += 1
        self.stats.rejected_in_a_row = 0
        return UpdateResult(True, nis, dof, nu, "ok")

    def _reject_inconsistent(
        self, cam: np.ndarray, phi: float, delta: Optional[float], nis: Optional[float], nu: np.ndarray, reason: str
    ) -> UpdateResult:
        """A valid view that contradicts the estimate (gated, or its update leaves the state's domain);
        after ``reinitialize_after`` of them in a row the estimate is lost: restart from this view."""
        if nis is None:
            self.stats.invalid += 1
        else:
            self.stats.gated += 1
        self._lost_in_a_row += 1
        if self._lost_in_a_row < self.params.reinitialize_after:
            self.stats.rejected_in_a_row += 1
            return UpdateResult(False, nis, nu.size, nu if nis is not None else None, reason)
        streak = self._lost_in_a_row
        self.initialize(cam, phi, delta)
        self.stats.reinitialized += 1
        self.stats.rejected_in_a_row = 0
        return UpdateResult(True, nis, nu.size, nu, f"re-initialized after {streak} consecutive views inconsistent with the estimate ({reason})")

    def _publish(self) -> None:
        """x, P of the inverse-range state, to first order: x = x(y), P = J P_y J^T."""
        beta, rho, size = self._y
        self.x = np.array([self._anchor[0] + math.cos(beta) / rho, self._anchor[1] + math.sin(beta) / rho, size / rho])
        J = self._cartesian_jacobian(self._y)
        self.P = J @ self._Py @ J.T

    @staticmethod
    def _cartesian_jacobian(y: np.ndarray) -> np.ndarray:
        """J = d(xo, yo, r) / d(beta, rho, s)."""
        beta, rho, size = y
        c, s = math.cos(beta), math.sin(beta)
        return np.array([[-s / rho, -c / rho**2, 0.0], [c / rho, -s / rho**2, 0.0], [0.0, -size / rho**2, 1.0 / rho]])

    def _cartesian_model(self, x: np.ndarray, cam: np.ndarray, dof: int) -> Tuple[np.ndarray, np.ndarray]:
        p = self.params
        return measure(x, cam, p.width_model)[:dof], measurement_jacobian(x, cam, p.width_model)[:dof]

    def _inverse_range_model(self, y: np.ndarray, cam: np.ndarray, dof: int) -> Tuple[np.ndarray, np.ndarray]:
        """h and dh/dy through the scaled state u = rho (xo - cx, yo - cy, r) seen from the origin (h is
        homogeneous of degree 0): u = (rho (ax - cx) + cos beta, rho (ay - cy) + sin beta, s)."""
        beta, rho, size = y
        offset = self._anchor - cam[:2]
        u = np.array([rho * offset[0] + math.cos(beta), rho * offset[1] + math.sin(beta), size])
        du_dy = np.array([[-math.sin(beta), offset[0], 0.0], [math.cos(beta), offset[1], 0.0], [0.0, 0.0, 1.0]])
        origin = np.array([0.0, 0.0, cam[2]])
        h, H = self._cartesian_model(u, origin, dof)
        return h, H @ du_dy

    def _valid(self, m: np.ndarray, cam: np.ndarray, inverse_range: bool) -> bool:
        if not inverse_range:
            return self._outside(m, cam)
        # In front of the anchor at a finite range, and the camera outside the object.
        return m[1] > 0.0 and 0.0 < m[2] < 1.0 and math.hypot(*(m[1] * (self._anchor - cam[:2]) + (math.cos(m[0]), math.sin(m[0])))) > m[2]

    def _outside(self, x: np.ndarray, cam: np.ndarray) -> bool:
        return math.hypot(x[0] - cam[0], x[1] - cam[1]) > x[2]

    @staticmethod
    def _wrapped(nu: np.ndarray) -> np.ndarray:
        nu = nu.copy()
        nu[0] = wrap_angle(nu[0])
        return nu
