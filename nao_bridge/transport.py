"""Zenoh sessions for the bridge and the station: one place that turns options into a zenoh.Config.

Practice (DESIGN.md, checked with eclipse-zenoh 1.10): peer mode on both sides, multicast scouting
off, explicit listen (bridge) and connect (station) endpoints, and a short link lease so that a
frozen peer is noticed within about a second (its liveliness tokens then disappear).
``insert_json5`` takes JSON5 literals, hence ``json.dumps`` on every value.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Tuple

import zenoh

from .config import bounds


@dataclass(frozen=True)
class TransportConfig:
    listen: Tuple[str, ...] = ()  # e.g. ("tcp/[::]:7447",)
    connect: Tuple[str, ...] = ()  # e.g. ("tcp/nao.local:7447",)
    lease_ms: int = field(default=1500, metadata=bounds(200, 60000))
    keep_alive: int = field(default=4, metadata=bounds(1, 100))  # keep-alives per lease


def zenoh_config(options: TransportConfig) -> zenoh.Config:
    config = zenoh.Config()
    settings: dict[str, Any] = {
        "mode": "peer",
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "listen/endpoints": list(options.listen),
        "connect/endpoints": list(options.connect),
        "transport/link/tx/lease": options.lease_ms,
        "transport/link/tx/keep_alive": options.keep_alive,
    }
    for key, value in settings.items():
        config.insert_json5(key, json.dumps(value))
    return config


def open_session(options: TransportConfig) -> zenoh.Session:
    """Open a peer session with the given endpoints (raises zenoh.ZError with zenoh's reason)."""
    return zenoh.open(zenoh_config(options))
