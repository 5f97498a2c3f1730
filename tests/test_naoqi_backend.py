"""The NAOqi backend against the libqi stand-in (real qi sessions on loopback) and its pure helpers."""

from __future__ import annotations

import dataclasses
import math
import socket
import threading
import time

import cv2
import numpy as np
import pytest

from nao_bridge.bridge import BridgeParams
from nao_bridge.capture_kinematics import (
    AFTER,
    BEFORE,
    GAP,
    KinematicSample,
    KinematicsHistory,
    interpolate_transform,
)
from nao_bridge.naoqi_backend import (
    COLOR_SPACE_IDS,
    ClockOffset,
    ClockProbe,
    NaoqiBackend,
    image_to_bgr,
    on_this_machine,
)
from nao_core.config import CONFIG_DIR, load
from nao_core.geometry import rot_x, rot_z
from nao_core.naoqi_api import CLOCK_PROBE_KEY, RESOLUTION_IDS, TOP_CAMERA, RGB_COLOR_SPACE, Y_COLOR_SPACE, YUV_COLOR_SPACE
from nao_core.robot_model import load_robot_model, nao_to_optical
from nao_sim.scenarios import load_sim_config
from nao_sim.standin import ALMotion, ALVideoDevice, CameraDelivery, StandIn
from nao_sim.world import SimWorld

pytestmark = pytest.mark.serial  # a qi session to the stand-in and its timing: run alone (Makefile test)

MODEL = load_robot_model()
NAOQI_PARAMS = load(BridgeParams, [CONFIG_DIR / "bridge.yaml"], section="bridge").naoqi  # the shipped defaults
SIM = load_sim_config()
BGR, YUV422 = COLOR_SPACE_IDS["bgr"], COLOR_SPACE_IDS["yuv422"]
FPS = 15.0
STAMP_ERROR = 0.005  # s: a probed stamp is within half the shortest loopback round trip (ms on a loaded machine)


def rotation_angle(A: np.ndarray, B: np.ndarray) -> float:
    """Angle (rad) of the rotation between two transforms."""
    rotvec, _ = cv2.Rodrigues(A[:3, :3].T @ B[:3, :3])
    return float(np.linalg.norm(rotvec))


def test_image_buffer_as_bytes_bytearray_or_latin1_text():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    raw = image.tobytes()
    for buffer in (raw, bytearray(raw), raw.decode("latin-1")):
        assert np.array_equal(image_to_bgr(8, 6, BGR, buffer), image)
    assert np.array_equal(image_to_bgr(8, 6, RGB_COLOR_SPACE, image[:, :, ::-1].tobytes()), image)


def test_yuv422_round_trip_keeps_colours():
    image = np.zeros((4, 8, 3), np.uint8)
    image[:, :4] = (30, 40, 200)  # red-ish, in pixel pairs so chroma subsampling is lossless
    image[:, 4:] = (200, 180, 20)
    back = image_to_bgr(8, 4, YUV422, cv2.cvtColor(image, cv2.COLOR_BGR2YUV_YUYV).tobytes())
    assert np.abs(back.astype(int) - image.astype(int)).max() <= 3


@pytest.mark.parametrize(
    "width, height, space, size, message",
    [(8, 6, BGR, 10, "expected 8x6x3"), (8, 6, 6, 144, "colour space 6"), (8, 6, YUV422, 144, "expected 8x6x2")],
)
def test_bad_image_buffers_are_named(width, height, space, size, message):
    with pytest.raises(ValueError, match=message):
        image_to_bgr(width, height, space, bytes(size))


def test_clock_offset_is_the_minimum_latency_estimate():
    true_offset = -1000.0  # the robot clock runs 1000 s ahead
    rng = np.random.default_rng(1)
    clock = ClockOffset(window=50)
    capture = 5000.0 + np.arange(200) / 15.0
    latency = 0.02 + rng.exponential(0.03, capture.size)
    stamps = [clock.update(c - true_offset, c + lat) for c, lat in zip(capture, latency)]
    errors = np.asarray(stamps) - capture  # late by the smallest latency seen in the window, never early
    assert np.all(errors >= 0.02 - 1e-9)
    assert np.all(errors[50:] <= latency.min() + 0.01)
    assert np.all(errors <= latency + 1e-9)


def test_clock_offset_forgets_a_clock_step_after_the_window():
    clock = ClockOffset(window=10)
    for k in range(20):
        clock.update(100.0 + k, 100.0 + k + 0.01)
    for k in range(20, 31):  # the robot clock steps 5 s back
        stamp = clock.update(95.0 + k, 100.0 + k + 0.01)
    assert stamp == pytest.approx(130.01)  # capture time 130 plus the 10 ms latency


def test_clock_probe_keeps_the_shortest_round_trip():
    probe = ClockProbe(window=3)
    assert probe.best() is None
    probe.add(10.0, 10.2, 4.0)  # offset 6.1 +- 0.1
    probe.add(11.0, 11.02, 5.005)  # offset 6.005 +- 0.01
    probe.add(12.0, 11.9, 0.0)  # answered before sent (a clock step): ignored
    assert probe.best() == pytest.approx((6.005, 0.01))
    for k in range(3):  # the window forgets the short round trip
        probe.add(20.0 + k, 20.05 + k, 14.0 + k)
    assert probe.best() == pytest.approx((6.025, 0.025))


def test_frames_take_the_probe_only_while_it_agrees_with_the_camera(standin):
    backend = backend_for(standin, camera_latency_max=0.3)
    assert backend._capture_stamp(100.0, 50.04) == pytest.approx(50.04)  # no probe yet: the camera bound
    backend._probe.add(49.0, 49.002, 99.0)  # offset -49.999: the camera's shortest latency 39 ms
    assert backend._capture_stamp(100.0, 50.04) == pytest.approx(50.001) and backend.clock_source == "probe"
    backend._probe.add(60.0, 60.0001, 99.0)  # offset -39 s: the frames' latency would be negative
    assert backend._capture_stamp(101.0, 51.05) == pytest.approx(51.04) and backend.clock_source == "camera"


def test_without_a_probe_synchronized_clocks_keep_the_robot_stamps():
    backend = NaoqiBackend("tcp://127.0.0.1:9", MODEL, dataclasses.replace(NAOQI_PARAMS, camera_latency_max=0.3), "qvga", FPS)
    assert backend._capture_stamp(100.0, 100.08) == 100.0 and backend.clock_source == "synchronized"  # 80 ms late: our clock
    assert backend._capture_stamp(100.1, 100.15) == 100.1  # the bound is now 50 ms: still ours
    other = NaoqiBackend("tcp://127.0.0.1:9", MODEL, NAOQI_PARAMS, "qvga", FPS)
    assert other._capture_stamp(100.0, 50.08) == pytest.approx(50.08) and other.clock_source == "camera"  # 50 s off


@pytest.mark.parametrize("clock_offset, source", [(0.0, "synchronized"), (2000.0, "camera")])
def test_a_naoqi_without_a_clock_probe_stamps_frames_by_its_clock_or_the_camera_bound(clock_offset, source):
    """A bare NAOqi (no getTimestamp), frames 0.2 s late: on a clock that is ours the frames keep the
    robot's stamps, exact; on another clock the camera bound stamps them, 0.2 s late."""
    world = SimWorld("can", MODEL, resolution="qvga", seed=8)
    with StandIn(world, clock_offset=clock_offset, latency=LATE, bare=True) as standin:
        backend = backend_for(standin)
        backend.start()
        errors = []
        for _ in range(6):
            frame = backend.grab_frame(2.0)
            errors.append(frame.stamp - standin.video.captures[-1][1])
        backend.close()
    assert backend.clock_source == source
    if source == "synchronized":
        assert np.abs(errors).max() <= STAMP_ERROR, errors
    else:  # never early; late by the shortest latency seen so far (longer while a loaded machine polls late)
        assert min(errors) >= LATE[0] - NAOQI_PARAMS.camera_latency_min - STAMP_ERROR and max(errors) < LATE[1] + 0.1, errors


def test_probe_stamps_frames_whose_shortest_latency_is_unknown():
    """0.2 s late frames, camera_latency_min 0: the camera bound alone is 0.2 s late, the probe is not."""
    world = SimWorld("can", MODEL, resolution="qvga", seed=8)
    with StandIn(world, clock_offset=3000.0, latency=LATE) as standin:
        backend = backend_for(standin)
        backend.start()
        for _ in range(6):
            frame = backend.grab_frame(2.0)
            assert frame is not None
            assert abs(frame.stamp - standin.video.captures[-1][1]) <= STAMP_ERROR
        backend.close()
    assert backend.clock_source == "probe"
    assert {c.args[0] for c in standin.calls_to("ALMemory.getTimestamp")} == {CLOCK_PROBE_KEY}


def test_clock_offset_subtracts_the_known_minimum_latency():
    clock = ClockOffset(window=10, latency_min=0.03)
    assert clock.update(100.0, 100.0 - 50.0 + 0.035) == pytest.approx(50.005)  # 35 ms latency, 30 of them known


# -- capture-time interpolation ------------------------------------------------------------------


def sample(stamp: float, yaw: float, T: np.ndarray, theta: float = 0.0) -> KinematicSample:
    return KinematicSample(stamp, (yaw, -yaw), T, (stamp, 2.0 * stamp, theta))


def test_transform_interpolation_is_the_rotation_geodesic_and_the_translation_lerp():
    T_a, T_b = rot_x(0.2) @ rot_z(0.1), rot_x(0.2) @ rot_z(0.9)
    T_a[:3, 3], T_b[:3, 3] = (0.0, 0.0, 0.5), (0.1, -0.2, 0.3)
    for alpha in (0.0, 0.25, 0.5, 1.0):
        expected = rot_x(0.2) @ rot_z(0.1 + 0.8 * alpha)  # both about the same axis: the angle is lerped
        T = interpolate_transform(T_a, T_b, alpha)
        np.testing.assert_allclose(T[:3, :3], expected[:3, :3], atol=1e-12)
        np.testing.assert_allclose(T[:3, 3], (1 - alpha) * T_a[:3, 3] + alpha * T_b[:3, 3], atol=1e-12)


def test_history_interpolates_between_samples_and_names_stamps_it_cannot_serve():
    history = KinematicsHistory(size=5, max_gap=0.05)
    for k in range(6):  # 0.00 .. 0.05, then a gap to 0.20: the 5 kept are 0.02 .. 0.05 and 0.20
        history.add(sample(0.01 * k, 0.1 * k, rot_z(0.1 * k), theta=math.pi - 0.01 + 0.01 * k))
    history.add(sample(0.20, 2.0, rot_z(2.0)))
    history.add(sample(0.19, 9.0, rot_z(9.0)))  # older than the newest: ignored
    kin = history.at(0.035)
    assert kin.head == pytest.approx((0.35, -0.35)) and kin.odom[:2] == pytest.approx((0.035, 0.07))
    assert kin.odom[2] == pytest.approx(math.remainder(math.pi - 0.01 + 0.035, 2 * math.pi))  # across +-pi
    assert rotation_angle(kin.T, rot_z(0.35)) < 1e-12
    assert history.at(0.02).head == pytest.approx((0.2, -0.2))  # exactly on a sample
    assert history.at(0.015) == BEFORE and history.at(0.21) == AFTER and history.at(0.1) == GAP
    assert history.wait_at(0.21, timeout=0.0) == AFTER
    late = threading.Timer(0.01, history.add, args=(sample(0.22, 2.2, rot_z(2.2)),))
    late.start()
    assert history.wait_at(0.21, timeout=30.0).head == pytest.approx((2.1, -2.1))  # woken by the new sample
    late.join()


# -- the backend against the stand-in --------------------------------------------------------------


@pytest.fixture
def standin():
    world = SimWorld("can", MODEL, resolution="qvga", seed=2)
    with StandIn(world, clock_offset=1000.0) as served:
        yield served


def backend_for(standin: StandIn, **changes) -> NaoqiBackend:
    return NaoqiBackend(standin.url, MODEL, dataclasses.replace(NAOQI_PARAMS, **changes), "qvga", FPS)


def test_start_prepares_the_robot_and_close_releases_it(standin):
    backend = backend_for(standin)
    backend.start()
    names = [c.name for c in standin.calls]
    assert standin.calls_to("ALAutonomousLife.setState")[0].args == ("disabled",)
    assert standin.calls_to("ALRobotPosture.goToPosture")[0].args == ("StandInit", 0.5)
    assert names.index("ALMotion.wakeUp") < names.index("ALRobotPosture.goToPosture")
    subscribed = standin.calls_to("ALVideoDevice.subscribeCamera")[0].args
    assert subscribed[1:] == (0, 1, YUV422, 15)  # top camera, QVGA, YUV422, 15 fps
    assert {c.args[0] for c in standin.calls_to("ALMemory.subscriber")} == {"robotHasFallen", "ALMotion/RobotIsFalling"}
    backend.close()
    backend.close()  # idempotent
    after = [c.name for c in standin.calls]
    assert after.count("ALVideoDevice.unsubscribe") == 1 and after.count("ALMotion.rest") == 1
    assert after.index("ALMotion.stopMove") < after.index("ALMotion.rest")


def test_options_turn_off_autonomous_life_posture_and_rest(standin):
    backend = backend_for(standin, disable_autonomous_life=False, stand_init_at_start=False, rest_on_exit=False,
                          color_space="bgr")
    backend.start()
    assert backend.grab_frame(1.0).image.shape == (240, 320, 3)
    backend.close()
    names = {c.name for c in standin.calls}
    assert not names & {"ALAutonomousLife.setState", "ALRobotPosture.goToPosture", "ALMotion.rest"}
    assert standin.calls_to("ALVideoDevice.subscribeCamera")[0].args[3] == BGR


def test_frames_are_new_images_with_the_camera_pose_and_stamp_of_their_capture(standin):
    world = standin.world
    world.teleport(world.true_pose(), head=(0.4, -0.2))
    backend = backend_for(standin, camera_latency_min=SIM.noise.latency[0])
    backend.start()
    renders = []
    render = world.render
    world.render = lambda at=None: renders.append(render(at)) or renders[-1]
    grabs = [(backend.grab_frame(1.0), standin.video.captures[-1][1]) for _ in range(8)]  # served: the last capture
    backend.close()
    assert backend.clock_source == "probe"
    assert len({f.stamp for f, _ in grabs}) == len(grabs)  # no duplicate handed out
    assert backend.duplicates > 0  # the backend polls faster than 15 fps and saw repeats
    for frame, stamp in grabs:
        capture = next(r for r in renders if r.stamp == stamp)
        assert abs(frame.stamp - capture.stamp) <= STAMP_ERROR  # robot clock 1000 s ahead, corrected by the probe
        assert np.abs(frame.image.astype(int) - capture.image.astype(int)).mean() < 3.0  # YUV422 round trip
        assert np.allclose(frame.T_BC, MODEL.camera_in_robot(0.4, -0.2))
        assert (frame.head_yaw, frame.head_pitch) == pytest.approx((0.4, -0.2))


def kinematic_errors(standin: StandIn, backend: NaoqiBackend, count: int, latency_min: float):
    """Grab ``count`` frames; per frame, the T_BC rotation, head yaw and odometry position errors against
    the simulator's reported truth at the capture, then the same errors of readings taken ``latency_min``
    after the capture (the earliest the old read-after-return bridge could read them)."""
    world, errors = standin.world, []
    for _ in range(count):
        frame = backend.grab_frame(2.0)
        assert frame is not None
        robot_stamp, capture = standin.video.captures[-1]  # the image just served is this frame's
        assert robot_stamp == pytest.approx(capture + standin.delivery.clock_offset, abs=2e-6)
        assert abs(frame.stamp - capture) <= STAMP_ERROR  # the clock probe: within half a loopback round trip
        truth, old = world.kinematics_at(capture), world.kinematics_at(capture + latency_min)
        T_true = nao_to_optical(truth.T_BC_nao)
        errors.append((
            rotation_angle(frame.T_BC, T_true), abs(frame.head_yaw - truth.head[0]),
            math.dist(frame.odom[:2], truth.odom[:2]),
            rotation_angle(nao_to_optical(old.T_BC_nao), T_true), abs(old.head[0] - truth.head[0]),
            math.dist(old.odom[:2], truth.odom[:2]),
        ))
    return np.array(errors)


def assert_only_sampler_stalls_dropped(backend: NaoqiBackend, frames: int) -> None:
    """Every frame kept its kinematics, except a few the sampler stalled across: on a loaded machine the
    sampler thread shares the GIL with the stand-in's renderer and can miss ``kinematics_max_gap``, and a
    frame in such a gap is rightly dropped. A frame outside the history (BEFORE, AFTER) is a stamping error."""
    dropped = backend.kinematics_dropped
    assert set(dropped) <= {GAP} and sum(dropped.values()) <= frames // 4, dropped


# Frames are served 0.20-0.24 s after their capture: the old bridge, reading the kinematics when the image
# arrived, was at least 0.20 s late; the capture stamp itself is off by at most half the clock probe's
# shortest round trip, so errors are compared with that 0.20 s.
LATE = (0.20, 0.24)


def test_frame_kinematics_are_those_of_the_capture_while_the_head_turns():
    latency = LATE
    world = SimWorld("can", MODEL, resolution="qvga", seed=4)
    world.teleport(world.true_pose(), head=(-1.5, 0.0))
    with StandIn(world, clock_offset=-250.0, latency=latency) as standin:
        backend = backend_for(standin)  # the camera's shortest latency unknown: the probe alone
        backend.start()
        world.set_head(1.5, 0.0, 0.1)  # 0.4 rad/s: 3 rad take 7.5 s, longer than the frames below
        errors = kinematic_errors(standin, backend, 12, latency[0])
        backend.close()
    rate = 0.1 * MODEL.head.max_speed
    # a reading latency_min after the capture is rate * latency_min = 80 mrad off (less the world's 5 ms steps)
    step = SIM.dynamics.timestep
    assert (errors[:, 4] >= rate * (latency[0] - 2 * step)).all()  # the old bridge fails both bounds below
    assert np.median(errors[:, 1]) < 0.5 * rate * latency[0]
    assert errors[:, 1].max() < 0.75 * rate * latency[0]
    assert errors[:, 0].max() < 0.75 * rate * latency[0]  # T_BC turns with the head
    assert_only_sampler_stalls_dropped(backend, len(errors))


def test_frame_kinematics_follow_the_torso_roll_while_walking():
    latency = LATE
    world = SimWorld("can", MODEL, resolution="qvga", seed=5)
    with StandIn(world, latency=latency) as standin:
        world.walk(MODEL.walk.v_max, 0.0, 0.0)  # full speed: full sway
        backend = backend_for(standin)
        backend.start()
        # 1.5 s of frames after the walk's lag: the sway's 1 Hz roll and 2 Hz pitch through all phases
        errors = kinematic_errors(standin, backend, int(1.5 * FPS) + 8, latency[0])[8:]
        backend.stop_walking()
        backend.close()
    sway = SIM.dynamics.sway
    # a reading 0.2 s late is off by 2 rho sin(pi f 0.2) = 1.2 rho at the roll's fastest phase
    assert errors[:, 3].max() > sway.reported_fraction * sway.roll
    assert np.median(errors[:, 0]) < 0.5 * np.median(errors[:, 3])  # the old read-after-return bridge fails these
    assert errors[:, 0].max() < 0.75 * errors[:, 3].max()
    assert np.median(errors[:, 2]) < 0.5 * np.median(errors[:, 5])  # odometry: 2 cm walked in 0.2 s
    assert_only_sampler_stalls_dropped(backend, len(errors) + 8)


def test_frames_outside_the_kinematics_history_are_dropped_and_counted():
    world = SimWorld("can", MODEL, resolution="qvga", seed=6)
    with StandIn(world, latency=(0.5, 0.5)) as standin:  # frames older than the history kept below
        backend = backend_for(standin, kinematics_history=0.2, camera_latency_min=0.5)
        backend.start()
        assert backend.grab_frame(1.5) is None
        backend.close()
    assert backend.kinematics_dropped["before_history"] >= 1 and set(backend.kinematics_dropped) == {"before_history"}


def test_standin_serves_late_dropped_frames_on_a_seeded_schedule():
    delivery = CameraDelivery(latency=(0.03, 0.12), drop_rate=0.3, clock_offset=5.0, seed=11)
    draws = [delivery.frame(k) for k in range(400)]
    assert draws == [CameraDelivery((0.03, 0.12), 0.3, 5.0, 11).frame(k) for k in range(400)]  # seeded
    assert draws != [CameraDelivery((0.03, 0.12), 0.3, 5.0, 12).frame(k) for k in range(400)]
    latencies = np.array([d[0] for d in draws])
    dropped = np.mean([d[1] for d in draws])
    assert latencies.min() >= 0.03 and latencies.max() <= 0.12
    assert abs(dropped - 0.3) < 4 * math.sqrt(0.3 * 0.7 / 400)  # binomial: 4 sigma
    world = SimWorld("can", MODEL, resolution="qvga", seed=7)
    with StandIn(world, clock_offset=5.0, latency=(0.03, 0.12), drop_rate=0.3) as standin:
        backend = backend_for(standin)
        backend.start()
        frames = [backend.grab_frame(2.0) for _ in range(10)]
        backend.close()
        served = standin.video.captures
        calls = standin.calls_to("ALVideoDevice.getImageRemote")
    start = standin.calls_to("ALVideoDevice.subscribeCamera")[0].time
    slots = [(capture - start) * FPS for _, capture in served]  # capture instants on the 1/fps grid
    assert all(f is not None for f in frames)
    assert np.all(np.diff([c for _, c in served]) > 0)
    for (robot_stamp, capture), slot in zip(served, slots):
        k = round(slot)  # the world stamps a capture on its 5 ms step grid, a fraction of a slot early
        latency, dropped = standin.delivery.frame(k)  # the stand-in's draws: seeded by the world's seed
        assert not dropped
        served_at = next(c.time for c in calls if c.time >= start + k / FPS + latency)
        assert served_at >= capture + latency  # served no sooner than its latency after the capture
        assert robot_stamp == pytest.approx(capture + 5.0, abs=2e-6)


def test_standin_refuses_a_latency_beyond_the_worlds_history():
    world = SimWorld("can", MODEL, resolution="qvga", seed=7)
    with pytest.raises(ValueError, match="dynamics.history"):
        StandIn(world, latency=(0.1, SIM.dynamics.history + 1.0))


def test_grab_frame_returns_none_within_its_timeout_when_no_new_image(standin):
    backend = backend_for(standin)
    backend.start()
    backend.grab_frame(1.0)
    started = time.monotonic()
    assert backend.grab_frame(0.0) is None  # the next image is not due for 1/15 s
    assert time.monotonic() - started < 0.5
    backend.close()


def test_walk_head_state_and_fall_signal(standin):
    backend = backend_for(standin)
    backend.start()
    backend.walk(0.05, 0.0, 0.1)
    backend.set_head(0.3, 0.1, 0.5)
    assert standin.calls_to("ALMotion.move")[-1].args == pytest.approx((0.05, 0.0, 0.1))
    assert standin.calls_to("ALMotion.setAngles")[-1].args[1:] == ([pytest.approx(0.3), pytest.approx(0.1)], 0.5)
    time.sleep(0.3)
    state = backend.read_state()
    assert state.walking and not state.fallen and state.odom[0] > 0.0
    assert state.battery == pytest.approx(standin.world.battery(), abs=1e-3)
    standin.fall()
    deadline = time.monotonic() + 2.0
    while not backend.read_state().fallen and time.monotonic() < deadline:
        time.sleep(0.01)
    assert backend.read_state().fallen  # from the ALMemory signal
    backend.stop_walking()
    assert standin.calls_to("ALMotion.stopMove")
    backend.close()


def test_a_bare_naoqi_runs_the_backend_and_each_thing_it_lacks_is_named(caplog):
    """Only ALMotion, ALVideoDevice and an ALMemory of getData/insertData, images in RGB (StandIn bare):
    the backend starts, decodes the images, reads the fall keys by polling, reports the battery as
    unknown, and warns once for each missing part, naming it."""
    world = SimWorld("can", MODEL, resolution="qvga", seed=4)
    renders = []
    render = world.render
    world.render = lambda at=None: renders.append(render(at)) or renders[-1]
    with StandIn(world, bare=True) as standin, caplog.at_level("WARNING", logger="nao_bridge.naoqi_backend"):
        backend = backend_for(standin)
        backend.start()
        grabs = [(backend.grab_frame(2.0), standin.video.captures[-1][1]) for _ in range(3)]  # served: the last capture
        standing = backend.read_state()
        standin.fall()
        fallen = backend.read_state()
        backend.close()
    warnings = [r.getMessage() for r in caplog.records]
    for lost in ("ALAutonomousLife", "ALRobotPosture", "subscriber('robotHasFallen')",
                 "subscriber('ALMotion/RobotIsFalling')", "Device/SubDeviceList/Battery", "clock probe unavailable"):
        assert sum(lost in w for w in warnings) == 1, lost  # once each, not at every state read
    assert standin.calls_to("ALMotion.wakeUp") and standin.calls_to("ALVideoDevice.unsubscribe")
    for frame, stamp in grabs:
        truth = next(r for r in renders if r.stamp == stamp).image
        assert np.array_equal(frame.image, truth)  # RGB decoded to BGR, losslessly
    assert standing.battery is None and not standing.fallen
    assert fallen.fallen  # robotHasFallen polled with getData once the event was raised


class MotionWithoutMoveState(ALMotion):
    """An ALMotion as another stand-in may serve it: no ``moveIsActive``, ``killMove`` or ``wakeUp``."""

    moveIsActive = None  # not callable: not served
    killMove = None
    wakeUp = None


class VideoOfAnotherSize(ALVideoDevice):
    """Serves the world's resolution whatever was subscribed, in ``served`` (kYUV 10 or luma-only 0),
    through NAOqi 1.x's ``subscribe`` only."""

    subscribeCamera = None  # not callable: not served

    def __init__(self, standin: StandIn, served: int):
        super().__init__(standin.world, standin._record, standin.delivery)
        self.served = served

    def subscribe(self, name: str, resolution: int, color_space: int, fps: int) -> str:
        return ALVideoDevice.subscribeCamera(self, name, TOP_CAMERA, RESOLUTION_IDS[self._world.resolution], BGR, fps)

    def _image(self, capture: float, color_space: int):
        image, stamps = super()._image(capture, BGR)
        bgr = np.frombuffer(image[6].encode("latin-1"), np.uint8).reshape(image[1], image[0], 3)
        pixels = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV if self.served == YUV_COLOR_SPACE else cv2.COLOR_BGR2GRAY)
        image[2], image[3], image[6] = 1 if pixels.ndim == 2 else 3, self.served, pixels.tobytes().decode("latin-1")
        return image, stamps


@pytest.mark.parametrize("served", [YUV_COLOR_SPACE, Y_COLOR_SPACE])
def test_a_naoqi_written_by_others_serving_another_size_and_colour_space_without_move_state(served, caplog):
    """VGA images for a QVGA subscription, in kYUV or luma only, through ``subscribe`` alone, and an
    ALMotion without moveIsActive, killMove or wakeUp: the frames arrive at the subscribed size, as
    the rendered image resized; walking is what was commanded; killMove falls back to stopMove;
    each loss is named once."""
    world = SimWorld("can", MODEL, resolution="vga", seed=5)
    renders = []
    render = world.render
    world.render = lambda at=None: renders.append(render(at)) or renders[-1]
    with caplog.at_level("WARNING", logger="nao_bridge.naoqi_backend"):
        standin = StandIn(world, latency=(0.03, 0.05), drop_rate=0.0)
        standin.video = VideoOfAnotherSize(standin, served)
        standin.services.update(ALMotion=MotionWithoutMoveState(world, standin._record), ALVideoDevice=standin.video)
        with standin:
            backend = backend_for(standin)  # asks for QVGA
            backend.start()
            grabs = [(backend.grab_frame(2.0), standin.video.captures[-1][1]) for _ in range(3)]
            backend.walk(0.05, 0.0, 0.0)
            walking = backend.read_state().walking
            backend.stop_walking()
            stopped = backend.read_state().walking
            backend.walk(0.05, 0.0, 0.0)
            backend.kill_move()
            killed = (backend.move_is_active(), [c.name for c in standin.calls if c.name in ("ALMotion.move", "ALMotion.stopMove")][-1])
            backend.close()
    warnings = [r.getMessage() for r in caplog.records]
    for lost in ("ALMotion.moveIsActive unavailable", "ALMotion.killMove unavailable", "ALMotion.wakeUp unavailable",
                 "subscribeCamera unavailable", "640x480 images for the 320x240"):
        assert sum(lost in w for w in warnings) == 1, lost
    for frame, stamp in grabs:
        truth = cv2.resize(next(r for r in renders if r.stamp == stamp).image, (320, 240), interpolation=cv2.INTER_AREA)
        if served == Y_COLOR_SPACE:
            truth = cv2.cvtColor(cv2.cvtColor(truth, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
        assert frame.image.shape == (240, 320, 3)
        assert np.abs(frame.image.astype(int) - truth.astype(int)).mean() < 1.5  # the YUV or grey round trip's rounding
    assert walking and not stopped and killed == (False, "ALMotion.stopMove")


def test_an_image_of_another_aspect_is_refused_naming_both_sizes():
    backend = NaoqiBackend("tcp://127.0.0.1:9", MODEL, NAOQI_PARAMS, "qvga", 15.0)
    with pytest.raises(ValueError, match="320x180.*320x240"):
        backend._to_subscribed_size(np.zeros((180, 320, 3), np.uint8))


def test_unreachable_robot_is_a_connection_error_naming_the_url():
    backend = NaoqiBackend("tcp://127.0.0.1:9", MODEL, NAOQI_PARAMS, "qvga", 15.0)
    with pytest.raises(ConnectionError, match="tcp://127.0.0.1:9"):
        backend.start()
    backend.close()


def own_address() -> str:
    """This machine's address on its default route (a UDP connect sends nothing)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect(("203.0.113.1", 9))
        return probe.getsockname()[0]


@pytest.mark.parametrize("url, remote", [
    ("tcp://127.0.0.1:9559", False), ("tcp://127.0.0.2:9559", False), ("tcp://localhost:9559", False),
    ("tcp://[::1]:9559", False), ("tcp://0.0.0.0:9559", False), ("tcp://OWN:9559", False),
    ("tcp://203.0.113.7:9559", True), ("tcp://nao.invalid:9559", True),
])
def test_a_naoqi_is_remote_unless_its_host_is_this_machine(url, remote):
    """The robot-side watchdog is required for a NAOqi on another machine: a loopback address other than
    127.0.0.1, or this machine's own address, is not another machine; an address of no interface here,
    or a name that does not resolve, is."""
    backend = NaoqiBackend(url.replace("OWN", own_address()), MODEL, NAOQI_PARAMS, "qvga", 15.0)
    assert backend.remote is remote
    assert on_this_machine(own_address()) and not on_this_machine("")


def test_unknown_resolution_is_refused():
    with pytest.raises(KeyError, match="hd"):
        NaoqiBackend("tcp://127.0.0.1:9", MODEL, NAOQI_PARAMS, "hd", 15.0)


def test_a_failing_sampler_read_drops_frames_until_it_recovers():
    world = SimWorld("can", MODEL, resolution="qvga", seed=8)
    with StandIn(world, latency=(0.03, 0.05)) as standin:
        backend = backend_for(standin)
        backend.start()
        assert backend.grab_frame(2.0) is not None
        transform = world.camera_in_robot_nao
        world.camera_in_robot_nao = lambda: (_ for _ in ()).throw(RuntimeError("joint sensors lost"))
        injected = time.time()
        outage = [backend.grab_frame(0.5) for _ in range(4)]  # the history stops at the outage
        last_sample = backend.kinematics.samples()[-1].stamp
        world.camera_in_robot_nao = transform
        recovered = backend.grab_frame(2.0)
        backend.close()
    # a frame captured before the failure (in flight when it was injected) still has its kinematics
    assert last_sample < injected + 0.1
    assert all(frame.stamp <= last_sample for frame in outage if frame is not None)
    assert outage[-3:] == [None, None, None] and recovered is not None
    assert set(backend.kinematics_dropped) <= {"after_history", "history_gap"} and backend.kinematics_dropped
