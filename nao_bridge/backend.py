"""The robot interface the bridge process drives: one class per robot (NAOqi, simulator).

The bridge calls a backend from several threads (camera loop, command handling, deadman,
state publisher): implementations must be thread-safe, and ``stop_walking`` must return
promptly even while another thread is blocked in ``grab_frame``.

All times are the bridge machine's clock (``time.time()``, seconds): a backend that reads
timestamps in another clock (NAOqi's images carry the robot's clock) converts them.
Camera poses are in the optical convention (``nao_core.robot_model``).
"""

from __future__ import annotations

import abc
from typing import Optional

from nao_core.records import CameraFrame, RobotState


class RobotBackend(abc.ABC):
    """What the bridge needs from a robot, real or simulated."""

    @abc.abstractmethod
    def start(self) -> None:
        """Connect and prepare (wake up, posture, camera subscription)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop walking, release the camera, rest if configured. Idempotent."""

    @abc.abstractmethod
    def grab_frame(self, timeout: float) -> Optional[CameraFrame]:
        """The next new frame, or None when none arrived within ``timeout`` seconds."""

    @abc.abstractmethod
    def walk(self, v: float, vy: float, omega: float) -> None:
        """Walk at the given velocities (already clamped by the caller), until told otherwise."""

    @abc.abstractmethod
    def stop_walking(self) -> None:
        """Stop walking now."""

    @abc.abstractmethod
    def set_head(self, yaw: float, pitch: float, speed_fraction: float) -> None:
        """Move the head towards the given angles (already clamped by the caller)."""

    @abc.abstractmethod
    def read_state(self) -> RobotState:
        """Odometry, head angles, walking and fall flags, battery."""

    def ground_truth(self) -> Optional[dict]:
        """Simulator truth (robot pose, object) as a JSON-able dict; None on a real robot."""
        return None
