"""HSV ranges of a colour class from sample image regions, printed as perception-config YAML.

The pixels of all regions are converted to OpenCV HSV. Hue is circular (0-179, red straddles 0),
so it is summarized around its circular mean m (angles 2 pi h / 180)::

    o = wrap(h - m) in [-90, 90),   hue = [m + P_p(o) - margin_h, m + P_{100-p}(o) + margin_h] mod 180,

a range with lo > hi wrapping through 0 as ``agent.perception.color_mask`` expects. Saturation and
value take the p and 100 - p percentiles, widened by ``margin_sv`` and clipped to [0, 255].

Usage (images from ``station capture``)::

    station pick-colors red frame1.jpg:210,140,40,60 frame2.jpg:90,100,30,30

With a camera whose tone curve is set (``robot.camera.response_gamma``), pass it as ``--gamma``: the
station matches colours in light, and so must the ranges.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path
from typing import Optional, Sequence, Tuple

import cv2
import numpy as np
import yaml

from agent.tone_curve import in_light
from nao_core.robot_model import CameraSpec

log = logging.getLogger("station.pick_colors")
Region = Tuple[Path, Tuple[int, int, int, int]]


class SampleError(ValueError):
    """A sample cannot be used (the message says why)."""


def parse_region(text: str) -> Region:
    """'IMAGE:X,Y,W,H' (pixels, top-left corner and size)."""
    path, sep, box = text.rpartition(":")
    try:
        x, y, w, h = (int(v) for v in box.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected IMAGE:X,Y,W,H, got {text!r}") from None
    if not sep or not path:
        raise argparse.ArgumentTypeError(f"expected IMAGE:X,Y,W,H, got {text!r}")
    if w <= 0 or h <= 0 or x < 0 or y < 0:
        raise argparse.ArgumentTypeError(f"region {box!r} needs x, y >= 0 and a positive width and height")
    return Path(path), (x, y, w, h)


def sample_hsv(regions: Sequence[Region], gamma: float = 1.0) -> np.ndarray:
    """HSV pixels (N x 3) of all regions, read in light through the inverse of a tone curve ``gamma``
    as the station reads frames (docs/frames.md, "The camera's tone curve")."""
    samples = []
    for path, (x, y, w, h) in regions:
        if not path.is_file():
            raise SampleError(f"{path}: no such file")
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise SampleError(f"{path}: cannot read it as an image")
        if x + w > image.shape[1] or y + h > image.shape[0]:
            raise SampleError(f"{path}: region {x},{y},{w},{h} leaves the {image.shape[1]}x{image.shape[0]} image")
        samples.append(cv2.cvtColor(in_light(image[y:y + h, x:x + w], gamma), cv2.COLOR_BGR2HSV).reshape(-1, 3))
    return np.vstack(samples).astype(float)


def hsv_ranges(hsv: np.ndarray, percentile: float, margin_h: int, margin_sv: int) -> dict:
    """Colour class {hue, saturation, value} covering the central (100 - 2p) % of the samples."""
    angles = hsv[:, 0] * (2.0 * np.pi / 180.0)
    mean = np.arctan2(np.sin(angles).mean(), np.cos(angles).mean()) * 180.0 / (2.0 * np.pi)
    offsets = (hsv[:, 0] - mean + 90.0) % 180.0 - 90.0
    lo, hi = np.percentile(offsets, [percentile, 100.0 - percentile])
    if hi - lo + 2 * margin_h >= 179:
        hue = [0, 179]
    else:
        hue = [int(np.floor(mean + lo - margin_h)) % 180, int(np.ceil(mean + hi + margin_h)) % 180]

    def channel(values: np.ndarray) -> list:
        a, b = np.percentile(values, [percentile, 100.0 - percentile])
        return [int(max(0, np.floor(a - margin_sv))), int(min(255, np.ceil(b + margin_sv)))]

    return {"hue": hue, "saturation": channel(hsv[:, 1]), "value": channel(hsv[:, 2])}


def percentile(text: str) -> float:
    value = float(text)
    if not 0.0 <= value < 50.0:
        raise argparse.ArgumentTypeError(f"--percentile must be in [0, 50), got {text}")
    return value


def gamma_arg(text: str) -> float:
    """``--gamma``: within the bounds of ``robot.camera.response_gamma`` (nao_core/robot_model.py)."""
    value = float(text)
    lo, hi = next(f for f in dataclasses.fields(CameraSpec) if f.name == "response_gamma").metadata["bounds"]
    if not lo <= value <= hi:
        raise argparse.ArgumentTypeError(f"--gamma must be in [{lo:g}, {hi:g}], got {text}")
    return value


def margin(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"margins must be non-negative, got {text}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", help="colour class name (e.g. red)")
    parser.add_argument("regions", nargs="+", type=parse_region, help="IMAGE:X,Y,W,H sample regions")
    parser.add_argument("--percentile", type=percentile, default=1.0, help="ignore this percent of outliers at each end")
    parser.add_argument("--margin-h", type=margin, default=3, help="hue margin (OpenCV units, degrees / 2)")
    parser.add_argument("--margin-sv", type=margin, default=20, help="saturation and value margin (0-255)")
    parser.add_argument("--gamma", type=gamma_arg, default=1.0,
                        help="the camera's tone curve, robot.camera.response_gamma as `station calibrate` writes it (default 1: linear)")


def run(args: argparse.Namespace) -> int:
    """``station pick-colors``: the YAML on stdout and 0, or 2 with one line naming what was wrong."""
    try:
        ranges = hsv_ranges(sample_hsv(args.regions, args.gamma), args.percentile, args.margin_h, args.margin_sv)
    except (SampleError, OSError, cv2.error) as exc:
        log.error("pick-colors: %s", exc)
        return 2
    sys.stdout.write(yaml.safe_dump({"perception": {"colors": {args.name: ranges}}}, default_flow_style=None, sort_keys=False))
    return 0
