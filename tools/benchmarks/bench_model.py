"""Model quality: the mission's carved model against the truth and against two visual hulls.

For each simulated object (``station start --robot sim --scenario NAME``, one mission each), on one
common 2 mm grid around the true object (voxel centres; truth = centre inside the scenario's parts):

* mission: the run's ``voxels.npz`` (nearest voxel of the run's grid);
* same poses: the visual hull of *exact* masks (the true object's mesh projected) at the run's
  keyframe camera poses (the estimated T_WC the run carved with), k = 0, no dilation, no floor prior;
* ceiling: the visual hull of exact masks from 36 ideal views on a 0.8 m ring at the NAO camera's
  height (0.50 m), aimed at the object's mid-height: the best silhouettes can do (issue 13).

IoU = |A and B| / |A or B| against the truth; Chamfer = mean of the two directed mean distances
between the surface voxels (occupied with an empty 6-neighbour) of the model and of the truth, mm.
Figures (the paper's Fig. 5/6 style: truth, ceiling and mission model side by side, with the
keyframe cameras seen from above) go to ``docs/img/model_<name>.png``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import cv2
import numpy as np
from scipy.ndimage import binary_erosion
from scipy.spatial import cKDTree

from agent.camera import CameraModel
from agent.carving import carve, load_carving_params, load_npz
from agent.mesh import occupancy_to_mesh
from nao_core.geometry import rot2
from nao_core.robot_model import load_robot_model
from nao_sim.scenarios import load_sim_config
from station.mcap_log import read_log
from station.result import log_figures
from station.topics import KEYFRAME

OBJECTS = ("can", "flat_box", "mug", "figure", "bunny")
PITCH = 0.002
RING = 0.8  # m, the ceiling's ring (issue 13)
ROOT = Path(__file__).resolve().parents[2]


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_WC (optical: x right, y down, z forward) of a camera at ``eye`` looking at ``target``, z up."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


def _truth(name: str, centre: Sequence[float], yaw: float, lo: np.ndarray, shape: Tuple[int, int, int], pitch: float) -> np.ndarray:
    """Voxels of the grid (centre lo + pitch (i, j, k)) whose centre lies in the scenario's parts."""
    scenario = load_sim_config().scenarios[name]
    grid = np.stack(np.meshgrid(*(lo[a] + pitch * np.arange(n) for a, n in enumerate(shape)), indexing="ij"), -1).reshape(-1, 3)
    local = grid.copy()
    local[:, :2] = (grid[:, :2] - np.asarray(centre)) @ rot2(yaw)  # world -> object frame (rows times R)
    inside = np.zeros(len(grid), dtype=bool)
    for part in scenario.parts:
        inside |= part.contains(local)
    return inside.reshape(shape)


def _masks(truth: np.ndarray, lo: np.ndarray, camera: CameraModel, poses: Sequence[np.ndarray]) -> List[np.ndarray]:
    """Exact silhouettes: the truth's surface mesh projected and filled, one per pose."""
    mesh = occupancy_to_mesh(truth, lo, PITCH, 0.0)
    masks = []
    for T_WC in poses:
        uv, in_front = camera.project_world(mesh.vertices, T_WC)
        faces = mesh.faces[np.all(in_front[mesh.faces], axis=1)]
        mask = np.zeros((camera.height, camera.width), dtype=np.uint8)
        cv2.fillPoly(mask, list(np.round(uv[faces] * 16).astype(np.int32)), 1, shift=4)
        masks.append(mask)
    return masks


def _surface(occupancy: np.ndarray, lo: np.ndarray) -> np.ndarray:
    inner = binary_erosion(occupancy, border_value=0)
    return lo + PITCH * np.argwhere(occupancy & ~inner)


def _scores(model: np.ndarray, truth: np.ndarray, lo: np.ndarray) -> Dict[str, float]:
    both, either = np.count_nonzero(model & truth), np.count_nonzero(model | truth)
    a, b = _surface(model, lo), _surface(truth, lo)
    chamfer = 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean()) if len(a) and len(b) else math.inf
    width = lambda occ: PITCH * np.ptp(np.flatnonzero(occ.any(axis=(1, 2)))) + PITCH if occ.any() else 0.0  # noqa: E731
    return {"iou": both / either if either else 0.0, "chamfer_mm": 1000.0 * chamfer, "width_error_mm": 1000.0 * (width(model) - width(truth))}


def _figure(name: str, grids: Dict[str, np.ndarray], lo: np.ndarray, poses: Sequence[np.ndarray], centre: Sequence[float]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(12, 3.4))
    for index, (label, occupancy) in enumerate(grids.items()):
        ax = fig.add_subplot(1, len(grids) + 1, index + 1, projection="3d")
        mesh = occupancy_to_mesh(occupancy, lo, PITCH)
        if len(mesh.faces):
            ax.plot_trisurf(*mesh.vertices.T, triangles=mesh.faces, color="tab:red", linewidth=0, shade=True)
        ax.set_box_aspect(np.ptp(mesh.vertices, axis=0) if len(mesh.faces) else (1, 1, 1))
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    ax = fig.add_subplot(1, len(grids) + 1, len(grids) + 1)
    cams = np.array([T[:3, 3] for T in poses]).reshape(-1, 3)
    ax.scatter(cams[:, 0], cams[:, 1], s=10, label="keyframe cameras")
    ax.plot(*centre, "k+", label="object")
    ax.set_aspect("equal")
    ax.legend(fontsize=7)
    ax.set_title("keyframes (top view)", fontsize=9)
    path = ROOT / "docs" / "img" / f"model_{name}.png"
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path.name


def measure(name: str, out: Path) -> Dict[str, object]:
    """One mission on object ``name`` and its scores (module docstring)."""
    run = subprocess.run([str(Path(sys.executable).parent / "station"), "start", "--robot", "sim", "--scenario", name,
                          "--out", str(out)], capture_output=True, text=True, timeout=1200)
    return score(name, out, f"exit {run.returncode}")


def score(name: str, out: Path, failure: str = "no result") -> Dict[str, object]:
    """The scores of the run in ``out`` on object ``name``."""
    result = json.loads((out / "result.json").read_text()) if (out / "result.json").exists() else {}
    if not (out / "voxels.npz").exists():
        return {"status": result.get("status", failure), "error": "no model"}
    truth_msg = log_figures(out / "run.mcap")["truth"].object
    robot = load_robot_model()
    camera = CameraModel.from_intrinsics(robot.camera.intrinsics(result.get("resolution", "qvga")))
    reach = truth_msg.radius + 0.1
    centre = np.asarray(truth_msg.centre, dtype=float)
    lo = np.array([centre[0] - reach, centre[1] - reach, 0.5 * PITCH])
    shape = tuple(int(n) for n in np.ceil(np.array([2 * reach, 2 * reach, truth_msg.height + 0.1]) / PITCH))
    truth = _truth(name, centre, truth_msg.yaw, lo, shape, PITCH)
    occupancy, origin, pitch = load_npz(out / "voxels.npz")
    index = np.round((lo + PITCH * np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), -1) - origin) / pitch).astype(int)
    valid = np.all((index >= 0) & (index < np.array(occupancy.shape)), axis=-1)
    mission = np.zeros(shape, dtype=bool)
    mission[valid] = occupancy[tuple(index[valid].T)]
    poses = [np.asarray(m.json()["T_WC"], dtype=float).reshape(4, 4) for m in read_log(out / "run.mcap", topics={KEYFRAME})]
    exact = dataclasses.replace(load_carving_params(), tolerance=0, dilation=0, floor_prior=False)
    hi = lo + PITCH * np.array(shape)
    corner = lo - 0.5 * PITCH
    same = carve(list(zip(_masks(truth, lo, camera, poses), [camera] * len(poses), poses)), corner, hi - 0.5 * PITCH, PITCH, exact).occupancy
    eye_height = robot.neck_height + robot.camera.offset[2]
    ring = [_look_at(np.array([centre[0] + RING * math.cos(a), centre[1] + RING * math.sin(a), eye_height]),
                     np.array([centre[0], centre[1], 0.5 * truth_msg.height])) for a in np.linspace(0, 2 * math.pi, 36, endpoint=False)]
    ceiling = carve(list(zip(_masks(truth, lo, camera, ring), [camera] * 36, ring)), corner, hi - 0.5 * PITCH, PITCH, exact).occupancy
    scores = {label: _scores(grid[: shape[0], : shape[1], : shape[2]], truth, lo) for label, grid in
              (("mission", mission), ("same_poses", same), ("ceiling", ceiling))}
    figure = _figure(name, {"truth": truth, "ceiling (36 ideal views)": ceiling[: shape[0], : shape[1], : shape[2]],
                            "mission": mission}, lo, poses, centre)
    return {"status": result.get("status"), "duration": result.get("duration"), "keyframes": len(poses), "figure": figure, **scores}


def run(objects: Sequence[str] = OBJECTS) -> str:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in objects:
            m = measure(name, Path(tmp) / name)
            if "error" in m:
                rows.append(f"| {name} | {m['status']} | - | - | - | - | - | - | - |")
                continue
            mi, sp, ce = m["mission"], m["same_poses"], m["ceiling"]
            rows.append(
                f"| {name} | {m['status']}, {m['keyframes']} keyframes | {mi['iou']:.3f} | {sp['iou']:.3f} | {ce['iou']:.3f} | "
                f"{mi['iou'] / ce['iou']:.2f} | {mi['chamfer_mm']:.1f} / {sp['chamfer_mm']:.1f} / {ce['chamfer_mm']:.1f} | "
                f"{mi['width_error_mm']:+.0f} | ![{name}](img/{m['figure']}) |"
            )
    return "\n".join([
        "## Model quality (`model`)",
        "",
        "One simulated mission per object (`station start --robot sim --scenario NAME`); the run's model, the",
        "visual hull of exact masks at the run's keyframe poses, and the 36-view ceiling (0.8 m ring at camera",
        "height), all on one 2 mm grid against the truth (tools/benchmarks/bench_model.py). Targets (issue 13):",
        "mission IoU >= 0.9 of the ceiling (can >= 0.84), can Chamfer <= 3 mm, width within 5 mm (can, box).",
        "",
        "| object | run | IoU mission | IoU same poses | IoU ceiling | mission / ceiling | Chamfer mm (mission / same / ceiling) | width error mm | figure |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *rows,
        "",
        "Command: `.venv/bin/python -m tools.bench --only model`.",
    ])


if __name__ == "__main__":
    names = sys.argv[1:] or OBJECTS
    print(run(names))
