"""The package boundaries of DESIGN.md, checked on the import statements of every module."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NAO_BRIDGE_PUBLIC = {"nao_bridge", "nao_bridge.config", "nao_bridge.robot_model", "nao_bridge.landmark_map", "nao_bridge.protocol"}


def imports(package: str) -> list[tuple[str, str]]:
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                found += [(str(path.relative_to(ROOT)), alias.name) for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.append((str(path.relative_to(ROOT)), node.module))
    return found


@pytest.mark.parametrize("forbidden", ["agent", "station", "scipy", "skimage", "trimesh", "matplotlib", "mcap", "numba"])
def test_bridge_stays_light(forbidden):
    """The robot-side process imports neither the algorithms, the station, nor station-only libraries."""
    offenders = [(f, m) for f, m in imports("nao_bridge") if m == forbidden or m.startswith(forbidden + ".")]
    assert not offenders


def test_agent_is_pure():
    """The algorithms never import the station, and use only the bridge's public data modules."""
    offenders = [(f, m) for f, m in imports("agent")
                 if m.split(".")[0] == "station" or (m.startswith("nao_bridge") and m not in NAO_BRIDGE_PUBLIC)]
    assert not offenders
