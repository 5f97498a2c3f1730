"""The mission as an explicit, pure state machine: events in, decisions out, no I/O.

Phases and transitions (t is the caller's clock, s; the first ``tick`` starts the mission)::

    INIT    --head centred (|yaw|, |pitch - init_pitch| <= head_tolerance) or init_timeout--> SEARCH
    SEARCH  --a frame saw the object while the robot is localized--> ACTIVE
            --a frame saw the object, no landmark fix yet--> LOCALIZE
            head scan: one ``search_dwell`` per yaw of ``search_head_yaws``, counted from the head's
            arrival there (|yaw - target| <= head_tolerance in a state; a head that has not arrived
            within init_timeout is taken as there: the scan never hangs), then turn in place at
            ``search_turn_rate`` for at most search_max_turns * 2 pi / search_turn_rate s
    LOCALIZE --a landmark fix--> ACTIVE   (the robot stands; the object is tracked in the odometry
            frame and the caller's head alternates between it and the landmarks)
    INIT, SEARCH, LOCALIZE --no landmark fix for no_fix_timeout s since the start--> STOPPING
            (outcome 'landmarks_lost', the reason says how many landmarks frames showed, and
            ``landmark_note``: markers seen that the map does not hold)
    ACTIVE  --on_goal (coverage and uncertainty reached)--> DONE (outcome 'completed')
    any of INIT, SEARCH, ACTIVE --t - t_start >= max_duration--> DONE (outcome 'time_limit')
    DONE    --next tick--> STOPPING
    any     --fall, bridge lost, interrupt, object lost, landmarks lost, search exhausted--> STOPPING
            (a search exhausted: outcome 'object_not_found', the reason ending with ``object_note``:
            other colour classes' silhouettes the frames showed)
    STOPPING --a state received after the stop says not walking, or stop_timeout--> FINISHED

Abort rules in LOCALIZE and ACTIVE: the object unseen for ``object_lost_timeout`` s of frames
that were meant to show it, or for ``object_away_timeout`` s in all ('object_lost'). A frame turned
away from the object on purpose (a look at the landmarks, the self-calibration's views, the head on
its way back, the body turning faster than the head: ``on_frame``'s ``gaze_on_object``) was not
meant to show it; a standstill's view 120 deg from the object, then the walk turning the body away
while the head came back, took 6 s and ended stress world 314 'object_lost' with the object 0.8 m
away. In ACTIVE, no landmark fix for ``landmarks_lost_timeout`` s, or the pose's position std
(odometry since the last fix, reported with each frame) above ``landmarks_lost_std``
('landmarks_lost').
In any phase before DONE, ``max_frame_failures`` frames in a row that a per-frame step failed on
end the mission ('frame_failures'; the reason names the step and its last error). No processed frame
for ``frame_stall`` s (since the last one, or the start) holds the robot: every decision stands it
still (``Decision.hold``: the caller adds no walk of its own) and no object, landmark or search
clock is judged on frames that never came; ``frame_timeout`` s of it end the mission ('camera_lost':
the bridge is connected and sends no frame the station can use). Without it a camera that stopped
left the robot walking its last plan blind for the object-lost timeout, or turning its search, and
the reason blamed the object. A gap that ends (a Wi-Fi stall) counts as the head looking away.
The first outcome wins; later events cannot change it. Every decision from DONE on carries ``stop=True``: the robot is stopped
before anything else happens, whatever the outcome.

In LOCALIZE the mission keeps the robot still and leaves the head to the caller; in ACTIVE it
does not choose the motion: ``Decision.walk`` and ``Decision.head`` are None
and the caller applies the planner's command and the head servo's target (or, while the pose is
uncertain, ``lookout_std``, alternates it with the best landmark direction, standing for it after
``lookout_stand`` s without a fix: station/pilot.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from typing import Callable, Optional, Tuple

from nao_core.config import bounds
from nao_core.robot_model import head_at


class Phase(str, Enum):
    INIT = "init"
    SEARCH = "search"
    LOCALIZE = "localize"
    ACTIVE = "active"
    DONE = "done"
    STOPPING = "stopping"
    FINISHED = "finished"


class Outcome(str, Enum):
    COMPLETED = "completed"
    TIME_LIMIT = "time_limit"
    OBJECT_NOT_FOUND = "object_not_found"
    OBJECT_LOST = "object_lost"
    LANDMARKS_LOST = "landmarks_lost"
    FALLEN = "fallen"
    BRIDGE_LOST = "bridge_lost"
    INTERRUPTED = "interrupted"
    FRAME_FAILURES = "frame_failures"
    CAMERA_LOST = "camera_lost"

    @property
    def success(self) -> bool:
        return self is Outcome.COMPLETED


@dataclass(frozen=True)
class MissionParams:
    max_duration: float = field(metadata=bounds(1.0, 86400.0))
    init_timeout: float = field(metadata=bounds(0.0, 60.0))
    head_tolerance: float = field(metadata=bounds(0.001, 1.0))
    init_pitch: float = field(metadata=bounds(-0.6, 0.5))
    search_head_yaws: Tuple[float, ...] = field(metadata=bounds(-2.0, 2.0))
    search_dwell: float = field(metadata=bounds(0.05, 30.0))
    search_turn_rate: float = field(metadata=bounds(0.01, 2.0))
    search_max_turns: float = field(metadata=bounds(0.0, 10.0))
    object_lost_timeout: float = field(metadata=bounds(0.1, 600.0))
    object_away_timeout: float = field(metadata=bounds(0.1, 600.0))
    landmarks_lost_timeout: float = field(metadata=bounds(0.1, 600.0))
    landmarks_lost_std: float = field(metadata=bounds(0.001, 10.0))
    no_fix_timeout: float = field(metadata=bounds(0.1, 3600.0))
    max_frame_failures: int = field(metadata=bounds(1, 100000))
    frame_stall: float = field(metadata=bounds(0.1, 60.0))  # s without a processed frame: the robot stands until one comes
    frame_timeout: float = field(metadata=bounds(0.1, 600.0))  # ... and this long ends the mission ('camera_lost')
    gaze_dwell: float = field(metadata=bounds(0.1, 30.0))
    lookout_std: float = field(metadata=bounds(0.001, 10.0))
    lookout_stand: float = field(metadata=bounds(0.0, 600.0))
    lookout_stand_dwell: float = field(metadata=bounds(0.1, 60.0))
    lookout_still: float = field(metadata=bounds(0.0, 60.0))
    lookout_settle: float = field(metadata=bounds(0.0, 30.0))
    lookout_head_speed: float = field(metadata=bounds(0.01, 1.0))
    localize_turn_after: float = field(metadata=bounds(0.0, 600.0))
    min_image_distance: float = field(metadata=bounds(0.0, 5.0))
    wall_stop: float = field(metadata=bounds(0.0, 5.0))  # m: walking towards a wall of the map stops nearer than this
    relocalize_shift: float = field(metadata=bounds(0.0, 100.0))  # m or rad: a fix moving the pose further rebuilds the object filter
    stop_timeout: float = field(metadata=bounds(0.0, 60.0))

    def __post_init__(self) -> None:
        if self.frame_stall >= self.frame_timeout:
            raise ValueError(f"frame_stall ({self.frame_stall} s) must be shorter than frame_timeout ({self.frame_timeout} s)")
        if self.lookout_still >= self.lookout_stand_dwell:
            raise ValueError(f"lookout_still ({self.lookout_still} s) must be shorter than lookout_stand_dwell "
                             f"({self.lookout_stand_dwell} s): the head needs the rest of the dwell to get to the look")

    @property
    def search_turn_duration(self) -> float:
        return self.search_max_turns * 2.0 * math.pi / self.search_turn_rate


@dataclass(frozen=True)
class Decision:
    """What the robot should do now. ``walk``/``head`` None: not the mission's to choose."""

    phase: Phase
    walk: Optional[Tuple[float, float, float]] = None  # (v, vy, omega)
    head: Optional[Tuple[float, float]] = None  # (yaw, pitch)
    head_speed: Optional[float] = None  # fraction of the head's maximum speed; None: the station's ``head_speed``
    stop: bool = False
    hold: bool = False  # stand still: no walk of the caller's (no frames to walk by)
    outcome: Optional[Outcome] = None
    reason: str = ""

    @property
    def finished(self) -> bool:
        return self.phase is Phase.FINISHED


class Mission:
    """The state machine. Feed events in time order, call ``tick`` once per control period."""

    def __init__(self, params: MissionParams):
        self.params = params
        self.phase = Phase.INIT
        self.outcome: Optional[Outcome] = None
        self.reason = ""
        self._t_start: Optional[float] = None
        self._t_phase = 0.0
        self._head: Optional[Tuple[float, float]] = None
        self._walking = True  # unknown until the robot reports otherwise
        self._t_state = -math.inf
        self._t_object: Optional[float] = None
        self._looked_away = 0.0  # s since _t_object the head was turned away from the object on purpose
        self._t_frame: Optional[float] = None  # the last processed frame's time
        self.frames = 0  # frames processed
        self._t_fix: Optional[float] = None
        self._position_std = 0.0  # m, the pose's, as the last frame reported it
        self._scan = 0  # index of the head scan's current yaw
        self._t_target: Optional[float] = None  # when the head was sent to it
        self._t_arrived: Optional[float] = None  # when the head got there (its dwell starts)
        self._t_turn: Optional[float] = None  # when the scan ended and the turn in place began
        self.landmark_frames = 0  # frames in which landmarks were detected (fix or not)
        self.flooded_frames = 0  # frames the object's colour filled from side to side (not a sighting)
        # the caller's account of what the frames showed that the map does not hold, read when 'landmarks_lost' is said
        self.landmark_note: Callable[[], str] = str
        # and of the colours it showed where the object's was not, read when the object is said not seen
        self.object_note: Callable[[], str] = str
        self.frame_failures = 0  # frames in a row a per-frame step failed on

    # events -----------------------------------------------------------------------------------

    def on_state(self, t: float, fallen: bool, walking: bool, head_yaw: float, head_pitch: float) -> None:
        self._head = (head_yaw, head_pitch)
        self._walking, self._t_state = walking, t
        if fallen:
            self._end(t, Outcome.FALLEN, "the robot fell")

    def on_frame(self, t: float, object_seen: bool, landmark_fix: bool, localized: bool, landmarks_seen: bool = False,
                 position_std: float = 0.0, flooded: bool = False, gaze_on_object: bool = True) -> None:
        """One processed frame: was the object measured, did landmarks fix the pose, is a pose
        known, were landmarks detected at all, how much the pose is worth (m), did the object's
        colour fill the image from side to side (then the object is not seen; the reasons say so), and
        was the head meant to be on the object (the time since the last frame of one that was not
        does not count towards ``object_lost_timeout``)."""
        self.frame_failures = 0
        self.frames += 1
        if self._t_frame is not None and self._t_object is not None and t - self._t_frame >= self.params.frame_stall:
            self._looked_away += t - max(self._t_frame, self._t_object)  # no frame came to show it
        self._position_std = position_std
        self.landmark_frames += landmarks_seen or landmark_fix
        self.flooded_frames += flooded
        if object_seen:
            self._t_object, self._looked_away = t, 0.0
        elif not gaze_on_object and self._t_frame is not None and self._t_object is not None:
            self._looked_away += max(0.0, t - max(self._t_frame, self._t_object))
        self._t_frame = t
        if landmark_fix:
            self._t_fix = t
        if self.phase in (Phase.SEARCH, Phase.LOCALIZE) and object_seen and localized:
            self._enter(Phase.ACTIVE, t)
        elif self.phase is Phase.SEARCH and object_seen:
            self._enter(Phase.LOCALIZE, t)

    def _lost(self, t: float) -> bool:
        """The object unseen ``object_lost_timeout`` s while the head was meant to be on it, or
        ``object_away_timeout`` s in all (module docstring)."""
        p = self.params
        return t - self._t_object - self._looked_away > p.object_lost_timeout or t - self._t_object > p.object_away_timeout

    def _lost_reason(self, t: float) -> str:
        if self._t_object is None:
            return f"object not seen for {self.params.object_lost_timeout:g} s"
        away = f", the head turned away from it for {self._looked_away:.1f} s of them" if self._looked_away > 0.0 else ""
        return f"object not seen for {t - self._t_object:.1f} s{away}"

    def in_phase(self, t: float) -> float:
        """Seconds since the current phase began."""
        return t - self._t_phase

    def since_fix(self, t: float) -> float:
        """Seconds since the last landmark fix (infinite before the first)."""
        return math.inf if self._t_fix is None else t - self._t_fix

    def on_frame_failed(self, t: float, step: str, error: str) -> None:
        """A frame a per-frame step raised on (the caller dropped it)."""
        self.frame_failures += 1
        if self.frame_failures >= self.params.max_frame_failures:
            self._end(t, Outcome.FRAME_FAILURES, f"{step} failed on {self.frame_failures} frames in a row: {error}")

    def on_goal(self, t: float, reason: str) -> None:
        if self.phase is Phase.ACTIVE:
            self._end(t, Outcome.COMPLETED, reason, abort=False)

    def on_bridge_lost(self, t: float, reason: str) -> None:
        self._end(t, Outcome.BRIDGE_LOST, reason)

    def on_interrupt(self, t: float, signal_name: str) -> None:
        self._end(t, Outcome.INTERRUPTED, f"interrupted by {signal_name}")

    # decisions --------------------------------------------------------------------------------

    def tick(self, t: float) -> Decision:
        p = self.params
        if self._t_start is None:
            self._t_start = self._t_phase = t
        if self.phase in (Phase.INIT, Phase.SEARCH, Phase.ACTIVE) and t - self._t_start >= p.max_duration:
            self._end(t, Outcome.TIME_LIMIT, f"time limit of {p.max_duration:g} s reached", abort=False)
        if self.phase in (Phase.INIT, Phase.SEARCH, Phase.LOCALIZE) and self._t_fix is None \
                and t - self._t_start >= p.no_fix_timeout:
            seen = "the object seen" if self._t_object is not None else "the object not seen"
            self._end(t, Outcome.LANDMARKS_LOST, f"no landmark fix in {p.no_fix_timeout:g} s: landmarks detected in "
                                                 f"{self.landmark_frames} frames, {seen}" + self._landmark_note())
        silent = t - (self._t_start if self._t_frame is None else self._t_frame)
        if self.phase in (Phase.INIT, Phase.SEARCH, Phase.LOCALIZE, Phase.ACTIVE) and silent >= p.frame_stall:
            if silent < p.frame_timeout:
                return Decision(self.phase, walk=(0.0, 0.0, 0.0), head=(0.0, p.init_pitch) if self.phase is Phase.INIT else None,
                                hold=True, reason=f"no camera frame for {silent:.1f} s: standing until frames come")
            since = "since the start" if self._t_frame is None else f"after {self.frames} frames"
            self._end(t, Outcome.CAMERA_LOST, f"no camera frame for {silent:.1f} s {since}: the bridge is connected and "
                                              f"sends none the station can use (the robot's camera, or the link's bandwidth)")
        elapsed = t - self._t_phase

        if self.phase is Phase.INIT:
            if elapsed >= p.init_timeout or self._head_centred():
                self._enter(Phase.SEARCH, t)
            else:
                return Decision(self.phase, walk=(0.0, 0.0, 0.0), head=(0.0, p.init_pitch))
        if self.phase is Phase.SEARCH:
            return self._search(t)
        if self.phase is Phase.LOCALIZE:
            if self._lost(t):
                self._end(t, Outcome.OBJECT_LOST, self._lost_reason(t) + " while waiting for a landmark fix" + self._object_notes(colours=False))
            else:
                return Decision(self.phase, walk=(0.0, 0.0, 0.0))
        if self.phase is Phase.ACTIVE:
            if self._t_object is None or self._lost(t):
                self._end(t, Outcome.OBJECT_LOST, self._lost_reason(t) + self._object_notes(colours=False))
            elif self._t_fix is None or t - self._t_fix > p.landmarks_lost_timeout:
                self._end(t, Outcome.LANDMARKS_LOST, f"no landmark fix for {p.landmarks_lost_timeout:g} s" + self._landmark_note())
            elif self._position_std > p.landmarks_lost_std:
                self._end(t, Outcome.LANDMARKS_LOST, f"no landmark fix for {t - self._t_fix:.1f} s: the pose's std "
                                                     f"{100 * self._position_std:.1f} cm passed {100 * p.landmarks_lost_std:g} cm"
                                                     + self._landmark_note())
            else:
                return Decision(self.phase)
        if self.phase is Phase.DONE:
            decision = self._stop_decision()
            self._enter(Phase.STOPPING, t)
            return decision
        stopped = not self._walking and self._t_state > self._t_phase  # reported after the stop began
        if self.phase is Phase.STOPPING and (stopped or elapsed >= p.stop_timeout):
            self._enter(Phase.FINISHED, t)
        return self._stop_decision()

    def _search(self, t: float) -> Decision:
        p = self.params
        yaws = p.search_head_yaws
        while self._scan < len(yaws):
            yaw = yaws[self._scan]
            if self._t_target is None:
                self._t_target = t
            if self._t_arrived is None and (self._head_at(yaw, p.init_pitch) or t - self._t_target >= p.init_timeout):
                self._t_arrived = t
            if self._t_arrived is None or t - self._t_arrived < p.search_dwell:
                return Decision(self.phase, walk=(0.0, 0.0, 0.0), head=(yaw, p.init_pitch))
            self._scan, self._t_target, self._t_arrived = self._scan + 1, None, None
        if self._t_turn is None:
            self._t_turn = t
        if t - self._t_turn >= p.search_turn_duration:
            self._end(t, Outcome.OBJECT_NOT_FOUND, f"object not seen in a head scan and {p.search_max_turns:g} turns "
                      f"(landmarks detected in {self.landmark_frames} frames)" + self._object_notes())
            return self.tick(t)
        return Decision(self.phase, walk=(0.0, 0.0, p.search_turn_rate), head=(0.0, p.init_pitch))

    # helpers ----------------------------------------------------------------------------------

    def _landmark_note(self) -> str:
        note = self.landmark_note()
        return f"; {note}" if note else ""

    def _object_notes(self, colours: bool = True) -> str:
        """What the frames showed instead of the object: its colour flooding them, and (``colours``: an object
        never seen) other colours' silhouettes."""
        notes = []
        if self.flooded_frames:
            notes.append(f"the object's colour filled {self.flooded_frames} frames from side to side: the floor, a wall "
                         f"or something large has its colour (docs/perception.md, \"Colours\")")
        if colours:
            notes.append(self.object_note())
        return "".join(f"; {note}" for note in notes if note)

    @property
    def head(self) -> Optional[Tuple[float, float]]:
        """The latest head angles (yaw, pitch) the robot's state reported, rad, or None before the first."""
        return self._head

    def _head_centred(self) -> bool:
        return self._head_at(0.0, self.params.init_pitch)

    def _head_at(self, yaw: float, pitch: float) -> bool:
        return self._head is not None and head_at(self._head, (yaw, pitch), self.params.head_tolerance)

    def _stop_decision(self) -> Decision:
        return Decision(self.phase, walk=(0.0, 0.0, 0.0), stop=True, outcome=self.outcome, reason=self.reason)

    def _enter(self, phase: Phase, t: float) -> None:
        self.phase = phase
        self._t_phase = t

    def _end(self, t: float, outcome: Outcome, reason: str, abort: bool = True) -> None:
        if self.outcome is not None:
            return
        self.outcome, self.reason = outcome, reason
        self._enter(Phase.STOPPING if abort else Phase.DONE, t)
