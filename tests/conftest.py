"""Fixtures shared by the test modules."""

from __future__ import annotations

import pytest

from nao_core.robot_model import RobotModel, load_robot_model


@pytest.fixture(scope="session")
def robot() -> RobotModel:
    """The default robot model (NAO V6)."""
    return load_robot_model()
