"""SimBackend: the simulated NAO behind the bridge's ``RobotBackend`` interface.

Frames are paced at ``fps`` on the process clock (``nao_core.clock.now``, the world's default):
``grab_frame`` waits for the next frame slot (t_k = t_0 + k / fps, skipping slots already past, as
a camera does) and renders it. ``close`` wakes a waiting ``grab_frame`` at once.
"""

from __future__ import annotations

import threading
from typing import Optional

from nao_bridge.backend import RobotBackend
from nao_core.clock import now
from nao_core.records import CameraFrame, RobotState
from nao_core.robot_model import RobotModel
from nao_sim.world import SimWorld


class SimBackend(RobotBackend):
    def __init__(self, world: SimWorld, fps: Optional[float] = None):
        fps = world.config.fps if fps is None else fps
        if not fps > 0.0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.world = world
        self.period = 1.0 / fps
        self._closed = threading.Event()
        self._next_slot: Optional[float] = None
        self._grab_lock = threading.Lock()

    @classmethod
    def in_new_world(cls, scenario: str, model: RobotModel, resolution: str, seed: int, fps: float) -> "SimBackend":
        """A backend on a fresh simulated world; KeyError names an unknown scenario."""
        return cls(SimWorld(scenario, model, resolution=resolution, seed=seed), fps=fps)

    def start(self) -> None:
        self._closed.clear()
        self._next_slot = now()

    def close(self) -> None:
        if not self._closed.is_set():
            self._closed.set()
            self.world.stop_walking()

    def grab_frame(self, timeout: float) -> Optional[CameraFrame]:
        with self._grab_lock:
            if self._closed.is_set():
                return None
            t = now()
            if self._next_slot is None:
                self._next_slot = t
            if self._next_slot < t - self.period:  # slots missed: skip to the next one
                self._next_slot += self.period * int((t - self._next_slot) / self.period)
            wait = self._next_slot - t
            if wait > timeout:
                self._closed.wait(timeout)
                return None
            if wait > 0.0 and self._closed.wait(wait):
                return None
            self._next_slot += self.period
            return self.world.render()

    def walk(self, v: float, vy: float, omega: float) -> None:
        self.world.walk(v, vy, omega)

    def stop_walking(self) -> None:
        self.world.stop_walking()

    def set_head(self, yaw: float, pitch: float, speed_fraction: float) -> None:
        self.world.set_head(yaw, pitch, speed_fraction)

    def read_state(self) -> RobotState:
        return self.world.state()

    def ground_truth(self) -> dict:
        return self.world.truth()
