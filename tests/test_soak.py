"""Soak: many consecutive station sessions against one long-running simulated bridge (``slow`` marker).

One ``nao-bridge --sim`` process runs for the whole soak (``SOAK_SECONDS``, default 1800 s). Each
mission opens the station's link (``station.link.BridgeLink``) in this process, fetches the info,
subscribes, walks for ``SOAK_MISSION_SECONDS`` at 10 Hz while draining every frame and state,
stops, and closes the link (the lease handed back): the bridge sees a station come and go each
time. After a warm-up of three missions, the bridge's resident memory, threads and open file
descriptors, and this process's threads and descriptors, are sampled after every mission, once an
observer session sees that the bridge has let the station go (a state with no lease owner, no
station token left), and must stay flat:
the maximum over the last third of the soak may exceed the maximum over the first third by at
most ``RSS_SLACK_MB`` of memory and 2 threads or descriptors (Zenoh's runtime parks and spawns
workers; a leaked thread, socket or session per mission would grow by one per mission). The
samples are written to ``SOAK_REPORT`` when set.

    SOAK_SECONDS=1800 SOAK_REPORT=runs/soak.json .venv/bin/python -m pytest -q -m slow tests/test_soak.py
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Dict, List

import pytest

from nao_core.protocol import RobotKeys, State, decode
from nao_core.transport import TransportConfig, open_session
from station.launch import LocalBridge
from station.link import BridgeLink
from tests.zenoh_peers import wait_until

pytestmark = pytest.mark.serial  # a long mission's processes: run alone (Makefile test)

SOAK_SECONDS = float(os.environ.get("SOAK_SECONDS", "1800"))
MISSION_SECONDS = float(os.environ.get("SOAK_MISSION_SECONDS", "20"))
RSS_SLACK_MB = 25.0
WARM_UP = 3


def proc_status(pid: int) -> Dict[str, float]:
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    return {
        "rss_mb": int(fields["VmRSS"].split()[0]) / 1024.0,
        "threads": int(fields["Threads"]),
        "fds": len(os.listdir(f"/proc/{pid}/fd")),
    }


def mission(endpoint: str) -> Dict[str, int]:
    """One station session: info, subscriptions, walking at 10 Hz with everything drained, stop, close."""
    link = BridgeLink(TransportConfig.with_credentials("station", connect=(endpoint,), lease_ms=1000), "nao")
    counts = {"frames": 0, "states": 0, "walking_states": 0}
    try:
        link.fetch_info(timeout=20.0)
        link.start()  # subscriptions, station token, the lease
        end = time.monotonic() + MISSION_SECONDS
        while time.monotonic() < end:
            link.send_walk(0.05, 0.0, 0.3, ttl=0.3)
            time.sleep(0.1)
            counts["frames"] += len(link.take_frames())
            while not link.inbox.empty():
                event = link.inbox.get_nowait()
                if event.kind == "state":
                    counts["states"] += 1
                    counts["walking_states"] += decode(event.payload, State).walking
                assert event.kind != "bridge_lost", "the bridge went away during the soak"
        link.send_walk(0.0, 0.0, 0.0, ttl=0.3)
    finally:
        link.close()
    return counts


class Observer:
    """A session (no station token, no lease) watching the bridge's state and the station tokens."""

    def __init__(self, endpoint: str, keys: RobotKeys = RobotKeys()):
        self.keys = keys
        self.session = open_session(TransportConfig.with_credentials("station", connect=(endpoint,)))
        self.states: List[tuple] = []  # (arrival, owner)
        self.sub = self.session.declare_subscriber(
            keys.state, lambda s: self.states.append((time.monotonic(), decode(s.payload.to_bytes(), State).owner)))

    def station_gone(self, since: float) -> bool:
        """A state published after ``since`` has no owner and no station token is declared any more."""
        released = any(t > since and owner is None for t, owner in self.states[-20:])
        return released and not list(self.session.liveliness().get(self.keys.station_alive, timeout=1.0))

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


@pytest.mark.slow
@pytest.mark.timeout(int(SOAK_SECONDS) + 600)
def test_soak_many_sessions_flat_memory_no_leaked_threads_or_sessions(tmp_path):
    (tmp_path / "bridge.yaml").write_text("bridge:\n  resolution: qvga\n")
    bridge = LocalBridge(["--sim", "--config", str(tmp_path / "bridge.yaml")], tmp_path / "bridge.log")
    samples: List[Dict[str, float]] = []
    started = time.monotonic()
    observer = None
    try:
        while time.monotonic() - started < SOAK_SECONDS or len(samples) < WARM_UP + 2:
            counts = mission(bridge.endpoint)
            closed = time.monotonic()
            observer = observer or Observer(bridge.endpoint)  # the bridge listens once a mission has run
            assert counts["frames"] > 0 and counts["walking_states"] > 0, counts
            assert wait_until(lambda: observer.station_gone(closed), 10.0), "the bridge never let the station go"
            bridge_status = proc_status(bridge.process.pid)
            own = proc_status(os.getpid())
            samples.append({"t": time.monotonic() - started, **counts,
                            **{f"bridge_{k}": v for k, v in bridge_status.items()},
                            **{f"station_{k}": v for k, v in own.items()}})
            assert bridge.exit_code() is None, "the bridge died"
    finally:
        if observer is not None:
            observer.close()
        code = bridge.close()
        if os.environ.get("SOAK_REPORT"):
            Path(os.environ["SOAK_REPORT"]).write_text(json.dumps(samples, indent=1))
    assert code == 0
    steady = samples[WARM_UP:]
    first, last_third = steady[: max(1, len(steady) // 3)], steady[-max(1, len(steady) // 3):]
    for key, slack in (("bridge_rss_mb", RSS_SLACK_MB), ("bridge_threads", 2), ("bridge_fds", 2),
                       ("station_threads", 2), ("station_fds", 2)):
        growth = max(s[key] for s in last_third) - max(s[key] for s in first)
        assert growth <= slack, f"{key} grew by {growth} over the soak"
    print(f"soak: {len(samples)} missions in {samples[-1]['t']:.0f} s; bridge RSS {samples[0]['bridge_rss_mb']:.1f} -> "
          f"{samples[-1]['bridge_rss_mb']:.1f} MB, threads {samples[0]['bridge_threads']} -> "
          f"{samples[-1]['bridge_threads']}, fds {samples[0]['bridge_fds']} -> {samples[-1]['bridge_fds']}")
