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
of the frames j = 1..N the localizer saw (no step links two unbroken segments: a reset starts another), and

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

Landmark places from the walk. A map measured with a tape puts each landmark a few millimetres off,
and every fix reads its landmarks' mapped places: a fix's error is mostly G_i delta, delta the
landmarks' displacements from where the map has them (three axes each and, a marker, its turn about
the vertical) and G_i = d fix / d delta the fit's own sensitivity to them (agent/localization.py, Map
error). One fix cannot tell that error from its pose; the walk can, since the odometry carries the
robot between fixes made of other landmarks. With the map's stated error, delta joins the unknowns,

    ... + sum_i rho(|| R'_i^-1/2 wrap(p_i + G_i delta - z_i) ||^2) + sum_q delta_q^2 / sigma_q^2,

R'_i the fix's covariance without the map's share (R_i - G_i S G_i^T, the fit's generalized least
squares: what the pixels alone leave), sigma_q the map's stated precision, every segment's poses
sharing delta. The displacements are returned with the poses (``Smoothed``): the final carve moves
a keyframe's landmark points by them (station/pilot.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Hashable, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from nao_core.geometry import Pose, wrap_angle

STEP_FLOOR = 1e-4  # eps: (m, rad) of noise every step keeps, so a standing robot's steps stay finite in the cost
Label = Tuple[Hashable, int]  # (landmark id, axis): 0-2 its move along the world's x, y, z; 3 a marker's turn about the vertical


@dataclass(frozen=True)
class MapGain:
    """How a fix moves with its landmarks' displacements from their mapped places (module docstring)."""

    labels: Tuple[Label, ...]  # the displacements it depends on
    gain: np.ndarray  # 3 x q: d(x, y, theta) / d displacement
    sigma: np.ndarray  # q: the map's stated std of each (m, rad)
    covariance: np.ndarray  # 3 x 3: the fix's covariance without the map's share


@dataclass(frozen=True)
class TrackPoint:
    """One frame the localizer saw, with a pose (after fusing the frame's own fix, if any)."""

    stamp: float
    odom: Pose  # the odometry reading at capture
    pose: Pose  # the filter's pose at capture
    segment: int  # frames of one unbroken pose share it; a reset (a fall, a teleport) starts the next
    fix: Optional[Pose] = None  # the frame's fused landmark fix, unconditioned
    fix_covariance: Optional[np.ndarray] = None  # 3 x 3, what the filter fused it with
    map_gain: Optional[MapGain] = field(default=None, compare=False)  # with a map that states its error


class Smoothed(NamedTuple):
    poses: np.ndarray  # N x 3, the track's frames in order
    displacement: Dict[Label, float]  # the landmarks' displacements the walk found (empty: the map held exact)


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise (-a) (+) b for N x 3 arrays of poses (nao_core.geometry.relative, vectorized)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[:, 2] - a[:, 2])])


def _whitener(covariance: np.ndarray) -> np.ndarray:
    """W with W^T W = covariance^-1 (the upper Cholesky factor of the information)."""
    return np.linalg.cholesky(np.linalg.inv(covariance)).T


def smooth_track(track: Sequence[TrackPoint], scale: Sequence[float], translation_noise: float,
                 rotation_noise: float, outlier_sigmas: float = 3.0) -> Smoothed:
    """The smoothed poses of a track's frames and the landmarks' displacements (module docstring): the
    segments' poses apart, linked only through the displacements; a segment without a fix, or of one
    frame, keeps the filter's poses."""
    poses = np.array([p.pose for p in track], dtype=float).reshape(-1, 3)
    segments = np.array([p.segment for p in track])
    fixed = {p.segment for p in track if p.fix is not None and p.fix_covariance is not None}
    rows = np.flatnonzero([p.segment in fixed and np.sum(segments == p.segment) > 1 for p in track])
    if not len(rows):
        return Smoothed(poses, {})
    solved = [track[j] for j in rows]
    labels = list(dict.fromkeys(label for p in solved if p.fix is not None and p.map_gain is not None for label in p.map_gain.labels))
    column = {label: k for k, label in enumerate(labels)}  # after the poses' 3 n
    sigma = np.ones(len(labels))
    for p in solved:
        if p.fix is not None and p.map_gain is not None:
            for label, std in zip(p.map_gain.labels, p.map_gain.sigma):
                sigma[column[label]] = std
    n = len(solved)
    odom = np.array([p.odom for p in solved], dtype=float)
    same = np.array([solved[j].segment == solved[j + 1].segment for j in range(n - 1)], dtype=bool)
    steps = _relative(odom[:-1], odom[1:])[same] * np.asarray(scale, dtype=float)
    first = np.flatnonzero(same)  # step k links frames first[k] and first[k] + 1
    length = np.hypot(steps[:, 0], steps[:, 1])
    step_std = np.hypot(np.column_stack([translation_noise * np.sqrt(length), translation_noise * np.sqrt(length),
                                         rotation_noise * np.sqrt(length + np.abs(steps[:, 2]))]), STEP_FLOOR)
    fixes = [(j, p) for j, p in enumerate(solved) if p.fix is not None and p.fix_covariance is not None]
    fix_index = np.array([j for j, _ in fixes], dtype=int)
    z = np.array([p.fix for _, p in fixes], dtype=float).reshape(-1, 3)
    W = np.array([_whitener(np.asarray(p.map_gain.covariance if p.map_gain is not None else p.fix_covariance, dtype=float))
                  for _, p in fixes]).reshape(-1, 3, 3)
    gains = [(k, [column[label] for label in p.map_gain.labels], np.asarray(p.map_gain.gain, dtype=float))
             for k, (_, p) in enumerate(fixes) if p.map_gain is not None]
    values, g_rows, g_columns = [np.zeros(0)], [np.zeros(0, dtype=int)], [np.zeros(0, dtype=int)]
    for k, columns, gain in gains:  # every fix's gain, stacked: e += G delta
        values.append(gain.ravel())
        g_rows.append(np.repeat(3 * k + np.arange(3), len(columns)))
        g_columns.append(np.tile(columns, 3))
    G = coo_matrix((np.concatenate(values), (np.concatenate(g_rows), np.concatenate(g_columns))),
                   shape=(3 * len(fixes), len(labels))).tocsr()

    def residuals(v: np.ndarray) -> np.ndarray:
        p = v[:3 * n].reshape(-1, 3)
        odometry = _relative(p[first], p[first + 1]) - steps
        odometry[:, 2] = wrap_angle(odometry[:, 2])
        e = p[fix_index] - z + (G @ v[3 * n:]).reshape(-1, 3)
        e[:, 2] = wrap_angle(e[:, 2])
        return np.concatenate([(odometry / step_std).ravel(), np.einsum("kij,kj->ki", W, e).ravel(), v[3 * n:] / sigma])

    size = 3 * n + len(labels)
    r, c = [], []
    for k, j in enumerate(first):  # a step: its two frames
        r.append(np.repeat(3 * k + np.arange(3), 6))
        c.append(np.tile(3 * j + np.arange(6), 3))
    base = 3 * len(first)
    for k, j in enumerate(fix_index):  # a fix: its frame
        r.append(np.repeat(base + 3 * k + np.arange(3), 3))
        c.append(np.tile(3 * j + np.arange(3), 3))
    for k, columns, _ in gains:  # and its landmarks' displacements
        r.append(np.repeat(base + 3 * k + np.arange(3), len(columns)))
        c.append(3 * n + np.tile(columns, 3))
    base += 3 * len(fix_index)
    r.append(base + np.arange(len(labels)))
    c.append(3 * n + np.arange(len(labels)))
    r, c = np.concatenate(r), np.concatenate(c)
    sparsity = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(base + len(labels), size))
    start = np.concatenate([poses[rows].ravel(), np.zeros(len(labels))])
    solution = least_squares(residuals, start, jac_sparsity=sparsity, loss="soft_l1", f_scale=outlier_sigmas,
                             x_scale="jac", method="trf")
    smoothed = poses.copy()
    smoothed[rows] = solution.x[:3 * n].reshape(-1, 3)
    smoothed[:, 2] = wrap_angle(smoothed[:, 2])
    return Smoothed(smoothed, {label: float(solution.x[3 * n + k]) for k, label in enumerate(labels)})
