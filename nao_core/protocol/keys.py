"""Zenoh key expressions of one robot: everything lives under ``nao/<name>/``."""

from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "nao"
_NAME = re.compile(r"[A-Za-z0-9_\-]{1,64}")


@dataclass(frozen=True)
class RobotKeys:
    """The key expressions of the robot called ``name`` (``nao`` by default)."""

    name: str = "nao"

    def __post_init__(self) -> None:
        if not _NAME.fullmatch(self.name):
            raise ValueError(f"robot name {self.name!r}: expected 1-64 characters from A-Z a-z 0-9 _ -")

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.name}"

    @property
    def camera_top(self) -> str:  # frames, bridge -> station
        return f"{self.prefix}/camera/top"

    @property
    def state(self) -> str:  # robot state, bridge -> station
        return f"{self.prefix}/state"

    @property
    def cmd_walk(self) -> str:  # walk commands, station -> bridge
        return f"{self.prefix}/cmd/walk"

    @property
    def cmd_head(self) -> str:  # head commands, station -> bridge
        return f"{self.prefix}/cmd/head"

    @property
    def info(self) -> str:  # queryable served by the bridge
        return f"{self.prefix}/info"

    @property
    def alive(self) -> str:  # liveliness token of the bridge
        return f"{self.prefix}/alive"

    @property
    def station_alive(self) -> str:  # liveliness tokens of stations: station/alive/<station id>
        return f"{self.prefix}/station/alive/*"

    def station_token(self, station: str) -> str:  # the liveliness token of one station
        return f"{self.prefix}/station/alive/{station}"

    @property
    def lease(self) -> str:  # queryable served by the bridge: LeaseRequest -> LeaseReply
        return f"{self.prefix}/lease"

    @property
    def sim_truth(self) -> str:  # simulator ground truth (tests and reports only)
        return f"{self.prefix}/sim/truth"
