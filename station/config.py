"""The station's configuration: every section of config/*.yaml composed into one frozen object.

Each section lives in ``config/<section>.yaml`` under a single top-level key. ``--config FILE``
overrides (any number, merged left to right) may hold any of the sections::

    StationConfig.<section> = load(Params, [config/<section>.yaml, *overrides], section=<section>)

A top-level key of an override that names no section is an error naming the file (a typo would
otherwise be ignored silently). The robot model is the one the bridge reports in its info (one
source of truth for the robot); a ``robot`` section (e.g. a calibrated camera) is accepted here and
handed to the bridges the station starts itself (``--robot sim``, ``--naoqi``). The landmark map
is the file ``station.landmark_map`` names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Sequence, Union

from agent.carving import CarvingParams
from agent.ekf import EKFParams
from agent.localization import LocalizationParams
from agent.mission import MissionParams
from agent.perception import PerceptionParams
from agent.planner import PlannerParams
from nao_core.config import CONFIG_DIR, ConfigError, bounds, load, read_yaml
from nao_core.landmark_map import LandmarkMap, load_landmark_map


@dataclass(frozen=True)
class StationParams:
    robot_name: str = "nao"
    port: int = field(default=7447, metadata=bounds(1, 65535))
    resolution: str = "qvga"
    landmark_map: str = "landmarks/sim_room.yaml"
    control_period: float = field(default=0.1, metadata=bounds(0.01, 0.25))
    walk_ttl: float = field(default=0.3, metadata=bounds(0.05, 2.0))
    head_speed: float = field(default=0.25, metadata=bounds(0.01, 1.0))
    lease_ms: int = field(default=1000, metadata=bounds(200, 60000))
    bridge_timeout: float = field(default=20.0, metadata=bounds(1.0, 600.0))
    flush_interval: float = field(default=1.0, metadata=bounds(0.05, 60.0))
    keyframe_min_angle: float = field(default=0.17, metadata=bounds(0.0, 3.2))
    carve_max_position_std: float = field(default=0.02, metadata=bounds(1e-4, 10.0))


SECTIONS: Dict[str, type] = {
    "station": StationParams,
    "mission": MissionParams,
    "ekf": EKFParams,
    "planner": PlannerParams,
    "carving": CarvingParams,
    "perception": PerceptionParams,
    "localization": LocalizationParams,
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
    landmarks = load_landmark_map(map_path if map_path.is_absolute() else CONFIG_DIR / map_path)
    return StationConfig(landmarks=landmarks, overrides=tuple(paths), **sections)


def _top_level(path: Path) -> Dict[str, Any]:
    return read_yaml(path, what="a mapping of sections")
