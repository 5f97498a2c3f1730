"""Camera intrinsics and distortion from chessboard images, written as robot-config YAML.

Per image ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` give the inner corners; with the
board's corner grid X_ij = (i s, j s, 0) (s = square side) ``cv2.calibrateCamera`` minimizes the
reprojection error over K, the distortion (k1, k2, p1, p2, k3) and one pose per view. The camera's
tone curve (``robot.camera.response_gamma``) is measured from the squares' edges (agent/tone_curve.py):
left out, with a warning, when the edges cannot tell it (too sharp, too few, clipped). The result is
written in the shape of ``robot.camera`` of config/robots/nao_v6.yaml, so it can be passed to the
bridge and the station with ``--config``.

Usage (images from ``station capture``)::

    station calibrate --pattern 9x6 --square 0.025 --resolution vga --output my_nao.yaml shots/*.jpg
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np
import yaml

from agent.tone_curve import ToneCurveError, tone_gamma

MIN_VIEWS = 5
log = logging.getLogger("station.calibrate")
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)


class CalibrationError(ValueError):
    """The inputs cannot give a calibration (the message says why)."""


def parse_pattern(text: str) -> Tuple[int, int]:
    """'COLSxROWS' inner corners, e.g. '9x6'."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"pattern must be COLSxROWS inner corners (e.g. 9x6), got {text!r}") from None
    if cols < 3 or rows < 3:
        raise argparse.ArgumentTypeError(f"pattern needs at least 3x3 inner corners, got {text!r}")
    return cols, rows


def find_corners(path: Path, pattern: Tuple[int, int]) -> Tuple[Optional[np.ndarray], np.ndarray]:
    """Sub-pixel inner corners of one image (None when the board is not found) and the grey image."""
    if not path.is_file():
        raise CalibrationError(f"{path}: no such file")
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise CalibrationError(f"{path}: cannot read it as an image")
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None, gray
    return cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), _SUBPIX_CRITERIA), gray


def calibrate(paths: Sequence[Path], pattern: Tuple[int, int], square: float) -> dict:
    """Calibrate from image files; returns K, dist, size, rms, the tone curve (gamma, its standard error,
    the edges used; or the reason it was not measured) and the images used and skipped."""
    grid = np.zeros((pattern[0] * pattern[1], 3), np.float32)
    grid[:, :2] = np.mgrid[0:pattern[0], 0:pattern[1]].T.reshape(-1, 2) * square
    object_points: List[np.ndarray] = []
    image_points: List[np.ndarray] = []
    used: List[str] = []
    skipped: List[str] = []
    size: Optional[Tuple[int, int]] = None
    grays: List[np.ndarray] = []
    for path in paths:
        corners, gray = find_corners(path, pattern)
        image_size = (gray.shape[1], gray.shape[0])
        if size is not None and image_size != size:
            raise CalibrationError(f"{path}: image is {image_size[0]}x{image_size[1]}, the others {size[0]}x{size[1]}")
        size = image_size
        if corners is None:
            skipped.append(str(path))
            continue
        object_points.append(grid)
        image_points.append(corners)
        grays.append(gray)
        used.append(str(path))
    if len(used) < MIN_VIEWS:
        raise CalibrationError(
            f"the {pattern[0]}x{pattern[1]} board was found in {len(used)} of {len(paths)} images; at least {MIN_VIEWS} needed"
        )
    assert size is not None
    rms, K, dist, _, _ = cv2.calibrateCamera(object_points, image_points, size, None, None)
    try:
        tone: Union[Tuple[float, float, int], str] = tone_gamma(grays, image_points, pattern)
    except ToneCurveError as exc:
        tone = str(exc)
    return {"K": K, "dist": dist.ravel()[:5], "size": size, "rms": float(rms), "tone": tone, "used": used, "skipped": skipped}


def config_yaml(result: dict, resolution: str) -> str:
    """The calibration as a robot-config override (robot.camera.resolutions.<resolution>)."""
    K, dist, (width, height) = result["K"], result["dist"], result["size"]
    entry = {
        "width": int(width), "height": int(height),
        "fx": round(float(K[0, 0]), 4), "fy": round(float(K[1, 1]), 4),
        "cx": round(float(K[0, 2]), 4), "cy": round(float(K[1, 2]), 4),
        "dist": [round(float(d), 6) for d in dist],
    }
    header = (
        f"# station calibrate: {len(result['used'])} views, reprojection RMS {result['rms']:.3f} px\n"
        "# Pass with --config to override the robot model's intrinsics at this resolution.\n"
    )
    camera: dict = {"resolutions": {resolution: entry}}
    tone = result["tone"]
    if isinstance(tone, str):
        header += f"# tone curve not measured ({tone}): the camera is taken as linear\n"
    else:
        header += f"# tone curve: gamma {tone[0]:.3f} +- {tone[1]:.3f} from {tone[2]} edges (docs/frames.md)\n"
        camera["response_gamma"] = round(float(tone[0]), 3)
    return header + yaml.safe_dump({"robot": {"camera": camera}}, sort_keys=False)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", type=Path, help="chessboard images (all the same size)")
    parser.add_argument("--pattern", type=parse_pattern, required=True, help="inner corners COLSxROWS, e.g. 9x6")
    parser.add_argument("--square", type=positive_length, required=True, help="side of one square, m")
    parser.add_argument("--resolution", default="vga", help="resolution name in the robot config (vga, qvga)")
    parser.add_argument("--output", type=Path, help="YAML file to write (default: print)")


def positive_length(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value > 0:
        raise argparse.ArgumentTypeError(f"--square must be a positive length in metres, got {text}")
    return value


def run(args: argparse.Namespace) -> int:
    """``station calibrate``: 0, or 2 with one line naming what was wrong."""
    try:
        result = calibrate(args.images, args.pattern, args.square)
        text = config_yaml(result, args.resolution)
        if args.output is None:
            sys.stdout.write(text)
        else:
            args.output.write_text(text, encoding="utf-8")
    except (CalibrationError, OSError, cv2.error) as exc:
        log.error("calibrate: %s", exc)
        return 2
    for path in result["skipped"]:
        log.warning("calibrate: board not found in %s (skipped)", path)
    if isinstance(result["tone"], str):
        log.warning("calibrate: tone curve not measured: %s; response_gamma left out (linear)", result["tone"])
    else:
        log.info("calibrate: tone curve gamma %.3f +- %.3f", result["tone"][0], result["tone"][1])
    log.info("calibrate: %d views, RMS %.3f px", len(result["used"]), result["rms"])
    return 0
