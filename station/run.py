"""The live control loop: bridge link in, agent (:class:`station.pilot.Pilot`) in the middle,
commands out, everything into the MCAP log; then stop, final carve and outputs.

One pass of the loop (single thread; Zenoh callbacks only enqueue):

    wait for the inbox (at most until the next tick is due)
    drain it: states -> pilot; truth -> log; bridge lost -> pilot; frames -> log all, keep the newest
    an interrupt flag set by SIGINT/SIGTERM -> pilot
    newest frame -> pilot (per-frame pipeline), keyframes -> carving worker
    tick due (t >= t_last_tick + control_period), or a frame just processed and half a period
    passed -> ``Tick`` -> walk and head commands sent, the walk command with its TTL;
    then ``Replan`` (the planner, when due: never delays the tick's commands)
    flush the log about once a second

Every event handed to ``Pilot.handle`` (:mod:`station.events`) is journalled on
``/station/input`` right after its raw bytes, so replay feeds the same events in the same order.
The log writes of a pass are queued and written, in order, once its commands are sent. Every
decision with ``stop`` sends a zero walk command; the robot is stopped before the loop returns, on
every path: an exception from the pilot is logged on ``/station/error`` (with its traceback) and
ends the run with outcome ``error``; a final carve that raises is reported in ``carving_error``.
The final carve takes the keyframes' poses from ``Pilot.smoothed_keyframes`` (those without a fix
on their frame smoothed over the whole walk, agent/pose_smoother.py), logged on
``/station/keyframe_poses``; when smoothing fails, the poses they were taken with.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import sys
import traceback
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Tuple

import numpy as np

from agent.mesh import Z_UP_TO_Y_UP
from agent.mission import Outcome, Phase
from nao_core.clock import now
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
from station.events import LIVELINESS_LOST, BridgeLost, Event, FrameReceived, Interrupted, JournalEntry, Replan, StateReceived, Tick
from station.link import BridgeLink, Received
from station.mcap_log import McapLog
from station.outputs import EkfRecord, MeasurementRecord, PoseRecord, Record
from station.pilot import Pilot, Step
from station.runlog import config_record, pilot_sources  # noqa: F401 - pilot_sources: the digest's file list
from station.topics import (
    ANNOTATIONS,
    CALIBRATION,
    CARVING,
    CMD_HEAD,
    CMD_WALK,
    CONFIG,
    ESTIMATE,
    ERROR,
    FRAME_IMAGE,
    FRAME_META,
    INFO,
    INPUT,
    KEYFRAME_POSES,
    REJECTED,
    SCENE_KEYFRAMES,
    SCENE_LANDMARKS,
    SCENE_MODEL,
    SCENE_OBJECT,
    STATE,
    TF,
    TRAJECTORY,
    TRUTH,
)

STATION_SCHEMA = {"title": "station.Json", "type": "object"}
log = logging.getLogger("station.run")


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
    dropped: dict = dataclasses.field(default_factory=dict)  # frames the pilot dropped, by failing step


class ControlLoop:
    def __init__(self, config: StationConfig, link: BridgeLink, info: Info, info_bytes: bytes, log: McapLog,
                 interrupted: Callable[[], Optional[str]], clock: Callable[[], float] = now):
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
        self._trajectory: List[Tuple[float, ...]] = []
        self._estimate: Optional[Tuple[float, float]] = None

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
            t = self.clock()
            self._later(self.log.json, ERROR, {"t": t, "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()},
                        t, STATION_SCHEMA)
        finally:
            self._send_stop()
            self._commit()
            x, P = self.pilot.ekf.x, self.pilot.ekf.P
            carver, carving_error = self._final_carve(x, P)
            summary = RunSummary(
                outcome=outcome, reason=reason, success=outcome == Outcome.COMPLETED.value,
                frames_received=self.frames_received, frames_processed=self.frames_processed,
                duration=self.clock() - t_start, carver=carver, carving_error=carving_error, x=x, P=P,
                dropped=dict(self.pilot.dropped),
            )
        return summary

    def _final_carve(self, x: Optional[np.ndarray], P: Optional[np.ndarray]) -> Tuple[Any, Optional[str]]:
        """The final model, or None and why: whatever the carver raises, the run's outputs are written."""
        try:
            carver = self.carving.finish(x, P, self._smoothed_keyframes())
            if carver is not None:
                t = self.clock()
                self.log.proto(SCENE_MODEL, foxglove.model(t, _glb(carver)), t)
            return carver, self.carving.error
        except Exception as exc:  # noqa: BLE001 - the result must be written whatever the carver did
            traceback.print_exc()
            return None, f"final carving failed: {type(exc).__name__}: {exc}"

    def _smoothed_keyframes(self) -> dict:
        """The keyframes' T_WC for the final carve by frame seq (``Pilot.smoothed_keyframes``), logged; {}
        (the poses they were taken with) when the smoothing raises."""
        try:
            poses = self.pilot.smoothed_keyframes()
        except Exception as exc:  # noqa: BLE001 - the model is still carved, from the filter's poses
            log.warning("keyframe poses not smoothed: %s: %s", type(exc).__name__, exc)
            return {}
        t = self.clock()
        self.log.json(KEYFRAME_POSES, {"t": t, "keyframes": [{"seq": seq, "T_WC": np.asarray(T).ravel().tolist()}
                                                              for seq, T in sorted(poses.items())]}, t, STATION_SCHEMA)
        return poses

    # one pass -----------------------------------------------------------------------------------

    def _pass(self) -> bool:
        period = self.config.station.control_period
        timeout = max(0.0, self._t_tick + period - self.clock())
        newest: Optional[Frame] = None
        for received in self._drain(timeout):
            if received.kind == "state":
                state = self._raw(STATE, received, State)
                if state is not None:
                    self._handle(StateReceived(received.t, state))
            elif received.kind == "truth":
                self._raw(TRUTH, received, Truth)
            elif received.kind == "bridge_lost":
                self._handle(BridgeLost(received.t, received.payload.decode("utf-8", "replace") or LIVELINESS_LOST))
        for received in self.link.take_frames():
            newest = self._frame_log(received) or newest
        signal_name = self.interrupted()
        if signal_name and not self._interrupt_sent:
            self._interrupt_sent = True
            self._handle(Interrupted(self.clock(), signal_name))
        if newest is not None:
            self.frames_processed += 1
            self._handle(FrameReceived(self.clock(), newest))
        t = self.clock()
        finished = False
        if t >= self._t_tick + period or (newest is not None and t >= self._t_tick + 0.5 * period):
            self._t_tick = t
            finished = self._apply(self._handle(Tick(t)), t)
            if newest is not None:
                self.latencies.append(self.clock() - self._frame_arrival)
            t_plan = self.clock()
            plan = self._handle(Replan(t))
            if plan.outputs:
                self.plan_times.append(self.clock() - t_plan)
            self._apply(plan, t)
        self._commit()
        self.log.maybe_flush()
        return finished

    def _handle(self, event: Event) -> Step:
        """Journal an event and hand it to the pilot; states, frames and events are acted on at once,
        ticks and replans by the caller (it times them)."""
        self._later(self.log.json, INPUT, JournalEntry.of(event).to_json(), event.t, JournalEntry.schema())
        step = self.pilot.handle(event)
        if not isinstance(event, (Tick, Replan)):
            self._apply(step, event.t)
        return step

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
        self._frame_arrival = event.t
        return frame

    # outputs ------------------------------------------------------------------------------------

    def _apply(self, step: Step, t: float) -> bool:
        for record in step.outputs:
            self._later(self.log.json, record.TOPIC, record.to_json(), t, record.schema())
            self._later(self._visualize, record, t)
        self._later(self._annotate, step, t)
        if step.keyframe is not None:
            view = step.keyframe
            self.carving.submit(view.mask, view.T_WC, view.x, view.P, view.image, view.quality, view.camera, view.seq)
            self._keyframe_poses.append(view.T_WC)
            poses = list(self._keyframe_poses)
            self._later(lambda: self.log.proto(SCENE_KEYFRAMES, foxglove.frusta(t, self.camera, poses), t))
        decision = step.decision
        if decision is None:
            return False
        if decision.phase is not self._phase:
            self._phase = decision.phase
            log.info("phase %s", decision.phase.value)
        if decision.walk is not None:
            self._send_walk(*decision.walk)
        if decision.head is not None:
            self._send_head(*decision.head, decision.head_speed or self.config.station.head_speed)
        return decision.finished

    def _visualize(self, record: Record, t: float) -> None:
        """Foxglove views of an agent output (runs inside ``_commit``: writes directly)."""
        if isinstance(record, EkfRecord) and record.x is not None:
            self.log.proto(SCENE_OBJECT, foxglove.object_estimate(t, np.asarray(record.x), np.asarray(record.P)), t)
            self.log.json(ESTIMATE, foxglove.estimate(t, record.x, record.P), t, foxglove.ESTIMATE_SCHEMA)
        elif isinstance(record, PoseRecord):
            T_WB, T_odom_B = planar_transform(*record.pose), planar_transform(*record.odom)
            T_BC = np.asarray(record.T_BC).reshape(4, 4)
            self.log.proto(TF, foxglove.frame_transforms(record.stamp, T_WB @ invert(T_odom_B), T_odom_B, T_BC), t)

    def _annotate(self, step: Step, t: float) -> None:
        """After a frame's step: the robot's trajectory and the frame's image annotations (station.foxglove)."""
        records = {type(r): r for r in step.outputs}
        pose, measurement, ekf = records.get(PoseRecord), records.get(MeasurementRecord), records.get(EkfRecord)
        if ekf is not None and ekf.x is not None:
            self._estimate = (ekf.x[0], ekf.x[1])
        if pose is None:
            return
        self._trajectory.append(tuple(pose.pose))
        self.log.proto(TRAJECTORY, foxglove.trajectory(t, self._trajectory), t)
        mask = step.keyframe.mask if step.keyframe is not None else None  # the silhouette the carver gets
        view = foxglove.frame_view(pose, measurement, self._estimate, mask, self.config.landmarks,
                                   self.config.head_servo.aim_height)
        self.log.proto(ANNOTATIONS, foxglove.image_annotations(pose.stamp, self.camera, view), t)

    def _send_walk(self, vx: float, vy: float, omega: float) -> None:
        command = self.link.send_walk(vx, vy, omega, self.config.station.walk_ttl)
        t = self.clock()
        self._later(self.log.json, CMD_WALK, encode(command), t, json_schema(WalkCommand))

    def _send_head(self, yaw: float, pitch: float, speed: float) -> None:
        yaw, pitch = self.pilot.robot.head.clamp(yaw, pitch)
        command = self.link.send_head(yaw, pitch, speed)
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
    """The model as GLB, y up like the model.glb file (glTF's convention: Foxglove turns it z up)."""
    mesh = carver.to_mesh()
    mesh.apply_transform(Z_UP_TO_Y_UP)
    return mesh.export(file_type="glb")
