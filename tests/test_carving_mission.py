"""A simulated mission's model against the simulator's true object (result.json ``model.accuracy``).

Slow (a real-time mission, ~60 s): ``make test-slow``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from agent.carving import CarvingParams
from nao_core.config import CONFIG_DIR, load
from nao_sim.scenarios import load_sim_config

pytestmark = pytest.mark.serial  # a mission's processes: run alone (Makefile test)

# With the base in view (issue 13) the excess is the conservative shell and mm pose errors; an
# unseen skirt around the base (the failure this guards against) costs about half the IoU (0.51)
# and adds decimetres of width.
MIN_IOU = 0.75
MAX_WIDTH_ERROR = 0.03  # m: a 3 cm margin over a 0.11 m can; the skirt made it 0.12 m wider


def min_containment() -> float:
    """The share of the true can the hull must hold: all but a shell one voxel thick on its side and
    top. The final carve has no dilation (config/carving.yaml) and takes the least tolerance whose
    hull covers the silhouettes, so keyframe poses a voxel pitch off (the configured world's are
    off by a few mm, docs/benchmarks.md) may shave that shell; a hull missing more lost the object."""
    pitch = load(CarvingParams, [CONFIG_DIR / "carving.yaml"], section="carving").pitch
    can = load_sim_config().scenario("can")
    height = float(can.world_points()[:, 2].max())
    return (1.0 - pitch / can.radius) ** 2 * (1.0 - pitch / height)


@pytest.mark.slow
def test_sim_can_mission_model_contains_the_true_object(tmp_path: Path):
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "station.cli", "start", "--robot", "sim", "--scenario", "can", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    result = json.loads((out / "result.json").read_text())
    assert proc.returncode == 0 and result["status"] == "success", (result.get("reason"), proc.stderr[-2000:])
    assert result["model"] is not None, proc.stderr[-2000:]
    accuracy = result["model"]["accuracy"]
    assert accuracy["containment"] >= min_containment(), accuracy
    assert accuracy["iou"] >= MIN_IOU, accuracy
    assert abs(accuracy["width_error"]) <= MAX_WIDTH_ERROR and abs(accuracy["depth_error"]) <= MAX_WIDTH_ERROR, accuracy
