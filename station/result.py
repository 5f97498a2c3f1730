"""result.json: the summary of a run that other tools read (fields in docs/result.md, kept stable).

Everything but the outcome and the model comes from the run log, so the same function serves a
live run and a log read afterwards. Path length is the odometry's (sum of |p_k+1 - p_k| over the
received states): smoother than the landmark-corrected poses, whose jitter would add up.
The object's centre: the carved model's centroid (x, y) when the mission completed with a model,
else the filter's; the radius and the covariance stay the filter's (why, and the matrix's figures:
docs/result.md). Against simulator truth (when the log has it)::

    centre_error = |(x, y) - (x_true, y_true)|,   radius_error = r - r_true

and the model against the true shape voxelized on the model's grid (a voxel is true iff its centre
lies in one of the object's parts, a vertical cylinder or a box turned about z)::

    IoU = |M & T| / |M | T|,   containment = |M & T| / |T|,   extent errors = extent(M) - extent(T)
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Union

import numpy as np

from agent.carving import VoxelCarver
from agent.ekf import position_std
from agent.mission import Outcome
from nao_core.protocol import State, Truth, TruthObject, decode
from station.mcap_log import LogError, read_log
from station.topics import COVERAGE, KEYFRAME, STATE, TRUTH

RESULT_VERSION = 1
EXIT_SUCCESS, EXIT_FAILURE, EXIT_CONFIG, EXIT_TIME_LIMIT = 0, 1, 2, 3


def status_of(outcome: str) -> str:
    if outcome == Outcome.COMPLETED.value:
        return "success"
    return "incomplete" if outcome == Outcome.TIME_LIMIT.value else "failure"


def exit_code(outcome: str) -> int:
    return {"success": EXIT_SUCCESS, "incomplete": EXIT_TIME_LIMIT}.get(status_of(outcome), EXIT_FAILURE)


def log_figures(log_path: Union[str, Path]) -> Dict[str, Any]:
    """Path length, final coverage, keyframe count and the last simulator truth from a run log."""
    path_length, previous = 0.0, None
    coverage, keyframes, truth = None, 0, None
    for message in read_log(log_path, topics={STATE, COVERAGE, KEYFRAME, TRUTH}):
        if message.topic == STATE:
            odom = decode(message.data, State).odom
            if previous is not None:
                path_length += math.hypot(odom[0] - previous[0], odom[1] - previous[1])
            previous = odom
        elif message.topic == COVERAGE:
            coverage = message.json()["fraction"]
        elif message.topic == KEYFRAME:
            keyframes += 1
        else:
            truth = decode(message.data, Truth)
    return {"path_length": path_length, "coverage": coverage, "keyframes": keyframes, "truth": truth}


def truth_occupancy(obj: TruthObject, origin: np.ndarray, pitch: float, shape: Tuple[int, int, int]) -> np.ndarray:
    """Bool grid: voxels (centre origin + pitch (i, j, k)) whose centre lies inside the true object."""
    x, y, z = (origin[a] + pitch * np.arange(n) for a, n in enumerate(shape))
    c, s = math.cos(obj.yaw), math.sin(obj.yaw)
    dx, dy = (x - obj.centre[0])[:, None], (y - obj.centre[1])[None, :]
    ox, oy = c * dx + s * dy, -s * dx + c * dy  # object frame
    occupancy = np.zeros(shape, dtype=bool)
    for part in obj.parts:
        px, py = ox - part.centre[0], oy - part.centre[1]
        if part.shape == "cylinder":
            inside_xy = np.hypot(px, py) <= 0.5 * part.size[0]
        else:
            cp, sp = math.cos(part.yaw), math.sin(part.yaw)
            inside_xy = (np.abs(cp * px + sp * py) <= 0.5 * part.size[0]) & (np.abs(-sp * px + cp * py) <= 0.5 * part.size[1])
        inside_z = np.abs(z - part.centre[2]) <= 0.5 * part.size[2]
        occupancy |= inside_xy[:, :, None] & inside_z[None, None, :]
    return occupancy


def _extents(occupancy: np.ndarray, pitch: float) -> np.ndarray:
    """Extents (m) of the occupied voxels along x, y, z."""
    spans = []
    for axis in range(3):
        filled = np.flatnonzero(occupancy.any(axis=tuple(a for a in range(3) if a != axis)))
        spans.append(pitch * (filled[-1] - filled[0] + 1) if filled.size else 0.0)
    return np.array(spans)


def model_accuracy(carver: VoxelCarver, obj: TruthObject) -> Dict[str, float]:
    """The carved model against the true object on the same grid (module docstring)."""
    # The grid grown to hold the whole object too, so parts outside the carving volume count as lost.
    pad_lo = np.maximum(np.ceil((carver.corner - np.array([obj.centre[0] - obj.radius, obj.centre[1] - obj.radius, 0.0])) / carver.pitch), 0).astype(int)
    far = np.array([obj.centre[0] + obj.radius, obj.centre[1] + obj.radius, obj.height])
    pad_hi = np.maximum(np.ceil((far - carver.corner) / carver.pitch) - np.array(carver.shape), 0).astype(int)
    model = np.pad(carver.occupancy, list(zip(pad_lo, pad_hi)))
    true = truth_occupancy(obj, carver.origin - carver.pitch * pad_lo, carver.pitch, model.shape)
    both, either, n_true = (int(np.count_nonzero(g)) for g in (model & true, model | true, true))
    errors = _extents(model, carver.pitch) - _extents(true, carver.pitch)
    return {"iou": both / either if either else 0.0, "containment": both / n_true if n_true else 0.0,
            "true_volume": n_true * carver.pitch**3, "volume_error": float(np.count_nonzero(model) - n_true) * carver.pitch**3,
            "width_error": float(errors[0]), "depth_error": float(errors[1]), "height_error": float(errors[2])}


def build_result(summary, log_path: Path, files: Dict[str, Any], resolution: str) -> Dict[str, Any]:
    """The result.json document of a run (``summary``: station.run.RunSummary); the log may be missing
    or damaged: the log's figures are then absent and ``files["log_error"]`` says why."""
    figures = {"path_length": 0.0, "coverage": None, "keyframes": 0, "truth": None}  # no log: nothing was walked
    if log_path.exists():
        try:
            figures = log_figures(log_path)
        except LogError as exc:  # the mission's own outcome and estimate do not depend on reading it back
            figures = {"path_length": None, "coverage": None, "keyframes": None, "truth": None}  # unknown
            files["log_error"] = str(exc)
    x, P = summary.x, summary.P
    metrics = summary.carver.metrics() if summary.carver is not None else None
    estimate: Optional[Dict[str, Any]] = None
    if x is not None:
        from_model = summary.outcome == Outcome.COMPLETED.value and metrics is not None and metrics.volume > 0.0
        centre = metrics.centroid[:2] if from_model else x[:2]
        estimate = {
            "x": float(centre[0]), "y": float(centre[1]), "r": float(x[2]), "centre_source": "model" if from_model else "filter",
            "filter_x": float(x[0]), "filter_y": float(x[1]), "covariance": np.asarray(P).tolist(),
            "position_std": position_std(P),
            "radius_std": math.sqrt(max(float(P[2, 2]), 0.0)),
        }
    truth = figures["truth"]
    ground_truth = None
    if truth is not None:
        obj = truth.object
        ground_truth = {"x": obj.centre[0], "y": obj.centre[1], "r": obj.radius, "height": obj.height, "kind": obj.kind,
                        "scenario": truth.scenario}
        if estimate is not None:
            ground_truth["centre_error"] = math.hypot(estimate["x"] - obj.centre[0], estimate["y"] - obj.centre[1])
            ground_truth["filter_centre_error"] = math.hypot(estimate["filter_x"] - obj.centre[0], estimate["filter_y"] - obj.centre[1])
            ground_truth["radius_error"] = estimate["r"] - obj.radius
    model = None
    if summary.carver is not None:
        model = {"metrics": dataclasses.asdict(metrics), "pitch": summary.carver.pitch,
                 "views": summary.carver.views_added}
        if truth is not None:
            model["accuracy"] = model_accuracy(summary.carver, truth.object)
    return {
        "version": RESULT_VERSION,
        "status": status_of(summary.outcome),
        "outcome": summary.outcome,
        "reason": summary.reason,
        "object": estimate,
        "coverage": figures["coverage"],
        "path_length": figures["path_length"],
        "duration": summary.duration,
        "frames": {"received": summary.frames_received, "processed": summary.frames_processed,
                   "keyframes": figures["keyframes"], "resolution": resolution},
        "model": model,
        "carving_error": summary.carving_error,
        "ground_truth": ground_truth,
        "files": files,
    }


def write_result(result: Dict[str, Any], path: Path) -> Path:
    path.write_text(json.dumps(result, indent=2) + "\n")
    return path
