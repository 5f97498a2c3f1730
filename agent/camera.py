"""Camera geometry: pinhole + distortion model, pixel rays, poses, horizontal azimuths.

Conventions (docs/frames.md): the camera frame is OpenCV's optical frame (x right, y down,
z forward). Poses are 4x4 homogeneous transforms named ``T_AB`` mapping points of frame B into
frame A: ``p_A = T_AB @ p_B``. The world W has z up and the floor at z = 0; the robot frame B is
NAO's FRAME_ROBOT; the camera-in-robot transform ``T_BC`` arrives in the optical convention (the
NAO-camera to optical conversion is done once, at the bridge: ``nao_core.robot_model``).

Pixel to ray (undistorted by OpenCV's iterative model inversion)::

    (x_n, y_n) = undistort(K^-1 [u v 1]^T)   (iterated to convergence),   ray_C = [x_n, y_n, 1] / ||[x_n, y_n, 1]||

Azimuth of a ray in the world's horizontal plane::

    r_W = R_WC ray_C,   a = atan2(r_W.y, r_W.x)

The lens's field: OpenCV's polynomial r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6) (r the normalized
radius) folds back beyond its maximum for some lenses (k1 = -0.12, k2 = -0.05: a point 57 deg off the
axis lands in the image's corner), so a point is projected only within ``field_radius``, 1.1 times
the largest undistorted radius of the image's corners: beyond, no pixel shows it.

For a vertical cylinder, the extreme left/right silhouette pixels back-project to rays lying in
the two vertical tangent planes, whatever the camera pitch, so their azimuths a_l > a_r give the
apparent width delta = a_l - a_r and the bearing of the centre (a_l + a_r) / 2 exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from nao_core.geometry import invert

# OpenCV's default undistortion stops after a few iterations (about 1e-4 deg of error); iterate to
# convergence instead so that back-projected rays are exact to well below a micro-radian.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)



@dataclass(frozen=True)
class CameraModel:
    """Intrinsics K (3x3), distortion (k1, k2, p1, p2, k3) and image size."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int

    @classmethod
    def from_intrinsics(cls, intrinsics) -> "CameraModel":
        """From a robot model's ``CameraIntrinsics`` (anything with K, dist, width and height)."""
        return cls(K=np.asarray(intrinsics.K, dtype=float), dist=np.asarray(intrinsics.dist, dtype=float),
                   width=int(intrinsics.width), height=int(intrinsics.height))

    @classmethod
    def from_fov(cls, width: int, height: int, hfov: float) -> "CameraModel":
        """An ideal pinhole with square pixels and the given horizontal field of view (rad)."""
        f = 0.5 * width / math.tan(0.5 * hfov)
        K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
        return cls(K=K, dist=np.zeros(5), width=width, height=height)

    @property
    def hfov(self) -> float:
        return 2.0 * math.atan(0.5 * self.width / self.K[0, 0])

    def normalized(self, uv: np.ndarray) -> np.ndarray:
        """Normalized coordinates (x_n, y_n) (N x 2) of pixel coordinates ``uv`` (N x 2), distortion removed."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if not len(pts):  # OpenCV returns None for no points
            return np.zeros((0, 2))
        return cv2.undistortPoints(pts, self.K, self.dist, R=None, P=None, criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Pixel coordinates ``uv`` (N x 2) with the distortion removed: where the ideal pinhole of K sees them."""
        if not np.any(self.dist):
            return np.asarray(uv, dtype=float).reshape(-1, 2)
        return self.normalized(uv) @ self.K[:2, :2].T + self.K[:2, 2]

    def distort(self, uv: np.ndarray) -> np.ndarray:
        """Where the lens shows what the ideal pinhole of K shows at ``uv`` (N x 2): the inverse of
        ``undistort``; NaN beyond the lens's field (``field_radius``)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        if not np.any(self.dist):
            return uv
        normalized = (uv - self.K[:2, 2]) @ np.linalg.inv(self.K[:2, :2]).T
        out = np.full(uv.shape, np.nan)
        ok = np.hypot(normalized[:, 0], normalized[:, 1]) <= self.field_radius  # NaN pixels fail it too
        out[ok] = self.project(np.column_stack([normalized[ok], np.ones(int(ok.sum()))]))
        return out

    def pixels_to_rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit rays in the optical frame for pixel coordinates ``uv`` (N x 2), distortion removed."""
        normalized = self.normalized(uv)
        rays = np.hstack([normalized, np.ones((normalized.shape[0], 1))])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def project(self, points_C: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N x 2) of optical-frame points (N x 3) in front of the camera."""
        pts = np.asarray(points_C, dtype=np.float64).reshape(-1, 3)
        if not len(pts):  # OpenCV returns None for no points
            return np.zeros((0, 2))
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(-1, 2)

    @cached_property
    def field_radius(self) -> float:
        """The normalized radius beyond which the lens shows nothing (module docstring); inf without distortion."""
        if not np.any(self.dist):
            return math.inf
        corners = np.array([[0.0, 0.0], [self.width - 1.0, 0.0], [0.0, self.height - 1.0], [self.width - 1.0, self.height - 1.0]])
        return 1.1 * float(np.linalg.norm(self.normalized(corners), axis=1).max())

    def project_world(self, points_W: np.ndarray, T_WC: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of world points and a mask of those in front of the camera (z_C > 0) and within the
        lens's field (``field_radius``); NaN pixels for the others."""
        T_CW = invert(T_WC)
        pts = np.asarray(points_W, dtype=np.float64).reshape(-1, 3)
        pc = pts @ T_CW[:3, :3].T + T_CW[:3, 3]
        in_front = pc[:, 2] > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            in_front &= np.hypot(pc[:, 0], pc[:, 1]) <= self.field_radius * pc[:, 2]
        uv = np.full((pts.shape[0], 2), np.nan)
        if in_front.any():
            uv[in_front] = self.project(pc[in_front])
        return uv, in_front






def ray_azimuths(rays_C: np.ndarray, T_WC: np.ndarray) -> np.ndarray:
    """World azimuths atan2(y, x) of optical-frame rays (N x 3) after rotation into the world."""
    r_W = np.asarray(rays_C, dtype=float).reshape(-1, 3) @ T_WC[:3, :3].T
    return np.arctan2(r_W[:, 1], r_W[:, 0])


def optical_axis_heading(T_WC: np.ndarray) -> float:
    """Azimuth psi of the optical axis (the camera's z) projected on the floor."""
    z = T_WC[:3, 2]
    return math.atan2(z[1], z[0])
