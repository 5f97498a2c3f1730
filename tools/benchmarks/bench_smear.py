"""Landmark fixes from a turning camera, smeared over its exposure (agent/localization.py, Smear).

In a room drawn as users lay markers out (nao_sim/layouts.py ``sample_layout("aruco")``), VIEWS
times: the robot stands on the orbit round the can (``orbit_pose``) with a marker 2-3.2 m away
coming into view, and turns in place at RATE rad/s for FRAMES frames 0.1 s apart, VGA, the simulator's
noise and the shutter given. Each frame gets the kinematics of its exposure's middle (as the bridge
stamps it, docs/frames.md "Exposure"), a prior 2 cm / 0.6 deg off, and is fitted four ways with the
whole map: *told* the camera's rate (from the previous frame, as ``on_frame`` reads it) with the
configured ``exposure`` and with ASSUMED s, markers tracked (``SMEAR_FACTORS``: tracking is off by
default, agent/marker_tracking.py), the baseline *still* (rate zero and no marker
tracked: no smear in the covariance, the fit before the smear was modelled), and the baseline
*untracked* (told, the configured exposure, the detector alone: ``track_smear_factors`` empty,
agent/marker_tracking.py).
NEES: e^T R^-1 e of a fix's (x, y) error e and covariance R (2 if R is honest); "> 3.7 sigma": fixes
with NEES above 13.8 (0.999 of chi-square with 2 DOF), which the jump gate would let pass where they
fall within its own 4 sigma.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Dict, List, Tuple

import numpy as np

from agent.camera import CameraModel
from agent.localization import LocalizationParams, RobotLocalizer, angular_velocity, camera_rotation
from agent.marker_tracking import SMEAR_FACTORS
from agent.perception import PerceptionParams
from nao_core.config import CONFIG_DIR, load
from nao_core.robot_model import load_robot_model, nao_to_optical
from nao_sim.layouts import layout_file, sample_layout
from nao_sim.randomize import load_randomizer
from nao_sim.scenarios import load_sim_config
from nao_sim.world import SimWorld, orbit_pose

VIEWS = 40
FRAMES = 20
PERIOD = 0.1  # s between frames
RATE = 0.2  # rad/s, the body's turn (a NAO's search turn is 0.35)
SHUTTERS = (0.0, 0.015, 0.03)  # s
ASSUMED = 0.015  # s, the other exposure the smear is reckoned with
OUTLIER = 13.8  # NEES: 0.999 of chi-square with 2 DOF
UNTRACKED = "untracked"
Fix = Tuple[float, float, int]  # (position error m, NEES, landmarks)


def turning_fixes(shutter: float, exposures: Tuple[float, ...] = (), rate: float = RATE, views: int = VIEWS,
                  seed: int = 7) -> Dict[object, List[Fix]]:
    """Fixes of the frames described in the module docstring: told the camera's rate (key True, the
    configured ``exposure``; key e, each of ``exposures``; ``UNTRACKED``, no marker tracked) or not (False)."""
    robot = load_robot_model()
    params = load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization")
    untracked = dataclasses.replace(params, track_smear_factors=())
    tracking = dataclasses.replace(params, track_smear_factors=SMEAR_FACTORS)
    solvers = {True: (tracking, True), False: (untracked, False), UNTRACKED: (untracked, True),
               **{e: (dataclasses.replace(tracking, exposure=e), True) for e in exposures}}
    perception = load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")
    camera = CameraModel.from_intrinsics(robot.camera.intrinsics("vga"))
    drawn = sample_layout("aruco", load_randomizer().drawn_layout)
    config = load_sim_config().with_layout(str(layout_file(drawn)), drawn.half_size)
    config = dataclasses.replace(config, noise=dataclasses.replace(config.noise, shutter=shutter))
    now = [100.0]
    world = SimWorld("can", robot, "vga", seed=3, config=config, clock=lambda: now[0])
    rng = np.random.default_rng(seed)
    fixes: Dict[object, List[Fix]] = {key: [] for key in solvers}
    for _ in range(views):
        position = orbit_pose(rng, world.scenario.position)[:2]
        far = [lm for lm in world.landmarks.landmarks if 2.0 <= math.dist(lm.position[:2], position) <= 3.2]
        target = far[int(rng.integers(len(far)))]
        bearing = math.atan2(target.position[1] - position[1], target.position[0] - position[0])
        pitch = robot.look_at((*position, bearing), target.position)[1]
        world.teleport((*position, bearing - math.copysign(0.6, rate)), (0.0, pitch))  # the marker comes into view
        world.walk(0.0, 0.0, rate)
        before = None
        for _ in range(FRAMES):
            now[0] += PERIOD
            frame = world.render()
            middle = world.kinematics_at(frame.stamp - shutter / 2)
            T_BC = nao_to_optical(middle.T_BC_nao)
            R_OC = camera_rotation(middle.odom, T_BC)
            omega = np.zeros(3) if before is None else angular_velocity(before, R_OC, PERIOD)
            before = R_OC
            truth = np.array(world.true_pose())  # turning in place: where it stood mid-exposure too
            prior = tuple(truth + rng.normal(0.0, [0.02, 0.02, 0.01]))
            for key, (solver_params, told) in solvers.items():
                localizer = RobotLocalizer(solver_params, world.landmarks, camera, perception)
                fix = localizer.measure(frame.image, T_BC, prior, params.roll_sigma, omega if told else np.zeros(3))
                if fix is not None:
                    e = np.array(fix.pose[:2]) - truth[:2]
                    fixes[key].append((float(np.linalg.norm(e)), float(e @ np.linalg.solve(fix.covariance[:2, :2], e)),
                                       len(fix.landmark_ids)))
        world.stop_walking()
        now[0] += 2.0
    return fixes


def _row(shutter: float, mode: str, fixes: List[Fix]) -> str:
    a = np.array(fixes, dtype=float).reshape(-1, 3)
    one = a[a[:, 2] == 1]
    outliers = int((a[:, 1] > OUTLIER).sum())
    return (f"| {shutter * 1e3:.0f} | {mode} | {len(a)} | {len(one)} | {np.median(a[:, 0]) * 1e3:.1f} | {a[:, 0].max() * 1e3:.0f} | "
            f"{a[:, 1].mean():.2f} | {outliers} | {int((one[:, 1] > OUTLIER).sum())} |")


def _ratio(shutter: float, fixes: np.ndarray, baseline: np.ndarray) -> str:
    return (f"| {shutter * 1e3:.0f} | {len(fixes) / max(1, len(baseline)):.2f} | "
            f"{fixes[:, 0].max() / baseline[:, 0].max():.2f} | {fixes[:, 1].mean() / baseline[:, 1].mean():.2f} |")


def run() -> str:
    exposure = load(LocalizationParams, [CONFIG_DIR / "localization.yaml"], section="localization").exposure
    rows, ratios, tracking = [], [], []
    for shutter in SHUTTERS:
        fixes = turning_fixes(shutter, (ASSUMED,))
        rows += [_row(shutter, f"told, {exposure * 1e3:.0f} ms assumed", fixes[True]),
                 _row(shutter, f"told, {ASSUMED * 1e3:.0f} ms assumed", fixes[ASSUMED]), _row(shutter, "still (baseline)", fixes[False]),
                 _row(shutter, "told, untracked (baseline)", fixes[UNTRACKED])]
        told, still, untracked = (np.array(fixes[k], dtype=float).reshape(-1, 3) for k in (True, False, UNTRACKED))
        ratios.append(_ratio(shutter, told, still))
        tracking.append(_ratio(shutter, told, untracked))
    return "\n".join([
        "## Fixes from a turning camera (`smear`)",
        "",
        __doc__.split("\n\n", 1)[1].replace("\n", " ").replace("VIEWS", str(VIEWS)).replace("FRAMES", str(FRAMES))
        .replace("RATE", f"{RATE:g}").replace("ASSUMED", f"{ASSUMED:g}").strip(),
        "",
        "Command: `.venv/bin/python -m tools.bench --only smear`",
        "",
        "| shutter ms | mode | fixes | one-marker fixes | median error mm | max error mm | NEES | > 3.7 sigma | one-marker > 3.7 sigma |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *rows,
        "",
        f"Told ({exposure * 1e3:.0f} ms assumed) against still, in the same run (ratios):",
        "",
        "| shutter ms | fixes | max error | NEES |",
        "| --- | --- | --- | --- |",
        *ratios,
        "",
        "Tracked against untracked (both told, the configured exposure), in the same run (ratios):",
        "",
        "| shutter ms | fixes | max error | NEES |",
        "| --- | --- | --- | --- |",
        *tracking,
    ])
