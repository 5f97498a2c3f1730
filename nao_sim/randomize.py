"""Randomized simulated worlds for the mission matrix (tools/matrix.py) and its CI sample.

``random_world(seed)`` draws, from ``np.random.default_rng(seed)`` alone, one world a user could
build (``config/sim.yaml`` ``randomizer`` section holds every range):

* a landmark layout from ``layouts`` (walls at several heights, the low ring, repeated colours,
  mixed, sparse), with the room size the layout was written for; or, drawn last with probability
  ``drawn_layout.share`` (so that the other worlds stay as they were), a layout and room size drawn as
  users lay them out (nao_sim/layouts.py, from ``default_rng([seed, 1])``) in its place;
* an object from ``objects`` (named scenarios of real sizes and shapes: cans, a bottle, a bucket, boxes, a mug, a
  figure, meshes), moved by up to ``object_offset`` from its place and turned at random;
* the start: at a distance U(``start_distance``) from the object and an azimuth U(-pi, pi), with
  the object U(-``start_bearing``, ``start_bearing``) off the heading;
* walking: per-axis speed-scale sigma and slip drawn in ``speed_scale_sigma`` / ``slip``; the torso
  sway scaled by U(``sway_scale``);
* the camera: the simulator's true intrinsics differ from the configured (what the station uses) by
  ``focal_error`` (relative, random sign per axis) and ``principal_error`` px (random sign per axis);
* the lens: a distortion (k1, k2, p1, p2, 0) uniform within +-``lens_distortion`` = (|k1|, |k2|, |p|),
  from ``default_rng([seed, 2])`` (so the other draws stay), rendered (nao_sim/render.py, "Lens
  distortion") and told the station as a calibration finds it (``WorldSpec.station_overrides``);
* the NAOqi stand-in's frames: latency range, drop rate and clock offset drawn in their ranges;
* the NAOqi itself: with probability ``bare_naoqi`` the stand-in is bare (``StandIn(bare=True)``: no
  posture or autonomous-life service, no ALMemory subscriber, timestamps or battery key, images in
  RGB), drawn after the above so that their draws for a seed do not depend on it;
* the sensor: pixel noise, optical blur and the room's brightness (exposure) in
  ``pixel_sigma``, ``blur_sigma`` and ``exposure``;
* the camera on its mount: a roll and a pitch uniform within +-``mount_error`` that
  the reported camera transform omits (agent/camera_tilt.py learns them);
* the shutter: an exposure time U(``shutter``) over which the camera's rotation blurs the frame
  (docs/simulator.md, "The camera image");
* the camera's tone curve: a gamma U(``response_gamma``) (nao_sim/render.py), from
  ``default_rng([seed, 4])`` (so the other draws stay), told the station as a calibration finds it;
* drawn last, the room's looks: a floor and a wall paint from ``floor_colors`` and ``wall_colors``
  (colours of real rooms that none of the perception's colour classes takes), and the light from
  an azimuth U(-pi, pi) at an elevation U(``light_elevation``) above the horizon, with an ambient
  share U(``ambient``);
* after the drawn layout, the object's finish: a highlight of gloss U(``object_gloss``) and
  shininess U(``object_shininess``) (Blinn-Phong, nao_sim/render.py); then its paint: one of
  ``object_colors`` (a perception colour class and its lit BGR), or the next in their order that
  no ball of the map has; the station is told it (``WorldSpec.object_color``: ``perception.object_color``).

The frames reach the bridge in YUV422 (the bridge's default NAOqi colour space), RGB from a bare NAOqi.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple, Union

import numpy as np

from nao_core.config import CONFIG_DIR, ConfigError, bounds, load
from nao_core.geometry import Pose
from nao_core.landmark_map import load_landmark_map
from nao_core.robot_model import CameraIntrinsics, RobotModel, load_robot_model
from nao_sim.layouts import DrawnLayoutParams, draw_layout, layout_file, map_yaml, measured, one_wall
from nao_sim.scenarios import Room, Scenario, SimConfig, load_sim_config
from nao_sim.world import SimWorld


@dataclass(frozen=True)
class Layout:
    file: str  # landmark map, relative to config/
    half_size: float = field(metadata=bounds(1.0, 50.0))  # the room it was written for, m


LENS_CORNER_RADIUS = 0.68  # normalized radius of a NAO top camera image's corner (57 x 44 deg: 400 px / 587 px at VGA)
LENS_FIELD = 1.1  # the lens model must invert this far beyond it (agent/camera.py, "The lens's field")


@dataclass(frozen=True)
class Randomizer:
    layouts: Dict[str, Layout]
    objects: Tuple[str, ...]  # scenario names of config/sim.yaml
    object_offset: float = field(metadata=bounds(0.0, 1.0))  # m, uniform in a square about the scenario's place
    start_distance: Tuple[float, float] = field(metadata=bounds(0.3, 3.0))  # m
    start_bearing: float = field(metadata=bounds(0.0, math.pi))  # rad, the object off the heading, at most
    speed_scale_sigma: Tuple[float, float] = field(metadata=bounds(0.0, 0.5))  # range of the per-axis sigma
    slip: Tuple[float, float] = field(metadata=bounds(0.0, 0.5))  # range of slip_translation and slip_rotation
    sway_scale: Tuple[float, float] = field(metadata=bounds(0.0, 5.0))  # range of the sway amplitude factor
    focal_error: float = field(metadata=bounds(0.0, 0.1))  # relative, random sign per axis
    principal_error: float = field(metadata=bounds(0.0, 10.0))  # px, random sign per axis
    latency: Tuple[float, float] = field(metadata=bounds(0.0, 1.0))  # s, range of the latency range's ends
    drop_rate: Tuple[float, float] = field(metadata=bounds(0.0, 0.9))
    clock_offset: Tuple[float, float] = field(metadata=bounds(-1e9, 1e9))  # s
    bare_naoqi: float = field(metadata=bounds(0.0, 1.0))  # share of worlds served by a bare NAOqi stand-in
    pixel_sigma: Tuple[float, float] = field(metadata=bounds(0.0, 50.0))  # grey levels
    blur_sigma: Tuple[float, float] = field(metadata=bounds(0.0, 10.0))  # px at VGA
    exposure: Tuple[float, float] = field(metadata=bounds(0.1, 3.0))  # mean brightness factor
    mount_error: Tuple[float, float] = field(metadata=bounds(0.0, 0.1))  # rad, largest |roll| and |pitch| of the camera on its mount
    shutter: Tuple[float, float] = field(metadata=bounds(0.0, 0.1))  # s, exposure time
    lens_distortion: Tuple[float, float, float] = field(metadata=bounds(0.0, 0.3))  # largest |k1|, |k2|, |p1| and |p2|
    response_gamma: Tuple[float, float] = field(metadata=bounds(0.2, 3.0))  # the camera's tone curve (nao_sim/render.py)
    response_gamma_told: bool  # the station is told the tone curve (as station calibrate measures it); false: it assumes linear
    map_error: Tuple[float, float] = field(metadata=bounds(0.0, 0.5))  # the station's map measured off: m per axis, rad of facing (1 sigma)
    map_error_told: bool  # the station's map says how well it is measured (its position_sigma, yaw_sigma)
    floor_colors: Tuple[Tuple[float, float, float], ...] = field(metadata=bounds(0.0, 255.0))  # BGR paints to draw from
    wall_colors: Tuple[Tuple[float, float, float], ...] = field(metadata=bounds(0.0, 255.0))
    light_elevation: Tuple[float, float] = field(metadata=bounds(0.1, math.pi / 2))  # rad above the horizon
    ambient: Tuple[float, float] = field(metadata=bounds(0.0, 1.0))
    object_gloss: Tuple[float, float] = field(metadata=bounds(0.0, 1.0))  # share of white in the object's highlight
    object_shininess: Tuple[float, float] = field(metadata=bounds(1.0, 1000.0))  # its Blinn-Phong exponent
    object_colors: Dict[str, Tuple[float, float, float]] = field(metadata=bounds(0.0, 255.0))  # class -> lit BGR
    drawn_layout: DrawnLayoutParams

    def __post_init__(self) -> None:
        k1, k2, _ = self.lens_distortion
        r = np.linspace(0.0, 3.0, 3001)  # undistorted normalized radii, the worst lens (a barrel of both terms)
        r_d = r * (1.0 - k1 * r**2 - k2 * r**4)
        fold = int(np.argmax(np.diff(r_d) <= 0.0)) if np.any(np.diff(r_d) <= 0.0) else len(r) - 1
        corner = int(np.argmax(r_d >= LENS_CORNER_RADIUS))
        if r_d[fold] < LENS_CORNER_RADIUS or LENS_FIELD * r[corner] > r[fold]:
            raise ValueError(f"randomizer: lens_distortion {list(self.lens_distortion)}: a lens of k1 = {-k1:g}, k2 = {-k2:g} folds "
                             f"back at r = {r[fold]:.2f}, before {LENS_FIELD:g} x the radius its image corner ({LENS_CORNER_RADIUS:g} "
                             "distorted) comes from: its model does not invert over the field")
        if not self.layouts or not self.objects:
            raise ValueError("randomizer: 'layouts' and 'objects' must not be empty")
        if not self.floor_colors or not self.wall_colors or not self.object_colors:
            raise ValueError("randomizer: 'floor_colors', 'wall_colors' and 'object_colors' must not be empty")


def load_randomizer(overrides: Sequence[Union[str, Path]] = ()) -> Randomizer:
    """The ``randomizer`` section of config/sim.yaml, merged with ``overrides`` (e.g. config/stress.yaml);
    ConfigError naming the files when an object is not a scenario of config/sim.yaml."""
    files = [CONFIG_DIR / "sim.yaml", *overrides]
    randomizer = load(Randomizer, files, section="randomizer")
    known = load_sim_config().scenarios
    unknown = [name for name in randomizer.objects if name not in known]
    if unknown:
        raise ConfigError(f"{' + '.join(map(str, files))}: randomizer.objects: {', '.join(map(repr, unknown))} "
                          f"is not a scenario of config/sim.yaml (known: {', '.join(sorted(known))})")
    return randomizer


@dataclass(frozen=True)
class WorldSpec:
    """One drawn world: what the simulator is, what the station is told, and a one-line summary."""

    seed: int
    layout: str
    landmark_path: str  # absolute: the station's landmark_map
    config: SimConfig  # the simulator's (truth)
    scenario: Scenario
    object_name: str
    robot: RobotModel  # the simulator's true camera; the station keeps the configured one
    start: Pose
    bare_naoqi: bool = False  # served by StandIn(bare=True)
    object_color: str = "red"  # the object's perception colour class (the station's perception.object_color)
    map_error: Tuple[float, float] = (0.0, 0.0)  # the station's map measured this far off (m, rad; ``station_map``)
    map_error_told: bool = True
    response_gamma_told: bool = True

    @property
    def lens(self) -> Tuple[float, ...]:
        """The true camera's distortion (k1, k2, p1, p2, k3), the same at every resolution."""
        return tuple(next(iter(self.robot.camera.resolutions.values())).dist)

    def station_overrides(self) -> Dict[str, object]:
        """The station's ``robot`` section for this world: the configured camera with the true lens's
        distortion and tone curve, as ``station calibrate`` finds them (the focal lengths and principal
        point stay the configured ones: the calibration error the self-calibration corrects)."""
        camera: Dict[str, object] = {}
        if any(self.lens):
            camera["resolutions"] = {name: {"dist": list(self.lens)} for name in self.robot.camera.resolutions}
        if self.config.noise.response_gamma != 1.0 and self.response_gamma_told:
            camera["response_gamma"] = self.config.noise.response_gamma
        return {"robot": {"camera": camera}} if camera else {}

    def station_map(self) -> str:
        """The landmark file the station is given: the world's, or with ``map_error`` each landmark moved by
        N(0, sigma^2 I_3) and each marker turned by N(0, sigma_yaw^2), as a user's tape measures it (drawn
        from ``default_rng([seed, 3])``), saying so when ``map_error_told`` (nao_sim/layouts.py ``measured``)."""
        exact = load_landmark_map(self.landmark_path)
        if not any(self.map_error):
            return map_yaml(exact, "# the world's landmark map\n")
        measured_map = measured(exact, *self.map_error, np.random.default_rng([self.seed, 3]), self.map_error_told)
        return map_yaml(measured_map, f"# the world's landmark map measured off by {self.map_error[0] * 1e3:g} mm and "
                                      f"{math.degrees(self.map_error[1]):g} deg (1 sigma)\n")

    def station_robot(self) -> RobotModel:
        """The configured robot model (NAO V6) as the station holds it in this world (``station_overrides``)."""
        robot = load_robot_model().with_lens(self.lens)
        if not self.response_gamma_told:
            return robot
        return dataclasses.replace(robot, camera=dataclasses.replace(robot.camera, response_gamma=self.config.noise.response_gamma))

    def summary(self) -> Dict[str, object]:
        dyn, noise = self.config.dynamics, self.config.noise
        return {"seed": self.seed, "layout": self.layout, "object": self.object_name, "object_color": self.object_color,
                "start_distance": round(math.dist(self.start[:2], self.scenario.position), 3),
                "start_bearing_deg": round(math.degrees(_bearing(self.start, self.scenario.position)), 1),
                "speed_scale_sigma": round(dyn.speed_scale_sigma[0], 3), "sway_roll": round(dyn.sway.roll, 3),
                "drop_rate": round(noise.drop_rate, 3), "latency": [round(x, 3) for x in noise.latency],
                "bare_naoqi": self.bare_naoqi, "pixel_sigma": round(noise.pixel_sigma, 2),
                "blur_sigma": round(noise.blur_sigma, 2), "exposure": round(noise.exposure, 2),
                "mount_error_deg": [round(math.degrees(a), 2) for a in noise.mount_error],
                "shutter_ms": round(1e3 * noise.shutter, 1), "floor_color": list(self.config.room.floor_color),
                "wall_color": list(self.config.room.wall_color), "light": [round(x, 2) for x in self.config.room.light],
                "ambient": round(self.config.room.ambient, 2), "object_finish": [round(x, 2) for x in self.scenario.finish or ()],
                "lens": [round(x, 4) for x in self.lens[:4]], "response_gamma": round(noise.response_gamma, 3)}


def _bearing(pose: Pose, target: Tuple[float, float]) -> float:
    return math.remainder(math.atan2(target[1] - pose[1], target[0] - pose[0]) - pose[2], 2.0 * math.pi)


def _intrinsics(intr: CameraIntrinsics, rng: np.random.Generator, focal: float, principal: float) -> CameraIntrinsics:
    sx, sy, su, sv = rng.choice([-1.0, 1.0], 4)
    return dataclasses.replace(intr, fx=float(intr.fx * (1.0 + sx * focal)), fy=float(intr.fy * (1.0 + sy * focal)),
                               cx=float(intr.cx + su * principal), cy=float(intr.cy + sv * principal))


def _looks(room: Room, r: Randomizer, rng: np.random.Generator) -> Room:
    """The room with a floor and wall paint and a light drawn from ``r`` (module docstring)."""
    floor = r.floor_colors[int(rng.integers(len(r.floor_colors)))]
    wall = r.wall_colors[int(rng.integers(len(r.wall_colors)))]
    azimuth, elevation = rng.uniform(-math.pi, math.pi), rng.uniform(*r.light_elevation)
    light = (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation))
    return dataclasses.replace(room, floor_color=floor, wall_color=wall, light=light, ambient=float(rng.uniform(*r.ambient)))


def random_world(seed: int, randomizer: Optional[Randomizer] = None, base: Optional[SimConfig] = None,
                 robot: Optional[RobotModel] = None, one_wall_only: bool = False) -> WorldSpec:
    """Draw world ``seed`` (module docstring); ``robot`` is the configured model (default NAO V6).
    ``one_wall_only``: every world's layout is drawn, then cut to its most-marked wall
    (``layouts.one_wall``); the world is otherwise the same as without it."""
    r = randomizer or load_randomizer()
    base = base or load_sim_config()
    robot = robot or load_robot_model()
    rng = np.random.default_rng(seed)
    layout_name = sorted(r.layouts)[int(rng.integers(len(r.layouts)))]
    layout = r.layouts[layout_name]
    object_name = r.objects[int(rng.integers(len(r.objects)))]
    scenario = base.scenario(object_name)
    position = tuple(float(p + rng.uniform(-r.object_offset, r.object_offset)) for p in scenario.position)
    scenario = dataclasses.replace(scenario, position=position, yaw=float(rng.uniform(-math.pi, math.pi)))
    distance, azimuth = rng.uniform(*r.start_distance), rng.uniform(-math.pi, math.pi)
    x, y = position[0] + distance * math.cos(azimuth), position[1] + distance * math.sin(azimuth)
    heading = math.remainder(azimuth + math.pi + rng.uniform(-r.start_bearing, r.start_bearing), 2.0 * math.pi)

    dyn = base.dynamics
    sway = rng.uniform(*r.sway_scale)
    dyn = dataclasses.replace(
        dyn,
        speed_scale_sigma=tuple(float(s) for s in rng.uniform(*r.speed_scale_sigma, 3)),
        slip_translation=float(rng.uniform(*r.slip)), slip_rotation=float(rng.uniform(*r.slip)),
        sway=dataclasses.replace(dyn.sway, lateral=dyn.sway.lateral * sway, roll=dyn.sway.roll * sway,
                                 bob=dyn.sway.bob * sway),
    )
    low, high = np.sort(rng.uniform(*r.latency, 2))
    noise = dataclasses.replace(base.noise, latency=(float(low), float(high)), drop_rate=float(rng.uniform(*r.drop_rate)),
                                clock_offset=float(rng.uniform(*r.clock_offset)))
    config = dataclasses.replace(base.with_layout(layout.file, layout.half_size), dynamics=dyn, noise=noise,
                                 scenarios={object_name: scenario})
    camera = robot.camera
    k1, k2, p = r.lens_distortion
    lens = tuple(float(x) for x in np.random.default_rng([seed, 2]).uniform(-1.0, 1.0, 4) * (k1, k2, p, p)) + (0.0,)
    resolutions = {k: dataclasses.replace(_intrinsics(v, rng, r.focal_error, r.principal_error), dist=lens)
                   for k, v in camera.resolutions.items()}
    true_robot = dataclasses.replace(robot, camera=dataclasses.replace(camera, resolutions=resolutions))
    bare = bool(rng.uniform() < r.bare_naoqi)  # after the above: their draws do not depend on it
    sensor = dataclasses.replace(noise, pixel_sigma=float(rng.uniform(*r.pixel_sigma)),  # last
                                 blur_sigma=float(rng.uniform(*r.blur_sigma)), exposure=float(rng.uniform(*r.exposure)))
    sensor = dataclasses.replace(sensor, mount_error=tuple(float(m) for m in rng.uniform(-1.0, 1.0, 2) * r.mount_error))
    sensor = dataclasses.replace(sensor, shutter=float(rng.uniform(*r.shutter)))  # drawn after the rest: their draws stay
    config = dataclasses.replace(config, noise=sensor, room=_looks(config.room, r, rng))
    landmark_path = (CONFIG_DIR / layout.file).resolve()
    if rng.uniform() < r.drawn_layout.share or one_wall_only:  # drawn last: the other worlds' draws stay
        drawn = draw_layout(np.random.default_rng([seed, 1]), r.drawn_layout)
        drawn = one_wall(drawn) if one_wall_only else drawn
        layout_name, landmark_path = f"drawn {drawn.kind}{', one wall' if one_wall_only else ''}", layout_file(drawn)
        config = config.with_layout(str(landmark_path), drawn.half_size)
    scenario = dataclasses.replace(scenario, finish=(float(rng.uniform(*r.object_gloss)), float(rng.uniform(*r.object_shininess))))
    balls = load_landmark_map(landmark_path).ball_colors
    names = sorted(r.object_colors)
    first = int(rng.integers(len(names)))  # then the next one no ball has: another map repaints only where a ball took it
    object_color = next((name for name in names[first:] + names[:first] if name not in balls), None)
    if object_color is None:
        raise ValueError(f"randomizer: every object colour {names} is a ball's in {landmark_path}")
    scenario = dataclasses.replace(scenario, color=tuple(int(c) for c in r.object_colors[object_color]))
    gamma = float(np.random.default_rng([seed, 4]).uniform(*r.response_gamma))  # its own draw: the others stay
    config = dataclasses.replace(config, scenarios={object_name: scenario},
                                 noise=dataclasses.replace(config.noise, response_gamma=gamma))
    return WorldSpec(seed, layout_name, str(landmark_path), config, scenario, object_name, true_robot, (x, y, heading), bare,
                     object_color, tuple(float(e) for e in r.map_error), r.map_error_told, r.response_gamma_told)


class RandomWorld(SimWorld):
    """The SimWorld of a ``WorldSpec``: its config, true camera, object and start pose."""

    def __init__(self, spec: WorldSpec, resolution: str = "qvga", **kwargs):
        self._spec_start = spec.start
        super().__init__(spec.scenario, spec.robot, resolution=resolution, seed=spec.seed, config=spec.config, **kwargs)
        self.scenario_name = spec.object_name

    def _start_pose(self) -> Pose:
        return self._spec_start


def fixed_world(scenario: str, seed: int, robot: Optional[RobotModel] = None) -> WorldSpec:
    """The configured world (config/sim.yaml: its layout, dynamics, noise, exact camera) with scenario
    ``scenario`` and the start ``SimWorld`` draws for ``seed``: the un-randomized reference."""
    base = load_sim_config()
    robot = robot or load_robot_model()
    start = SimWorld(scenario, robot, seed=seed, config=base).start_pose
    return WorldSpec(seed, "configured", str(base.landmark_path.resolve()), base, base.scenario(scenario), scenario, robot, start)
