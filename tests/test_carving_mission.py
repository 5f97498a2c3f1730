"""A simulated mission's model against the simulator's true object (result.json ``model.accuracy``).

Slow (a real-time mission, ~60 s): ``make test-slow``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

MIN_CONTAINMENT = 0.99  # the conservative hull must hold the true object
# With the base in view (issue 13) the excess is the conservative shell (~0.75 voxel + 1 px dilation)
# and mm pose errors; an unseen skirt around the base (the failure this guards against) costs about
# half the IoU (0.51) and adds decimetres of width.
MIN_IOU = 0.75
MAX_WIDTH_ERROR = 0.03  # m: a 3 cm margin over a 0.11 m can; the skirt made it 0.12 m wider


@pytest.mark.slow
def test_sim_can_mission_model_contains_the_true_object(tmp_path: Path):
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "station.cli", "start", "--robot", "sim", "--scenario", "can", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    result = json.loads((out / "result.json").read_text())
    assert result["model"] is not None, proc.stderr[-2000:]
    accuracy = result["model"]["accuracy"]
    assert accuracy["containment"] >= MIN_CONTAINMENT, accuracy
    assert accuracy["iou"] >= MIN_IOU, accuracy
    assert abs(accuracy["width_error"]) <= MAX_WIDTH_ERROR and abs(accuracy["depth_error"]) <= MAX_WIDTH_ERROR, accuracy
