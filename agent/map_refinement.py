"""Landmark places refined from the walk: a bundle adjustment of the keyframes' cameras and the map.

A user's map is measured with a tape, each landmark a few millimetres off (``LandmarkMap.position_sigma``,
``yaw_sigma``). The localizer weighs every fix by that error (agent/localization.py, Map error), which makes
the fixes honest but not right: a frame's pose reads its markers' mapped places, and the map's errors move
it by centimetres that change with the landmarks in view (the matrix's worlds, the map 5 mm and 1 deg off:
pose error median 9-44 mm against 4-12 with the exact map, docs/benchmarks.md "Maps measured off"). Over a
walk each landmark is seen from many keyframes beside others, and their views disagree where the map is
wrong: the relative errors are observable, and the carve needs the keyframes' cameras only at the end.

The unknowns are every keyframe camera k's pose, as a correction (omega_k, c_k) of the pose it was taken
with (R_k = R0_k Exp(omega_k), C_k = C0_k + c_k: agent/keyframe_pose.py), and every landmark m's
displacement d_m (three axes) and, a marker, its turn psi_m about the vertical through its mapped centre
b_m; a mapped point X_i of m moves to

    X_i' = b_m + R_z(psi_m) (X_i - b_m) + d_m,       u_ki' = pi(K, R_k^T (X_i' - C_k)),

and the maximum a posteriori estimate is

    min  sum_k sum_i rho(||u_ki' - u_ki||^2 / s_k^2) + sum_k (||omega_k||^2 / sigma_rot^2 + ||c_k||^2 / sigma_pos^2)
         + sum_m (||d_m||^2 / sigma_p^2 + psi_m^2 / sigma_psi^2),

with s_k the keyframe's pixel noise (its fix's reprojection RMS at least), the cameras' priors those of a
keyframe's own refinement, the map's the file's own, and rho the soft-l1 loss beyond ``OUTLIER_SIGMAS``
(a corner the detector misplaced pulls no further). The map's overall place is held by its prior alone:
a shift of every landmark with every camera is not seen by the images, and the object is carved in the
map's frame. Solved by ``scipy.optimize.least_squares`` (trust region, finite differences over the
Jacobian's sparsity: a point's residual depends on its camera and its landmark only) from zero
corrections. A camera whose points end with a reprojection RMS above ``max_rms`` px keeps the pose it
had. With an exact map (sigma_p = sigma_psi = 0) there is nothing to estimate and nothing runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Hashable, List, Optional, Sequence, Tuple

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

MIN_DEPTH = 0.05  # m: a point nearer the camera plane than this gives a huge residual (it crossed behind)
OUTLIER_SIGMAS = 3.0  # residuals (in their sigmas) beyond which the loss grows linearly
MIN_SHARED = 2  # keyframes that must see a landmark for its place to be estimated (else the prior alone holds it)


@dataclass(frozen=True)
class KeyframeView:
    """One keyframe's landmark points: the camera pose it was taken with, the mapped points, their
    landmark ids and the pinhole pixels (distortion removed) they were seen at."""

    T_WC: np.ndarray  # 4 x 4, the prior
    world: np.ndarray  # N x 3, mapped
    pixels: np.ndarray  # N x 2
    ids: Tuple[Hashable, ...]  # landmark id per point
    pixel_sigma: float  # px
    K: np.ndarray  # 3 x 3, the intrinsics the pixels were undistorted with


@dataclass(frozen=True)
class Adjustment:
    """The adjusted cameras (None: a camera kept its pose) and landmark displacements (d_m, psi_m)."""

    T_WC: List[Optional[np.ndarray]]  # one per view given
    displacement: Dict[Hashable, Tuple[np.ndarray, float]]
    rms_px: List[float]  # one per view given (nan: not adjusted)


def adjust(given: Sequence[KeyframeView], position_sigma: float, yaw_sigma: float, rotation_sigma: float,
           camera_position_sigma: float, max_rms: float) -> Optional[Adjustment]:
    """The bundle adjustment of the ``given`` views and the landmarks they share (module docstring), or
    None when the map is exact or no landmark is seen by ``MIN_SHARED`` keyframes. A view with a point
    or pose not finite, or a point behind its camera, is left out (its T_WC None)."""
    if position_sigma <= 0.0 and yaw_sigma <= 0.0:
        return None
    usable = [k for k, v in enumerate(given) if _finite(v) and np.all(_depths(v) > MIN_DEPTH)]
    views = [given[k] for k in usable]
    seen: Dict[Hashable, set] = {}
    for k, view in enumerate(views):
        for landmark in view.ids:
            seen.setdefault(landmark, set()).add(k)
    landmarks = [m for m, frames in seen.items() if len(frames) >= MIN_SHARED]
    if not landmarks:
        return None
    problem = _Problem(views, landmarks, position_sigma, yaw_sigma, rotation_sigma, camera_position_sigma)
    solution = least_squares(problem.residuals, np.zeros(problem.size), jac_sparsity=problem.sparsity(),
                             loss="soft_l1", f_scale=OUTLIER_SIGMAS, x_scale="jac")
    T_WC: List[Optional[np.ndarray]] = [None] * len(given)
    rms = [math.nan] * len(given)
    for k, T, r in zip(usable, problem.cameras(solution.x), problem.rms(solution.x)):
        T_WC[k], rms[k] = (T if r <= max_rms else None), r
    return Adjustment(T_WC, problem.displacements(solution.x), rms)


def _finite(view: KeyframeView) -> bool:
    return bool(len(view.world) and len(view.world) == len(view.pixels) == len(view.ids) and np.all(np.isfinite(view.world))
                and np.all(np.isfinite(view.pixels)) and np.all(np.isfinite(view.T_WC)) and view.pixel_sigma > 0.0)


def _depths(view: KeyframeView) -> np.ndarray:
    return (view.world - view.T_WC[:3, 3]) @ view.T_WC[:3, 2]


class _Problem:
    """The stacked unknowns [omega_k, c_k for every camera; d_m, psi_m for every estimated landmark]."""

    def __init__(self, views: Sequence[KeyframeView], landmarks: Sequence[Hashable], position_sigma: float, yaw_sigma: float, rotation_sigma: float, camera_position_sigma: float):
        index = {m: j for j, m in enumerate(landmarks)}
        self.landmarks = list(landmarks)
        self.R0 = np.array([v.T_WC[:3, :3] for v in views])
        self.C0 = np.array([v.T_WC[:3, 3] for v in views])
        self.X = np.vstack([v.world for v in views])
        self.u = np.vstack([v.pixels for v in views])
        self.camera = np.concatenate([np.full(len(v.world), k) for k, v in enumerate(views)])
        self.sigma = np.concatenate([np.full(len(v.world), v.pixel_sigma) for v in views])
        landmark = np.array([index.get(m, -1) for v in views for m in v.ids])
        self.landmark = landmark
        self.moved = landmark >= 0  # points of landmarks seen once stay where the map has them
        centres = np.zeros((len(landmarks), 3))
        for j, m in enumerate(landmarks):  # a marker's mapped centre: the mean of its distinct corners
            centres[j] = np.unique(self.X[landmark == j].round(9), axis=0).mean(axis=0)
        self.centre = centres
        K = np.vstack([np.tile(np.asarray(v.K, dtype=float).reshape(1, 9), (len(v.world), 1)) for v in views])
        self.f, self.c = K[:, [0, 4]], K[:, [2, 5]]
        self.n_cameras, self.n_landmarks = len(views), len(landmarks)
        self.size = 6 * self.n_cameras + 4 * self.n_landmarks
        self.prior = np.concatenate([np.tile([rotation_sigma] * 3 + [camera_position_sigma] * 3, self.n_cameras),
                                     np.tile([position_sigma] * 3 + [yaw_sigma], self.n_landmarks)])
        self.held = self.prior <= 0.0  # a map exact in yaw (or position) keeps it exactly
        self.prior = np.where(self.held, 1.0, self.prior)

    def _split(self, v: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        cams = v[:6 * self.n_cameras].reshape(-1, 6)
        lms = np.where(self.held[6 * self.n_cameras:], 0.0, v[6 * self.n_cameras:]).reshape(-1, 4)
        return cams[:, :3], cams[:, 3:], lms[:, :3], lms[:, 3]

    def _poses(self, v: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        omega, c, _, _ = self._split(v)
        return self.R0 @ Rotation.from_rotvec(omega).as_matrix(), self.C0 + c

    def _points(self, v: np.ndarray) -> np.ndarray:
        _, _, d, psi = self._split(v)
        X = self.X.copy()
        j = self.landmark[self.moved]
        arm = X[self.moved, :2] - self.centre[j, :2]
        cos, sin = np.cos(psi[j]), np.sin(psi[j])
        X[self.moved, 0] = self.centre[j, 0] + cos * arm[:, 0] - sin * arm[:, 1]
        X[self.moved, 1] = self.centre[j, 1] + sin * arm[:, 0] + cos * arm[:, 1]
        X[self.moved] += d[j]
        return X

    def _in_cameras(self, v: np.ndarray) -> np.ndarray:
        R, C = self._poses(v)
        k = self.camera
        return np.einsum("nji,nj->ni", R[k], self._points(v) - C[k])

    def _pixels(self, v: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        X_C = self._in_cameras(v)
        depth = X_C[:, 2]
        uv = X_C[:, :2] / np.where(depth > MIN_DEPTH, depth, MIN_DEPTH)[:, None] * self.f + self.c
        return np.where(depth[:, None] > MIN_DEPTH, uv, self.u + 1e6), depth

    def residuals(self, v: np.ndarray) -> np.ndarray:
        uv, _ = self._pixels(v)
        return np.concatenate([((uv - self.u) / self.sigma[:, None]).ravel(), np.where(self.held, 0.0, v / self.prior)])

    def sparsity(self) -> coo_matrix:
        n = len(self.X)
        point = np.arange(n)
        rows, columns = [], []
        for axis in range(2):  # a pixel residual: its camera's six columns and its landmark's four
            rows.append(np.repeat(2 * point + axis, 6))
            columns.append((6 * self.camera[:, None] + np.arange(6)).ravel())
            moved = point[self.moved]
            rows.append(np.repeat(2 * moved + axis, 4))
            columns.append((6 * self.n_cameras + 4 * self.landmark[moved][:, None] + np.arange(4)).ravel())
        rows.append(2 * n + np.arange(self.size))  # the priors
        columns.append(np.arange(self.size))
        rows, columns = np.concatenate(rows), np.concatenate(columns)
        return coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, columns)), shape=(2 * n + self.size, self.size))

    def rms(self, v: np.ndarray) -> List[float]:
        uv, _ = self._pixels(v)
        squared = np.sum((uv - self.u) ** 2, axis=1)
        return [float(np.sqrt(np.mean(squared[self.camera == k]))) for k in range(self.n_cameras)]

    def cameras(self, v: np.ndarray) -> List[np.ndarray]:
        R, C = self._poses(v)
        poses = []
        for k in range(self.n_cameras):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R[k], C[k]
            poses.append(T)
        return poses

    def displacements(self, v: np.ndarray) -> Dict[Hashable, Tuple[np.ndarray, float]]:
        _, _, d, psi = self._split(v)
        return {m: (d[j].copy(), float(psi[j])) for j, m in enumerate(self.landmarks)}
