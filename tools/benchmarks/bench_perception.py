"""Perception + localization per camera frame (target: median <= 3 ms at VGA).

Frames are simulator renders (``can`` scenario), in two sequences:

* tracking: 80 frames along a walk around the object (0.7-1.1 m, 4.5 deg of orbit a frame, the
  head aimed at it), the localizer keeping its pose between frames as the station's does, fed
  with odometry that drifts (1 cm and 0.5 deg of random walk a frame). This is the station's
  steady state: markers are searched around their predicted projections.
* cold: 80 independent views on a 0.6-1.2 m orbit, the localizer reset before each (no prior:
  whole-frame marker search), as after a fall or at the start.

Per frame the station's work is timed: ``RobotLocalizer.on_frame`` (ArUco + colour landmarks, PnP,
planar refinement, fusion), ``extract_silhouette`` and ``measure_object``: wall time per step and
the mean process CPU time per frame (all OpenCV threads counted). The machine is shared by several
engineers: the figures are noisy, so the frames are processed in ``PASSES`` passes and the table
gives the lowest per-pass median (timeit's practice: other processes only ever add time) next to
the median over all passes, and the load average while it ran.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from agent.camera import CameraModel
from agent.localization import LocalizationParams, RobotLocalizer
from agent.perception import PerceptionParams, extract_silhouette, measure_object
from nao_core.config import CONFIG_DIR, load
from nao_core.geometry import camera_in_world, compose
from nao_core.landmark_map import load_landmark_map
from nao_core.robot_model import load_robot_model
from nao_sim.world import SimWorld

FRAMES = 80
PASSES = 3
ODOM_DRIFT = (0.01, math.radians(0.5))  # m, rad of odometry random walk per frame (tracking)


class _Clock:
    def __call__(self) -> float:
        return 0.0


def _frames(resolution: str, tracking: bool):
    """(frame, odometry) pairs and the camera model."""
    robot = load_robot_model()
    world = SimWorld("can", robot, resolution, seed=0, clock=_Clock())
    rng = np.random.default_rng(0)
    ox, oy = world.scenario.position
    frames = []
    drift = (0.0, 0.0, 0.0)
    for k in range(FRAMES):
        if tracking:
            az, d = math.radians(4.5 * k), 0.9 + 0.2 * math.sin(k / 9)
            pose = (ox + d * math.cos(az), oy + d * math.sin(az), az + math.pi + 0.15 * math.sin(k / 5))
            drift = compose(drift, (*rng.normal(0.0, ODOM_DRIFT[0], 2), rng.normal(0.0, ODOM_DRIFT[1])))
        else:
            d, az = rng.uniform(0.6, 1.2), rng.uniform(-math.pi, math.pi)
            pose = (ox + d * math.cos(az), oy + d * math.sin(az), az + math.pi)
        world.teleport(pose, robot.look_at(pose, (ox, oy, 0.1)))
        frames.append((world.render(), compose(drift, pose)))
    intr = robot.camera.intrinsics(resolution)
    return frames, CameraModel.from_intrinsics(intr)


def _timed(fn):
    w0 = time.perf_counter()
    out = fn()
    return out, (time.perf_counter() - w0) * 1e3


def _measure(resolution: str, tracking: bool) -> dict:
    perception = load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")
    params = load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization")
    landmarks = load_landmark_map(CONFIG_DIR / "landmarks" / "sim_room.yaml")
    frames, camera = _frames(resolution, tracking)
    passes = [_pass(frames, camera, perception, RobotLocalizer(params, landmarks, camera, perception), tracking)
              for _ in range(PASSES)]
    return {
        "best": {k: min(np.median(p["times"][k]) for p in passes) for k in passes[0]["times"]},
        "all": {k: np.concatenate([p["times"][k] for p in passes]) for k in passes[0]["times"]},
        "cpu": min(p["cpu"] for p in passes),
        "fixes": passes[0]["fixes"],
        "measured": passes[0]["measured"],
    }


def _pass(frames, camera: CameraModel, perception: PerceptionParams, localizer: RobotLocalizer, tracking: bool) -> dict:
    times = {"total": [], "localization": [], "silhouette": [], "measurement": []}
    fixes = measured = 0
    cpu_start = 0.0
    # The first five frames (the last five of the sequence, run first) warm up caches and, when
    # tracking, the pose; they are not counted. CPU time is taken over the whole loop
    # (time.process_time costs about 0.5 ms a call on this machine).
    for k, (frame, odom) in enumerate(frames[-5:] + frames):
        if k == 5:
            cpu_start = time.process_time()
            if tracking:
                localizer.reset()  # the sequence restarts: the first counted frame searches the whole frame
        if not tracking:
            localizer.reset()  # independent poses: no prior, no jump gate
        fix, t_loc = _timed(lambda: localizer.on_frame(frame.image, frame.T_BC, odom, float(k)))
        silhouette, t_sil = _timed(lambda: extract_silhouette(frame.image, perception))
        T_WC = camera_in_world(localizer.pose_at(odom) or (0.0, 0.0, 0.0), frame.T_BC)
        m, t_meas = _timed(lambda: None if silhouette is None else measure_object(silhouette, camera, T_WC, perception))
        if k < 5:
            continue
        fixes += fix is not None
        measured += m is not None
        times["localization"].append(t_loc)
        times["silhouette"].append(t_sil)
        times["measurement"].append(t_meas)
        times["total"].append(t_loc + t_sil + t_meas)
    cpu = (time.process_time() - cpu_start) * 1e3 / FRAMES
    return {"times": {k: np.array(v) for k, v in times.items()}, "cpu": cpu, "fixes": fixes, "measured": measured}


def run() -> str:
    rows = []
    load_before = os.getloadavg()[0]
    for sequence in ("tracking", "cold"):
        for resolution in ("qvga", "vga"):
            r = _measure(resolution, sequence == "tracking")
            best, every = r["best"], r["all"]
            rows.append(
                f"| {sequence} | {resolution} | {best['total']:.2f} | {np.median(every['total']):.2f} | "
                f"{np.percentile(every['total'], 95):.2f} | {r['cpu']:.2f} | {best['localization']:.2f} | "
                f"{best['silhouette']:.2f} | {best['measurement']:.2f} | {r['fixes']}/{FRAMES} | {r['measured']}/{FRAMES} |"
            )
    load_after = os.getloadavg()[0]
    table = "\n".join([
        f"| sequence | resolution | total median, best of {PASSES} passes (ms) | total median, all passes (ms) | total p95 (ms) | "
        "CPU mean, best pass (ms) | localization (ms) | silhouette (ms) | measurement (ms) | landmark fixes | object measured |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *rows,
    ])
    return (
        "## Perception and localization\n\n"
        f"Per frame over {FRAMES} simulator frames of the can: `RobotLocalizer.on_frame` (ArUco + colour landmarks, PnP, "
        "planar refinement, fusion) + `extract_silhouette` + `measure_object`, medians of wall time, and the mean process "
        "CPU time (all OpenCV threads). *tracking*: a walk around the object (0.7-1.1 m), the localizer keeping its pose "
        "with drifting odometry (markers searched around their predicted projections), the station's steady state; "
        "*cold*: independent orbit views (0.6-1.2 m) with the localizer reset before each (whole-frame search). "
        f"Target: total median <= 3 ms at VGA. Shared 2-core machine (load average {load_before:.1f} before, "
        f"{load_after:.1f} after): noisy, so {PASSES} passes over the frames; the step columns are best-pass medians.\n\n"
        "Command: `.venv/bin/python -m tools.bench --only perception`\n\n"
        f"{table}\n"
    )


if __name__ == "__main__":
    print(run())
