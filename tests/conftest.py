"""Fixtures shared by the test modules.

Shared data sets live beside the repository (``../shared`` from its root, ``SHARED``); a test that
needs one fails with a message saying what is missing and where it was looked for, never skips.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from nao_core.robot_model import RobotModel, load_robot_model

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared"
MIDDLEBURY_TEMPLE = SHARED / "data" / "middlebury" / "templeSparseRing"


@pytest.fixture(scope="session")
def robot() -> RobotModel:
    """The default robot model (NAO V6)."""
    return load_robot_model()


@pytest.fixture(scope="session")
def middlebury_temple() -> Path:
    """The Middlebury templeSparseRing data set (images and templeSR_par.txt), or a clear failure."""
    if not (MIDDLEBURY_TEMPLE / "templeSR_par.txt").is_file():
        pytest.fail(f"data set missing: Middlebury templeSparseRing expected at {MIDDLEBURY_TEMPLE} "
                    "(../shared/data/middlebury/templeSparseRing from the repository root)", pytrace=False)
    return MIDDLEBURY_TEMPLE
