"""The agent pipeline the station runs, as a deterministic function of the logged inputs.

Inputs, each stamped with the station time t at which it was processed: robot states, frames,
control ticks, the bridge going away, interrupts. The live loop (:mod:`station.run`) and the
replay (:mod:`station.replay`) feed the same inputs in the same order to a fresh ``Pilot`` and
must get the same outputs: nothing here reads a clock, a random source without a fixed seed, or
anything not passed in.

Per frame (capture time s, head kinematics T_BC and odometry at capture, in the frame's meta)::

    image = imdecode(JPEG);  localizer.on_frame(...);  pose = localizer.pose_at(odom at capture)
    T_WC = T_WB(pose) T_BC;  cam = (C_x, C_y, psi(T_WC))                 camera on the floor plane
    silhouette = extract_silhouette(image, predicted pixel of the estimate)
    (phi, delta) = measure_object(silhouette, camera, T_WC)               delta None when cut by a border
    EKF: predict(s - s_prev), then update(cam, phi, delta), or initialize on the first measurement
    coverage.add(cam);  keyframe iff the whole silhouette was measured and the viewing azimuth
    a = atan2(C - o) differs from every earlier keyframe's by >= keyframe_min_angle

Per tick: the mission decides (:mod:`agent.mission`); in ACTIVE the walk command is the current
plan's first command, re-sent every tick (the bridge's deadman), and the head follows the head
servo's target (the estimate's direction blended with the last silhouette centroid). Then, once the tick's commands are out (planning never delays them), every
``planner.period`` in ACTIVE the planner's termination test runs (goal reached ->
``mission.on_goal``, the next tick stops the robot), else it replans (the new command goes out on
the next tick).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import cv2
import numpy as np

from agent.camera import CameraModel, optical_axis_heading
from agent.coverage import Coverage
from agent.ekf import ObjectEKF
from agent.head_servo import head_target
from agent.localization import RobotLocalizer
from agent.mission import Decision, Mission, Phase
from agent.perception import extract_silhouette, measure_object
from agent.planner import Planner, termination_reason
from nao_core.geometry import camera_in_world, wrap_angle
from nao_core.protocol import Frame, Info, State
from nao_core.robot_model import RobotModel
from station.config import StationConfig
from station.topics import (
    COVERAGE,
    DECISION,
    EKF,
    FRAME_REJECTED,
    KEYFRAME,
    MEASUREMENT,
    PLAN,
    POSE,
)

Output = Tuple[str, Dict[str, Any]]


@dataclass
class Step:
    """What one input produced: log outputs, a decision to act on, a view for the carver."""

    outputs: List[Output] = field(default_factory=list)
    decision: Optional[Decision] = None
    keyframe: Optional[Tuple[np.ndarray, np.ndarray]] = None  # (silhouette mask, T_WC)


def camera_from_info(info: Info) -> CameraModel:
    return CameraModel.from_intrinsics(info.intrinsics)


class Pilot:
    def __init__(self, config: StationConfig, info: Info):
        self.config = config
        self.robot: RobotModel = info.robot
        self.camera = camera_from_info(info)
        self.mission = Mission(config.mission)
        self.ekf = ObjectEKF(config.ekf)
        self.planner = Planner.for_robot(config.planner, self.robot, info.resolution, ekf=config.ekf)
        self.coverage = Coverage(config.planner.coverage, self.camera.hfov)
        self.localizer = RobotLocalizer(config.localization, config.landmarks, self.camera, config.perception)
        self.pose: Optional[Tuple[float, float, float]] = None
        self.command: Tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._t_plan: Optional[float] = None
        self._t_active: Optional[float] = None
        self._last_capture: Optional[float] = None
        self._keyframe_azimuths: List[float] = []
        self._sighting: Optional[Tuple[Tuple[float, float], Tuple[float, float]]] = None  # centroid, head at capture

    # inputs -----------------------------------------------------------------------------------

    def on_state(self, state: State, t: float) -> Step:
        self.localizer.on_odometry(state.odom, state.stamp)
        self.mission.on_state(t, state.fallen, state.walking, state.head_yaw, state.head_pitch)
        return Step()

    def on_frame(self, frame: Frame, t: float) -> Step:
        meta = frame.meta
        image = cv2.imdecode(np.frombuffer(frame.jpeg, dtype=np.uint8), cv2.IMREAD_COLOR)
        if image is None or image.shape[:2] != (self.camera.height, self.camera.width):
            return Step([(FRAME_REJECTED, {"t": t, "seq": meta.seq, "reason": "JPEG does not decode to the camera's image size"})])
        T_BC = np.asarray(meta.T_BC, dtype=float).reshape(4, 4)
        fix = self.localizer.on_frame(image, T_BC, meta.odom, meta.stamp)
        self.pose = self.localizer.pose_at(meta.odom)  # at capture time
        step = Step()
        object_seen = False
        if self.pose is not None:
            T_WC = camera_in_world(self.pose, T_BC)
            cam = (float(T_WC[0, 3]), float(T_WC[1, 3]), optical_axis_heading(T_WC))
            step.outputs.append((POSE, {"t": t, "seq": meta.seq, "stamp": meta.stamp, "pose": list(self.pose),
                                        "odom": list(meta.odom), "landmark_fix": fix is not None, "T_WC": T_WC.ravel().tolist()}))
            predicted = self._predicted_pixel(T_WC)
            silhouette = extract_silhouette(image, self.config.perception, predicted)
            measurement = None if silhouette is None else measure_object(silhouette, self.camera, T_WC, self.config.perception)
            self._sighting = None
            if measurement is not None:
                object_seen = True
                self._sighting = (silhouette.centroid, (meta.head_yaw, meta.head_pitch))
                self._filter(step, t, meta.seq, meta.stamp, cam, measurement)
                if silhouette.width_valid:
                    self._maybe_keyframe(step, t, meta.seq, cam, silhouette.mask, T_WC, predicted)
            self.coverage.add(np.asarray(cam))
            if self.ekf.initialized:
                step.outputs.append((COVERAGE, {"t": t, "fraction": self.coverage.fraction(self.ekf.x)}))
        self.mission.on_frame(t, object_seen, fix is not None, self.pose is not None)
        return step

    def on_bridge_lost(self, t: float) -> Step:
        self.mission.on_bridge_lost(t)
        return Step()

    def on_interrupt(self, t: float, signal_name: str) -> Step:
        self.mission.on_interrupt(t, signal_name)
        return Step()

    def tick(self, t: float) -> Step:
        """The mission's decision for now; in ACTIVE the current plan's command and the head target."""
        decision = self.mission.tick(t)
        if decision.phase is Phase.ACTIVE:
            centroid, head_at_capture = self._sighting if self._sighting else (None, None)
            head = head_target(self.robot, self.pose, self.ekf.x, self.config.perception, centroid, self.camera, head_at_capture)
            decision = Decision(decision.phase, walk=self.command, head=head)
        return Step([(DECISION, {
            "t": t, "phase": decision.phase.value, "walk": decision.walk, "head": decision.head, "stop": decision.stop,
            "outcome": decision.outcome.value if decision.outcome else None, "reason": decision.reason,
        })], decision=decision)

    def replan(self, t: float) -> Step:
        """After the tick's commands are sent: every planner period in ACTIVE, the termination test
        (goal reached -> the next tick stops the robot) or a new plan (its command goes out next tick)."""
        step = Step()
        if self.mission.phase is Phase.ACTIVE:
            self._control(step, t)
        return step

    # helpers ----------------------------------------------------------------------------------

    def _filter(self, step: Step, t: float, seq: int, stamp: float, cam, measurement) -> None:
        if self.ekf.initialized:
            self.ekf.predict(max(stamp - (self._last_capture or stamp), 0.0))
            result = self.ekf.update(cam, measurement.phi, measurement.delta)
        else:
            result = self.ekf.initialize(cam, measurement.phi, measurement.delta)
        self._last_capture = stamp
        step.outputs.append((MEASUREMENT, {
            "t": t, "seq": seq, "cam": list(cam), "phi": measurement.phi, "delta": measurement.delta,
            "accepted": result.accepted, "nis": result.nis, "reason": result.reason,
        }))
        step.outputs.append((EKF, {"t": t, **self.ekf.snapshot()}))

    def _predicted_pixel(self, T_WC: np.ndarray) -> Optional[Tuple[float, float]]:
        """Where the estimate's centre (at the servo's aim height) should appear, to pick the right blob."""
        if not self.ekf.initialized:
            return None
        x = self.ekf.x
        uv, in_front = self.camera.project_world(np.array([[x[0], x[1], self.config.perception.aim_height]]), T_WC)
        return (float(uv[0, 0]), float(uv[0, 1])) if in_front[0] else None

    def _maybe_keyframe(self, step: Step, t: float, seq: int, cam, mask: np.ndarray, T_WC: np.ndarray,
                        predicted: Optional[Tuple[float, float]]) -> None:
        if not self.ekf.initialized:
            return
        azimuth = math.atan2(cam[1] - self.ekf.x[1], cam[0] - self.ekf.x[0])
        gap = min((abs(wrap_angle(azimuth - a)) for a in self._keyframe_azimuths), default=math.inf)
        if gap < self.config.station.keyframe_min_angle:
            return
        self._keyframe_azimuths.append(azimuth)
        step.keyframe = (mask, T_WC)
        step.outputs.append((KEYFRAME, {"t": t, "seq": seq, "azimuth": azimuth, "T_WC": T_WC.ravel().tolist(),
                                        "predicted_uv": predicted}))

    def _control(self, step: Step, t: float) -> None:
        if self._t_active is None:
            self._t_active = t
        if self._t_plan is not None and t - self._t_plan < self.config.planner.period - 1e-9:
            return
        if not self.ekf.initialized:
            return
        self._t_plan = t
        x, P = self.ekf.x, self.ekf.P
        fraction = self.coverage.fraction(x)
        reason = termination_reason(fraction, P, t - self._t_active, self.config.planner.termination)
        if reason is not None and reason.startswith("complete"):  # the time limit is the mission's
            self.mission.on_goal(t, reason)
            return
        plan = self.planner.plan(np.asarray(self.pose), x, P, self.coverage)
        self.command = plan.command
        step.outputs.append((PLAN, {
            "t": t, "omegas": plan.omegas.tolist(), "command": list(plan.command), "cost": plan.cost,
            "terms": plan.terms, "evaluations": plan.evaluations, "coverage": fraction,
        }))
