"""The floor the robot may walk on, read from the landmark map: it keeps off the walls.

Landmarks are put on the room's walls, or on posts around the place the robot works
(docs/landmarks.md). Each gives a half-plane of the floor that the robot stays inside, by
``wall_clearance`` m (its body and walking error)::

    ArUco marker at p facing n (its horizontal normal):   s(x) = n . (x - p) >= m
    colour ball at p (no facing):  n = (c - p) / |c - p|,  c the centroid of all the landmarks

and the walkable floor is their intersection, convex as a room seen from inside. Balls along one
wall give half-planes slanted towards the centroid; together they approximate the wall, and they
never cut the floor between the wall and the centroid. A half-plane that does not hold the object
estimate o (n . (o - p) < r: a marker on a box in the room, facing out, is no wall) is left out.

The planner's cost (agent/planner.py) adds the hard term

    c_wall = W sum_k sum_j max(0, m - s_j(p_k))^2

over the horizon's positions p_k, with the weight W of the object clearance: a sequence that keeps
off every wall beats any that does not; when none can (a robot put down too near a wall), the
least violating one leads away from it. The pilot also cuts a walk command that approaches a wall
nearer than ``wall_stop`` to its turn (station/pilot.py), the last line when the plan is late.
Both act only once the robot's pose is in the map's frame (anchored).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from nao_core.landmark_map import LandmarkMap

MIN_FACING = 0.5  # horizontal part of a marker's normal below which it does not face a wall (on the floor)


class KeepIn:
    """Half-planes n_j . x >= n_j . p_j of the floor, from a landmark map."""

    def __init__(self, landmark_map: LandmarkMap):
        points = np.array([lm.position[:2] for lm in landmark_map.landmarks], float).reshape(-1, 2)
        centroid = points.mean(axis=0) if len(points) else np.zeros(2)
        normals, anchors = [], []
        for lm, p in zip(landmark_map.landmarks, points):
            n = lm.normal[:2] if lm.kind == "aruco" else centroid - p
            length = float(np.linalg.norm(n))
            if length < (MIN_FACING if lm.kind == "aruco" else 1e-6):  # a floor marker, or a ball at the centroid
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
