"""The bridge process: one robot backend exposed on Zenoh, with the safety rules of DESIGN.md.

Threads (none ever waits on another; every hand-over keeps only the newest item):

* camera: ``backend.grab_frame`` -> ``cv2.imencode`` JPEG -> frame envelope, published with
  ``CongestionControl.DROP`` and ``express`` (a slow link drops frames, never queues them);
* state: ``backend.read_state`` at ``state_rate_hz`` -> ``state`` (and ``sim/truth`` for the
  simulator), ``CongestionControl.BLOCK``; it also latches the fall flag;
* Zenoh callbacks: decode, check, store the newest command; malformed -> counted per reason;
* safety: every ``control_period_s`` (and at once when a command or an event arrives) decides
  walk or stop; it issues ``stop_walking`` itself and hands walk commands to the actuator;
* actuator: the only caller of the slow ``backend.walk`` / ``set_head``; holds the latest only.

Walk rule, evaluated by the safety thread at time t for the newest accepted command c received at
t_c:  walk(clamp(c)) iff not fallen and not shutting down and (station alive or not required) and
t - t_c <= min(deadman_s, c.ttl); otherwise stop, and c is dropped (only a newer command resumes).
A command is accepted when it decodes, its seq is newer than the last accepted one of the current
station session (a new station liveliness token starts a new session) and its ttl is positive.

Race between a stop and a slow walk call: every stop increments a generation counter before calling
``stop_walking``; the actuator compares the generation before and after ``backend.walk`` and stops
again if a stop overtook the call, so the robot never keeps walking after a stop decision.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Callable, Dict, Optional, Tuple

import cv2
import zenoh

from nao_bridge.backend import RobotBackend
from nao_bridge.naoqi_backend import NaoqiParams
from nao_core.config import bounds, from_mapping
from nao_core.protocol import (
    FrameMeta,
    HeadCommand,
    Info,
    ProtocolError,
    RobotKeys,
    State,
    Truth,
    WalkCommand,
    decode,
    encode,
    encode_frame,
)
from nao_core.robot_model import RobotModel
from nao_core.transport import TransportConfig, open_session

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BridgeParams:
    """The ``bridge`` section of config/bridge.yaml."""

    name: str
    transport: TransportConfig
    robot: Optional[str]  # extra robot model file, relative to config/ or absolute
    resolution: str
    fps: float = field(metadata=bounds(0.5, 60.0))
    jpeg_quality: int = field(metadata=bounds(10, 100))
    state_rate_hz: float = field(metadata=bounds(10.0, 50.0))
    deadman_s: float = field(metadata=bounds(0.05, 2.0))
    control_period_s: float = field(metadata=bounds(0.002, 0.1))
    require_station: bool
    head_speed_max: float = field(metadata=bounds(0.01, 1.0))
    naoqi: NaoqiParams


def bridge_version() -> str:
    try:
        return metadata.version("nao-active-recon")
    except metadata.PackageNotFoundError:
        return "unknown"


class _Latest:
    """A one-item mailbox: ``put`` replaces, ``take`` empties."""

    def __init__(self) -> None:
        self._item: Any = None
        self._lock = threading.Lock()

    def put(self, item: Any) -> None:
        with self._lock:
            self._item = item

    def take(self) -> Any:
        with self._lock:
            item, self._item = self._item, None
            return item


class Bridge:
    """Runs ``backend`` on a Zenoh session until :meth:`close`."""

    def __init__(self, backend: RobotBackend, model: RobotModel, params: BridgeParams, backend_name: str):
        self.backend = backend
        self.model = model
        self.params = params
        self.keys = RobotKeys(params.name)
        self.intrinsics = model.camera.intrinsics(params.resolution)
        self.info = Info(
            bridge_version=bridge_version(),
            backend=backend_name,
            robot=model,
            resolution=params.resolution,
            intrinsics=self.intrinsics,
            fps=params.fps,
            state_rate_hz=params.state_rate_hz,
            deadman_s=params.deadman_s,
        )
        self.rejected: Dict[str, int] = collections.Counter()
        self.ignored: Dict[str, int] = collections.Counter()
        self._lock = threading.Lock()
        self._walk: Optional[Tuple[WalkCommand, float]] = None  # newest accepted command, arrival (monotonic)
        self._last_arrival: Optional[float] = None
        self._last_seq = {"walk": -1, "head": -1}
        self._station_alive = False
        self._fallen = False  # latched
        self._fall_handled = False  # the safety thread has stopped the robot for the fall
        self._shutdown = False
        self._watchdog = "idle"
        self._moving = False  # a walk was handed to the actuator since the last stop (safety thread only)
        self._generation = 0  # incremented by every stop
        self._walk_box = _Latest()
        self._head_box = _Latest()
        self._wake_safety = threading.Event()
        self._wake_actuator = threading.Event()
        self._stopping = threading.Event()
        self._threads: list = []
        self._entities: list = []
        self._session: Optional[zenoh.Session] = None
        self._last_log: Dict[str, float] = {}
        self._closed = False
        self._backend_started = False

    # -- lifecycle -------------------------------------------------------------------------------

    def start(self) -> None:
        """Start the backend, open the session, declare everything and start the threads."""
        self.backend.start()
        self._backend_started = True
        session = open_session(self.params.transport)
        self._session = session
        keys = self.keys
        self._frame_pub = session.declare_publisher(
            keys.camera_top, congestion_control=zenoh.CongestionControl.DROP, express=True
        )
        self._state_pub = session.declare_publisher(keys.state, congestion_control=zenoh.CongestionControl.BLOCK)
        self._truth_pub = session.declare_publisher(keys.sim_truth, congestion_control=zenoh.CongestionControl.BLOCK)
        self._entities += [self._frame_pub, self._state_pub, self._truth_pub]
        self._entities.append(session.declare_subscriber(keys.cmd_walk, self._on_walk))
        self._entities.append(session.declare_subscriber(keys.cmd_head, self._on_head))
        self._entities.append(session.declare_queryable(keys.info, self._on_info))
        self._entities.append(
            session.liveliness().declare_subscriber(keys.station_alive, self._on_station, history=True)
        )
        self._entities.append(session.liveliness().declare_token(keys.alive))
        for name, loop in (
            ("safety", self._safety_loop),
            ("actuator", self._actuator_loop),
            ("state", self._state_loop),
            ("camera", self._camera_loop),
        ):
            thread = threading.Thread(target=loop, name=f"bridge-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        log.info("bridge %s up: listening on %s, keys under %s", self.info.bridge_version,
                 ", ".join(self.params.transport.listen), keys.prefix)

    def close(self) -> None:
        """Stop the robot, stop the threads, undeclare, close the backend and the session. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with self._lock:
            self._shutdown = True
            self._walk = None
        if self._backend_started:
            self._stop_robot("shutdown", always=True)
        self._stopping.set()
        self._wake_safety.set()
        self._wake_actuator.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
        for entity in reversed(self._entities):
            _quietly(entity.undeclare, "undeclare")
        self._entities.clear()
        _quietly(self.backend.close, "backend close")
        if self._session is not None:
            _quietly(self._session.close, "session close")
        log.info("bridge closed (rejected %s, ignored %s)", dict(self.rejected), dict(self.ignored))

    @property
    def station_alive(self) -> bool:
        with self._lock:
            return self._station_alive

    def __enter__(self) -> "Bridge":
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- Zenoh callbacks: decode, check, store the newest ------------------------------------------

    def _decode(self, sample: zenoh.Sample, cls: type) -> Any:
        try:
            return decode(sample.payload.to_bytes(), cls)
        except ProtocolError as exc:
            with self._lock:
                self.rejected[exc.reason] += 1
            self._log_limited(f"reject-{exc.reason}", "rejected %s on %s: %s", cls.TYPE, sample.key_expr, exc)
            return None

    def _ignore(self, cause: str, what: str) -> None:
        self.ignored[cause] += 1  # caller holds self._lock
        self._log_limited(f"ignore-{cause}", "ignored %s: %s", what, cause)

    def _admit(self, kind: str, seq: int) -> bool:
        """Not shutting down, station alive if required, seq newer: then record seq (caller holds the lock)."""
        if self._shutdown:
            self._ignore("shutdown", f"{kind} command")
        elif self.params.require_station and not self._station_alive:
            self._ignore("no_station", f"{kind} command")
        elif seq <= self._last_seq[kind]:
            self._ignore("stale_seq", f"{kind} command seq {seq}")
        else:
            self._last_seq[kind] = seq
            return True
        return False

    def _on_walk(self, sample: zenoh.Sample) -> None:
        command = self._decode(sample, WalkCommand)
        if command is None:
            return
        with self._lock:
            if self._fallen:
                return self._ignore("fallen", "walk command")
            if not self._admit("walk", command.seq):
                return
            if command.ttl <= 0.0:
                return self._ignore("expired", f"walk command seq {command.seq}")
            now = time.monotonic()
            self._walk = (command, now)
            self._last_arrival = now
        self._wake_safety.set()

    def _on_head(self, sample: zenoh.Sample) -> None:
        command = self._decode(sample, HeadCommand)
        if command is None:
            return
        with self._lock:
            if not self._admit("head", command.seq):
                return
        yaw, pitch = self.model.head.clamp(command.yaw, command.pitch)
        self._head_box.put((yaw, pitch, min(command.speed, self.params.head_speed_max)))
        self._wake_actuator.set()

    def _on_station(self, sample: zenoh.Sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            self._station_alive = alive
            if alive:  # a new station session numbers its commands from scratch
                self._last_seq = {"walk": -1, "head": -1}
            else:
                self._walk = None
        log.warning("station %s (%s)", "connected" if alive else "lost", sample.key_expr)
        self._wake_safety.set()

    def _on_info(self, query: zenoh.Query) -> None:
        query.reply(self.keys.info, encode(self.info), encoding=zenoh.Encoding.APPLICATION_JSON)

    # -- safety ------------------------------------------------------------------------------------

    def _safety_loop(self) -> None:
        while not self._stopping.is_set():
            self._wake_safety.wait(self.params.control_period_s)
            self._wake_safety.clear()
            if self._stopping.is_set():
                return
            try:
                self._safety_tick(time.monotonic())
            except Exception as exc:  # noqa: BLE001 - the deadman must keep running
                self._log_limited("safety", "safety tick failed: %s", exc, level=logging.ERROR)

    def _safety_tick(self, now: float) -> None:
        with self._lock:
            reason = self._stop_reason(now)
            command = self._walk[0] if reason is None and self._walk is not None else None
            if reason is not None:
                self._walk = None
                self._watchdog = reason
            elif command is not None:
                self._watchdog = "walking"
            new_fall = self._fallen and not self._fall_handled
            self._fall_handled = self._fallen
        if command is None:
            self._stop_robot(self._watchdog, always=new_fall)
            return
        velocities = self.model.walk.clamp(command.vx, command.vy, command.omega)
        self._walk_box.put((self._generation, command.seq, velocities))
        self._moving = True
        self._wake_actuator.set()

    def _stop_reason(self, now: float) -> Optional[str]:
        """Why the robot must not walk now, or None (caller holds the lock)."""
        if self._fallen:
            return "fallen"
        if self.params.require_station and not self._station_alive:
            return "station_lost"
        if self._walk is not None:
            command, arrived = self._walk
            if now - arrived > min(self.params.deadman_s, command.ttl):
                return "deadman"
        return None

    def _stop_robot(self, reason: str, always: bool = False) -> None:
        if not (self._moving or always):
            return
        self._generation += 1
        self._walk_box.take()
        self._moving = False
        log.info("stop walking: %s", reason)
        try:
            self.backend.stop_walking()
        except Exception as exc:  # noqa: BLE001 - logged; the next tick or close retries
            log.error("stop_walking failed (%s): %s", reason, exc)

    # -- actuator ----------------------------------------------------------------------------------

    def _actuator_loop(self) -> None:
        sent_seq = -1
        while not self._stopping.is_set():
            self._wake_actuator.wait(0.5)
            self._wake_actuator.clear()
            try:
                head = self._head_box.take()
                if head is not None:
                    self.backend.set_head(*head)
                walk = self._walk_box.take()
                if walk is None:
                    continue
                generation, seq, velocities = walk
                if generation != self._generation or seq == sent_seq:
                    continue
                self.backend.walk(*velocities)
                sent_seq = seq
                if generation != self._generation:  # a stop overtook this call
                    self.backend.stop_walking()
            except Exception as exc:  # noqa: BLE001
                self._log_limited("actuator", "actuator call failed: %s", exc, level=logging.ERROR)

    # -- publishers --------------------------------------------------------------------------------

    def _state_loop(self) -> None:
        period = 1.0 / self.params.state_rate_hz
        next_tick = time.monotonic()
        while not self._stopping.is_set():
            try:
                self._publish_state()
            except Exception as exc:  # noqa: BLE001
                self._log_limited("state", "state publishing failed: %s", exc, level=logging.ERROR)
            next_tick = max(next_tick + period, time.monotonic())
            self._stopping.wait(next_tick - time.monotonic())

    def _publish_state(self) -> None:
        robot = self.backend.read_state()
        with self._lock:
            if bool(robot.fallen) and not self._fallen:
                self._fallen = True
                log.error("robot fallen: walking stopped, walk commands refused until restart")
                self._wake_safety.set()
            now = time.monotonic()
            state = State(
                stamp=robot.stamp,
                odom=robot.odom,
                head_yaw=robot.head_yaw,
                head_pitch=robot.head_pitch,
                walking=bool(robot.walking),
                fallen=self._fallen,
                battery=float(robot.battery),
                cmd_age=None if self._last_arrival is None else now - self._last_arrival,
                watchdog="shutdown" if self._shutdown else self._watchdog,
                rejected=dict(self.rejected),
                ignored=dict(self.ignored),
            )
        self._state_pub.put(encode(state), encoding=zenoh.Encoding.APPLICATION_JSON)
        truth = self.backend.ground_truth()
        if truth is not None:
            message = from_mapping(Truth, truth, source="backend ground truth")
            self._truth_pub.put(encode(message), encoding=zenoh.Encoding.APPLICATION_JSON)

    def _camera_loop(self) -> None:
        seq = 0
        quality = [cv2.IMWRITE_JPEG_QUALITY, self.params.jpeg_quality]
        while not self._stopping.is_set():
            try:
                frame = self.backend.grab_frame(timeout=0.2)
                if frame is None:
                    continue
                ok, jpeg = cv2.imencode(".jpg", frame.image, quality)
                if not ok:
                    raise RuntimeError("cv2.imencode failed")
                height, width = frame.image.shape[:2]
                meta = FrameMeta(
                    seq=seq,
                    stamp=frame.stamp,
                    width=width,
                    height=height,
                    encoding="jpeg",
                    head_yaw=frame.head_yaw,
                    head_pitch=frame.head_pitch,
                    T_BC=tuple(float(x) for x in frame.T_BC.ravel()),
                    odom=tuple(float(x) for x in frame.odom),
                    resolution=self.params.resolution,
                )
                self._frame_pub.put(encode_frame(meta, jpeg.tobytes()))
                seq += 1
            except Exception as exc:  # noqa: BLE001
                self._log_limited("camera", "camera loop: %s", exc, level=logging.ERROR)
                self._stopping.wait(0.1)

    def _log_limited(self, topic: str, fmt: str, *args: Any, level: int = logging.WARNING) -> None:
        """Log at most once per second per topic (a flood of bad messages must not flood the log)."""
        now = time.monotonic()
        if now - self._last_log.get(topic, -1e9) >= 1.0:
            self._last_log[topic] = now
            log.log(level, fmt, *args)


def _quietly(call: Callable[[], Any], what: str) -> None:
    try:
        call()
    except Exception as exc:  # noqa: BLE001 - shutdown continues whatever fails
        log.error("%s failed: %s", what, exc)
