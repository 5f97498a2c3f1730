"""The bridge process: one robot backend exposed on Zenoh, with the safety rules of docs/bridge.md.

Threads (none ever waits on another; every hand-over keeps only the newest item):

* camera: ``backend.grab_frame`` -> ``cv2.imencode`` JPEG -> frame envelope, published with
  ``CongestionControl.DROP`` and ``express`` (a slow link drops frames, never queues them);
* state: ``backend.read_state`` at ``state_rate_hz`` -> ``state`` (and ``sim/truth`` for the
  simulator), ``CongestionControl.BLOCK``; it also latches the fall flag;
* Zenoh callbacks: decode, check, store the newest command; malformed -> counted per reason;
* safety: every ``control_period_s`` (and at once when a command or an event arrives) decides
  walk or stop; it issues ``stop_walking`` itself and hands walk commands to the actuator;
* actuator: the only caller of the slow ``backend.walk`` / ``set_head``; holds the latest only;
* heartbeat: while the safety thread ticks, writes the heartbeat the robot-side watchdog
  (``nao_bridge.watchdog``) waits for, and checks that the watchdog answers.

Every backend call goes through :class:`TimedCalls`: it returns within ``call_timeout_s`` or
raises :class:`CallTimeout` (the call is left to finish on its own thread), so a dead NAOqi link
never stalls the safety thread.

One owner. A station takes the lease (``lease`` queryable, :class:`LeaseRequest`) while its
liveliness token ``station/alive/<id>`` is alive: first come; a second station is refused until
the owner releases it (hand-over). Commands must carry the lease's secret; any other command is
ignored and counted as ``not_owner`` before its sequence number is even looked at. When the
owner's token goes away the lease is revoked (``station_lost``): the robot stays stopped until a
station takes a new lease (the explicit re-arm).

Walk rule, evaluated by the safety thread at time t for the newest accepted command c received at
t_c:  walk(clamp(c)) iff not fallen and not shutting down and a lease is held and the stop is not
failing and (the robot watchdog answers or is not required) and t - t_c <= min(deadman_s, c.ttl);
otherwise stop, and c is dropped (only a newer command resumes). A command is accepted when it
decodes, carries the current lease, its seq is newer than the last accepted one of this lease and
its ttl is positive.

Confirmed stops. A stop decision opens a pending stop; every control period the safety thread
(re)sends ``stop_walking`` while the last attempt failed, then asks ``move_is_active``: the moving
flag clears only when that says no. Unconfirmed after ``stop_escalate_s`` it calls ``kill_move``
and reports ``stop_failed`` (walks are refused until the stop is confirmed), after twice that
``rest``. Every failed stop call and every escalation is counted in ``State.stop_failures``
(a robot still decelerating is not a failure: NAOqi ends the walk at the next double support).

Race between a stop and a slow walk call: every stop increments a generation counter before calling
``stop_walking``; the actuator compares the generation before and after ``backend.walk`` and stops
again if a stop overtook the call, so the robot never keeps walking after a stop decision.
"""

from __future__ import annotations

import collections
import logging
import secrets
import threading
import time
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Callable, Dict, Literal, Optional, Set, Tuple

import cv2
import zenoh

from nao_bridge.backend import RobotBackend
from nao_bridge.naoqi_backend import NaoqiParams
from nao_core.config import bounds, from_mapping
from nao_core.protocol import (
    FrameMeta,
    HeadCommand,
    Info,
    LeaseReply,
    LeaseRequest,
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
    head_speed_max: float = field(metadata=bounds(0.01, 1.0))
    call_timeout_s: float = field(metadata=bounds(0.05, 5.0))
    stop_escalate_s: float = field(metadata=bounds(0.1, 10.0))
    robot_watchdog: Literal["auto", "required", "off"]
    heartbeat_period_s: float = field(metadata=bounds(0.01, 0.5))
    watchdog_answer_s: float = field(metadata=bounds(0.1, 10.0))
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


class CallTimeout(RuntimeError):
    """A backend call did not return within its time limit."""


class TimedCalls:
    """Run each backend call on its own daemon thread and wait for it at most ``timeout`` seconds.

    A call that times out keeps its thread until it returns; at most ``max_stuck`` such calls per
    name are allowed, further ones fail at once (a dead link never piles up threads).
    """

    def __init__(self, timeout: float, max_stuck: int = 4):
        self.timeout = timeout
        self.max_stuck = max_stuck
        self._stuck: Dict[str, int] = collections.Counter()
        self._lock = threading.Lock()

    def __call__(self, name: str, call: Callable[..., Any], *args: Any) -> Any:
        with self._lock:
            if self._stuck[name] >= self.max_stuck:
                raise CallTimeout(f"{name}: {self._stuck[name]} earlier calls still blocked")
        box: Dict[str, Any] = {}
        done = threading.Event()

        def run() -> None:
            try:
                box["value"] = call(*args)
            except BaseException as exc:  # noqa: BLE001 - handed to the waiting thread
                box["error"] = exc
            with self._lock:
                done.set()
                if box.get("late"):
                    self._stuck[name] -= 1

        threading.Thread(target=run, name=f"call-{name}", daemon=True).start()
        if not done.wait(self.timeout):
            with self._lock:
                if not done.is_set():
                    box["late"] = True
                    self._stuck[name] += 1
                    raise CallTimeout(f"{name}: no answer within {self.timeout:g} s")
        if "error" in box:
            raise box["error"]
        return box.get("value")


@dataclass
class _PendingStop:
    """A stop decided by the safety thread and not yet confirmed by ``move_is_active``."""

    reason: str
    since: float  # monotonic time of the decision
    sent: bool = False  # the last stop_walking call returned without error
    escalation: int = 0  # 0 none, 1 kill_move, 2 rest


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
        self._stations: Set[str] = set()  # ids of the live station tokens
        self._owner: Optional[str] = None  # the station holding the lease
        self._lease: Optional[str] = None  # its secret
        self._lost = False  # the owner went away: stopped until a new lease is taken
        self._fallen = False  # latched
        self._fall_handled = False  # the safety thread has stopped the robot for the fall
        self._shutdown = False
        self._watchdog = "idle"
        self._moving = False  # a walk was handed to the actuator and no stop confirmed since (safety thread)
        self._pending: Optional[_PendingStop] = None  # safety thread only
        self._stop_failed = False  # a stop stayed unconfirmed past stop_escalate_s
        self._stop_failures = 0
        self._generation = 0  # incremented by every stop
        self.calls = TimedCalls(params.call_timeout_s)
        self._watchdog_required = params.robot_watchdog == "required" or (
            params.robot_watchdog == "auto" and backend.remote)
        self._robot_watchdog = "off" if params.robot_watchdog == "off" else "missing"
        self._last_tick = time.monotonic()  # of the safety thread, read by the heartbeat thread
        self._walk_box = _Latest()
        self._head_box = _Latest()
        self._wake_safety = threading.Event()
        self._wake_actuator = threading.Event()
        self._stopping = threading.Event()
        self._threads: list = []
        self._entities: list = []
        self._session: Optional[zenoh.Session] = None
        self._last_log: Dict[str, float] = {}
        self._suppressed: Dict[str, int] = collections.Counter()
        self._log_lock = threading.Lock()
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
        self._entities.append(session.declare_queryable(keys.lease, self._on_lease))
        self._entities.append(
            session.liveliness().declare_subscriber(keys.station_alive, self._on_station, history=True)
        )
        self._entities.append(session.liveliness().declare_token(keys.alive))
        for name, loop in (
            ("safety", self._safety_loop),
            ("actuator", self._actuator_loop),
            ("state", self._state_loop),
            ("camera", self._camera_loop),
            ("heartbeat", self._heartbeat_loop),
        ):
            thread = threading.Thread(target=loop, name=f"bridge-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        log.info("bridge %s up: listening on %s, keys under %s", self.info.bridge_version,
                 ", ".join(self.params.transport.listen), keys.prefix)
        if self._watchdog_required:
            log.info("the robot-side watchdog must answer before the robot walks (nao-bridge install-watchdog)")

    def close(self) -> None:
        """Stop the robot, stop the threads, undeclare, close the backend and the session. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with self._lock:
            self._shutdown = True
            self._walk = None
        self._stopping.set()
        self._wake_safety.set()
        self._wake_actuator.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
        if self._backend_started:
            self._generation += 1
            try:
                self.calls("stop_walking", self.backend.stop_walking)
            except Exception as exc:  # noqa: BLE001 - backend.close stops once more
                log.error("stop at shutdown failed: %s", exc)
        for entity in reversed(self._entities):
            _quietly(entity.undeclare, "undeclare")
        self._entities.clear()
        _quietly(self.backend.close, "backend close")
        if self._session is not None:
            _quietly(self._session.close, "session close")
        log.info("bridge closed (rejected %s, ignored %s)", dict(self.rejected), dict(self.ignored))

    @property
    def station_alive(self) -> bool:
        """Whether some station's liveliness token is alive."""
        with self._lock:
            return bool(self._stations)

    @property
    def owner(self) -> Optional[str]:
        """The id of the station holding the lease."""
        with self._lock:
            return self._owner

    def __enter__(self) -> "Bridge":
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- Zenoh callbacks: decode, check, store the newest ------------------------------------------

    def _decode(self, payload: Optional[zenoh.ZBytes], key: Any, cls: type) -> Any:
        try:
            return decode(payload.to_bytes() if payload is not None else b"", cls)
        except ProtocolError as exc:
            with self._lock:
                self.rejected[exc.reason] += 1
            self._log_limited(f"reject-{exc.reason}", "rejected %s on %s: %s", cls.TYPE, key, exc)
            return None

    def _ignore(self, cause: str, what: str) -> None:
        self.ignored[cause] += 1  # caller holds self._lock
        self._log_limited(f"ignore-{cause}", "ignored %s: %s", what, cause)

    def _admit(self, kind: str, command: Any) -> bool:
        """Not shutting down, the lease's secret, seq newer: then record seq (caller holds the lock)."""
        if self._shutdown:
            self._ignore("shutdown", f"{kind} command")
        elif self._lease is None or not secrets.compare_digest(command.lease.encode(), self._lease.encode()):
            self._ignore("not_owner", f"{kind} command without the lease")
        elif command.seq <= self._last_seq[kind]:
            self._ignore("stale_seq", f"{kind} command seq {command.seq}")
        else:
            self._last_seq[kind] = command.seq
            return True
        return False

    def _on_walk(self, sample: zenoh.Sample) -> None:
        command = self._decode(sample.payload, sample.key_expr, WalkCommand)
        if command is None:
            return
        with self._lock:
            if not self._admit("walk", command):
                return
            if self._fallen:
                return self._ignore("fallen", "walk command")
            if command.ttl <= 0.0:
                return self._ignore("expired", f"walk command seq {command.seq}")
            now = time.monotonic()
            self._walk = (command, now)
            self._last_arrival = now
        self._wake_safety.set()

    def _on_head(self, sample: zenoh.Sample) -> None:
        command = self._decode(sample.payload, sample.key_expr, HeadCommand)
        if command is None:
            return
        with self._lock:
            if not self._admit("head", command):
                return
        yaw, pitch = self.model.head.clamp(command.yaw, command.pitch)
        self._head_box.put((yaw, pitch, min(command.speed, self.params.head_speed_max)))
        self._wake_actuator.set()

    def _on_station(self, sample: zenoh.Sample) -> None:
        station = str(sample.key_expr).rsplit("/", 1)[-1]
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if alive:
                self._stations.add(station)
            else:
                self._stations.discard(station)
            lost = not alive and station == self._owner
            if lost:  # the lease dies with its station: stopped until a station takes a new one
                self._owner = self._lease = None
                self._walk = None
                self._lost = True
        if alive or lost:
            log.warning("station %s %s", station, "connected" if alive else "lost: lease revoked, robot stays stopped")
        self._wake_safety.set()

    def _on_lease(self, query: zenoh.Query) -> None:
        request = self._decode(query.payload, query.key_expr, LeaseRequest)
        if request is None:
            reply = LeaseReply(granted=False, lease="", reason="malformed")
        else:
            with self._lock:
                reply = self._lease_decision(request)
            log.warning("lease %s by station %s: %s", request.op, request.station, reply.reason)
            self._wake_safety.set()
        query.reply(self.keys.lease, encode(reply), encoding=zenoh.Encoding.APPLICATION_JSON)

    def _lease_decision(self, request: LeaseRequest) -> LeaseReply:
        """Take: first come, while the station's token lives. Release: only with the secret (lock held)."""
        held = self._lease is not None
        if request.op == "release":
            if not held or not secrets.compare_digest(request.lease.encode(), self._lease.encode()):
                self._ignore("not_owner", "lease release")
                return LeaseReply(granted=False, lease="", reason="bad_lease")
            self._owner = self._lease = None
            self._walk = None
            return LeaseReply(granted=False, lease="", reason="released")
        if held:
            self._ignore("lease_held", f"lease for station {request.station}")
            return LeaseReply(granted=False, lease="", reason="held")
        if request.station not in self._stations:  # not counted: its token may simply be on its way
            return LeaseReply(granted=False, lease="", reason="no_token")
        self._owner, self._lease, self._lost = request.station, secrets.token_hex(16), False
        self._last_seq = {"walk": -1, "head": -1}  # a lease numbers its commands from scratch
        return LeaseReply(granted=True, lease=self._lease, reason="granted")

    def _on_info(self, query: zenoh.Query) -> None:
        query.reply(self.keys.info, encode(self.info), encoding=zenoh.Encoding.APPLICATION_JSON)

    # -- safety ------------------------------------------------------------------------------------

    def _safety_loop(self) -> None:
        while not self._stopping.is_set():
            self._wake_safety.wait(self.params.control_period_s)
            self._wake_safety.clear()
            if self._stopping.is_set():
                return
            self._last_tick = time.monotonic()
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
            if self._pending is None and (self._moving or new_fall):
                self._begin_stop(self._watchdog, now)
            if self._pending is not None:
                self._advance_stop(now)
            return
        self._pending = None  # a valid walk supersedes a stop that is not failing
        velocities = self.model.walk.clamp(command.vx, command.vy, command.omega)
        self._walk_box.put((self._generation, command, velocities))
        self._moving = True
        self._wake_actuator.set()

    def _stop_reason(self, now: float) -> Optional[str]:
        """Why the robot must not walk now, or None (caller holds the lock)."""
        if self._fallen:
            return "fallen"
        if self._shutdown:
            return "shutdown"
        if self._stop_failed:
            return "stop_failed"
        if self._lost or self._lease is None:
            return "station_lost" if self._lost else "idle"
        if self._watchdog_required and self._robot_watchdog != "ok":
            return "no_robot_watchdog"
        if self._walk is not None:
            command, arrived = self._walk
            if now - arrived > min(self.params.deadman_s, command.ttl):
                return "deadman"
        return None

    def _begin_stop(self, reason: str, now: float) -> None:
        self._generation += 1  # the actuator drops (or undoes) any walk in flight
        self._walk_box.take()
        self._pending = _PendingStop(reason, now)
        log.info("stop walking: %s", reason)

    def _advance_stop(self, now: float) -> None:
        """One control period of a pending stop: send, confirm, escalate (safety thread only)."""
        pending = self._pending
        assert pending is not None
        try:
            if not pending.sent:
                self.calls("stop_walking", self.backend.stop_walking)
                pending.sent = True
            if not self.calls("move_is_active", self.backend.move_is_active):
                self._pending = None
                self._moving = False
                if pending.escalation:
                    log.warning("stop confirmed after %.2f s", now - pending.since)
                with self._lock:
                    self._stop_failed = False
                    if self._watchdog == "stop_failed":
                        self._watchdog = pending.reason
                return
        except Exception as exc:  # noqa: BLE001 - retried next period
            pending.sent = False
            with self._lock:
                self._stop_failures += 1
            self._log_limited("stop", "stop (%s) failed: %s", pending.reason, exc, level=logging.ERROR)
        late = now - pending.since
        if late >= self.params.stop_escalate_s and pending.escalation == 0:
            pending.escalation = 1
            with self._lock:
                self._stop_failures += 1
                self._stop_failed = True
                self._watchdog = "stop_failed"
            log.error("stop (%s) unconfirmed for %.2f s: killMove", pending.reason, late)
            self._escalate("kill_move", self.backend.kill_move)
        elif late >= 2 * self.params.stop_escalate_s and pending.escalation == 1:
            pending.escalation = 2
            log.error("stop (%s) unconfirmed for %.2f s: rest", pending.reason, late)
            self._escalate("rest", self.backend.rest)

    def _escalate(self, name: str, call: Callable[[], None]) -> None:
        try:
            self.calls(name, call)
        except Exception as exc:  # noqa: BLE001 - the next period tries to confirm again
            log.error("%s failed: %s", name, exc)

    # -- actuator ----------------------------------------------------------------------------------

    def _actuator_loop(self) -> None:
        sent: Optional[WalkCommand] = None  # the command last handed to backend.walk
        while not self._stopping.is_set():
            self._wake_actuator.wait(0.5)
            self._wake_actuator.clear()
            try:
                head = self._head_box.take()
                if head is not None:
                    self.calls("set_head", self.backend.set_head, *head)
                walk = self._walk_box.take()
                if walk is None:
                    continue
                generation, command, velocities = walk
                if generation != self._generation or command is sent:
                    continue
                try:
                    self.calls("walk", self.backend.walk, *velocities)
                finally:
                    sent = command
                    if generation != self._generation:  # a stop overtook this call
                        self.calls("stop_walking", self.backend.stop_walking)
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

    def _heartbeat_loop(self) -> None:
        """Heartbeats for the robot-side watchdog while the safety thread ticks; watch its answer."""
        period = self.params.heartbeat_period_s
        count, seen, seen_at = 0, None, time.monotonic()
        while not self._stopping.wait(period):
            now = time.monotonic()
            try:
                if now - self._last_tick <= 3 * self.params.control_period_s + period:
                    count += 1
                    self.calls("heartbeat", self.backend.heartbeat, count)
                if self.params.robot_watchdog == "off":
                    continue
                answer = self.calls("watchdog_count", self.backend.watchdog_count)
                if answer is not None and answer != seen:
                    seen, seen_at = answer, now
            except Exception as exc:  # noqa: BLE001
                self._log_limited("heartbeat", "heartbeat failed: %s", exc, level=logging.ERROR)
            state = "ok" if seen is not None and now - seen_at <= self.params.watchdog_answer_s else "missing"
            if state != self._robot_watchdog:
                level = logging.INFO if state == "ok" or not self._watchdog_required else logging.ERROR
                log.log(level, "robot-side watchdog %s", "answers" if state == "ok" else "does not answer")
                with self._lock:
                    self._robot_watchdog = state
                self._wake_safety.set()

    def _publish_state(self) -> None:
        robot = self.calls("read_state", self.backend.read_state)
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
                battery=None if robot.battery is None else float(robot.battery),
                cmd_age=None if self._last_arrival is None else now - self._last_arrival,
                watchdog="shutdown" if self._shutdown else self._watchdog,
                rejected=dict(self.rejected),
                ignored=dict(self.ignored),
                owner=self._owner,
                stop_failures=self._stop_failures,
                robot_watchdog=self._robot_watchdog,
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
                    stamp_std=frame.stamp_std,
                )
                self._frame_pub.put(encode_frame(meta, jpeg.tobytes()))
                seq += 1
            except Exception as exc:  # noqa: BLE001
                self._log_limited("camera", "camera loop: %s", exc, level=logging.ERROR)
                self._stopping.wait(0.1)

    def _log_limited(self, topic: str, fmt: str, *args: Any, level: int = logging.WARNING) -> None:
        """Log at most once per second per topic (a flood of bad messages must not flood the log).

        Topics are a fixed set (one per ProtocolError reason, ignore cause and thread), so the
        bookkeeping stays bounded; each line says how many were suppressed since the last one.
        """
        now = time.monotonic()
        with self._log_lock:
            if now - self._last_log.get(topic, -1e9) < 1.0:
                self._suppressed[topic] += 1
                return
            self._last_log[topic] = now
            suppressed = self._suppressed.pop(topic, 0)
        log.log(level, fmt + (f" (+{suppressed} more like it)" if suppressed else ""), *args)


def _quietly(call: Callable[[], Any], what: str) -> None:
    try:
        call()
    except Exception as exc:  # noqa: BLE001 - shutdown continues whatever fails
        log.error("%s failed: %s", what, exc)
