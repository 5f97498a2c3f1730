"""The agent pipeline the station runs, as a deterministic function of its input events.

``Pilot.handle(event) -> Step`` is the one entry point (events in :mod:`station.events`, output
records in :mod:`station.outputs`). The live loop (:mod:`station.run`) and the replay
(:mod:`station.replay`) hand the same events in the same order to a fresh ``Pilot`` and must get
the same outputs: nothing here reads a clock, a random source without a fixed seed, or anything
not passed in.

Per frame (capture time s, head kinematics T_BC and odometry at capture, in the frame's meta),
each step guarded: a step that raises drops the frame (``/agent/frame_rejected``: step, error,
failures in a row; counted in ``dropped``) and the mission counts it (:mod:`agent.mission`)::

    decode:        image = imdecode(JPEG) at the camera's size, in light through the camera's inverse
                   tone curve when it has one (docs/frames.md, "The camera's tone curve")
    localization:  localizer.on_frame(...);  pose = localizer.pose_at(odom at capture), or the
                   odometry itself before the first landmark fix (the odometry frame)
    T_WC = T_WB(pose) T_BC;  cam = (C_x, C_y, psi(T_WC))                 camera on the floor plane
    calibration:   a fix made standing is stored by agent/self_calibration.py; an estimate applied
                   switches the camera of every step to the corrected intrinsics (/agent/self_calibration)
    perception:    silhouette, (phi, delta) (delta None when cut by a side border), the distance
                   the image gives (agent/clearance.py), and, with the base in view, its floor
                   contact: the depression atan2(C_z, d_floor) of the silhouette's lowest row
    filter:        EKF predict(s - s_prev), then update(cam, phi, delta, C_cam), or initialize, with
                   C_cam = J P_t J^T + diag(0, 0, (w sigma_s)^2) from the localizer's total_covariance P_t
                   (agent/ekf.py) and the camera's turn rate w in O since the last frame: a frame's
                   stamp is off by sigma_s = max(``stamp_sigma``, the frame's ``stamp_std``) (an
                   exposure's offset, a latency not yet learnt: the bridge says which, docs/frames.md),
                   which turns the camera's heading by w times it; the filter starts
                   only from a camera turning slower than ``start_max_turn_rate`` (a bare NAOqi's
                   frames, late by 0.14 s before its latency was learnt, started matrix world 0's
                   filter 0.1 rad off from a head turning at 0.6 rad/s, and it gated every good view after);
                   the floor contact fused into a start (agent/ekf.py: the range a radius prior
                   left 3x off, matrix world 11, docs/estimation.md "Floor contact");
                   none once the mission has decided (DONE, STOPPING: the same view again and again
                   while the robot stops must not move, let alone re-initialize, the estimate decided on)
    coverage, keyframe (once anchored): coverage.add(cam); keyframe iff the whole silhouette was
                   measured and agent.keyframes.KeyframePool keeps it: its viewing azimuth
                   a = atan2(C - o) differs from every earlier keyframe's by >= keyframe_min_angle,
                   or its quality (pose precision x silhouette) doubles every one's near it (the
                   pose's heading variance includes the filter's (w sigma_s)^2: a turning camera's
                   stamp error misplaces its silhouette as a heading error does); a
                   keyframe whose frame gave a landmark fix of detected markers (none tracked:
                   agent/marker_tracking.py) gets its camera pose refined in 6-DOF against that
                   fix's points (agent/keyframe_pose.py); at the end the planar pose of every
                   keyframe without one is smoothed over all fixes (``smoothed_keyframes``,
                   agent/pose_smoother.py)

Re-anchoring: every filter measurement is also kept with its camera in the odometry frame O (the
last ``VIEWS_KEPT``); before the first fix the filter runs in O. At the first fix, with the
correction T_WO = pose_W (+) odom^-1, each kept measurement is moved into W (cam_xy <- T_WO cam_xy,
psi += theta_WO; phi, relative to psi, is unchanged) and the filter is rebuilt from them in order:
the estimate of the odometry frame becomes the same estimate in W. The same happens when a fix
moves the pose by more than ``mission.relocalize_shift`` (m, or rad of heading) before the mission
has decided: a wrong fix (a cold colour hypothesis on the far side of a wall) corrected; the
estimate built on it is rebuilt from the same views under the new correction, the coverage
likewise (measured: matrix seed 23 with the camera tilted on its mount, lost without it).
Keyframes already taken keep their cameras (a standing robot takes none before its standstill).

Per ``Tick``: the mission decides (:mod:`agent.mission`). ACTIVE starts with the self-calibration
standstill when the map can give a fix to store (agent/self_calibration.py), from the first tick
with an object estimate (a side-cut sighting alone gives none, and the scan would look away from
it): a zero walk, the head alternating between the object and the directions predicted from the
pose to show a fix to store within ``standstill_travel`` x the head's look speed of the object's
direction (agent/standstill.py: each dwell counted from the head's arrival, fixes are stored once
it has settled; the head at ``mission.lookout_head_speed``), until an estimate is applied, its time is up or a cycle of
views stored nothing; tried again ``standstill_interval`` s later while no estimate is applied,
``standstill_attempts`` in all (no keyframes meanwhile). Then in ACTIVE the walk command is the
current plan's first command (re-sent every tick: the bridge's deadman) and the head follows the
head servo's target; in LOCALIZE the robot stands and its looks are standing looks: the head
alternates, ``lookout_stand_dwell`` each at ``lookout_head_speed``, between the object (before an
estimate, its last sighting: matrix world 23 once first saw its bunny cut by the image's side,
started no filter and scanned for landmarks until the object was lost) and the next yaw of the
landmark scan more than half the field of view from the object (a one-second dwell at 1 rad/s
never got the head to a scan yaw 1.8 rad from the object: one-wall world 506 saw its wall only at
the head's yaw 1.4). After ``localize_turn_after`` s in LOCALIZE the body sweeps in place at
``search_turn_rate``, reversing whenever the object's head yaw comes within ``TURN_MARGIN`` of a
yaw limit, its looks at the scan's last yaw in the turn's direction: a look at a fixed yaw of the
turning body sweeps the room, and the object's dwells between miss less than a field of view of it
(2.5 s at 0.35 rad/s; one-wall world 508: the scan's yaws in turn never met the wall behind the
robot's shoulder). The looks then see every direction round the robot (rooms with landmarks on one wall behind the robot's back gave no fix in 30 s, docs/benchmarks.md). Before an estimate exists the head servo centres the last sighting (in ACTIVE too:
the robot stands until the filter starts).
Active localization (ACTIVE): while the localizer's position std sigma_p (dead reckoning since the
last fix, agent/localization.py) exceeds ``mission.lookout_std``, odd dwells (slot = floor(t /
gaze_dwell)) aim the head at the direction of ``localizer.best_landmark_view`` from the current pose
over the head's range (the smallest predicted fix std; the next landmark-scan yaw when no direction
predicts a fix), clamped to the head limits; even dwells and any tick with sigma_p <= lookout_std
follow the object. The decision's reason then says ``landmark lookout``. After ``lookout_stand`` s
without a fix, whatever sigma_p (the mission ends after ``landmarks_lost_timeout`` without one),
the lookouts stand still (a zero walk), since a walking camera's smeared frames show
no small marker (docs/frames.md "Exposure"), and alternate from then on with the object, the
lookout first, ``lookout_stand_dwell`` s each, so that the head gets there and settles (and back:
the mission ends when the object is unseen for ``object_lost_timeout``). A standing look searches
only the directions the head reaches in time, ``(lookout_stand_dwell - lookout_still) x head speed``
from where the head is (on both joints; the scan yaw, when none predicts a fix, is cut to it): with
the object at the head's yaw limit, the best views lay 2.7 rad away and the head never got there
(matrix seed 38, ``landmarks_lost``). In a drought every head command goes at
``lookout_head_speed`` (0.5 of the maximum against the station's 0.25: the reach is then 3 rad, and a
one-wall room's markers lay 1.8-2.7 rad from the object, docs/landmarks.md). When no direction the
head reaches predicts a fix, a standing look searches every direction round the robot the head
reaches by turning the other way or once the body has turned: body yaw y (taken as y or y +- 2 pi,
whichever is nearer the head, within the reach) is looked at by turning the body in place by
tau = y - clip(y, lo + ``TURN_MARGIN``, hi - ``TURN_MARGIN``), omega = clip((heading goal - theta) /
``TURN_TIME``, +-omega_max), the head at y - tau, unless the object's yaw minus
tau leaves the head's range [lo, hi] (one-wall rooms: the orbit kept the wall behind the robot's
shoulder, or 4 rad round the head from the object at its yaw limit, for 20 s). The turn goes on
through the object's dwell, the head on the object, until the heading is within ``TURN_DONE`` of its
goal or a fix comes: a 2.2 rad turn takes longer than a dwell at omega_max, and the planner's walk in
between turned the body back (one-wall worlds 504 and 506, ``landmarks_lost``). A standing look that gave
no fix rules out the directions within ``FRUITLESS_RADIUS`` of it until the next fix (the
prediction was wrong there: the view of matrix world 0 chosen three times in a row gave none). No
keyframe is taken while
looking away, nor after it until a frame's head at capture is within ``head_tolerance`` of the
object target or ``lookout_settle`` s have passed. Whatever the phase, a walk command that approaches the
object (v cos b + v_y sin b > 0, b its bearing in the robot frame) is cut to its turn when the
object is nearer than ``mission.min_image_distance`` to the robot's origin by the image alone, and
once anchored, one that approaches a wall the landmark map shows (agent/keep_in.py) nearer than
``mission.wall_stop``; the planner itself keeps ``planner.wall_clearance`` off them.
The image's surface point (camera C, distance d from agent/clearance.py along the measured
azimuth a) is kept in the odometry frame O, independent of the landmark pose and the filter::

    q_O = C_O + d (cos a_O, sin a_O),   a_O = a - theta_pose + theta_odom
    d_R = |q_O - (x, y)_odom|,  b = atan2(q_O - (x, y)_odom) - theta_odom     (latest odometry)

and carried by odometry while the object is out of view (a flat object near the feet leaves the
bottom of the image before the robot reaches it); the next measured sighting replaces it, unless
it is cut by the bottom border (its distance is then only an upper bound) and the kept point is
nearer. A
silhouette cut by the bottom border hides the base the floor distance needs (it is then only an
upper bound): the next head target in ACTIVE pitches down at least to the capture pitch plus the
bottom row's angle below the optical axis, pitch >= pitch_c + atan2(r_y, r_z) with r the ray of
(c_x, H - 1), which puts the old bottom row at the centre and the base back in view. The head's
pitch limit shrinks with its yaw (the anti-collision table: 0.20 rad at a yaw of 1.53 against 0.515
straight ahead), so a base cut while the head is at that limit (within ``FACING_TOLERANCE``), at a
yaw whose limit is lower than straight ahead's, is out of the head's reach: the ACTIVE walk is then
a turn in place towards the object, omega = sign(yaw_c) omega_max, until a frame shows the base or
the head off its limit, and no self-calibration standstill starts meanwhile; only until the filter
has measured widths (its radius std below ``MEASURED_RADIUS`` of the prior's: later, an orbit's views
with the base cut still give bearings and carve, and a turn the plan did not foresee would point its
next forward step at the object). Stress world 314 (docs/benchmarks.md, "Stress worlds"): a 26 cm
bucket 0.77 m away at 87 deg, its base never in view, so no width and no range; the estimate was
1.24 m off, the clearance margin of an unknown radius turned the robot away, the object lost.
Per ``Replan`` (after the tick's commands are out: planning never delays them), every
``planner.period`` in ACTIVE: the termination test on the coverage within ``facing_margin``
(once anchored, of the bins the map's walls leave reachable, ``Planner.reachable_bins``; with
some hidden, those count as covered after ``termination.stall`` s without a new bin) (goal
reached -> ``mission.on_goal``, the next tick stops the robot), else a new plan (its command goes
out on the next tick).
"""

from __future__ import annotations

import math
from collections import Counter, deque
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Callable, Deque, Dict, Iterator, List, NamedTuple, Optional, Tuple, Type

import cv2
import numpy as np

from agent.camera import CameraModel, optical_axis_heading
from agent.clearance import floor_contact, floor_distance, image_distance
from agent.keep_in import KeepIn
from agent.landmark_reach import LandmarkReach
from agent.coverage import Coverage, seen_fraction
from agent.ekf import FloorContact, ObjectEKF, UpdateResult, measure
from agent.head_servo import ObjectHeight, head_target
from agent.keyframe_pose import refine_camera_pose
from agent.keyframes import KeyframePool, pose_quality, silhouette_quality
from agent.localization import PoseFix, RobotLocalizer, head_directions
from agent.mission import Decision, Mission, Phase
from agent.perception import ColourTally, extract_silhouette, measure_object
from agent.planner import Planner, termination_reason
from agent.self_calibration import SelfCalibration
from agent.standstill import CalibrationStandstill
from agent.tone_curve import in_light
from nao_core.geometry import Pose, camera_in_world, compose, invert, planar_transform, relative, wrap_angle
from nao_core.protocol import Info
from nao_core.robot_model import RobotModel, head_at
from station.config import StationConfig
from station.events import BridgeLost, Event, FrameReceived, Interrupted, Replan, StateReceived, Tick
from station.outputs import (
    CalibrationRecord,
    CoverageRecord,
    DecisionRecord,
    EkfRecord,
    FrameRejectedRecord,
    KeyframeRecord,
    MeasurementRecord,
    PlanRecord,
    PoseRecord,
    Record,
)

Cam = Tuple[float, float, float]
VIEWS_KEPT = 900  # filter views kept in the odometry frame for a rebuild (a minute at 15 fps)
FACING_TOLERANCE = 0.05  # rad: a head pitch this near its limit at the head's yaw is at the limit (joint tracking, sensor lag)
MEASURED_RADIUS = 0.5  # the radius std below this share of its prior: widths were measured, no facing turn
FRUITLESS_RADIUS = 0.3  # rad (yaw or pitch): head directions this near a standing look that gave no fix are not looked at again
TURN_MARGIN = 0.3  # rad inside the head's yaw limit where a body turn brings a look beyond it
TURN_TIME = 0.5  # s: a standing look's body turn closes its heading error at omega = error / TURN_TIME (at most omega_max)
TURN_DONE = 0.05  # rad: a standing look's body turn that got this near its heading is done


@dataclass(frozen=True)
class KeyframeView:
    """A view for the carver: the silhouette, the camera pose, and the estimate it was chosen with."""

    mask: np.ndarray
    T_WC: np.ndarray
    x: np.ndarray
    P: np.ndarray
    image: Optional[np.ndarray] = None  # the frame (BGR), for the model's vertex colours
    quality: float = 1.0  # agent/keyframes.py: pose precision x silhouette quality at capture
    camera: Optional[CameraModel] = None  # the intrinsics it was seen with (self-calibration), None: the bridge's
    seq: int = -1  # the frame's


class Lookout(NamedTuple):
    """A look away from the object at the landmarks (module docstring, Active localization)."""

    slot: Tuple[bool, int]  # (standing, dwell index): one search per dwell
    head: Tuple[float, float]  # (yaw, pitch) target
    heading: Optional[float] = None  # world heading the body turns to first (a look beyond the head's yaw range), else None


@dataclass
class Step:
    """What one event produced: log records, a decision to act on, a view for the carver."""

    outputs: List[Record] = field(default_factory=list)
    decision: Optional[Decision] = None
    keyframe: Optional[KeyframeView] = None


class FrameStepFailed(Exception):
    def __init__(self, step: str, error: BaseException):
        super().__init__(f"{step}: {type(error).__name__}: {error}")
        self.step, self.error = step, f"{type(error).__name__}: {error}"


@contextmanager
def guarded(step: str) -> Iterator[None]:
    """Run one per-frame step; whatever it raises becomes FrameStepFailed naming the step."""
    try:
        yield
    except Exception as exc:  # noqa: BLE001 - nothing a frame contains may end the mission
        raise FrameStepFailed(step, exc) from exc


class _View(NamedTuple):
    """One view the filter was given, kept in the odometry frame O to rebuild it (``_reanchor``)."""

    stamp: float
    cam: Cam  # (cx, cy, psi) in O
    phi: float
    delta: Optional[float]
    turn_rate: Optional[float]
    stamp_variance: float  # the camera heading's variance from its stamp error, rad^2
    floor: Optional[FloorContact]


def _surface_point(odom: Pose, T_BC: np.ndarray, distance: float, bearing: float) -> Tuple[float, float]:
    """q_O: the point ``distance`` from the camera along ``bearing`` (robot frame), in the odometry frame."""
    T_OC = camera_in_world(tuple(float(v) for v in odom), T_BC)
    azimuth = float(odom[2]) + bearing
    return float(T_OC[0, 3] + distance * math.cos(azimuth)), float(T_OC[1, 3] + distance * math.sin(azimuth))


def _moved(a: Pose, b: Pose) -> float:
    """How far pose ``a`` is from ``b``: the larger of the distance (m) and the heading change (rad)."""
    return max(math.hypot(a[0] - b[0], a[1] - b[1]), abs(wrap_angle(a[2] - b[2])))


def _flat(T: np.ndarray) -> Tuple[float, ...]:
    return tuple(float(v) for v in T.ravel())


class Pilot:
    def __init__(self, config: StationConfig, info: Info):
        self.config = config
        self.robot: RobotModel = info.robot
        self.camera = CameraModel.from_intrinsics(info.intrinsics)
        self.mission = Mission(config.mission)
        self.ekf = ObjectEKF(config.ekf)
        self.planner = Planner.for_robot(config.planner, self.robot, info.resolution, ekf=config.ekf)
        self.coverage = Coverage(config.planner.coverage, self.camera.hfov)
        self.localizer = RobotLocalizer(config.localization, config.landmarks, self.camera, config.perception)
        self.mission.landmark_note = self.localizer.detector.diagnosis  # read only when a reason needs it
        self.colours = ColourTally(config.perception, config.landmarks.ball_colors)
        self.mission.object_note = self.colours.note
        self.keep_in = KeepIn(config.landmarks)  # the walls the map shows (agent/keep_in.py)
        self.landmark_reach = LandmarkReach.from_map(config.landmarks, float(self.camera.K[0, 0]),
                                                     config.localization.aruco_min_side_px)  # the planner's c_m
        self.calibration = SelfCalibration(config.self_calibration, self.camera, self.localizer.tilt)
        self.localizer.set_intrinsics_covariance(self.calibration.covariance)
        self.standstill = CalibrationStandstill(config.self_calibration, config.mission.gaze_dwell, config.mission.head_tolerance,
                                                self.calibration.can_store_fixes_from(config.landmarks))
        self.pose: Optional[Pose] = None  # in W once anchored, else in the odometry frame
        self.anchored = False
        self.command: Tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.dropped: Counter = Counter()  # frames dropped, by the step that raised
        self._views: Deque[_View] = deque(maxlen=VIEWS_KEPT)
        self.relocalized = 0  # filters rebuilt after a fix moved the pose by more than relocalize_shift
        self._t_plan: Optional[float] = None
        self._t_active: Optional[float] = None
        self._covered: Tuple[int, float] = (0, 0.0)  # the most bins the termination saw seen, and when
        self._last_capture: Optional[float] = None
        self._keyframes = KeyframePool(self.config.station.keyframe_min_angle)
        self._keyframe_frames: Dict[int, Tuple[float, np.ndarray, bool]] = {}  # seq -> (capture stamp, T_WC taken with, a fix of detected markers on it)
        self.height = ObjectHeight()  # the object's top from the silhouettes: aim height and the planner's c_h
        self._sighting: Optional[Tuple[Tuple[float, float], Tuple[float, float]]] = None  # centroid, head at capture
        self._last_sighting: Optional[Tuple[Tuple[float, float], Tuple[float, float]]] = None  # kept while unseen
        self._near: Optional[Tuple[float, float]] = None  # the surface point q_O the last measured image gave (odometry frame)
        self._base_pitch: Optional[float] = None  # least head pitch that brings a bottom-cut base back in view
        self._facing_turn = 0.0  # rad/s: the turn in place that brings a base out of the head's reach back into it (0: none)
        ray = self.camera.pixels_to_rays(np.array([[self.camera.width / 2.0, self.camera.height - 1.0]]))[0]
        self._bottom_row_angle = math.atan2(float(ray[1]), float(ray[2]))  # bottom row below the optical axis, rad
        self._odom: Optional[Pose] = None  # latest odometry reading (robot state)
        self._directions = head_directions(self.robot.head)  # head grid the landmark lookout searches
        self._around = head_directions(replace(self.robot.head, yaw=(-math.pi, math.pi)))  # with the body turned
        self._lookout: Optional[Lookout] = None  # while looking away
        self._turn_goal: Optional[float] = None  # heading a standing look's body turn goes on to through the object's dwell
        self._sweep = -1.0  # LOCALIZE: the sign of the body's sweep (module docstring)
        self._fruitless: List[Tuple[float, float]] = []  # head targets of standing looks without a fix, this drought
        self._object_gaze: Optional[Tuple[float, float]] = None  # last head target on the object
        self._t_back: Optional[float] = None  # when the head was last sent back to the object after a lookout
        self._handlers: Dict[Type, Callable[..., Step]] = {
            StateReceived: self._on_state, FrameReceived: self._on_frame, Tick: self._on_tick, Replan: self._on_replan,
            BridgeLost: self._on_bridge_lost, Interrupted: self._on_interrupt,
        }

    def handle(self, event: Event) -> Step:
        """The pilot's response to one input event."""
        return self._handlers[type(event)](event)

    # events -----------------------------------------------------------------------------------

    def _on_state(self, event: StateReceived) -> Step:
        state = event.state
        self.localizer.on_odometry(state.odom, state.stamp)
        self._odom = tuple(float(v) for v in state.odom)
        self.mission.on_state(event.t, state.fallen, state.walking, state.head_yaw, state.head_pitch)
        return Step()

    def _on_frame(self, event: FrameReceived) -> Step:
        step = Step()
        try:
            self._frame(event, step)
        except FrameStepFailed as failure:
            self.dropped[failure.step] += 1
            self.mission.on_frame_failed(event.t, failure.step, failure.error)
            step.outputs.append(FrameRejectedRecord(event.t, event.frame.meta.seq, failure.step, failure.error,
                                                    self.mission.frame_failures))
        return step

    def _on_bridge_lost(self, event: BridgeLost) -> Step:
        self.mission.on_bridge_lost(event.t, event.reason)
        return Step()

    def _on_interrupt(self, event: Interrupted) -> Step:
        self.mission.on_interrupt(event.t, event.signal)
        return Step()

    def _on_tick(self, event: Tick) -> Step:
        """The mission's decision for now, with the pilot's walk and head where the mission leaves them."""
        t = event.t
        decision = self.mission.tick(t)
        if decision.hold:  # no frames to walk or look by: the mission's stand
            pass
        elif decision.phase is Phase.ACTIVE and self._calibration_standstill(t, start=not self._facing_turn):
            p = self.config.self_calibration
            decision = Decision(decision.phase, walk=(0.0, 0.0, 0.0), head=self.standstill.head(t, self._object_head()),
                                head_speed=self.config.mission.lookout_head_speed, reason=(
                f"self-calibration: standing for landmark views ({len(self.calibration.fixes)} of {p.min_frames} fixes, "
                f"standstill {self.standstill.attempts} of {p.standstill_attempts})"))
        elif decision.phase is Phase.ACTIVE:
            centroid, head_at_capture = self._servo_sighting()
            look = self._landmark_lookout(t)
            standing = self._drought(t) > 0.0  # frames smeared by walking show no small marker (docs/frames.md "Exposure")
            speed = self.config.mission.lookout_head_speed if standing else None
            if look is None:
                head = head_target(self.robot, self.pose, self.ekf.x, self.config.head_servo, centroid, self.camera,
                                   head_at_capture, self.height.aim)
                if self._base_pitch is not None and head[1] < self._base_pitch:  # the base was cut: look down at it
                    head = self.robot.head.clamp(head[0], self._base_pitch)
                self._object_gaze = head
                goal = self._turn_pending() if standing and not self._facing_turn else None
                if self._facing_turn:
                    walk, reason = (0.0, 0.0, self._facing_turn), "facing the object: its base is below the head's reach at this yaw"
                elif goal is not None:
                    walk, reason = self._turn_walk(goal), f"turning to {goal:.2f} rad for the next landmark look"
                else:
                    walk, reason = self.command, ""
                decision = Decision(decision.phase, walk=walk, head=head, head_speed=speed, reason=reason)
            else:
                p = self.config.mission
                turn = "" if look.heading is None else f", turning to {look.heading:.2f} rad"
                decision = Decision(decision.phase, walk=self._turn_walk(look.heading) if standing else self.command, head=look.head,
                                    head_speed=speed, reason=(
                    f"landmark lookout: pose std {self.localizer.position_std() * 100:.1f} cm (lookout above {p.lookout_std * 100:.1f} cm)"
                    + (f"; standing: no fix for {self.mission.since_fix(t):.1f} s{turn}" if standing else "")))
        elif decision.phase is Phase.LOCALIZE:
            on_object = self._object_head() if self.ekf.initialized or self._last_sighting is not None else None
            sweep = self._localize_sweep(t, on_object)
            decision = Decision(decision.phase, walk=(0.0, 0.0, sweep) if sweep else decision.walk,
                                head=self._localize_gaze(t, sweep, on_object),
                                head_speed=self.config.mission.lookout_head_speed,
                                reason=f"sweeping for landmarks: no fix in {self.mission.in_phase(t):.0f} s of standing" if sweep else "")
        if decision.walk is not None and not decision.stop:
            decision = replace(decision, walk=self._clear(decision.walk))
        record = DecisionRecord(t, decision.phase.value, decision.walk, decision.head, decision.stop,
                                decision.outcome.value if decision.outcome else None, decision.reason)
        return Step([record], decision=decision)

    def _on_replan(self, event: Replan) -> Step:
        step = Step()
        if self.mission.phase is Phase.ACTIVE:
            self._control(step, event.t)
        return step

    # per frame --------------------------------------------------------------------------------

    def _frame(self, event: FrameReceived, step: Step) -> None:
        t, meta = event.t, event.frame.meta
        with guarded("decode"):
            image = cv2.imdecode(np.frombuffer(event.frame.jpeg, dtype=np.uint8), cv2.IMREAD_COLOR)
            if image is None or image.shape[:2] != (self.camera.height, self.camera.width):
                raise ValueError(f"JPEG does not decode to the camera's {self.camera.width} x {self.camera.height} image")
            image = in_light(image, self.robot.camera.response_gamma)
            T_BC = np.asarray(meta.T_BC, dtype=float).reshape(4, 4)
        decided = self.mission.phase in (Phase.DONE, Phase.STOPPING, Phase.FINISHED)  # the estimate decided on is the result
        with guarded("localization"):
            before = self.localizer.pose_at(meta.odom)
            fix = self.localizer.on_frame(image, T_BC, meta.odom, meta.stamp)
            T_BC = self.localizer.tilt.correct(T_BC)  # the camera on its mount, as learnt (agent/camera_tilt.py)
            world = self.localizer.pose_at(meta.odom)  # at capture time
            if world is not None and not self.anchored:
                self._reanchor(world, meta.odom)
            elif not decided and world is not None and before is not None and _moved(world, before) > self.config.mission.relocalize_shift:
                self.relocalized += 1
                self._reanchor(world, meta.odom)
                step.outputs.append(self._ekf_record(t))
            self.pose = world if world is not None else tuple(float(v) for v in meta.odom)
            T_WC = camera_in_world(self.pose, T_BC)
            cam = (float(T_WC[0, 3]), float(T_WC[1, 3]), optical_axis_heading(T_WC))
            T_OC = camera_in_world(tuple(float(v) for v in meta.odom), T_BC)
            cam_odom = (float(T_OC[0, 3]), float(T_OC[1, 3]), optical_axis_heading(T_OC))
            turn_rate = self.localizer.heading_rate()  # from this frame and the last (agent/localization.py)
            stamp_variance = self._stamp_heading_variance(turn_rate, meta.stamp_std)
        with guarded("calibration"):
            self.calibration.on_head(meta.head_yaw, meta.head_pitch, meta.stamp)
            self.standstill.on_head(t, meta.head_yaw, meta.head_pitch)
            if fix is not None:
                self.standstill.on_fix(t)
                stored = self.calibration.stored
                if self.calibration.add(fix, meta.stamp):
                    self._recalibrated(step, t)
                if self.calibration.stored != stored:
                    self.standstill.on_stored(t)
        step.outputs.append(PoseRecord(t, meta.seq, meta.stamp, self.pose, tuple(map(float, meta.odom)), fix is not None,
                                       _flat(T_WC), _flat(T_BC), self.anchored))
        with guarded("perception"):
            predicted = self._predicted_pixel(T_WC)
            silhouette = extract_silhouette(image, self.config.perception, predicted)
            if silhouette is None and self.mission.phase in (Phase.INIT, Phase.SEARCH):  # only an object never seen is named
                self.colours.look(image)
            flooded = silhouette is not None and silhouette.spans_image
            measurement = None if silhouette is None or flooded else measure_object(silhouette, self.camera, T_WC,
                                                                                   self.config.perception)
            self._sighting = self._base_pitch = floor = None
            self._facing_turn = 0.0
            if measurement is not None:
                self._sighting = self._last_sighting = (silhouette.centroid, (meta.head_yaw, meta.head_pitch))
                if silhouette.touches_bottom:
                    self._base_pitch = meta.head_pitch + self._bottom_row_angle
                    self._facing_turn = self._turn_to_reach_base(meta.head_yaw, meta.head_pitch)
                base_distance = floor_distance(silhouette, self.camera, T_WC)
                floor = floor_contact(silhouette, base_distance, float(T_WC[2, 3]))
                self.height.update(silhouette.bbox[1], silhouette.centroid[0], silhouette.touches_top, self.camera, T_WC,
                                   self.ekf.x if self.ekf.initialized else None)
                radius = self.ekf.x[2] if self.ekf.initialized else self.config.ekf.radius_prior
                distance = image_distance(silhouette, base_distance, measurement.delta, float(radius))
                if distance is not None:
                    near = _surface_point(meta.odom, T_BC, distance, measurement.azimuth - self.pose[2])
                    if not (silhouette.touches_bottom and self._near is not None
                            and math.dist(self._near, meta.odom[:2]) < math.dist(near, meta.odom[:2])):
                        self._near = near  # a bottom-cut view (an upper bound) never replaces a nearer point
        if measurement is not None and measurement.bearing_valid and not decided:  # a side-cut silhouette gives neither bearing nor width
            with guarded("filter"):
                self._filter(step, t, meta.seq, meta.stamp, cam, cam_odom, measurement.phi, measurement.delta, self._camera_covariance(cam),
                             turn_rate, stamp_variance, floor)
            if self.anchored and not self._calibration_standstill(t) and self._gaze_on_object(t, (meta.head_yaw, meta.head_pitch)):  # top/bottom-cut views still carve
                with guarded("keyframe"):
                    self._maybe_keyframe(step, t, meta.seq, meta.stamp, cam, silhouette.mask, T_WC, predicted, image, fix, stamp_variance)
        if self.anchored:
            with guarded("coverage"):
                self.coverage.add(np.asarray(cam))
                if self.ekf.initialized:
                    step.outputs.append(CoverageRecord(t, self.coverage.fraction(self.ekf.x)))
        self.mission.on_frame(t, measurement is not None, fix is not None, self.anchored, self.localizer.landmarks_seen > 0,
                              self.localizer.position_std() if self.anchored else 0.0, flooded, self._object_expected(cam))

    def _object_expected(self, cam: Cam) -> bool:
        """Was the object meant to be in this frame: no estimate yet, or the estimate's outline within the
        image's width, |phi| <= hfov / 2 + delta / 2 (agent/ekf.py ``measure``). A frame turned away from it
        (a landmark look, the self-calibration's views, the head on its way back, the body turning faster
        than the head) is not one the object was missed in (agent/mission.py: the object-lost clock does
        not count it)."""
        if not self.ekf.initialized:
            return True
        phi, delta = measure(self.ekf.x, np.asarray(cam))
        return abs(phi) <= 0.5 * (self.camera.hfov + delta)

    def _camera_covariance(self, cam: Cam) -> Optional[np.ndarray]:
        """Covariance of (cx, cy, psi) from the localizer's pose covariance at this capture (with the
        intrinsics' share, which fixes do not average out), through the camera's lever arm:
        d(cx, cy, psi)/d(x, y, theta) = [[1, 0, -(cy - y)], [0, 1, cx - x], [0, 0, 1]]. None in the
        odometry frame (unanchored views are exact relative to the start) or without a finite covariance."""
        P = self.localizer.total_covariance
        if not self.anchored or not np.all(np.isfinite(P)):
            return None
        J = np.array([[1.0, 0.0, self.pose[1] - cam[1]], [0.0, 1.0, cam[0] - self.pose[0]], [0.0, 0.0, 1.0]])
        return J @ P @ J.T

    def _stamp_heading_variance(self, turn_rate: Optional[float], stamp_std: float) -> float:
        """rad^2: the camera heading's variance from a stamp off by max(``stamp_sigma``, ``stamp_std``)
        while the camera turns at ``turn_rate`` (unknown: 0) (module docstring)."""
        return ((turn_rate or 0.0) * max(self.config.station.stamp_sigma, stamp_std)) ** 2

    def _filter(self, step: Step, t: float, seq: int, stamp: float, cam: Cam, cam_odom: Cam, phi: float, delta: Optional[float],
                cam_cov: Optional[np.ndarray], turn_rate: Optional[float], stamp_variance: float, floor: Optional[FloorContact]) -> None:
        self._views.append(_View(stamp, cam_odom, phi, delta, turn_rate, stamp_variance, floor))
        result = self._observe(stamp, cam, phi, delta, turn_rate, stamp_variance, floor, cam_cov)
        step.outputs.append(MeasurementRecord(t, seq, cam, float(phi), None if delta is None else float(delta),
                                              result.accepted, None if result.nis is None else float(result.nis), result.reason))
        step.outputs.append(self._ekf_record(t))

    def _observe(self, stamp: float, cam: Cam, phi: float, delta: Optional[float], turn_rate: Optional[float],
                 stamp_variance: float, floor: Optional[FloorContact], cam_cov: Optional[np.ndarray] = None) -> UpdateResult:
        """Update the filter, or start it (from a camera known to turn slowly, with the view's floor
        contact); ``stamp_variance``, the camera's turn over the stamp's error, widens its heading's
        variance (module docstring)."""
        c = self.config.station
        if self.ekf.initialized:
            self.ekf.predict(max(stamp - (self._last_capture or stamp), 0.0))
            turn = np.diag([0.0, 0.0, stamp_variance])
            result = self.ekf.update(cam, phi, delta, turn if cam_cov is None else cam_cov + turn, floor)
        elif turn_rate is None:
            return UpdateResult(False, None, 0, None, "no start from a camera whose turn is not known yet")
        elif turn_rate > c.start_max_turn_rate:
            return UpdateResult(False, None, 0, None, f"no start from a camera turning at {turn_rate:.2f} rad/s "
                                                      f"(above {c.start_max_turn_rate:g})")
        else:
            result = self.ekf.initialize(cam, phi, delta, floor)
        self._last_capture = stamp
        return result

    def _recalibrated(self, step: Step, t: float) -> None:
        """Every user of the camera (localizer, perception, head servo, keyframes) switches to the
        intrinsics the landmark fixes gave, the localizer to their markers' edge shift
        (agent/self_calibration.py); from the next frame on."""
        self.camera = self.localizer.camera = self.calibration.camera
        self.localizer.edge_shift = self.calibration.edge_shift
        self.localizer.set_intrinsics_covariance(self.calibration.covariance)
        applied = self.calibration.applied
        std = np.sqrt(np.diag(applied.covariance))
        step.outputs.append(CalibrationRecord(t, _flat(self.camera.K), tuple(map(float, applied.c[:4])), tuple(map(float, std[:4])),
                                              applied.frames, applied.rms, float(applied.c[4]), float(std[4])))

    def _reanchor(self, world: Pose, odom: Pose) -> None:
        """Rebuild the filter in W from the views kept in the odometry frame (module docstring)."""
        x0, y0, theta = compose(world, relative(odom, (0.0, 0.0, 0.0)))  # T_WO
        c, s = math.cos(theta), math.sin(theta)
        relocated = self.anchored
        self.anchored = True
        self.ekf = ObjectEKF(self.config.ekf)
        self._last_capture = None
        if relocated:
            self.coverage = Coverage(self.config.planner.coverage, self.camera.hfov)
        for view in self._views:
            cx, cy, psi = view.cam
            cam = (x0 + c * cx - s * cy, y0 + s * cx + c * cy, wrap_angle(psi + theta))
            self._observe(view.stamp, cam, view.phi, view.delta, view.turn_rate, view.stamp_variance, view.floor)  # phi is measured from psi: a rigid move leaves it
            if relocated:
                self.coverage.add(np.asarray(cam))

    def _ekf_record(self, t: float) -> EkfRecord:
        x, P = self.ekf.x, self.ekf.P
        return EkfRecord(t, None if x is None else tuple(map(float, x)), None if P is None else tuple(tuple(map(float, row)) for row in P),
                         {k: int(v) for k, v in self.ekf.stats.as_dict().items()})

    def _predicted_pixel(self, T_WC: np.ndarray) -> Optional[Tuple[float, float]]:
        """Where the estimate's centre (at the servo's aim height) should appear, to pick the right blob."""
        if not self.ekf.initialized:
            return None
        x = self.ekf.x
        uv, in_front = self.camera.project_world(np.array([[x[0], x[1], self.config.head_servo.aim_height]]), T_WC)
        return (float(uv[0, 0]), float(uv[0, 1])) if in_front[0] else None

    def _maybe_keyframe(self, step: Step, t: float, seq: int, stamp: float, cam: Cam, mask: np.ndarray, T_WC: np.ndarray,
                        predicted: Optional[Tuple[float, float]], image: Optional[np.ndarray] = None,
                        fix: Optional[PoseFix] = None, stamp_variance: float = 0.0) -> None:
        if not self.ekf.initialized:
            return
        azimuth = math.atan2(cam[1] - self.ekf.x[1], cam[0] - self.ekf.x[0])
        c = self.config.carving
        covariance = self.localizer.covariance + np.diag([0.0, 0.0, stamp_variance])  # a turning camera's stamp error
        quality = pose_quality(covariance, math.hypot(cam[0] - self.ekf.x[0], cam[1] - self.ekf.x[1]),
                               c.keyframe_pose_std) * silhouette_quality(mask, image, c.keyframe_cut)
        if not self._keyframes.offer(azimuth, quality):
            return
        detected = fix is not None and not fix.tracked  # a tracked marker's centre is too few points for 6 DOF (matrix world 3: 2 of them)
        if detected and fix.inliers is not None:  # the frame's own landmarks refine its camera pose (agent/keyframe_pose.py)
            loc = self.config.localization
            refined = refine_camera_pose(T_WC, *fix.inliers, self.camera.K, self._keyframe_pixel_sigma(T_WC, fix),
                                         c.keyframe_rotation_sigma, c.keyframe_position_sigma, loc.max_reprojection_px)
            T_WC = T_WC if refined is None else refined
        step.keyframe = KeyframeView(mask, T_WC, self.ekf.x.copy(), self.ekf.P.copy(), image, quality, self.camera, seq)
        self._keyframe_frames[seq] = (stamp, T_WC, detected)
        step.outputs.append(KeyframeRecord(t, seq, azimuth, _flat(T_WC), predicted, quality, _flat(self.camera.K)))

    def _keyframe_pixel_sigma(self, T_WC: np.ndarray, fix: PoseFix) -> float:
        """px: what a keyframe's landmark points are worth to its 6-DOF refinement: the fit's pixel noise or
        (whitened) residual, and the map's own error at the points' median depth, f position_sigma / z
        (agent/localization.py, Map error; the refinement holds the map exact)."""
        pixel = max(self.config.localization.pixel_sigma, fix.rms_px)
        position_sigma = self.config.landmarks.position_sigma
        if position_sigma == 0.0:
            return pixel
        depth = float(np.median((np.asarray(fix.inliers[0]) - T_WC[:3, 3]) @ T_WC[:3, 2]))
        return math.hypot(pixel, self.camera.K[0, 0] * position_sigma / max(depth, 0.1))

    def smoothed_keyframes(self) -> Dict[int, np.ndarray]:
        """T_WC of every keyframe (by frame seq) for the final carve: one without a fix on its frame has
        its planar pose smoothed over the whole walk (agent/pose_smoother.py), the T_WC it was taken with
        moved by T(p_smoothed) T(p_filtered)^-1; one with a fix keeps its own, refined against the
        frame's points, which see the camera's sway that the smoothed walk irons out (docs/carving.md)."""
        poses = {seq: T_WC for seq, (_, T_WC, fixed) in self._keyframe_frames.items() if fixed}
        if len(poses) == len(self._keyframe_frames):
            return poses  # nothing to smooth: the solve is skipped
        track = self.localizer.track
        smoothed = self.localizer.smoothed_track()
        index = {point.stamp: j for j, point in enumerate(track)}
        for seq, (stamp, T_WC, fixed) in self._keyframe_frames.items():
            if not fixed:
                j = index.get(stamp)
                poses[seq] = T_WC if j is None else planar_transform(*smoothed[j]) @ invert(planar_transform(*track[j].pose)) @ T_WC
        return poses

    # per tick ---------------------------------------------------------------------------------

    def _servo_sighting(self) -> Tuple[Optional[Tuple[float, float]], Optional[Tuple[float, float]]]:
        """(centroid, head at capture) the head servo centres: this frame's sighting, or before an
        estimate exists the last one (a silhouette cut by a side border starts no filter, and without
        an estimate the robot stands, so its head angles still hold), or (None, None)."""
        sighting = self._sighting or (None if self.ekf.initialized else self._last_sighting)
        return sighting if sighting else (None, None)

    def _turn_to_reach_base(self, yaw: float, pitch: float) -> float:
        """rad/s: the turn in place towards a bottom-cut object seen with the head at (``yaw``, ``pitch``),
        when the head is at its pitch limit there and a smaller yaw would raise it; else 0 (module docstring)."""
        head = self.robot.head
        limit = head.pitch_range(yaw)[1]
        if pitch < limit - FACING_TOLERANCE or limit >= head.pitch_range(0.0)[1] - FACING_TOLERANCE:
            return 0.0
        if self.ekf.initialized and math.sqrt(self.ekf.P[2, 2]) < MEASURED_RADIUS * self.config.ekf.radius_prior_std:
            return 0.0  # widths measured (the covariance is converted from the filter's state only here)
        return math.copysign(self.robot.walk.omega_max, yaw)

    def _object_head(self) -> Tuple[float, float]:
        """The head servo's target on the object estimate (and its sighting, :meth:`_servo_sighting`)."""
        centroid, head_at_capture = self._servo_sighting()
        return head_target(self.robot, self.pose, self.ekf.x, self.config.head_servo, centroid, self.camera, head_at_capture)

    def _localize_gaze(self, t: float, sweep: float, on_object: Optional[Tuple[float, float]]) -> Tuple[float, float]:
        """LOCALIZE: standing looks (module docstring), even ``lookout_stand_dwell`` s on the object (its
        estimate, or before one its last sighting: a silhouette cut by a side border starts no filter),
        odd ones on the next yaw of the landmark scan more than half the field of view from it; while
        the body sweeps (turn rate ``sweep``), on the scan's last yaw in the turn's direction.
        ``on_object``: the head's target on the object, None with neither estimate nor sighting."""
        p = self.config.mission
        slot = int(t // p.lookout_stand_dwell)
        if slot % 2 == 0 and on_object is not None:
            return on_object
        if sweep:
            return self.robot.head.clamp((max if sweep > 0.0 else min)(p.search_head_yaws), p.init_pitch)
        yaws = [y for y in p.search_head_yaws if on_object is None or abs(y - on_object[0]) > 0.5 * self.camera.hfov]
        yaws = yaws or list(p.search_head_yaws)
        return self.robot.head.clamp(yaws[(slot // 2) % len(yaws)], p.init_pitch)

    def _localize_sweep(self, t: float, on_object: Optional[Tuple[float, float]]) -> float:
        """LOCALIZE: the turn rate of the body's sweep (0: stand), after ``localize_turn_after`` s: at
        ``search_turn_rate``, reversed whenever the object's head yaw comes within ``TURN_MARGIN`` of a
        yaw limit, so the object stays in the head's range while the head's scan sweeps the room."""
        p = self.config.mission
        if self.mission.in_phase(t) < p.localize_turn_after or not self.ekf.initialized:
            return 0.0
        yaw, (lo, hi) = on_object[0], self.robot.head.yaw  # an estimate exists: on_object is its target
        if yaw >= hi - TURN_MARGIN:  # turning left moves the object right in the head's range
            self._sweep = 1.0
        elif yaw <= lo + TURN_MARGIN:
            self._sweep = -1.0
        return self._sweep * p.search_turn_rate

    def _views_to_calibrate(self) -> List[Tuple[float, float]]:
        """Head directions from the current pose predicted to show a fix the self-calibration stores
        (``min_points`` points of ``min_landmarks`` landmarks), most points first, at most
        ``standstill_views`` of them at least ``standstill_view_spacing`` apart in yaw (distinct
        geometry: one view's fixes repeat each other), each within ``standstill_travel`` x the head's
        speed for looks (``mission.lookout_head_speed``) of the object's direction: the head there and
        back and a dwell before the object is lost (one-wall world 31: views 4.2 rad away at 1 rad/s,
        the object unseen 9 s, ``object_lost``)."""
        p = self.config.self_calibration
        if self.pose is None or not self.anchored:
            return []
        reach = p.standstill_travel * self._look_speed
        on_object = self._object_head()
        scored = []
        for yaw, pitch in self._directions:
            if not head_at((yaw, pitch), on_object, reach):
                continue
            points, landmarks = self.localizer.visible_landmarks(self.pose, self.robot.camera_in_robot(yaw, pitch))
            if points >= p.min_points and landmarks >= p.min_landmarks:
                scored.append((points, yaw, pitch))
        views: List[Tuple[float, float]] = []
        for _, yaw, pitch in sorted(scored, key=lambda v: -v[0]):
            if all(abs(yaw - other) >= p.standstill_view_spacing for other, _ in views):
                views.append((yaw, pitch))
        return views[:p.standstill_views]

    def _calibration_standstill(self, t: float, start: bool = False) -> bool:
        """Is the robot standing for its self-calibration (agent/standstill.py): one is under way, or
        (``start``, an ACTIVE tick with an object estimate, whose object legs keep it in view) one is
        due and a direction is predicted to show a fix to store. None once an estimate is applied. No
        keyframe is taken meanwhile."""
        if self.calibration.applied is not None:
            self.standstill.stop(t)
            return False
        if self.standstill.standing(t):
            return True
        return start and self.ekf.initialized and self.standstill.due(t) and self.standstill.begin(t, self._views_to_calibrate())

    def _drought(self, t: float) -> float:
        """s past ``lookout_stand`` without a fix: positive while the lookouts stand (module docstring)."""
        return self.mission.since_fix(t) - self.config.mission.lookout_stand

    def _landmark_lookout(self, t: float) -> Optional[Lookout]:
        """ACTIVE: the look at the landmarks to make now, or None to follow the object (module docstring)."""
        p = self.config.mission
        pose = self.localizer.pose
        drought = self._drought(t)
        if drought > 0.0:  # standing lookouts from then on, first; each half long enough for the head to get there and settle
            period, phase = divmod(drought, 2.0 * p.lookout_stand_dwell)
            slot, looking = (True, int(period)), phase < p.lookout_stand_dwell
        else:
            period = int(t // p.gaze_dwell)
            slot, looking = (False, period), period % 2 == 1
        uncertain = self.localizer.position_std() > p.lookout_std or drought > 0.0  # a drought ends the mission in the end
        if drought <= 0.0:
            self._fruitless.clear()
            self._turn_goal = None
        if pose is None or not uncertain or not looking:
            if self._lookout is not None:
                if self._lookout.slot[0] and self._lookout.heading is None and drought > 0.0:  # a still look without a fix
                    self._fruitless.append(self._lookout.head)
                self._lookout, self._t_back = None, t
            return None
        if self._lookout is None or self._lookout.slot != slot:  # one search per dwell, from the pose at its start
            head, reach = self.mission.head, self._look_reach() if slot[0] else None
            directions = [d for d in self._directions if not any(head_at(d, f, FRUITLESS_RADIUS) for f in self._fruitless)
                          and (reach is None or head_at(d, head, reach))]
            view = self.localizer.best_landmark_view(pose, self.robot.camera_in_robot, directions)
            turned = self._turned_look(slot, pose, head, reach) if view is None and reach is not None else None
            scan = p.search_head_yaws[(slot[1] // 2) % len(p.search_head_yaws)]
            if reach is not None:
                scan = min(max(scan, head[0] - reach), head[0] + reach)
            self._lookout = turned or Lookout(slot, self.robot.head.clamp(*((view.yaw, view.pitch) if view else (scan, p.init_pitch))))
            self._turn_goal = self._lookout.heading
        return self._lookout

    def _turned_look(self, slot: Tuple[bool, int], pose: Pose, head: Tuple[float, float], reach: float) -> Optional[Lookout]:
        """The best standing look the head reaches only with the body turned (module docstring), or None."""
        lo, hi = self.robot.head.yaw
        on_object = self._object_gaze or head

        def turn(yaw: float) -> float:
            return yaw - min(max(yaw, lo + TURN_MARGIN), hi - TURN_MARGIN)

        directions = []
        for yaw, pitch in self._around:
            yaw = min((yaw - 2.0 * math.pi, yaw, yaw + 2.0 * math.pi), key=lambda y: abs(y - head[0]))  # the way the head turns
            if abs(yaw - head[0]) <= reach and turn(yaw) != 0.0 and lo <= on_object[0] - turn(yaw) <= hi:
                directions.append((yaw, pitch))
        view = self.localizer.best_landmark_view(pose, self.robot.camera_in_robot, directions)
        if view is None:
            return None
        return Lookout(slot, self.robot.head.clamp(view.yaw - turn(view.yaw), view.pitch), wrap_angle(pose[2] + turn(view.yaw)))

    def _turn_walk(self, heading: Optional[float]) -> Tuple[float, float, float]:
        """A standing look's walk: still, or the turn in place towards its heading (module docstring)."""
        if heading is None or self.pose is None:
            return (0.0, 0.0, 0.0)
        omega_max = self.robot.walk.omega_max
        return (0.0, 0.0, min(max(wrap_angle(heading - self.pose[2]) / TURN_TIME, -omega_max), omega_max))

    def _turn_pending(self) -> Optional[float]:
        """The heading a standing look's body turn still goes on to in the object's dwell, or None
        (none, or reached within ``TURN_DONE``)."""
        if self._turn_goal is not None and self.pose is not None and abs(wrap_angle(self._turn_goal - self.pose[2])) < TURN_DONE:
            self._turn_goal = None
        return self._turn_goal

    def _look_reach(self) -> Optional[float]:
        """rad a standing look may turn the head from where it is (module docstring), or None (head angles unknown)."""
        head = self.mission.head
        if head is None or not all(map(math.isfinite, head)):
            return None
        p = self.config.mission
        return (p.lookout_stand_dwell - p.lookout_still) * self._look_speed

    @property
    def _look_speed(self) -> float:
        """rad/s the head turns at ``mission.lookout_head_speed`` (standing looks, the standstill)."""
        return self.config.mission.lookout_head_speed * self.robot.head.max_speed

    def _gaze_on_object(self, t: float, head: Tuple[float, float]) -> bool:
        """May a frame captured with this head be a keyframe: not looking away, and back on the object since."""
        if self._lookout is not None:
            return False
        if self._t_back is None:
            return True
        target, p = self._object_gaze, self.config.mission
        if t - self._t_back >= p.lookout_settle or (
                target is not None and head_at(head, target, p.head_tolerance)):
            self._t_back = None
        return self._t_back is None

    def _clear(self, walk: Tuple[float, float, float]) -> Tuple[float, float, float]:
        """The walk command, cut to its turn when it approaches the image's surface point or a wall, too near
        (module docstring)."""
        if self._approaches_object(walk) or self._approaches_wall(walk):
            return (0.0, 0.0, walk[2])
        return walk

    def _approaches_object(self, walk: Tuple[float, float, float]) -> bool:
        if self._near is None or self._odom is None:
            return False
        dx, dy = self._near[0] - self._odom[0], self._near[1] - self._odom[1]
        if math.hypot(dx, dy) >= self.config.mission.min_image_distance:
            return False
        bearing = math.atan2(dy, dx) - self._odom[2]
        return walk[0] * math.cos(bearing) + walk[1] * math.sin(bearing) > 1e-9

    def _approaches_wall(self, walk: Tuple[float, float, float]) -> bool:
        """Nearer than ``wall_stop`` to a wall of the map (agent/keep_in.py) and walking towards it."""
        if not self.anchored or self.pose is None or not self.ekf.initialized:
            return False
        nearest = self.keep_in.nearest(np.asarray(self.pose), self.ekf.x)
        if nearest is None or nearest[0] >= self.config.mission.wall_stop:
            return False
        c, s = math.cos(self.pose[2]), math.sin(self.pose[2])
        velocity = (walk[0] * c - walk[1] * s, walk[0] * s + walk[1] * c)  # in the map's frame
        return -(nearest[1] * velocity[0] + nearest[2] * velocity[1]) > 1e-9  # towards the wall, against its normal

    def _control(self, step: Step, t: float) -> None:
        if self._t_active is None:
            self._t_active = t
            self._covered = (0, t)
        if self._t_plan is not None and t - self._t_plan < self.config.planner.period - 1e-9:
            return
        if not self.ekf.initialized:
            return
        self._t_plan = t
        x, P = self.ekf.x, self.ekf.P
        termination = self.config.planner.termination
        reachable = self.planner.reachable_bins(x, self.keep_in) if self.anchored else None
        seen = self.coverage.seen(x, termination.facing_margin)
        covered = seen_fraction(seen, reachable)
        walled = reachable is not None and not reachable.all()
        if seen.sum() > self._covered[0]:
            self._covered = (int(seen.sum()), t)
        stalled = walled and t - self._covered[1] >= termination.stall
        reason = termination_reason(1.0 if stalled else covered, P, t - self._t_active, termination)
        if reason is not None and reason.startswith("complete"):  # the time limit is the mission's
            if walled:
                reason += (f" ({int(reachable.sum())} of {reachable.size} bins reachable off the walls, {covered:.2f} of them seen"
                           + (f", none new for {termination.stall:g} s)" if stalled else ")"))
            self.mission.on_goal(t, reason)
            return
        walls, landmarks = (self.keep_in, self.landmark_reach) if self.anchored else (None, None)  # in the map's frame only
        plan = self.planner.plan(np.asarray(self.pose), x, P, self.coverage, self.height.top, walls, landmarks)
        self.command = plan.command
        step.outputs.append(PlanRecord(t, [float(w) for w in plan.omegas], tuple(map(float, plan.command)), float(plan.cost),
                                       {k: float(v) for k, v in plan.terms.items()}, int(plan.evaluations),
                                       self.coverage.fraction(x)))
