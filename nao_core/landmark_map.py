"""The landmark map a user writes for their room (contract in docs/frames.md and docs/landmarks.md).

Shared by the simulator (which draws the landmarks) and the localization (which uses them).
A colour landmark is a ball (of ``diameter``) whose centre is the point; an ArUco landmark is a vertical square
marker of side ``size`` whose outward normal points along ``yaw``. Its corners are ordered as
``cv2.aruco`` reports them: top-left, top-right, bottom-right, bottom-left, seen from the front::

    n = (cos yaw, sin yaw, 0),  right = (-n) x z_up = (-sin yaw, cos yaw, 0),  up = z
    corners = c + s/2 * [(-right + up), (right + up), (right - up), (-right - up)]
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import FrozenSet, Literal, Optional, Tuple, Union

import numpy as np

from nao_core.config import ConfigError, bounds, from_mapping, read_yaml

log = logging.getLogger(__name__)

# A map file that does not state how well it is measured is held exact, with a warning. Taken as a tape's
# (5 mm, 1 deg) instead, an exact map's missions kept their centre and model in 16 matrix worlds but lost
# one of 12 one-wall rooms (no cold fix within the gate in 45 s): docs/landmarks.md "Writing the map".
PRECISION_KEYS = ("position_sigma", "yaw_sigma")
ARUCO_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_100", "DICT_5X5_50", "DICT_5X5_100", "DICT_6X6_50", "DICT_6X6_250")


@dataclass(frozen=True)
class Landmark:
    id: Union[int, str]
    kind: Literal["color", "aruco"]
    position: Tuple[float, float, float] = field(metadata=bounds(-100.0, 100.0))
    color: Optional[str] = None  # colour class (perception config), for kind 'color'
    diameter: float = field(default=0.08, metadata=bounds(0.005, 2.0))  # colour ball, m
    dictionary: Optional[Literal[ARUCO_DICTIONARIES]] = None  # type: ignore[valid-type]
    size: Optional[float] = field(default=None, metadata=bounds(0.01, 2.0))  # ArUco black square side, m
    yaw: float = field(default=0.0, metadata=bounds(-2 * math.pi, 2 * math.pi))  # ArUco normal, rad

    def __post_init__(self) -> None:
        if self.kind == "color" and self.color is None:
            raise ValueError(f"landmark {self.id!r}: kind 'color' needs 'color'")
        if self.kind == "aruco":
            if self.dictionary is None or self.size is None:
                raise ValueError(f"landmark {self.id!r}: kind 'aruco' needs 'dictionary' and 'size'")
            if not isinstance(self.id, int) or self.id < 0:
                raise ValueError(f"landmark {self.id!r}: an ArUco id is a non-negative integer")

    @property
    def normal(self) -> np.ndarray:
        return np.array([math.cos(self.yaw), math.sin(self.yaw), 0.0])

    def aruco_corners(self) -> np.ndarray:
        """World corners (4 x 3) in cv2.aruco order: top-left, top-right, bottom-right, bottom-left."""
        if self.size is None:
            raise ValueError(f"landmark {self.id!r} is not an ArUco marker")
        right = np.array([-math.sin(self.yaw), math.cos(self.yaw), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        h = 0.5 * self.size
        c = np.asarray(self.position, dtype=float)
        return np.array([c - h * right + h * up, c + h * right + h * up, c + h * right - h * up, c - h * right - h * up])


@dataclass(frozen=True)
class LandmarkMap:
    landmarks: Tuple[Landmark, ...]
    # how well the map is measured (1 sigma): each landmark's centre on each axis, m, and each marker's
    # facing, rad; the fixes carry what that does to them (agent/localization.py, "Map error"; default: exact)
    position_sigma: float = field(default=0.0, metadata=bounds(0.0, 0.5))
    yaw_sigma: float = field(default=0.0, metadata=bounds(0.0, 0.5))

    def __post_init__(self) -> None:
        seen = set()
        for lm in self.landmarks:
            key = (lm.kind, str(lm.id))
            if key in seen:
                raise ValueError(f"duplicate landmark id {lm.id!r}")
            seen.add(key)

    def of_kind(self, kind: str) -> Tuple[Landmark, ...]:
        return tuple(lm for lm in self.landmarks if lm.kind == kind)

    @property
    def ball_colors(self) -> FrozenSet[str]:
        """The colour classes of its balls."""
        return frozenset(lm.color for lm in self.of_kind("color"))


def load_landmark_map(path: Union[str, Path]) -> LandmarkMap:
    """Load and validate a landmark map YAML (``read_landmark_map``'s map)."""
    return read_landmark_map(path)[0]


def read_landmark_map(path: Union[str, Path]) -> Tuple[LandmarkMap, Tuple[str, ...]]:
    """The map of a landmark file (top-level key ``landmarks``; a map without one is refused: the robot
    localizes by nothing else) and the ``PRECISION_KEYS`` it does not state. Those are 0, exact, with a
    warning: only a simulated room's map is, and it says so."""
    data = read_yaml(Path(path))  # the file read once: the map, and what it states
    landmark_map = from_mapping(LandmarkMap, data, str(path))
    if not landmark_map.landmarks:
        raise ConfigError(f"{path}: the map has no landmarks: the robot cannot localize (docs/landmarks.md)")
    unstated = tuple(key for key in PRECISION_KEYS if key not in data)
    if unstated:
        log.warning("%s does not say how well it is measured (%s): held exact; a map measured with a tape is a few mm "
                    "off, which costs several times that in every fix unless it says so (docs/landmarks.md, "
                    "\"Writing the map\")", path, ", ".join(unstated))
    return landmark_map, unstated
