"""When the mission stands for its self-calibration, and where the head looks meanwhile
(docs/landmarks.md "Self-calibration", agent/self_calibration.py).

The self-calibration stores only fixes made standing, with the head still: walking sway, and head
angles read a few milliseconds off while it turns, pass for a calibration error. A mission that
finds its object at once has stood for none, so ACTIVE opens with a *standstill*: a zero walk,
the head going through legs

    object, view_0, object, view_1, ..., object, view_{n-1}, object, view_0, ...

where the views are the head directions predicted from the pose to show a fix to store. A leg's
dwell (``mission.gaze_dwell`` on the object, ``standstill_dwell`` on a view) starts when a frame
shows the head within ``mission.head_tolerance`` of the leg's target, or ``standstill_travel`` s
after the leg began when none does: a head that needs 1.7 s to turn to a view leaves no settled
frame in a dwell counted from the command, and fixes are stored only once it has settled. The
object legs keep it in view (the mission ends ``object_lost`` after ``object_lost_timeout``).

A standstill ends after ``standstill`` s, or when a whole cycle of its views stored no fix
(sparse markers, a view the prediction got wrong), or when no landmark fix at all came for
``standstill_fix_patience`` s (the mission ends ``landmarks_lost`` after
``mission.landmarks_lost_timeout`` without one, and walking brings the landmark lookout), or when
the estimate is applied. One that ended
without an applied estimate is tried again ``standstill_interval`` s later from wherever the walk
has taken the robot (new views, new geometry), ``standstill_attempts`` standstills in all. A try
from where no direction is predicted to show a fix to store is no standstill and no attempt.
"""

from __future__ import annotations

import math
from typing import List, Optional, Tuple

from agent.self_calibration import SelfCalibrationParams
from nao_core.robot_model import head_at

Head = Tuple[float, float]  # (yaw, pitch), rad


class CalibrationStandstill:
    """The standstill's schedule (module docstring). Times are the station's event times."""

    def __init__(self, params: SelfCalibrationParams, gaze_dwell: float, head_tolerance: float, possible: bool = True):
        self.params = params
        self.gaze_dwell = gaze_dwell
        self.head_tolerance = head_tolerance
        self.attempts = 0  # standstills started
        self._possible = possible and params.enabled and params.standstill > 0.0 and params.standstill_attempts > 0
        self._start: Optional[float] = None  # the current standstill's start, None when not standing
        self._last_try = -math.inf  # when the last standstill ended, or a try found no view
        self.views: List[Head] = []
        self._leg = 0  # even: the object, odd: views[(leg // 2) % len(views)]
        self._leg_start = 0.0
        self._arrived: Optional[float] = None  # when a frame showed the head on the leg's target
        self._target: Optional[Head] = None  # the leg's target, as last returned
        self._leg_stored = False  # a fix was stored during this view leg
        self._fruitless = 0  # view legs in a row that stored no fix
        self._last_fix = -math.inf  # when the localizer last gave a fix (stored or not)

    def due(self, t: float) -> bool:
        """May a standstill start now: none under way, attempts left, ``standstill_interval`` since the last try."""
        p = self.params
        return (self._possible and self._start is None and self.attempts < p.standstill_attempts
                and t - self._last_try >= p.standstill_interval)

    def begin(self, t: float, views: List[Head]) -> bool:
        """Start a standstill through ``views`` (``due`` first); without a view there is none, and the next try waits."""
        if not views:
            self._last_try = t
            return False
        self.views, self.attempts, self._start = list(views), self.attempts + 1, t
        self._leg, self._leg_start, self._arrived, self._target = 0, t, None, None
        self._leg_stored, self._fruitless = False, 0
        return self.standing(t)

    def standing(self, t: float) -> bool:
        """Is a standstill under way at ``t``; ends it when its time is up or a cycle of views stored nothing."""
        if self._start is None:
            return False
        self._advance(t)
        p = self.params
        if (t - self._start >= p.standstill or self._fruitless >= len(self.views)
                or t - max(self._start, self._last_fix) >= p.standstill_fix_patience):
            self.stop(t)
        return self._start is not None

    def stop(self, t: float) -> None:
        """End the standstill under way (the estimate was applied, or its time is up)."""
        if self._start is not None:
            self._start, self._last_try = None, t

    def head(self, t: float, object_head: Head) -> Head:
        """The head target at ``t``: the object's (``object_head``) on even legs, the leg's view on odd ones."""
        self._advance(t)
        self._target = object_head if self._leg % 2 == 0 else self.views[(self._leg // 2) % len(self.views)]
        return self._target

    def on_head(self, t: float, yaw: float, pitch: float) -> None:
        """A frame's head angles at capture: the leg's dwell starts once they are on its target."""
        self._advance(t)
        target = self._target
        if (self._start is not None and self._arrived is None and target is not None
                and head_at((yaw, pitch), target, self.head_tolerance)):
            self._arrived = t

    def on_fix(self, t: float) -> None:
        """The localizer gave a landmark fix at ``t`` (stored or not)."""
        self._last_fix = t

    def on_stored(self, t: float) -> None:
        """The self-calibration stored a fix at ``t``."""
        self._advance(t)
        if self._start is not None and self._leg % 2 == 1:
            self._leg_stored = True

    def _advance(self, t: float) -> None:
        """Move on through every leg whose dwell ended before ``t``."""
        while self._start is not None:
            view_leg = self._leg % 2 == 1
            dwell = self.params.standstill_dwell if view_leg else self.gaze_dwell
            there = self._leg_start + self.params.standstill_travel  # at the latest
            end = (there if self._arrived is None else min(self._arrived, there)) + dwell
            if t < end:
                return
            if view_leg:
                self._fruitless = 0 if self._leg_stored else self._fruitless + 1
            self._leg, self._leg_start, self._arrived, self._target, self._leg_stored = self._leg + 1, end, None, None, False
