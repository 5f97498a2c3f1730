"""Simulator configuration: the room, the scenarios (object + robot start), dynamics and noise.

Loaded from ``config/sim.yaml`` (top-level key ``sim``) with the strict loader of
``nao_core.config``. An object is a union of red *parts* in its own frame O (origin on the floor
at the object's centre, z up), placed in the world at ``position`` with heading ``yaw``:

* ``cylinder``: vertical, centred at ``centre`` (x, y, z of its middle), ``size`` = (diameter,
  diameter, height);
* ``box``: centred at ``centre``, ``size`` = extents along its own x, y, z, turned by ``yaw`` about z;
* ``mesh``: a triangle mesh (``mesh``: ``procedural:NAME`` or a mesh file, relative to config/ or
  absolute; see nao_sim/meshes.py) scaled per axis so that its bounding box is ``size`` centred at
  ``centre``, turned by ``yaw``. Unlike the others it need not be convex.

``Scenario.contains(points)`` is the exact inside test of the object the renderer draws (analytic
for cylinders and boxes, the winding number for meshes): the truth of silhouettes and models.

The robot starts at a seeded distance in ``start_distance`` from the object, at a seeded azimuth
(seen from the object) in ``start_azimuth``, facing the object up to a Gaussian heading error of
``start_heading_sigma``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Dict, Literal, Optional, Sequence, Tuple, Union

import numpy as np
from scipy.spatial import ConvexHull

from nao_core.config import CONFIG_DIR, bounds, load
from nao_core.geometry import rot2
from nao_sim.meshes import PROCEDURAL_PREFIX, Mesh, contains, fit_box, load_mesh


@dataclass(frozen=True)
class Part:
    """One convex red part of an object, in the object frame O."""

    shape: Literal["cylinder", "box", "mesh"]
    centre: Tuple[float, float, float] = field(metadata=bounds(-2.0, 2.0))
    size: Tuple[float, float, float] = field(metadata=bounds(0.001, 2.0))
    yaw: float = field(default=0.0, metadata=bounds(-math.pi, math.pi))
    mesh: Optional[str] = None  # shape 'mesh': procedural:NAME or a mesh file (relative to config/)

    def __post_init__(self) -> None:
        if (self.shape == "mesh") != (self.mesh is not None):
            raise ValueError(f"part {self.shape}: 'mesh' is given exactly for shape 'mesh', got mesh={self.mesh!r}")
        if self.shape == "cylinder" and self.size[0] != self.size[1]:
            raise ValueError(f"a cylinder part has size (diameter, diameter, height), got {self.size}")
        if self.centre[2] - 0.5 * self.size[2] < -1e-9:
            raise ValueError(f"part {self.shape} at {self.centre} reaches below the floor")

    @cached_property
    def triangles(self) -> Mesh:
        """Shape 'mesh': (vertices, faces) in the object frame, loaded once."""
        if self.mesh is None:
            raise ValueError(f"a {self.shape} part has no triangle mesh")
        source = self.mesh if self.mesh.startswith(PROCEDURAL_PREFIX) else CONFIG_DIR / self.mesh
        vertices, faces = fit_box(load_mesh(source), (0.0, 0.0, 0.0), self.size)
        vertices[:, :2] = vertices[:, :2] @ rot2(self.yaw).T
        return vertices + np.asarray(self.centre), faces

    def world_points(self, position: Tuple[float, float], yaw: float, samples: int = 72) -> np.ndarray:
        """Vertices (N x 3, world): box corners, the two end circles of a cylinder, a mesh's vertices.

        The convex hull of the points is the part, except for a mesh (the hull of a concave one holds more).
        """
        sx, sy, sz = (0.5 * s for s in self.size)
        if self.shape == "mesh":
            local = self.triangles[0].copy()
        elif self.shape == "box":
            local = np.array([[x, y, z] for z in (-sz, sz) for x, y in ((-sx, -sy), (sx, -sy), (sx, sy), (-sx, sy))])
            local[:, :2] = local[:, :2] @ rot2(self.yaw).T
        else:
            a = np.linspace(0.0, 2.0 * math.pi, samples, endpoint=False)
            ring = np.stack([sx * np.cos(a), sx * np.sin(a)], axis=1)
            local = np.vstack([np.column_stack([ring, np.full(samples, z)]) for z in (-sz, sz)])
        if self.shape != "mesh":
            local = local + np.asarray(self.centre)
        local[:, :2] = local[:, :2] @ rot2(yaw).T + np.asarray(position)
        return local

    def world_mesh(self, position: Tuple[float, float], yaw: float) -> Mesh:
        """Shape 'mesh': vertices in the world and faces."""
        return self.world_points(position, yaw), self.triangles[1]

    def contains(self, points_O: np.ndarray) -> np.ndarray:
        """Bool per point (N x 3, object frame O): inside this part."""
        if self.shape == "mesh":
            return contains(self.triangles, points_O)
        p = points_O - np.asarray(self.centre)
        inside_z = np.abs(p[:, 2]) <= 0.5 * self.size[2]
        if self.shape == "cylinder":
            return inside_z & (np.hypot(p[:, 0], p[:, 1]) <= 0.5 * self.size[0])
        local = p[:, :2] @ rot2(self.yaw)  # rows times R: the inverse rotation
        return inside_z & np.all(np.abs(local) <= 0.5 * np.asarray(self.size[:2]), axis=1)


@dataclass(frozen=True)
class Scenario:
    """An object to find and where the robot starts."""

    kind: Literal["cylinder", "box", "composite", "mesh"]
    position: Tuple[float, float] = field(metadata=bounds(-2.5, 2.5))  # object centre on the floor, world, m
    yaw: float = field(metadata=bounds(-math.pi, math.pi))
    color: Tuple[int, int, int] = field(metadata=bounds(0, 255))  # BGR of a lit face
    parts: Tuple[Part, ...]
    start_distance: Tuple[float, float] = field(metadata=bounds(0.3, 3.0))  # m
    start_azimuth: Tuple[float, float] = field(metadata=bounds(-2 * math.pi, 2 * math.pi))  # rad, seen from the object
    start_heading_sigma: float = field(metadata=bounds(0.0, 1.0))  # rad
    finish: Optional[Tuple[float, float]] = field(default=None, metadata=bounds(0.0, 1000.0))  # (gloss, shininess) of
                                           # a Blinn-Phong highlight, gloss the share of white (nao_sim/render.py); None: matte

    def __post_init__(self) -> None:
        if not self.parts:
            raise ValueError("a scenario needs at least one part")
        if self.start_distance[0] > self.start_distance[1] or self.start_azimuth[0] > self.start_azimuth[1]:
            raise ValueError("start_distance and start_azimuth are [low, high] ranges")

    def world_points(self) -> np.ndarray:
        return np.vstack([p.world_points(self.position, self.yaw) for p in self.parts])

    def contains(self, points_W: np.ndarray) -> np.ndarray:
        """Bool per point (N x 3, world): inside one of the parts (the exact truth of the rendered object)."""
        points_W = np.asarray(points_W, dtype=float).reshape(-1, 3)
        local = points_W.copy()
        local[:, :2] = (points_W[:, :2] - np.asarray(self.position)) @ rot2(self.yaw)  # world -> object frame
        inside = np.zeros(len(points_W), dtype=bool)
        for part in self.parts:
            inside |= part.contains(local)
        return inside

    @cached_property  # the scenario is frozen; SimWorld.truth() asks at every state tick
    def height(self) -> float:
        return float(self.world_points()[:, 2].max())

    @cached_property
    def radius(self) -> float:
        """Radius of the smallest vertical cylinder about the object centre that holds the object."""
        pts = self.world_points()
        return float(np.max(np.hypot(pts[:, 0] - self.position[0], pts[:, 1] - self.position[1])))

    @cached_property
    def mean_half_breadth(self) -> float:
        """Half the footprint's width averaged over all viewing directions: the radius a filter that
        fits a cylinder to apparent widths converges to, seen from all round (docs/estimation.md).
        By Cauchy's formula the mean width of a convex set is its perimeter / pi, so this is the
        perimeter of the footprint's convex hull / (2 pi); the radius itself for a cylinder."""
        return float(ConvexHull(self.world_points()[:, :2]).area / (2.0 * math.pi))  # a 2-D hull's "area" is its perimeter


@dataclass(frozen=True)
class Room:
    """The room's size and looks: its floor and wall paint (BGR, 0-255) and its light (nao_sim/render.py)."""

    half_size: float = field(metadata=bounds(1.0, 50.0))  # walls at x, y = +-half_size, m
    wall_height: float = field(metadata=bounds(0.5, 10.0))  # m
    floor_color: Tuple[float, float, float] = field(metadata=bounds(0.0, 255.0))  # BGR
    wall_color: Tuple[float, float, float] = field(metadata=bounds(0.0, 255.0))  # BGR
    light: Tuple[float, float, float] = field(metadata=bounds(-1.0, 1.0))  # towards the light, world
    ambient: float = field(metadata=bounds(0.0, 1.0))  # share of the light every surface gets

    def __post_init__(self) -> None:
        if not self.light[2] > 0.0:
            raise ValueError(f"room.light must point upwards (positive z), got {list(self.light)}")


@dataclass(frozen=True)
class Sway:
    """Torso sway while walking: lateral shift, roll and vertical bob at the step frequency."""

    frequency: float = field(metadata=bounds(0.0, 10.0))  # Hz, one lateral cycle per two steps
    lateral: float = field(metadata=bounds(0.0, 0.1))  # m, amplitude at full speed
    roll: float = field(metadata=bounds(0.0, 0.3))  # rad, at the lateral frequency
    pitch: float = field(metadata=bounds(0.0, 0.3))  # rad, at the step frequency (twice the lateral one)
    bob: float = field(metadata=bounds(0.0, 0.05))  # m
    reported_fraction: float = field(metadata=bounds(0.0, 1.0))  # share of the sway the joint sensors report


@dataclass(frozen=True)
class Dynamics:
    timestep: float = field(metadata=bounds(0.0005, 0.05))  # s, fixed integration step
    velocity_time_constant: float = field(metadata=bounds(0.0, 5.0))  # s, first-order lag on (v, vy, omega)
    speed_scale_sigma: Tuple[float, float, float] = field(metadata=bounds(0.0, 0.5))  # per-run scale error
    slip_translation: float = field(metadata=bounds(0.0, 0.5))  # m per sqrt(m walked), random walk
    slip_rotation: float = field(metadata=bounds(0.0, 0.5))  # rad per sqrt(m + rad)
    sway: Sway
    battery_initial: float = field(metadata=bounds(0.0, 1.0))
    battery_drain_idle: float = field(metadata=bounds(0.0, 0.1))  # fraction per s
    battery_drain_walking: float = field(metadata=bounds(0.0, 0.1))  # extra fraction per s while walking
    fallen_camera_height: float = field(metadata=bounds(0.0, 1.0))  # m, torso thickness lying face down
    history: float = field(metadata=bounds(0.1, 30.0))  # s of past kinematics kept (render / kinematics_at)


@dataclass(frozen=True)
class Noise:
    pixel_sigma: float = field(metadata=bounds(0.0, 50.0))  # Gaussian image noise, grey levels
    gain_sigma: float = field(metadata=bounds(0.0, 0.5))  # per-frame exposure gain jitter
    latency: Tuple[float, float] = field(metadata=bounds(0.0, 1.0))  # s, stand-in capture-to-delivery range
    drop_rate: float = field(metadata=bounds(0.0, 0.9))  # stand-in: share of frames never delivered
    clock_offset: float = field(metadata=bounds(-1e9, 1e9))  # s, stand-in robot clock minus bridge clock
    blur_sigma: float = field(metadata=bounds(0.0, 10.0))  # px at VGA, Gaussian optical blur (0: none)
    exposure: float = field(metadata=bounds(0.1, 3.0))  # mean brightness factor of every frame
    mount_error: Tuple[float, float] = field(metadata=bounds(-0.1, 0.1))  # rad, (roll, pitch) of the camera on its mount, unreported
    shutter: float = field(metadata=bounds(0.0, 0.1))  # s, exposure time: the camera's rotation over it blurs the image
    response_gamma: float = field(metadata=bounds(0.2, 3.0))  # the camera's tone curve: a pixel is 255 (L / 255)^gamma of its light L

    def __post_init__(self) -> None:
        if self.latency[0] > self.latency[1]:
            raise ValueError(f"noise.latency is a [low, high] range, got {list(self.latency)}")


@dataclass(frozen=True)
class SimConfig:
    landmarks: str  # landmark map: relative to config/, or an absolute path
    fps: float = field(metadata=bounds(0.1, 120.0))
    room: Room
    dynamics: Dynamics
    noise: Noise
    scenarios: Dict[str, Scenario]

    def scenario(self, name: str) -> Scenario:
        if name not in self.scenarios:
            raise KeyError(f"unknown scenario {name!r}; known: {sorted(self.scenarios)}")
        return self.scenarios[name]

    @property
    def landmark_path(self) -> Path:
        return CONFIG_DIR / self.landmarks

    def with_layout(self, landmarks: str, half_size: float) -> "SimConfig":
        """This world with the landmark map ``landmarks`` in a room of ``half_size`` m (its looks kept)."""
        return dataclasses.replace(self, landmarks=landmarks, room=dataclasses.replace(self.room, half_size=half_size))


def load_sim_config(files: Sequence[Union[str, Path]] = ()) -> SimConfig:
    """The ``sim`` section of config/sim.yaml merged with override ``files``."""
    return load(SimConfig, [CONFIG_DIR / "sim.yaml", *files], section="sim")
