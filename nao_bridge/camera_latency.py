"""When a frame's image was taken, from the images themselves: the camera's latency for a NAOqi
whose clock cannot be probed, and the exposure's offset from the stamps of one that can.

Without ``ALMemory.getTimestamp`` and with the robot's clock off the bridge's, a frame's capture
time is known only up to the camera's shortest latency L: the camera bound b_k (docs/frames.md)
is the capture time plus tau = L - ``camera_latency_min`` >= 0, and tau is tens of ms. While the
head turns at 1 rad/s, kinematics read tau late are tau rad off, and the station's bearings with
them. The images themselves say when they were taken: between two frames the scene shifts
horizontally by the camera's turn. With psi(t) the camera's heading in the odometry frame (the
odometry heading plus the yaw of the camera's optical axis in the robot frame, both from the
kinematics history), the shift of frame k against frame k - 1 (``cv2.phaseCorrelate`` on
thumbnails ``THUMB_WIDTH`` px wide, focal length f in thumbnail pixels) is

    dx_k = f (psi(b_k - tau) - psi(b_{k-1} - tau)) + e_k,

and tau is the grid value in [0, ``max_latency``] (step ``STEP``) that minimizes
sum_k min(r_k^2, ``MAX_RESIDUAL``^2) (r_k: dx_k's residual; the cap keeps a pair the turn does not
explain, a passer-by or a failed correlation, from choosing tau) over the last ``window`` frame
pairs whose predicted shift exceeds ``MIN_SHIFT`` px (turns, not stillness) and between which the
robot travelled at most ``MAX_TRAVEL`` by odometry (a walking robot's floor streams past by
parallax, which no turn explains). psi is interpolated from the history as each frame arrives, for
every grid value at once, since the history keeps only the last seconds; each history is unwrapped
on its own, so the turn between two frames is taken modulo 2 pi (a heading crossing +-pi while the
history slides shifts a whole unwrapped history by 2 pi, and an unwrapped difference would then
predict a full turn between two frames). No estimate until
``min_pairs`` such pairs; the estimate holds when the best residual beats the no-latency one.

Stamped frames (a probed or synchronized clock) need the same estimate for another reason: a
frame's image is the mean over its exposure (5-30 ms indoors) while the camera turns, so its scene
is where the camera looked in the exposure's middle, whatever instant the stamp names (its start,
its end). The grid is then [-``max_latency``, ``max_latency``] about the stamp (``min_latency``
negative): tau is how much earlier than its stamp the image's scene was seen, half the exposure
for a stamp at the exposure's end (docs/frames.md, "Exposure": on still frames smeared by 3 px and
stamped at the smear's end, landmark fixes erred by 16 mm median instead of 1).
"""

from __future__ import annotations

import collections
import math
from typing import Deque, Optional, Sequence, Tuple

import cv2
import numpy as np

THUMB_WIDTH = 160  # px: images are correlated at this width
STEP = 0.002  # s between candidate latencies
MIN_SHIFT = 2.0  # px (thumbnail): pairs whose predicted shift is smaller say little about tau
MIN_RESPONSE = 0.05  # phase-correlation peak below this: no reliable shift (blur, a blank view)
MAX_RESIDUAL = 2.0  # px (thumbnail): a pair's squared residual is capped at this squared
MAX_TRAVEL = 0.002  # m of odometry travel between a pair's frames: more is walking, whose parallax no turn explains
LEARNT_STD = 0.01  # s: a learnt tau's error (the stand-in's 30 ms exposure stamped at its end, 15 ms: 10-14 ms learnt at 1 rad/s, 2-20 at 2)


def camera_heading(odom_theta: np.ndarray, T_robot_camera: np.ndarray) -> np.ndarray:
    """rad: the heading of the camera's optical axis (NAO camera frame: x forward) in the odometry frame,
    for N odometry headings and N x 4 x 4 camera transforms."""
    return odom_theta + np.arctan2(T_robot_camera[..., 1, 0], T_robot_camera[..., 0, 0])


class LatencyEstimator:
    """tau, the camera bound's lateness, from image shifts against the camera's turns (module docstring)."""

    def __init__(self, max_latency: float, focal_px: float, image_width: int, window: int = 300, min_pairs: int = 20,
                 min_latency: float = 0.0):
        if not min_latency <= 0.0 <= max_latency:
            raise ValueError(f"latency grid [{min_latency}, {max_latency}] s must hold 0")
        self.taus = STEP * np.arange(round(min_latency / STEP), round(max_latency / STEP) + 1)
        self._zero = int(np.argmin(np.abs(self.taus)))  # the no-latency candidate
        self.focal = focal_px * THUMB_WIDTH / image_width  # in thumbnail pixels
        self.min_pairs = min_pairs
        self._window = window
        # per frame pair, its squared residual per tau when informative (predicted shift >= MIN_SHIFT), else None
        self._pairs: Deque[Optional[np.ndarray]] = collections.deque()
        self._residual = np.zeros(len(self.taus))  # sum over the informative pairs in the window
        self._previous: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None  # (thumbnail, psi per tau, position)
        self._hanning: Optional[np.ndarray] = None
        self.tau = 0.0
        self.pairs_used = 0

    def add(self, bgr: np.ndarray, bound_stamp: float, history: Tuple[Sequence[float], Sequence[float]],
            position: Sequence[float] = (0.0, 0.0)) -> None:
        """One frame: its image, camera-bound stamp, the history as (stamps, unwrapped psi) arrays, and
        the robot's odometry position (x, y) at the stamp."""
        stamps, psi = history
        if len(stamps) < 2:
            return
        times = bound_stamp - self.taus
        if times[0] < stamps[0] or times[-1] > stamps[-1]:  # no candidate capture inside the history
            self._previous = None
            return
        heading = np.interp(times, stamps, psi)  # held at the ends: candidates past the newest reading
        height = max(1, round(bgr.shape[0] * THUMB_WIDTH / bgr.shape[1]))
        thumb = cv2.resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), (THUMB_WIDTH, height), interpolation=cv2.INTER_AREA)
        thumb = thumb.astype(np.float32)
        if self._hanning is None or self._hanning.shape != thumb.shape:
            self._hanning = cv2.createHanningWindow(thumb.shape[::-1], cv2.CV_32F)
        position = np.asarray(position, dtype=float)
        if self._previous is not None:
            previous, previous_heading, previous_position = self._previous
            (dx, _), response = cv2.phaseCorrelate(previous, thumb, self._hanning)
            if response >= MIN_RESPONSE and math.isfinite(dx) and np.linalg.norm(position - previous_position) <= MAX_TRAVEL:
                turn = np.remainder(heading - previous_heading + math.pi, 2.0 * math.pi) - math.pi
                self._add_pair(float(dx), self.focal * turn)
        self._previous = (thumb, heading, position)

    @property
    def learnt(self) -> bool:
        """Enough turning pairs (``min_pairs``) for an estimate."""
        return self.pairs_used >= self.min_pairs

    def _add_pair(self, dx: float, predicted: np.ndarray) -> None:
        """A frame pair's observed and predicted (per tau) shifts; tau re-chosen over the window."""
        if len(self._pairs) == self._window:
            dropped = self._pairs.popleft()
            if dropped is not None:
                self._residual -= dropped
                self.pairs_used -= 1
        squared = np.minimum((dx - predicted) ** 2, MAX_RESIDUAL**2) if np.abs(predicted).max() >= MIN_SHIFT else None
        self._pairs.append(squared)
        if squared is not None:
            self._residual += squared
            self.pairs_used += 1
        if self.learnt:
            best = int(np.argmin(self._residual))
            if self._residual[best] < self._residual[self._zero]:
                self.tau = float(self.taus[best])
