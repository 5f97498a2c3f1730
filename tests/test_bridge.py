"""The bridge end to end: real Zenoh sessions on loopback, the real NAOqi backend on the libqi stand-in
(or the simulator backend), a station side built here from the protocol package.

Timing assertions are behaviour (the deadman fires after the deadman time and before deadman time +
one control period + transport), checked on recorded timestamps, not speed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import time
from typing import List

import cv2
import numpy as np
import pytest
import zenoh
from zenoh_peers import free_port, wait_until

from nao_bridge.bridge import Bridge, BridgeParams
from nao_bridge.naoqi_backend import NaoqiBackend
from nao_bridge.sim_backend import SimBackend
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
from nao_sim.standin import StandIn
from nao_sim.world import SimWorld

MODEL = load_robot_model()
WAIT = 3.0  # s, generous: only a broken bridge waits this long
TRANSPORT_SLACK = 0.03  # s: Zenoh and libqi on a loaded loopback, on top of deadman + one period


def bridge_params(port: int, **changes) -> BridgeParams:
    params = load(BridgeParams, [CONFIG_DIR / "bridge.yaml"], section="bridge")
    transport = TransportConfig(listen=(f"tcp/127.0.0.1:{port}",), lease_ms=1000)
    return dataclasses.replace(params, transport=transport, resolution="qvga", **changes)


class Station:
    """The station's side of the protocol, as small as a test needs."""

    def __init__(self, port: int, name: str = "nao"):
        self.keys = RobotKeys(name)
        self.session = open_session(TransportConfig(connect=(f"tcp/127.0.0.1:{port}",), lease_ms=1000))
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
        self.token = self.session.liveliness().declare_token(self.keys.station_alive)
        self.seq = 0

    def walk(self, vx: float, vy: float = 0.0, omega: float = 0.0, ttl: float = 1.0) -> float:
        self.seq += 1
        self.walk_pub.put(encode(WalkCommand(seq=self.seq, vx=vx, vy=vy, omega=omega, ttl=ttl)))
        return time.time()

    def head(self, yaw: float, pitch: float, speed: float = 0.5) -> None:
        self.seq += 1
        self.head_pub.put(encode(HeadCommand(seq=self.seq, yaw=yaw, pitch=pitch, speed=speed)))

    def state(self) -> State:
        assert wait_until(lambda: bool(self.states), WAIT), "no state received"
        return self.states[-1]

    def fresh_state(self) -> State:
        count = len(self.states)
        assert wait_until(lambda: len(self.states) > count + 1, WAIT), "no fresh state"
        return self.states[-1]

    def close(self) -> None:
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
    station = Station(port)
    assert wait_until(lambda: bridge.station_alive, WAIT), "the bridge never saw the station"
    station.state()
    yield bridge, station, standin
    station.close()
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
    good = {"v": 1, "type": "cmd.walk", "seq": 1000, "vx": 0.05, "vy": 0.0, "omega": 0.0, "ttl": 1.0}

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
    station.head_pub.put(json.dumps({"v": 1, "type": "cmd.head", "seq": 1, "yaw": 0.0, "pitch": 0.0, "speed": 0.0}).encode())
    expected["bad_value"] += 1
    station.head_pub.put(encode(WalkCommand(seq=1, vx=0.05, vy=0.0, omega=0.0, ttl=1.0)))  # walk on the head key
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


def test_station_liveliness_lost_stops_before_the_deadman(standin):
    port = free_port()
    params = bridge_params(port, deadman_s=2.0)
    bridge = Bridge(NaoqiBackend(standin.url, MODEL, params.naoqi, "qvga", 15.0), MODEL, params, "naoqi")
    with bridge:
        station = Station(port)
        assert wait_until(lambda: bridge.station_alive, WAIT)
        station.walk(0.05, ttl=5.0)
        assert wait_until(lambda: bool(moves(standin)), WAIT)
        lost = time.time()
        station.token.undeclare()
        assert wait_until(lambda: any(c.time > lost for c in stops(standin)), timeout=1.0)
        assert next(c for c in stops(standin) if c.time > lost).time - lost < 0.5 < params.deadman_s
        station.walk(0.05, ttl=5.0)  # without a station token, walking is refused
        assert wait_until(lambda: station.state().ignored.get("no_station") == 1, WAIT)
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
    world.render = lambda: capture_stamps.append(render()) or capture_stamps[-1]
    yaw, pitch = look_at_marker(world)
    station.head(yaw, pitch, speed=0.5)
    assert wait_until(lambda: np.allclose(world.head_angles(), (yaw, pitch), atol=1e-6), timeout=3.0)
    settled = time.time()
    frame = newest_frame_after(station, settled + 0.1)
    check_frame_matches_truth(frame, world)
    # The robot clock runs 1000 s ahead: the bridge's stamp is the capture time on its own clock, late by
    # at most the smallest capture-to-receive latency (the clock-offset estimate), never early.
    # Each stamp must fall after its capture and before the next one (1/15 s later).
    errors = [f.meta.stamp - max(c.stamp for c in capture_stamps if c.stamp <= f.meta.stamp) for f in station.frames[-10:]]
    assert all(0.0 <= e < 1.0 / 15.0 for e in errors), errors


def test_sim_frames_and_truth_match(tmp_path):
    port = free_port()
    world = SimWorld("can", MODEL, resolution="qvga", seed=4)
    with Bridge(SimBackend(world, fps=15.0), MODEL, bridge_params(port), "sim") as bridge:
        station = Station(port)
        assert wait_until(lambda: bridge.station_alive, WAIT)
        yaw, pitch = look_at_marker(world)
        station.head(yaw, pitch, speed=0.5)
        assert wait_until(lambda: np.allclose(world.head_angles(), (yaw, pitch), atol=1e-6), timeout=3.0)
        frame = newest_frame_after(station, time.time() + 0.1)
        check_frame_matches_truth(frame, world)
        assert abs(frame.meta.stamp - world.truth()["camera"]["stamp"]) < 0.2
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
        station = Station(port, name="clitest")
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
        (["--sim", "--scenario", "nope"], "configuration error: --scenario: unknown scenario 'nope'; known: ['can', 'figure', 'remote']"),
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
