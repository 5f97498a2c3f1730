"""The floor the robot may walk on, read from the landmark map: it keeps off the walls.

Landmarks are put on the room's walls, or on posts around the place the robot works
(docs/landmarks.md). Each gives a half-plane of the floor that the robot stays inside, by
``wall_clearance`` m (its body and walking error)::

    ArUco marker at p facing n (its horizontal normal):   s(x) = n . (x - p) >= m
    colour ball at p (no facing):  n = (o - p) / |o - p|,  o the object estimate

and the walkable floor is their intersection, convex as a room seen from inside. A ball's wall faces
where the robot works: its half-plane is tangent to the circle through it round the object, so the
disc |x - o| <= |p - o| - m is always walkable, whatever walls the balls are on. Balls along one wall
give half-planes slanted towards the object; together they approximate the wall (in a 4 x 4 m room
of balls every 0.6 m, the object in the middle, at most 5 cm beyond it and 20 cm inside it beside a
ball: tests/test_keep_in.py). Facing the balls' centroid instead, as before, balls on one wall only
faced along it and cut the room into a band 0.5 m wide round the object: the planner fled it with
the object behind the robot (one-wall colour worlds 502 and 503, ``object_lost``). Without an object
(:meth:`KeepIn.distances` without walls: the localizer's check that a cold hypothesis stands inside
the floor the balls enclose) a ball faces the balls' centroid, and balls on one line enclose none.
A half-plane that does not hold the object estimate o (n . (o - p) < r: a marker on a box in the
room, facing out, is no wall) is left out.

The planner's cost (agent/planner.py) adds the hard term

    c_wall = W sum_k sum_j max(0, m - s_j(p_k))^2

over the horizon's positions p_k, with the weight W of the object clearance: a sequence that keeps
off every wall beats any that does not; when none can (a robot put down too near a wall), the
least violating one leads away from it. The pilot also cuts a walk command that approaches a wall
nearer than ``wall_stop`` to its turn (station/pilot.py), the last line when the plan is late.
Both act only once the robot's pose is in the map's frame (anchored).

Walls can hide part of the object: bin i of the coverage (agent/coverage.py: at q_i = o + r n_i,
seen from within alpha of its normal n_i) is reachable when some camera position

    c = q_i + rho (cos(a_i + beta), sin(a_i + beta)),  |beta| <= alpha - margin,  rho >= clearance,

keeps the object clearance (|c - o| - r >= clearance) and every wall's (s_j(c) >= m) (a grid of
beta and rho up to ``REACH`` m). The mission's coverage target counts the reachable bins only
(:func:`reachable_bins`, with the slack of ``Planner.reachable_bins``: the walk at constant speed
needs its turn radius to get into a pocket and out), so an object too near a wall to go round
completes with the views the room allows instead of walking its time limit out.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np

from agent.coverage import CoverageParams, bin_angles
from nao_core.landmark_map import LandmarkMap

REACH = 1.0  # m beyond the object clearance searched for a camera position that sees a bin
COLLINEAR = 0.05  # m: balls whose positions spread less than this across their main line lie on one line (enclose no floor)


class HalfPlanes(NamedTuple):
    """Half-planes n_j . x >= d_j of the floor: unit normals (J, 2) and offsets d_j (J,)."""

    normals: np.ndarray
    offsets: np.ndarray


class KeepIn:
    """The floor's half-planes from a landmark map: each ArUco marker's, and each ball's facing a point."""

    def __init__(self, landmark_map: LandmarkMap):
        markers = [lm for lm in landmark_map.landmarks if lm.kind == "aruco"]
        normals = np.array([lm.normal[:2] / np.linalg.norm(lm.normal[:2]) for lm in markers], float).reshape(-1, 2)
        anchors = np.array([lm.position[:2] for lm in markers], float).reshape(-1, 2)
        self._markers = HalfPlanes(normals, np.einsum("ij,ij->i", normals, anchors))  # an ArUco normal is horizontal (yaw)
        self._balls = np.array([lm.position[:2] for lm in landmark_map.landmarks if lm.kind == "color"], float).reshape(-1, 2)
        # without an object: the balls facing their centroid, none when they lie on one line (fixed: the localizer's hot path)
        self._enclosing = self._markers if _collinear(self._balls) else self._facing(self._balls.mean(axis=0))

    def _facing(self, point: np.ndarray) -> HalfPlanes:
        """The markers' half-planes and the balls' facing ``point`` (a ball at the point faces no way)."""
        towards = np.asarray(point, float) - self._balls
        length = np.hypot(towards[:, 0], towards[:, 1])
        keep = length >= 1e-6
        normals = towards[keep] / length[keep, None]
        return HalfPlanes(np.concatenate([self._markers.normals, normals]),
                          np.concatenate([self._markers.offsets, np.einsum("ij,ij->i", normals, self._balls[keep])]))

    def walls(self, x: np.ndarray) -> HalfPlanes:
        """The room's walls for the object estimate x = (xo, yo, r): the half-planes (balls facing the
        object) that hold it."""
        o = np.asarray(x[:2], float)
        planes = self._facing(o)
        holds = planes.normals @ o - planes.offsets >= float(x[2])
        return HalfPlanes(planes.normals[holds], planes.offsets[holds])

    def distances(self, positions: np.ndarray, walls: Optional[HalfPlanes] = None) -> np.ndarray:
        """Signed distances s_j (..., J) of positions (..., 2) in front of ``walls``; without them, of the
        markers' half-planes and the balls' facing their centroid (none when the balls lie on one line)."""
        walls = self._enclosing if walls is None else walls
        return positions @ walls.normals.T - walls.offsets

    def nearest(self, position: np.ndarray, x: np.ndarray) -> Optional[np.ndarray]:
        """(distance, normal x, normal y) of the nearest wall of the object estimate x to a position, or None."""
        walls = self.walls(x)
        if not len(walls.offsets):
            return None
        distances = self.distances(np.asarray(position[:2], float), walls)
        j = int(np.argmin(distances))
        return np.array([distances[j], *walls.normals[j]])


def _collinear(points: np.ndarray) -> bool:
    """Do the points (N, 2) lie on one line (or are fewer than three), so that they enclose no floor?"""
    if len(points) < 3:
        return True
    return bool(np.linalg.svd(points - points.mean(axis=0), compute_uv=False)[1] / math.sqrt(len(points)) < COLLINEAR)


def reachable_bins(keep_in: KeepIn, x: np.ndarray, params: CoverageParams, clearance: float, wall_clearance: float,
                   margin: float = 0.0) -> np.ndarray:
    """Bins (N0,) of the cylinder x = (xo, yo, r) seen from some camera position off the object and
    the walls (module docstring)."""
    x = np.asarray(x, float)
    walls = keep_in.walls(x)
    a = bin_angles(params.bins)[:, None, None]
    half = max(params.facing_angle - margin, 0.0)
    beta = np.linspace(-half, half, 9)[None, :, None]
    rho = np.linspace(clearance, clearance + REACH, 11)[None, None, :]
    cx = x[0] + x[2] * np.cos(a) + rho * np.cos(a + beta)
    cy = x[1] + x[2] * np.sin(a) + rho * np.sin(a + beta)
    cams = np.stack(np.broadcast_arrays(cx, cy), axis=-1)  # (N0, beta, rho, 2)
    ok = np.hypot(cx - x[0], cy - x[1]) - x[2] >= clearance
    ok &= np.all(keep_in.distances(cams, walls) >= wall_clearance, axis=-1)  # no wall: all of none holds
    return ok.any(axis=(1, 2))
