"""The robot interface the bridge process drives: one class per robot (NAOqi, simulator).

The bridge calls a backend from several threads (camera loop, command handling, deadman,
state publisher): implementations must be thread-safe, and ``stop_walking`` must return
promptly even while another thread is blocked in ``grab_frame``.

All times are the bridge machine's clock (``nao_core.clock.now()``, s: wall time that never jumps):
a backend that reads timestamps in another clock (NAOqi's images carry the robot's clock) converts them.
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

    # -- what the bridge's stop confirmation and the robot-side watchdog need ----------------------

    @property
    def remote(self) -> bool:
        """Whether the robot is on another machine (its link can fail while the bridge runs)."""
        return False

    def move_is_active(self) -> bool:
        """Whether the robot is still walking (confirms a stop); by default from :meth:`read_state`."""
        return bool(self.read_state().walking)

    def kill_move(self) -> None:
        """Stop walking at once, less gently than :meth:`stop_walking` (the escalation of a failed stop)."""
        self.stop_walking()

    def rest(self) -> None:
        """Go to the rest posture, motors off (the last escalation of a failed stop)."""

    def heartbeat(self, count: int) -> None:
        """Tell the robot-side watchdog (nao_bridge.watchdog) the bridge is alive; no-op without one."""

    def watchdog_count(self) -> Optional[int]:
        """The robot-side watchdog's own counter (it changes while the watchdog runs), None without one."""
        return None
