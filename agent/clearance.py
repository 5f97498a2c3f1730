"""Distance to the object from one image, independent of the filter's estimate (a safety check).

Bottom edge on the floor: the silhouette's lowest row v_b (its columns' mean u_b) is where the
object meets the floor (z = 0). With the camera centre C and the pixel's world ray
d = R_WC K^-1 (u_b, v_b, 1) (d_z < 0: looking down)::

    s = -C_z / d_z,   p = C + s d,   d_floor = |p_xy - C_xy|

A silhouette cut by the bottom border hides its base, which is then nearer than the floor seen at
the bottom row: d_floor is an upper bound there, the best the image gives.

Apparent width: a cylinder of radius r seen under the angle delta has its centre at
r / sin(delta / 2), so its surface at d_width = r / sin(delta / 2) - r (r from the estimate, or
the prior before one exists).

The distance is d_floor when the silhouette's base is in view: it does not depend on the object's
shape, while d_width assumes the estimate's cylinder, and an object that is not one looks wider
from some sides than that radius says, which d_width reads as near (measured: a figure 0.84 m
away read as 0.17 m from the side, and the guard held the robot turning on the spot to the time
limit, docs/benchmarks.md "Mission matrix"). With the base cut, min(d_floor, d_width) over those
available; None when neither is.

The same contact starts the object filter's range (agent/ekf.py, docs/estimation.md "Floor
contact"): its depression below the horizontal, atan2(C_z, d_floor), seen from the height C_z.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from agent.camera import CameraModel
from agent.ekf import FloorContact
from agent.perception import Silhouette


def floor_distance(silhouette: Silhouette, camera: CameraModel, T_WC: np.ndarray) -> Optional[float]:
    """Horizontal distance from the camera to where the silhouette's bottom edge meets the floor."""
    x, y, w, h = silhouette.bbox
    v = y + h - 1
    columns = np.flatnonzero(silhouette.mask[v, x:x + w])
    if columns.size == 0:
        return None
    ray = camera.pixels_to_rays(np.array([[x + float(columns.mean()), float(v)]]))[0]
    d = T_WC[:3, :3] @ ray
    C = T_WC[:3, 3]
    if d[2] >= -1e-9 or C[2] <= 0.0:
        return None  # the bottom edge is not on the floor in front of this camera
    p = C + (-C[2] / d[2]) * d
    return float(math.hypot(p[0] - C[0], p[1] - C[1]))


def floor_contact(silhouette: Silhouette, floor: Optional[float], height: float) -> Optional[FloorContact]:
    """The floor contact of a silhouette whose base is in view (not cut by the bottom border), from
    its :func:`floor_distance` ``floor`` and the camera's ``height``; None otherwise."""
    if silhouette.touches_bottom or floor is None:
        return None
    contact = FloorContact(math.atan2(height, floor), height)
    return contact if contact.valid() else None  # a pose without a finite height above the floor gives none


def width_distance(delta: Optional[float], radius: float) -> Optional[float]:
    """Distance to the surface of a cylinder of ``radius`` seen under the apparent width ``delta``."""
    if delta is None or not 0.0 < delta < math.pi or not radius > 0.0:
        return None
    return radius / math.sin(0.5 * delta) - radius


def image_distance(silhouette: Silhouette, floor: Optional[float], delta: Optional[float], radius: float) -> Optional[float]:
    """The :func:`floor_distance` ``floor`` with the base in view, else the nearer of the two (module
    docstring), or None."""
    if floor is not None and not silhouette.touches_bottom:
        return floor
    found = [d for d in (floor, width_distance(delta, radius)) if d is not None]
    return min(found) if found else None
