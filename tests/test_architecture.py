"""The package arrows of docs/architecture.md, checked on the import statements of every module.

    station -> agent -> nao_core <- nao_bridge        station -> nao_core        nao_sim -> nao_core

The bridge stays light (no SciPy, no algorithms) and reaches the simulator only through its thin
simulated backend, imported for ``--sim``; the 2-D planner simulation closes the loop around the
agent's planner, so it alone in nao_sim imports agent. The suite's own shape: a test module that starts processes or
sessions is marked ``serial`` (Makefile ``test`` runs those alone, docs/testing.md).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PROJECT = {"agent", "station", "nao_bridge", "nao_core", "nao_sim", "tools", "tests"}
ALLOWED = {
    "nao_core": set(),
    "agent": {"nao_core"},
    "station": {"agent", "nao_core"},
    "nao_bridge": {"nao_core"},
    "nao_sim": {"nao_core"},
}
EXCEPTIONS = {
    ("nao_bridge/sim_backend.py", "nao_sim"),  # the simulated backend, imported only for --sim
    ("nao_sim/sim2d.py", "agent"),  # the 2-D simulation runs the agent's planner in the loop
}
STATION_ONLY_LIBRARIES = ["scipy", "skimage", "trimesh", "matplotlib", "mcap", "numba"]


def imports(package: str) -> list[tuple[str, str]]:
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                found += [(str(path.relative_to(ROOT)), alias.name) for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.append((str(path.relative_to(ROOT)), node.module))
            elif isinstance(node, ast.ImportFrom) and node.level > 0:
                found.append((str(path.relative_to(ROOT)), "<relative>"))
    return found


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_package_imports_follow_the_arrows(package):
    """A package imports only itself and the packages its arrows point to (absolute imports only)."""
    offenders = []
    for file, module in imports(package):
        top = module.split(".")[0]
        if module == "<relative>" or (top in PROJECT and top != package and top not in ALLOWED[package]
                                       and (file, top) not in EXCEPTIONS):
            offenders.append((file, module))
    assert not offenders


@pytest.mark.parametrize("package", ["nao_bridge", "nao_core"])
@pytest.mark.parametrize("library", STATION_ONLY_LIBRARIES)
def test_robot_side_stays_light(package, library):
    """The robot-side process and the core it shares import no station-only library."""
    assert not [(f, m) for f, m in imports(package) if m.split(".")[0] == library]


def test_exceptions_are_still_needed():
    """Each allowed exception is used; an unused one would silently widen the arrows."""
    used = {(f, m.split(".")[0]) for package in ALLOWED for f, m in imports(package)}
    assert EXCEPTIONS <= used


# What a test needs to start a process, a session or a paced simulator (tests/zenoh_peers.py, tools/matrix.py)
PROCESS_NAMES = {"subprocess", "Popen", "StandIn", "SimBackend", "bridge_on_standin", "run_mission", "zenoh",
                 "ci_mission", "BridgeLink"}


def test_test_modules_that_start_processes_are_marked_serial():
    """A module naming any of PROCESS_NAMES carries ``pytest.mark.serial`` (on the module or on its
    tests that do): unmarked, `make test` would run it beside another test on a loaded core. A
    module's unmarked test that starts one beside marked ones is not caught."""
    unmarked = []
    for path in sorted((ROOT / "tests").glob("test_*.py")):
        text = path.read_text()
        names = set()
        for node in ast.walk(ast.parse(text, filename=str(path))):
            if isinstance(node, ast.Name):
                names.add(node.id)
            elif isinstance(node, ast.Attribute):
                names.add(node.attr)
            elif isinstance(node, ast.arg):
                names.add(node.arg)
            elif isinstance(node, (ast.Import, ast.ImportFrom)):
                names.update(alias.name.split(".")[0] for alias in node.names)
        if names & PROCESS_NAMES and "pytest.mark.serial" not in text:
            unmarked.append((path.name, sorted(names & PROCESS_NAMES)))
    assert not unmarked
