"""The NAOqi backend against the libqi stand-in (real qi sessions on loopback) and its pure helpers."""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np
import pytest

from nao_bridge.naoqi_backend import (
    COLOR_SPACE_IDS,
    ClockOffset,
    NaoqiBackend,
    NaoqiParams,
    image_to_bgr,
)
from nao_core.robot_model import load_robot_model, nao_to_optical
from nao_sim.standin import StandIn
from nao_sim.world import SimWorld

MODEL = load_robot_model()
BGR, YUV422 = COLOR_SPACE_IDS["bgr"], COLOR_SPACE_IDS["yuv422"]


def test_image_buffer_as_bytes_bytearray_or_latin1_text():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    raw = image.tobytes()
    for buffer in (raw, bytearray(raw), raw.decode("latin-1")):
        assert np.array_equal(image_to_bgr(8, 6, BGR, buffer), image)


def test_yuv422_round_trip_keeps_colours():
    image = np.zeros((4, 8, 3), np.uint8)
    image[:, :4] = (30, 40, 200)  # red-ish, in pixel pairs so chroma subsampling is lossless
    image[:, 4:] = (200, 180, 20)
    back = image_to_bgr(8, 4, YUV422, cv2.cvtColor(image, cv2.COLOR_BGR2YUV_YUYV).tobytes())
    assert np.abs(back.astype(int) - image.astype(int)).max() <= 3


@pytest.mark.parametrize(
    "width, height, space, size, message",
    [(8, 6, BGR, 10, "expected 8x6x3"), (8, 6, 11, 144, "colour space 11"), (8, 6, YUV422, 144, "expected 8x6x2")],
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


@pytest.fixture
def standin():
    world = SimWorld("can", MODEL, resolution="qvga", seed=2)
    with StandIn(world, clock_offset=1000.0) as served:
        yield served


def backend_for(standin: StandIn, **changes) -> NaoqiBackend:
    return NaoqiBackend(standin.url, MODEL, dataclasses.replace(NaoqiParams(), **changes), "qvga", 15.0)


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
    world.set_head(0.4, -0.2, 1.0)
    time.sleep(0.3)
    backend = backend_for(standin)
    backend.start()
    renders = []
    render = world.render
    world.render = lambda: renders.append(render()) or renders[-1]
    frames = [backend.grab_frame(1.0) for _ in range(8)]
    backend.close()
    assert len({f.stamp for f in frames}) == len(frames)  # no duplicate handed out
    assert backend.duplicates > 0  # the backend polls faster than 15 fps and saw repeats
    for frame in frames:
        capture = max((r for r in renders if r.stamp <= frame.stamp), key=lambda r: r.stamp)
        assert 0.0 <= frame.stamp - capture.stamp < 1.0 / 15.0  # robot clock 1000 s ahead, corrected
        assert np.abs(frame.image.astype(int) - capture.image.astype(int)).mean() < 3.0  # YUV422 round trip
        assert np.allclose(frame.T_BC, nao_to_optical(world.camera_in_robot_nao()))
        assert np.allclose(frame.T_BC, MODEL.camera_in_robot(0.4, -0.2))
        assert (frame.head_yaw, frame.head_pitch) == pytest.approx((0.4, -0.2))


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


def test_unreachable_robot_is_a_connection_error_naming_the_url():
    backend = NaoqiBackend("tcp://127.0.0.1:9", MODEL, NaoqiParams(), "qvga", 15.0)
    with pytest.raises(ConnectionError, match="tcp://127.0.0.1:9"):
        backend.start()
    backend.close()


def test_unknown_resolution_is_refused():
    with pytest.raises(KeyError, match="hd"):
        NaoqiBackend("tcp://127.0.0.1:9", MODEL, NaoqiParams(), "hd", 15.0)
