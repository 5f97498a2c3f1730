"""A NAOqi stand-in: the NAOqi services the bridge uses, served over libqi, driven by a SimWorld.

``StandIn(world).start()`` listens on ``tcp://127.0.0.1:<free port>`` with
``qi.Session().listenStandalone`` and registers ALMotion, ALVideoDevice, ALMemory, ALRobotPosture
and ALAutonomousLife with the real NAOqi signatures, so :class:`NaoqiBackend` runs unchanged
against it (``url``). Every call is recorded as ``Call(time.time(), "Service.method", args)`` in
``calls``; tests assert on that record (e.g. the time of the ``ALMotion.stopMove`` after the
station went silent). ``fall()`` makes the world fall and fires the ALMemory fall signals.

The camera behaves like NAOqi's: a new image every 1/fps on the robot's clock, which runs
``clock_offset`` seconds ahead of the bridge's; asking sooner returns the same image with the same
stamp (a duplicate); the buffer is latin-1 text in BGR or packed YUYV, as requested.

    python -m nao_sim.standin --scenario can      # serve until Ctrl-C, print the URL
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Union

import cv2
import qi

from nao_core.naoqi_api import (
    BATTERY_KEY,
    COLOR_SPACE_IDS,
    FALL_KEYS,
    HEAD_JOINTS,
    RESOLUTION_IDS,
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


class ALVideoDevice:
    def __init__(self, world: SimWorld, record: _Recorder, clock_offset: float):
        self._world = world
        self._record = record
        self._clock_offset = clock_offset
        self._subscribers: Dict[str, Dict[str, Any]] = {}
        self._lock = threading.Lock()

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
            self._subscribers[handle] = {"color_space": color_space, "period": 1.0 / fps, "image": None, "due": 0.0}
        return handle

    def getImageRemote(self, handle: str) -> Optional[list]:
        self._record("ALVideoDevice.getImageRemote", handle)
        with self._lock:
            sub = self._subscribers.get(handle)
            if sub is None:
                raise RuntimeError(f"ALVideoDevice.getImageRemote: unknown handle {handle!r}")
            now = time.time()
            if sub["image"] is None or now >= sub["due"]:
                sub["image"] = self._image(sub["color_space"])
                due = sub["due"] + sub["period"]
                sub["due"] = due if due >= now else now + sub["period"]  # keep the cadence unless behind
            return sub["image"]

    def _image(self, color_space: int) -> list:
        frame = self._world.render()
        pixels = frame.image if color_space == COLOR_SPACE_IDS["bgr"] else cv2.cvtColor(frame.image, cv2.COLOR_BGR2YUV_YUYV)
        height, width, layers = pixels.shape
        robot_stamp = frame.stamp + self._clock_offset
        seconds = math.floor(robot_stamp)
        micros = int(round((robot_stamp - seconds) * 1e6))
        buffer = pixels.tobytes().decode("latin-1")
        return [width, height, layers, color_space, seconds, micros, buffer, TOP_CAMERA, 0.5, 0.4, -0.5, -0.4]

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


class ALMemory:
    def __init__(self, world: SimWorld, record: _Recorder):
        self._world = world
        self._record = record
        self._subscribers: Dict[str, _MemorySubscriber] = {}
        self._lock = threading.Lock()

    def getData(self, key: str) -> Any:
        self._record("ALMemory.getData", key)
        if key in FALL_KEYS:
            return bool(self._world.is_fallen())
        if key == BATTERY_KEY:
            return float(self._world.battery())
        raise RuntimeError(f"ALMemory::getData: key {key!r} not found")

    def subscriber(self, key: str) -> _MemorySubscriber:
        self._record("ALMemory.subscriber", key)
        with self._lock:
            return self._subscribers.setdefault(key, _MemorySubscriber())

    def _raise_event(self, key: str, value: Any) -> None:
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

    def __init__(self, world: SimWorld, clock_offset: float = 1000.0, listen: str = "tcp://127.0.0.1:0"):
        self.world = world
        self.listen = listen
        self._record = _Recorder()
        self.memory = ALMemory(world, self._record)
        self.services = {
            "ALMotion": ALMotion(world, self._record),
            "ALVideoDevice": ALVideoDevice(world, self._record, clock_offset),
            "ALMemory": self.memory,
            "ALRobotPosture": ALRobotPosture(self._record),
            "ALAutonomousLife": ALAutonomousLife(self._record),
        }
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
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    world = SimWorld(args.scenario, load_robot_model(), resolution=args.resolution, seed=args.seed)
    with StandIn(world, listen=args.listen) as standin:
        print(f"NAOqi stand-in serving {args.scenario!r} at {standin.url}", flush=True)
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
