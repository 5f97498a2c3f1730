"""The live control loop: bridge link in, agent (:class:`station.pilot.Pilot`) in the middle,
commands out, everything into the MCAP log; then stop, final carve and outputs.

One pass of the loop (single thread; Zenoh callbacks only enqueue):

    wait for the inbox (at most until the next tick is due)
    drain it: states -> pilot; truth -> log; bridge lost -> pilot; frames -> log all, keep the newest
    newest frame -> pilot (per-frame pipeline), keyframes -> carving worker
    tick due (t >= t_last_tick + control_period), or a frame just processed and half a period
    passed -> pilot.tick -> walk and head commands sent, the walk command with its TTL;
    then pilot.replan (planner, when due: never delays the tick's commands)
    an interrupt flag set by SIGINT/SIGTERM -> pilot.on_interrupt
    flush the log about once a second

Every input handed to the pilot is journalled on ``/station/input`` (kind, station time t) right
after its raw bytes, so replay can feed the same inputs in the same order. The log writes of a
pass are queued and written, in order, once its commands are sent. Every decision with
``stop`` sends a zero walk command; the robot is stopped before the loop returns, on every path.
"""

from __future__ import annotations

import dataclasses
import hashlib
import queue
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from agent.mission import Outcome, Phase
from nao_core.geometry import invert, planar_transform
from nao_core.protocol import (
    Frame,
    HeadCommand,
    Info,
    ProtocolError,
    State,
    Truth,
    WalkCommand,
    decode,
    decode_frame,
    encode,
    json_schema,
)
from station import foxglove
from station.carving_worker import CarvingWorker
from station.config import StationConfig
from station.link import BridgeLink, Received
from station.mcap_log import McapLog
from station.pilot import Pilot, Step
from station.topics import (
    CALIBRATION,
    CARVING,
    CMD_HEAD,
    CMD_WALK,
    CONFIG,
    EKF,
    FRAME_IMAGE,
    FRAME_META,
    INFO,
    INPUT,
    POSE,
    REJECTED,
    SCENE_KEYFRAMES,
    SCENE_LANDMARKS,
    SCENE_MODEL,
    SCENE_OBJECT,
    STATE,
    TF,
    TRUTH,
)

STATION_SCHEMA = {"title": "station.Json", "type": "object"}


@dataclass
class RunSummary:
    outcome: str  # an agent.mission.Outcome value, or "error"
    reason: str
    success: bool
    frames_received: int
    frames_processed: int
    duration: float
    carver: Any  # agent.carving.VoxelCarver or None
    carving_error: Optional[str]
    x: Optional[np.ndarray]
    P: Optional[np.ndarray]


def pilot_sources(root: Path) -> List[Path]:
    """Every source file the pilot runs: the algorithms, the core they build on, the pilot itself."""
    return sorted([*(root / "agent").rglob("*.py"), *(root / "nao_core").rglob("*.py"), root / "station" / "pilot.py"])


def code_digest() -> str:
    """SHA-256 of the code the pilot executes (agent/, nao_core/ and the pilot): replay says when it changed."""
    root = Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for path in pilot_sources(root):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def config_record(config: StationConfig) -> Dict[str, Any]:
    """The resolved configuration, as logged on /station/config (replay rebuilds it from this),
    with the digest of the agent's code under ``code``."""
    record: Dict[str, Any] = {name: dataclasses.asdict(getattr(config, name)) for name in config.section_names}
    record["landmarks"] = dataclasses.asdict(config.landmarks)
    record["code"] = code_digest()
    return record


class ControlLoop:
    def __init__(self, config: StationConfig, link: BridgeLink, info: Info, info_bytes: bytes, log: McapLog,
                 interrupted: Callable[[], Optional[str]], clock: Callable[[], float] = time.time):
        self.config = config
        self.link = link
        self.info = info
        self.log = log
        self.clock = clock
        self.interrupted = interrupted
        self.pilot = Pilot(config, info)
        self.camera = self.pilot.camera
        self.carving = CarvingWorker(config.carving, self.camera, config.station.carve_max_position_std, self._on_carving)
        self.frames_received = 0
        self.frames_processed = 0
        self.latencies: List[float] = []  # frame arrival -> command sent, s (benchmark)
        self.plan_times: List[float] = []  # duration of each replan, s (benchmark)
        t = clock()
        log.json(INFO, info_bytes, t, json_schema(Info))
        log.json(CONFIG, config_record(config), t, STATION_SCHEMA)
        log.proto(SCENE_LANDMARKS, foxglove.landmarks(t, config.landmarks), t)
        self._keyframe_poses: List[np.ndarray] = []
        self._t_tick = -float("inf")
        self._interrupt_sent = False
        self._phase: Optional[Phase] = None
        self._pending: List[Tuple[Callable[..., None], Tuple[Any, ...]]] = []

    def run(self) -> RunSummary:
        t_start = self.clock()
        outcome, reason = "error", ""
        try:
            finished = False
            while not finished:
                finished = self._pass()
            outcome, reason = self.pilot.mission.outcome.value, self.pilot.mission.reason
        except Exception as exc:  # a bug must still stop the robot, keep the log and say why
            reason = f"station error: {type(exc).__name__}: {exc}"
            traceback.print_exc()
        finally:
            self._send_stop()
            self._commit()
            x, P = self.pilot.ekf.x, self.pilot.ekf.P
            carver = self.carving.finish(x, P)
            if carver is not None:
                t = self.clock()
                self.log.proto(SCENE_MODEL, foxglove.model(t, _glb(carver)), t)
            summary = RunSummary(
                outcome=outcome, reason=reason, success=outcome == Outcome.COMPLETED.value,
                frames_received=self.frames_received, frames_processed=self.frames_processed,
                duration=self.clock() - t_start, carver=carver, carving_error=self.carving.error, x=x, P=P,
            )
        return summary

    # one pass -----------------------------------------------------------------------------------

    def _pass(self) -> bool:
        period = self.config.station.control_period
        timeout = max(0.0, self._t_tick + period - self.clock())
        events = self._drain(timeout)
        newest: Optional[Received] = None
        for event in events:
            if event.kind == "state":
                self._state(event)
            elif event.kind == "truth":
                self._raw(TRUTH, event, Truth)
            elif event.kind == "bridge_lost":
                self._journal("bridge_lost", event.t)
                self._apply(self.pilot.on_bridge_lost(event.t), event.t)
        for frame in self.link.take_frames():
            decoded = self._frame_log(frame)
            if decoded is not None:
                newest = frame
                newest_decoded = decoded
        signal_name = self.interrupted()
        if signal_name and not self._interrupt_sent:
            self._interrupt_sent = True
            t = self.clock()
            self._journal("interrupt", t, signal=signal_name)
            self._apply(self.pilot.on_interrupt(t, signal_name), t)
        if newest is not None:
            t = self.clock()
            self._journal("frame", t, seq=newest_decoded.meta.seq)
            self.frames_processed += 1
            self._apply(self.pilot.on_frame(newest_decoded, t), t)
        t = self.clock()
        finished = False
        if t >= self._t_tick + period or (newest is not None and t >= self._t_tick + 0.5 * period):
            self._t_tick = t
            self._journal("tick", t)
            finished = self._apply(self.pilot.tick(t), t)
            if newest is not None:
                self.latencies.append(self.clock() - newest.t)
            t_plan = self.clock()
            plan = self.pilot.replan(t)
            if plan.outputs:
                self.plan_times.append(self.clock() - t_plan)
            self._apply(plan, t)
        self._commit()
        self.log.maybe_flush()
        return finished

    def _later(self, write: Callable[..., None], *args: Any) -> None:
        """Queue a log write (in order) until the pass's commands are out: logging never delays them."""
        self._pending.append((write, args))

    def _commit(self) -> None:
        pending, self._pending = self._pending, []
        for write, args in pending:
            write(*args)

    def _drain(self, timeout: float) -> List[Received]:
        events: List[Received] = []
        try:
            events.append(self.link.inbox.get(timeout=timeout))
            while True:
                events.append(self.link.inbox.get_nowait())
        except queue.Empty:
            pass
        return events

    # inputs -------------------------------------------------------------------------------------

    def _state(self, event: Received) -> None:
        state = self._raw(STATE, event, State)
        if state is not None:
            self._journal("state", event.t)
            self._apply(self.pilot.on_state(state, event.t), event.t)

    def _raw(self, topic: str, event: Received, cls: type) -> Any:
        try:
            message = decode(event.payload, cls)
        except ProtocolError as exc:
            self._later(self.log.json, REJECTED, {"t": event.t, "topic": topic, "reason": exc.reason, "detail": str(exc)}, event.t, STATION_SCHEMA)
            return None
        self._later(self.log.json, topic, event.payload, event.t, json_schema(cls))
        return message

    def _frame_log(self, event: Received) -> Optional[Frame]:
        self.frames_received += 1
        try:
            frame = decode_frame(event.payload)
        except ProtocolError as exc:
            self._later(self.log.json, REJECTED, {"t": event.t, "topic": FRAME_META, "reason": exc.reason, "detail": str(exc)}, event.t, STATION_SCHEMA)
            return None
        self._later(self.log.json, FRAME_META, frame.meta_json, event.t, json_schema(type(frame.meta)))
        self._later(self.log.proto, FRAME_IMAGE, foxglove.compressed_image(frame.meta.stamp, frame.jpeg), event.t)
        if self.frames_received == 1:
            self._later(self.log.proto, CALIBRATION, foxglove.camera_calibration(frame.meta.stamp, self.camera), event.t)
        return frame

    def _journal(self, kind: str, t: float, **extra: Any) -> None:
        self._later(self.log.json, INPUT, {"kind": kind, "t": t, **extra}, t, STATION_SCHEMA)

    # outputs ------------------------------------------------------------------------------------

    def _apply(self, step: Step, t: float) -> bool:
        for topic, payload in step.outputs:
            self._later(self.log.json, topic, payload, t, {"title": f"agent{topic.replace('/', '.')}", "type": "object"})
            self._later(self._visualize, topic, payload, t)
        if step.keyframe is not None:
            mask, T_WC = step.keyframe
            self.carving.submit(mask, T_WC, self.pilot.ekf.x, self.pilot.ekf.P)
            self._keyframe_poses.append(T_WC)
            poses = list(self._keyframe_poses)
            self._later(lambda: self.log.proto(SCENE_KEYFRAMES, foxglove.frusta(t, self.camera, poses), t))
        decision = step.decision
        if decision is None:
            return False
        if decision.phase is not self._phase:
            self._phase = decision.phase
            print(f"station: phase {decision.phase.value}", file=sys.stderr, flush=True)
        if decision.walk is not None:
            self._send_walk(*decision.walk)
        if decision.head is not None:
            self._send_head(*decision.head)
        return decision.finished

    def _visualize(self, topic: str, payload: Dict[str, Any], t: float) -> None:
        """Foxglove views of an agent output (runs inside ``_commit``: writes directly)."""
        if topic == EKF and payload["x"] is not None:
            self.log.proto(SCENE_OBJECT, foxglove.object_estimate(t, np.asarray(payload["x"]), np.asarray(payload["P"])), t)
        elif topic == POSE:
            T_WB, T_odom_B = planar_transform(*payload["pose"]), planar_transform(*payload["odom"])
            T_BC = invert(T_WB) @ np.asarray(payload["T_WC"]).reshape(4, 4)
            self.log.proto(TF, foxglove.frame_transforms(payload["stamp"], T_WB @ invert(T_odom_B), T_odom_B, T_BC), t)

    def _send_walk(self, vx: float, vy: float, omega: float) -> None:
        command = self.link.send_walk(vx, vy, omega, self.config.station.walk_ttl)
        t = self.clock()
        self._later(self.log.json, CMD_WALK, encode(command), t, json_schema(WalkCommand))

    def _send_head(self, yaw: float, pitch: float) -> None:
        yaw, pitch = self.pilot.robot.head.clamp(yaw, pitch)
        command = self.link.send_head(yaw, pitch, self.config.station.head_speed)
        t = self.clock()
        self._later(self.log.json, CMD_HEAD, encode(command), t, json_schema(HeadCommand))

    def _send_stop(self) -> None:
        try:
            self._send_walk(0.0, 0.0, 0.0)
        except Exception:  # noqa: BLE001 - the link may be gone; the bridge's deadman stops the robot
            pass

    def _on_carving(self, metrics, views: int) -> None:
        t = self.clock()
        self.log.json(CARVING, {"t": t, "views": views, "metrics": dataclasses.asdict(metrics)}, t, STATION_SCHEMA)


def _glb(carver) -> bytes:
    return carver.to_mesh().export(file_type="glb")
