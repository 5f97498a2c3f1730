"""A NAOqi stand-in: the NAOqi services the bridge uses, served over libqi, driven by a SimWorld.

``StandIn(world).start()`` listens on ``tcp://127.0.0.1:<free port>`` with
``qi.Session().listenStandalone`` and registers ALMotion, ALVideoDevice, ALMemory, ALRobotPosture
and ALAutonomousLife with the real NAOqi signatures, so :class:`NaoqiBackend` runs unchanged
against it (``url``). Every call is recorded as ``Call(time.time(), "Service.method", args)`` in
``calls``; tests assert on that record (e.g. the time of the ``ALMotion.stopMove`` after the
station went silent). ``fall()`` makes the world fall and fires the ALMemory fall signals;
``freeze_camera()`` stops the camera (every later reply is its last image, a duplicate).

The camera behaves like NAOqi's. Image k is captured at t_k = t_0 + k / fps (t_0 the
subscription) and can be served only from t_k + L_k on, with a latency L_k ~ U(latency) drawn from
``(seed, k)``; with probability ``drop_rate`` (same draw) it is never served. ``getImageRemote``
returns the newest image that is due, rendered with the world as it was at t_k
(``SimWorld.render(at=t_k)``), so the head angles and camera transform read after it has arrived
are those of a later instant, as on a real NAO. Asking again before a newer image is due returns
the same image with the same stamp (a duplicate). The stamp is t_k on the robot's clock, which
runs ``clock_offset`` seconds ahead of the bridge's; the buffer is latin-1 text in BGR or packed
YUYV (kYUV422 = 9, 2 bytes a pixel), as requested. Latency, drop rate and clock offset default to
``noise`` in config/sim.yaml; all draws depend on the seed and the frame index only. ALMemory
stamps every ``insertData`` on the same robot clock and returns it with ``getTimestamp`` (the
bridge's clock probe, docs/frames.md).

``StandIn(world, bare=True)`` is a NAOqi with the least a robot API may have, to hold the bridge to
what it requires (docs/bridge.md): ALMotion, ALVideoDevice and an ALMemory of ``insertData`` and
``getData`` alone, which knows no key before it is written (the fall events before a fall, the
battery); no ALRobotPosture, no ALAutonomousLife, no ``subscriber``, no ``getTimestamp``, and the
camera answers in RGB (kRGBColorSpace, 11) whatever colour space was asked.

    python -m nao_sim.standin --scenario can      # serve until Ctrl-C, print the URL
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple, Union

import cv2
import numpy as np
import qi

from nao_core.naoqi_api import (
    BATTERY_KEY,
    COLOR_SPACE_IDS,
    FALL_KEYS,
    HEAD_JOINTS,
    RESOLUTION_IDS,
    RGB_COLOR_SPACE,
    TOP_CAMERA,
)
from nao_core.robot_model import load_robot_model
from nao_sim.world import SimWorld

log = logging.getLogger(__name__)


class Call(NamedTuple):
    time: float  # time.time() when the call arrived
    name: str  # "Service.method"
    args: tuple


class _Recorder:
    def __init__(self) -> None:
        self.calls: List[Call] = []
        self._lock = threading.Lock()

    def __call__(self, name: str, *args: Any) -> None:
        with self._lock:
            self.calls.append(Call(time.time(), name, args))

    def snapshot(self) -> List[Call]:
        with self._lock:
            return list(self.calls)


def _joint_names(names: Union[str, Sequence[str]]) -> List[str]:
    names = [names] if isinstance(names, str) else list(names)
    if names in (["Head"], []):
        return list(HEAD_JOINTS)
    unknown = [n for n in names if n not in HEAD_JOINTS]
    if unknown:
        raise RuntimeError(f"ALMotion stand-in: only the head joints are simulated, got {unknown}")
    return names


class ALMotion:
    def __init__(self, world: SimWorld, record: _Recorder):
        self._world = world
        self._record = record

    def move(self, x: float, y: float, theta: float) -> None:
        self._record("ALMotion.move", x, y, theta)
        self._world.walk(x, y, theta)

    def moveToward(self, x: float, y: float, theta: float) -> None:
        self._record("ALMotion.moveToward", x, y, theta)
        limits = self._world.robot.walk
        self._world.walk(x * (limits.v_max if x >= 0 else -limits.v_min), y * limits.vy_max, theta * limits.omega_max)

    def stopMove(self) -> None:
        self._record("ALMotion.stopMove")
        self._world.stop_walking()

    def moveIsActive(self) -> bool:
        self._record("ALMotion.moveIsActive")
        return bool(self._world.is_walking())

    def killMove(self) -> None:
        self._record("ALMotion.killMove")
        self._world.stop_walking()

    def setAngles(self, names: Any, angles: Any, fraction: float) -> None:
        self._record("ALMotion.setAngles", names, angles, fraction)
        joints = _joint_names(names)
        values = [angles] if isinstance(angles, (int, float)) else list(angles)
        if len(values) != len(joints):
            raise RuntimeError(f"ALMotion.setAngles: {len(joints)} names but {len(values)} angles")
        target = dict(zip(HEAD_JOINTS, self._world.head_angles()))
        target.update(zip(joints, values))
        self._world.set_head(target["HeadYaw"], target["HeadPitch"], fraction)

    def getAngles(self, names: Any, use_sensors: bool) -> List[float]:
        self._record("ALMotion.getAngles", names, use_sensors)
        current = dict(zip(HEAD_JOINTS, self._world.head_angles()))
        return [current[n] for n in _joint_names(names)]

    def getRobotPosition(self, use_sensors: bool) -> List[float]:
        self._record("ALMotion.getRobotPosition", use_sensors)
        return list(self._world.odometry())

    def getTransform(self, name: str, space: int, use_sensors: bool) -> List[float]:
        self._record("ALMotion.getTransform", name, space, use_sensors)
        if name != "CameraTop" or space != 2:
            raise RuntimeError(f"ALMotion stand-in: only getTransform('CameraTop', 2 = FRAME_ROBOT), got {name!r}, {space}")
        return [float(x) for x in self._world.camera_in_robot_nao().ravel()]

    def wakeUp(self) -> None:
        self._record("ALMotion.wakeUp")

    def rest(self) -> None:
        self._record("ALMotion.rest")
        self._world.stop_walking()


class CameraDelivery(NamedTuple):
    """When the stand-in's camera serves its frames: latency range (s), drop rate, robot clock offset (s), seed."""

    latency: Tuple[float, float]
    drop_rate: float
    clock_offset: float
    seed: int

    def frame(self, k: int) -> Tuple[float, bool]:
        """(latency of frame k, whether it is dropped): a function of (seed, k) only."""
        rng = np.random.default_rng([self.seed, k])
        return float(rng.uniform(*self.latency)), bool(rng.random() < self.drop_rate)


class ALVideoDevice:
    def __init__(self, world: SimWorld, record: _Recorder, delivery: CameraDelivery, answer_color_space: Optional[int] = None):
        """``answer_color_space``: serve every image in it, whatever the subscription asked (None: as asked)."""
        self._world = world
        self._record = record
        self._delivery = delivery
        self._answer_color_space = answer_color_space
        self._subscribers: Dict[str, Dict[str, Any]] = {}
        self._lock = threading.Lock()
        self.frozen = False  # the camera stopped: every reply is the last image again (``StandIn.freeze_camera``)
        self.captures: List[Tuple[float, float]] = []  # (robot stamp, world capture time) of every image served

    def subscribeCamera(self, name: str, camera: int, resolution: int, color_space: int, fps: int) -> str:
        self._record("ALVideoDevice.subscribeCamera", name, camera, resolution, color_space, fps)
        wanted = RESOLUTION_IDS.get(self._world.resolution)
        if camera != TOP_CAMERA or resolution != wanted or color_space not in COLOR_SPACE_IDS.values() or fps <= 0:
            raise RuntimeError(
                f"ALVideoDevice stand-in: serves the top camera ({TOP_CAMERA}) at {self._world.resolution} "
                f"(id {wanted}) in colour spaces {sorted(COLOR_SPACE_IDS.values())}; asked camera {camera}, "
                f"resolution {resolution}, colour space {color_space}, fps {fps}"
            )
        with self._lock:
            handle = f"{name}_{len(self._subscribers)}"
            answered = color_space if self._answer_color_space is None else self._answer_color_space
            self._subscribers[handle] = {
                "color_space": answered, "period": 1.0 / fps, "start": time.time(), "index": -1, "image": None,
                "pending": {},  # frame index -> (image, (robot stamp, capture)) captured (rendered), not yet due
            }
        return handle

    def getImageRemote(self, handle: str) -> Optional[list]:
        self._record("ALVideoDevice.getImageRemote", handle)
        with self._lock:
            sub = self._subscribers.get(handle)
            if sub is None:
                raise RuntimeError(f"ALVideoDevice.getImageRemote: unknown handle {handle!r}")
            if self.frozen:
                return sub["image"]
            now = time.time()
            captured = math.floor((now - sub["start"]) / sub["period"])
            if captured > sub["index"] and captured not in sub["pending"] and not self._delivery.frame(captured)[1]:
                # the camera captures it now: render it before it is due, so the reply is not slowed by the render
                sub["pending"][captured] = self._image(sub["start"] + captured * sub["period"], sub["color_space"])
            k = self._newest_due(sub, now)
            if k is not None and k > sub["index"]:
                image, capture = sub["pending"].get(k) or self._image(sub["start"] + k * sub["period"], sub["color_space"])
                sub["index"], sub["image"] = k, image
                sub["pending"] = {i: p for i, p in sub["pending"].items() if i > k}
                self.captures.append(capture)
            return sub["image"]  # None until the first image is due, as NAOqi before its first capture

    def _newest_due(self, sub: Dict[str, Any], now: float) -> Optional[int]:
        """The newest frame index captured since the subscription, not dropped, whose latency has passed."""
        newest = math.floor((now - sub["start"]) / sub["period"])
        oldest = max(newest - math.ceil(self._delivery.latency[1] / sub["period"]) - 1, 0)
        for k in range(newest, oldest - 1, -1):
            latency, dropped = self._delivery.frame(k)
            if not dropped and sub["start"] + k * sub["period"] + latency <= now:
                return k
        return None

    def _image(self, capture: float, color_space: int) -> Tuple[list, Tuple[float, float]]:
        """The NAOqi image of a capture at world time ``capture``, and its (robot stamp, capture stamp)."""
        frame = self._world.render(at=capture)
        conversion = {COLOR_SPACE_IDS["yuv422"]: cv2.COLOR_BGR2YUV_YUYV, RGB_COLOR_SPACE: cv2.COLOR_BGR2RGB}.get(color_space)
        pixels = frame.image if conversion is None else cv2.cvtColor(frame.image, conversion)
        height, width, layers = pixels.shape
        robot_stamp = frame.stamp + self._delivery.clock_offset
        seconds = math.floor(robot_stamp)
        micros = int(round((robot_stamp - seconds) * 1e6))
        if micros == 1_000_000:
            seconds, micros = seconds + 1, 0
        buffer = pixels.tobytes().decode("latin-1")
        image = [width, height, layers, color_space, seconds, micros, buffer, TOP_CAMERA, 0.5, 0.4, -0.5, -0.4]
        return image, (seconds + 1e-6 * micros, frame.stamp)

    def releaseImage(self, handle: str) -> bool:
        self._record("ALVideoDevice.releaseImage", handle)
        return True

    def unsubscribe(self, handle: str) -> bool:
        self._record("ALVideoDevice.unsubscribe", handle)
        with self._lock:
            return self._subscribers.pop(handle, None) is not None


class _MemorySubscriber:
    def __init__(self) -> None:
        self.signal = qi.Signal("(m)")


class BareALMemory:
    """ALMemory's ``insertData`` and ``getData``: a key is known once written (an event once raised)."""

    def __init__(self, record: _Recorder, clock_offset: float):
        self._record = record
        self._clock_offset = clock_offset
        self._data: Dict[str, Any] = {}  # written by insertData or a raised event
        self._stamps: Dict[str, float] = {}  # robot clock time of each write
        self._lock = threading.Lock()

    def insertData(self, key: str, value: Any) -> None:
        self._record("ALMemory.insertData", key, value)
        self._write(key, value)

    def getData(self, key: str) -> Any:
        self._record("ALMemory.getData", key)
        return self._lookup(key)

    def _lookup(self, key: str) -> Any:
        with self._lock:
            if key in self._data:
                return self._data[key]
        raise RuntimeError(f"ALMemory::getData: key {key!r} not found")

    def _write(self, key: str, value: Any) -> None:
        with self._lock:
            self._data[key] = value
            self._stamps[key] = time.time() + self._clock_offset

    def _raise_event(self, key: str, value: Any) -> None:
        self._write(key, value)  # NAOqi's raiseEvent stores the value as well


class ALMemory(BareALMemory):
    """ALMemory with event subscribers, write timestamps and the robot's fall and battery keys."""

    def __init__(self, world: SimWorld, record: _Recorder, clock_offset: float):
        super().__init__(record, clock_offset)
        self._world = world
        self._subscribers: Dict[str, _MemorySubscriber] = {}

    def getTimestamp(self, key: str) -> list:
        """[value, seconds, microseconds] of the last write, on the robot's clock (as the images)."""
        self._record("ALMemory.getTimestamp", key)
        with self._lock:
            if key not in self._data:
                raise RuntimeError(f"ALMemory::getTimestamp: key {key!r} not found")
            seconds, fraction = divmod(self._stamps[key], 1.0)
            return [self._data[key], int(seconds), int(fraction * 1e6)]

    def _lookup(self, key: str) -> Any:
        if key in FALL_KEYS:
            return bool(self._world.is_fallen())
        if key == BATTERY_KEY:
            return float(self._world.battery())
        return super()._lookup(key)

    def subscriber(self, key: str) -> _MemorySubscriber:
        self._record("ALMemory.subscriber", key)
        with self._lock:
            return self._subscribers.setdefault(key, _MemorySubscriber())

    def _raise_event(self, key: str, value: Any) -> None:
        super()._raise_event(key, value)
        with self._lock:
            subscriber = self._subscribers.get(key)
        if subscriber is not None:
            subscriber.signal(value)


class ALRobotPosture:
    def __init__(self, record: _Recorder):
        self._record = record

    def goToPosture(self, name: str, speed: float) -> bool:
        self._record("ALRobotPosture.goToPosture", name, speed)
        return True


class ALAutonomousLife:
    def __init__(self, record: _Recorder):
        self._record = record

    def setState(self, state: str) -> None:
        self._record("ALAutonomousLife.setState", state)


class StandIn:
    """NAOqi services for ``world`` on a loopback libqi session."""

    def __init__(
        self,
        world: SimWorld,
        clock_offset: Optional[float] = None,
        listen: str = "tcp://127.0.0.1:0",
        latency: Optional[Tuple[float, float]] = None,
        drop_rate: Optional[float] = None,
        bare: bool = False,
    ):
        """Camera delivery defaults to ``world.config.noise``; the seed is the world's. ``bare``: the least
        NAOqi (module docstring)."""
        noise = world.config.noise
        latency = noise.latency if latency is None else (float(latency[0]), float(latency[1]))
        drop_rate = noise.drop_rate if drop_rate is None else float(drop_rate)
        if not 0.0 <= latency[0] <= latency[1] < world.config.dynamics.history:
            raise ValueError(f"stand-in latency {latency}: expected 0 <= low <= high < dynamics.history "
                             f"({world.config.dynamics.history} s, how far back the world can render)")
        if not 0.0 <= drop_rate < 1.0:
            raise ValueError(f"stand-in drop_rate {drop_rate}: expected in [0, 1)")
        self.delivery = CameraDelivery(latency, drop_rate, noise.clock_offset if clock_offset is None else clock_offset,
                                       world.seed)
        self.world = world
        self.listen = listen
        self._record = _Recorder()
        self.memory = (BareALMemory(self._record, self.delivery.clock_offset) if bare
                       else ALMemory(world, self._record, self.delivery.clock_offset))
        self.video = ALVideoDevice(world, self._record, self.delivery, RGB_COLOR_SPACE if bare else None)
        self.services = {"ALMotion": ALMotion(world, self._record), "ALVideoDevice": self.video, "ALMemory": self.memory}
        if not bare:
            self.services.update(ALRobotPosture=ALRobotPosture(self._record), ALAutonomousLife=ALAutonomousLife(self._record))
        self._session: Optional[Any] = None

    @property
    def url(self) -> str:
        if self._session is None:
            raise RuntimeError("the stand-in is not started")
        return self._session.endpoints()[0]

    @property
    def calls(self) -> List[Call]:
        return self._record.snapshot()

    def calls_to(self, name: str) -> List[Call]:
        return [c for c in self.calls if c.name == name]

    def start(self) -> "StandIn":
        session = qi.Session()
        session.listenStandalone(self.listen)
        for name, service in self.services.items():
            session.registerService(name, service)
        self._session = session
        return self

    def freeze_camera(self) -> None:
        """The camera stops capturing: ``getImageRemote`` answers its last image again, as a stalled camera does."""
        self.video.frozen = True

    def fall(self) -> None:
        """The robot falls: the world falls and ALMemory raises both fall events."""
        self.world.inject_fall()
        self.memory._raise_event("ALMotion/RobotIsFalling", True)
        self.memory._raise_event("robotHasFallen", 1)

    def close(self) -> None:
        if self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> "StandIn":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description="Serve a simulated NAO through NAOqi's API on libqi.")
    parser.add_argument("--scenario", default="can")
    parser.add_argument("--resolution", default="vga")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--listen", default="tcp://127.0.0.1:9559")
    parser.add_argument("--latency", type=float, nargs=2, metavar=("LOW", "HIGH"), help="s, capture to delivery")
    parser.add_argument("--drop-rate", type=float, help="share of frames never served")
    parser.add_argument("--clock-offset", type=float, help="s, robot clock minus bridge clock")
    parser.add_argument("--bare", action="store_true", help="the least NAOqi: no posture, autonomous life, "
                        "memory subscribers or timestamps, no battery key, RGB images")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    world = SimWorld(args.scenario, load_robot_model(), resolution=args.resolution, seed=args.seed)
    try:
        standin = StandIn(world, args.clock_offset, args.listen, args.latency, args.drop_rate, args.bare)
    except ValueError as exc:
        parser.error(str(exc))
    with standin:
        print(f"NAOqi stand-in serving {args.scenario!r} at {standin.url}", flush=True)
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
