"""The randomized mission matrix: whole missions through the NAOqi backend in randomized worlds.

For each seed, ``nao_sim.randomize.random_world(seed)`` draws a world (a layout of the project's or
one drawn as users lay them out, object, start, walking errors, sway, camera calibration error,
frame latency, drops, clock offset, a bare NAOqi for a quarter, sensor noise, blur, brightness and
shutter); the world is served by the NAOqi stand-in
(``nao_sim.standin.StandIn``) in this process over libqi, and ``station start --naoqi`` runs the
mission against it as a separate process (its bridge drives the stand-in with YUV422 frames, RGB
from a bare one), with the layout as its landmark map and the configured (not the true) camera.
Measured against the simulator's truth:

* centre error |(x, y) - (x_true, y_true)| of the result's centre (the carved model's centroid once
  completed, docs/result.md) and of the filter's beside it, (x_true, y_true) the object's origin
  (its axis for a cylinder, a box or the mug, its bounding box's centre for a mesh); radius
  error r - r_true, r_true the object's mean
  half-breadth (``Scenario.mean_half_breadth``: what a cylinder fitted to apparent widths from all
  round converges to; the radius for a cylinder, less than the enclosing radius for other shapes);
* IoU of the final model (voxels.npz) with the true object voxelized on the model's lattice, grown
  to hold the whole object (``Scenario.contains``: exact for meshes too);
* minimum clearance: the least horizontal distance from the true robot origin to the object's
  outline, sampled every ``POLL`` s while the mission runs;
* pose error: median and 95th percentile of |(x, y) - (x_true, y_true)| and of |theta - theta_true|
  over the anchored poses the station logged (/agent/pose, at each frame's capture stamp), the truth
  interpolated at that stamp from the same samples (the stand-in's world runs on this clock);
* keyframe misalignment: per keyframe (/agent/keyframe), the distance (px) between where the T_WC the
  final carve used (/station/keyframe_poses; else the keyframe's own) and the true camera of that
  capture (recorded at each render) project the object's centre at mid-height: what the carve's intersection of silhouettes suffers from;
* the stop: the first ALMotion call that stops the walk (stopMove, killMove, move(0, 0, 0)) after
  the station's final decision, and
  whether the robot is at rest when the station has exited;
* the focal error the mission ended with: max over both axes of |s - s_true|, s the focal scale
  error of the last self-calibration estimate applied (/agent/self_calibration, 0 when none was),
  s_true the world's (its true over the configured focal length, less one);
* the camera tilt error: |b - b_true| of the roll and the pitch of the camera on its mount
  (agent/camera_tilt.py), b the rotation between the reported (/nao/camera/meta) and the corrected
  (/agent/pose) T_BC of the last logged pose, b_true the world's ``mount_error`` with, in pitch,
  what the camera's principal point error amounts to (a row shift is a pitch):
  pitch_true = pitch_mount - (c_y,true - c_y) / f_y, c_y the configured one with the applied
  self-calibration's d_v.

    python -m tools.matrix [--count 40] [--first-seed 0] [--resolution vga] [--out runs/matrix]
                           [--doc docs/benchmarks.md] [--rebuild] [--ranges config/stress.yaml] [--one-wall]

``--rebuild`` runs no mission: it rewrites the table from the runs already in ``--out`` (each
seed's matrix.json, the radius error recomputed from its result.json), e.g. after an interrupted run.
``--ranges FILE`` merges FILE's ``randomizer`` section over config/sim.yaml's and writes the table to
the document's ``stress`` section instead: config/stress.yaml widens every range beyond what the
matrix promises (docs/benchmarks.md, "Stress worlds"), to find what breaks first. ``--one-wall``
runs each seed's world with its layout drawn as users lay them out and cut to its most-marked wall
(``random_world(seed, one_wall_only=True)``; a user who taped landmarks on one wall) and writes the
``one_wall`` section.

A benchmark, not a test: a few fixed seeds run in the default suite (tests/test_matrix.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np
import yaml

from agent.camera import CameraModel
from nao_core.config import ConfigError
from nao_sim.randomize import Randomizer, RandomWorld, WorldSpec, load_randomizer, random_world
from nao_sim.standin import StandIn
from station.carve import keyframe_camera
from station.config import load_station_config
from station.mcap_log import read_log
from station.topics import DECISION, FRAME_META, KEYFRAME, KEYFRAME_POSES, POSE, SELF_CALIBRATION
from tools.bench import BEGIN, END, section

BLURRED = 0.7  # px at VGA: worlds blurred at least this much are counted apart in the table
POLL = 0.02  # s, truth sampling period for the clearance (<= 2 mm of walking at 0.1 m/s)
STOP_CALLS = ("ALMotion.stopMove", "ALMotion.killMove")
MISSION_TIMEOUT = 400.0  # s of wall time, beyond the mission's own limit (start-up, final carve, outputs)


@dataclasses.dataclass(frozen=True)
class MissionResult:
    seed: int
    world: dict
    outcome: str
    reason: str
    returncode: int
    centre_error: Optional[float]  # m
    radius_error: Optional[float]  # m
    iou: Optional[float]
    min_clearance: float  # m
    pose_error: Optional[Tuple[float, float]]  # m, median and 95th percentile of the logged poses' position error
    heading_error: Optional[Tuple[float, float]]  # rad, the same for the heading
    keyframe_shift: Optional[Tuple[float, float]]  # px, median and maximum misalignment of the carve's keyframes
    duration: Optional[float]  # s, the station's mission time
    stop_delay: Optional[float]  # s, final decision -> first stop call on the robot
    stopped: bool  # the robot at rest once the station exited
    out: str
    focal_error: Optional[float] = None  # relative, the camera the mission ended with (module docstring)
    self_calibrated: bool = False  # a self-calibration estimate was applied
    filter_centre_error: Optional[float] = None  # m, the filter's centre (module docstring)
    min_wall_distance: Optional[float] = None  # m, the true robot origin's least distance to a wall of the room
    tilt_error: Optional[Tuple[float, float]] = None  # rad, the learnt camera tilt's roll and pitch error (module docstring)


class _ClearanceMonitor(threading.Thread):
    """Samples the true robot pose every POLL s; keeps the least distance to the object's outline and
    to the room's walls (at +-half_size)."""

    def __init__(self, world: RandomWorld):
        super().__init__(daemon=True)
        self._world = world
        self._outline = world.scenario.world_points()[:, :2]
        self._half_size = world.config.room.half_size
        self.minimum = math.inf
        self.wall = math.inf
        self.trace: List[Tuple[float, float, float, float]] = []  # (time, x, y, theta) of the true pose
        self._done = threading.Event()

    def run(self) -> None:
        while not self._done.wait(POLL):
            x, y, theta = self._world.true_pose()
            self.trace.append((time.time(), x, y, theta))
            self.minimum = min(self.minimum, float(np.hypot(*(self._outline - (x, y)).T).min()))
            self.wall = min(self.wall, self._half_size - max(abs(x), abs(y)))

    def stop(self) -> float:
        self._done.set()
        self.join()
        return self.minimum


def model_iou(voxels: Path, spec: WorldSpec) -> float:
    """IoU of the model's occupied voxels with the true object on the same lattice (module docstring)."""
    data = np.load(voxels)
    occupancy, origin, pitch = data["occupancy"], data["origin"], float(data["pitch"])
    points = spec.scenario.world_points()
    lo = np.minimum(np.floor((points.min(axis=0) - origin) / pitch), 0).astype(int)
    hi = np.maximum(np.ceil((points.max(axis=0) - origin) / pitch) + 1, occupancy.shape).astype(int)
    model = np.zeros(hi - lo, dtype=bool)
    model[tuple(slice(-l, -l + n) for l, n in zip(lo, occupancy.shape))] = occupancy
    axes = [origin[a] + pitch * np.arange(lo[a], hi[a]) for a in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    true = spec.scenario.contains(centres).reshape(model.shape)
    either = np.count_nonzero(model | true)
    return float(np.count_nonzero(model & true) / either) if either else 0.0


def pose_errors(poses: List[dict], trace: List[Tuple[float, float, float, float]]) -> Tuple[Optional[Tuple[float, float]], ...]:
    """(median, 95th percentile) of the anchored logged ``poses``' (/agent/pose records) position and
    heading errors (module docstring); None where there is none."""
    if len(trace) < 2:
        return None, None
    t, x, y, theta = np.asarray(trace).T
    theta = np.unwrap(theta)
    position, heading = [], []
    for record in poses:
        stamp = record.get("stamp")
        if not record.get("anchored") or stamp is None or not t[0] <= stamp <= t[-1]:
            continue
        px, py, ptheta = record["pose"]
        position.append(math.hypot(px - np.interp(stamp, t, x), py - np.interp(stamp, t, y)))
        heading.append(abs(math.remainder(ptheta - np.interp(stamp, t, theta), 2.0 * math.pi)))
    stats = lambda v: (float(np.median(v)), float(np.percentile(v, 95))) if v else None  # noqa: E731
    return stats(position), stats(heading)


def keyframe_shifts(log: Path, poses: List[dict], renders: Dict[float, np.ndarray], spec: WorldSpec,
                    resolution: str) -> Optional[Tuple[float, float]]:
    """(median, maximum) over the carve's keyframes of how far (px) the object's centre at mid-height,
    seen through the logged T_WC and K (the configured one in logs without), lands from where the true camera of that
    capture sees it at the end of its exposure: the misalignment the carve suffers (with the camera's turn over the
    part of the exposure after the frame's stamp). ``poses``: the log's /agent/pose records."""
    stamps = {record["seq"]: record["stamp"] for record in poses}
    camera = CameraModel.from_intrinsics(spec.station_robot().camera.intrinsics(resolution))
    true_camera = CameraModel.from_intrinsics(spec.robot.camera.intrinsics(resolution))
    points = spec.scenario.world_points()
    centre = np.array([[*spec.scenario.position, 0.5 * float(points[:, 2].max())]])
    captured = np.array(sorted(renders))
    shifts = []
    smoothed = {int(k["seq"]): k["T_WC"] for message in read_log(log, topics={KEYFRAME_POSES}) for k in message.json()["keyframes"]}
    for message in read_log(log, topics={KEYFRAME}):
        record = message.json()
        record["T_WC"] = smoothed.get(record["seq"], record["T_WC"])  # the pose the final carve used
        stamp = stamps.get(record["seq"])
        if stamp is None or not len(captured):
            continue
        nearest = captured[np.argmin(np.abs(captured - stamp))]
        if abs(nearest - stamp) > 0.005 + spec.config.noise.shutter:  # a frame is stamped within its exposure (docs/frames.md)
            continue
        logged, _ = keyframe_camera(camera, record).project_world(centre, np.asarray(record["T_WC"], dtype=float).reshape(4, 4))
        true, _ = true_camera.project_world(centre, renders[nearest])
        shifts.append(float(np.hypot(*(logged[0] - true[0]))))
    return (float(np.median(shifts)), float(np.max(shifts))) if shifts else None


def focal_error(applied: List[dict], spec: WorldSpec, resolution: str) -> Tuple[float, bool]:
    """(max over axes of |s - s_true|, any applied): the focal scale error the mission ended with, from
    its /agent/self_calibration messages in log order (module docstring)."""
    true, configured = spec.robot.camera.intrinsics(resolution), spec.station_robot().camera.intrinsics(resolution)
    s_true = np.array([true.fx / configured.fx - 1.0, true.fy / configured.fy - 1.0])
    s = np.array(applied[-1]["error"][:2]) if applied else np.zeros(2)
    return float(np.abs(s - s_true).max()), bool(applied)


def _log_records(log: Path) -> Tuple[List[dict], List[dict], Dict[int, list]]:
    """The log's /agent/pose records, /agent/self_calibration messages and reported T_BC by frame seq, in one read."""
    poses, applied, reported = [], [], {}
    for m in read_log(log, topics={POSE, SELF_CALIBRATION, FRAME_META}):
        record = m.json()
        if m.topic == POSE:
            poses.append(record)
        elif m.topic == SELF_CALIBRATION:
            applied.append(record)
        else:
            reported[record.get("seq")] = record.get("T_BC")
    return poses, applied, reported


def tilt_error(poses: List[dict], reported_T_BC: Dict[int, list], spec: WorldSpec, resolution: str,
               applied: List[dict]) -> Optional[Tuple[float, float]]:
    """(|roll error|, |pitch error|) of the camera tilt the mission ended with, from its /agent/pose
    records, the reported T_BC of their frames and its /agent/self_calibration messages (module docstring)."""
    if not poses:
        return None
    last = poses[-1]
    reported = reported_T_BC.get(last["seq"])
    if reported is None:
        return None
    R = np.asarray(reported, dtype=float).reshape(4, 4)[:3, :3].T @ np.asarray(last["T_BC"], dtype=float).reshape(4, 4)[:3, :3]
    omega = cv2.Rodrigues(R)[0].ravel()  # optical axes: roll about z, pitch down about -x
    roll, pitch = spec.config.noise.mount_error
    true, configured = spec.robot.camera.intrinsics(resolution), spec.station_robot().camera.intrinsics(resolution)
    c_y = configured.cy + (applied[-1]["error"][3] if applied else 0.0)
    return abs(float(omega[2]) - roll), abs(float(-omega[0]) - (pitch - (true.cy - c_y) / true.fy))


def _final_decision_time(log: Path) -> Optional[float]:
    """Log time (station clock, s since the epoch) of the first decision of the final run of stops."""
    decided = None
    for message in read_log(log, topics={DECISION}):
        stop = bool(message.json().get("stop"))
        decided = (decided if decided is not None else message.t) if stop else None
    return decided


def run_mission(seed: int, out: Path, resolution: Optional[str] = None, max_duration: Optional[float] = None,
                spec: Optional[WorldSpec] = None) -> MissionResult:
    """One mission in world ``spec`` (default: ``random_world(seed)``) at ``resolution`` (default: the
    station's, config/station.yaml); the run's files go to ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    resolution = resolution or load_station_config().station.resolution
    spec = spec or random_world(seed)
    (out / "world.json").write_text(json.dumps(spec.summary(), indent=2) + "\n")
    landmarks = out / "landmarks.yaml"  # the run keeps the map it was given (a drawn layout's lives in a temporary folder)
    landmarks.write_text(spec.station_map())
    override = out / "station.yaml"
    override.write_text(yaml.safe_dump({"station": {"landmark_map": str(landmarks.resolve()), "resolution": resolution},
                                        "perception": {"object_color": spec.object_color}, **spec.station_overrides()}))
    world = RandomWorld(spec, resolution=resolution)
    monitor = _ClearanceMonitor(world)
    renders: Dict[float, np.ndarray] = {}  # capture stamp -> true T_WC of every image the stand-in renders
    render = world.render

    def recording_render(at: Optional[float] = None):
        frame = render(at)
        camera = world.truth()["camera"]
        renders[camera["stamp"]] = np.asarray(camera["T_WC"])
        return frame

    world.render = recording_render
    command = [sys.executable, "-m", "station.cli", "start", "--out", str(out / "run"), "--config", str(override)]
    if max_duration is not None:
        command += ["--max-duration", str(max_duration)]
    with StandIn(world, bare=spec.bare_naoqi) as standin, open(out / "station.err", "wb") as err:
        monitor.start()
        proc = subprocess.Popen([*command, "--naoqi", standin.url], stdout=subprocess.DEVNULL, stderr=err)
        try:
            proc.wait(MISSION_TIMEOUT + (max_duration or 0.0))
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        clearance = monitor.stop()
        stopped = not world.is_walking()
        calls = standin.calls
    run = out / "run"
    result = json.loads((run / "result.json").read_text()) if (run / "result.json").exists() else {}
    estimate = result.get("object")
    centre_error = filter_centre_error = radius_error = iou = stop_delay = None
    if estimate:
        centre_error, filter_centre_error = _centre_errors(estimate, spec)
        radius_error = _radius_error(estimate, spec)
    if (run / "voxels.npz").exists():
        iou = model_iou(run / "voxels.npz", spec)
    decided = _final_decision_time(run / "run.mcap") if (run / "run.mcap").exists() else None
    pose_error, heading_error, keyframe_shift, focal, tilt = None, None, None, (None, False), None
    if (run / "run.mcap").exists():
        poses, applied, reported = _log_records(run / "run.mcap")
        pose_error, heading_error = pose_errors(poses, monitor.trace)
        keyframe_shift = keyframe_shifts(run / "run.mcap", poses, renders, spec, resolution)
        focal = focal_error(applied, spec, resolution)
        tilt = tilt_error(poses, reported, spec, resolution, applied)
    if decided is not None:
        after = [c.time for c in calls if c.time >= decided and (c.name in STOP_CALLS or (c.name == "ALMotion.move" and not any(c.args)))]
        stop_delay = after[0] - decided if after else None
    return MissionResult(spec.seed, spec.summary(), result.get("outcome", "no result"), result.get("reason", ""), proc.returncode,
                         centre_error, radius_error, iou, clearance, pose_error, heading_error, keyframe_shift, result.get("duration"), stop_delay,
                         stopped, str(out), focal_error=focal[0], self_calibrated=focal[1], filter_centre_error=filter_centre_error,
                         min_wall_distance=monitor.wall, tilt_error=tilt)


def _stored_result(path: Path, spec: WorldSpec, resolution: str) -> MissionResult:
    """A mission's matrix.json, its centre and radius errors taken again from its result.json and its
    focal and tilt errors from its log (module docstring)."""
    fields = json.loads(path.read_text())
    fields = {k: tuple(v) if isinstance(v, list) and k != "world" else v for k, v in fields.items()}
    run = path.parent / "run"
    estimate = json.loads((run / "result.json").read_text()).get("object") if (run / "result.json").exists() else None
    fields["radius_error"] = _radius_error(estimate, spec) if estimate else None
    fields["centre_error"], fields["filter_centre_error"] = _centre_errors(estimate, spec) if estimate else (None, None)
    if (run / "run.mcap").exists():
        poses, applied, reported = _log_records(run / "run.mcap")
        fields["focal_error"], fields["self_calibrated"] = focal_error(applied, spec, resolution)
        fields["tilt_error"] = tilt_error(poses, reported, spec, resolution, applied)
    return MissionResult(**fields)


def _centre_errors(estimate: dict, spec: WorldSpec) -> Tuple[float, float]:
    """(result's, filter's) distance to the object's origin; a result.json from before the model's
    centre (no ``filter_x``) has the filter's as its centre."""
    x0, y0 = spec.scenario.position
    filter_xy = (estimate.get("filter_x", estimate["x"]), estimate.get("filter_y", estimate["y"]))
    return math.hypot(estimate["x"] - x0, estimate["y"] - y0), math.hypot(filter_xy[0] - x0, filter_xy[1] - y0)


def _radius_error(estimate: dict, spec: WorldSpec) -> float:
    """r - r_true against the object's mean half-breadth (module docstring)."""
    return estimate["r"] - spec.scenario.mean_half_breadth


def _fmt(value: Optional[float], scale: float = 1.0, digits: int = 1) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{scale * value:.{digits}f}"


def _pair(values: Optional[Tuple[float, float]], scale: float, digits: int = 1) -> str:
    return "-" if values is None else f"{_fmt(values[0], scale, digits)} / {_fmt(values[1], scale, digits)}"


MATRIX_COMMAND = "`make matrix`, `python -m tools.matrix`"  # what the matrix section says ran it


def table(results: List[MissionResult], resolution: str, machine: str = "", ranges: Optional[Randomizer] = None,
          command: str = MATRIX_COMMAND) -> str:
    """Markdown: a summary per object kind and overall, then one row per mission; ``machine`` says where and
    when, ``ranges`` the randomizer the worlds were drawn with (default config/sim.yaml's), ``command`` what ran them."""
    done = [r for r in results if r.outcome == "completed"]

    def stats(rows: List[MissionResult], label: str) -> str:
        ok = [r for r in rows if r.outcome == "completed"]
        centre = [r.centre_error for r in ok if r.centre_error is not None]
        filter_centre = [r.filter_centre_error for r in ok if r.filter_centre_error is not None]
        radius = [abs(r.radius_error) for r in ok if r.radius_error is not None]
        iou = [r.iou for r in ok if r.iou is not None]
        dur = [r.duration for r in ok if r.duration is not None]
        focal = [r.focal_error for r in ok if r.focal_error is not None]
        walls = [r.min_wall_distance for r in rows if r.min_wall_distance is not None]
        tilt = [max(r.tilt_error) for r in ok if r.tilt_error is not None]
        med = lambda v, s=1.0, d=1: _fmt(float(np.median(v)) if v else None, s, d)  # noqa: E731
        return (f"| {label} | {len(ok)}/{len(rows)} | {sum(r.outcome == 'error' for r in rows)} | {med(centre, 1000)} | "
                f"{_fmt(max(centre) if centre else None, 1000)} | {med(filter_centre, 1000)} / "
                f"{_fmt(max(filter_centre) if filter_centre else None, 1000)} | {med(radius, 1000)} | {med(iou, 1, 3)} | "
                f"{_fmt(min(r.min_clearance for r in rows), 1, 3)} | {_fmt(min(walls) if walls else None, 1, 3)} | {med(dur, 1, 0)} | {med(focal, 100, 2)} / "
                f"{_fmt(max(focal) if focal else None, 100, 2)} | {sum(r.self_calibrated for r in ok)} | "
                f"{med(tilt, 180 / math.pi, 2)} / {_fmt(max(tilt) if tilt else None, 180 / math.pi, 2)} |")

    objects = sorted({r.world["object"] for r in results})
    bare = [r for r in results if r.world.get("bare_naoqi")]
    blurred = [r for r in results if r.world.get("blur_sigma", 0.0) >= BLURRED]
    ranges = ranges or load_randomizer()
    users = [r for r in results if r.world["layout"].startswith("drawn")]
    lines = [
        f"{len(results)} randomized missions ({command}) at {resolution.upper()}, each through the NAOqi backend "
        f"against the stand-in (YUV422, latency, drops, clock offset; {100 * ranges.bare_naoqi:g} % of them a bare NAOqi: "
        "docs/bridge.md), in a random landmark layout (one of config/landmarks, or for "
        f"{100 * ranges.drawn_layout.share:g} % of the worlds one drawn as users lay them out: a room of "
        f"{2 * ranges.drawn_layout.half_size[0]:g}-{2 * ranges.drawn_layout.half_size[1]:g} m, markers or balls or both on "
        f"{ranges.drawn_layout.walls[0]}-{ranges.drawn_layout.walls[1]} walls; nao_sim/layouts.py), with a random object "
        f"painted {', '.join(sorted(ranges.object_colors))} (a colour no ball of the map has, the station told it) with a gloss of "
        f"{ranges.object_gloss[0]:g}-{ranges.object_gloss[1]:g}, start pose "
        f"({ranges.start_distance[0]:g}-{ranges.start_distance[1]:g} m, object up to {math.degrees(ranges.start_bearing):.0f} deg off the heading), "
        f"walking errors, sway, a camera calibration off by {100 * ranges.focal_error:g} % and {ranges.principal_error:g} px, a lens "
        f"distortion within k1 +-{ranges.lens_distortion[0]:g}, k2 +-{ranges.lens_distortion[1]:g}, p1 and p2 +-{ranges.lens_distortion[2]:g} "
        "(calibrated: the station told it), the camera "
        f"rolled up to {math.degrees(ranges.mount_error[0]):.1f} deg and pitched up to {math.degrees(ranges.mount_error[1]):.1f} deg on its mount "
        "(unreported), and a sensor "
        f"of {ranges.pixel_sigma[0]:g}-{ranges.pixel_sigma[1]:g} grey levels of noise, {ranges.blur_sigma[0]:g}-{ranges.blur_sigma[1]:g} px of blur "
        f"and {ranges.exposure[0]:g}-{ranges.exposure[1]:g} of the brightness, its shutter open {1e3 * ranges.shutter[0]:g}-{1e3 * ranges.shutter[1]:g} ms "
        f"(motion blur), its tone curve a gamma of {ranges.response_gamma[0]:g}-{ranges.response_gamma[1]:g} ({'calibrated: the station told it' if ranges.response_gamma_told else 'not told the station, which reads frames as linear'}), in a room painted one of {len(ranges.floor_colors)} floors and {len(ranges.wall_colors)} walls, lit from any azimuth "
        f"{math.degrees(ranges.light_elevation[0]):.0f}-{math.degrees(ranges.light_elevation[1]):.0f} deg up with "
        f"{ranges.ambient[0]:g}-{ranges.ambient[1]:g} of ambient light{_map_sentence(ranges)}. Errors over completed missions (centre: the result's, the carved model's "
        "centroid; filter: the filter's cylinder; both against the object's origin); clearance is the least over all missions (true robot "
        "origin to the object's outline), the wall distance the least from it to the room's walls; focal error: the camera the mission ended with against the world's, "
        "self-calibrated or configured; tilt error: the larger of the learnt camera roll's and pitch's on its mount against the world's "
        f"(tools/matrix.py).{(' ' + machine) if machine else ''}",
        "",
        "| object | completed | error | centre median (mm) | centre max (mm) | filter centre median / max (mm) | abs radius error median (mm) | IoU median | min clearance (m) | min wall distance (m) | duration median (s) | focal error median / max (%) | self-calibrated | tilt error median / max (deg) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *[stats([r for r in results if r.world["object"] == o], o) for o in objects],
        stats(results, "**all**"),
        "",
        f"Through a bare NAOqi: {sum(r.outcome == 'completed' for r in bare)}/{len(bare)} completed; sensor blur "
        f"of {BLURRED:g} px or more: {sum(r.outcome == 'completed' for r in blurred)}/{len(blurred)} completed; in a drawn layout: "
        f"{sum(r.outcome == 'completed' for r in users)}/{len(users)} completed.",
        "",
        "| seed | layout | object | outcome | centre (mm) | filter centre (mm) | radius (mm) | IoU | pose error median / p95 (mm) | keyframe misalignment median / max (px) | heading error median (mrad) | clearance (m) | wall distance (m) | duration (s) | stop after decision (ms) | focal error (%) | tilt error roll / pitch (deg) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *[f"| {r.seed} | {r.world['layout']} | {r.world['object']} | {r.outcome} | {_fmt(r.centre_error, 1000)} | "
          f"{_fmt(r.filter_centre_error, 1000)} | {_fmt(r.radius_error, 1000)} | {_fmt(r.iou, 1, 3)} | {_pair(r.pose_error, 1000)} | {_pair(r.keyframe_shift, 1)} | "
          f"{_fmt(r.heading_error[0] if r.heading_error else None, 1000)} | {_fmt(r.min_clearance, 1, 3)} | "
          f"{_fmt(r.min_wall_distance, 1, 3)} | {_fmt(r.duration, 1, 0)} | {_fmt(r.stop_delay, 1000, 0)} | "
          f"{_fmt(r.focal_error, 100, 2)}{'' if r.self_calibrated else ' (configured)'} | {_pair(r.tilt_error, 180 / math.pi, 2)} |"
          for r in results],
    ]
    if len(done) < len(results):
        lines += ["", "Reasons of the missions that did not complete:", ""]
        lines += [f"- seed {r.seed}: `{r.outcome}`: {r.reason[:200]}" for r in results if r.outcome != "completed"]
    return "\n".join(lines)


def _map_sentence(ranges: Randomizer) -> str:
    """How the station's map is off the world's, for the table's first sentence ("" when exact)."""
    position, yaw = ranges.map_error
    if not position and not yaw:
        return ""
    return (f", the station's landmark map measured off by N(0, {1e3 * position:g} mm) per axis and each marker's facing by "
            f"N(0, {math.degrees(yaw):g} deg) (nao_sim/layouts.py `measured`), the map {'saying' if ranges.map_error_told else 'not saying'} so")


SECTIONS = {"matrix": "Mission matrix: randomized worlds through the NAOqi stand-in",
            "stress": "Stress worlds: the matrix with its ranges widened (`--ranges`, config/stress.yaml)",
            "map_error": "Maps measured off: the matrix's worlds, the station's map off as a tape measures it (`--ranges config/map_error.yaml --section map_error`)",
            "one_wall": "One-wall rooms: the matrix's worlds with landmarks on one wall only (`--one-wall`)"}
ONE_WALL_NOTE = ("Each world is the matrix's world of the same seed, its layout drawn as users lay them out and cut to its "
                 "most-marked wall (nao_sim/layouts.py `one_wall`); the layout sentence below is the draw before the cut.\n\n")


def write_section(doc: Path, body: str, name: str = "matrix") -> None:
    """Replace (or append) the ``name`` section (of ``SECTIONS``) of the benchmarks document, as tools/bench.py does."""
    text = doc.read_text() if doc.exists() else "# Benchmarks\n"
    new = section(name, f"## {SECTIONS[name]}\n\n" + body)
    pattern = re.compile(re.escape(BEGIN.format(name=name)) + r".*?" + re.escape(END.format(name=name)) + r"\n", re.S)
    doc.write_text(pattern.sub(lambda _: new, text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + new)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=40, help="missions (seeds first-seed .. first-seed + count - 1)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--resolution", default=None, help="camera resolution (default: config/station.yaml's)")
    parser.add_argument("--out", type=Path, default=Path("runs/matrix"))
    parser.add_argument("--doc", type=Path, default=Path("docs/benchmarks.md"), help="document whose matrix section is rewritten")
    parser.add_argument("--rebuild", action="store_true", help="no missions: the table from the runs already in --out")
    parser.add_argument("--ranges", type=Path, help="randomizer overrides (e.g. config/stress.yaml): the stress section")
    parser.add_argument("--one-wall", action="store_true", help="landmarks on the most-marked wall only: the one_wall section")
    parser.add_argument("--section", choices=("stress", "map_error"), default="stress", help="the section a --ranges run writes")
    args = parser.parse_args(argv)
    if args.count < 1:
        parser.error("--count must be at least 1")
    if args.one_wall and args.ranges:
        parser.error("--one-wall and --ranges write different sections: give one of them")
    resolution = args.resolution or load_station_config().station.resolution
    try:
        ranges = load_randomizer([args.ranges] if args.ranges else [])
    except ConfigError as exc:
        parser.error(str(exc))  # exit 2 with the file, the key and the rule, no traceback
    results = []
    for seed in range(args.first_seed, args.first_seed + args.count):
        if args.rebuild:
            stored = args.out / f"seed{seed:03d}" / "matrix.json"
            if stored.exists():
                results.append(_stored_result(stored, random_world(seed, ranges, one_wall_only=args.one_wall), resolution))
            continue
        start = time.monotonic()
        result = run_mission(seed, args.out / f"seed{seed:03d}", resolution, spec=random_world(seed, ranges, one_wall_only=args.one_wall))
        results.append(result)
        (args.out / f"seed{seed:03d}" / "matrix.json").write_text(json.dumps(dataclasses.asdict(result), indent=2) + "\n")
        print(f"matrix: seed {seed} {result.world['layout']}/{result.world['object']}: {result.outcome}, centre "
              f"{_fmt(result.centre_error, 1000)} mm, IoU {_fmt(result.iou, 1, 3)}, clearance {_fmt(result.min_clearance, 1, 3)} m "
              f"({time.monotonic() - start:.0f} s wall)", file=sys.stderr, flush=True)
    machine = (f"Run {time.strftime('%Y-%m-%d')} on {platform.machine()} with {os.cpu_count()} cores, "
               f"shared with other work (wall times vary; durations are the station's mission time).")
    name = args.section if args.ranges else "one_wall" if args.one_wall else "matrix"
    command = {"stress": f"`python -m tools.matrix --ranges {args.ranges}`", "one_wall": "`python -m tools.matrix --one-wall`",
               "map_error": f"`python -m tools.matrix --ranges {args.ranges} --section map_error`", "matrix": MATRIX_COMMAND}[name]
    write_section(args.doc, (ONE_WALL_NOTE if args.one_wall else "") + table(results, resolution, machine, ranges, command), name)
    print(f"matrix: wrote the {name} section of {args.doc}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
