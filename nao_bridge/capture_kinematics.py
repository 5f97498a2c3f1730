"""Capture-time kinematics: a time-stamped history of the robot's readings, interpolated to a stamp.

NAOqi does not return the joint angles with an image, and an image reaches the bridge 30-120 ms
after its capture, so readings taken when it arrives belong to a later instant (the torso has
rolled, the head has turned). The NAOqi backend therefore samples head angles, the camera transform
T_BC and odometry at a high rate into a short history, each sample stamped with the midpoint of the
calls that read it (bridge clock), and evaluates the history at each image's capture stamp.

Between the samples a (stamp t_a) and b (t_b) bracketing t, with alpha = (t - t_a) / (t_b - t_a):

    head      = (1 - alpha) head_a + alpha head_b
    odom xy   = (1 - alpha) xy_a + alpha xy_b,   theta = theta_a + alpha wrap(theta_b - theta_a)
    T_BC      = [R_a Exp(alpha Log(R_a^T R_b)),  (1 - alpha) p_a + alpha p_b]

(translation lerped, rotation on the geodesic: the rotation-matrix form of quaternion slerp, with
Exp/Log by ``cv2.Rodrigues``). A stamp before the oldest sample, after the newest, or between two
samples further apart than ``max_gap`` (the sampler stalled) has no kinematics: ``at`` says why.
"""

from __future__ import annotations

import bisect
import collections
import math
import threading
from typing import Deque, List, NamedTuple, Tuple, Union

import cv2
import numpy as np

from nao_core.geometry import Pose, wrap_angle

BEFORE, AFTER, GAP = "before_history", "after_history", "history_gap"  # reasons a stamp has no kinematics


class KinematicSample(NamedTuple):
    stamp: float  # bridge clock, s
    head: Tuple[float, float]  # (HeadYaw, HeadPitch), rad
    T: np.ndarray  # 4x4 camera transform (any fixed convention)
    odom: Pose


def interpolate_transform(T_a: np.ndarray, T_b: np.ndarray, alpha: float) -> np.ndarray:
    """SE(3) interpolation: lerp of the translation, geodesic (slerp) of the rotation."""
    rotvec, _ = cv2.Rodrigues(T_a[:3, :3].T @ T_b[:3, :3])
    step, _ = cv2.Rodrigues(alpha * rotvec)
    T = np.eye(4)
    T[:3, :3] = T_a[:3, :3] @ step
    T[:3, 3] = (1.0 - alpha) * T_a[:3, 3] + alpha * T_b[:3, 3]
    return T


def interpolate(a: KinematicSample, b: KinematicSample, stamp: float) -> KinematicSample:
    """The readings at ``stamp`` between samples ``a`` and ``b`` (module docstring)."""
    span = b.stamp - a.stamp
    alpha = 0.0 if span <= 0.0 else min(max((stamp - a.stamp) / span, 0.0), 1.0)
    head = tuple((1.0 - alpha) * ha + alpha * hb for ha, hb in zip(a.head, b.head))
    theta = float(wrap_angle(a.odom[2] + alpha * wrap_angle(b.odom[2] - a.odom[2])))
    odom = ((1.0 - alpha) * a.odom[0] + alpha * b.odom[0], (1.0 - alpha) * a.odom[1] + alpha * b.odom[1], theta)
    return KinematicSample(stamp, (float(head[0]), float(head[1])), interpolate_transform(a.T, b.T, alpha), odom)


class KinematicsHistory:
    """The last ``size`` samples in stamp order; thread-safe; ``wait_at`` waits for a sample past a stamp."""

    def __init__(self, size: int, max_gap: float):
        if size < 2 or not max_gap > 0.0:
            raise ValueError(f"kinematics history: need size >= 2 and max_gap > 0, got {size}, {max_gap}")
        self.max_gap = max_gap
        self._samples: Deque[KinematicSample] = collections.deque(maxlen=size)
        self._stamps: Deque[float] = collections.deque(maxlen=size)
        self._changed = threading.Condition()

    def add(self, sample: KinematicSample) -> None:
        """Append a sample; one not newer than the last is ignored (stamps must increase)."""
        with self._changed:
            if self._stamps and sample.stamp <= self._stamps[-1]:
                return
            self._samples.append(sample)
            self._stamps.append(sample.stamp)
            self._changed.notify_all()

    def __len__(self) -> int:
        with self._changed:
            return len(self._samples)

    def samples(self) -> List[KinematicSample]:
        """A copy of the samples kept, oldest first."""
        with self._changed:
            return list(self._samples)

    def at(self, stamp: float) -> Union[KinematicSample, str]:
        """The interpolated readings at ``stamp``, or the reason there are none (BEFORE, AFTER, GAP)."""
        with self._changed:
            return self._at(stamp)

    def wait_at(self, stamp: float, timeout: float) -> Union[KinematicSample, str]:
        """``at(stamp)``, first waiting up to ``timeout`` s for a sample at or after ``stamp``."""
        with self._changed:
            self._changed.wait_for(lambda: bool(self._stamps) and self._stamps[-1] >= stamp, timeout)
            return self._at(stamp)

    def _at(self, stamp: float) -> Union[KinematicSample, str]:
        stamps: List[float] = list(self._stamps)
        if not stamps or stamp > stamps[-1]:
            return AFTER
        if stamp < stamps[0] or not math.isfinite(stamp):
            return BEFORE
        i = bisect.bisect_left(stamps, stamp)  # stamps[i - 1] < stamp <= stamps[i]
        b = self._samples[i]
        if i == 0 or b.stamp == stamp:
            return b
        a = self._samples[i - 1]
        if b.stamp - a.stamp > self.max_gap:
            return GAP
        return interpolate(a, b, stamp)
