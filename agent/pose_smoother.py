"""Frame poses smoothed over the whole walk: every landmark fix, before and after, and the odometry between.

The localizer is a filter (agent/localization.py, docs/landmarks.md): a frame between two fixes gets
the earlier fix carried forward by odometry, whose heading random-walks by k_r per sqrt(m + rad) and
whose turn scale is a few percent off, and the next fix corrects the pose only from then on. While
the robot walks, fixes are rare (a NAO's torso sway and a 30 ms exposure smear 8 cm markers beyond
detection: in stress world 308, a 3 m room with 28 such markers, 18 % of frames gave one, almost all
while standing), so most keyframes were captured a few seconds of walking after the last fix:
headings 10-50 mrad off, silhouettes misplaced by 6-30 mm at 0.6 m (docs/carving.md, "Keyframe
poses smoothed"). The carve needs the keyframes' poses only at the end, when every fix is known.

Fixed-interval smoothing as a pose graph. The unknowns are the planar poses p_j = (x_j, y_j, theta_j)
of the frames j = 1..N the localizer saw (one unbroken segment: a reset starts another), and

    min_p  sum_j rho(|| Q_j^-1/2 wrap((p_j (-) p_j+1) - S d_j) ||^2) + sum_{i in fixes} rho(|| R_i^-1/2 wrap(p_i - z_i) ||^2)

with d_j = o_j (-) o_j+1 the odometry step between the readings at the two captures (robot frame),
S = diag(s) the walk's scales as the localizer estimated them at the end (not smoothed themselves),
Q_j = diag(k_t^2 l_j, k_t^2 l_j, k_r^2 (l_j + |dtheta_j|)) + eps^2 I the filter's own step noise
(l_j the step's length), z_i and R_i a fix and the covariance the filter fused it with (R + F; a
conditioned fix, whose covariance holds the prior's information, is not a factor), and rho the
soft-l1 loss at ``outlier_sigmas`` (a fall or a kidnap the odometry missed, a wrong fix that passed
the gate: beyond a few sigmas a residual costs linearly and pulls the rest no further). For a linear
model and rho = identity this is the Rauch-Tung-Striebel smoother's estimate; here it is solved by
``scipy.optimize.least_squares`` (trust region, the Jacobian's block-tridiagonal sparsity given)
from the filter's poses. A segment without a fix has nothing to smooth towards and keeps them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from nao_core.geometry import Pose, wrap_angle

STEP_FLOOR = 1e-4  # eps: (m, rad) of noise every step keeps, so a standing robot's steps stay finite in the cost


@dataclass(frozen=True)
class TrackPoint:
    """One frame the localizer saw, with a pose (after fusing the frame's own fix, if any)."""

    stamp: float
    odom: Pose  # the odometry reading at capture
    pose: Pose  # the filter's pose at capture
    segment: int  # frames of one unbroken pose share it; a reset (a fall, a teleport) starts the next
    fix: Optional[Pose] = None  # the frame's fused landmark fix, unconditioned
    fix_covariance: Optional[np.ndarray] = None  # 3 x 3, what the filter fused it with


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise (-a) (+) b for N x 3 arrays of poses (nao_core.geometry.relative, vectorized)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[:, 2] - a[:, 2])])


def _whitener(covariance: np.ndarray) -> np.ndarray:
    """W with W^T W = covariance^-1 (the upper Cholesky factor of the information)."""
    return np.linalg.cholesky(np.linalg.inv(covariance)).T


def smooth_segment(track: Sequence[TrackPoint], scale: Sequence[float], translation_noise: float,
                   rotation_noise: float, outlier_sigmas: float = 3.0) -> np.ndarray:
    """The smoothed poses (N x 3) of one segment's frames, in order (module docstring); the filter's own
    when the segment has no fix or fewer than two frames."""
    poses = np.array([p.pose for p in track], dtype=float).reshape(-1, 3)
    fixes = [(j, p) for j, p in enumerate(track) if p.fix is not None and p.fix_covariance is not None]
    n = len(track)
    if n < 2 or not fixes:
        return poses
    odom = np.array([p.odom for p in track], dtype=float)
    steps = _relative(odom[:-1], odom[1:]) * np.asarray(scale, dtype=float)
    length = np.hypot(steps[:, 0], steps[:, 1])
    step_std = np.column_stack([translation_noise * np.sqrt(length), translation_noise * np.sqrt(length),
                                rotation_noise * np.sqrt(length + np.abs(steps[:, 2]))])
    step_std = np.hypot(step_std, STEP_FLOOR)
    fix_index = np.array([j for j, _ in fixes])
    z = np.array([p.fix for _, p in fixes], dtype=float)
    W = np.array([_whitener(np.asarray(p.fix_covariance, dtype=float)) for _, p in fixes])

    def residuals(v: np.ndarray) -> np.ndarray:
        p = v.reshape(-1, 3)
        odometry = _relative(p[:-1], p[1:]) - steps
        odometry[:, 2] = wrap_angle(odometry[:, 2])
        e = p[fix_index] - z
        e[:, 2] = wrap_angle(e[:, 2])
        return np.concatenate([(odometry / step_std).ravel(), np.einsum("kij,kj->ki", W, e).ravel()])

    sparsity = lil_matrix((3 * (n - 1) + 3 * len(fixes), 3 * n), dtype=np.int8)
    for j in range(n - 1):
        sparsity[3 * j:3 * j + 3, 3 * j:3 * j + 6] = 1
    for k, j in enumerate(fix_index):
        sparsity[3 * (n - 1) + 3 * k:3 * (n - 1) + 3 * k + 3, 3 * j:3 * j + 3] = 1
    solution = least_squares(residuals, poses.ravel(), jac_sparsity=sparsity, loss="soft_l1", f_scale=outlier_sigmas,
                             x_scale="jac", method="trf")
    smoothed = solution.x.reshape(-1, 3)
    smoothed[:, 2] = wrap_angle(smoothed[:, 2])
    return smoothed


def smooth_track(track: Sequence[TrackPoint], scale: Sequence[float], translation_noise: float,
                 rotation_noise: float, outlier_sigmas: float = 3.0) -> np.ndarray:
    """The smoothed poses (N x 3) of a track, each segment smoothed on its own (module docstring)."""
    smoothed = np.zeros((len(track), 3))
    segments = np.array([p.segment for p in track])
    for segment in np.unique(segments):
        rows = np.flatnonzero(segments == segment)
        smoothed[rows] = smooth_segment([track[j] for j in rows], scale, translation_noise, rotation_noise, outlier_sigmas)
    return smoothed
