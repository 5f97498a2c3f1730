"""Where a landmark fix stays possible: the landmark points a robot pose's head can bring into view.

The planner keeps the robot where landmarks are visible (docs/planner.md, "Landmark reach"): an
orbit that turns the robot's back on the only wall with markers leaves the landmark lookouts
(station/pilot.py) nothing to find when the pose gets uncertain. For a planar robot pose
(x, y, theta), the head pivot at height h_c, and landmark j at c_j = (c_x, c_y, z_j)::

    d_j   = |c_j,xy - (x, y)|,   rho_j = sqrt(d_j^2 + (z_j - h_c)^2)
    b_j   = wrap(atan2(c_y - y, c_x - x) - theta)         bearing from the heading
    e_j   = atan2(z_j - h_c, d_j)                         elevation, up positive
    a_j   = f s_j cos(phi_j) / rho_j                      an ArUco marker's narrowest side, px
                                                          (cos phi_j = n_j . (x - c_j) / d_j, n_j its normal)
    a_j   = f D_j / rho_j                                 a colour ball's diameter, px
    m_j   = (a_j / 2 + margin) / f                        its half size and the border margin, rad

It is in reach when the head's yaw and pitch limits can put it wholly inside the image::

    yaw_min - h_h + m_j <= b_j <= yaw_max + h_h - m_j          h_h = hfov / 2
    -p_hi(y_j) - h_v + m_j <= e_j <= -p_lo(y_j) + h_v - m_j    h_v = vfov / 2, y_j = clip(b_j, yaw limits),
                                                               [p_lo, p_hi] the pitch limits at y_j (down positive)
    a_j >= a_min,  cos phi_j > 0 (ArUco)                       the localizer's prediction rules
                                                               (``aruco_min_side_px``; a ball's ``landmark_min_area``)

and the pose's reachable points are n = sum_j k_j [in reach], k_j = 4 for a marker (its corners), 1
for a ball. A fix needs ``min_points`` in one frame: n counts over the whole head range, so it is
optimistic for balls spread wider than the field of view and exact for one marker. The object
hiding a landmark is not modelled.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from agent.camera import CameraModel
from agent.localization import LocalizationParams
from agent.perception import PerceptionParams
from nao_core.geometry import wrap_angle
from nao_core.landmark_map import LandmarkMap
from nao_core.robot_model import RobotModel


class LandmarkReach:
    """The landmark points each robot pose's head can bring into view (module docstring)."""

    def __init__(self, landmark_map: LandmarkMap, robot: RobotModel, camera: CameraModel,
                 localization: LocalizationParams, perception: Optional[PerceptionParams]):
        landmarks = [lm for lm in landmark_map.landmarks if lm.kind == "aruco" or perception is not None]
        self.aruco = np.array([lm.kind == "aruco" for lm in landmarks], bool)
        self.centres = np.array([lm.position for lm in landmarks], float).reshape(-1, 3)
        self.normals = np.array([lm.normal[:2] for lm in landmarks], float).reshape(-1, 2)  # used for markers only
        self.sizes = np.array([lm.size if lm.kind == "aruco" else lm.diameter for lm in landmarks], float)
        self.counts = np.where(self.aruco, 4, 1)  # k_j
        ball_px = 2.0 * math.sqrt(perception.landmark_min_area / math.pi) if perception is not None else math.inf
        self.min_px = np.where(self.aruco, localization.aruco_min_side_px, ball_px)
        self.min_points = localization.min_points
        self.focal = float(camera.K[0, 0])
        self.margin_px = localization.view_margin_px
        self.half_hfov = 0.5 * camera.hfov
        self.half_vfov = math.atan2(camera.height / 2.0, float(camera.K[1, 1]))
        self.camera_height = robot.neck_height + robot.camera.offset[2]
        self.yaw_limits = robot.head.yaw
        self.pitch_by_yaw = np.asarray(robot.head.pitch_by_yaw, float)

    def in_reach(self, poses: np.ndarray) -> np.ndarray:
        """Whether each landmark is in reach (..., J) of planar robot poses (..., 3) (module docstring)."""
        poses = np.asarray(poses, float)[..., None, :]
        dx, dy = self.centres[:, 0] - poses[..., 0], self.centres[:, 1] - poses[..., 1]
        rise = self.centres[:, 2] - self.camera_height
        d = np.maximum(np.hypot(dx, dy), 1e-6)
        bearing = wrap_angle(np.arctan2(dy, dx) - poses[..., 2])
        elevation = np.arctan2(rise, d)
        facing = -(self.normals[:, 0] * dx + self.normals[:, 1] * dy) / d  # cos phi
        size_px = self.focal * self.sizes * np.where(self.aruco, facing, 1.0) / np.hypot(d, rise)
        half = (0.5 * size_px + self.margin_px) / self.focal
        yaw = np.clip(bearing, *self.yaw_limits)
        p_lo = np.interp(yaw, self.pitch_by_yaw[:, 0], self.pitch_by_yaw[:, 1])
        p_hi = np.interp(yaw, self.pitch_by_yaw[:, 0], self.pitch_by_yaw[:, 2])
        across = (bearing >= self.yaw_limits[0] - self.half_hfov + half) & (bearing <= self.yaw_limits[1] + self.half_hfov - half)
        upright = (elevation >= -p_hi - self.half_vfov + half) & (elevation <= -p_lo + self.half_vfov - half)
        return across & upright & (size_px >= self.min_px) & (~self.aruco | (facing > 0.0))

    def points(self, poses: np.ndarray) -> np.ndarray:
        """The reachable landmark points n (...,) of planar robot poses (..., 3)."""
        return np.sum(self.in_reach(poses) * self.counts, axis=-1)

    def starved(self, poses: np.ndarray) -> np.ndarray:
        """Whether no fix is possible from planar robot poses (..., 3): n < the localizer's ``min_points``."""
        return self.points(poses) < self.min_points
