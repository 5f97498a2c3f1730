"""Helpers for tests with real Zenoh sessions on loopback: free ports, lab certificates, waiting,
the station's lease, and the real bridge on the NAOqi stand-in."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path
from typing import Callable, Iterator, Optional, Tuple

import zenoh

from nao_bridge.bridge import Bridge, BridgeParams
from nao_bridge.naoqi_backend import NaoqiBackend
from nao_core.config import CONFIG_DIR, load
from nao_core.protocol import LeaseReply, LeaseRequest, RobotKeys, decode, encode
from nao_core.robot_model import load_robot_model
from nao_core.transport import TransportConfig
from nao_sim.standin import StandIn
from nao_sim.world import SimWorld
from station.launch import free_port
from station.certs import make_lab_certificates

__all__ = ["arm", "bridge_on_standin", "free_port", "lab_certificates", "station_token", "take_lease", "wait_until"]


def lab_certificates(folder: Path) -> Path:
    """A fresh lab CA with bridge, station and viewer certificates in ``folder``."""
    make_lab_certificates(folder)
    return folder


def wait_until(condition: Callable[[], bool], timeout: float, poll: float = 0.01) -> bool:
    """Poll ``condition`` until it holds or ``timeout`` seconds pass; return whether it held."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll)
    return condition()


def station_token(session: zenoh.Session, keys: RobotKeys = RobotKeys()) -> Tuple[str, zenoh.LivelinessToken]:
    """Declare the station liveliness token of ``session``; return its station id and the token."""
    station = str(session.zid())
    return station, session.liveliness().declare_token(keys.station_token(station))


def take_lease(session: zenoh.Session, station: str, keys: RobotKeys = RobotKeys(), timeout: float = 5.0,
               op: str = "take", lease: str = "") -> Optional[LeaseReply]:
    """Ask the bridge's lease queryable; ``no_token`` (the token not seen yet) is retried until ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        reply = None
        for answer in session.get(keys.lease, payload=encode(LeaseRequest(op=op, station=station, lease=lease)),
                                  timeout=1.0):
            if answer.ok is not None:
                reply = decode(answer.ok.payload.to_bytes(), LeaseReply)
        if (reply is not None and reply.reason != "no_token") or time.monotonic() > deadline:
            return reply
        time.sleep(0.02)


def arm(session: zenoh.Session, keys: RobotKeys = RobotKeys(), timeout: float = 5.0) -> Tuple[str, zenoh.LivelinessToken]:
    """Arm ``session`` as ``station.link`` does: declare its station token, take the lease.

    Returns the lease secret (every command must carry it) and the token; raises AssertionError
    naming the bridge's reason when the lease is not granted."""
    station, token = station_token(session, keys)
    reply = take_lease(session, station, keys, timeout)
    if reply is None or not reply.granted:
        token.undeclare()
        raise AssertionError(f"the bridge did not grant the lease to {station}: {reply}")
    return reply.lease, token


@contextlib.contextmanager
def bridge_on_standin(transport: TransportConfig, seed: int = 0, fps: float = 5.0) -> Iterator[Tuple[Bridge, StandIn]]:
    """The real bridge on the NAOqi backend, served by the libqi stand-in that records every ALMotion call."""
    model = load_robot_model()
    params = load(BridgeParams, [CONFIG_DIR / "bridge.yaml"], section="bridge")
    params = dataclasses.replace(params, resolution="qvga", fps=fps, transport=transport)
    with StandIn(SimWorld("can", model, resolution="qvga", seed=seed)) as standin:
        bridge = Bridge(NaoqiBackend(standin.url, model, params.naoqi, "qvga", fps), model, params, "naoqi")
        bridge.start()
        try:
            yield bridge, standin
        finally:
            bridge.close()
