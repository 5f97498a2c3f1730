"""result.json: the summary of a run that other tools read (fields in docs/result.md, kept stable).

Everything but the outcome and the model comes from the run log, so the same function serves a
live run and a log read afterwards. Path length is the odometry's (sum of |p_k+1 - p_k| over the
received states): smoother than the landmark-corrected poses, whose jitter would add up.
Against simulator truth (when the log has it)::

    centre_error = |(x, y) - (x_true, y_true)|,   radius_error = r - r_true
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Dict, Optional, Union

import numpy as np

from agent.mission import Outcome
from nao_bridge.protocol import State, Truth, decode
from station.carving_worker import position_std
from station.mcap_log import read_log
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


def build_result(summary, log_path: Path, files: Dict[str, Any], resolution: str) -> Dict[str, Any]:
    """The result.json document of a run (``summary``: station.run.RunSummary); the log may be missing."""
    figures = log_figures(log_path) if log_path.exists() else {"path_length": 0.0, "coverage": None, "keyframes": 0, "truth": None}
    x, P = summary.x, summary.P
    estimate: Optional[Dict[str, Any]] = None
    if x is not None:
        estimate = {
            "x": float(x[0]), "y": float(x[1]), "r": float(x[2]), "covariance": np.asarray(P).tolist(),
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
            ground_truth["radius_error"] = estimate["r"] - obj.radius
    model = None
    if summary.carver is not None:
        model = {"metrics": dataclasses.asdict(summary.carver.metrics()), "pitch": summary.carver.pitch,
                 "views": summary.carver.views_added}
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
