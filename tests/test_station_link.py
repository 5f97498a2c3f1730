"""The station's side of the wire against a real `nao-bridge --sim` process on loopback."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from nao_core.protocol import Info, State, decode, decode_frame
from nao_core.transport import TransportConfig
from station.launch import LocalBridge
from station.link import BridgeLink, BridgeUnavailable

pytestmark = pytest.mark.serial  # Zenoh sessions and their leases: run alone (Makefile test)


def plain(endpoint: str) -> TransportConfig:
    """The station's default: the credentials generated on first use (shared with the bridge on this machine)."""
    return TransportConfig.with_credentials("station", connect=(endpoint,), lease_ms=1000)


def wait_for(predicate, timeout: float, step: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(step)
    return predicate()


@pytest.fixture
def bridge(tmp_path):
    (tmp_path / "bridge.yaml").write_text("bridge:\n  resolution: qvga\n")
    local = LocalBridge(["--sim", "--config", str(tmp_path / "bridge.yaml")], tmp_path / "bridge.log")
    yield local
    local.close()


def test_info_frames_state_commands_and_bridge_lost(bridge, tmp_path):
    link = BridgeLink(plain(bridge.endpoint), "nao")
    try:
        info, raw = link.fetch_info(timeout=20.0)
        assert isinstance(info, Info) and info.backend == "sim" and info.resolution == "qvga"
        assert decode(raw, Info) == info  # the bytes as received are kept for the log
        link.start()
        frames = wait_for(lambda: link.take_frames(), 10.0)
        frame = decode_frame(frames[-1].payload)
        assert (frame.meta.width, frame.meta.height) == (320, 240) and frame.jpeg[:2] == b"\xff\xd8"
        state = decode(wait_for(lambda: _first(link, "state"), 5.0).payload, State)
        assert not state.fallen
        link.send_walk(0.05, 0.0, 0.2, ttl=0.3)
        link.send_head(0.3, 0.1, 0.5)
        walking = wait_for(lambda: _any_state(link, lambda s: s.walking and s.cmd_age is not None), 5.0)
        assert walking, "the bridge never reported walking after a walk command"
        # no further walk command: the bridge's deadman stops the robot
        assert wait_for(lambda: _any_state(link, lambda s: not s.walking and s.watchdog == "deadman"), 5.0)
        # the bridge goes away: liveliness says so at once
        bridge.process.kill()
        lost = wait_for(lambda: _first(link, "bridge_lost"), 5.0)
        assert lost is not None
    finally:
        link.close()


def test_close_terminates_the_bridge(bridge):
    link = BridgeLink(plain(bridge.endpoint), "nao")
    link.fetch_info(timeout=20.0)  # up and serving (its signal handlers installed)
    link.close()
    assert bridge.exit_code() is None
    assert bridge.close() == 0  # SIGTERM: a clean stop
    assert bridge.close() == 0  # idempotent


def test_no_bridge_is_a_clear_error():
    link = BridgeLink(plain("tcp/127.0.0.1:9"), "nao")
    try:
        with pytest.raises(BridgeUnavailable, match="no info from the bridge at tcp/127.0.0.1:9"):
            link.fetch_info(timeout=1.0)
    finally:
        link.close()


def _first(link: BridgeLink, kind: str):
    while not link.inbox.empty():
        event = link.inbox.get_nowait()
        if event.kind == kind:
            return event
    return None


def _any_state(link: BridgeLink, predicate) -> bool:
    while not link.inbox.empty():
        event = link.inbox.get_nowait()
        if event.kind == "state" and predicate(decode(event.payload, State)):
            return True
    return False


def test_secure_bridge_talks_to_the_station_certificate_only(tmp_path):
    certs = tmp_path / "certs"
    subprocess.run([sys.executable, "-m", "station.cli", "make-certs", "--out", str(certs)], check=True, capture_output=True)
    local = LocalBridge(["--sim", "--secure", str(certs)], tmp_path / "bridge.log")
    try:
        secure = BridgeLink(TransportConfig.secure("station", certs, connect=(local.endpoint,), lease_ms=1000), "nao")
        try:
            info, _ = secure.fetch_info(timeout=20.0)
            assert info.backend == "sim"
        finally:
            secure.close()
        intruder = BridgeLink(plain(local.endpoint), "nao")
        try:
            with pytest.raises(BridgeUnavailable):
                intruder.fetch_info(timeout=2.0)
        finally:
            intruder.close()
    finally:
        local.close()
