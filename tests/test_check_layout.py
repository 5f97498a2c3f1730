"""``station check-layout``: predicted fixes on the orbit, the verdict and the figure."""

from __future__ import annotations

import argparse
import math

import pytest

from agent.camera import CameraModel
from agent.localization import RobotLocalizer
from nao_core.config import CONFIG_DIR
from nao_core.landmark_map import load_landmark_map
from nao_core.robot_model import load_robot_model
from station.check_layout import OrbitPoint, add_arguments, longest_gap, predict_orbit, run
from station.config import load_station_config


def main(argv):
    """``station check-layout ARGS`` (the subcommand's own parser and runner, as station.cli wires them)."""
    parser = argparse.ArgumentParser(prog="station check-layout")
    add_arguments(parser)
    return run(parser.parse_args(argv))


def test_a_good_layout_passes_and_draws_the_figure(tmp_path, capsys):
    png = tmp_path / "layout.png"
    code = main(["--landmarks", str(CONFIG_DIR / "landmarks" / "sim_room.yaml"), "--object", "0.1,0",
                 "--distances", "0.8", "--step", "30", "-o", str(png)])
    out = capsys.readouterr().out
    assert code == 0 and "everywhere" in out and png.stat().st_size > 10_000


def test_the_walls_say_how_much_of_the_object_the_robot_can_see(tmp_path, capsys):
    """The small 3 x 3 m room: from its middle the object is seen from all round; 0.6 m from a wall,
    the bins facing it are out of reach (agent/keep_in.py), and the line is drawn either way."""
    room = str(CONFIG_DIR / "landmarks" / "small_room.yaml")
    for obj, everywhere in (("0,0", True), ("0.9,0", False)):
        png = tmp_path / f"{obj}.png"
        main(["--landmarks", room, "--object", obj, "--distances", "0.8", "--step", "45", "-o", str(png)])
        line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("walls:"))
        assert ("of the object's 36 coverage bins" in line) and ("36 of" in line) is everywhere
        assert ("too near a wall" in line) is not everywhere and png.stat().st_size > 10_000


def test_one_marker_leaves_gaps(tmp_path, capsys):
    """A single marker on one wall: from the far side of the object it is behind the robot's head
    range or seen edge-on; the verdict names the gap and the exit code is 1."""
    lines = (CONFIG_DIR / "landmarks" / "sparse.yaml").read_text().splitlines()
    path = tmp_path / "one.yaml"
    path.write_text("\n".join(line for line in lines if not line.startswith("  - ") or "id: 0," in line))
    code = main(["--landmarks", str(path), "--object", "0,0", "--distances", "0.8", "--step", "30",
                 "-o", str(tmp_path / "one.png")])
    assert code == 1 and "gaps" in capsys.readouterr().out


def test_bad_arguments_are_usage_errors(tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["--landmarks", "x.yaml", "--object", "nan,oops"])
    assert exc.value.code == 2
    assert main(["--landmarks", str(tmp_path / "missing.yaml"), "--object", "0,0"]) == 2
    (tmp_path / "empty.yaml").write_text("landmarks: []\n")
    assert main(["--landmarks", str(tmp_path / "empty.yaml"), "--object", "0,0"]) == 2


def test_prediction_agrees_with_the_localizer_and_gaps_wrap_around():
    """The orbit prediction is the localizer's own predicted_fix (same camera, same gate)."""
    config = load_station_config([])
    robot = load_robot_model()
    camera = CameraModel.from_intrinsics(robot.camera.intrinsics("vga"))
    localizer = RobotLocalizer(config.localization, config.landmarks, camera, config.perception)
    points = predict_orbit(localizer, robot, (0.0, 0.0), config.head_servo.aim_height, (0.8,), 45.0)
    assert len(points) == 8 and all(p.best_std <= p.aimed_std for p in points)
    bad = [OrbitPoint(0.8, a, math.inf, math.inf, math.nan) for a in range(3)]
    good = OrbitPoint(0.8, 0.0, 0.01, 0.01, 0.0)
    assert longest_gap([bad[0], good, good, bad[1], bad[2]], 0.025, 10.0) == 30.0  # the last two and the first


def test_the_map_s_stated_precision_is_printed_and_widens_the_prediction(tmp_path, capsys):
    """A map that states 0 is called exact, with the warning; one that states 1 cm says so, and its
    predicted fix stds along the orbit are wider than the exact map's (agent/localization.py, Map
    error); one that states nothing is held exact, and says it was not stated."""
    exact = CONFIG_DIR / "landmarks" / "walls.yaml"
    measured, silent = tmp_path / "measured.yaml", tmp_path / "silent.yaml"
    text = exact.read_text()
    assert "position_sigma: 0.0\n" in text and "yaw_sigma: 0.0\n" in text
    measured.write_text(text.replace("position_sigma: 0.0\n", "position_sigma: 0.01\n").replace("yaw_sigma: 0.0\n", "yaw_sigma: 0.02\n"))
    silent.write_text(text.replace("position_sigma: 0.0\n", "").replace("yaw_sigma: 0.0\n", ""))
    stds = []
    for path, said in ((exact, "map precision: exact"), (measured, "map precision: 10 mm per axis"),
                       (silent, "map precision: not stated (position_sigma and yaw_sigma): held exact")):
        main(["--landmarks", str(path), "--object", "0,0", "--distances", "0.8", "--step", "45", "-o", str(tmp_path / "l.png")])
        assert said in capsys.readouterr().out
    config = load_station_config()
    robot = load_robot_model()
    camera = CameraModel.from_intrinsics(robot.camera.intrinsics("vga"))
    for path in (exact, measured):
        localizer = RobotLocalizer(config.localization, load_landmark_map(path), camera, config.perception)
        points = predict_orbit(localizer, robot, (0.0, 0.0), config.head_servo.aim_height, (0.8,), 45)
        stds.append([p.best_std for p in points])
    finite = [(narrow, wide) for narrow, wide in zip(*stds) if math.isfinite(narrow)]
    assert len(finite) >= 4 and all(wide > narrow for narrow, wide in finite)
