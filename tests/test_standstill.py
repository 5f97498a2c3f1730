"""The self-calibration standstill's schedule (agent/standstill.py): dwells counted from the head's
arrival, the end of a standstill, and the later tries."""

from __future__ import annotations

import dataclasses

import pytest

from agent.self_calibration import SelfCalibrationParams
from agent.standstill import CalibrationStandstill
from nao_core.config import CONFIG_DIR, load

PARAMS = load(SelfCalibrationParams, [CONFIG_DIR / "self_calibration.yaml"], section="self_calibration")
GAZE_DWELL, TOLERANCE = 1.0, 0.05
OBJECT = (0.3, 0.2)
VIEWS = [(-1.3, 0.05), (1.2, 0.1)]


def schedule(**params: float) -> CalibrationStandstill:
    return CalibrationStandstill(dataclasses.replace(PARAMS, **params), GAZE_DWELL, TOLERANCE)


def first_visit(trace: list, target: tuple) -> list:
    """The ticks of the first leg on ``target``."""
    ticks = [k for k, (_, aim) in enumerate(trace) if aim == target]
    return [trace[k][0] for k in ticks if k - ticks[0] == ticks.index(k)]


def follow(standstill: CalibrationStandstill, t0: float, t1: float, speed: float = 1.0, dt: float = 0.05,
           store_every: float = 0.0) -> list:
    """Ticks and frames from t0 to t1: a head turning at ``speed`` rad/s towards each target, a fix
    stored every ``store_every`` s on views (never when 0); the (t, target) of every tick."""
    head, trace, last_store = OBJECT, [], t0
    t = t0
    while t < t1 and standstill.standing(t):
        target = standstill.head(t, OBJECT)
        step = speed * dt
        head = tuple(h + max(-step, min(step, g - h)) for h, g in zip(head, target))
        standstill.on_head(t, *head)
        standstill.on_fix(t)  # landmark fixes come all along: only the views' are stored
        if store_every and target != OBJECT and head == target and t - last_store >= store_every:
            standstill.on_stored(t)
            last_store = t
        trace.append((t, target))
        t = round(t + dt, 9)
    return trace


def test_each_dwell_starts_when_the_head_gets_there():
    """A view 1.6 rad from the object, reached at 1 rad/s in 1.6 s: its dwell is counted from then,
    so the head stays on it standstill_dwell s after arriving, not after it was sent."""
    standstill = schedule(standstill_travel=5.0)
    assert standstill.due(0.0) and standstill.begin(0.0, VIEWS)
    trace = follow(standstill, 0.0, 12.0, store_every=0.5)
    view_ticks = first_visit(trace, VIEWS[0])
    first, last = view_ticks[0], view_ticks[-1]
    assert first == pytest.approx(GAZE_DWELL, abs=0.06)  # the head is on the object from the start
    travel = abs(VIEWS[0][0] - OBJECT[0]) - TOLERANCE  # 1.55 s at 1 rad/s to within the tolerance
    assert last - first == pytest.approx(travel + PARAMS.standstill_dwell, abs=0.1)
    assert trace[len(first_visit(trace, OBJECT)) + len(view_ticks)][1] == OBJECT  # then the object again, then the next view
    assert first_visit(trace, VIEWS[1])[0] > last


def test_a_head_that_never_gets_there_dwells_after_the_travel_time():
    standstill = schedule()
    standstill.begin(0.0, VIEWS)
    trace = follow(standstill, 0.0, 10.0, speed=0.0, store_every=0.0)  # the head does not move: only the object leg arrives
    view_ticks = first_visit(trace, VIEWS[0])
    assert view_ticks[0] == pytest.approx(GAZE_DWELL, abs=0.06)
    assert view_ticks[-1] - view_ticks[0] == pytest.approx(PARAMS.standstill_travel + PARAMS.standstill_dwell, abs=0.06)


def test_it_ends_after_a_cycle_of_views_without_a_fix_or_when_its_time_is_up():
    fruitless = schedule()
    fruitless.begin(0.0, VIEWS)
    trace = follow(fruitless, 0.0, 60.0)
    assert not fruitless.standing(trace[-1][0] + 0.1)
    assert {target for _, target in trace} == {OBJECT, *VIEWS}  # each view was given its dwell
    assert trace[-1][0] < PARAMS.standstill
    fruitful = schedule()
    fruitful.begin(0.0, VIEWS)
    trace = follow(fruitful, 0.0, 60.0, store_every=0.5)
    assert trace[-1][0] == pytest.approx(PARAMS.standstill, abs=0.06)  # fixes keep coming: it lasts its full length
    assert not fruitful.standing(PARAMS.standstill)


def test_it_ends_when_no_landmark_fix_came_for_its_patience():
    """Before the mission's landmarks_lost_timeout: views that give no fix at all must not hold the robot there."""
    standstill = schedule(standstill_fix_patience=3.0)
    standstill.begin(10.0, VIEWS)
    assert standstill.standing(12.9)  # the patience counts from the start, whenever the last fix was
    standstill.on_fix(12.9)
    assert standstill.standing(15.8) and not standstill.standing(15.95)


def test_it_is_tried_again_later_a_few_times_and_a_try_without_a_view_is_no_attempt():
    standstill = schedule(standstill_attempts=2)
    standstill.begin(0.0, VIEWS)
    standstill.stop(3.0)
    interval = PARAMS.standstill_interval
    assert not standstill.due(3.0 + interval - 0.01) and standstill.due(3.0 + interval)
    assert not standstill.begin(3.0 + interval, [])  # nothing predicted from here: wait again
    assert standstill.attempts == 1 and not standstill.due(3.0 + 2 * interval - 0.01)
    assert standstill.begin(3.0 + 2 * interval, VIEWS) and standstill.attempts == 2
    standstill.stop(4.0 + 2 * interval)
    assert not standstill.due(100 * interval)  # attempts spent


@pytest.mark.parametrize("params,possible", [({"standstill": 0.0}, True), ({"standstill_attempts": 0}, True),
                                             ({"enabled": False}, True), ({}, False)])
def test_no_standstill_when_switched_off_or_the_map_cannot_give_fixes_to_store(params: dict, possible: bool):
    standstill = CalibrationStandstill(dataclasses.replace(PARAMS, **params), GAZE_DWELL, TOLERANCE, possible)
    assert not standstill.due(0.0) and not standstill.standing(0.0)
