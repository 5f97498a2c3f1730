"""Active localization in ACTIVE (station.pilot): an uncertain pose sends the head, every other
dwell, towards the best predicted landmark view, never takes a keyframe meanwhile, and a fix brings
it back to the object. The pilot is fed real events; only the localizer's measurement is stubbed
(a fix when the test says so, else the real detector on a blank frame: no landmarks)."""

from __future__ import annotations

import dataclasses

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import yaml

from agent.head_servo import head_target
from agent.localization import PoseFix, head_directions
from agent.mission import Phase
from nao_core.landmark_map import load_landmark_map
from nao_core.protocol import Frame, FrameMeta, Info
from nao_core.robot_model import load_robot_model
from station.config import load_station_config
from station.events import FrameReceived, StateReceived, Tick
from station.pilot import Pilot

MODEL = load_robot_model()
# the self-calibration standstill at the start of ACTIVE (tests/test_pilot.py) off: the lookout follows it
CONFIG = load_station_config()
CONFIG = dataclasses.replace(CONFIG, self_calibration=dataclasses.replace(CONFIG.self_calibration, standstill=0.0))
# ticks between sparse frames: the camera-silence rule (tests/test_mission.py) is not what is tested here
CONFIG = dataclasses.replace(CONFIG, mission=dataclasses.replace(CONFIG.mission, frame_stall=1e3, frame_timeout=2e3))
INFO = Info(bridge_version="test", backend="sim", robot=MODEL, resolution="qvga", intrinsics=MODEL.camera.intrinsics("qvga"),
            fps=15.0, state_rate_hz=20.0, deadman_s=0.3)
W, H = INFO.intrinsics.width, INFO.intrinsics.height
BLANK = cv2.imencode(".jpg", np.full((H, W, 3), 128, np.uint8))[1].tobytes()  # no landmark, no object
START = (-0.7, 0.0, 0.0)  # inside the map's landmark ring (config/landmarks), facing the object at the origin
DWELL = CONFIG.mission.gaze_dwell


def state(stamp: float, odom) -> SimpleNamespace:
    """The fields of a ``State`` the pilot reads (the bridge's health fields are not the pilot's)."""
    return SimpleNamespace(stamp=stamp, odom=tuple(odom), head_yaw=0.0, head_pitch=CONFIG.mission.init_pitch, walking=True,
                           fallen=False)


def frame(seq: int, stamp: float, odom, head=(0.0, 0.2)) -> Frame:
    meta = FrameMeta(seq=seq, stamp=stamp, width=W, height=H, encoding="jpeg", head_yaw=head[0], head_pitch=head[1],
                     T_BC=tuple(MODEL.camera_in_robot(*head).ravel()), odom=tuple(odom), resolution="qvga")
    return Frame(meta, b"", BLANK)


class Fixes:
    """Stands in for ``RobotLocalizer.measure``: a precise fix at the odometry pose when asked, else the real one."""

    def __init__(self, real):
        self.real, self.pending = real, 0

    def __call__(self, image, T_BC, prior=None, *rest):
        if self.pending:
            self.pending -= 1
            pose = prior if prior is not None else START
            return PoseFix(tuple(pose), np.diag([1e-4, 1e-4, 1e-4]), 0.1, (0,), 8, np.eye(4))
        return self.real(image, T_BC, prior, *rest)


def active_pilot(monkeypatch, config=CONFIG, target=(0.0, 0.0)):
    """A pilot in ACTIVE at START with a fresh fix and an object estimate at ``target`` (the origin)."""
    pilot = Pilot(config, INFO)
    fixes = Fixes(pilot.localizer.measure)
    monkeypatch.setattr(pilot.localizer, "measure", fixes)
    pilot.handle(StateReceived(0.0, state(0.0, (0.0, 0.0, 0.0))))
    pilot.handle(Tick(0.0))  # INIT
    pilot.handle(Tick(0.1))  # head centred: SEARCH
    fixes.pending = 1
    pilot.handle(FrameReceived(0.1, frame(1, 0.1, (0.0, 0.0, 0.0))))
    assert pilot.anchored
    pilot.ekf.initialize((START[0], START[1], math.atan2(target[1] - START[1], target[0] - START[0])), 0.0, 0.1)
    pilot.mission.on_frame(0.1, True, True, True)
    assert pilot.mission.phase is Phase.ACTIVE
    return pilot, fixes


def walk_until_uncertain(pilot, t: float) -> float:
    """Odometry walking sideways (no fix) until the pose std passes lookout_std; returns the time."""
    y = 0.0
    while pilot.localizer.position_std() <= CONFIG.mission.lookout_std:
        t, y = t + 0.05, y + 0.01
        assert y < 20.0, "dead reckoning never grew the std past lookout_std"
        pilot.handle(StateReceived(t, state(t, (0.0, y, 0.0))))
    pilot.mission.on_frame(t, True, True, True)  # keep the mission's object and fix timers fresh: this test is about the head
    return t


def object_head(pilot):
    return head_target(pilot.robot, pilot.pose, pilot.ekf.x, CONFIG.head_servo, aim_height=pilot.height.aim)


def test_an_uncertain_pose_alternates_the_head_with_the_best_landmark_view_and_a_fix_brings_it_back(monkeypatch):
    pilot, fixes = active_pilot(monkeypatch)
    t = walk_until_uncertain(pilot, 0.2)
    odom = pilot.localizer._odom
    pilot.handle(FrameReceived(t, frame(2, t, odom)))  # a frame without landmarks: no fix, the std stays
    assert pilot.localizer.position_std() > CONFIG.mission.lookout_std
    best = pilot.localizer.best_landmark_view(pilot.localizer.pose, MODEL.camera_in_robot, head_directions(MODEL.head))
    assert best is not None  # inside the ring some head direction sees enough markers
    expected = MODEL.head.clamp(best.yaw, best.pitch)

    even = (math.floor(t / DWELL / 2) + 1) * 2 * DWELL  # start of the next object dwell
    on_object = pilot.handle(Tick(even + 0.1 * DWELL)).decision
    away = pilot.handle(Tick(even + 1.1 * DWELL)).decision
    assert on_object.head == object_head(pilot) and not on_object.reason
    assert away.head == expected and "landmark lookout" in away.reason
    # the landmarks lie beside the robot, the object ahead: looking at them is looking away
    assert max(abs(away.head[0] - on_object.head[0]), abs(away.head[1] - on_object.head[1])) > CONFIG.mission.head_tolerance
    assert not pilot._gaze_on_object(even + 1.2 * DWELL, away.head)  # no keyframe while looking away

    fixes.pending = 1  # the lookout's frame gives a fix: the std drops below the threshold
    pilot.handle(FrameReceived(even + 1.2 * DWELL, frame(3, t, odom, head=away.head)))
    assert pilot.localizer.position_std() <= CONFIG.mission.lookout_std
    back = pilot.handle(Tick(even + 1.3 * DWELL)).decision  # same odd dwell, but the pose is certain again
    assert back.head == object_head(pilot) and not back.reason
    # keyframes resume once a frame shows the head back on the object
    assert not pilot._gaze_on_object(even + 1.4 * DWELL, away.head)
    assert pilot._gaze_on_object(even + 1.5 * DWELL, back.head)


def test_a_certain_pose_never_looks_away(monkeypatch):
    pilot, _ = active_pilot(monkeypatch)
    assert pilot.localizer.position_std() <= CONFIG.mission.lookout_std
    for k in range(8):  # four full object/landmark cycles
        pilot.mission.on_frame(0.2 + k * DWELL, True, True, True)  # object and landmarks seen (the mission's timers)
        decision = pilot.handle(Tick(0.2 + k * DWELL)).decision
        assert decision.head == object_head(pilot) and not decision.reason


def test_a_lookout_long_without_a_fix_stands_still_and_the_object_dwell_walks_on(monkeypatch):
    """Frames smeared by walking show no small marker: once no fix came for ``lookout_stand`` s, the
    lookouts stand (a zero walk) and say so, the first at once, alternating with the object (and the
    planner's walk), ``lookout_stand_dwell`` each."""
    pilot, _ = active_pilot(monkeypatch)
    t = walk_until_uncertain(pilot, 0.2)  # its last fix at t
    pilot.command = (0.05, 0.0, 0.1)  # what the planner asks for
    standing = t + CONFIG.mission.lookout_stand  # from here on
    first_lookout = (math.floor(t / DWELL / 2) + 1) * 2 * DWELL + 1.1 * DWELL  # the next odd dwell: soon after the fix
    assert first_lookout - t < CONFIG.mission.lookout_stand
    early = pilot.handle(Tick(first_lookout)).decision
    long_dwell = CONFIG.mission.lookout_stand_dwell
    pilot.mission.on_frame(standing, True, False, True)  # the object seen since, no fix
    away = pilot.handle(Tick(standing + 0.6 * long_dwell)).decision  # past a plain dwell
    on_object = pilot.handle(Tick(standing + 1.9 * long_dwell)).decision  # past a plain dwell
    again = pilot.handle(Tick(standing + 2 * long_dwell + 0.1)).decision
    assert standing + 2.5 * long_dwell - t < CONFIG.mission.landmarks_lost_timeout  # a second look before the mission gives up
    assert 2 * long_dwell < CONFIG.mission.object_lost_timeout  # a look and the head's way back before the object is lost
    assert "landmark lookout" in early.reason and "standing" not in early.reason and early.walk != (0.0, 0.0, 0.0)
    assert on_object.walk != (0.0, 0.0, 0.0) and not on_object.reason
    assert away.walk == (0.0, 0.0, 0.0) and "landmark lookout" in away.reason and "standing: no fix for" in away.reason
    assert again.walk == (0.0, 0.0, 0.0) and "standing" in again.reason


def test_a_fix_drought_sends_the_head_to_the_landmarks_even_when_odometry_keeps_the_pose_certain(monkeypatch):
    """The mission ends after ``landmarks_lost_timeout`` without a fix whatever the pose's std, so
    a drought of ``lookout_stand`` s looks for landmarks, standing, though the std stays small."""
    pilot, _ = active_pilot(monkeypatch)  # its fix at 0.1 s, standing still: the std stays put
    assert pilot.localizer.position_std() <= CONFIG.mission.lookout_std
    t = 0.1 + CONFIG.mission.lookout_stand + 0.5
    pilot.mission.on_frame(t, True, False, True)  # the object seen, no fix
    decision = pilot.handle(Tick(t)).decision
    assert decision.walk == (0.0, 0.0, 0.0) and "standing: no fix for" in decision.reason
    assert decision.head != object_head(pilot)


def test_a_standing_look_without_a_fix_is_not_repeated_until_a_fix(monkeypatch):
    """The predicted best view gave no fix standing: the next standing look goes elsewhere (no
    direction within FRUITLESS_RADIUS of it), and a fix makes every direction eligible again."""
    from station.pilot import FRUITLESS_RADIUS

    pilot, fixes = active_pilot(monkeypatch)
    long_dwell = CONFIG.mission.lookout_stand_dwell
    standing = 0.1 + CONFIG.mission.lookout_stand
    first = pilot.handle(Tick(standing + 0.5)).decision.head
    pilot.mission.on_frame(standing + long_dwell, True, False, True)
    pilot.handle(Tick(standing + long_dwell + 0.5))  # back on the object: that look gave nothing
    second = pilot.handle(Tick(standing + 2 * long_dwell + 0.5)).decision.head
    assert max(abs(second[0] - first[0]), abs(second[1] - first[1])) > FRUITLESS_RADIUS - 1e-9, (first, second)
    fixes.pending = 1
    t = standing + 2 * long_dwell + 1.0
    pilot.handle(FrameReceived(t, frame(9, t, (0.0, 0.0, 0.0), head=second)))  # a fix: the drought ends
    pilot.handle(Tick(t + 0.1))
    assert pilot.mission.since_fix(t) == 0.0 and not pilot._fruitless


def test_a_standing_look_goes_only_where_the_head_gets_in_time(monkeypatch):
    """With the object at the head's yaw limit, a standing look searches the directions the head reaches
    within lookout_stand_dwell - lookout_still at its speed (matrix seed 38: every look 2.7 rad away,
    the head back on the object before it got there, no fix in 20 s); those directions still predict a fix."""
    pilot, _ = active_pilot(monkeypatch)
    p = CONFIG.mission
    reach = (p.lookout_stand_dwell - p.lookout_still) * p.lookout_head_speed * MODEL.head.max_speed
    t = 0.1 + p.lookout_stand + 0.5
    pilot.mission.on_frame(t, True, False, True)  # the object seen, no fix: a standing look
    best = pilot.localizer.best_landmark_view(pilot.localizer.pose, MODEL.camera_in_robot, head_directions(MODEL.head))
    head = MODEL.head.clamp(MODEL.head.yaw[1] if best.yaw < 0.0 else MODEL.head.yaw[0], 0.3)  # the yaw limit away from it
    assert max(abs(best.yaw - head[0]), abs(best.pitch - head[1])) > reach  # the best view over the whole range: out of reach
    pilot.handle(StateReceived(t, SimpleNamespace(**{**vars(state(t, (0.0, 0.0, 0.0))), "head_yaw": head[0], "head_pitch": head[1]})))
    look = pilot.handle(Tick(t)).decision
    assert look.walk == (0.0, 0.0, 0.0) and "standing" in look.reason
    assert max(abs(look.head[0] - head[0]), abs(look.head[1] - head[1])) <= reach + 1e-9, (head, look.head, reach)
    assert pilot.localizer.predicted_fix(pilot.localizer.pose, MODEL.camera_in_robot(*look.head))[1] is not None


def one_wall(tmp_path, bearing: float):
    """The station config with one wall of six 12 cm markers 1.6 m from START at ``bearing`` (world),
    facing the robot: the room of a user who taped markers on one wall."""
    centre = np.array(START[:2]) + 1.6 * np.array([math.cos(bearing), math.sin(bearing)])
    facing = bearing - math.pi
    along = np.array([-math.sin(facing), math.cos(facing)])
    markers = [{"kind": "aruco", "dictionary": "DICT_4X4_50", "id": i, "size": 0.12, "yaw": facing,
                "position": [*map(float, centre + s * along), 0.35 if i % 2 else 0.5]}
               for i, s in enumerate(np.linspace(-0.4, 0.4, 6))]
    path = tmp_path / "one_wall.yaml"
    path.write_text(yaml.safe_dump({"landmarks": markers}))
    return dataclasses.replace(CONFIG, landmarks=load_landmark_map(path))


def test_a_standing_look_at_a_wall_beyond_the_head_s_yaw_range_turns_the_body_to_it(monkeypatch, tmp_path):
    """One marked wall behind the robot's left shoulder (2.9 rad), beyond the head's yaw limit (one-wall
    rooms: no fix for 20 s while the orbit kept the wall behind): the standing look turns the body in
    place towards it at the head's speed for lookouts, the head TURN_MARGIN inside its limit; once the
    body has turned, it stands still and the view it looks at predicts a fix."""
    from station.pilot import TURN_MARGIN

    p = CONFIG.mission
    pilot, _ = active_pilot(monkeypatch, one_wall(tmp_path, 2.9))
    pose = pilot.localizer.pose
    assert pilot.localizer.best_landmark_view(pose, MODEL.camera_in_robot, head_directions(MODEL.head)) is None
    pilot.handle(Tick(0.2))  # the head on the object (straight ahead)
    t = 0.1 + p.lookout_stand + 0.2
    pilot.mission.on_frame(t, True, False, True)  # the object seen, no fix: a standing look
    look = pilot.handle(Tick(t)).decision
    assert look.walk[:2] == (0.0, 0.0) and look.walk[2] == MODEL.walk.omega_max, look  # turning left, at full rate
    assert "turning" in look.reason and look.head_speed == p.lookout_head_speed
    assert look.head[0] == pytest.approx(MODEL.head.yaw[1] - TURN_MARGIN)
    heading = pilot._lookout.heading
    assert heading == pytest.approx(2.9 - (MODEL.head.yaw[1] - TURN_MARGIN), abs=0.15)  # the grid's 0.25 rad step

    odom = (0.0, 0.0, heading)  # the body has turned
    pilot.handle(FrameReceived(t + 1.0, frame(5, t + 1.0, odom, head=look.head)))
    pilot.mission.on_frame(t + 1.0, True, False, True)
    assert pilot.handle(Tick(t + 1.1)).decision.walk == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    assert pilot.localizer.predicted_fix(pilot.localizer.pose, MODEL.camera_in_robot(*look.head))[1] is not None


def test_a_standing_look_s_body_turn_goes_on_through_the_object_s_dwell_until_its_heading(monkeypatch, tmp_path):
    """The turn to the wall behind the shoulder (2.9 rad) outlasts a look's dwell at omega_max. In the
    object's dwell that follows, the body turns on towards the look's heading, the head on the object,
    instead of walking the plan (which turned it back: one-wall worlds 504 and 506 ended
    ``landmarks_lost``); once the heading is reached the plan's walk comes back."""
    p = CONFIG.mission
    pilot, _ = active_pilot(monkeypatch, one_wall(tmp_path, 2.9))
    pilot.command = (0.08, 0.0, -0.5)  # the plan turns the other way
    pilot.handle(Tick(0.2))
    t = 0.1 + p.lookout_stand + 0.2
    pilot.mission.on_frame(t, True, False, True)
    look = pilot.handle(Tick(t)).decision
    heading = pilot._lookout.heading
    assert heading > 0.5 and look.walk[2] > 0.0

    def object_dwell(at: float, body: float):
        pilot.handle(FrameReceived(at, frame(int(at * 10), at, (0.0, 0.0, body), head=look.head)))
        pilot.mission.on_frame(at, True, False, True)
        return pilot.handle(Tick(at)).decision

    half = object_dwell(t + p.lookout_stand_dwell + 0.2, heading / 2.0)  # the body half way round
    assert pilot._lookout is None  # the object's dwell
    assert half.walk[:2] == (0.0, 0.0) and half.walk[2] == MODEL.walk.omega_max and "turning to" in half.reason, half
    assert half.head[0] == pytest.approx(-heading / 2.0, abs=0.15)  # the head on the object, straight ahead of START
    done = object_dwell(t + p.lookout_stand_dwell + 0.8, heading)
    assert done.walk == pilot.command and "turning" not in done.reason, done


def test_a_body_turn_goes_the_way_that_keeps_the_object_in_the_head_s_range(monkeypatch, tmp_path):
    """The same wall, the object on the robot's right (-1.7 rad): the left turn the wall needs (0.6-1.1
    rad) would put the object beyond the head's right limit. With the head on the object, the
    look turns the body right instead and the head looks at the wall round the other way (yaw below
    -pi + its half field); with the head away on the left (1.0 rad) that way is out of its reach in
    time, and the standing look makes no turn."""
    from station.pilot import TURN_MARGIN

    p = CONFIG.mission
    target = (START[0] + 0.8 * math.cos(-1.7), START[1] + 0.8 * math.sin(-1.7))
    for head_yaw, turns in ((None, True), (1.0, False)):
        pilot, _ = active_pilot(monkeypatch, one_wall(tmp_path, 2.9), target)
        on_object = pilot.handle(Tick(0.2)).decision.head
        assert on_object[0] < -1.5  # the head on the object
        head = on_object if head_yaw is None else MODEL.head.clamp(head_yaw, 0.2)
        t = 0.1 + p.lookout_stand + 0.2
        pilot.handle(StateReceived(t, SimpleNamespace(**{**vars(state(t, (0.0, 0.0, 0.0))), "head_yaw": head[0], "head_pitch": head[1]})))
        pilot.mission.on_frame(t, True, False, True)
        look = pilot.handle(Tick(t)).decision
        if turns:
            assert look.walk == (0.0, 0.0, -MODEL.walk.omega_max) and "turning" in look.reason, look
            assert look.head[0] == pytest.approx(MODEL.head.yaw[0] + TURN_MARGIN)
            assert on_object[0] - (pilot._lookout.heading - START[2]) <= MODEL.head.yaw[1]  # the object stays in range
        else:
            assert look.walk == (0.0, 0.0, 0.0) and "standing" in look.reason and "turning" not in look.reason, look
            assert pilot._lookout.heading is None
