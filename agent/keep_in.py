"""The floor the robot may walk on, read from the landmark map: it keeps off the walls.

Landmarks are put on the room's walls, or on posts around the place the robot works
(docs/landmarks.md). Each gives a half-plane of the floor that the robot stays inside, by
``wall_clearance`` m (its body and walking error)::

    ArUco marker at p facing n (its horizontal normal):   s(x) = n . (x - p) >= m
    colour ball at p (no facing):  n = (c - p) / |c - p|,  c the centroid of all the landmarks

and the walkable floor is their intersection, convex as a room seen from inside. Balls along one
wall give half-planes slanted towards the centroid; together they approximate the wall (in a
4 x 4 m room of balls every 0.6 m, at most 5 cm beyond it and 20 cm inside it beside a ball:
tests/test_keep_in.py). A half-plane that does not hold the object
estimate o (n . (o - p) < r: a marker on a box in the room, facing out, is no wall) is left out.

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

from typing import Optional

import numpy as np

from agent.coverage import CoverageParams, bin_angles
from nao_core.landmark_map import LandmarkMap

REACH = 1.0  # m beyond the object clearance searched for a camera position that sees a bin


class KeepIn:
    """Half-planes n_j . x >= n_j . p_j of the floor, from a landmark map."""

    def __init__(self, landmark_map: LandmarkMap):
        points = np.array([lm.position[:2] for lm in landmark_map.landmarks], float).reshape(-1, 2)
        centroid = points.mean(axis=0) if len(points) else np.zeros(2)
        normals, anchors = [], []
        for lm, p in zip(landmark_map.landmarks, points):
            n = lm.normal[:2] if lm.kind == "aruco" else centroid - p  # an ArUco normal is horizontal (yaw)
            length = float(np.linalg.norm(n))
            if length < 1e-6:  # a ball at the centroid faces no way
                continue
            normals.append(n / length)
            anchors.append(p)
        self.normals = np.array(normals, float).reshape(-1, 2)
        self.offsets = np.einsum("ij,ij->i", self.normals, np.array(anchors, float).reshape(-1, 2))

    def walls(self, x: np.ndarray) -> np.ndarray:
        """Mask of the half-planes holding the object estimate x = (xo, yo, r): the room's walls."""
        return self.normals @ np.asarray(x[:2], float) - self.offsets >= float(x[2])

    def distances(self, positions: np.ndarray, walls: Optional[np.ndarray] = None) -> np.ndarray:
        """Signed distances s_j (..., J) of positions (..., 2) in front of the half-planes (masked by ``walls``)."""
        normals, offsets = (self.normals, self.offsets) if walls is None else (self.normals[walls], self.offsets[walls])
        return positions @ normals.T - offsets

    def nearest(self, position: np.ndarray, x: np.ndarray) -> Optional[np.ndarray]:
        """(distance, normal x, normal y) of the nearest wall of the object estimate x to a position, or None."""
        walls = self.walls(x)
        if not walls.any():
            return None
        distances = self.distances(np.asarray(position[:2], float), walls)
        j = int(np.argmin(distances))
        return np.array([distances[j], *self.normals[walls][j]])


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
