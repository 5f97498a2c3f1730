"""Synthetic ground truth for space carving: analytic shapes, cameras around them, exact silhouettes.

A silhouette pixel is on iff the ray through its centre (lens distortion removed) meets the shape
in front of the camera; the analytic visual hull of a set of views is the set of points whose ray
from each camera centre meets the shape (a point projecting outside an image is not constrained by
that view, as in the carver; here every view sees the whole volume). Ray tests, with d a unit direction from the camera centre o:

* sphere (c, R): with t* = (c - o) . d, hit iff |c - o|^2 - t*^2 <= R^2 and t* + sqrt(R^2 - ...) > 0;
* box and vertical cylinder: intersect the ray's parameter intervals (slabs; the circle in xy and
  the slab z0 <= z <= z1) with t > 0.

Used by tests/test_carving.py and tools/benchmarks/bench_carving.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np

from agent.camera import CameraModel


def look_at(eye: Sequence[float], target: Sequence[float]) -> np.ndarray:
    """T_WC of a camera at ``eye`` looking at ``target`` with image rows parallel to the floor."""
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, (0.0, 0.0, 1.0))
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


def ring_poses(target: Sequence[float], distance: float, count: int, elevations: Sequence[float]) -> List[np.ndarray]:
    """``count`` cameras evenly around ``target``, cycling through the ``elevations`` (rad)."""
    target = np.asarray(target, dtype=float)
    poses = []
    for i in range(count):
        azimuth, elevation = 2.0 * np.pi * i / count, elevations[i % len(elevations)]
        offset = np.array([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.sin(elevation)])
        poses.append(look_at(target + distance * offset, target))
    return poses


@dataclass(frozen=True)
class Sphere:
    centre: Tuple[float, float, float]
    radius: float

    def contains(self, p: np.ndarray) -> np.ndarray:
        return np.sum((p - self.centre) ** 2, axis=-1) <= self.radius**2

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        oc = np.asarray(self.centre) - o
        t = np.sum(oc * d, axis=-1)
        gap2 = np.sum(oc * oc, axis=-1) - t**2
        return (gap2 <= self.radius**2) & (t + np.sqrt(np.maximum(self.radius**2 - gap2, 0.0)) > 0)


@dataclass(frozen=True)
class Box:
    lo: Tuple[float, float, float]
    hi: Tuple[float, float, float]

    def contains(self, p: np.ndarray) -> np.ndarray:
        return np.all((p >= self.lo) & (p <= self.hi), axis=-1)

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (np.asarray(self.lo) - o) / d, (np.asarray(self.hi) - o) / d
        inside = (o >= self.lo) & (o <= self.hi)
        near = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        far = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        enter, leave = near.max(axis=-1), far.min(axis=-1)
        return (enter <= leave) & (leave > 0)


@dataclass(frozen=True)
class Cylinder:
    """Vertical cylinder: axis through (x, y), radius, from z0 to z1."""

    x: float
    y: float
    radius: float
    z0: float
    z1: float

    def contains(self, p: np.ndarray) -> np.ndarray:
        r2 = (p[..., 0] - self.x) ** 2 + (p[..., 1] - self.y) ** 2
        return (r2 <= self.radius**2) & (p[..., 2] >= self.z0) & (p[..., 2] <= self.z1)

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ox, oy = o[..., 0] - self.x, o[..., 1] - self.y
        a = d[..., 0] ** 2 + d[..., 1] ** 2
        b = ox * d[..., 0] + oy * d[..., 1]
        c = ox**2 + oy**2 - self.radius**2
        disc = b**2 - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            root = np.sqrt(np.maximum(disc, 0.0))
            t_in = np.where(a > 0, (-b - root) / a, np.where(c <= 0, -np.inf, np.inf))
            t_out = np.where(a > 0, (-b + root) / a, np.where(c <= 0, np.inf, -np.inf))
            tz1, tz2 = (self.z0 - o[..., 2]) / d[..., 2], (self.z1 - o[..., 2]) / d[..., 2]
        z_inside = (o[..., 2] >= self.z0) & (o[..., 2] <= self.z1)
        flat = d[..., 2] == 0
        z_in = np.where(flat, np.where(z_inside, -np.inf, np.inf), np.minimum(tz1, tz2))
        z_out = np.where(flat, np.where(z_inside, np.inf, -np.inf), np.maximum(tz1, tz2))
        enter, leave = np.maximum(t_in, z_in), np.minimum(t_out, z_out)
        return (disc >= 0) & (enter <= leave) & (leave > 0)


@dataclass(frozen=True)
class Union:
    parts: Tuple[object, ...]

    def contains(self, p: np.ndarray) -> np.ndarray:
        return np.any([s.contains(p) for s in self.parts], axis=0)

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        return np.any([s.hit(o, d) for s in self.parts], axis=0)


def render_mask(shape, camera: CameraModel, T_WC: np.ndarray, box: Tuple[Sequence[float], Sequence[float]]) -> np.ndarray:
    """Exact silhouette (uint8 0/1): pixels whose centre ray meets the shape.

    Only pixels inside the projection of ``box`` (a world box around the shape, grown by 2 px)
    are ray-cast; a box reaching behind the camera means the whole image.
    """
    mask = np.zeros((camera.height, camera.width), dtype=np.uint8)
    corners = np.array([[x, y, z] for x in (box[0][0], box[1][0]) for y in (box[0][1], box[1][1]) for z in (box[0][2], box[1][2])])
    uv, in_front = camera.project_world(corners, T_WC)
    u0, v0, u1, v1 = 0, 0, camera.width, camera.height
    if in_front.all():
        u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 2, 0)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 3, (camera.width, camera.height))
    if u1 <= u0 or v1 <= v0:
        return mask
    u, v = np.meshgrid(np.arange(u0, u1, dtype=float), np.arange(v0, v1, dtype=float))
    rays = camera.pixels_to_rays(np.column_stack([u.ravel(), v.ravel()])) @ T_WC[:3, :3].T
    hits = shape.hit(np.broadcast_to(T_WC[:3, 3], rays.shape), rays)
    mask[v0:v1, u0:u1] = hits.reshape(v1 - v0, u1 - u0)
    return mask


def analytic_hull(
    shape, views: Sequence[Tuple[np.ndarray, CameraModel, np.ndarray]], points: np.ndarray, chunk: int = 65536
) -> np.ndarray:
    """Which ``points`` (N x 3) lie in every view's silhouette cone; every view must see all of them."""
    keep = np.ones(len(points), dtype=bool)
    for start in range(0, len(points), chunk):  # chunks keep the temporaries in cache
        part = points[start : start + chunk]
        inside = keep[start : start + chunk]
        for _, _, T_WC in views:
            rays = part - T_WC[:3, 3]
            rays /= np.linalg.norm(rays, axis=1, keepdims=True)
            inside &= shape.hit(np.broadcast_to(T_WC[:3, 3], rays.shape), rays)
    return keep
