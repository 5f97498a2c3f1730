"""``station check-layout``: will the landmarks give fixes on the orbit the planner flies?

Before the first run in a room, from the landmark map alone: for robot poses on circles around the
object at the planner's comfortable distance d_min and either side of it (``--distances``, default
0.75 d_min, d_min, 1.35 d_min), every ``--step`` degrees of azimuth, the robot facing the object,

* *aimed*: the head aimed at the object (``head_servo.aim_height``), as while measuring it;
* *best*: the head turned to the direction with the most precise predicted fix
  (``RobotLocalizer.best_landmark_view`` over the head's range), as when the pilot looks for landmarks;

the localizer predicts the fix (``RobotLocalizer.predicted_fix``: the landmark points that would
be detected, in the image, facing the camera, large enough, give the fix covariance
sigma_px^2 (J^T J)^-1 with the torso-roll prior; agent/localization.py). A pose has a fix when
the predicted position std is within the localizer's ``max_position_std``.

Printed: per distance, the share of the orbit with a fix aimed and with a head turn, the median
and worst predicted std, and the longest arc without any fix; the walls the map shows
(agent/keep_in.py) and how many of the object's coverage bins the robot can see keeping off them
and off the object (``Planner.reachable_bins`` for an object of ``--radius``); the PNG (``-o``,
default ``layout.png``) draws the room from above with the landmarks, the line the robot keeps
inside (``planner.wall_clearance`` off the walls) and the orbit coloured by the aimed std, and the
std along the orbit. Exit code 0 when every pose of the orbit at d_min has a fix with
a head turn at most, 1 otherwise (the layout leaves gaps: docs/landmarks.md says what to change),
2 for a bad map, config or argument.
"""

from __future__ import annotations

import argparse
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

from agent.camera import CameraModel
from agent.keep_in import HalfPlanes, KeepIn
from agent.localization import RobotLocalizer, head_directions
from agent.planner import Planner
from nao_core.config import ConfigError
from nao_core.geometry import wrap_angle
from nao_core.landmark_map import LandmarkMap, read_landmark_map
from nao_core.robot_model import RobotModel, load_robot_model
from station.config import load_station_config

log = logging.getLogger("station.check_layout")
EXIT_GAPS = 1
EXIT_USAGE = 2
DISTANCE_FACTORS = (0.75, 1.0, 1.35)  # of d_min: the band the planner's standoff cost keeps the robot in


def object_position(text: str) -> Tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres, got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"expected finite X,Y, got {text!r}")
    return x, y


def distances(text: str) -> Tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected D1,D2,... in metres, got {text!r}") from None
    if not values or not all(0.2 <= v <= 10.0 for v in values):
        raise argparse.ArgumentTypeError(f"distances must be within 0.2-10 m, got {text!r}")
    return values


def step_degrees(text: str) -> float:
    value = float(text)
    if not 0.5 <= value <= 90.0:
        raise argparse.ArgumentTypeError(f"step must be within 0.5-90 degrees, got {text}")
    return value


def positive_radius(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a radius in metres, got {text!r}") from None
    if not 0.0 < value < 5.0:
        raise argparse.ArgumentTypeError(f"expected a radius in (0, 5) m, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--landmarks", type=Path, required=True, metavar="FILE", help="landmark map (YAML, docs/frames.md)")
    parser.add_argument("--object", type=object_position, required=True, metavar="X,Y", help="object position in the map's frame, m")
    parser.add_argument("--config", action="append", default=[], metavar="FILE", help="config override(s) (camera, localization, planner)")
    parser.add_argument("--resolution", help="camera resolution (default: the station's)")
    parser.add_argument("--distances", type=distances, metavar="D1,D2,...", help="orbit radii, m (default 0.75, 1, 1.35 x planner d_min)")
    parser.add_argument("--step", type=step_degrees, default=5.0, metavar="DEG", help="azimuth step along the orbit, degrees")
    parser.add_argument("--radius", type=positive_radius, default=0.05, metavar="R", help="object radius, m (for the walls' check)")
    parser.add_argument("-o", "--output", type=Path, default=Path("layout.png"), help="figure (PNG)")


@dataclass(frozen=True)
class OrbitPoint:
    distance: float
    azimuth: float  # rad, of the robot seen from the object
    aimed_std: float  # m, predicted position std with the head on the object (inf: no fix)
    best_std: float  # m, with the best head direction (inf: none)
    best_yaw: float  # rad, that head yaw (nan: none)


def predict_orbit(localizer: RobotLocalizer, robot: RobotModel, obj: Tuple[float, float], aim_height: float,
                  radii: Sequence[float], step: float) -> List[OrbitPoint]:
    """The predicted fixes around the object (module docstring)."""
    directions = head_directions(robot.head)
    out = []
    for d in radii:
        for azimuth in np.radians(np.arange(-180.0, 180.0, step)):
            pose = (obj[0] + d * math.cos(azimuth), obj[1] + d * math.sin(azimuth), wrap_angle(azimuth + math.pi))
            _, cov = localizer.predicted_fix(pose, robot.camera_in_robot(*robot.look_at(pose, (*obj, aim_height))))
            aimed = _position_std(cov)
            best = localizer.best_landmark_view(pose, robot.camera_in_robot, directions + [robot.look_at(pose, (*obj, aim_height))])
            out.append(OrbitPoint(d, float(azimuth), aimed, best.position_std if best else math.inf,
                                  best.yaw if best else math.nan))
    return out


def _position_std(cov: Optional[np.ndarray]) -> float:
    return math.inf if cov is None else float(math.sqrt(max(0.0, np.linalg.eigvalsh(cov[:2, :2])[-1])))


def longest_gap(points: Sequence[OrbitPoint], limit: float, step: float) -> float:
    """Degrees: the longest run of consecutive azimuths (wrapping around) with no fix even with a head turn."""
    bad = [p.best_std > limit and p.aimed_std > limit for p in points]
    if all(bad):
        return 360.0
    run = longest = 0
    for b in bad + bad:  # twice round: a gap across -180 deg counts whole
        run = run + 1 if b else 0
        longest = max(longest, run)
    return min(360.0, longest * step)


def summarize(points: Sequence[OrbitPoint], limit: float, step: float) -> List[str]:
    lines = []
    for d in sorted({p.distance for p in points}):
        ring = [p for p in points if p.distance == d]
        aimed = np.array([p.aimed_std for p in ring])
        best = np.array([p.best_std for p in ring])
        ok_aimed, ok_any = aimed <= limit, (aimed <= limit) | (best <= limit)
        finite = aimed[ok_aimed]
        lines.append(
            f"orbit {d:.2f} m: fix aimed at the object on {100 * ok_aimed.mean():.0f} % of it, with a head turn on "
            f"{100 * ok_any.mean():.0f} %; aimed std median {_cm(np.median(finite) if len(finite) else math.inf)}, "
            f"worst {_cm(finite.max() if len(finite) else math.inf)}; longest arc without a fix {longest_gap(ring, limit, step):.0f} deg"
        )
    return lines


def _cm(value: float) -> str:
    return "none" if not math.isfinite(value) else f"{100 * value:.1f} cm"


def draw(path: Path, landmarks: LandmarkMap, obj: Tuple[float, float], points: Sequence[OrbitPoint], limit: float,
         keep_in: KeepIn, walls: HalfPlanes, wall_clearance: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, along) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1.1, 1]})
    for lm in landmarks.landmarks:
        x, y, z = lm.position
        if lm.kind == "aruco":
            n = lm.normal
            top.plot([x - 0.5 * lm.size * n[1], x + 0.5 * lm.size * n[1]], [y + 0.5 * lm.size * n[0], y - 0.5 * lm.size * n[0]], "k-", lw=3)
            top.annotate("", (x + 0.15 * n[0], y + 0.15 * n[1]), (x, y), arrowprops={"arrowstyle": "->", "color": "0.4"})
        else:
            top.plot(x, y, "o", color=lm.color if lm.color in ("green", "yellow", "magenta", "cyan", "blue") else "0.5",
                     mec="k", ms=7)
    top.plot(*obj, "s", color="tab:red", ms=9, label="object")
    if len(walls.offsets):
        lo, hi = top.get_xlim(), top.get_ylim()
        gx, gy = np.meshgrid(np.linspace(*lo, 300), np.linspace(*hi, 300))
        nearest = np.min(keep_in.distances(np.stack([gx, gy], axis=-1), walls), axis=-1)
        top.contour(gx, gy, nearest, levels=[wall_clearance], colors="tab:brown", linestyles="--")
        top.plot([], [], "--", color="tab:brown", label=f"{wall_clearance:g} m off the walls: the robot keeps inside")
    xy = np.array([[obj[0] + p.distance * math.cos(p.azimuth), obj[1] + p.distance * math.sin(p.azimuth)] for p in points])
    std = np.array([p.aimed_std for p in points])
    ok = std <= limit
    scatter = top.scatter(xy[ok, 0], xy[ok, 1], c=100 * std[ok], cmap="viridis_r", vmin=0, vmax=100 * limit, s=18,
                          label="fix aimed at the object")
    turn = ~ok & np.array([p.best_std <= limit for p in points])
    top.scatter(xy[turn, 0], xy[turn, 1], marker="^", color="tab:orange", s=18, label="fix with a head turn only")
    none = ~ok & ~turn
    top.scatter(xy[none, 0], xy[none, 1], marker="x", color="tab:red", s=22, label="no fix")
    fig.colorbar(scatter, ax=top, label="predicted position std, aimed (cm)")
    top.set_aspect("equal")
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m)")
    top.set_title("Landmarks (ArUco: bar and normal; colour: dot) and the orbit")
    top.legend(loc="lower left", fontsize=8)
    for d in sorted({p.distance for p in points}):
        ring = [p for p in points if p.distance == d]
        az = np.degrees([p.azimuth for p in ring])
        along.plot(az, [100 * min(p.aimed_std, 10 * limit) for p in ring], "-", label=f"aimed, {d:.2f} m")
        along.plot(az, [100 * min(p.best_std, 10 * limit) for p in ring], ":", label=f"best head turn, {d:.2f} m")
    along.axhline(100 * limit, color="tab:red", lw=1, label="fix gate (max_position_std)")
    along.set_yscale("log")
    along.set_xlabel("azimuth of the robot seen from the object (deg)")
    along.set_ylabel("predicted position std (cm; clipped at 10 x the gate: no fix)")
    along.set_title("Predicted fix precision along the orbit")
    along.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def map_precision(landmarks: LandmarkMap, unstated: Tuple[str, ...] = ()) -> str:
    """The line that says how well the map says it is measured (docs/landmarks.md, "Writing the map"); ``unstated``:
    the precision keys the file left out (``read_landmark_map``)."""
    if landmarks.position_sigma == 0.0 and landmarks.yaw_sigma == 0.0:
        said = f"not stated ({' and '.join(unstated)}): held exact" if unstated else "exact (position_sigma and yaw_sigma 0)"
        return (f"map precision: {said}: a map measured with a tape is a few mm off, "
                "which costs several times that in every fix unless the map says so (docs/landmarks.md)")
    return (f"map precision: {1e3 * landmarks.position_sigma:g} mm per axis, {math.degrees(landmarks.yaw_sigma):g} deg "
            "of facing (the predicted precision holds it)")


def run(args: argparse.Namespace) -> int:
    """``station check-layout``: the summary on stdout, the PNG, and the exit code of the module docstring."""
    try:
        landmarks, unstated = read_landmark_map(args.landmarks)
        config = load_station_config(args.config)
        robot = load_robot_model(config.robot_overrides)
        resolution = args.resolution or config.station.resolution
        camera = CameraModel.from_intrinsics(robot.camera.intrinsics(resolution))
        localizer = RobotLocalizer(config.localization, landmarks, camera, config.perception)
    except (ConfigError, OSError, KeyError, ValueError) as exc:
        log.error("check-layout: %s", exc)
        return EXIT_USAGE
    d_min = config.planner.d_min
    radii = args.distances or tuple(round(f * d_min, 3) for f in DISTANCE_FACTORS)
    points = predict_orbit(localizer, robot, args.object, config.head_servo.aim_height, radii, args.step)
    limit = config.localization.max_position_std
    print(f"{args.landmarks}: {len(landmarks.landmarks)} landmarks, object at ({args.object[0]:.2f}, {args.object[1]:.2f}) m, "
          f"camera {resolution}, fix gate {100 * limit:.1f} cm")
    print(map_precision(landmarks, unstated))
    for line in summarize(points, limit, args.step):
        print(line)
    keep_in, x = KeepIn(landmarks), np.array([*args.object, args.radius])
    walls = keep_in.walls(x)
    reachable = Planner.for_robot(config.planner, robot, resolution).reachable_bins(x, keep_in)
    print(f"walls: {len(walls.offsets)} landmark planes; keeping "
          f"{config.planner.wall_clearance:g} m off them and {config.planner.clearance:g} m off the object, the robot can see "
          f"{int(reachable.sum())} of the object's {reachable.size} coverage bins"
          + ("" if reachable.all() else ": it is too near a wall to be seen from all round (docs/landmarks.md)"))
    draw(args.output, landmarks, args.object, points, limit, keep_in, walls, config.planner.wall_clearance)
    print(f"figure: {args.output}")
    nominal = [p for p in points if p.distance == min(radii, key=lambda r: abs(r - d_min))]
    if any(p.aimed_std > limit and p.best_std > limit for p in nominal):
        print("verdict: gaps on the orbit (no fix even with a head turn): add or move landmarks (docs/landmarks.md)")
        return EXIT_GAPS
    print("verdict: a fix is possible everywhere on the orbit")
    return 0
