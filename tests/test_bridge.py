"""The bridge end to end: real Zenoh sessions on loopback, the real NAOqi backend on the libqi stand-in
(or the simulator backend), a station side built here from the protocol package.

Timing assertions are behaviour (the deadman fires after the deadman time and before deadman time +
one control period + transport), checked on recorded timestamps, not speed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import List

import cv2
import numpy as np
import pytest
import zenoh
from zenoh_peers import free_port, station_token, take_lease, wait_until

from nao_bridge.bridge import Bridge, BridgeParams
from nao_bridge.naoqi_backend import NaoqiBackend
from nao_bridge.sim_backend import SimBackend
from nao_bridge.watchdog import STOPS_KEY as WATCHDOG_STOPS
from nao_core.config import CONFIG_DIR, load
from nao_core.landmark_map import load_landmark_map
from nao_core.protocol import (
    HeadCommand,
    Info,
    RobotKeys,
    State,
    Truth,
    WalkCommand,
    decode,
    decode_frame,
    encode,
)
from nao_core.robot_model import load_robot_model
from nao_core.transport import TransportConfig, open_session
from nao_sim.scenarios import load_sim_config
from nao_sim.standin import StandIn
from nao_sim.world import SimWorld

pytestmark = pytest.mark.serial  # the bridge process, Zenoh sessions and its watchdog's timing: run alone (Makefile test)

MODEL = load_robot_model()
WAIT = 3.0  # s, generous: only a broken bridge waits this long
TRANSPORT_SLACK = 0.1  # s: Zenoh, libqi and thread wake-ups on a loaded 2-core loopback, on top of deadman + one period
# (the rule itself is tested exactly on a fake clock: test_the_deadman_rule_on_the_safety_ticks_own_clock)


def bridge_params(port: int, **changes) -> BridgeParams:
    params = load(BridgeParams, [CONFIG_DIR / "bridge.yaml"], section="bridge")
    transport = TransportConfig(listen=(f"tcp/127.0.0.1:{port}",), lease_ms=1000)
    return dataclasses.replace(params, transport=transport, resolution="qvga", **changes)


OPEN_STATIONS: List["Station"] = []


@pytest.fixture(autouse=True)
def close_stations():
    """Every Station a test opened is closed, whether the test passed or not: a Zenoh session left
    open keeps its subscribers' callback threads (not daemons) waiting, and the interpreter never exits."""
    yield
    while OPEN_STATIONS:
        OPEN_STATIONS[-1].close()


class Station:
    """The station's side of the protocol, as small as a test needs."""

    def __init__(self, port: int, name: str = "nao", credentials: bool = False, ready: float = WAIT):
        """Connect, subscribe, wait up to ``ready`` s for the bridge's liveliness token, take the lease.
        Closed by the ``close_stations`` fixture at the latest, even when this fails."""
        self.keys = RobotKeys(name)
        endpoint = (f"tcp/127.0.0.1:{port}",)
        self.session = open_session(TransportConfig.with_credentials("station", connect=endpoint, robot=name)
                                    if credentials else TransportConfig(connect=endpoint, lease_ms=1000, robot=name))
        OPEN_STATIONS.append(self)
        self._start(ready)

    def _start(self, ready: float) -> None:
        self.states: List[State] = []
        self.frames: list = []
        self.truths: List[Truth] = []
        self.bridge_alive: List[bool] = []
        block = zenoh.CongestionControl.BLOCK
        self.walk_pub = self.session.declare_publisher(self.keys.cmd_walk, congestion_control=block)
        self.head_pub = self.session.declare_publisher(self.keys.cmd_head, congestion_control=block)
        self.subs = [
            self.session.declare_subscriber(self.keys.state, lambda s: self.states.append(decode(s.payload.to_bytes(), State))),
            self.session.declare_subscriber(self.keys.camera_top, lambda s: self.frames.append(decode_frame(s.payload.to_bytes()))),
            self.session.declare_subscriber(self.keys.sim_truth, lambda s: self.truths.append(decode(s.payload.to_bytes(), Truth))),
            self.session.liveliness().declare_subscriber(
                self.keys.alive, lambda s: self.bridge_alive.append(s.kind == zenoh.SampleKind.PUT), history=True
            ),
        ]
        assert wait_until(lambda: self.bridge_alive[-1:] == [True], ready), "the bridge is not up"
        self.id, self.token = station_token(self.session, self.keys)
        self.seq = 0
        self.lease = self.rearm()

    def rearm(self) -> str:
        """Take the bridge's lease (the explicit arm); commands carry it."""
        reply = take_lease(self.session, self.id, self.keys)
        assert reply is not None and reply.granted, reply
        self.lease, self.seq = reply.lease, 0
        return reply.lease

    def walk(self, vx: float, vy: float = 0.0, omega: float = 0.0, ttl: float = 1.0) -> float:
        self.seq += 1
        self.walk_pub.put(encode(WalkCommand(seq=self.seq, vx=vx, vy=vy, omega=omega, ttl=ttl, lease=self.lease)))
        return time.time()

    def head(self, yaw: float, pitch: float, speed: float = 0.5) -> None:
        self.seq += 1
        self.head_pub.put(encode(HeadCommand(seq=self.seq, yaw=yaw, pitch=pitch, speed=speed, lease=self.lease)))

    def state(self) -> State:
        assert wait_until(lambda: bool(self.states), WAIT), "no state received"
        return self.states[-1]

    def fresh_state(self) -> State:
        count = len(self.states)
        assert wait_until(lambda: len(self.states) > count + 1, WAIT), "no fresh state"
        return self.states[-1]

    def close(self) -> None:
        """Close the session (its subscribers and their threads); idempotent."""
        if self in OPEN_STATIONS:
            OPEN_STATIONS.remove(self)
            self.session.close()


@pytest.fixture
def standin():
    world = SimWorld("can", MODEL, resolution="qvga", seed=4)
    with StandIn(world) as served:
        yield served


@pytest.fixture
def rig(standin):
    """A bridge on the NAOqi backend (through the stand-in) and a connected station."""
    port = free_port()
    backend = NaoqiBackend(standin.url, MODEL, bridge_params(port).naoqi, "qvga", 15.0)
    bridge = Bridge(backend, MODEL, bridge_params(port), "naoqi")
    bridge.start()
    try:
        station = Station(port)
        try:
            assert wait_until(lambda: bridge.station_alive, WAIT), "the bridge never saw the station"
            station.state()
            yield bridge, station, standin
        finally:
            station.close()
    finally:
        bridge.close()


def moves(standin: StandIn) -> list:
    return standin.calls_to("ALMotion.move")


def stops(standin: StandIn) -> list:
    return standin.calls_to("ALMotion.stopMove")


def walk_for(station: Station, duration: float, vx: float = 0.05, rate: float = 20.0, ttl: float = 1.0) -> float:
    end = time.monotonic() + duration
    last = 0.0
    while time.monotonic() < end:
        last = station.walk(vx, ttl=ttl)
        time.sleep(1.0 / rate)
    return last


def malformed_walks() -> List[tuple]:
    good = {"v": 1, "type": "cmd.walk", "seq": 1000, "vx": 0.05, "vy": 0.0, "omega": 0.0, "ttl": 1.0, "lease": "ab12"}

    def variant(**changes):
        data = dict(good, **changes)
        return json.dumps({k: v for k, v in data.items() if v is not None}, separators=(",", ":")).encode()

    return [
        ("oversize", b" " * 70000),
        ("encoding", b"\x80\x81 not utf-8"),
        ("encoding", b"{not json"),
        ("version", variant(v=2)),
        ("type", variant(type="cmd.head")),
        ("missing_field", variant(ttl=None)),
        ("unknown_field", variant(extra=1)),
        ("non_finite", variant().replace(b'"vx":0.05', b'"vx":NaN')),
        ("non_finite", variant().replace(b'"omega":0.0', b'"omega":-Infinity')),
        ("bad_value", variant(vx="fast")),
        ("bad_value", variant(vx=5.0)),
        ("bad_value", variant(ttl=-1.0)),
    ]


def test_malformed_commands_are_rejected_counted_and_never_move_the_robot(rig):
    bridge, station, standin = rig
    expected: dict = {}
    for reason, payload in malformed_walks():
        station.walk_pub.put(payload)
        expected[reason] = expected.get(reason, 0) + 1
    station.head_pub.put(json.dumps({"v": 1, "type": "cmd.head", "seq": 1, "yaw": 0.0, "pitch": 0.0, "speed": 0.0,
                                     "lease": station.lease}).encode())
    expected["bad_value"] += 1
    station.head_pub.put(encode(WalkCommand(seq=1, vx=0.05, vy=0.0, omega=0.0, ttl=1.0, lease=station.lease)))  # walk on the head key
    expected["type"] += 1
    assert wait_until(lambda: station.state().rejected == expected, WAIT), station.state().rejected
    time.sleep(0.1)
    assert moves(standin) == [] and standin.calls_to("ALMotion.setAngles") == []
    assert station.state().walking is False


def test_valid_walk_moves_with_clamped_velocities(rig):
    bridge, station, standin = rig
    station.walk(0.5, vy=-0.3, omega=2.0)  # valid on the wire, beyond the robot's limits
    assert wait_until(lambda: bool(moves(standin)), WAIT)
    assert moves(standin)[0].args == pytest.approx((MODEL.walk.v_max, -MODEL.walk.vy_max, MODEL.walk.omega_max))
    station.walk(-0.5, omega=-2.0)
    assert wait_until(lambda: len(moves(standin)) == 2, WAIT)
    assert moves(standin)[1].args == pytest.approx((MODEL.walk.v_min, 0.0, -MODEL.walk.omega_max))


def test_head_commands_are_clamped_to_the_yaw_dependent_limits(rig):
    bridge, station, standin = rig
    station.head(3.0, 1.0, speed=1.0)
    assert wait_until(lambda: bool(standin.calls_to("ALMotion.setAngles")), WAIT)
    names, (yaw, pitch), speed = standin.calls_to("ALMotion.setAngles")[0].args
    assert list(names) == ["HeadYaw", "HeadPitch"]
    assert yaw == pytest.approx(MODEL.head.yaw[1])
    assert pitch == pytest.approx(MODEL.head.pitch_range(MODEL.head.yaw[1])[1])
    assert speed == pytest.approx(bridge.params.head_speed_max)


def test_deadman_stops_after_the_deadman_time_and_within_one_period(rig):
    bridge, station, standin = rig
    last_sent = walk_for(station, 0.5, ttl=5.0)
    assert moves(standin), "the robot never walked"
    assert wait_until(lambda: any(c.time > last_sent for c in stops(standin)), timeout=2.0)
    stop = next(c for c in stops(standin) if c.time > last_sent)
    delay = stop.time - last_sent
    params = bridge.params
    assert params.deadman_s - 0.005 <= delay <= params.deadman_s + params.control_period_s + TRANSPORT_SLACK, delay
    assert all(c.time < stop.time for c in moves(standin))
    assert station.fresh_state().watchdog == "deadman"


@pytest.mark.parametrize("ttl", [5.0, 0.1])
def test_the_deadman_rule_on_the_safety_ticks_own_clock(ttl):
    """The rule itself, on a fake clock (the safety tick's ``now``): a walk holds until min(deadman_s,
    ttl) after its arrival, not a tick longer; the tick past it stops the robot and says why. The
    real-time tests around it check that the ticks come at the control period. The world's clock
    stands still: on a wall clock a slow machine let the walk's sway build up, which outlasts the stop."""
    world = SimWorld("can", MODEL, "qvga", seed=1, clock=lambda: 1000.0)
    bridge = Bridge(SimBackend(world, fps=15.0), MODEL, bridge_params(free_port()), "sim")
    bridge._lease = "lease"
    limit, arrived = min(bridge.params.deadman_s, ttl), 1000.0
    bridge._walk = (WalkCommand(seq=1, vx=0.05, vy=0.0, omega=0.0, ttl=ttl, lease="lease"), arrived)
    world.walk(0.05, 0.0, 0.0)
    bridge._safety_tick(arrived + limit - 1e-6)
    assert bridge._watchdog == "walking" and world.is_walking()
    bridge._safety_tick(arrived + limit + 1e-6)
    assert bridge._watchdog == "deadman" and bridge._walk is None
    assert not world.is_walking()


def test_short_ttl_stops_before_the_deadman(rig):
    bridge, station, standin = rig
    sent = station.walk(0.05, ttl=0.1)
    assert wait_until(lambda: any(c.time > sent for c in stops(standin)), timeout=2.0)
    delay = next(c for c in stops(standin) if c.time > sent).time - sent
    assert 0.1 - 0.005 <= delay <= 0.1 + bridge.params.control_period_s + TRANSPORT_SLACK, delay


def test_stale_commands_are_ignored(rig):
    bridge, station, standin = rig
    station.seq = 10
    station.walk(0.05, ttl=5.0)
    assert wait_until(lambda: len(moves(standin)) == 1, WAIT)
    station.seq = 4  # older sequence number
    station.walk(0.09, ttl=5.0)
    station.seq = 10  # same sequence number again
    station.walk(0.09, ttl=5.0)
    station.seq = 20
    station.walk(0.09, ttl=0.0)  # expired on arrival
    assert wait_until(lambda: station.state().ignored == {"stale_seq": 2, "expired": 1}, WAIT), station.state().ignored
    assert [c.args[0] for c in moves(standin)] == [pytest.approx(0.05)]


def test_fall_stops_reports_fallen_and_refuses_walking(rig):
    bridge, station, standin = rig
    station.walk(0.05, ttl=5.0)
    assert wait_until(lambda: bool(moves(standin)), WAIT)
    fall_time = time.time()
    standin.fall()
    assert wait_until(lambda: any(c.time >= fall_time for c in stops(standin)), timeout=1.0)
    assert wait_until(lambda: station.state().fallen and station.state().watchdog == "fallen", WAIT)
    count = len(moves(standin))
    for _ in range(3):
        station.walk(0.05, ttl=5.0)
    assert wait_until(lambda: station.state().ignored.get("fallen") == 3, WAIT)
    assert len(moves(standin)) == count


def test_station_lost_stops_before_the_deadman_and_stays_stopped_until_rearmed(standin):
    port = free_port()
    params = bridge_params(port, deadman_s=2.0)
    bridge = Bridge(NaoqiBackend(standin.url, MODEL, params.naoqi, "qvga", 15.0), MODEL, params, "naoqi")
    with bridge:
        station = Station(port)
        station.walk(0.05, ttl=5.0)
        assert wait_until(lambda: bool(moves(standin)), WAIT)
        lost = time.time()
        station.token.undeclare()  # what a frozen station looks like once its link lease expires
        assert wait_until(lambda: any(c.time > lost for c in stops(standin)), timeout=1.0)
        assert next(c for c in stops(standin) if c.time > lost).time - lost < 0.5 < params.deadman_s
        assert wait_until(lambda: station.state().watchdog == "station_lost" and station.state().owner is None, WAIT)
        # the station comes back (a frozen one resuming): its token again, its old lease, newer seqs
        station.token = station.session.liveliness().declare_token(station.keys.station_token(station.id))
        assert wait_until(lambda: bridge.station_alive, WAIT)
        count = len(moves(standin))
        for _ in range(5):
            station.walk(0.05, ttl=5.0)
        assert wait_until(lambda: station.state().ignored.get("not_owner") == 5, WAIT), station.state().ignored
        assert len(moves(standin)) == count and station.state().watchdog == "station_lost"
        station.rearm()  # the explicit re-arm: a new lease
        station.walk(0.05, ttl=5.0)
        assert wait_until(lambda: len(moves(standin)) > count, WAIT)
        station.close()


def test_close_stops_unsubscribes_and_rests(rig):
    bridge, station, standin = rig
    station.walk(0.05, ttl=5.0)
    assert wait_until(lambda: bool(moves(standin)), WAIT)
    closed = time.time()
    bridge.close()
    names = [c.name for c in standin.calls if c.time >= closed]
    assert names.index("ALMotion.stopMove") < names.index("ALVideoDevice.unsubscribe") < names.index("ALMotion.rest")
    assert wait_until(lambda: station.bridge_alive[-1:] == [False], WAIT), "the bridge's liveliness token is still there"


def test_info_queryable_describes_the_robot(rig):
    bridge, station, standin = rig
    replies = list(station.session.get(station.keys.info, timeout=2.0))
    assert len(replies) == 1
    info = decode(replies[0].ok.payload.to_bytes(), Info)
    assert info.robot == MODEL and info.backend == "naoqi" and info.resolution == "qvga"
    assert info.intrinsics == MODEL.camera.intrinsics("qvga") and info.deadman_s == bridge.params.deadman_s


def planar(x: float, y: float, theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def look_at_marker(world: SimWorld) -> tuple:
    """Head (yaw, pitch) centring the ArUco marker nearest to 1.5 m away among those the head can face."""
    x, y, theta = world.true_pose()
    camera_height = MODEL.camera_in_robot(0.0, 0.0)[2, 3]
    best = None
    for lm in load_landmark_map(world.config.landmark_path).landmarks:
        dx, dy = lm.position[0] - x, lm.position[1] - y
        yaw = math.remainder(math.atan2(dy, dx) - theta, 2 * math.pi)
        if lm.kind == "aruco" and abs(yaw) < MODEL.head.yaw[1] - 0.1:
            distance = math.hypot(dx, dy)
            if best is None or abs(distance - 1.5) < abs(best[0] - 1.5):
                best = (distance, yaw, math.atan2(camera_height - lm.position[2], distance))
    assert best is not None
    return MODEL.head.clamp(best[1], best[2])


def marker_reprojection_error(frame, world: SimWorld, T_WC: np.ndarray) -> float:
    """Largest pixel distance between the ArUco corners detected in the JPEG and the true corners
    projected with the camera pose T_WC: small only if image and pose belong together."""
    image = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR)
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    corners, ids, _ = detector.detectMarkers(image)
    assert ids is not None, "no marker in view"
    landmarks = {lm.id: lm for lm in load_landmark_map(world.config.landmark_path).landmarks}
    intr = MODEL.camera.intrinsics(frame.meta.resolution)
    T_CW = np.linalg.inv(T_WC)
    errors = []
    for marker_id, seen in zip(ids.ravel(), corners):
        rvec = cv2.Rodrigues(T_CW[:3, :3])[0]
        expected, _ = cv2.projectPoints(landmarks[int(marker_id)].aruco_corners(), rvec, T_CW[:3, 3], intr.K, np.asarray(intr.dist))
        errors.append(np.max(np.linalg.norm(expected.reshape(4, 2) - seen.reshape(4, 2), axis=1)))
    return float(max(errors))


def check_frame_matches_truth(frame, world: SimWorld) -> None:
    meta = frame.meta
    T_BC = np.asarray(meta.T_BC).reshape(4, 4)
    T_WC_meta = planar(*world.start_pose) @ planar(*meta.odom) @ T_BC  # where the frame's metadata puts the camera
    T_WC_true = np.asarray(world.truth()["camera"]["T_WC"])
    assert np.allclose(T_WC_meta, T_WC_true, atol=1e-6)  # the robot stood still: odometry is exact
    assert marker_reprojection_error(frame, world, T_WC_meta) < 2.0
    assert abs(meta.head_yaw - world.head_angles()[0]) < 1e-6
    assert (meta.width, meta.height) == (320, 240)


def newest_frame_after(station: Station, moment: float):
    assert wait_until(lambda: any(f.meta.stamp > moment for f in station.frames), timeout=3.0)
    return station.frames[-1]


def test_standin_frames_carry_the_true_camera_pose_on_the_bridge_clock(rig):
    bridge, station, standin = rig
    world = standin.world
    render, capture_stamps = world.render, []
    world.render = lambda at=None: capture_stamps.append(render(at=at)) or capture_stamps[-1]  # the stand-in's call
    yaw, pitch = look_at_marker(world)
    station.head(yaw, pitch, speed=0.5)
    assert wait_until(lambda: np.allclose(world.head_angles(), (yaw, pitch), atol=1e-6), timeout=3.0)
    settled = time.time()
    frame = newest_frame_after(station, settled + 0.1)
    check_frame_matches_truth(frame, world)
    # The robot clock runs 1000 s ahead: the bridge's stamp is the capture time on its own clock, off by
    # half the clock probe's shortest loopback round trip (docs/frames.md), far less than a frame period
    errors = [min(abs(f.meta.stamp - c.stamp) for c in capture_stamps) for f in station.frames[-10:]]
    assert all(e <= 0.005 for e in errors), errors


def test_sim_frames_and_truth_match(tmp_path):
    port = free_port()
    world = SimWorld("can", MODEL, resolution="qvga", seed=4)
    render, render_stamps = world.render, []
    world.render = lambda: render_stamps.append(render()) or render_stamps[-1]  # what the sim backend calls
    with Bridge(SimBackend(world, fps=15.0), MODEL, bridge_params(port), "sim") as bridge:
        station = Station(port)
        assert wait_until(lambda: bridge.station_alive, WAIT)
        yaw, pitch = look_at_marker(world)
        station.head(yaw, pitch, speed=0.5)
        assert wait_until(lambda: np.allclose(world.head_angles(), (yaw, pitch), atol=1e-6), timeout=3.0)
        frame = newest_frame_after(station, time.time() + 0.1)
        check_frame_matches_truth(frame, world)
        assert frame.meta.stamp in [f.stamp for f in render_stamps]  # its render's capture time, not the send time
        assert wait_until(lambda: bool(station.truths), WAIT)
        truth = station.truths[-1]
        assert truth.robot_pose == pytest.approx(world.true_pose(), abs=1e-9)
        assert truth.object.radius == pytest.approx(0.055, abs=1e-3)
        station.close()


def test_cli_sim_runs_and_exits_cleanly_on_sigterm():
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "nao_bridge.cli", "--sim", "--listen", f"tcp/127.0.0.1:{port}", "--name", "clitest"],
        stderr=subprocess.PIPE, text=True,
    )
    try:
        # the CLI's default: generated credentials; the process starts on a loaded machine
        station = Station(port, name="clitest", credentials=True, ready=30.0)
        assert wait_until(lambda: bool(station.frames) and bool(station.states), timeout=15.0)
        station.close()
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "bridge closed" in err


@pytest.mark.parametrize(
    "args, message",
    [
        (["--sim", "--config", "{bad}"], "configuration error: {bad}: bridge.deadman_s: expected a number in [0.05, 2.0], got 9"),
        (["--sim", "--scenario", "nope"],  # the known scenarios are those of config/sim.yaml
         f"configuration error: --scenario: unknown scenario 'nope'; known: {sorted(load_sim_config().scenarios)}"),
    ],
)
def test_cli_config_errors_are_one_line(tmp_path, args, message):
    bad = tmp_path / "bad.yaml"
    bad.write_text("bridge:\n  deadman_s: 9\n")
    args = [str(bad) if a == "{bad}" else a for a in args]
    proc = subprocess.run([sys.executable, "-m", "nao_bridge.cli", *args], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip() == message.replace("{bad}", str(bad))


def test_cli_unreachable_robot_exits_1_without_traceback():
    proc = subprocess.run(
        [sys.executable, "-m", "nao_bridge.cli", "--naoqi", f"tcp://127.0.0.1:{free_port()}", "--listen", f"tcp/127.0.0.1:{free_port()}"],
        capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 1
    assert "cannot reach NAOqi" in proc.stderr and "Traceback" not in proc.stderr


# -- confirmed stops ----------------------------------------------------------------------------------


def test_a_stop_that_fails_once_is_retried_and_confirmed_and_reported(rig):
    bridge, station, standin = rig
    real_stop, failures = bridge.backend.stop_walking, []

    def stop_once_broken() -> None:
        if not failures:
            failures.append(time.time())
            raise RuntimeError("injected: NAOqi link down")
        real_stop()

    bridge.backend.stop_walking = stop_once_broken
    station.walk(0.05, ttl=0.2)
    assert wait_until(lambda: bool(moves(standin)), WAIT)
    assert wait_until(lambda: bool(failures) and bool(stops(standin)), WAIT), "the failed stop was never retried"
    retry = stops(standin)[0]
    # retried by the next control period, not by a later command (none is sent)
    assert retry.time - failures[0] <= bridge.params.control_period_s + bridge.params.call_timeout_s
    assert wait_until(lambda: any(c.time >= retry.time for c in standin.calls_to("ALMotion.moveIsActive")), WAIT), \
        "the stop was never confirmed with moveIsActive"
    assert wait_until(lambda: not station.state().walking, WAIT), "the robot never stopped (it decelerates first)"
    state = station.fresh_state()
    assert state.stop_failures == 1 and state.watchdog == "deadman", state
    assert not bridge._moving and bridge._pending is None  # confirmed: the safety thread stopped retrying


def test_a_stop_never_confirmed_escalates_reports_stop_failed_and_refuses_walks(standin):
    port = free_port()
    params = bridge_params(port, stop_escalate_s=0.2)
    bridge = Bridge(NaoqiBackend(standin.url, MODEL, params.naoqi, "qvga", 15.0), MODEL, params, "naoqi")
    with bridge:
        station = Station(port)
        bridge.backend.move_is_active = lambda: True  # NAOqi keeps saying the robot walks
        station.walk(0.05, ttl=0.1)
        assert wait_until(lambda: bool(standin.calls_to("ALMotion.killMove")), WAIT), "no killMove"
        assert wait_until(lambda: bool(standin.calls_to("ALMotion.rest")), WAIT), "no rest after twice the time"
        assert wait_until(lambda: station.state().watchdog == "stop_failed", WAIT)
        count = len(moves(standin))
        station.walk(0.05, ttl=5.0)
        station.fresh_state()
        assert len(moves(standin)) == count and station.state().stop_failures >= 1
        del bridge.backend.move_is_active  # NAOqi confirms the stop again
        assert wait_until(lambda: station.state().watchdog != "stop_failed", WAIT)
        station.close()


def test_a_blocked_backend_call_times_out_and_the_stop_is_retried(rig):
    bridge, station, standin = rig
    real_stop, blocked = bridge.backend.stop_walking, []

    def stop_blocked_once() -> None:
        if not blocked:
            blocked.append(time.time())
            time.sleep(2.0)  # a NAOqi call that never answers in time
        real_stop()

    bridge.backend.stop_walking = stop_blocked_once
    station.walk(0.05, ttl=0.2)
    assert wait_until(lambda: bool(blocked), WAIT)
    # the retry arrives after the call timeout, long before the blocked call returns
    assert wait_until(lambda: any(c.time < blocked[0] + 2.0 for c in stops(standin)), WAIT)
    assert wait_until(lambda: station.state().stop_failures == 1 and not station.state().walking, WAIT)


# -- the robot-side watchdog --------------------------------------------------------------------------


def test_watchdog_is_python_2_7_compatible():
    """vermin (a test extra) finds the minimum Python versions of every construct and module used."""
    done = subprocess.run([str(Path(sys.executable).with_name("vermin")), "-t=2.7-", "-t=3.6-", "--no-tips", "--violations",
                           str(Path(__file__).parents[1] / "nao_bridge" / "watchdog.py")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


def _bridge_process(standin: StandIn, port: int, tmp_path: Path, required: bool) -> subprocess.Popen:
    override = tmp_path / "bridge.yaml"
    override.write_text(json.dumps({"bridge": {"resolution": "qvga", "fps": 5.0,
                                               "robot_watchdog": "required" if required else "auto"}}))
    return subprocess.Popen([sys.executable, "-m", "nao_bridge.cli", "--naoqi", standin.url, "--insecure",
                             "--listen", f"tcp/127.0.0.1:{port}", "--config", str(override)],
                            stdout=open(tmp_path / "bridge.log", "wb"), stderr=subprocess.STDOUT)


def test_frozen_bridge_is_stopped_by_the_robot_side_watchdog(standin, tmp_path):
    """Bridge off the robot, watchdog required: no walk without the watchdog; SIGSTOP -> stopMove from it."""
    port = free_port()
    bridge = _bridge_process(standin, port, tmp_path, required=True)
    watchdog = None
    try:
        station = Station(port, ready=30.0)  # a process starting on a loaded machine
        assert wait_until(lambda: station.state().robot_watchdog == "missing", 20.0)
        walk_for(station, 0.5)
        assert moves(standin) == [] and station.state().watchdog == "no_robot_watchdog"
        timeout, period = 0.3, 0.05
        watchdog = subprocess.Popen([sys.executable, "-m", "nao_bridge.watchdog", "--url", standin.url,
                                     "--timeout", str(timeout), "--period", str(period)])
        assert wait_until(lambda: station.state().robot_watchdog == "ok", 10.0)
        walk_for(station, 0.5, ttl=5.0)
        assert moves(standin), "the robot never walked with the watchdog answering"
        frozen = time.time()
        bridge.send_signal(signal.SIGSTOP)  # the station machine freezes: no heartbeat, no stop from the bridge
        assert wait_until(lambda: any(c.time > frozen for c in stops(standin)), 2.0), "nothing stopped the robot"
        stop = next(c for c in stops(standin) if c.time > frozen)
        # the watchdog's bound: last heartbeat <= freeze, + timeout + one check period + one NAOqi call
        assert stop.time - frozen <= 0.5, stop.time - frozen
        def from_watchdog() -> list:  # the watchdog counts a stop right after its stopMove
            return [c for c in standin.calls_to("ALMemory.insertData") if c.args[0] == WATCHDOG_STOPS]

        assert wait_until(lambda: bool(from_watchdog()), WAIT), "the watchdog never counted a stop"
        assert from_watchdog()[0].time >= stop.time
        assert not standin.world.is_walking() or standin.calls_to("ALMotion.moveIsActive")
        bridge.send_signal(signal.SIGCONT)
        station.close()
    finally:
        for process in (watchdog, bridge):
            if process is not None:
                process.send_signal(signal.SIGCONT)
                process.terminate()
                process.wait(10)


def test_install_watchdog_copies_and_starts_it_over_ssh(tmp_path):
    """``install-watchdog`` with stand-ins for ssh and scp that run on this machine in a fake home."""
    home = tmp_path / "home"
    home.mkdir()
    fake_ssh, fake_scp = tmp_path / "ssh", tmp_path / "scp"
    fake_ssh.write_text(f'#!/bin/sh\necho "$1" >> {tmp_path}/targets\nshift\ncd {home} && HOME={home} sh -c "$*"\n')
    fake_scp.write_text(f'#!/bin/sh\necho "$2" >> {tmp_path}/targets\ncp "$1" "{home}/${{2#*:}}"\n')
    for script in (fake_ssh, fake_scp):
        script.chmod(0o755)
    code = subprocess.run([sys.executable, "-m", "nao_bridge.cli", "install-watchdog", "nao.local", "--timeout", "0.3",
                           "--python", sys.executable, "--ssh", str(fake_ssh), "--scp", str(fake_scp)],
                          capture_output=True, text=True, timeout=60)
    pid_file = home / "nao-active-recon" / "watchdog.pid"
    try:
        assert code.returncode == 0, code.stderr
        assert "watchdog running" in code.stdout
        assert (home / "nao-active-recon" / "watchdog.py").read_bytes() == \
            (Path(__file__).parents[1] / "nao_bridge" / "watchdog.py").read_bytes()
        assert set((tmp_path / "targets").read_text().split()) == {"nao@nao.local", "nao@nao.local:nao-active-recon/watchdog.py"}
    finally:
        if pid_file.exists():
            os.kill(int(pid_file.read_text()), signal.SIGTERM)
