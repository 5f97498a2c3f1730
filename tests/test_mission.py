"""The mission state machine: every transition and every outcome, driven by synthetic events."""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Optional

import pytest

from agent.mission import Mission, MissionParams, Outcome, Phase
from nao_core.config import CONFIG_DIR, ConfigError, load

DEFAULTS = load(MissionParams, [CONFIG_DIR / "mission.yaml"], section="mission")
P = dataclasses.replace(DEFAULTS, max_duration=100.0, init_timeout=2.0, search_head_yaws=(0.0, 0.5, -0.5), search_dwell=1.0,
                  search_turn_rate=0.5, search_max_turns=1.0, object_lost_timeout=3.0,
                  landmarks_lost_timeout=5.0, stop_timeout=1.0,
                  frame_stall=1000.0, frame_timeout=2000.0)  # most tests tick without frames: the camera rule has its own
CAMERA = dataclasses.replace(P, frame_stall=DEFAULTS.frame_stall, frame_timeout=DEFAULTS.frame_timeout)
DT = 0.1


def run_until(mission: Mission, t: float, t_end: float, on_tick=None):
    decision = None
    while t < t_end - 1e-9:
        if on_tick:
            on_tick(mission, t)
        decision = mission.tick(t)
        t = round(t + DT, 6)
    return t, decision


def active_mission(params: MissionParams = P) -> tuple[Mission, float]:
    mission = Mission(params)
    mission.tick(0.0)
    mission.on_state(0.05, fallen=False, walking=False, head_yaw=0.0, head_pitch=P.init_pitch)
    mission.tick(0.1)
    assert mission.phase is Phase.SEARCH
    mission.on_frame(0.2, object_seen=True, landmark_fix=True, localized=True)
    assert mission.phase is Phase.ACTIVE
    return mission, 0.2


def test_defaults_live_in_the_yaml_only():
    """config/mission.yaml is the one source of the defaults: the dataclass cannot be built without it."""
    with pytest.raises(TypeError):
        MissionParams()
    assert DEFAULTS.no_fix_timeout > DEFAULTS.landmarks_lost_timeout > 0


def test_bad_value_is_named(tmp_path):
    bad = tmp_path / "m.yaml"
    bad.write_text("mission:\n  search_dwell: -1\n")
    with pytest.raises(ConfigError, match=r"mission.search_dwell: expected a number in \[0.05"):
        load(MissionParams, [CONFIG_DIR / "mission.yaml", bad], section="mission")


def test_a_standing_look_still_longer_than_its_dwell_is_refused(tmp_path):
    bad = tmp_path / "m.yaml"
    bad.write_text("mission:\n  lookout_still: 3.0\n  lookout_stand_dwell: 2.5\n")
    with pytest.raises(ConfigError, match="lookout_still .* must be shorter than lookout_stand_dwell"):
        load(MissionParams, [CONFIG_DIR / "mission.yaml", bad], section="mission")


def test_init_centres_head_then_times_out_into_search():
    mission = Mission(P)
    d = mission.tick(0.0)
    assert d.phase is Phase.INIT and d.head == (0.0, P.init_pitch) and d.walk == (0.0, 0.0, 0.0)
    mission.on_state(0.5, fallen=False, walking=False, head_yaw=0.3, head_pitch=0.0)  # not centred
    assert mission.tick(1.0).phase is Phase.INIT
    assert mission.tick(2.0).phase is Phase.SEARCH  # init_timeout


def follow_head(mission: Mission, t: float, t_end: float, lag: float = 0.0, heads: Optional[list] = None) -> Decision:
    """Tick every DT until t_end with a head that reaches each commanded target ``lag`` s after it
    changes; the commanded heads are appended to ``heads``."""
    target, since, decision = None, t, None
    while t < t_end - 1e-9:
        decision = mission.tick(t)
        if heads is not None:
            heads.append(decision.head)
        if decision.head != target:
            target, since = decision.head, t
        if target is not None and t - since >= lag:
            mission.on_state(t, fallen=False, walking=False, head_yaw=target[0], head_pitch=target[1])
        t = round(t + DT, 6)
    return decision


def test_an_object_colour_filling_the_frames_is_named_when_the_object_is_not_found():
    """Frames whose object colour filled the image from side to side (a floor of that colour) are no
    sighting: the search goes on and its failure says how many there were and what it means."""
    mission = searching_mission()
    for k in range(4):
        mission.on_frame(0.1 * (k + 1), object_seen=False, landmark_fix=True, localized=True, flooded=True)
    assert mission.phase is Phase.SEARCH and mission.flooded_frames == 4
    d = follow_head(mission, 0.0, len(P.search_head_yaws) * (P.search_dwell + DT) + P.search_turn_duration + 2 * DT)
    assert d.outcome is Outcome.OBJECT_NOT_FOUND
    assert "object's colour filled 4 frames from side to side" in d.reason and "floor" in d.reason


def test_an_object_never_found_is_said_with_the_caller_s_note_on_other_colours():
    """``object_note`` (the pilot's tally of other colour classes' silhouettes: agent/perception.py
    ``ColourTally``) ends the reason of an object never found, read once, when it is written."""
    mission = searching_mission()
    calls = []
    mission.object_note = lambda: calls.append(1) or "blue in 5 of 9 frames searched"
    d = follow_head(mission, 0.0, len(P.search_head_yaws) * (P.search_dwell + DT) + P.search_turn_duration + 2 * DT)
    assert d.outcome is Outcome.OBJECT_NOT_FOUND and d.reason.endswith("frames); blue in 5 of 9 frames searched"), d.reason
    assert calls == [1]


def test_object_lost_says_when_the_object_colour_filled_the_frames():
    """... and not the note on other colours: an object lost was seen (its colour is right)."""
    mission, t = active_mission()
    mission.object_note = lambda: "blue in 5 of 9 frames searched"
    mission.on_frame(t + 0.1, object_seen=False, landmark_fix=True, localized=True, flooded=True)
    _, d = run_until(mission, t, t + P.object_lost_timeout + 1.0)
    assert d.outcome is Outcome.OBJECT_LOST and "filled 1 frames" in d.reason and "blue" not in d.reason


def test_frames_turned_away_from_the_object_do_not_count_towards_losing_it():
    """Unseen in frames turned away on purpose (a landmark look, the way back), then in frames meant to
    show it: lost only after ``object_lost_timeout`` s of the latter, and the reason says how long the
    head was away; frames meant to show it alone lose it after the timeout."""
    mission, t = active_mission()
    away_until = t + 2 * P.object_lost_timeout
    frame = t
    while frame < away_until:
        frame = round(frame + DT, 6)
        mission.on_frame(frame, object_seen=False, landmark_fix=True, localized=True, gaze_on_object=False)
        assert mission.tick(frame).outcome is None, frame
    while frame < away_until + P.object_lost_timeout - 2 * DT:
        frame = round(frame + DT, 6)
        mission.on_frame(frame, object_seen=False, landmark_fix=True, localized=True)
        assert mission.tick(frame).outcome is None, frame
    _, d = run_until(mission, frame, frame + 4 * DT)
    assert d.outcome is Outcome.OBJECT_LOST and "turned away from it for" in d.reason
    assert float(d.reason.split("for ")[2].split(" s")[0]) == pytest.approx(2 * P.object_lost_timeout, abs=2 * DT)
    mission, t = active_mission()
    mission.on_frame(t + DT, object_seen=False, landmark_fix=True, localized=True)
    _, d = run_until(mission, t, t + P.object_lost_timeout + 2 * DT)
    assert d.outcome is Outcome.OBJECT_LOST and "turned away" not in d.reason


def test_a_head_kept_away_from_the_object_loses_it_after_the_away_timeout():
    """Frames all turned away: the object is lost after ``object_away_timeout`` s, not never."""
    mission, t = active_mission()
    frame, d = t, None
    while d is None or d.outcome is None:
        frame = round(frame + DT, 6)
        mission.on_frame(frame, object_seen=False, landmark_fix=True, localized=True, gaze_on_object=False)
        d = mission.tick(frame)
    assert d.outcome is Outcome.OBJECT_LOST
    assert frame - t == pytest.approx(P.object_away_timeout, abs=2 * DT)


def test_search_scans_head_then_turns_then_gives_up():
    mission = Mission(P)
    mission.on_state(0.0, fallen=False, walking=False, head_yaw=0.0, head_pitch=P.init_pitch)
    assert mission.tick(0.0).phase is Phase.SEARCH  # head already centred
    # a head that is there one state after each command: one dwell per yaw (plus a tick to report it)
    heads = [follow_head(mission, 0.0, t).head[0] for t in (0.6, 1.6, 2.6)]
    assert heads == [0.0, 0.5, -0.5]
    d, t = None, 2.6
    while d is None or d.walk[2] == 0.0:
        d, t = follow_head(mission, t, t + DT), round(t + DT, 6)
    turn_start = t - DT
    assert d.walk == (0.0, 0.0, P.search_turn_rate) and d.head == (0.0, P.init_pitch)
    assert turn_start <= len(P.search_head_yaws) * (P.search_dwell + DT) + DT
    assert follow_head(mission, t, turn_start + P.search_turn_duration - DT).phase is Phase.SEARCH
    d = follow_head(mission, turn_start + P.search_turn_duration - DT, turn_start + P.search_turn_duration + 2 * DT)
    assert d.outcome is Outcome.OBJECT_NOT_FOUND and d.stop and d.phase is Phase.STOPPING


def test_each_scan_dwell_counts_from_the_heads_arrival():
    """A head slower than the dwell still looks search_dwell at every yaw of the scan (it never
    reached the far side when the dwell ran on the clock); one that never arrives moves on after init_timeout."""
    lag = 0.7 * P.search_dwell
    mission = Mission(P)
    mission.on_state(0.0, fallen=False, walking=False, head_yaw=0.0, head_pitch=P.init_pitch)
    mission.tick(0.0)
    seen: list = []
    follow_head(mission, 0.0, len(P.search_head_yaws) * (P.search_dwell + lag + DT) + DT, lag, seen)
    held = {yaw: sum(h == (yaw, P.init_pitch) for h in seen) * DT for yaw in P.search_head_yaws}
    assert held[P.search_head_yaws[0]] >= P.search_dwell - 1e-6  # already there: the dwell alone
    assert all(held[yaw] >= P.search_dwell + lag - 1e-6 for yaw in P.search_head_yaws[1:]), held  # travel, then a full dwell
    assert seen[-1] == (0.0, P.init_pitch)  # then the turn
    stuck = Mission(P)
    stuck.tick(0.0)
    stuck.on_state(0.0, fallen=False, walking=False, head_yaw=0.0, head_pitch=P.init_pitch)
    assert stuck.tick(P.init_timeout).phase is Phase.SEARCH
    assert stuck.tick(P.init_timeout + P.search_dwell).head == (P.search_head_yaws[1], P.init_pitch)  # never reported there
    stuck.tick(P.init_timeout + P.search_dwell + P.init_timeout)  # not there after init_timeout: taken as there
    assert stuck.tick(P.init_timeout + P.search_dwell + P.init_timeout + P.search_dwell).head == (P.search_head_yaws[2], P.init_pitch)


def searching_mission() -> Mission:
    mission = Mission(P)
    mission.on_state(0.0, fallen=False, walking=False, head_yaw=0.0, head_pitch=P.init_pitch)
    mission.tick(0.0)
    assert mission.phase is Phase.SEARCH
    return mission


def test_object_seen_without_pose_localizes_standing_then_goes_active_on_the_fix():
    mission = searching_mission()
    mission.on_frame(0.1, object_seen=True, landmark_fix=False, localized=False)
    d = mission.tick(0.2)
    # LOCALIZE: the robot stands, the head is the caller's (it alternates object / landmarks)
    assert d.phase is Phase.LOCALIZE and d.walk == (0.0, 0.0, 0.0) and d.head is None and not d.stop
    mission.on_frame(0.3, object_seen=True, landmark_fix=True, localized=True)
    assert mission.phase is Phase.ACTIVE


def test_localize_loses_the_object_after_its_timeout():
    mission = searching_mission()
    mission.on_frame(0.1, object_seen=True, landmark_fix=False, localized=False)
    assert mission.tick(0.1 + P.object_lost_timeout - 0.05).phase is Phase.LOCALIZE
    d = mission.tick(0.1 + P.object_lost_timeout + 0.05)
    assert d.outcome is Outcome.OBJECT_LOST and d.stop


@pytest.mark.parametrize("object_seen", [True, False])
def test_no_fix_at_all_ends_as_landmarks_lost_and_says_so(object_seen):
    params = dataclasses.replace(P, object_lost_timeout=1000.0, search_max_turns=100.0)
    mission = Mission(params)
    mission.tick(0.0)
    t = 0.0
    while mission.outcome is None and t < params.no_fix_timeout + 1.0:
        t = round(t + DT, 6)
        mission.on_frame(t, object_seen=object_seen, landmark_fix=False, localized=False)
        mission.tick(t)
    assert mission.outcome is Outcome.LANDMARKS_LOST
    assert t == pytest.approx(params.no_fix_timeout, abs=DT)  # the timeout counts from the first tick
    assert mission.reason.startswith(f"no landmark fix in {params.no_fix_timeout:g} s: landmarks detected in 0 frames")
    assert ("the object seen" if object_seen else "the object not seen") in mission.reason


def test_landmarks_lost_names_the_markers_the_map_does_not_hold():
    """The caller's ``landmark_note`` (the detector's markers seen that the map does not hold) ends every
    'landmarks_lost' reason: before the first fix, and after the timeout in ACTIVE."""
    note = "ArUco markers the map does not hold were seen (DICT_4X4_50 ids 3, 7; the map's: DICT_6X6_250)"
    mission = Mission(dataclasses.replace(P, object_lost_timeout=1000.0, search_max_turns=100.0))
    mission.landmark_note = lambda: note
    run_until(mission, 0.0, P.no_fix_timeout + 0.2, on_tick=lambda m, t: m.on_frame(t, object_seen=True, landmark_fix=False,
                                                                                     localized=False))
    assert mission.outcome is Outcome.LANDMARKS_LOST and mission.reason.endswith("; " + note)
    mission, t = active_mission()
    mission.landmark_note = lambda: note
    run_until(mission, 0.3, 0.2 + P.landmarks_lost_timeout + 0.3,
              on_tick=lambda m, t: m.on_frame(t, object_seen=True, landmark_fix=False, localized=True))
    assert mission.outcome is Outcome.LANDMARKS_LOST and mission.reason == f"no landmark fix for {P.landmarks_lost_timeout:g} s; {note}"


def test_object_not_found_says_what_localization_saw():
    mission = searching_mission()
    for k in range(3):
        mission.on_frame(0.1 * (k + 1), object_seen=False, landmark_fix=False, localized=False, landmarks_seen=True)
    d = follow_head(mission, 0.0, len(P.search_head_yaws) * (P.search_dwell + DT) + P.search_turn_duration + 2 * DT)
    assert d.outcome is Outcome.OBJECT_NOT_FOUND and "landmarks detected in 3 frames" in d.reason


def test_frame_failures_in_a_row_end_the_mission_naming_the_step_and_error():
    mission, t = active_mission()
    n = P.max_frame_failures
    for _ in range(n - 1):
        mission.on_frame_failed(t, "localization", "LinAlgError: Singular matrix")
    keep_seeing(mission, t)  # one good frame resets the count
    assert mission.frame_failures == 0
    for k in range(n):
        assert mission.outcome is None
        mission.on_frame_failed(t, "perception", f"ValueError: bad {k}")
    d = mission.tick(t + DT)
    assert d.outcome is Outcome.FRAME_FAILURES and d.stop
    assert d.reason == f"perception failed on {n} frames in a row: ValueError: bad {n - 1}"


def test_active_leaves_motion_to_the_planner_and_completes_on_goal():
    mission, t = active_mission()
    d = mission.tick(0.3)
    assert d.phase is Phase.ACTIVE and d.walk is None and d.head is None and not d.stop
    mission.on_goal(0.35, "coverage 0.95 and uncertainty reached")
    d = mission.tick(0.4)
    assert d.phase is Phase.DONE and d.stop and d.outcome is Outcome.COMPLETED and d.outcome.success
    assert mission.tick(0.5).phase is Phase.STOPPING
    mission.on_state(0.55, fallen=False, walking=False, head_yaw=0.0, head_pitch=0.0)
    d = mission.tick(0.6)
    assert d.finished and d.stop and d.reason.startswith("coverage")


def test_stopping_waits_for_the_robot_or_the_timeout():
    mission, t = active_mission()
    mission.on_state(0.3, fallen=False, walking=True, head_yaw=0.0, head_pitch=0.0)
    mission.on_goal(0.3, "goal")
    mission.tick(0.4)
    assert mission.tick(0.5).phase is Phase.STOPPING
    assert mission.tick(1.0).phase is Phase.STOPPING  # still walking
    assert mission.tick(1.5).finished  # stop_timeout after entering STOPPING


def keep_seeing(mission: Mission, t: float) -> None:
    mission.on_frame(t, object_seen=True, landmark_fix=True, localized=True)


@pytest.mark.parametrize(
    "event, outcome",
    [
        (lambda m, t: m.on_state(t, fallen=True, walking=False, head_yaw=0, head_pitch=0), Outcome.FALLEN),
        (lambda m, t: m.on_bridge_lost(t, "the bridge went away"), Outcome.BRIDGE_LOST),
        (lambda m, t: m.on_interrupt(t, "SIGTERM"), Outcome.INTERRUPTED),
    ],
)
@pytest.mark.parametrize("phase_time", [0.0, 0.3])  # during INIT, during ACTIVE
def test_external_aborts_stop_the_robot_and_are_final(event, outcome, phase_time):
    mission, t = (Mission(P), 0.0) if phase_time == 0.0 else active_mission()
    mission.tick(t)
    event(mission, t + 0.05)
    d = mission.tick(t + 0.1)
    assert d.phase is Phase.STOPPING and d.stop and d.walk == (0.0, 0.0, 0.0) and d.outcome is outcome
    assert not d.outcome.success and d.reason
    mission.on_goal(t + 0.15, "late goal")  # cannot overwrite the first outcome
    mission.on_interrupt(t + 0.15, "SIGINT")
    assert mission.tick(t + 0.2).outcome is outcome


def test_object_lost_after_timeout():
    mission, t = active_mission()
    t, d = run_until(mission, 0.3, 0.2 + P.object_lost_timeout - 0.05,
                     on_tick=lambda m, t: m.on_frame(t, object_seen=False, landmark_fix=True, localized=True))
    assert d.phase is Phase.ACTIVE
    t, d = run_until(mission, t, t + 0.3)
    assert d.outcome is Outcome.OBJECT_LOST and d.stop


def test_landmarks_lost_after_timeout():
    mission, t = active_mission()
    seen_only = lambda m, t: m.on_frame(t, object_seen=True, landmark_fix=False, localized=True)  # noqa: E731
    t, d = run_until(mission, 0.3, 0.2 + P.landmarks_lost_timeout - 0.05, on_tick=seen_only)
    assert d.phase is Phase.ACTIVE
    t, d = run_until(mission, t, t + 0.3, on_tick=seen_only)
    assert d.outcome is Outcome.LANDMARKS_LOST


def test_landmarks_lost_sooner_when_the_pose_is_worth_too_little():
    """Without a fix, the pose's std reported with each frame ends the mission once it passes
    ``landmarks_lost_std``, before the timeout; below it the mission goes on."""
    mission, t = active_mission()
    std = lambda value: lambda m, t: m.on_frame(t, object_seen=True, landmark_fix=False, localized=True,  # noqa: E731
                                               position_std=value)
    t, d = run_until(mission, 0.3, 1.0, on_tick=std(0.9 * P.landmarks_lost_std))
    assert d.phase is Phase.ACTIVE
    t, d = run_until(mission, t, t + 0.3, on_tick=std(1.1 * P.landmarks_lost_std))
    assert d.outcome is Outcome.LANDMARKS_LOST and t < 0.2 + P.landmarks_lost_timeout
    assert "the pose's std" in d.reason and f"passed {100 * P.landmarks_lost_std:g} cm" in d.reason


def test_time_limit_ends_as_done_not_abort():
    mission, t = active_mission()
    t, d = run_until(mission, 0.3, P.max_duration + 0.05, on_tick=keep_seeing)
    assert d.outcome is Outcome.TIME_LIMIT and d.stop
    assert not d.outcome.success


def test_same_events_same_decisions():
    def trace():
        mission, _ = active_mission()
        return [mission.tick(round(0.3 + i * DT, 6)) for i in range(100)]
    assert trace() == trace()


def test_a_silent_camera_stands_the_robot_then_ends_the_mission_as_camera_lost():
    """No frame for ``frame_stall`` s: every decision stands the robot and says why (``hold``: the pilot adds
    no walk); ``frame_timeout`` s: 'camera_lost', naming how many frames came, not 'object_lost'."""
    mission, t = active_mission(CAMERA)
    t, d = run_until(mission, 0.3, 0.2 + CAMERA.frame_stall - 0.05)
    assert d.phase is Phase.ACTIVE and d.walk is None and not d.hold
    t, d = run_until(mission, t, t + 0.2)
    assert d.hold and d.walk == (0.0, 0.0, 0.0) and not d.stop and re.search(r"no camera frame for 1\.\d s", d.reason)
    assert CAMERA.object_lost_timeout < CAMERA.frame_timeout  # the object-lost clock waits for frames
    t, d = run_until(mission, t, 0.2 + CAMERA.frame_timeout - 0.05)
    assert d.hold and mission.outcome is None
    t, d = run_until(mission, t, t + 0.2)
    assert d.outcome is Outcome.CAMERA_LOST and d.stop and not d.outcome.success
    assert re.search(r"no camera frame for 10\.\d s after 1 frames: the bridge is connected", d.reason)


def test_frames_returning_after_a_stall_release_the_robot_and_the_gap_does_not_lose_the_object():
    """A Wi-Fi stall longer than the object-lost timeout: the frames that follow, the object not yet in
    them, do not end the mission at once (the gap counts as the head looking away); the object still
    unseen for ``object_lost_timeout`` s of frames after it ends it."""
    mission, t = active_mission(CAMERA)
    gap = CAMERA.object_lost_timeout + 1.0
    t, d = run_until(mission, 0.3, 0.2 + gap)
    assert d.hold
    unseen = lambda m, t: m.on_frame(t, object_seen=False, landmark_fix=True, localized=True)  # noqa: E731
    t, d = run_until(mission, t, t + CAMERA.object_lost_timeout - 0.2, on_tick=unseen)
    assert d.phase is Phase.ACTIVE and not d.hold and d.walk is None
    t, d = run_until(mission, t, t + 0.5, on_tick=unseen)
    assert d.outcome is Outcome.OBJECT_LOST


def test_no_frame_from_the_start_ends_as_camera_lost_without_turning_to_search():
    mission = Mission(CAMERA)
    mission.tick(0.0)
    mission.on_state(0.05, fallen=False, walking=False, head_yaw=0.0, head_pitch=CAMERA.init_pitch)
    t, d = run_until(mission, 0.1, CAMERA.frame_stall + 0.05)
    assert d.phase is Phase.SEARCH and d.hold and d.walk == (0.0, 0.0, 0.0)
    turns = []
    t, d = run_until(mission, t, CAMERA.frame_timeout + 0.05, on_tick=lambda m, t: turns.append(m.tick(t).walk))
    assert d.outcome is Outcome.CAMERA_LOST and "since the start" in d.reason
    assert all(w is None or w == (0.0, 0.0, 0.0) for w in turns)


def test_a_stall_not_shorter_than_the_timeout_is_refused(tmp_path):
    path = tmp_path / "mission.yaml"
    path.write_text("mission:\n  frame_stall: 5.0\n  frame_timeout: 5.0\n")
    with pytest.raises(ConfigError, match="frame_stall"):
        load(MissionParams, [CONFIG_DIR / "mission.yaml", path], section="mission")
