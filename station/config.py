"""The station's configuration: every section of config/*.yaml composed into one frozen object.

Each section lives in ``config/<section>.yaml`` under a single top-level key. ``--config FILE``
overrides (any number, merged left to right) may hold any of the sections::

    StationConfig.<section> = load(Params, [config/<section>.yaml, *overrides], section=<section>)

A top-level key of an override that names no section is an error naming the file (a typo would
otherwise be ignored silently). The robot model is the one the bridge reports in its info (one
source of truth for the robot); a ``robot`` section (e.g. a calibrated camera) is accepted here and
handed to the bridges the station starts itself (``--robot sim``, ``--naoqi``). The landmark map
is the file ``station.landmark_map`` names.

``station config`` prints the resolved configuration with, for each leaf key, the file that set it
(:func:`provenance`: the last file of the merge order holding the key).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Literal, Sequence, Tuple, Union

from agent.carving import CarvingParams
from agent.head_servo import HeadServoParams
from agent.ekf import EKFParams
from agent.localization import LocalizationParams, check_ball_colours
from agent.mission import MissionParams
from agent.perception import PerceptionParams
from agent.planner import PlannerParams
from agent.self_calibration import SelfCalibrationParams
from nao_core.config import CONFIG_DIR, ConfigError, bounds, load, read_yaml
from nao_core.landmark_map import LandmarkMap, load_landmark_map


@dataclass(frozen=True)
class StationParams:
    robot_name: str
    port: int = field(metadata=bounds(1, 65535))
    resolution: Literal["qqvga", "qvga", "vga", "4vga"]
    landmark_map: str
    control_period: float = field(metadata=bounds(0.01, 0.25))
    walk_ttl: float = field(metadata=bounds(0.05, 2.0))
    head_speed: float = field(metadata=bounds(0.01, 1.0))
    lease_ms: int = field(metadata=bounds(200, 60000))
    bridge_timeout: float = field(metadata=bounds(1.0, 600.0))
    watchdog_grace: float = field(metadata=bounds(0.5, 600.0))  # s a bridge may refuse to walk for want of the robot watchdog
    flush_interval: float = field(metadata=bounds(0.05, 60.0))
    keyframe_min_angle: float = field(metadata=bounds(0.0, 3.2))
    carve_max_position_std: float = field(metadata=bounds(1e-4, 10.0))
    doctor_min_battery: float = field(metadata=bounds(0.0, 1.0))
    stamp_sigma: float = field(metadata=bounds(0.0, 1.0))  # s, a frame stamp's error the object filter allows for
    start_max_turn_rate: float = field(metadata=bounds(0.0, 100.0))  # rad/s, the object filter starts only from a slower camera


SECTIONS: Dict[str, type] = {
    "station": StationParams,
    "mission": MissionParams,
    "ekf": EKFParams,
    "planner": PlannerParams,
    "carving": CarvingParams,
    "perception": PerceptionParams,
    "localization": LocalizationParams,
    "head_servo": HeadServoParams,
    "self_calibration": SelfCalibrationParams,
}
ROBOT_SECTION = "robot"


@dataclass(frozen=True)
class StationConfig:
    station: StationParams
    mission: MissionParams
    ekf: EKFParams
    planner: PlannerParams
    carving: CarvingParams
    perception: PerceptionParams
    localization: LocalizationParams
    head_servo: HeadServoParams
    self_calibration: SelfCalibrationParams
    landmarks: LandmarkMap
    overrides: Sequence[Path] = ()

    @property
    def section_names(self) -> Sequence[str]:
        return tuple(SECTIONS)

    @property
    def robot_overrides(self) -> Sequence[Path]:
        """The override files with a ``robot`` section, for a bridge the station starts."""
        return tuple(p for p in self.overrides if ROBOT_SECTION in _top_level(p))


def load_station_config(overrides: Sequence[Union[str, Path]] = ()) -> StationConfig:
    """Defaults from config/*.yaml merged with ``overrides``; ConfigError names file, key and rule."""
    paths = [Path(p) for p in overrides]
    for path in paths:
        unknown = sorted(set(_top_level(path)) - set(SECTIONS) - {ROBOT_SECTION})
        if unknown:
            raise ConfigError(f"{path}: {unknown[0]}: unknown section; expected one of {sorted([*SECTIONS, ROBOT_SECTION])}")
    sections = {name: load(cls, [CONFIG_DIR / f"{name}.yaml", *paths], section=name) for name, cls in SECTIONS.items()}
    map_path = Path(sections["station"].landmark_map)
    map_path = map_path if map_path.is_absolute() else CONFIG_DIR / map_path
    landmarks = load_landmark_map(map_path)
    try:
        check_ball_colours(landmarks, sections["perception"])
    except ValueError as exc:
        raise ConfigError(f"{map_path}: {exc}") from None
    return StationConfig(landmarks=landmarks, overrides=tuple(paths), **sections)


def _top_level(path: Path) -> Dict[str, Any]:
    return read_yaml(path, what="a mapping of sections")


def provenance(overrides: Sequence[Union[str, Path]] = ()) -> Dict[str, Tuple[Any, str]]:
    """Every leaf key of the resolved configuration, ``section.key[.sub...]`` -> (value, the file that
    set it): the last of [config/<section>.yaml, *overrides] holding the key (later files win)."""
    config = load_station_config(overrides)
    result: Dict[str, Tuple[Any, str]] = {}
    for name in SECTIONS:
        files = [CONFIG_DIR / f"{name}.yaml", *map(Path, overrides)]
        set_by = {}
        for path in files:
            for key in _leaves(read_yaml(path, what="a mapping of sections").get(name) or {}, name):
                set_by[key] = str(path)
        for key, value in _leaves(dataclasses.asdict(getattr(config, name)), name).items():
            result[key] = (value, set_by.get(key, _nearest(key, set_by)))
    return result


def print_config(args: Any) -> int:
    """``station config``: the resolved configuration, one key a line with its source (or ``--json``)."""
    table = provenance(args.config)
    if args.json:
        print(json.dumps({key: {"value": value, "file": source} for key, (value, source) in table.items()}, indent=1))
        return 0
    width = max(map(len, table))
    for key, (value, source) in table.items():
        print(f"{key:<{width}}  {json.dumps(value)}  # {source}")
    return 0


def _leaves(mapping: Any, prefix: str) -> Dict[str, Any]:
    """Flatten nested mappings to dotted keys; lists and scalars are leaves."""
    if not isinstance(mapping, dict):
        return {prefix: mapping}
    out: Dict[str, Any] = {}
    for key, value in mapping.items():
        out.update(_leaves(value, f"{prefix}.{key}"))
    return out


def _nearest(key: str, set_by: Dict[str, str]) -> str:
    """The file that set the closest enclosing key (a whole mapping replaced), else the code's default."""
    while "." in key:
        key = key.rsplit(".", 1)[0]
        if key in set_by:
            return set_by[key]
    for other, path in set_by.items():
        if other.startswith(key + "."):
            return path
    return "default"
