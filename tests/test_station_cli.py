"""The `station` command line: bad input gives one clear line and an exit code, never a traceback;
a bridge the station started that exits ends the command with its last log lines and exit 2."""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import time
from typing import Tuple

import pytest

from nao_core.config import CONFIG_DIR
from nao_core.robot_model import load_robot_model
from station.config import load_station_config

pytestmark = pytest.mark.serial  # station processes and the bridges they start: run alone (Makefile test)


def station(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "station.cli", *args], capture_output=True, text=True, timeout=60)


def station_here(capsys: pytest.CaptureFixture, *args: str) -> Tuple[int, str]:
    """The command run in this process, as the console script runs it (``main`` with argparse's
    exits): its exit code and standard error. Spares the 3 s a process takes to import everything."""
    from station.cli import main

    capsys.readouterr()
    try:
        code = main(list(args))
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err


@pytest.mark.parametrize("args, code, message", [
    (["start"], 2, "one of the arguments --robot --naoqi is required"),
    (["start", "--robot", "sim", "--max-duration", "-5"], 2, "expected a positive number"),
    (["carve", "x.mcap", "--tolerance", "-1"], 2, "expected an integer >= 0"),
    (["replay", "/nonexistent/run.mcap"], 1, "No such file"),
    (["start", "--robot", "sim", "--scenario", "bogus"], 2, "invalid choice: 'bogus'"),
    (["start", "--robot", "sim", "--resolution", "xga"], 2, "invalid choice: 'xga'"),
    (["capture", "-o", "/tmp/x", "--count", "-2"], 2, "expected an integer >= 0"),
])
def test_usage_errors(capsys, args, code, message):
    returncode, stderr = station_here(capsys, *args)
    assert returncode == code and message in stderr and "Traceback" not in stderr


def test_config_error_names_file_and_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("mission:\n  search_turn_rate: fast\n")
    result = station("start", "--robot", "sim", "--config", str(bad), "--out", str(tmp_path / "run"))
    assert result.returncode == 2
    assert f"{bad}: mission.search_turn_rate: expected a number" in result.stderr and "Traceback" not in result.stderr


def test_not_a_log(capsys, tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    for command in ("replay", "carve", "report"):
        returncode, stderr = station_here(capsys, command, str(junk))
        assert returncode == 1 and str(junk) in stderr and "Traceback" not in stderr, stderr


def test_unreachable_robot_writes_result(tmp_path):
    override = tmp_path / "o.yaml"
    override.write_text("station:\n  port: 9\n  bridge_timeout: 1.0\n")
    result = station("start", "--robot", "127.0.0.1", "--config", str(override), "--out", str(tmp_path / "run"))
    assert result.returncode == 2 and "no info from the bridge" in result.stderr and "within 1 s" in result.stderr
    assert json.loads((tmp_path / "run" / "result.json").read_text())["outcome"] == "bridge_unavailable"


def test_a_run_folder_in_use_is_refused_and_left_untouched(capsys, tmp_path):
    """A second mission into a folder another station holds exits 2 naming it, before it connects
    or writes anything; once the folder is free the same command runs."""
    from station.cli import claimed

    override = tmp_path / "o.yaml"
    override.write_text("station:\n  port: 9\n  bridge_timeout: 1.0\n")
    out = tmp_path / "run"
    out.mkdir()
    command = ("start", "--robot", "127.0.0.1", "--config", str(override), "--out", str(out))
    with claimed(out):
        returncode, stderr = station_here(capsys, *command)
        assert returncode == 2 and "another station is writing a mission into this folder" in stderr and str(out) in stderr
        assert sorted(p.name for p in out.iterdir()) == [".station.lock"]
    returncode, stderr = station_here(capsys, *command)
    assert returncode == 2 and json.loads((out / "result.json").read_text())["outcome"] == "bridge_unavailable"


def test_started_bridge_that_exits_ends_the_start_with_its_log(tmp_path):
    """Nothing listens on the NAOqi port: the bridge exits at once; the station does not wait out
    bridge_timeout (set far above anything the test harness would allow) and shows why."""
    override = tmp_path / "o.yaml"
    override.write_text("station:\n  bridge_timeout: 600\n")
    from station.launch import free_port

    result = subprocess.run([sys.executable, "-m", "station.cli", "start", "--naoqi", f"tcp://127.0.0.1:{free_port()}",
                             "--config", str(override), "--out", str(tmp_path / "run")],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert "the bridge exited with code" in result.stderr and "station: error: bridge: " in result.stderr
    bridge_log = (tmp_path / "run" / "bridge.log").read_text().strip().splitlines()
    assert bridge_log[-1] in result.stderr  # its last line, verbatim
    assert json.loads((tmp_path / "run" / "result.json").read_text())["outcome"] == "bridge_unavailable"


def test_version_on_both_command_lines():
    for module in ("station.cli", "nao_bridge.cli"):
        result = subprocess.run([sys.executable, "-m", module, "--version"], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0 and result.stdout.split()[1][0].isdigit(), result


def test_help_documents_exit_codes():
    result = station("--help")
    assert result.returncode == 0
    for code in ("0 success", "1 failure", "2 configuration, usage or connection error", "3 (start) the time limit"):
        assert code in " ".join(result.stdout.split())


def test_config_names_the_file_that_set_each_key(tmp_path):
    override = tmp_path / "o.yaml"
    override.write_text("mission:\n  max_duration: 42\n")
    result = station("config", "--config", str(override), "--json")
    table = json.loads(result.stdout)
    assert table["mission.max_duration"] == {"value": 42.0, "file": str(override)}
    assert table["station.port"]["file"].endswith("station.yaml")
    assert all(entry["file"] != "default" for entry in table.values())  # every default lives in config/*.yaml


def test_quiet_and_verbose(capsys, tmp_path):
    views = tmp_path / "none"
    returncode, stderr = station_here(capsys, "-q", "capture", "--log", str(tmp_path / "missing.mcap"), "-o", str(views))
    assert returncode == 1 and "station: error:" in stderr  # errors pass -q
    log = tmp_path / "run.mcap"
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from station.mcap_log import McapLog

    with McapLog(log) as run_log:
        for i in range(5):
            run_log.proto("/nao/camera/image", CompressedImage(format="jpeg", data=b"jpeg%d" % i), float(i))
    returncode, stderr = station_here(capsys, "capture", "-q", "--log", str(log), "-o", str(views), "--every", "2")
    assert returncode == 0 and stderr == ""
    assert sorted(p.read_bytes() for p in views.iterdir()) == [b"jpeg0", b"jpeg2", b"jpeg4"]  # one per 2 s of log time
    returncode, stderr = station_here(capsys, "capture", "-v", "--log", str(log), "-o", str(tmp_path / "v"), "--count", "2")
    assert "saved frame_0002.jpg" in stderr and "capture: 2 frames" in stderr


@pytest.mark.slow
def test_mission_log_holds_every_layout_topic_and_the_console(tmp_path):
    """A full simulated mission: the Foxglove layout names only topics its log contains, the console
    lines are in it as foxglove.Log, and every frame's pose has its image annotations."""
    from foxglove_schemas_protobuf.Log_pb2 import Log

    from station import foxglove
    from station.mcap_log import read_log

    result = subprocess.run([sys.executable, "-m", "station.cli", "start", "--robot", "sim", "--out", str(tmp_path)],
                            capture_output=True, text=True, timeout=900)
    assert result.returncode in (0, 1, 3), result.stderr
    layout = json.loads((Path(__file__).resolve().parent.parent / "config" / "foxglove" / "layout.json").read_text())
    messages = list(read_log(tmp_path / "run.mcap"))
    topics = {m.topic for m in messages}
    assert foxglove.layout_topics(layout) <= topics, foxglove.layout_topics(layout) - topics
    console = [m.proto(Log).message for m in messages if m.topic == "/station/log"]
    assert "phase active" in console and any(line.startswith("mission starts") or "mission starts" in line for line in console)
    count = {t: sum(m.topic == t for m in messages) for t in ("/agent/pose", "/nao/camera/annotations", "/scene/trajectory")}
    assert count["/agent/pose"] == count["/nao/camera/annotations"] == count["/scene/trajectory"] > 0


def test_doctor_on_the_simulated_nao(tmp_path):
    """Every check prints one PASS/FAIL line; the simulated NAO's bridge, camera, clock, battery,
    posture and watchdog pass (the landmark line depends on where the robot starts)."""
    result = subprocess.run([sys.executable, "-m", "station.cli", "doctor", "--robot", "sim", "--seconds", "2"],
                            capture_output=True, text=True, timeout=300, cwd=tmp_path)
    lines = {line.split()[1].rstrip(":"): line.split()[0] for line in result.stdout.splitlines() if line[:4] in ("PASS", "FAIL")}
    for name in ("bridge", "camera", "clock", "battery", "fallen", "watchdog", "object"):  # the can starts in view
        assert lines.get(name) == "PASS", result.stdout
    assert "landmarks" in lines and "Traceback" not in result.stderr
    assert result.returncode == (0 if lines["landmarks"] == "PASS" else 1)


def test_doctor_names_the_markers_and_the_colours_in_view_that_the_configuration_does_not_hold(tmp_path):
    """The simulated NAO starts with boards 18-22 of its room in view (the map's own gives a fix there); a map
    numbering the room's 24 boards 24-47 fails the landmark line, which names the ids seen (all of 0-23) and the
    map's dictionary (agent/localization.py ``LandmarkDetector.diagnosis``). The red can is in view too: told
    the object is blue, the object line fails naming red first, the largest (the map has no balls here, so
their colours are named too; station/doctor.py ``object_check``)."""
    rows = [line for line in (CONFIG_DIR / "landmarks" / "sim_room.yaml").read_text().splitlines() if "kind: aruco" in line]
    shifted = [row.replace(f"{{id: {k}, ", f"{{id: {k + 24}, ", 1) for k, row in enumerate(rows)]
    (tmp_path / "wrong.yaml").write_text("landmarks:\n" + "\n".join(shifted) + "\nposition_sigma: 0.0\nyaw_sigma: 0.0\n")
    (tmp_path / "doctor.yaml").write_text(f"station:\n  landmark_map: {tmp_path / 'wrong.yaml'}\nperception:\n  object_color: blue\n")
    result = subprocess.run([sys.executable, "-m", "station.cli", "doctor", "--robot", "sim", "--seconds", "2", "--config",
                             str(tmp_path / "doctor.yaml")], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    line = next(line for line in result.stdout.splitlines() if "landmarks visible" in line)
    assert line.startswith("FAIL") and result.returncode == 1, result.stdout
    assert "ArUco markers the map does not hold were seen (DICT_4X4_50 ids " in line and "the map's: DICT_4X4_50" in line, line
    ids = line.split("DICT_4X4_50 ids ", 1)[1].split(";", 1)[0].replace(", ...", "").split(", ")
    assert ids and {int(i) for i in ids} <= set(range(24))
    line = next(line for line in result.stdout.splitlines() if "object in view" in line)
    assert line.startswith("FAIL") and "no blue silhouette; in view: red (" in line and "perception.object_color" in line, line


def test_capture_from_the_simulated_nao(tmp_path):
    import cv2

    result = station("capture", "--robot", "sim", "-o", str(tmp_path / "shots"), "--count", "2", "--every", "0.2")
    assert result.returncode == 0, result.stderr
    shots = sorted((tmp_path / "shots").glob("frame_*.jpg"))
    intr = load_robot_model().camera.intrinsics(load_station_config().station.resolution)  # config/station.yaml's resolution
    assert len(shots) == 2 and all(cv2.imread(str(p)).shape == (intr.height, intr.width, 3) for p in shots)


@pytest.mark.parametrize("bare", [False, True], ids=["full", "bare"])
def test_doctor_through_naoqi_on_the_standin(tmp_path, bare):
    """`doctor --naoqi`: the libqi check, then a bridge started here against the NAOqi stand-in; a bare
    one (no posture, autonomous life, ALMemory subscriber, timestamps or battery key, RGB images) passes
    the same checks, its battery "not reported"."""
    import qi

    from station.launch import free_port

    from station.config import load_station_config

    url = f"tcp://127.0.0.1:{free_port()}"
    resolution = load_station_config([]).station.resolution  # the camera mode the doctor's bridge asks for
    standin = subprocess.Popen([sys.executable, "-m", "nao_sim.standin", "--listen", url, "--resolution", resolution,
                                *(["--bare"] if bare else [])], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(600):  # readiness: until a libqi session connects
            try:
                session = qi.Session()
                session.connect(url)
                session.close()
                break
            except RuntimeError:
                assert standin.poll() is None, "the stand-in exited"
                time.sleep(0.1)
        result = subprocess.run([sys.executable, "-m", "station.cli", "doctor", "--naoqi", url, "--seconds", "2"],
                                capture_output=True, text=True, timeout=300, cwd=tmp_path)
    finally:
        standin.terminate()
        standin.wait(10)
    lines = [line for line in result.stdout.splitlines() if line[:4] in ("PASS", "FAIL")]  # libqi may add its own
    assert lines[0].startswith(f"PASS  NAOqi: {url}"), result.stdout + result.stderr
    assert lines[1].startswith("PASS  bridge: naoqi bridge"), result.stdout + result.stderr
    for check in ("camera rate", "camera frame", "clock offset", "battery", "fallen", "watchdog"):
        assert any(line.startswith(f"PASS  {check}") for line in lines), result.stdout
    assert ("PASS  battery: not reported by the robot" in lines) == bare, result.stdout


def test_bridge_killed_mid_mission_ends_it_with_exit_2(tmp_path):
    """The started bridge is killed once the mission runs: the station ends the mission (the robot
    was stopped by the bridge's death), prints its last log lines and exits 2."""
    import signal

    station_process = subprocess.Popen([sys.executable, "-m", "station.cli", "start", "--robot", "sim", "--out", str(tmp_path)],
                                       stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    try:
        for line in station_process.stderr:  # readiness: the mission has started
            if "phase" in line:
                break
        children = Path(f"/proc/{station_process.pid}/task/{station_process.pid}/children").read_text().split()
        assert len(children) == 1  # the bridge
        os.kill(int(children[0]), signal.SIGKILL)
        rest = station_process.stderr.read()
        code = station_process.wait(120)
    finally:
        if station_process.poll() is None:
            station_process.kill()
    assert code == 2, rest
    assert "the bridge exited with code -9 during the mission" in rest and "station: error: bridge: " in rest
    assert json.loads((tmp_path / "result.json").read_text())["outcome"] == "bridge_lost"
