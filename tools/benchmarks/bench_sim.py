"""Simulator render time per frame at QVGA and VGA (target: VGA comfortably faster than 15 fps).

For each scenario and resolution, ``SimWorld.render()`` is timed over frames taken from poses on
an orbit of 0.6-1.2 m around the object with the camera aimed at it (object and several landmark
boards in view): wall time per frame (median, p95) and process CPU time per frame (all threads of
OpenCV and NumPy counted, so it is the cost in cores). Also the cost of the world's dynamics: CPU
per simulated second of walking (200 fixed steps). The machine is shared by several engineers:
the figures are noisy.
"""

from __future__ import annotations

import math
import time

import numpy as np

from nao_core.robot_model import load_robot_model
from nao_sim.world import SimWorld

FRAMES = 120


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _orbit_render_times(scenario: str, resolution: str) -> tuple:
    robot = load_robot_model()
    world = SimWorld(scenario, robot, resolution, seed=0, clock=_Clock())
    rng = np.random.default_rng(0)
    ox, oy = world.scenario.position
    wall, cpu = [], []
    for _ in range(FRAMES):
        d, az = rng.uniform(0.6, 1.2), rng.uniform(-math.pi, math.pi)
        pose = (ox + d * math.cos(az), oy + d * math.sin(az), az + math.pi)
        world.teleport(pose, robot.look_at(pose, (ox, oy, 0.5 * world.scenario.height)))
        w0, c0 = time.perf_counter(), time.process_time()
        world.render()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return np.array(wall) * 1e3, np.array(cpu) * 1e3


def _dynamics_cost() -> float:
    clock = _Clock()
    world = SimWorld("can", load_robot_model(), "qvga", seed=0, clock=clock)
    world.set_head(0.5, 0.1, 0.1)
    world.walk(0.08, 0.02, 0.2)
    c0 = time.process_time()
    for _ in range(100):
        clock.t += 0.1
        world.odometry()
    return (time.process_time() - c0) / 10.0 * 1e3


def run() -> str:
    rows = []
    for resolution in ("qvga", "vga"):
        for scenario in ("can", "remote", "figure"):
            wall, cpu = _orbit_render_times(scenario, resolution)
            rows.append(
                f"| {resolution} | {scenario} | {np.median(wall):.1f} | {np.percentile(wall, 95):.1f} | "
                f"{np.median(cpu):.1f} | {1e3 / np.median(wall):.0f} |"
            )
    table = "\n".join(
        ["| resolution | scenario | wall median (ms) | wall p95 (ms) | CPU median (ms) | frames/s (median) |",
         "| --- | --- | --- | --- | --- | --- |", *rows]
    )
    return (
        "## Simulator rendering\n\n"
        f"`SimWorld.render()` per frame over {FRAMES} poses on a 0.6-1.2 m orbit around the object, camera aimed "
        "at it (ray-cast floor and walls, object, ArUco boards, balls, noise). Wall time and process CPU time "
        "(all threads). Target: VGA comfortably faster than 15 fps (66.7 ms). Shared 2-core machine: noisy.\n\n"
        "Command: `.venv/bin/python -m tools.bench --only sim`\n\n"
        f"{table}\n\n"
        f"World dynamics while walking and turning the head: {_dynamics_cost():.1f} ms CPU per simulated second "
        "(200 steps of 5 ms).\n"
    )


if __name__ == "__main__":
    print(run())
