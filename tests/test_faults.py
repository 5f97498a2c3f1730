"""Faults across processes, each with its defined outcome (docs/security.md, "Faults").

Real processes and real Zenoh sessions on loopback. The robot side is the real bridge on the real
NAOqi backend, served by the libqi stand-in (which records every ALMotion call with its time), or
the ``nao-bridge --sim`` process; the station side is the station's own link (``station.link``),
in a child process when the test kills or freezes it.

| fault | defined outcome (asserted) |
| --- | --- |
| station SIGKILL mid-walk | ``ALMotion.stopMove`` within 300 ms of the kill, no move after it |
| station frozen (SIGSTOP) | deadman stop within 300 ms + one control period; the bridge drops the station after its lease |
| bridge frozen (SIGSTOP) | the station's link reports ``bridge_lost`` within 2 s |
| network stall, then a burst of stale commands | stopped by the deadman during the stall; the burst of 10 collapses to a few moves ending with the newest |
| NaN / inf in every command field | rejected and counted as ``non_finite``; no ALMotion call |
| wall-clock jumps (+-1 h) on the bridge | no effect: walking continues, the deadman still stops on time |
| log writer SIGKILLed | the MCAP log reads (with a warning) up to its last flush, <= about 1 s before the kill |
| ``station start`` SIGKILLed mid-walk | stopMove within 300 ms; ``station report`` and ``station replay`` read its log, with a warning |
| bridge frozen mid-mission | the station journals ``bridge_lost`` within 2 s, ends the mission, writes result.json, exits 1 |
| frames with corrupt JPEG, wrong size, 10 s late, seq gaps | all logged; undecodable ones rejected; the mission goes on |
| the camera stops mid-mission (the bridge alive) | no walk from ``mission.frame_stall`` + 1 s after it; the mission ends ``camera_lost`` after ``mission.frame_timeout``, naming it, exit 1 |

Timing bounds here are the safety requirements of the issue (300 ms, 2 s), measured on the
stand-in's and the link's own timestamps; they are not speed benchmarks.
"""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import threading
import time
import types
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np
import pytest

import nao_bridge.bridge as bridge_module
from agent.mission import MissionParams
from nao_core.config import CONFIG_DIR, load
from nao_core.protocol import FrameMeta, RobotKeys, WalkCommand, encode, encode_frame
from nao_core.transport import TransportConfig, open_session
from nao_sim.standin import StandIn
from station.launch import LocalBridge
from station.config import StationParams
from station.link import BridgeLink
from station.mcap_log import read_log
from station.topics import FRAME_META, FRAME_REJECTED, INPUT
from tests.zenoh_peers import arm, bridge_on_standin, free_port, wait_until

pytestmark = pytest.mark.serial  # missions' processes killed and frozen on a timer: run alone (Makefile test)

KEYS = RobotKeys("nao")
PY = sys.executable
STOP_WITHIN = 0.3  # s: SIGKILLed station -> stopMove (issue 8)
NOTICE_WITHIN = 2.0  # s: frozen bridge -> station notices (issue 8)

STATION_SCRIPT = """
import sys, time
from nao_core.transport import TransportConfig
from station.link import BridgeLink
link = BridgeLink(TransportConfig.with_credentials("station", connect=(sys.argv[1],), lease_ms=1000), "nao")
link.fetch_info(timeout=10.0)
link.start()  # takes the lease
print("walking", flush=True)
while True:
    link.send_walk(0.1, 0.0, 0.2, ttl=0.3)
    time.sleep(0.1)
"""

LOG_SCRIPT = """
import sys, time
from station.mcap_log import McapLog
log = McapLog(sys.argv[1], flush_interval=1.0)
print("writing", flush=True)
while True:
    t = time.time()
    log.json("/tick", {"t": t}, t, {"title": "nao.Tick", "type": "object"})
    log.maybe_flush()
    time.sleep(0.01)
"""


@pytest.fixture
def robot():
    """The real bridge (default security: generated credentials) on the NAOqi stand-in: (bridge, standin, port)."""
    port = free_port()
    transport = TransportConfig.with_credentials("bridge", listen=(f"tcp/127.0.0.1:{port}",))
    with bridge_on_standin(transport, seed=2) as (bridge, standin):
        yield bridge, standin, port


def station_transport(port: int, lease_ms: int = 1500) -> TransportConfig:
    """A station session (default credentials) to the bridge on ``port``; :func:`arm` takes the lease."""
    return TransportConfig.with_credentials("station", connect=(f"tcp/127.0.0.1:{port}",), lease_ms=lease_ms)


def station_process(port: int) -> subprocess.Popen:
    proc = subprocess.Popen([PY, "-c", STATION_SCRIPT, f"tcp/127.0.0.1:{port}"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout.readline().strip() == "walking"
    return proc


def moves_after(standin: StandIn, t: float) -> list:
    return [c for c in standin.calls_to("ALMotion.move") if c.time > t]


def first_stop_after(standin: StandIn, t: float) -> Optional[float]:
    stops = [c.time for c in standin.calls_to("ALMotion.stopMove") if c.time > t]
    return min(stops) if stops else None


def test_station_killed_mid_walk_stops_the_robot_within_300_ms(robot):
    bridge, standin, port = robot
    proc = station_process(port)
    try:
        assert wait_until(lambda: len(standin.calls_to("ALMotion.move")) > 0, 10.0), "never walked"
        time.sleep(0.5)  # mid-walk
        killed = time.time()
        proc.kill()
        assert wait_until(lambda: first_stop_after(standin, killed) is not None, 2.0)
        stopped = first_stop_after(standin, killed)
        assert stopped - killed <= STOP_WITHIN, f"stopMove {stopped - killed:.3f} s after the kill"
        time.sleep(0.5)
        assert moves_after(standin, stopped) == []
        assert not bridge.station_alive
    finally:
        proc.kill()
        proc.wait()


def test_station_frozen_is_stopped_by_the_deadman_then_dropped_after_its_lease(robot):
    bridge, standin, port = robot
    proc = station_process(port)
    try:
        assert wait_until(lambda: len(standin.calls_to("ALMotion.move")) > 0, 10.0), "never walked"
        frozen = time.time()
        proc.send_signal(signal.SIGSTOP)
        assert wait_until(lambda: first_stop_after(standin, frozen) is not None, 2.0)
        bound = bridge.params.deadman_s + bridge.params.control_period_s + 0.1  # + the command in flight
        assert first_stop_after(standin, frozen) - frozen <= bound
        assert wait_until(lambda: not bridge.station_alive, 3.0), "the frozen station was never dropped"
        dropped = time.time() - frozen
        assert dropped >= 0.5  # by the lease (1 s announced by the station), not by a disconnection
    finally:
        proc.send_signal(signal.SIGCONT)
        proc.kill()
        proc.wait()


@pytest.mark.parametrize("fault", ["SIGSTOP", "SIGKILL"])
def test_bridge_frozen_or_killed_is_noticed_by_the_station_within_2_s(tmp_path, fault):
    (tmp_path / "bridge.yaml").write_text("bridge:\n  resolution: qvga\n  fps: 5.0\n")
    bridge = LocalBridge(["--sim", "--config", str(tmp_path / "bridge.yaml")], tmp_path / "bridge.log")
    link = BridgeLink(TransportConfig.with_credentials("station", connect=(bridge.endpoint,), lease_ms=1000), "nao")
    try:
        link.fetch_info(timeout=20.0)
        link.start()
        assert wait_until(lambda: not link.inbox.empty(), 5.0), "no state from the bridge"
        bridge.process.send_signal(getattr(signal, fault))
        signalled = time.time()
        lost = _wait_for_event(link, "bridge_lost", 5.0)
        assert lost is not None, f"the station never noticed the {fault}"
        assert lost.t - signalled <= NOTICE_WITHIN, f"noticed {lost.t - signalled:.2f} s after {fault}"
    finally:
        bridge.process.send_signal(signal.SIGCONT)
        link.close()
        bridge.close(grace=2.0)


def _wait_for_event(link: BridgeLink, kind: str, timeout: float):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            event = link.inbox.get(timeout=0.05)
        except Exception:  # noqa: BLE001 - queue.Empty
            continue
        if event.kind == kind:
            return event
    return None


class StallingProxy:
    """A TCP relay on loopback that can stop forwarding (a network stall) and resume (a burst)."""

    def __init__(self, target_port: int):
        self.port = free_port()
        self.target_port = target_port
        self.flowing = threading.Event()
        self.flowing.set()
        self.loop = asyncio.new_event_loop()
        ready = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(ready,), daemon=True)
        self.thread.start()
        ready.wait(5.0)

    def _run(self, ready: threading.Event) -> None:
        asyncio.set_event_loop(self.loop)
        self.server = self.loop.run_until_complete(asyncio.start_server(self._client, "127.0.0.1", self.port))
        ready.set()
        self.loop.run_forever()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        await asyncio.gather(self._pipe(reader, up_writer), self._pipe(up_reader, writer), return_exceptions=True)

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(65536):
                while not self.flowing.is_set():  # hold the bytes: they arrive together on resume
                    await asyncio.sleep(0.005)
                writer.write(data)
                await writer.drain()
        finally:
            writer.close()

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.server.close)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5.0)


def test_network_stall_stops_the_robot_and_the_stale_burst_collapses_to_the_newest(robot):
    bridge, standin, port = robot
    proxy = StallingProxy(port)
    session = open_session(station_transport(proxy.port, lease_ms=5000))
    try:
        lease, token = arm(session, KEYS)
        assert bridge.station_alive
        seq = 0

        def walk(omega: float) -> None:
            nonlocal seq
            seq += 1
            session.put(KEYS.cmd_walk, encode(WalkCommand(seq=seq, vx=0.1, vy=0.0, omega=omega, ttl=0.3, lease=lease)))

        for _ in range(5):
            walk(0.1)
            time.sleep(0.05)
        assert wait_until(lambda: len(standin.calls_to("ALMotion.move")) > 0, 5.0)
        proxy.flowing.clear()
        stalled = time.time()
        for i in range(10):  # 1 s of commands held (shorter than the 1.5 s leases), the last one different
            walk(0.1 if i < 9 else -0.3)
            time.sleep(0.1)
        assert first_stop_after(standin, stalled) is not None, "the deadman did not stop the robot during the stall"
        resumed = time.time()
        proxy.flowing.set()
        assert wait_until(lambda: len(moves_after(standin, resumed)) > 0, 3.0)
        time.sleep(0.3)
        burst = moves_after(standin, resumed)
        assert len(burst) <= 4, f"{len(burst)} ALMotion.move calls for a burst of 10 commands"
        assert burst[-1].args[2] == pytest.approx(-0.3)  # the newest command wins
        assert wait_until(lambda: first_stop_after(standin, burst[-1].time) is not None, 1.0)  # then the deadman
        token.undeclare()
    finally:
        session.close()
        proxy.close()


FIELDS = {"cmd.walk": ("seq", "vx", "vy", "omega", "ttl"), "cmd.head": ("seq", "yaw", "pitch", "speed")}


def test_non_finite_values_in_every_command_field_are_rejected_without_motion(robot):
    bridge, standin, port = robot
    session = open_session(station_transport(port))
    try:
        lease, token = arm(session, KEYS)
        head_calls = len(standin.calls_to("ALMotion.setAngles"))
        sent = 0
        for kind, fields in FIELDS.items():
            valid = {"v": 1, "type": kind, "seq": 5, "vx": 0.1, "vy": 0.0, "omega": 0.1, "ttl": 0.5,
                     "yaw": 0.1, "pitch": 0.1, "speed": 0.2, "lease": lease}
            key = KEYS.cmd_walk if kind == "cmd.walk" else KEYS.cmd_head
            for name in fields:
                for literal in ("NaN", "Infinity", "-Infinity", "1e999"):
                    body = {k: valid[k] for k in ("v", "type", *fields, "lease")}  # the owner's commands
                    text = ",".join(f'"{k}":{literal if k == name else repr(v).replace(chr(39), chr(34))}'
                                    for k, v in body.items())
                    session.put(key, ("{" + text + "}").encode())
                    sent += 1
        assert wait_until(lambda: bridge.rejected.get("non_finite", 0) == sent, 5.0), dict(bridge.rejected)
        assert standin.calls_to("ALMotion.move") == []
        assert len(standin.calls_to("ALMotion.setAngles")) == head_calls
        token.undeclare()
    finally:
        session.close()


def test_wall_clock_jumps_do_not_change_walking_or_the_deadman(robot, monkeypatch):
    bridge, standin, port = robot
    jump = [0.0]
    clock = types.SimpleNamespace(**{name: getattr(time, name) for name in ("monotonic", "sleep", "perf_counter")})
    clock.time = lambda: time.time() + jump[0]
    monkeypatch.setattr(bridge_module, "time", clock)
    session = open_session(station_transport(port))
    try:
        lease, token = arm(session, KEYS)
        for seq in range(1, 31):
            if seq == 10:
                jump[0] = 3600.0
            if seq == 20:
                jump[0] = -3600.0
            session.put(KEYS.cmd_walk, encode(WalkCommand(seq=seq, vx=0.1, vy=0.0, omega=0.0, ttl=0.5, lease=lease)))
            time.sleep(0.05)
        last_sent = time.time()
        assert len(standin.calls_to("ALMotion.move")) >= 25  # every jump crossed while walking
        assert wait_until(lambda: first_stop_after(standin, last_sent) is not None, 2.0)
        stopped = first_stop_after(standin, last_sent)
        assert stopped - last_sent <= bridge.params.deadman_s + bridge.params.control_period_s + 0.1
        token.undeclare()
    finally:
        session.close()


def test_log_of_a_killed_writer_reads_up_to_its_last_flush(tmp_path):
    path = tmp_path / "run.mcap"
    proc = subprocess.Popen([PY, "-c", LOG_SCRIPT, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "writing"
        time.sleep(2.6)
    finally:
        killed = time.time()
        proc.kill()
        proc.wait()
    with pytest.warns(UserWarning, match="incomplete MCAP"):
        stamps: List[float] = [m.json()["t"] for m in read_log(path)]
    assert stamps == sorted(stamps) and len(stamps) > 50
    assert killed - stamps[-1] <= 1.0 + 0.2  # the flush interval, plus scheduling on a loaded machine


# -- whole station process ---------------------------------------------------------------------------


def start_station(tmp_path: Path, port: int) -> subprocess.Popen:
    # the robot walking at once, not standing for the self-calibration first (station/pilot.py)
    (tmp_path / "station.yaml").write_text(f"station:\n  port: {port}\nself_calibration:\n  standstill: 0.0\n")
    return subprocess.Popen([PY, "-m", "station.cli", "start", "--robot", "127.0.0.1", "--out", str(tmp_path / "run"),
                             "--config", str(tmp_path / "station.yaml")],
                            stdout=subprocess.DEVNULL, stderr=open(tmp_path / "station.err", "wb"))


def test_station_process_killed_mid_walk_stops_the_robot_and_leaves_a_readable_log(robot, tmp_path):
    bridge, standin, port = robot
    proc = start_station(tmp_path, port)
    try:
        walking = wait_until(lambda: len(standin.calls_to("ALMotion.move")) > 0, 90.0)
        assert walking, (tmp_path / "station.err").read_text()[-2000:]
        time.sleep(2.0)  # a log with a few flushes
        # mid-walk: the station also stands still at times (head search, localization), then nothing is to stop
        assert wait_until(standin.world.is_walking, 60.0), "the station never walked again"
        killed = time.time()
        proc.kill()
        assert wait_until(lambda: first_stop_after(standin, killed) is not None, 2.0)
        assert first_stop_after(standin, killed) - killed <= STOP_WITHIN
    finally:
        proc.kill()
        proc.wait()
    log = tmp_path / "run" / "run.mcap"
    with pytest.warns(UserWarning, match="incomplete MCAP"):
        stamps = sorted(m.t for m in read_log(log))
    # the loop flushes at the end of a pass once flush_interval has passed: what a kill loses is at most
    # that interval plus one pass (the longest this run logged, on however loaded a machine) and the
    # scheduling of a process on a loaded 2-core machine (1 s: seen 0.5 s late with the suite running)
    flush_interval = load(StationParams, [CONFIG_DIR / "station.yaml"], section="station").flush_interval
    longest_pass = max(later - earlier for earlier, later in zip(stamps, stamps[1:]))
    assert killed - stamps[-1] <= flush_interval + longest_pass + 1.0, (killed - stamps[-1], longest_pass)
    for command in (["report", str(log), "-o", str(tmp_path / "report")], ["replay", str(log)]):
        done = subprocess.run([PY, "-m", "station.cli", *command], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, (command, done.stderr[-2000:])
        assert "incomplete MCAP" in done.stderr


@pytest.mark.slow  # 10-16 s; fast: the station notices a frozen bridge within 2 s (above), a killed one ends
# the mission with its result (tests/test_station_cli.py)
def test_bridge_frozen_mid_mission_ends_it_cleanly_as_bridge_lost(tmp_path):
    (tmp_path / "bridge.yaml").write_text("bridge:\n  resolution: qvga\n")
    bridge = LocalBridge(["--sim", "--config", str(tmp_path / "bridge.yaml")], tmp_path / "bridge.log")
    proc = start_station(tmp_path, bridge.port)
    try:
        assert wait_until(lambda: "phase" in (tmp_path / "station.err").read_text(errors="replace"), 90.0)
        frozen = time.time()
        bridge.process.send_signal(signal.SIGSTOP)
        assert proc.wait(240.0) == 1  # the final carve and report figures take long on a loaded machine
        ended = time.time()
    finally:
        bridge.process.send_signal(signal.SIGCONT)
        proc.kill()
        bridge.close(grace=2.0)
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert result["status"] == "failure" and result["outcome"] == "bridge_lost"
    assert "liveliness" in result["reason"]  # the lease ran out (a killed bridge: tests/test_station_cli.py)
    lost = [m.json()["t"] for m in read_log(tmp_path / "run" / "run.mcap", topics={INPUT})
            if m.json()["kind"] == "bridge_lost"]
    assert len(lost) == 1 and lost[0] - frozen <= NOTICE_WITHIN  # then the final carve and outputs
    assert ended > lost[0]


def test_corrupt_late_and_missing_frames_are_rejected_and_the_mission_goes_on(robot, tmp_path):
    """Injected on the bridge's own frame publisher: corrupt JPEG, wrong size, stamps 10 s late, seq gaps."""
    bridge, standin, port = robot
    proc = start_station(tmp_path, port)
    try:
        assert wait_until(lambda: len(standin.calls_to("ALMotion.move")) > 0, 90.0), "never walked"
        meta = dict(seq=10**6, stamp=time.time() - 10.0, width=320, height=240, encoding="jpeg", head_yaw=0.0,
                    head_pitch=0.3, T_BC=tuple(float(x) for x in np.eye(4).ravel()), odom=(0.0, 0.0, 0.0),
                    resolution="qvga")
        small = cv2.imencode(".jpg", np.zeros((10, 10, 3), np.uint8))[1].tobytes()
        late = cv2.imencode(".jpg", np.zeros((240, 320, 3), np.uint8))[1].tobytes()
        for i in range(10):
            for jpeg in (b"\xff\xd8" + bytes(range(256)) * 4, small, late):
                fields = dict(meta, seq=meta["seq"] + 7 * i, stamp=meta["stamp"] + 0.01 * i)
                bridge._frame_pub.put(encode_frame(FrameMeta(**fields), jpeg))  # noqa: SLF001 - fault injection
            time.sleep(0.1)
        injected = time.time()
        assert wait_until(lambda: len(moves_after(standin, injected + 1.0)) > 0, 15.0), "the mission stopped"
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        assert proc.wait(240.0) == 1
    finally:
        proc.kill()
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert "interrupted" in json.dumps(result) and "station error" not in json.dumps(result)
    log = tmp_path / "run" / "run.mcap"
    logged = [m.json()["seq"] for m in read_log(log, topics={FRAME_META}) if m.json()["seq"] >= 10**6]
    assert len(logged) >= 20  # logged, processed or not (the bridge's frame publisher may drop under load)
    assert len(list(read_log(log, topics={FRAME_REJECTED}))) > 0  # the loop processes only the newest of a pass


def test_a_camera_that_stops_mid_mission_stands_the_robot_and_ends_the_mission_as_camera_lost(robot, tmp_path):
    """The bridge stays connected and its NAOqi answers, but the camera's image never changes: the station
    stands the robot once ``frame_stall`` passes without a frame and ends ``camera_lost`` after
    ``frame_timeout`` (agent/mission.py), not walking its last plan blind and blaming the object."""
    bridge, standin, port = robot
    mission = load(MissionParams, [CONFIG_DIR / "mission.yaml"], section="mission")
    proc = start_station(tmp_path, port)
    try:
        assert wait_until(lambda: len(standin.calls_to("ALMotion.move")) > 0, 90.0), (tmp_path / "station.err").read_text()[-2000:]
        assert wait_until(standin.world.is_walking, 60.0), "the station never walked again"
        frozen = time.time()
        standin.freeze_camera()
        assert proc.wait(240.0) == 1
        ended = time.time()
    finally:
        proc.kill()
    walks = [c for c in standin.calls_to("ALMotion.move") if c.time > frozen + mission.frame_stall + 1.0 and any(c.args[:3])]
    assert walks == []
    assert not standin.world.is_walking()
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert result["status"] == "failure" and result["outcome"] == "camera_lost"
    assert "no camera frame" in result["reason"] and "bridge is connected" in result["reason"]
    assert ended - frozen >= mission.frame_timeout
