"""Camera intrinsics refined in flight from the mission's own landmark fixes (docs/landmarks.md,
"Self-calibration").

A calibration off by 0.5 % in focal length and 1 px in principal point (what a checkerboard
calibration leaves) scales every marker range by 0.5 % and tilts every ray by a milliradian: at
1.5-2 m that is 1-2 cm of pose error, the same in every frame, and the object inherits it. The
landmark map is a calibration target the robot sees from many poses, so the error is observable.

Parameters: c = (s_x, s_y, d_u, d_v, e), the corrected pinhole

    f_x' = f_x (1 + s_x),  f_y' = f_y (1 + s_y),  c_x' = c_x + d_u,  c_y' = c_y + d_v,

and the markers' edge shift e (px along each edge's outward normal: a tone curve the station is not
told, a blur the corner refinement does not see symmetric; agent/marker_corners.py), which moves
marker corner i by e d_i (``edge_shift_jacobian``) and no ball,

common to all stored fixes k, each with its own planar pose p_k = (x, y, theta, delta) (the torso
roll delta held by the fix's roll prior w_k = sigma_px / sigma_roll,k), the projection of
agent/localization.py ``PlanarModel``. Bundle adjustment with known world points, Gauss-Newton on
all of them at once, the poses eliminated by the Schur complement:

    A_k = J_pk^T J_pk + diag(0, 0, 0, w_k^2),  B_k = J_pk^T J_ck,
    S = sum_k (J_ck^T J_ck - B_k^T A_k^-1 B_k) + Lambda,   b = sum_k (J_ck^T r_k - B_k^T A_k^-1 g_pk) + Lambda c,
    dc = -S^-1 b,   dp_k = -A_k^-1 (g_pk + B_k dc),

with J_c: du/ds_x = f_x x/z, dv/ds_y = f_y y/z, du/dd_u = dv/dd_v = 1, du/de = d_i, and the prior
Lambda = sigma_px^2 diag(1/sigma_s^2, 1/sigma_s^2, 1/sigma_d^2, 1/sigma_d^2, 1/sigma_e^2) (what a
calibration may be off by, and how far an edge may be moved). A view of two markers or more tells e
from the focal length and the range: e moves each marker's size by 2 e px, not the distances between
markers (measured on rendered frames of a camera with gamma 0.45 untold, docs/frames.md). Each fix's
pixels are stored as detected, before the localizer took the applied e out of them
(``PoseFix.edge_shift``). The estimate's covariance is s^2 S^-1, s^2 the residual variance per axis. A
principal point shift across the image is nearly a turn of the robot (d_u is held mostly by its
prior); the focal scales and d_v are not. Fixes whose RMS after the fit exceeds
``outlier_rms_ratio`` times the median are dropped as wrong associations, and the fit repeated.
A fix can also be wrong in a way the intrinsics absorb (its camera tilted by a head angle read a
few milliseconds off): its RMS stays low, but the others disagree with it. Its influence, the
squared Mahalanobis distance the estimate moves by when it is left out (one Gauss-Newton step from
the solution, S_k and b_k its terms of S and b),

    c_-k - c = (S - S_k)^-1 (b_k - b),   D_k = (c_-k - c)^T (S - S_k) (c_-k - c) / s^2,

is measured in the covariance of the estimate without it, so a fix that alone constrains some
direction (S - S_k small there) is not accused for moving it. The fix of largest D_k above
``max_influence`` is dropped and the fit repeated (at most three rounds in all).

A fix is stored when it has ``min_points`` points of ``min_landmarks`` landmarks or more: four
balls, or two markers (one marker's range comes from its size, which a focal error scales alike,
so it says nothing about the focal length). Only fixes made standing are stored (their roll prior
at most ``max_roll_sigma``): while walking
the torso sways, rolls and bobs by more than the kinematics report, and a bundle adjustment over
walking fixes turns that into a calibration error (measured: the focal scales drifted by 1 % over a
mission). Nor are fixes made while the head turns, or within ``head_settle`` s after it turned
faster than ``head_still_speed`` or after the first frame (docs/landmarks.md): the head angles
read for a frame are those of its capture stamp, and a stamp a few milliseconds off at the head's
speed tilts the fix's camera by a few milliradians, which the pitch-held bundle adjustment takes
for a vertical focal or principal point error (measured in the matrix: two such fixes of eight,
2.3 and 0.8 px off in v, put the vertical focal scale 0.7 % off with a stated std of 0.06 %). A
mission stands while it searches and localizes; ACTIVE starts with a standstill whose head
alternates between the object and the ``standstill_views`` head directions predicted from its pose
to show a fix to store, most points first and ``standstill_view_spacing`` apart in yaw, each dwell
counted from the head's arrival, and stands again later while no estimate is applied
(agent/standstill.py); not where no direction is predicted to show one (a sparse layout rarely
shows two markers at once).

Each fix keeps its camera transform as reported; a solve corrects it by the localizer's latest
camera tilt on its mount (agent/camera_tilt.py), learnt from the same standing fixes: corrected by
the estimate of its own time, a fix stored before the tilt had settled tilted the others'
solution (measured: matrix seed 23, the camera rolled 0.5 deg, focal scales 1 % off).

The estimate is *applied* (``camera`` returns the corrected model, ``edge_shift`` its e, which the
localizer takes out of every detected corner) once ``min_frames`` fixes agree on it with focal-scale
std <= ``max_scale_std``; until then the configured camera stays, and no edge shift.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import List, Optional, Tuple

import numpy as np

from agent.camera import CameraModel
from agent.camera_tilt import CameraTilt
from agent.localization import MIN_DEPTH, N_INTRINSICS, NoFix, PlanarModel, PoseFix
from agent.marker_corners import edge_shift_jacobian
from nao_core.config import bounds
from nao_core.landmark_map import LandmarkMap


@dataclass(frozen=True)
class SelfCalibrationParams:
    """config/self_calibration.yaml, section ``self_calibration``."""

    enabled: bool
    scale_sigma: float = field(metadata=bounds(1e-5, 0.2))  # prior std of each focal scale error (relative)
    principal_sigma: float = field(metadata=bounds(0.01, 50.0))  # prior std of each principal point error, px
    edge_sigma: float = field(metadata=bounds(1e-3, 5.0))  # prior std of the markers' edge shift e, px
    pixel_sigma: float = field(metadata=bounds(0.01, 10.0))  # image point noise, px (the prior's weight)
    min_points: int = field(metadata=bounds(4, 1000))  # a fix with fewer inlier points is not stored
    min_landmarks: int = field(metadata=bounds(2, 1000))  # ... nor one of fewer landmarks (one marker's size is its range)
    max_roll_sigma: float = field(metadata=bounds(1e-6, 0.2))  # rad: a fix fitted with a looser roll prior (walking) is not stored
    head_still_speed: float = field(metadata=bounds(1e-4, 10.0))  # rad/s: the head turning faster than this ...
    head_settle: float = field(metadata=bounds(0.0, 10.0))  # s: ... within this long before a fix: the fix is not stored
    min_interval: float = field(metadata=bounds(0.0, 60.0))  # s between stored fixes (consecutive frames say the same)
    max_frames: int = field(metadata=bounds(4, 1000))  # stored fixes (the oldest goes)
    min_frames: int = field(metadata=bounds(2, 1000))  # fixes before an estimate is applied
    update_every: int = field(metadata=bounds(1, 1000))  # new fixes between two estimates
    max_scale_std: float = field(metadata=bounds(1e-5, 0.2))  # the estimate is applied when its focal scales are this sure
    outlier_rms_ratio: float = field(metadata=bounds(1.0, 100.0))  # a fix this many times the median RMS is dropped
    max_influence: float = field(metadata=bounds(1.0, 1e6))  # ... and the fix whose removal moves c by more (D_k) than this
    iterations: int = field(metadata=bounds(1, 100))
    standstill: float = field(metadata=bounds(0.0, 60.0))  # s a standstill lasts at most (agent/standstill.py)
    standstill_dwell: float = field(metadata=bounds(0.1, 60.0))  # s the head stays on each calibration view once there, between object dwells
    standstill_fix_patience: float = field(metadata=bounds(0.1, 600.0))  # s without any landmark fix that end a standstill
    standstill_travel: float = field(metadata=bounds(0.0, 60.0))  # s after which a leg's dwell starts although no frame showed the head there
    standstill_attempts: int = field(metadata=bounds(0, 100))  # standstills in all, while no estimate is applied
    standstill_interval: float = field(metadata=bounds(0.0, 600.0))  # s from the end of one (or a try without a view) to the next
    standstill_views: int = field(metadata=bounds(1, 100))  # head directions the standstill looks through (predicted to give fixes to store)
    standstill_view_spacing: float = field(metadata=bounds(0.0, 3.0))  # rad of head yaw between two of them at least


@dataclass(frozen=True)
class _Fix:
    X: np.ndarray  # N x 3 world points
    u: np.ndarray  # N x 2 pixels, distortion removed, as detected (no edge shift taken out)
    group: np.ndarray  # N: the landmark of each (four points a marker)
    T_BC: np.ndarray  # as reported: corrected by the camera tilt learnt by the time of the solve
    p: np.ndarray  # (x, y, theta, delta) of the fix
    roll_sigma: float


@dataclass(frozen=True)
class Calibration:
    """An estimate: c = (s_x, s_y, d_u, d_v, e), its covariance, the fixes it used and their RMS (px)."""

    c: np.ndarray
    covariance: np.ndarray
    frames: int
    rms: float

    @property
    def scale_std(self) -> float:
        return float(np.sqrt(max(self.covariance[0, 0], self.covariance[1, 1])))


def corrected(camera: CameraModel, c: np.ndarray) -> CameraModel:
    """``camera`` with c = (s_x, s_y, d_u, d_v, ...) applied to its K (module docstring)."""
    K = camera.K.copy()
    K[0, 0] *= 1.0 + c[0]
    K[1, 1] *= 1.0 + c[1]
    K[0, 2] += c[2]
    K[1, 2] += c[3]
    return replace(camera, K=K)


class SelfCalibration:
    """Stores the landmark fixes of a mission and estimates the camera's intrinsics error from them."""

    def __init__(self, params: SelfCalibrationParams, camera: CameraModel, tilt: Optional[CameraTilt] = None):
        self.params = params
        self.configured = camera
        self.tilt = tilt  # the localizer's camera tilt (agent/camera_tilt.py): every solve corrects the fixes by its latest
        self.estimate: Optional[Calibration] = None  # the latest, applied or not
        self.applied: Optional[Calibration] = None
        self.fixes: List[_Fix] = []
        self.stored = 0  # fixes stored so far (the oldest leave ``fixes``)
        self._new = 0
        self._last_stamp = -np.inf
        self._head: Optional[Tuple[float, float, float]] = None  # (stamp, yaw, pitch) of the last frame
        self._head_moved = -np.inf  # stamp of the last frame the head turned at (or of the first frame)

    @property
    def camera(self) -> CameraModel:
        """The configured camera, corrected by the applied estimate."""
        return self.configured if self.applied is None else corrected(self.configured, self.applied.c)

    @property
    def edge_shift(self) -> float:
        """px, the applied estimate's e (0 before one)."""
        return 0.0 if self.applied is None else float(self.applied.c[4])

    @property
    def covariance(self) -> np.ndarray:
        """Of c = (s_x, s_y, d_u, d_v, e) for ``camera`` and ``edge_shift``: the applied estimate's, else
        the prior's (what a calibration may be off by)."""
        if self.applied is not None:
            return self.applied.covariance
        return np.diag(self._prior_sigmas() ** 2)

    def _prior_sigmas(self) -> np.ndarray:
        p = self.params
        return np.array([p.scale_sigma, p.scale_sigma, p.principal_sigma, p.principal_sigma, p.edge_sigma])

    def can_store_fixes_from(self, landmark_map: LandmarkMap) -> bool:
        """Could a fix from this map be stored: ``min_landmarks`` landmarks and ``min_points`` points (four per marker)?"""
        markers, balls = len(landmark_map.of_kind("aruco")), len(landmark_map.of_kind("color"))
        return (self.params.enabled and markers + balls >= self.params.min_landmarks
                and 4 * markers + balls >= self.params.min_points)

    def on_head(self, yaw: float, pitch: float, stamp: float) -> None:
        """A frame's head angles at its capture ``stamp`` (every frame, with a fix or not; an older stamp is ignored)."""
        last = self._head
        if last is None:
            self._head_moved = stamp  # the first reading starts the settle clock: nothing says the head was still before it
        else:
            if not stamp > last[0]:
                return
            speed = max(abs(yaw - last[1]), abs(pitch - last[2])) / (stamp - last[0])
            if not speed <= self.params.head_still_speed:  # NaN angles count as turning
                self._head_moved = stamp
        self._head = (stamp, yaw, pitch)

    @property
    def head_settled(self) -> bool:
        """Has the head been still for ``head_settle`` s up to the last frame (``on_head``)?"""
        return self._head is not None and self._head[0] - self._head_moved >= self.params.head_settle

    def add(self, fix: PoseFix, stamp: float) -> bool:
        """Store ``fix``, made at ``stamp`` (after ``on_head`` of its frame); True when a new estimate was
        applied. Its pixels have the lens distortion removed (by whichever K the localizer had: the
        distortion hardly depends on a K this close)."""
        p = self.params
        if (not p.enabled or fix.conditioned or fix.tracked or fix.inliers is None or len(fix.inliers[0]) < p.min_points
                or len(fix.landmark_ids) < p.min_landmarks or fix.roll_sigma > p.max_roll_sigma
                or not self.head_settled or stamp - self._last_stamp < p.min_interval):
            return False
        X, u = fix.inliers
        group = np.arange(len(X)) // 4 if fix.inlier_groups is None else np.asarray(fix.inlier_groups)
        detected = u + fix.edge_shift * edge_shift_jacobian(u, group)  # as detected: c's e is the whole shift
        reported = fix.T_BC if fix.T_BC_reported is None else fix.T_BC_reported
        self.fixes = (self.fixes + [_Fix(X, detected, group, reported, np.array([*fix.pose, fix.roll]), fix.roll_sigma)])[-p.max_frames:]
        self._last_stamp = stamp
        self.stored += 1
        self._new += 1
        if len(self.fixes) < p.min_frames or self._new < p.update_every:
            return False
        self._new = 0
        self.estimate = self.solve()
        if self.estimate is not None and self.estimate.scale_std <= p.max_scale_std:
            self.applied = self.estimate
            return True
        return False

    def solve(self) -> Optional[Calibration]:
        """Bundle adjustment of c and the stored fixes' poses (module docstring); None when it fails."""
        fixes = self.fixes if self.tilt is None else [replace(f, T_BC=self.tilt.correct(f.T_BC)) for f in self.fixes]
        for _ in range(3):  # drop wrong associations, then refit
            result = self._solve(fixes)
            if result is None:
                return None
            calibration, rms, influence = result
            keep = rms <= self.params.outlier_rms_ratio * max(float(np.median(rms)), 1e-3)
            if keep.all() and influence.max() > self.params.max_influence:
                keep[np.argmax(influence)] = False  # the one fix the others disagree with most
            if keep.all():
                return calibration
            fixes = [f for f, k in zip(fixes, keep) if k]
            if len(fixes) < self.params.min_frames:
                return None
        return None

    def _solve(self, fixes: List[_Fix]):
        p = self.params
        prior = (p.pixel_sigma / self._prior_sigmas()) ** 2
        c = np.zeros(N_INTRINSICS) if self.estimate is None else self.estimate.c.copy()
        poses = [f.p.copy() for f in fixes]
        K0 = self.configured.K
        try:
            for _ in range(p.iterations):
                S, b = np.diag(prior), prior * c
                blocks, terms = [], []  # per fix: its pose step's factors; its S_k and b_k (for D_k)
                camera = corrected(self.configured, c)
                for fix, pose in zip(fixes, poses):
                    r, Jp, Jc, w2 = self._linearize(camera, c[4], K0, fix, pose)
                    A = Jp.T @ Jp
                    A[3, 3] += w2
                    g = Jp.T @ r
                    g[3] += w2 * pose[3]
                    B = Jp.T @ Jc
                    A_inv = np.linalg.inv(A)
                    S_k, b_k = Jc.T @ Jc - B.T @ A_inv @ B, Jc.T @ r - B.T @ A_inv @ g
                    S += S_k
                    b += b_k
                    blocks.append((A_inv, B, g))
                    terms.append((S_k, b_k))
                dc = -np.linalg.solve(S, b)
                c += dc
                for pose, (A_inv, B, g) in zip(poses, blocks):
                    pose += -A_inv @ (g + B @ dc)
                if np.abs(dc).max() < 1e-7:
                    break
            camera = corrected(self.configured, c)
            residuals = [self._residual(camera, c[4], fix, pose) for fix, pose in zip(fixes, poses)]
        except (np.linalg.LinAlgError, NoFix):
            return None
        if not np.all(np.isfinite(c)):
            return None
        rms = np.array([float(np.sqrt(np.mean(r**2) * 2.0)) for r in residuals])
        n = sum(len(r) for r in residuals)
        dof = max(1, n - 4 * len(fixes) - N_INTRINSICS)
        s2 = max(p.pixel_sigma**2, float(sum(np.sum(r**2) for r in residuals)) / dof)
        covariance = s2 * np.linalg.inv(S)
        influence = np.zeros(len(fixes))
        for k, (S_k, b_k) in enumerate(terms):  # D_k (module docstring), at the last linearization
            try:
                shift = np.linalg.solve(S - S_k, b_k - b)
            except np.linalg.LinAlgError:
                continue
            influence[k] = float(shift @ (S - S_k) @ shift) / s2
        calibration = Calibration(c, covariance, len(fixes), float(np.sqrt(np.mean(np.concatenate(residuals) ** 2) * 2.0)))
        return calibration, rms, influence

    @staticmethod
    def _residual(camera: CameraModel, edge: float, fix: _Fix, pose: np.ndarray) -> np.ndarray:
        """Residuals (2N) of one fix at (c, pose), no Jacobian."""
        uv, z = PlanarModel(camera, fix.T_BC).project(pose, fix.X)
        if np.any(z < MIN_DEPTH):
            raise NoFix("landmark point behind the camera")
        return (uv + edge * edge_shift_jacobian(uv, fix.group) - fix.u).ravel()

    def _linearize(self, camera: CameraModel, edge: float, K0: np.ndarray, fix: _Fix, pose: np.ndarray):
        """Residuals (2N), J_p (2N x 4), J_c (2N x 5) and the roll prior weight of one fix at (c, pose)."""
        model = PlanarModel(camera, fix.T_BC)
        uv, z, J = model.jacobian(pose, fix.X)
        if np.any(z < MIN_DEPTH):
            raise NoFix("landmark point behind the camera")
        Jc = model.intrinsics_jacobian(uv, fix.group, K0)
        w2 = (self.params.pixel_sigma / fix.roll_sigma) ** 2
        return (uv + edge * Jc[:, :, 4] - fix.u).ravel(), J.reshape(-1, 4), Jc.reshape(-1, N_INTRINSICS), w2
