"""`station calibrate` and `station pick-colors`: camera calibration recovers a known K from synthetic chessboard views and writes a config
the robot-model loader accepts; the colour picker's ranges (red wraps through hue 0) segment the
sampled region; bad input gives an error message and exit code 2, never a traceback."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from agent.perception import ColorClass, color_mask
from agent.tone_curve import in_light
from nao_core.config import from_mapping
from nao_core.robot_model import load_robot_model, tone_curve
from station.cli import main as station

K_TRUE = np.array([[587.0, 0.0, 318.0], [0.0, 590.0, 243.0], [0.0, 0.0, 1.0]])
PATTERN = (9, 6)
SQUARE = 0.03
PX_PER_SQUARE = 40


def chessboard_texture() -> np.ndarray:
    """10 x 7 squares (9 x 6 inner corners) in a one-square white margin."""
    squares = (np.indices((PATTERN[1] + 1, PATTERN[0] + 1)).sum(axis=0) % 2) * 255
    board = np.kron(squares, np.ones((PX_PER_SQUARE, PX_PER_SQUARE))).astype(np.uint8)
    return cv2.copyMakeBorder(board, PX_PER_SQUARE, PX_PER_SQUARE, PX_PER_SQUARE, PX_PER_SQUARE, cv2.BORDER_CONSTANT, value=255)


def rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([rx, ry, rz]))[0]


def render_view(texture: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The board plane (z = 0, metres) seen by K_TRUE from pose (R, t): texture -> board -> image."""
    scale = SQUARE / PX_PER_SQUARE
    texture_to_board = np.array([[scale, 0.0, -2 * SQUARE], [0.0, scale, -2 * SQUARE], [0.0, 0.0, 1.0]])
    H = K_TRUE @ np.column_stack([R[:, 0], R[:, 1], t]) @ texture_to_board
    return cv2.warpPerspective(texture, H, (640, 480), flags=cv2.INTER_AREA, borderValue=128)


def write_views(folder, camera=lambda image: image):
    """Ten views of the board (each through ``camera``, the sensor's blur, curve and noise) as PNG files."""
    texture = chessboard_texture()
    centre = np.array([4 * SQUARE, 2.5 * SQUARE, 0.0])
    paths = []
    for k, (rx, ry, rz, z) in enumerate(
        [(0.0, 0.0, 0.0, 0.6), (0.4, 0.0, 0.1, 0.65), (-0.4, 0.1, -0.1, 0.6), (0.0, 0.45, 0.2, 0.7), (0.1, -0.45, 0.0, 0.6),
         (0.3, 0.3, 0.5, 0.75), (-0.3, -0.3, -0.4, 0.7), (0.2, -0.2, 1.2, 0.65), (-0.25, 0.35, -1.0, 0.8), (0.35, -0.1, 0.3, 0.55)]
    ):
        R = rotation(rx + math.pi, ry, rz)  # board facing the camera
        t = np.array([0.12 * (k % 3 - 1), 0.08 * (k % 2) - 0.04, z]) - R @ centre  # towards the image corners
        path = folder / f"view{k:02d}.png"
        cv2.imwrite(str(path), camera(render_view(texture, R, t)))
        paths.append(path)
    return paths


@pytest.fixture(scope="module")
def chessboard_views(tmp_path_factory):
    return write_views(tmp_path_factory.mktemp("chessboard"))


def test_clipped_views_calibrate_without_a_tone_curve(chessboard_views, tmp_path, capsys):
    """The board drawn pure black on pure white: every edge runs from 0 to 255, clipped, and tells no
    tone curve: gamma is left out (linear), with a warning and a note in the file saying why."""
    output = tmp_path / "calib.yaml"
    assert station(["calibrate", "--pattern", "9x6", "--square", str(SQUARE), "--output", str(output),
                    *map(str, chessboard_views)]) == 0
    assert "response_gamma" not in yaml.safe_load(output.read_text())["robot"]["camera"]
    assert "# tone curve not measured (0 usable chessboard edges" in output.read_text()
    assert "tone curve not measured" in capsys.readouterr().err


@pytest.mark.parametrize("gamma", [0.45, 1.0, 1.6])
def test_calibration_measures_the_camera_s_tone_curve(tmp_path, gamma):
    """Views blurred by 1 px in light, then through a tone curve (sRGB-like 0.45, linear, 1.6) and
    2 grey levels of noise: ``station calibrate`` writes robot.camera.response_gamma within 0.04 of the
    curve (agent/tone_curve.py), and the file loads as the robot model's camera."""
    rng = np.random.default_rng(int(gamma * 100))

    def camera(image: np.ndarray) -> np.ndarray:
        light = cv2.GaussianBlur(image.astype(np.float32) * 0.8 + 25.0, (0, 0), 1.0)  # 25-229: nothing clipped
        return np.clip(255.0 * (light / 255.0) ** gamma + rng.normal(0.0, 2.0, light.shape), 0, 255).astype(np.uint8)

    views = write_views(tmp_path, camera)
    output = tmp_path / "calib.yaml"
    assert station(["calibrate", "--pattern", "9x6", "--square", str(SQUARE), "--output", str(output), *map(str, views)]) == 0
    assert yaml.safe_load(output.read_text())["robot"]["camera"]["response_gamma"] == pytest.approx(gamma, abs=0.04)
    assert load_robot_model([output]).camera.response_gamma == pytest.approx(gamma, abs=0.04)


def test_calibration_recovers_a_known_K_within_1_percent(chessboard_views, tmp_path):
    output = tmp_path / "calib.yaml"
    args = ["--pattern", "9x6", "--square", str(SQUARE), "--resolution", "vga", "--output", str(output)]
    assert station(["calibrate", *args, *map(str, chessboard_views)]) == 0
    entry = yaml.safe_load(output.read_text())["robot"]["camera"]["resolutions"]["vga"]
    for key, truth in [("fx", K_TRUE[0, 0]), ("fy", K_TRUE[1, 1]), ("cx", K_TRUE[0, 2]), ("cy", K_TRUE[1, 2])]:
        assert entry[key] == pytest.approx(truth, rel=0.01), key
    assert float(output.read_text().split("RMS ")[1].split()[0]) < 0.5  # px, the fit itself
    # The file is a valid robot-config override.
    intr = load_robot_model([output]).camera.intrinsics("vga")
    assert (intr.width, intr.height) == (640, 480) and intr.fx == entry["fx"]


def test_calibration_errors_are_messages_not_tracebacks(chessboard_views, tmp_path, capsys):
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not a png")
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((240, 320), 128, np.uint8))
    base = ["--pattern", "9x6", "--square", "0.03"]
    cases = [
        ([*base, str(junk)], "cannot read"),
        ([*base, str(tmp_path / "missing.png")], "no such file"),
        ([*base, str(blank), *map(str, chessboard_views[:3])], "found in 3 of 4 images"),
        ([*base, *map(str, chessboard_views[:2]), str(small)], "320x240"),
    ]
    for argv, message in cases:
        assert station(["calibrate", *argv]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    for argv in (["--pattern", "9by6", "--square", "0.03", str(blank)], ["--pattern", "9x6", "--square", "-1", str(blank)]):
        with pytest.raises(SystemExit) as exc:
            station(["calibrate", *argv])
        assert exc.value.code == 2 and "Traceback" not in capsys.readouterr().err


def test_pick_colors_red_wraps_and_segments_the_region(tmp_path, capsys):
    rng = np.random.default_rng(0)
    hsv = np.zeros((100, 120, 3), np.uint8)
    hsv[..., 0] = rng.integers(0, 180, hsv.shape[:2])
    hsv[..., 1] = 40
    hsv[..., 2] = 200
    patch = hsv[20:60, 30:90]
    patch[..., 0] = (rng.normal(0.0, 2.0, patch.shape[:2]).round() % 180).astype(np.uint8)  # red around 0
    patch[..., 1] = rng.integers(150, 230, patch.shape[:2])
    patch[..., 2] = rng.integers(90, 200, patch.shape[:2])
    image = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    path = tmp_path / "sample.png"
    cv2.imwrite(str(path), image)
    assert station(["pick-colors", "red", f"{path}:30,20,60,40"]) == 0
    ranges = yaml.safe_load(capsys.readouterr().out)["perception"]["colors"]["red"]
    assert ranges["hue"][0] > ranges["hue"][1]  # wraps through 0
    color = from_mapping(ColorClass, ranges)
    mask = color_mask(cv2.cvtColor(image, cv2.COLOR_BGR2HSV), color)
    assert np.count_nonzero(mask[20:60, 30:90]) >= 0.97 * 40 * 60
    assert np.count_nonzero(mask) - np.count_nonzero(mask[20:60, 30:90]) == 0  # background has S = 40


def test_pick_colors_reads_the_samples_in_light_through_the_tone_curve(tmp_path, capsys):
    """A region of a blue paint in light (saturation 130-150), written through a camera's tone curve of
    0.45 (which lifts its dark channels: saturation 80 or so): with ``--gamma 0.45`` the ranges are the
    light's, as the station matches frames taken back to light (station/pilot.py), and segment it there."""
    rng = np.random.default_rng(1)
    hsv = np.zeros((60, 80, 3), np.uint8)
    hsv[..., 0] = 115
    hsv[..., 1] = rng.integers(130, 150, hsv.shape[:2])
    hsv[..., 2] = rng.integers(120, 200, hsv.shape[:2])
    light = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    path = tmp_path / "blue.png"
    cv2.imwrite(str(path), cv2.LUT(light, tone_curve(0.45)))
    for gamma, floor in (("1", 100), ("0.45", 120)):
        assert station(["pick-colors", "blue", f"{path}:0,0,80,60", "--margin-sv", "5", "--gamma", gamma]) == 0
        ranges = yaml.safe_load(capsys.readouterr().out)["perception"]["colors"]["blue"]
        assert (ranges["saturation"][0] >= floor) == (gamma == "0.45"), ranges  # encoded, the paint looks paler
    mask = color_mask(cv2.cvtColor(in_light(cv2.imread(str(path)), 0.45), cv2.COLOR_BGR2HSV),
                      from_mapping(ColorClass, ranges))
    assert np.count_nonzero(mask) >= 0.97 * mask.size
    with pytest.raises(SystemExit) as refused:  # argparse: a usage error, exit 2
        station(["pick-colors", "blue", f"{path}:0,0,8,8", "--gamma", "7"])
    assert refused.value.code == 2 and "--gamma must be in [0.2, 3], got 7" in capsys.readouterr().err


def test_pick_colors_bad_input_is_a_message(tmp_path, capsys):
    path = tmp_path / "sample.png"
    cv2.imwrite(str(path), np.zeros((50, 50, 3), np.uint8))
    assert station(["pick-colors", "red", f"{path}:40,40,20,20"]) == 2
    assert "leaves the 50x50 image" in capsys.readouterr().err
    assert station(["pick-colors", "red", f"{tmp_path / 'nope.png'}:0,0,5,5"]) == 2
    assert "no such file" in capsys.readouterr().err
    for bad in (f"{path}:1,2,3", f"{path}:0,0,0,5", "0,0,5,5"):
        with pytest.raises(SystemExit) as exc:
            station(["pick-colors", "red", bad])
        assert exc.value.code == 2 and "Traceback" not in capsys.readouterr().err
