"""Fixtures shared by the test modules.

Shared data sets live beside the repository (``../shared`` from its root); a clone made elsewhere
(a CI checkout in a temporary folder) finds them beside the repository it was cloned from, and
``$NAO_RECON_SHARED`` names another place. A test that needs one fails with a message saying what
is missing and where it was looked for, never skips.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from nao_core.robot_model import RobotModel, load_robot_model

ROOT = Path(__file__).resolve().parent.parent


def _shared_candidates() -> list:
    """Where the shared data may be: $NAO_RECON_SHARED, ../shared, ../shared of the clone's origin."""
    places = [Path(os.environ["NAO_RECON_SHARED"])] if os.environ.get("NAO_RECON_SHARED") else []
    places.append(ROOT.parent / "shared")
    origin = subprocess.run(["git", "-C", str(ROOT), "remote", "get-url", "origin"], capture_output=True, text=True)
    if origin.returncode == 0 and Path(origin.stdout.strip()).is_dir():  # a local clone: its source's neighbour
        places.append(Path(origin.stdout.strip()).resolve().parent / "shared")
    return places


SHARED_CANDIDATES = _shared_candidates()
TEMPLE = Path("data") / "middlebury" / "templeSparseRing"
SHARED = next((place for place in SHARED_CANDIDATES if (place / TEMPLE).is_dir()), SHARED_CANDIDATES[0])
MIDDLEBURY_TEMPLE = SHARED / TEMPLE


@pytest.fixture(scope="session")
def robot() -> RobotModel:
    """The default robot model (NAO V6)."""
    return load_robot_model()


@pytest.fixture(scope="session")
def middlebury_temple() -> Path:
    """The Middlebury templeSparseRing data set (images and templeSR_par.txt), or a clear failure."""
    if not (MIDDLEBURY_TEMPLE / "templeSR_par.txt").is_file():
        looked = ", ".join(str(place / TEMPLE) for place in SHARED_CANDIDATES)
        pytest.fail(f"data set missing: Middlebury templeSparseRing not found; looked in {looked} "
                    "(set NAO_RECON_SHARED to the folder holding data/middlebury)", pytrace=False)
    return MIDDLEBURY_TEMPLE


CI_SEED = 23  # the default suite's whole mission (tests/test_matrix.py names its world)


@pytest.fixture(scope="session")
def ci_mission(tmp_path_factory):
    """The default suite's one whole mission, run once: matrix world ``CI_SEED`` through the NAOqi
    stand-in (tools.matrix.run_mission). tests/test_matrix.py checks its outcome and accuracy;
    tests/test_station_mission.py replays and re-carves its log."""
    from tools.matrix import run_mission

    return run_mission(CI_SEED, tmp_path_factory.mktemp(f"matrix{CI_SEED}"))

