"""Run the 2-D active-reconstruction simulation: Fig.-4-like figures and the 50-seed comparison table.

    .venv/bin/python -m tools.plan_sim                      # both, into docs/img and docs/planner.md
    .venv/bin/python -m tools.plan_sim --seeds 10 --no-figures --out /tmp/planner.md

Figures: the corrected cost from one start for two values of d_min (the paper's Fig. 4): path,
measured bearing rays, 2-sigma position ellipses of the estimate, true object. Table: over N
seeds (:func:`nao_sim.sim2d.random_scenario`), a passive circle at d_min around the first estimate,
the paper's cost as printed, the corrected cost on the unicycle and with the lateral speed
(``omnidirectional``), all with the CEM optimizer, scored against the true object: final centre and
radius errors, runs that saw every bin, steps and path length to full coverage, closest approach
to the true surface.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np

from agent.camera import CameraModel
from agent.ekf import EKFParams, load_ekf_params
from agent.planner import PlannerParams, load_planner_params
from nao_core.config import ConfigError, main_error
from nao_core.robot_model import load_robot_model
from nao_sim.sim2d import SimResult, SimRobot, random_scenario, simulate
from tools.demo_estimation import sigma_ellipse

PAPER_FORMS = dict(uncertainty_form="paper", view_form="paper", coverage_form="paper", distance_form="paper")
TABLE_BEGIN, TABLE_END = "<!-- plan_sim:table -->", "<!-- /plan_sim:table -->"
FIGURE_D_MIN = (0.6, 1.0)


def sim_robot() -> SimRobot:
    model = load_robot_model()
    hfov = CameraModel.from_intrinsics(model.camera.intrinsics("vga")).hfov
    return SimRobot(model.walk, hfov, model.head.yaw, model.camera.offset[0])


def figure(result: SimResult, d_min: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    fig, ax = plt.subplots(figsize=(6.4, 6.4))
    truth = result.truth
    ax.add_patch(Circle(truth[:2], truth[2], color="saddlebrown", alpha=0.8, label="true object"))
    ax.add_patch(Circle(truth[:2], d_min, fill=False, ls=":", color="grey", label=f"d_min = {d_min} m"))
    for cam, (phi, delta) in zip(result.cameras, result.measurements):
        if np.isfinite(phi):
            rng = truth[2] / math.sin(0.5 * delta)
            end = cam[:2] + rng * np.array([math.cos(cam[2] + phi), math.sin(cam[2] + phi)])
            ax.plot([cam[0], end[0]], [cam[1], end[1]], color="tab:blue", lw=0.4, alpha=0.35)
    for k in np.unique(np.geomspace(1, len(result.poses) - 1, 8).astype(int)):
        x, P = result.estimates[k], result.covariances[k]
        if np.all(np.isfinite(x)):
            sigma_ellipse(ax, x[:2], P[:2, :2], sigmas=2.0, color="darkorange", lw=1.2)
    ax.plot(*result.poses[:, :2].T, "-", color="k", lw=1.0, label="robot path")
    ax.plot(*result.poses[::5, :2].T, "o", ms=3, color="k")
    ax.plot(*result.poses[0, :2], "s", ms=7, color="tab:green", label="start")
    full = result.steps_to_full_coverage()
    err_c, err_r = result.final_errors()
    ax.set_title(
        f"d_min = {d_min} m: {len(result.poses)} steps, full coverage at step {full}\n"
        f"final centre error {1000 * err_c:.1f} mm, radius error {1000 * err_r:.1f} mm",
        fontsize=10,
    )
    ax.plot([], [], color="tab:blue", lw=0.6, label="measured bearings")
    ax.plot([], [], color="darkorange", lw=1.2, label="2-sigma position ellipse")
    corners = np.vstack([result.poses[:, :2], truth[:2] - d_min, truth[:2] + d_min])
    lo, hi = corners.min(axis=0) - 0.3, corners.max(axis=0) + 0.3
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def score(results: List[SimResult], clearance: float) -> Dict[str, str]:
    centre = np.array([1000 * r.final_errors()[0] for r in results])
    radius = np.array([1000 * r.final_errors()[1] for r in results])
    steps = [r.steps_to_full_coverage() for r in results]
    reached = [s for s in steps if s is not None]
    paths = [r.path_length[s] for r, s in zip(results, steps) if s is not None]
    closest = [float(np.min(np.hypot(*(r.poses[:, :2] - r.truth[:2]).T) - r.truth[2])) for r in results]
    return {
        "centre error mm, median / 90 %": f"{np.median(centre):.1f} / {np.percentile(centre, 90):.1f}",
        "radius error mm, median / 90 %": f"{np.median(radius):.1f} / {np.percentile(radius, 90):.1f}",
        "runs with full coverage": f"{len(reached)} / {len(results)}",
        "steps to full coverage, median (max)": f"{np.median(reached):.0f} ({max(reached)})" if reached else "never",
        "path to full coverage m, median": f"{np.median(paths):.2f}" if paths else "never",
        f"closest to the surface m, min (clearance {clearance})": f"{min(closest):.2f}",
        "runs ended 'complete'": f"{sum(r.reason.startswith('complete') for r in results)} / {len(results)}",
    }


def comparison(params: PlannerParams, ekf: EKFParams, robot: SimRobot, seeds: int) -> str:
    variants = {
        "passive circle (initial guess)": (params, "circle"),
        "paper's cost as printed": (dataclasses.replace(params, **PAPER_FORMS), "planner"),
        "corrected cost": (dataclasses.replace(params, omnidirectional=False), "planner"),
        "corrected cost, omnidirectional": (dataclasses.replace(params, omnidirectional=True), "planner"),
    }
    columns = {}
    for name, (variant, policy) in variants.items():
        print(f"plan_sim: {name}: {seeds} seeds ...", file=sys.stderr, flush=True)
        runs = [simulate(*random_scenario(seed), variant, ekf, robot, seed, policy) for seed in range(seeds)]
        columns[name] = score(runs, params.clearance)
    rows = list(next(iter(columns.values())))
    lines = ["| metric | " + " | ".join(columns) + " |", "| --- |" + " --- |" * len(columns)]
    lines += [f"| {row} | " + " | ".join(col[row] for col in columns.values()) + " |" for row in rows]
    return "\n".join(lines)


def write_table(doc: Path, table: str, seeds: int) -> None:
    block = f"{TABLE_BEGIN}\n_{seeds} seeds, generated by `.venv/bin/python -m tools.plan_sim`._\n\n{table}\n{TABLE_END}"
    text = doc.read_text() if doc.exists() else f"# Planner\n\n{block}\n"
    pattern = re.compile(re.escape(TABLE_BEGIN) + ".*?" + re.escape(TABLE_END), re.S)
    doc.write_text(pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block + "\n")


def main(argv: List[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50, help="scenarios in the comparison table")
    parser.add_argument("--config", action="append", default=[], help="planner config override YAML (repeatable)")
    parser.add_argument("--out", type=Path, default=Path("docs/planner.md"), help="document holding the table")
    parser.add_argument("--img", type=Path, default=Path("docs/img"), help="folder for the figures")
    parser.add_argument("--no-figures", action="store_true")
    parser.add_argument("--no-table", action="store_true")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds must be at least 1, got {args.seeds}")
    try:
        params = load_planner_params(args.config)
    except ConfigError as exc:
        return main_error(exc)
    robot, ekf = sim_robot(), load_ekf_params()
    if not args.no_figures:
        truth, start = np.array([0.0, 0.0, 0.1]), np.array([2.0, 0.6, math.pi])
        for d_min in FIGURE_D_MIN:
            result = simulate(truth, start, dataclasses.replace(params, d_min=d_min), ekf, robot, seed=0)
            path = args.img / f"planner_dmin_{d_min:.1f}.png"
            figure(result, d_min, path)
            print(f"plan_sim: wrote {path} ({result.reason})", file=sys.stderr)
    if not args.no_table:
        table = comparison(params, ekf, robot, args.seeds)
        print(table)
        write_table(args.out, table, args.seeds)
        print(f"plan_sim: wrote the table into {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
