"""Whole missions with real processes, real Zenoh and real MCAP on loopback.

* The default suite's mission (tests/conftest.py ``ci_mission``: matrix world 23 through the NAOqi
  stand-in over libqi, ``station start --naoqi``; its outcome and accuracy: tests/test_matrix.py):
  the log reads without warnings and ends with the robot stopped, ``station replay`` reproduces
  every decision (and reports a tampered one), ``station carve`` gives a watertight mesh that holds
  the object and is carved around it.
* The mock-robot mission (slow, ``make test-slow``): ``nao-bridge --sim`` and ``station start`` as
  two processes at QVGA in the configured room; the mission completes, centre within 1 cm and radius
  within a quarter of the radius of the simulator's truth, model IoU >= 0.5, coverage >= 90 %, never
  nearer than 0.35 m to the can, standing still soon after the final decision. CI's wheel check
  (.ci/wheel-mission) runs ``--sim`` missions from the installed wheel.
* Every failure outcome: the bridge runs in this process (so the test can make the robot fall,
  hide the object or the landmarks), the station is a separate process; the robot ends stopped,
  the log is readable, result.json says why, the exit code says failure.
* Ctrl-C (SIGINT) and SIGTERM mid-mission; the bridge process killed mid-mission.

The default suite runs one whole mission, a fall, SIGTERM and the bridge killed; the other
outcomes (object lost, landmarks lost, object not found, SIGINT, the station killed) and the
mock-robot mission are marked slow (``make test-slow``) to keep the project suite under 10 minutes.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Callable, List, Optional, Tuple

import numpy as np
import pytest
import trimesh

from nao_bridge.bridge import Bridge, BridgeParams
from nao_bridge.sim_backend import SimBackend
from nao_core.config import CONFIG_DIR, load
from nao_core.landmark_map import LandmarkMap
from nao_core.protocol import State, Truth, WalkCommand, decode
from nao_core.robot_model import load_robot_model
from nao_sim.meshes import contains
from nao_sim.randomize import fixed_world, random_world
from nao_sim.render import Renderer
from nao_sim.scenarios import load_sim_config
from nao_sim.world import SimWorld
from station.launch import free_port
from station.mcap_log import read_log
from station.topics import CMD_WALK, DECISION, KEYFRAME, KEYFRAME_POSES, POSE, STATE, TRUTH

pytestmark = pytest.mark.serial  # missions' processes: run alone (Makefile test)

PY = sys.executable
MISSION_TIMEOUT = 240.0
SIM = load_sim_config()
BRIDGE = load(BridgeParams, [CONFIG_DIR / "bridge.yaml"], section="bridge")
CAN_RADIUS = SIM.scenario("can").radius
CYLINDER_CENTRE_ERROR = 0.01  # m, issue 12's target for cylinders (a fifth of the can's radius)
MIN_CLEARANCE = 0.35  # m, issue 12: never nearer the object's surface (the planner keeps 0.45 m)
# final decision -> the robot reports standing: the stop command (at once, or the bridge's deadman),
# then the velocity lag decays below the walking threshold (1e-3 of full speed) in tau ln(1000);
# 1 s margin for a loaded machine and the 20 Hz state rate
STOP_WITHIN = BRIDGE.deadman_s + SIM.dynamics.velocity_time_constant * math.log(1e3) + 1.0


def station(*args: str, stderr: Optional[Path] = None) -> subprocess.Popen:
    err = open(stderr, "wb") if stderr else subprocess.PIPE
    return subprocess.Popen([PY, "-m", "station.cli", *args], stdout=subprocess.PIPE, stderr=err)


# Failure tests need the robot walking, not the self-calibration standstill that opens ACTIVE (station/pilot.py)
NO_STANDSTILL = "self_calibration:\n  standstill: 0.0\n"


def write_override(path: Path, port: int, standstill: bool = True, **mission: float) -> Path:
    lines = ["station:", f"  port: {port}", "mission:"] + [f"  {k}: {v}" for k, v in mission.items()]
    path.write_text("\n".join(lines if mission else lines[:-1]) + "\n" + ("" if standstill else NO_STANDSTILL))
    return path


def wait_for_text(path: Path, text: str, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and text in path.read_text(errors="replace"):
            return True
        time.sleep(0.1)
    return False


def read_clean(path: Path) -> list:
    """All messages; fails if the log needed the crash fallback (it must have been finalized)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return list(read_log(path))


def last_walk(messages) -> WalkCommand:
    return decode([m for m in messages if m.topic == CMD_WALK][-1].data, WalkCommand)


# --- full missions ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sim_mission(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim_mission")
    port = free_port()
    (out / "bridge-config.yaml").write_text("bridge:\n  resolution: qvga\n")
    bridge = subprocess.Popen([PY, "-m", "nao_bridge.cli", "--sim", "--scenario", "can", "--seed", "1",
                               "--listen", f"tcp/127.0.0.1:{port}", "--config", str(out / "bridge-config.yaml")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        proc = station("start", "--robot", "127.0.0.1", "--out", str(out / "run"),
                       "--config", str(write_override(out / "station.yaml", port)), stderr=out / "station.err")
        proc.wait(MISSION_TIMEOUT)
    finally:
        bridge.send_signal(signal.SIGTERM)
        bridge.wait(10)
    return out / "run", proc.returncode, (out / "station.err").read_text()


@pytest.mark.slow  # the default suite's mission is tests/conftest.py's ci_mission
def test_sim_mission_completes_precisely(sim_mission):
    run, code, err = sim_mission
    result = json.loads((run / "result.json").read_text())
    assert code == 0, err[-2000:]
    assert result["status"] == "success" and result["outcome"] == "completed"
    truth = result["ground_truth"]
    assert truth["centre_error"] <= CYLINDER_CENTRE_ERROR and truth["filter_centre_error"] <= CYLINDER_CENTRE_ERROR
    # the centre is the carved model's centroid (station/result.py), the filter's is kept beside it
    estimate = result["object"]
    assert estimate["centre_source"] == "model"
    assert [estimate["x"], estimate["y"]] == result["model"]["metrics"]["centroid"][:2] != [estimate["filter_x"], estimate["filter_y"]]
    assert abs(truth["radius_error"]) <= 0.25 * truth["r"]  # the estimated cylinder is the can's size
    assert result["model"]["accuracy"]["iou"] >= 0.5  # more of the model is can than not
    assert result["coverage"] >= 0.90
    for name in ("run.mcap", "model.ply", "model.glb", "voxels.npz", "trajectory.png", "cameras.png", "errors.png", "progress.png"):
        assert (run / name).stat().st_size > 0, name


@pytest.mark.slow
def test_sim_mission_kept_its_distance_and_stopped_soon_after_deciding(sim_mission):
    run, _, _ = sim_mission
    messages = read_clean(run / "run.mcap")
    truths = [decode(m.data, Truth) for m in messages if m.topic == TRUTH]
    assert len(truths) > 100
    clearance = min(math.dist(t.robot_pose[:2], t.object.centre) - t.object.radius for t in truths)
    assert clearance >= MIN_CLEARANCE
    decisions = [(m.t, m.json()) for m in messages if m.topic == DECISION]
    final = next(t for i, (t, d) in enumerate(decisions) if all(e["stop"] for _, e in decisions[i:]))
    at_rest = [m.t for m in messages if m.topic == STATE and m.t >= final and not decode(m.data, State).walking]
    assert at_rest, "the robot never reported standing still after the final decision"
    assert at_rest[0] - final <= STOP_WITHIN


@pytest.fixture(scope="module")
def ci_run(ci_mission) -> Path:
    """The run folder of the default suite's mission (tests/conftest.py)."""
    return Path(ci_mission.out) / "run"


@pytest.fixture(scope="module")
def ci_replay(ci_run) -> Tuple[subprocess.CompletedProcess, dict]:
    """``station replay`` of the mission's log, run once: the process and its JSON report."""
    run = ci_run
    replayed = subprocess.run([PY, "-m", "station.cli", "replay", str(run / "run.mcap")], capture_output=True, text=True, timeout=300)
    return replayed, json.loads(replayed.stdout) if replayed.returncode == 0 else {}


def test_the_mission_log_replays_exactly_and_the_robot_ended_stopped(ci_run, ci_replay):
    run = ci_run
    messages = read_clean(run / "run.mcap")
    topics = {m.topic for m in messages}
    assert {"/nao/camera/image", "/nao/camera/calibration", "/tf", "/scene/object", "/agent/plan", "/agent/ekf"} <= topics
    assert last_walk(messages).vx == 0.0 and last_walk(messages).omega == 0.0
    assert not decode([m for m in messages if m.topic == STATE][-1].data, State).walking
    assert [m.json()["phase"] for m in messages if m.topic == DECISION][-1] == "finished"
    replay, report = ci_replay
    assert replay.returncode == 0, replay.stderr[-2000:]
    assert report["ok"] and report["decisions"] > 100 and report["divergence"] is None


def rewritten_copy(src: Path, dst: Path, topic: str, change: Callable[[int, bytes], bytes]) -> None:
    """Copy an MCAP log, the ``i``-th message on ``topic`` replaced by ``change(i, its bytes)``."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        writer = Writer(f_out)
        writer.start()
        schemas, channels, seen = {}, {}, 0
        for schema, channel, message in make_reader(f_in).iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding, schemas[schema.id])
            data = message.data
            if channel.topic == topic:
                data = change(seen, data)
                seen += 1
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        writer.finish()


def tampered_copy(src: Path, dst: Path, topic: str, rank: int) -> None:
    """Copy an MCAP log, changing the walk command of the ``rank``-th message on ``topic``."""

    def tamper(i: int, data: bytes) -> bytes:
        if i != rank:
            return data
        return json.dumps({**json.loads(data), "walk": [0.5, 0.0, 0.5]}, separators=(",", ":")).encode()

    rewritten_copy(src, dst, topic, tamper)


def test_replay_reports_the_first_divergence(ci_run, tmp_path):
    from station.replay import replay

    run = ci_run
    tampered = tmp_path / "tampered.mcap"
    tampered_copy(run / "run.mcap", tampered, DECISION, 40)
    result = replay(tampered)
    assert not result.ok
    assert (result.divergence.topic, result.divergence.rank) == (DECISION, 40)
    assert '"walk":[0.5,0.0,0.5]' in result.divergence.recorded


def test_replay_of_a_log_recorded_before_the_lease_compares_every_output(ci_run, ci_replay, tmp_path):
    """States logged before issue 14 lack owner, stop_failures and robot_watchdog: they decode with
    their documented defaults (nao_core.protocol.State), so replay compares outputs, not 'unreadable'."""
    from station.replay import replay

    run = ci_run
    added = ("owner", "stop_failures", "robot_watchdog")
    old = tmp_path / "old_states.mcap"
    rewritten_copy(run / "run.mcap", old, STATE,
                   lambda _, data: json.dumps({k: v for k, v in json.loads(data).items() if k not in added}).encode())
    assert all(not set(added) & set(m.json()) for m in read_log(old, topics={STATE}))
    current, result = ci_replay[1], replay(old)
    assert result.unreadable is None, result.unreadable
    assert result.inputs == current["inputs"] and result.compared == current["compared"] > 0
    assert result.ok == current["ok"]  # the pilot reads none of the added fields: the same outputs


def test_the_offline_carve_is_watertight_holds_the_object_and_is_carved_around_it(ci_mission, ci_run, tmp_path):
    run = ci_run
    result = json.loads((run / "result.json").read_text())
    model = tmp_path / "model.ply"
    carve = subprocess.run([PY, "-m", "station.cli", "carve", str(run / "run.mcap"), "-o", str(model)],
                           capture_output=True, text=True, timeout=300)
    assert carve.returncode == 0, carve.stderr[-2000:]
    mesh = trimesh.load(model)
    assert mesh.is_watertight
    scenario = random_world(ci_mission.seed).scenario
    # points well inside the true object (every point 1.5 cm around them inside it too) are inside the model
    x0, y0 = scenario.position
    r, h = scenario.radius, scenario.height
    grid = np.stack(np.meshgrid(np.linspace(x0 - r, x0 + r, 15), np.linspace(y0 - r, y0 + r, 15), np.linspace(0.0, h, 12)), -1).reshape(-1, 3)
    around = np.array([[a, b, c] for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]) * 0.015
    deep = grid[np.all([scenario.contains(grid + o) for o in around], axis=0)]
    assert len(deep) >= 10
    assert contains((mesh.vertices, mesh.faces), deep).all()
    # and carved: at mid-height, twice the enclosing radius from the centre is outside the object's
    # visual hull from any horizontal view around it (an uncarved volume would keep these)
    angles = np.linspace(0, 2 * math.pi, 8, endpoint=False)
    outer = np.array([(x0 + 2.0 * r * math.cos(a), y0 + 2.0 * r * math.sin(a), 0.5 * h) for a in angles])
    assert not contains((mesh.vertices, mesh.faces), outer).any()
    assert json.loads(carve.stdout)["metrics"]["volume"] == pytest.approx(result["model"]["metrics"]["volume"], rel=1e-9)


def test_the_final_carve_logs_a_smoothed_pose_for_every_keyframe(ci_run):
    """The poses the final carve used (agent/pose_smoother.py), one per keyframe, each a planar move of
    the pose it was taken with (the smoothing moves x, y and the heading only), none for a keyframe
    with a fix on its frame; the offline carve above reproduces the run's model from them."""
    run = ci_run
    taken = {m.json()["seq"]: np.reshape(m.json()["T_WC"], (4, 4)) for m in read_log(run / "run.mcap", topics={KEYFRAME})}
    [record] = [m.json() for m in read_log(run / "run.mcap", topics={KEYFRAME_POSES})]
    fixed = {m.json()["seq"] for m in read_log(run / "run.mcap", topics={POSE}) if m.json()["landmark_fix"]}
    smoothed = {k["seq"]: np.reshape(k["T_WC"], (4, 4)) for k in record["keyframes"]}
    assert taken and smoothed.keys() == taken.keys()
    for seq, T in smoothed.items():
        if seq in fixed:
            np.testing.assert_array_equal(T, taken[seq])
            continue
        D = T @ np.linalg.inv(taken[seq])  # = T(p_smoothed) T(p_filtered)^-1
        np.testing.assert_allclose(D[2], [0.0, 0.0, 1.0, 0.0], atol=1e-9)
        np.testing.assert_allclose(D[:3, :3] @ D[:3, :3].T, np.eye(3), atol=1e-9)
        assert abs(math.atan2(D[1, 0], D[0, 0])) < 0.1 and np.hypot(*D[:2, 3]) < 0.2  # a correction, not another place


@pytest.mark.slow  # the default suite runs a randomized world through the stand-in (tests/test_matrix.py)
def test_standin_mission_through_qi_completes(tmp_path):
    """The configured world (can, the low ring, exact camera) served by the stand-in in this process
    (tools.matrix.run_mission), the station running its NAOqi bridge against it: the same guarantees
    as tests/test_matrix.py's randomized worlds."""
    from tools.matrix import run_mission

    r = run_mission(2, tmp_path, "qvga", spec=fixed_world("can", 2))
    assert r.returncode == 0 and r.outcome == "completed", r.reason
    assert r.min_clearance >= MIN_CLEARANCE and r.stopped
    assert r.stop_delay is not None and r.stop_delay <= BRIDGE.deadman_s + 1.0  # see tests/test_matrix.py
    assert "naoqi" in (tmp_path / "run" / "run.mcap").read_bytes()[:100000].decode("latin-1")  # the info says so
    assert abs(r.radius_error) <= 0.25 * CAN_RADIUS
    assert r.centre_error <= CYLINDER_CENTRE_ERROR  # frames stamped by the clock probe (docs/frames.md)
    assert r.iou >= 0.5


# --- failure outcomes ---------------------------------------------------------------------------


class InProcessBridge:
    """A simulated bridge in the test process: the test can act on its world."""

    def __init__(self, port: int, seed: int = 3):
        model = load_robot_model()
        params = load(BridgeParams, [CONFIG_DIR / "bridge.yaml"], section="bridge")
        params = dataclasses.replace(params, resolution="qvga",
                                     transport=dataclasses.replace(params.transport, listen=(f"tcp/127.0.0.1:{port}",)))
        self.world = SimWorld("can", model, resolution="qvga", seed=seed)
        self.bridge = Bridge(SimBackend(self.world, fps=params.fps), model, params, "sim")
        self.bridge.start()

    def hide(self, objects: bool = False, landmarks: bool = False) -> None:
        """Re-render the room without the object or without the landmarks."""
        r, world = self.world.renderer, self.world
        scenario = dataclasses.replace(world.scenario, position=(40.0, 40.0)) if objects else world.scenario
        world.renderer = Renderer(r.intrinsics, r.room, LandmarkMap(()) if landmarks else world.landmarks, scenario,
                                  world.config.noise.pixel_sigma, world.config.noise.gain_sigma, world.seed)

    def close(self) -> None:
        self.bridge.close()


@pytest.fixture
def sim_bridge():
    port = free_port()
    bridge = InProcessBridge(port)
    yield bridge, port
    bridge.close()


def start_station(tmp_path: Path, port: int, **mission: float) -> subprocess.Popen:
    override = write_override(tmp_path / "station.yaml", port, standstill=False, **mission)
    return station("start", "--robot", "127.0.0.1", "--out", str(tmp_path / "run"), "--config", str(override),
                   stderr=tmp_path / "err")


def finish(tmp_path: Path, proc: subprocess.Popen, outcome: str, timeout: float = 60.0) -> dict:
    proc.wait(timeout)
    err = (tmp_path / "err").read_text()
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert result["outcome"] == outcome, err[-2000:]
    assert result["status"] == "failure" and proc.returncode == 1 and result["reason"]
    messages = read_clean(tmp_path / "run" / "run.mcap")
    assert last_walk(messages).vx == 0.0 and last_walk(messages).omega == 0.0
    decisions = [m.json() for m in messages if m.topic == DECISION]
    assert decisions[-1]["outcome"] == outcome and decisions[-1]["stop"]
    return result


SLOW = pytest.mark.slow  # the default suite keeps one test per exit path; these cover the other outcomes


@pytest.mark.parametrize("event, outcome, mission", [
    ("fall", "fallen", {}),
    pytest.param("hide_object", "object_lost", {"object_lost_timeout": 1.5}, marks=SLOW),
    pytest.param("hide_landmarks", "landmarks_lost", {"landmarks_lost_timeout": 2.0}, marks=SLOW),
    pytest.param("SIGINT", "interrupted", {}, marks=SLOW),
    ("SIGTERM", "interrupted", {}),
])
def test_failure_mid_mission_stops_robot_and_says_why(sim_bridge, tmp_path, event, outcome, mission):
    bridge, port = sim_bridge
    proc = start_station(tmp_path, port, **mission)
    try:
        assert wait_for_text(tmp_path / "err", "phase active", 60.0), (tmp_path / "err").read_text()[-2000:]
        time.sleep(1.0)
        if event == "fall":
            bridge.world.inject_fall()
        elif event == "hide_object":
            bridge.hide(objects=True)
        elif event == "hide_landmarks":
            bridge.hide(landmarks=True)
        else:
            proc.send_signal(getattr(signal, event))
        result = finish(tmp_path, proc, outcome)
    finally:
        proc.kill()
    if event != "fall":  # a fallen world ignores walks: its stop is the zero walk command finish() checks
        assert not bridge.world.is_walking()
    if event.startswith("SIG"):
        assert result["reason"] == f"interrupted by {event}"


def test_the_station_s_wall_clock_stepped_an_hour_either_way_mid_mission_changes_nothing(sim_bridge, tmp_path):
    """The station PC's wall clock stepped +1 h, then back 2 h (an NTP step, a hand-set ``date``) while
    the robot walks: the station times everything on ``nao_core.clock.now`` (wall time read once, then
    the monotonic clock), so no mission timer fires (+1 h was past ``max_duration``: 'time_limit'), the
    control ticks never pause (-1 h stopped them for an hour: the robot stood, the mission stalled),
    and the log's times run on without a gap. SIGTERM then ends the mission as usual."""
    bridge, port = sim_bridge
    offset = tmp_path / "clock_offset"
    offset.write_text("0")
    override = write_override(tmp_path / "station.yaml", port, standstill=False)
    env = dict(os.environ, CLOCK_OFFSET_FILE=str(offset),
               PYTHONPATH=os.pathsep.join([str(Path(__file__).parent / "clock_jump"), os.environ.get("PYTHONPATH", "")]))
    err = tmp_path / "err"
    proc = subprocess.Popen([PY, "-m", "station.cli", "start", "--robot", "127.0.0.1", "--out", str(tmp_path / "run"),
                             "--config", str(override)], stdout=subprocess.PIPE, stderr=open(err, "wb"), env=env)
    try:
        assert wait_for_text(err, "phase active", 60.0), err.read_text()[-2000:]
        for seconds in ("3600", "-3600"):
            offset.write_text(seconds)
            time.sleep(3.0)
        proc.send_signal(signal.SIGTERM)
        result = finish(tmp_path, proc, "interrupted")
    finally:
        proc.kill()
    assert result["reason"] == "interrupted by SIGTERM"
    messages = read_clean(tmp_path / "run" / "run.mcap")
    walks = [m.t for m in messages if m.topic == CMD_WALK]
    since = [t for t in walks if t >= walks[-1] - 7.0]  # the 6 s stepped, and the stop
    assert len(since) >= 30 and max(np.diff(since)) < 1.0, np.diff(since).max()
    assert abs(time.time() - walks[-1]) < 60.0  # the log's clock is the wall clock the station started with
    assert not bridge.world.is_walking()


def test_a_map_with_the_wrong_ids_ends_landmarks_lost_naming_the_markers_seen(sim_bridge, tmp_path):
    """The simulated room's boards (DICT_4X4_50, ids 0-23) under a map that numbers them 24-47 (and has no
    balls): no fix, the mission ends 'landmarks_lost' after ``no_fix_timeout``, and its reason names the
    markers seen that the map does not hold (agent/localization.py ``LandmarkDetector.diagnosis``)."""
    bridge, port = sim_bridge
    rows = [line for line in (CONFIG_DIR / "landmarks" / "sim_room.yaml").read_text().splitlines() if "kind: aruco" in line]
    assert len(rows) == 24 and all("dictionary: DICT_4X4_50" in row for row in rows)
    shifted = [row.replace(f"{{id: {k}, ", f"{{id: {k + 24}, ", 1) for k, row in enumerate(rows)]
    assert all(f"{{id: {k + 24}, " in row for k, row in enumerate(shifted))
    (tmp_path / "wrong.yaml").write_text("landmarks:\n" + "\n".join(shifted) + "\nposition_sigma: 0.0\nyaw_sigma: 0.0\n")
    override = write_override(tmp_path / "station.yaml", port, standstill=False, no_fix_timeout=8.0)
    override.write_text(override.read_text().replace("station:\n", f"station:\n  landmark_map: {tmp_path / 'wrong.yaml'}\n", 1))
    proc = station("start", "--robot", "127.0.0.1", "--out", str(tmp_path / "run"), "--config", str(override), stderr=tmp_path / "err")
    try:
        result = finish(tmp_path, proc, "landmarks_lost")
    finally:
        proc.kill()
    assert result["reason"].startswith("no landmark fix in 8 s")
    assert "ArUco markers the map does not hold were seen (DICT_4X4_50 ids " in result["reason"], result["reason"]
    seen = result["reason"].split("DICT_4X4_50 ids ", 1)[1].split(";", 1)[0]
    assert {int(i) for i in seen.replace(", ...", "").split(", ")} <= set(range(24))


def test_an_object_of_another_colour_than_configured_ends_object_not_found_naming_its_colour(sim_bridge, tmp_path):
    """The simulated room's can is red; a station told the object is blue (a class none of the room's
    balls has) never sees it, ends 'object_not_found' after its search, and its reason names red as the
    colour class whose silhouettes the frames showed (agent/perception.py ``ColourTally``); the robot
    ends stopped."""
    bridge, port = sim_bridge
    override = write_override(tmp_path / "station.yaml", port, standstill=False, search_max_turns=0.2, search_dwell=0.3)
    override.write_text(override.read_text() + "perception:\n  object_color: blue\n")
    proc = station("start", "--robot", "127.0.0.1", "--out", str(tmp_path / "run"), "--config", str(override), stderr=tmp_path / "err")
    try:
        result = finish(tmp_path, proc, "object_not_found")
    finally:
        proc.kill()
    assert result["reason"].startswith("object not seen in a head scan"), result["reason"]
    note = result["reason"].split("silhouettes of other colour classes were seen where none of blue was (", 1)[1]
    assert note.startswith("red in ") and "set perception.object_color" in note, result["reason"]
    assert not bridge.world.is_walking()


@SLOW
def test_object_never_seen_is_object_not_found(sim_bridge, tmp_path):
    bridge, port = sim_bridge
    bridge.hide(objects=True)
    proc = start_station(tmp_path, port, search_max_turns=0.2, search_dwell=0.3)
    try:
        finish(tmp_path, proc, "object_not_found")
    finally:
        proc.kill()
    assert not bridge.world.is_walking()


def test_a_bridge_refusing_to_walk_without_the_robot_watchdog_ends_the_mission_saying_how_to_fix_it(tmp_path):
    """A NAO reached over the network needs the robot-side watchdog (issue 14); a bridge that requires
    it and does not hear it refuses every walk. The station ends the mission after
    station.watchdog_grace with that reason instead of waiting out its time limit."""
    from nao_sim.standin import StandIn

    port, grace = free_port(), 1.0
    world = SimWorld("can", load_robot_model(), resolution="qvga", seed=3)
    (tmp_path / "bridge.yaml").write_text("bridge:\n  resolution: qvga\n  robot_watchdog: required\n")
    with StandIn(world) as standin:
        bridge = subprocess.Popen([PY, "-m", "nao_bridge.cli", "--naoqi", standin.url, "--listen", f"tcp/127.0.0.1:{port}",
                                   "--config", str(tmp_path / "bridge.yaml")], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        override = write_override(tmp_path / "station.yaml", port)
        override.write_text(override.read_text().replace("station:\n", f"station:\n  watchdog_grace: {grace}\n"))
        proc = station("start", "--robot", "127.0.0.1", "--out", str(tmp_path / "run"), "--config", str(override),
                       stderr=tmp_path / "err")
        try:
            result = finish(tmp_path, proc, "bridge_lost")
        finally:
            proc.kill()
            bridge.kill()
        walks = [c for c in standin.calls_to("ALMotion.move") if any(c.args)]
    assert "no_robot_watchdog" in result["reason"] and "nao-bridge install-watchdog" in result["reason"]
    assert walks == []  # the robot never walked
    assert result["duration"] < grace + 30.0  # not the mission's time limit (180 s)


@SLOW
def test_station_killed_takes_its_sim_bridge_down(tmp_path):
    proc = station("start", "--robot", "sim", "--out", str(tmp_path / "run"), stderr=tmp_path / "err")
    try:
        assert wait_for_text(tmp_path / "err", "connecting to the bridge", 30.0)
        assert wait_for_text(tmp_path / "err", "phase", 60.0)
        children = _children(proc.pid)
        assert children, "no bridge child process"
        proc.kill()  # no cleanup at all: the kernel's parent-death signal must stop the bridge
        proc.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_alive(pid) for pid in children):
            time.sleep(0.1)
        assert not any(_alive(pid) for pid in children)
    finally:
        proc.kill()


def _children(pid: int) -> List[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(p) for p in out.split()]


def _alive(pid: int) -> bool:
    state = subprocess.run(["ps", "-o", "stat=", "-p", str(pid)], capture_output=True, text=True).stdout.strip()
    return bool(state) and not state.startswith("Z")
