"""The config contract: strict typed loading, errors naming file, key path and expectation."""

from __future__ import annotations

import dataclasses
import logging
import typing
from pathlib import Path

import pytest

from nao_core.config import CONFIG_DIR, ConfigError
from nao_core.landmark_map import load_landmark_map
from nao_core.robot_model import load_robot_model


def write(tmp_path: Path, text: str, name: str = "override.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_defaults_load_v6_and_v5_override_merges():
    v6 = load_robot_model()
    assert v6.name == "nao_v6"
    assert v6.camera.intrinsics("vga").fx == pytest.approx(587.0)
    v5 = load_robot_model([CONFIG_DIR / "robots" / "nao_v5.yaml"])
    assert v5.name == "nao_v5" and v5.camera.sensor == "MT9M114"
    assert v5.walk == v6.walk  # untouched sections come from the defaults


@pytest.mark.parametrize(
    "text, key, expectation",
    [
        ("robot:\n  walk:\n    v_max: fast\n", "robot.walk.v_max", "expected a number in [0.0, 1.0], got 'fast'"),
        ("robot:\n  walk:\n    v_max: 3.0\n", "robot.walk.v_max", "expected a number in [0.0, 1.0], got 3.0"),
        ("robot:\n  walk:\n    v_mx: 0.1\n", "robot.walk.v_mx", "unknown key"),
        ("robot:\n  head:\n    yaw: [1.0]\n", "robot.head.yaw", "expected a list of 2 items, got 1"),
        ("robot:\n  camera:\n    tilt: .nan\n", "robot.camera.tilt", "expected a number"),
        ("robot:\n  neck_height: true\n", "robot.neck_height", "expected a number"),
        ("robot:\n  camera:\n    resolutions:\n      hd: {width: 1280}\n", "robot.camera.resolutions.hd.height", "missing required key"),
    ],
)
def test_bad_override_names_file_key_and_expectation(tmp_path, text, key, expectation):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_robot_model([path])
    message = str(err.value)
    assert message.startswith(f"{path}: {key}: "), message
    assert expectation in message


def test_error_in_default_file_is_attributed_to_default(tmp_path):
    default = write(tmp_path, (CONFIG_DIR / "robots" / "nao_v6.yaml").read_text().replace("v_max: 0.10", "v_max: -1"), "base.yaml")
    with pytest.raises(ConfigError, match=rf"^{default}: robot.walk.v_max: expected a number"):
        load_robot_model(default=default)


def test_cross_field_rule_reported(tmp_path):
    path = write(tmp_path, "robot:\n  camera:\n    resolutions:\n      qvga: {width: 320, height: 240, fx: 300, fy: 300, cx: 400, cy: 120, dist: [0,0,0,0,0]}\n")
    with pytest.raises(ConfigError, match="principal point"):
        load_robot_model([path])


@pytest.mark.parametrize("text", ["robot: [1, 2\n", "- just\n- a list\n", "\x00binary"])
def test_malformed_yaml_is_a_config_error(tmp_path, text):
    with pytest.raises(ConfigError, match=str(tmp_path)):
        load_robot_model([write(tmp_path, text)])


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_robot_model([tmp_path / "nope.yaml"])


def test_landmark_map_rules(tmp_path):
    room = load_landmark_map(CONFIG_DIR / "landmarks" / "sim_room.yaml")
    assert room.of_kind("aruco") and all(lm.kind in ("aruco", "color") for lm in room.landmarks)
    bad = write(tmp_path, "landmarks:\n  - {id: 3, kind: aruco, position: [0, 0, 0.3], yaw: 0}\n")
    with pytest.raises(ConfigError, match=r"landmarks.\[0\]: landmark 3: kind 'aruco' needs"):
        load_landmark_map(bad)
    dup = write(tmp_path, "landmarks:\n  - {id: a, kind: color, color: red, position: [0,0,0]}\n  - {id: a, kind: color, color: red, position: [1,0,0]}\n")
    with pytest.raises(ConfigError, match="duplicate landmark id 'a'"):
        load_landmark_map(dup)
    empty = write(tmp_path, "landmarks: []\n")
    with pytest.raises(ConfigError, match="no landmarks: the robot cannot localize"):
        load_landmark_map(empty)


def test_a_map_that_does_not_say_how_well_it_is_measured_is_held_exact_with_a_warning(tmp_path, caplog):
    """Unstated, ``position_sigma`` and ``yaw_sigma`` are 0 and the loader warns, naming the file and the keys;
    stated, they are the file's (the shipped simulated rooms state 0, without a warning)."""
    row = "landmarks:\n  - {id: g, kind: color, color: green, position: [0, 2, 0.3], diameter: 0.1}\n"
    silent = write(tmp_path, row)
    with caplog.at_level(logging.WARNING):
        assert (load_landmark_map(silent).position_sigma, load_landmark_map(silent).yaw_sigma) == (0.0, 0.0)
    assert str(silent) in caplog.text and "does not say how well it is measured (position_sigma, yaw_sigma): held exact" in caplog.text
    half = tmp_path / "half.yaml"
    half.write_text(row + "position_sigma: 0.002\n")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert (load_landmark_map(half).position_sigma, load_landmark_map(half).yaw_sigma) == (0.002, 0.0)
    assert "(yaw_sigma): held exact" in caplog.text
    for name in ("sim_room", "walls", "colours", "mixed", "sparse", "small_room"):  # simulated: exact, and said
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            shipped = load_landmark_map(CONFIG_DIR / "landmarks" / f"{name}.yaml")
        assert (shipped.position_sigma, shipped.yaw_sigma) == (0.0, 0.0) and "does not say" not in caplog.text


def _defaulted_fields(cls: type, path: str, seen: set) -> list:
    """Dotted names of the fields that carry a value in code, through nested config dataclasses."""
    if cls in seen:
        return []
    seen.add(cls)
    found = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
            found.append(f"{path}.{f.name}")
        for candidate in (hints[f.name], *typing.get_args(hints[f.name])):
            if dataclasses.is_dataclass(candidate):
                found += _defaulted_fields(candidate, f"{path}.{f.name}", seen)
    return found


# Not defaults of a config file: the transport is built from command-line flags (nao_core.transport),
# and a scenario part's yaw and mesh are optional per part (a cylinder has neither).
NOT_FROM_A_FILE = ("bridge.transport", "sim.scenarios.parts.yaw", "sim.scenarios.parts.mesh", "sim.scenarios.finish")


def test_defaults_live_in_the_yaml_files_only():
    """Every section's defaults come from config/*.yaml: no dataclass carries a second, possibly different, value."""
    from nao_bridge.bridge import BridgeParams
    from nao_core.robot_model import RobotModel
    from nao_sim.scenarios import SimConfig
    from station.config import SECTIONS

    sections = {**SECTIONS, "bridge": BridgeParams, "robot": RobotModel, "sim": SimConfig}
    defaulted = [name for section, cls in sections.items() for name in _defaulted_fields(cls, section, set())]
    assert [name for name in defaulted if not name.startswith(NOT_FROM_A_FILE)] == []
