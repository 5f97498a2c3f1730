"""Planner: per-replan time and cost reached, scipy Nelder-Mead (the paper's way) against batched CEM + polish.

The belief states are replayed from one 2-D simulation run (seed 0, the passive circle policy, so
the states do not depend on the optimizer being measured): every third step, robot pose, estimate,
covariance and the coverage of the path so far. At each horizon
both optimizers plan on the same states in order (each keeps its own warm start) and minimize the
same cost; Nelder-Mead evaluates it one candidate per call, CEM a batch of candidates per call.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Tuple

import numpy as np

from agent.coverage import Coverage
from agent.ekf import load_ekf_params
from agent.planner import Planner, load_planner_params
from nao_core.robot_model import load_robot_model
from nao_sim.sim2d import SimRobot, simulate

HORIZONS = (5, 10, 20)
STRIDE = 3


def recorded_states(params, ekf, robot):
    truth, start = np.array([0.0, 0.0, 0.1]), np.array([2.0, 0.3, math.pi])
    run = simulate(truth, start, params, ekf, robot, seed=0, policy="circle", max_steps=90)
    for k in range(1, len(run.poses) - 1, STRIDE):
        coverage = Coverage(params.coverage, robot.hfov)
        for cam in run.cameras[: k + 1]:
            coverage.add(cam)
        yield run.poses[k], run.estimates[k], run.covariances[k], coverage


def replay(planner: Planner, states) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Wall and CPU ms per replan, cost reached and candidates costed, state by state."""
    wall, cpu, costs, evaluations = [], [], [], []
    for pose, x, P, coverage in states:
        t0, c0 = time.perf_counter(), time.process_time()
        plan = planner.plan(pose, x, P, coverage)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        costs.append(plan.cost)
        evaluations.append(plan.evaluations)
    return 1000.0 * np.array(wall), 1000.0 * np.array(cpu), np.array(costs), np.array(evaluations)


def run() -> str:
    model = load_robot_model()
    intr = model.camera.intrinsics("vga")
    hfov = 2.0 * math.atan(0.5 * intr.width / intr.fx)
    robot = SimRobot(model.walk, hfov, model.head.yaw, model.camera.offset[0])
    base, ekf = load_planner_params(), load_ekf_params()
    states = list(recorded_states(base, ekf, robot))
    rows = []
    for horizon in HORIZONS:
        results = {}
        variants = {
            "nelder_mead": dict(optimizer="nelder_mead"),
            "cem": dict(optimizer="cem"),
            "cem, no polish": dict(optimizer="cem", cem=dataclasses.replace(base.cem, polish_calls=0)),
        }
        for name, changes in variants.items():
            params = dataclasses.replace(base, horizon=horizon, **changes)
            planner = Planner(params, robot.walk, hfov, robot.head_yaw_limits, robot.camera_offset, ekf)
            results[name] = replay(planner, states)
        nm_cost = results["nelder_mead"][2]
        for optimizer, (wall, cpu, costs, evaluations) in results.items():
            gap = 100.0 * (costs - nm_cost) / nm_cost
            not_worse = int(np.sum(costs <= nm_cost * (1 + 1e-9)))
            rows.append(
                f"| {horizon} | {optimizer} | {np.median(wall):.2f} | {np.percentile(wall, 90):.2f} | "
                f"{np.median(cpu):.2f} | {np.median(evaluations):.0f} | {np.mean(costs):.4f} | "
                f"{np.median(gap):+.3f} / {np.max(gap):+.2f} | {not_worse} / {len(costs)} |"
            )
    table = "\n".join(rows)
    return f"""## Planner: per-replan time and cost, Nelder-Mead vs CEM

{__doc__.splitlines()[0]} {len(states)} belief states replayed from one simulated run (every
{STRIDE}rd step); same cost function (config/planner.yaml, corrected forms), same warm-start rule.
Nelder-Mead: scipy.optimize.minimize(method="Nelder-Mead"), bounds at +-omega_max, initial simplex
edges 0.25 omega_max, scipy's default stopping rules (up to 200 D iterations). CEM: one batched
rollout of all candidates per iteration, then a TNC polish on batched finite-difference gradients
(config `cem`); "cem, no polish" is the CEM alone. "vs NM" is the median and the largest over the
states of the relative cost difference to Nelder-Mead's, "<= NM" the states where the cost is not
above Nelder-Mead's, "costed" the candidate sequences evaluated per replan (median). Wall and CPU
(process) time per replan: the 2 cores were shared with several other engineers' jobs, so wall
times are noisy and inflated, and CPU times are inflated too (shared caches and cores); compare the
rows of one run.

Command: `.venv/bin/python -m tools.bench --only planner`

| horizon D | optimizer | median ms | p90 ms | CPU median ms | costed | mean cost | vs NM %, median / max | <= NM |
| --- | --- | --- | --- | --- | --- | --- | --- | --- |
{table}
"""
