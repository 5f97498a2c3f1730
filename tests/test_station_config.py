"""Station configuration: all sections composed from config/*.yaml, overrides checked strictly."""

from __future__ import annotations

import pytest

from nao_core.config import CONFIG_DIR, ConfigError
from nao_core.landmark_map import load_landmark_map
from station.config import SECTIONS, StationParams, load_station_config


def test_defaults_compose_every_section():
    config = load_station_config()
    for name in SECTIONS:
        assert getattr(config, name) is not None
    with pytest.raises(TypeError):  # the defaults live in config/station.yaml only
        StationParams()
    assert config.station.control_period < 0.3  # walk commands must beat the bridge's deadman
    assert config.landmarks == load_landmark_map(CONFIG_DIR / "landmarks" / "sim_room.yaml")


def test_override_merges_into_several_sections(tmp_path):
    override = tmp_path / "o.yaml"
    override.write_text("mission:\n  max_duration: 42\nstation:\n  port: 7500\n")
    config = load_station_config([override])
    assert config.mission.max_duration == 42.0 and config.station.port == 7500
    assert config.mission.search_dwell == load_station_config().mission.search_dwell


def test_robot_section_goes_to_started_bridges(tmp_path):
    override = tmp_path / "cam.yaml"
    override.write_text("robot:\n  neck_height: 0.44\n")
    assert load_station_config([override]).robot_overrides == (override,)


@pytest.mark.parametrize(
    "text, match",
    [
        ("missoin:\n  max_duration: 3\n", r"o.yaml: missoin: unknown section"),
        ("mission:\n  max_duration: -3\n", r"o.yaml: mission.max_duration: expected a number in \[1.0"),
        ("station:\n  landmark_map: /nonexistent.yaml\n", r"/nonexistent.yaml: cannot read"),
        ("[1, 2]\n", r"o.yaml: expected a mapping of sections"),
    ],
)
def test_bad_override_is_named(tmp_path, text, match):
    override = tmp_path / "o.yaml"
    override.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_station_config([override])


def test_provenance_names_the_file_that_set_each_key(tmp_path):
    from station.config import provenance

    first, second = tmp_path / "a.yaml", tmp_path / "b.yaml"
    first.write_text("mission:\n  max_duration: 42\nstation:\n  port: 7500\n")
    second.write_text("station:\n  port: 7600\n")
    table = provenance([first, second])
    assert table["mission.max_duration"] == (42.0, str(first))
    assert table["station.port"] == (7600, str(second))  # the later file wins
    assert table["station.flush_interval"][1] == str(CONFIG_DIR / "station.yaml")
    config = load_station_config([first, second])
    assert {k.split(".")[0] for k in table} == set(SECTIONS) and table["ekf." + next(iter(vars(config.ekf)))][1] != "default"


@pytest.mark.parametrize(
    "colour, match",
    [
        ("red", r"m.yaml: landmark 'b-2': colour 'red' is the object's \(perception.object_color\)"),
        ("orange", r"m.yaml: landmark 'b-2': colour 'orange' is not a perception colour class"),
    ],
)
def test_a_ball_of_the_object_s_colour_or_of_no_class_is_refused_by_name(tmp_path, colour, match):
    """A ball the object's colour would be taken for the object; the station refuses the map at load,
    before it connects, naming the map, the landmark and the colour."""
    (tmp_path / "m.yaml").write_text(
        "landmarks:\n"
        "  - {id: b-1, kind: color, color: green, position: [2.0, 0.0, 0.3], diameter: 0.1}\n"
        f"  - {{id: b-2, kind: color, color: {colour}, position: [2.0, 0.6, 0.3], diameter: 0.1}}\n")
    override = tmp_path / "o.yaml"
    override.write_text(f"station:\n  landmark_map: {tmp_path / 'm.yaml'}\n")
    with pytest.raises(ConfigError, match=match):
        load_station_config([override])
    override.write_text(f"station:\n  landmark_map: {tmp_path / 'm.yaml'}\nperception:\n  object_color: blue\n")
    if colour == "red":  # the same map with a blue object is fine
        assert len(load_station_config([override]).landmarks.of_kind("color")) == 2
