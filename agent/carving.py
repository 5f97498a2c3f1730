"""Space carving (Kutulakos & Seitz): the visual hull of silhouettes in a voxel volume, conservative.

Volume. Around the object estimate (centre (x, y), radius r, covariance Sigma of (x, y, r)) the
volume is the box [x - rho, x + rho] x [y - rho, y + rho] x [0, h] with

    rho = r + margin + kappa (sqrt(lambda_max(Sigma_xy)) + sqrt(Sigma_rr)),

the floor at z = 0 and h = min(max_height, min_v h_v). A view's top silhouette row v_top bounds the
object from above: every object point p projects at a row v >= v_top - 1/2, i.e. m_W . (p - C) >= 0
with m_W = R_WC (0, 1, -(v_top - 1/2 - c_y) / f_y) and C the camera centre; over the disk of radius
rho this gives (when m_W,z < 0, an upright camera)

    h_v = C_z + (m_x (x - C_x) + m_y (y - C_y) + rho hypot(m_x, m_y)) / (-m_z).

Voxels. Cubes of edge ``pitch``; voxel (i, j, k) spans corner + pitch [i, i+1] x [j, j+1] x [k, k+1]
and its centre is origin + pitch (i, j, k) with origin = corner + pitch / 2.

Projection. [a, b, w]^T = K [R_CW | t_CW] [x; 1], (u, v) = (a / w, b / w); w is the depth.

Footprint test (conservative). For a cube Q with all eight corners in front of the camera
(w > 0), its image under a pinhole is the convex hull of the eight projected corners, so their
bounding box B = [u_min, u_max] x [v_min, v_max] contains the whole footprint (the eight corners
are exact, where a bounding sphere is looser and not nested between octree levels). Pixel j covers
[j - 1/2, j + 1/2], so the pixels j0 = floor(u_min + 1/2) .. j1 = floor(u_max + 1/2) (rows alike)
cover B, and the summed-area table I of the mask counts its silhouette pixels in O(1):

    S(B) = I[v1+1, u1+1] - I[v0, u1+1] - I[v1+1, u0] + I[v0, u0].

A view says the voxel is empty iff all corners are in front, B lies inside the image and S(B) = 0:
then no point of the voxel projects onto the silhouette. Voxels behind the camera or whose B leaves
the image are kept (unknown). A voxel survives while at most k views say empty (tolerance k).

Lens distortion. The mask is first resampled to an ideal pinhole (bilinear, thresholded at 1/2: the
edge stays where it was, with no growth; a 3 x 3 dilation here used to widen every silhouette by a
pixel a side, about 4 mm of width at 0.6 m in QVGA), the view's camera from then on: K with its
focal lengths scaled by the least s >= 1 that puts the pinhole's whole frame inside the lens's
image (``_pinhole``; s = 1 for a barrel, whose image reaches beyond the pinhole's frame; a
pincushion's does not reach its corners). Every pinhole pixel is then seen: pixels outside the
lens's image filled as silhouette (unknown) would make every silhouette touch the top border (no
height bound: a carve 0.6 m tall, IoU 0.10 in matrix world 6 with k1 = 0.12) and the bottom row's
floor extension span the frame.

Coarse to fine. Cells of 2^l x 2^l x 2^l voxels form an octree over the grid. Q_child is inside
Q_parent, so B_child is inside B_parent: a parent that is empty in a view has only empty children;
a parent whose B is all silhouette (S = area) has none; only the other cells are split, and only
their living children are tested. The result equals testing every voxel in every view. Each view
walks the octree depth first in a numba-compiled kernel (float64 geometry, one O(1) test per cell);
the NumPy level-by-level version of the same walk took 3.5 times the CPU time (docs/carving.md).

Incremental = batch. A voxel's fate depends only on how many views say it is empty, whatever
their order, so adding views one at a time (live) or all at once (offline) gives the same grid.

Consistent tolerance (the final carve). The true object projects exactly onto every silhouette;
a hull carved at tolerance k re-projects onto view i with the agreement

    a_i(k) = |S_i  and  proj(H_k)| / |S_i  or  proj(H_k)|     (proj: voxel centres, grown by half a voxel's image),

near 1 for every i with consistent views. Keyframe poses off by centimetres (a far, sparse
landmark layout) make the views disagree: each carves what the others saw, the hull loses parts
of the object and a_i falls; a larger k keeps them, until the hull grows past the silhouettes and
a_i falls again. :func:`carve_consistent` carves once with k_max = ``tolerance_max`` (counts are
exact up to k_max + 1) and keeps the k in [``tolerance``, k_max] of largest mean_i a_i(k) (the
smallest such k on a tie): the hull that best re-projects onto its own silhouettes.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np
import trimesh
from numba import njit

from agent.camera import CameraModel
from agent.ekf import position_std
from agent.mesh import ColourView, colour_vertices, occupancy_to_mesh
from nao_core.config import CONFIG_DIR, bounds, load
from nao_core.geometry import invert

View = Tuple[np.ndarray, CameraModel, np.ndarray]
"""(silhouette mask HxW bool/uint8, camera, T_WC 4x4 in the optical convention)."""

_MIN_DEPTH = 1e-6  # m: corners nearer than this to the camera plane count as behind it
_EMPTY, _KEEP, _SPLIT = 0, 1, 2  # a cell in one view: carve it; keep it and its children; test its children


@dataclass(frozen=True)
class CarvingParams:
    """Carving parameters (config/carving.yaml, section ``carving``)."""

    pitch: float = field(metadata=bounds(1e-4, 1.0))  # voxel edge, m
    cells: Optional[int] = field(metadata=bounds(1, 4096))  # or voxels along the longest axis
    margin: float = field(metadata=bounds(0.0, 5.0))
    sigma_scale: float = field(metadata=bounds(0.0, 10.0))
    max_height: float = field(metadata=bounds(1e-3, 10.0))
    tolerance: int = field(metadata=bounds(0, 200))
    tolerance_max: int = field(metadata=bounds(0, 200))  # the final carve's k may grow to this (carve_consistent)
    octree_levels: int = field(metadata=bounds(0, 10))
    max_voxels: int = field(metadata=bounds(1, 1 << 31))
    dilation: int = field(metadata=bounds(0, 50))
    floor_prior: bool
    mesh_smoothing: float = field(metadata=bounds(0.0, 5.0))  # sigma of the mesh's field, voxels (agent/mesh.py)
    keyframes: int = field(metadata=bounds(1, 1000))  # at most this many views in the final carve (agent/keyframes.py)
    keyframe_gap: float = field(metadata=bounds(0.0, math.pi))  # rad: no view closer than this to a chosen one
    keyframe_pose_std: float = field(metadata=bounds(1e-4, 1.0))  # m: pose std (at the object) that halves a view's quality
    keyframe_cut: float = field(metadata=bounds(0.0, 1.0))  # quality factor of a silhouette cut by an image border
    keyframe_rotation_sigma: float = field(metadata=bounds(1e-5, 1.0))  # rad: orientation prior of a keyframe's refinement (agent/keyframe_pose.py)
    keyframe_position_sigma: float = field(metadata=bounds(1e-5, 1.0))  # m: position prior of a keyframe's refinement


def load_carving_params(overrides: Sequence[Union[str, Path]] = ()) -> CarvingParams:
    """CarvingParams from config/carving.yaml merged with ``overrides``."""
    return load(CarvingParams, [CONFIG_DIR / "carving.yaml", *overrides], section="carving")


@dataclass(frozen=True)
class HullMetrics:
    """Size of the carved hull: volume (m^3), extents along x, y, z (m), centroid and box (m)."""

    volume: float
    width: float
    depth: float
    height: float
    centroid: Optional[Tuple[float, float, float]]
    bounds_min: Optional[Tuple[float, float, float]]
    bounds_max: Optional[Tuple[float, float, float]]


def volume_bounds(
    centre_xy: Sequence[float],
    radius: float,
    params: CarvingParams,
    covariance: Optional[np.ndarray] = None,
    views: Iterable[View] = (),
) -> Tuple[np.ndarray, np.ndarray]:
    """Box (min, max corners) around an object estimate; see the module docstring."""
    x, y = (float(c) for c in centre_xy)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(radius) and radius >= 0.0):
        raise ValueError(f"object estimate: expected a finite centre and radius >= 0, got ({x}, {y}), {radius}")
    spread = 0.0
    if covariance is not None:
        cov = np.asarray(covariance, dtype=float)
        if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
            raise ValueError(f"covariance: expected a finite 3x3 matrix of (x, y, r), got shape {cov.shape}")
        spread = position_std(cov) + math.sqrt(max(cov[2, 2], 0.0))
    rho = radius + params.margin + params.sigma_scale * spread
    top = params.max_height
    for mask, camera, T_WC in views:
        silhouette, pinhole = _pinhole_mask(*_checked_view(mask, camera, T_WC))
        top = min(top, _height_bound(silhouette, pinhole, np.asarray(T_WC, dtype=float), (x, y), rho))
    top = max(top, params.pitch)
    return np.array([x - rho, y - rho, 0.0]), np.array([x + rho, y + rho, top])


def estimate_footprint(bounds_min: np.ndarray, bounds_max: np.ndarray) -> Tuple[float, float, float]:
    """(x, y, rho): the disk inscribed in the square footprint of :func:`volume_bounds`."""
    centre = 0.5 * (bounds_min + bounds_max)
    return float(centre[0]), float(centre[1]), 0.5 * float(bounds_max[0] - bounds_min[0])


def _height_bound(silhouette: np.ndarray, camera: CameraModel, T_WC: np.ndarray, xy: Tuple[float, float], rho: float) -> float:
    rows = np.flatnonzero(silhouette.any(axis=1))
    if rows.size == 0 or rows[0] == 0:  # nothing seen, or the object may continue above the image
        return math.inf
    y_n = (rows[0] - 0.5 - camera.K[1, 2]) / camera.K[1, 1]
    m = T_WC[:3, :3] @ np.array([0.0, 1.0, -y_n])
    if m[2] >= -1e-9:  # camera not upright: the top row bounds nothing from above
        return math.inf
    c = T_WC[:3, 3]
    return float(c[2] + (m[0] * (xy[0] - c[0]) + m[1] * (xy[1] - c[1]) + rho * math.hypot(m[0], m[1])) / -m[2])


def _checked_view(mask: np.ndarray, camera: CameraModel, T_WC: np.ndarray) -> Tuple[np.ndarray, CameraModel]:
    """Validate one view; return the mask as uint8 0/1 and the camera. Raises ValueError naming the fault."""
    if not isinstance(camera, CameraModel):
        raise ValueError(f"camera: expected an agent.camera.CameraModel, got {type(camera).__name__}")
    K = np.asarray(camera.K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"camera.K: expected a finite 3x3 matrix, got {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], (0.0, 0.0, 1.0)) or abs(np.linalg.det(K)) < 1e-12:
        raise ValueError(f"camera.K: singular or not an intrinsic matrix (fx, fy > 0, last row 0 0 1): {K.tolist()}")
    dist = np.asarray(camera.dist, dtype=float).ravel()
    if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise ValueError(f"camera.dist: expected 4, 5, 8, 12 or 14 finite coefficients, got {dist.tolist()}")
    m = np.ascontiguousarray(mask)
    if m.shape != (camera.height, camera.width):
        raise ValueError(f"mask: shape {m.shape} does not match the camera image (height, width) = ({camera.height}, {camera.width})")
    if m.dtype not in (np.bool_, np.uint8):
        raise ValueError(f"mask: expected dtype bool or uint8, got {m.dtype}")
    T = np.asarray(T_WC, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_WC: expected a finite 4x4 pose, got shape {T.shape}{'' if T.shape != (4, 4) else ' with non-finite entries'}")
    R = T[:3, :3]
    if not np.allclose(T[3], (0.0, 0.0, 0.0, 1.0)) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("T_WC: not a rigid transform (rotation must be orthonormal with det +1, last row 0 0 0 1)")
    binary = m.view(np.uint8) if m.dtype == np.bool_ else cv2.threshold(m, 0, 1, cv2.THRESH_BINARY)[1]
    return binary, camera


PINHOLE_MAX_ZOOM = 2.0  # a lens whose image needs the pinhole's focal lengths scaled beyond this is refused


@functools.lru_cache(maxsize=4)
def _undistort_maps(K: bytes, dist: bytes, size: Tuple[int, int]) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(map_x, map_y, K'): pixel maps from the ideal pinhole K' (module docstring, "Lens distortion") to the
    distorted image (float64 K and dist as bytes). Every view of a run shares one camera, and a VGA
    map costs about 5 ms: it is computed once."""
    K_, dist_ = np.frombuffer(K).reshape(3, 3), np.frombuffer(dist)
    width, height = size
    border = np.concatenate([[(u, v) for u in range(width) for v in (0, height - 1)],
                             [(u, v) for v in range(height) for u in (0, width - 1)]]).astype(np.float64)
    normalized = (border - K_[:2, 2]) / np.diag(K_)[:2]

    def inside(scale: float) -> bool:  # the pinhole's border, its focal lengths times scale, within the lens's image
        rays = np.column_stack([normalized / scale, np.ones(len(normalized))])
        uv = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_, dist_)[0].reshape(-1, 2)
        return bool(np.all((uv >= 0.0) & (uv <= (width - 1, height - 1))))

    low, high = 1.0, PINHOLE_MAX_ZOOM
    if not inside(high):
        raise ValueError(f"camera.dist {dist_.tolist()}: the lens's image holds no pinhole frame of the same size "
                         f"with its focal lengths up to {PINHOLE_MAX_ZOOM} times K's")
    if not inside(low):
        for _ in range(30):  # bisection to 1e-9 of the scale
            low, high = (low, 0.5 * (low + high)) if inside(0.5 * (low + high)) else (0.5 * (low + high), high)
        low = high
    pinhole = K_.copy()
    pinhole[0, 0] *= low
    pinhole[1, 1] *= low
    return (*cv2.initUndistortRectifyMap(K_, dist_, None, pinhole, size, cv2.CV_32FC1), pinhole)


def _pinhole(camera: CameraModel) -> CameraModel:
    """The ideal pinhole a view of ``camera`` is resampled to (module docstring, "Lens distortion")."""
    if not np.any(camera.dist):
        return camera
    K = _undistort_maps(*_map_key(camera))[2]
    return CameraModel(K=K.copy(), dist=np.zeros(5), width=camera.width, height=camera.height)


def _map_key(camera: CameraModel) -> Tuple[bytes, bytes, Tuple[int, int]]:
    K, dist = np.asarray(camera.K, dtype=float), np.asarray(camera.dist, dtype=float).ravel()
    return K.tobytes(), dist.tobytes(), (camera.width, camera.height)


def _pinhole_mask(mask01: np.ndarray, camera: CameraModel) -> Tuple[np.ndarray, CameraModel]:
    """(silhouette, camera): the silhouette as the ideal pinhole sees it, and that pinhole (module docstring)."""
    if not np.any(camera.dist):
        return mask01, camera
    ideal = _remap_to_pinhole(mask01.astype(np.float32), camera)
    return (ideal >= 0.5).astype(np.uint8), _pinhole(camera)


def _pinhole_image(image: np.ndarray, camera: CameraModel) -> np.ndarray:
    """The colour image as the ideal pinhole ``_pinhole(camera)`` sees it (bilinear)."""
    if not np.any(camera.dist):
        return image
    return _remap_to_pinhole(image, camera)


def _remap_to_pinhole(image: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Bilinear resampling of a distorted image onto its ideal pinhole (maps cached per camera; every
    pinhole pixel lies inside the image, the border's replica covers the bilinear lookup's last half pixel)."""
    map_x, map_y, _ = _undistort_maps(*_map_key(camera))
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _dilated(silhouette: np.ndarray, radius: int) -> np.ndarray:
    """The silhouette grown by a disk of ``radius`` pixels (absorbs pose and edge errors)."""
    if radius <= 0:
        return silhouette
    return cv2.dilate(silhouette, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1)))


def _floor_extension(silhouette: np.ndarray, camera: CameraModel, T_WC: np.ndarray) -> np.ndarray:
    """Rows below the image (``floor_prior``, docs/carving.md): the bottom row's silhouette
    runs shrunk toward the vanishing point of the downward vertical, plus one pixel of slack.

    Empty (no rows) when vertical lines do not converge below the image (camera not looking down).
    """
    height, width = silhouette.shape
    down = np.asarray(camera.K, dtype=float) @ (T_WC[:3, :3].T @ np.array([0.0, 0.0, -1.0]))
    if down[2] <= 1e-9 or down[1] / down[2] <= height - 1:
        return np.zeros((0, width), dtype=np.uint8)
    u_vp, v_vp = down[0] / down[2], down[1] / down[2]
    rows = min(height, int(v_vp - (height - 1)))
    scale = (v_vp - (height - 1 + np.arange(1, rows + 1))) / (v_vp - (height - 1))  # 1 at the border, 0 at the VP
    edges = np.flatnonzero(np.diff(np.concatenate([[0], silhouette[-1].astype(np.int8), [0]])))
    columns = np.arange(width)
    extension = np.zeros((rows, width), dtype=bool)
    for first, last in zip(edges[0::2], edges[1::2] - 1):  # runs [first, last] of the bottom row
        lo = u_vp + (first - 0.5 - u_vp) * scale
        hi = u_vp + (last + 0.5 - u_vp) * scale
        extension |= (columns >= np.ceil(lo - 0.5)[:, None] - 1) & (columns <= np.floor(hi + 0.5)[:, None] + 1)
    return extension.astype(np.uint8)


class VoxelCarver:
    """A voxel volume carved by silhouettes, one view at a time (see the module docstring).

    ``bounds_min``/``bounds_max`` are the world box corners (m); ``pitch`` the voxel edge (m),
    defaulting to ``params.pitch`` or to the longest extent / ``params.cells``.
    """

    def __init__(
        self,
        bounds_min: Sequence[float],
        bounds_max: Sequence[float],
        pitch: Optional[float],
        params: CarvingParams,
        footprint: Optional[Tuple[float, float, float]] = None,
    ):
        lo, hi = np.asarray(bounds_min, dtype=float), np.asarray(bounds_max, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError(f"bounds: expected two finite 3-vectors, got {lo.tolist()} and {hi.tolist()}")
        if np.any(hi <= lo):
            raise ValueError(f"bounds: max {hi.tolist()} must exceed min {lo.tolist()} on every axis")
        if pitch is None:
            pitch = params.pitch if params.cells is None else float(np.max(hi - lo)) / params.cells
        if params.tolerance_max < params.tolerance:
            raise ValueError(f"tolerance_max {params.tolerance_max} is below tolerance {params.tolerance}")
        if not (math.isfinite(pitch) and pitch > 0):
            raise ValueError(f"pitch: expected a positive voxel edge in metres, got {pitch}")
        shape = tuple(int(n) for n in np.maximum(np.ceil((hi - lo) / pitch - 1e-9), 1))
        if math.prod(shape) > params.max_voxels:
            raise ValueError(f"volume: {shape} voxels exceed max_voxels = {params.max_voxels}; raise pitch or shrink bounds")
        self.params = params
        self.pitch = float(pitch)
        self.shape: Tuple[int, int, int] = shape  # type: ignore[assignment]
        self.corner = lo
        self.origin = lo + 0.5 * self.pitch
        self.views_added = 0
        self._levels = params.octree_levels
        cell = 1 << self._levels
        padded = tuple(-(-n // cell) * cell for n in shape)
        # Per voxel: how many views said "empty", saturated at k + 1 (dead). The padding is dead.
        self._counts = np.full(padded, params.tolerance + 1, dtype=np.uint8)
        self._counts[: shape[0], : shape[1], : shape[2]] = 0
        if footprint is not None:  # voxels wholly outside the vertical cylinder over the disk are dead
            fx, fy, radius = footprint
            gx = np.abs(self.origin[0] + self.pitch * np.arange(shape[0]) - fx)[:, None]
            gy = np.abs(self.origin[1] + self.pitch * np.arange(shape[1]) - fy)[None, :]
            nearest = np.hypot(np.maximum(gx - 0.5 * self.pitch, 0.0), np.maximum(gy - 0.5 * self.pitch, 0.0))
            self._counts[: shape[0], : shape[1], : shape[2]][nearest > radius] = params.tolerance + 1
        # Octree levels l = 0..L: cells per axis, and for l >= 1 a flat "holds a living voxel" flag
        # per cell, level l stored from _offsets[l].
        self._dims = np.array([[n >> level for n in padded] for level in range(self._levels + 1)], dtype=np.int64)
        sizes = [int(np.prod(d)) if level else 0 for level, d in enumerate(self._dims)]
        self._offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self._alive = np.zeros(self._offsets[-1] + sizes[-1], dtype=bool)
        living = self._counts <= params.tolerance
        for level in range(1, self._levels + 1):  # at first a cell lives iff it holds a living voxel
            d = self._dims[level]
            living = living.reshape(d[0], 2, d[1], 2, d[2], 2).any(axis=(1, 3, 5))
            self._alive[self._offsets[level] : self._offsets[level] + sizes[level]] = living.ravel()
        # Floor prior: the same carve without it, and each view's evidence (projection matrix, silhouette),
        # so that the prior never removes a voxel some view saw inside its image on the silhouette.
        self._plain = VoxelCarver(lo, hi, pitch, dataclasses.replace(params, floor_prior=False), footprint) if params.floor_prior else None
        self._evidence: List[Tuple[np.ndarray, np.ndarray]] = []
        self._occupancy: Optional[Tuple[int, np.ndarray]] = None
        self._colour_views: List[ColourView] = []  # keyframe images for the mesh's vertex colours

    @classmethod
    def from_estimate(
        cls,
        centre_xy: Sequence[float],
        radius: float,
        params: CarvingParams,
        covariance: Optional[np.ndarray] = None,
        views: Iterable[View] = (),
    ) -> "VoxelCarver":
        """A carver whose volume is the vertical cylinder about the object estimate (:func:`volume_bounds`)."""
        lo, hi = volume_bounds(centre_xy, radius, params, covariance, views)
        return cls(lo, hi, None, params, estimate_footprint(lo, hi))

    @property
    def occupancy(self) -> np.ndarray:
        """Bool grid X x Y x Z: True where the voxel survives (with the floor prior: see :meth:`_seen`)."""
        nx, ny, nz = self.shape
        occupied = self._counts[:nx, :ny, :nz] <= self.params.tolerance
        if self._plain is None:
            return occupied
        if self._occupancy is None or self._occupancy[0] != self.views_added:
            disputed = np.argwhere(self._plain.occupancy & ~occupied)  # removed by the prior alone
            occupied[tuple(disputed[self._seen(disputed)].T)] = True
            self._occupancy = (self.views_added, occupied)
        return self._occupancy[1].copy()

    def _seen(self, voxels: np.ndarray) -> np.ndarray:
        """Which voxels (N x 3 indices) some view saw on its silhouette: the centre projects inside the
        image onto the silhouette grown by one pixel (evidence of matter the prior must not override)."""
        seen = np.zeros(len(voxels), dtype=bool)
        centres = np.column_stack([self.origin + self.pitch * voxels, np.ones(len(voxels))])
        for P, silhouette in self._evidence:
            a, b, w = P @ centres.T
            front = w > _MIN_DEPTH
            u = np.floor(np.where(front, a / np.where(front, w, 1.0), -1.0) + 0.5).astype(np.int64)
            v = np.floor(np.where(front, b / np.where(front, w, 1.0), -1.0) + 0.5).astype(np.int64)
            inside = front & (u >= 0) & (u < silhouette.shape[1]) & (v >= 0) & (v < silhouette.shape[0])
            seen[inside] |= silhouette[v[inside], u[inside]] > 0
        return seen

    def add_view(self, mask: np.ndarray, camera: CameraModel, T_WC: np.ndarray, image: Optional[np.ndarray] = None) -> int:
        """Carve with one silhouette; returns the number of voxels it removed. ``image`` (BGR, the
        camera's size) is kept for the mesh's vertex colours."""
        pinhole, ideal = _pinhole_mask(*_checked_view(mask, camera, T_WC))
        if image is not None:
            if np.shape(image) != (camera.height, camera.width, 3) or np.asarray(image).dtype != np.uint8:
                raise ValueError(f"image: expected a {camera.height} x {camera.width} x 3 uint8 BGR image, got {np.shape(image)}")
            self._colour_views.append((_pinhole_image(np.asarray(image), camera), pinhole, ideal.K, np.asarray(T_WC, dtype=float)))
        silhouette = _dilated(pinhole, self.params.dilation)
        P = ideal.K @ invert(np.asarray(T_WC, dtype=float))[:3]
        if self._plain is not None:
            self._plain.add_view(mask, camera, T_WC)
            self._evidence.append((P, _dilated(silhouette, 1)))
            silhouette = np.vstack([silhouette, _floor_extension(silhouette, ideal, np.asarray(T_WC, dtype=float))])
        x, y, w, h = cv2.boundingRect(silhouette)  # the summed-area table covers the silhouette's box only
        table = cv2.integral(silhouette[y : y + h, x : x + w], sdepth=cv2.CV_32S)
        image = np.array([camera.width, silhouette.shape[0], x, y], dtype=np.int64)
        removed = _carve_view(
            self._counts, self._alive, self._offsets, self._dims, P, self.corner, self.pitch, table, image, self.params.tolerance
        )
        self.views_added += 1
        return int(removed)

    def at_tolerance(self, k: int) -> "VoxelCarver":
        """The same views' hull at a tolerance k <= this carver's (counts are exact up to it): a
        read-only view sharing this carver's grid (add views to this carver, not to it)."""
        if not 0 <= k <= self.params.tolerance:
            raise ValueError(f"tolerance {k}: expected 0 .. {self.params.tolerance} (the carve's own)")
        view = copy.copy(self)
        view.params = dataclasses.replace(self.params, tolerance=k)
        view._plain = None if self._plain is None else self._plain.at_tolerance(k)
        view._occupancy = None
        return view

    def silhouette_agreement(self, views: Sequence[View]) -> np.ndarray:
        """a_i per view: the IoU of its silhouette (on the pinhole) and the hull's projection (module
        docstring); 1.0 when both are empty."""
        return self._agreement(_pinhole_views(views))

    def _agreement(self, pinholes: Sequence[View]) -> np.ndarray:
        """:meth:`silhouette_agreement` of views whose masks are already bool pinhole silhouettes."""
        centres = self.origin + self.pitch * np.argwhere(self.occupancy)
        agreement = np.ones(len(pinholes))
        for i, (silhouette, camera, T_WC) in enumerate(pinholes):
            projection = _project_centres(centres, self.pitch, camera, T_WC, silhouette.shape, 0)
            union = np.count_nonzero(silhouette | projection)
            if union:
                agreement[i] = np.count_nonzero(silhouette & projection) / union
        return agreement

    def to_mesh(self) -> trimesh.Trimesh:
        """Closed, smooth mesh of the hull (marching cubes on the smoothed occupancy, agent/mesh.py), world units."""
        mesh = occupancy_to_mesh(self.occupancy, self.origin, self.pitch, self.params.mesh_smoothing)
        return colour_vertices(mesh, self._colour_views) if self._colour_views else mesh

    def save_npz(self, path: Union[str, Path]) -> Path:
        """Write ``occupancy`` (bool), ``origin`` (centre of voxel 0, m) and ``pitch`` (m)."""
        path = Path(path)
        np.savez_compressed(path, occupancy=self.occupancy, origin=self.origin, pitch=np.float64(self.pitch))
        return path

    def metrics(self) -> HullMetrics:
        """Volume (voxel count x pitch^3), axis extents of the occupied voxels, centroid of their centres."""
        occupancy = self.occupancy
        count = int(np.count_nonzero(occupancy))
        if not count:
            return HullMetrics(0.0, 0.0, 0.0, 0.0, None, None, None)
        # Occupied voxels per slice along each axis: extents and centroid without listing the voxels.
        slices = [occupancy.sum(axis=tuple(a for a in range(3) if a != axis), dtype=np.int64) for axis in range(3)]
        first = np.array([np.flatnonzero(s)[0] for s in slices])
        last = np.array([np.flatnonzero(s)[-1] for s in slices])
        lo, hi = self.corner + self.pitch * first, self.corner + self.pitch * (last + 1)
        width, depth, height = (float(e) for e in hi - lo)
        centroid = self.origin + self.pitch * np.array([s @ np.arange(len(s)) for s in slices]) / count
        return HullMetrics(
            volume=count * self.pitch**3,
            width=width,
            depth=depth,
            height=height,
            centroid=tuple(float(c) for c in centroid),
            bounds_min=tuple(float(c) for c in lo),
            bounds_max=tuple(float(c) for c in hi),
        )


def carve(
    views: Iterable[View],
    bounds_min: Sequence[float],
    bounds_max: Sequence[float],
    pitch: Optional[float],
    params: CarvingParams,
    footprint: Optional[Tuple[float, float, float]] = None,
    images: Sequence[Optional[np.ndarray]] = (),
) -> VoxelCarver:
    """Offline carving of all ``views`` (same grid as adding them one by one, in any order); ``images``
    (BGR, one per view or None) colour the mesh."""
    carver = VoxelCarver(bounds_min, bounds_max, pitch, params, footprint)
    views = list(views)
    if images and len(images) != len(views):
        raise ValueError(f"images: {len(images)} given for {len(views)} views")
    for index, (mask, camera, T_WC) in enumerate(views):
        carver.add_view(mask, camera, T_WC, images[index] if images else None)
    return carver


def carve_consistent(
    views: Sequence[View],
    bounds_min: Sequence[float],
    bounds_max: Sequence[float],
    pitch: Optional[float],
    params: CarvingParams,
    footprint: Optional[Tuple[float, float, float]] = None,
    images: Sequence[Optional[np.ndarray]] = (),
) -> VoxelCarver:
    """The final carve at the tolerance whose hull best re-projects onto the silhouettes (module docstring)."""
    views = list(views)
    top = carve(views, bounds_min, bounds_max, pitch, dataclasses.replace(params, tolerance=params.tolerance_max),
                footprint, images)
    pinholes = _pinhole_views(views)  # resampled once for every k tried
    hulls = [top.at_tolerance(k) for k in range(min(params.tolerance, params.tolerance_max), params.tolerance_max + 1)]
    agreement = [float(np.mean(hull._agreement(pinholes))) for hull in hulls]
    return hulls[int(np.argmax(agreement))]  # its occupancy already computed


def _pinhole_views(views: Sequence[View]) -> List[View]:
    """The views with each mask resampled to a bool silhouette on its ideal pinhole (``_pinhole_mask``), and that pinhole."""
    pinholes = [_pinhole_mask(*_checked_view(mask, camera, T_WC)) for mask, camera, T_WC in views]
    return [(silhouette > 0, ideal, np.asarray(T_WC, dtype=float)) for (silhouette, ideal), (_, _, T_WC) in zip(pinholes, views)]


def _project_centres(centres: np.ndarray, pitch: float, camera: CameraModel, T_WC: np.ndarray, shape: Tuple[int, int],
                     pad: int) -> np.ndarray:
    """Bool image (``shape`` grown by ``pad`` px a side) of voxel ``centres`` (N x 3, m) projected on the
    pinhole, each grown by half a voxel's image (edge ``pitch``) at the median depth."""
    height, width = shape
    projection = np.zeros((height + 2 * pad, width + 2 * pad), dtype=np.uint8)
    if not len(centres):
        return projection.astype(bool)
    a, b, w = (np.asarray(camera.K, dtype=float) @ invert(T_WC)[:3]) @ np.column_stack([centres, np.ones(len(centres))]).T
    front = w > _MIN_DEPTH
    if not front.any():
        return projection.astype(bool)
    u, v = np.round(a[front] / w[front]).astype(np.int64), np.round(b[front] / w[front]).astype(np.int64)
    inside = (u >= -pad) & (u < width + pad) & (v >= -pad) & (v < height + pad)
    projection[v[inside] + pad, u[inside] + pad] = 1
    grow = int(math.ceil(0.5 * pitch * camera.K[0, 0] / max(float(np.median(w[front])), 1e-6)))
    return _dilated(projection, grow).astype(bool)


def load_npz(path: Union[str, Path]) -> Tuple[np.ndarray, np.ndarray, float]:
    """(occupancy, origin, pitch) written by :meth:`VoxelCarver.save_npz`."""
    with np.load(Path(path)) as data:
        return data["occupancy"].astype(bool), data["origin"].astype(float), float(data["pitch"])


# Compiled kernels (numba): one view walks the octree depth first, so each cell is tested once, only
# living cells are visited, and the "holds a living voxel" flags are refreshed on the way back up.


@njit(cache=True, inline="always")
def _classify(level, i, j, k, P, corner, pitch, table, image):
    """_EMPTY, _KEEP or _SPLIT for cell (i, j, k) of ``level`` (see the module docstring).

    ``image`` is (width, height, u, v): the image size and the top-left pixel of the silhouette's
    bounding box, whose summed-area table is ``table`` (no silhouette pixel lies outside it).
    """
    edge = pitch * (1 << level)
    x0, y0, z0 = corner[0] + i * edge, corner[1] + j * edge, corner[2] + k * edge
    a0 = P[0, 0] * x0 + P[0, 1] * y0 + P[0, 2] * z0 + P[0, 3]
    b0 = P[1, 0] * x0 + P[1, 1] * y0 + P[1, 2] * z0 + P[1, 3]
    w0 = P[2, 0] * x0 + P[2, 1] * y0 + P[2, 2] * z0 + P[2, 3]
    u_min = v_min = w_min = np.inf
    u_max = v_max = w_max = -np.inf
    for c in range(8):  # corner (x0, y0, z0) + edge * (bit 2, bit 1, bit 0 of c)
        sx, sy, sz = edge * ((c >> 2) & 1), edge * ((c >> 1) & 1), edge * (c & 1)
        w = w0 + P[2, 0] * sx + P[2, 1] * sy + P[2, 2] * sz
        w_min, w_max = min(w_min, w), max(w_max, w)
        if w > _MIN_DEPTH:
            inv = 1.0 / w
            u = (a0 + P[0, 0] * sx + P[0, 1] * sy + P[0, 2] * sz) * inv
            v = (b0 + P[1, 0] * sx + P[1, 1] * sy + P[1, 2] * sz) * inv
            u_min, u_max, v_min, v_max = min(u_min, u), max(u_max, u), min(v_min, v), max(v_max, v)
    if w_max <= _MIN_DEPTH:
        return _KEEP  # behind the camera, and so are its children
    if w_min <= _MIN_DEPTH:
        return _SPLIT  # straddles the camera plane
    width, height = image[0], image[1]
    u0, u1 = np.floor(u_min + 0.5), np.floor(u_max + 0.5)
    v0, v1 = np.floor(v_min + 0.5), np.floor(v_max + 0.5)
    if u1 < 0 or v1 < 0 or u0 >= width or v0 >= height:
        return _KEEP  # wholly outside the image
    if u0 < 0 or v0 < 0 or u1 >= width or v1 >= height:
        return _SPLIT  # partly outside the image
    area = (u1 - u0 + 1) * (v1 - v0 + 1)
    a0, b0 = max(int(u0) - image[2], 0), max(int(v0) - image[3], 0)  # the box clipped to the table
    a1, b1 = min(int(u1) + 1 - image[2], table.shape[1] - 1), min(int(v1) + 1 - image[3], table.shape[0] - 1)
    if a1 <= a0 or b1 <= b0:
        return _EMPTY
    count = table[b1, a1] - table[b0, a1] - table[b1, a0] + table[b0, a0]
    if count == 0:
        return _EMPTY
    return _KEEP if count == area else _SPLIT


@njit(cache=True, inline="always")
def _living(level, i, j, k, counts, alive, offsets, dims, tolerance):
    if level == 0:
        return counts[i, j, k] <= tolerance
    return alive[offsets[level] + (i * dims[level, 1] + j) * dims[level, 2] + k]


@njit(cache=True, inline="always")
def _refresh(level, i, j, k, counts, alive, offsets, dims, tolerance):
    """Recompute the flag of cell (i, j, k) of ``level`` >= 1 from its eight children."""
    any_alive = False
    for c in range(8):
        if _living(level - 1, 2 * i + ((c >> 2) & 1), 2 * j + ((c >> 1) & 1), 2 * k + (c & 1), counts, alive, offsets, dims, tolerance):
            any_alive = True
            break
    alive[offsets[level] + (i * dims[level, 1] + j) * dims[level, 2] + k] = any_alive
    return any_alive


@njit(cache=True)
def _vote(level, i, j, k, counts, alive, offsets, dims, tolerance, removed):
    """One "empty" vote for every voxel of the cell; refresh the flags inside it."""
    size = 1 << level
    for x in range(i * size, (i + 1) * size):
        for y in range(j * size, (j + 1) * size):
            for z in range(k * size, (k + 1) * size):
                if counts[x, y, z] <= tolerance:
                    if counts[x, y, z] == tolerance:
                        removed[0] += 1
                    counts[x, y, z] += 1
    for m in range(1, level + 1):  # finest first, so each level reads refreshed children
        f = 1 << (level - m)
        for a in range(i * f, (i + 1) * f):
            for b in range(j * f, (j + 1) * f):
                for c in range(k * f, (k + 1) * f):
                    _refresh(m, a, b, c, counts, alive, offsets, dims, tolerance)


@njit(cache=True, nogil=True)  # releases the GIL: a carving thread does not stall the control loop
def _carve_view(counts, alive, offsets, dims, P, corner, pitch, table, image, tolerance):
    """Carve the whole octree with one view, depth first; returns the number of voxels removed.

    A split cell is pushed back as a "refresh" entry under its children, so its flag is recomputed
    once they are done (post-order without recursion).
    """
    removed = np.zeros(1, np.int64)
    top = dims.shape[0] - 1
    stack = np.empty((9 * (top + 1) + 1, 5), np.int64)  # level, i, j, k, refresh?
    for i0 in range(dims[top, 0]):
        for j0 in range(dims[top, 1]):
            for k0 in range(dims[top, 2]):
                if not _living(top, i0, j0, k0, counts, alive, offsets, dims, tolerance):
                    continue
                stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = top, i0, j0, k0, 0
                n = 1
                while n:
                    n -= 1
                    level, i, j, k, refresh = stack[n, 0], stack[n, 1], stack[n, 2], stack[n, 3], stack[n, 4]
                    if refresh:
                        _refresh(level, i, j, k, counts, alive, offsets, dims, tolerance)
                        continue
                    status = _classify(level, i, j, k, P, corner, pitch, table, image)
                    if status == _EMPTY:
                        _vote(level, i, j, k, counts, alive, offsets, dims, tolerance, removed)
                    elif status == _SPLIT and level > 0:
                        stack[n, 4] = 1
                        n += 1
                        for c in range(8):
                            a, b, d = 2 * i + ((c >> 2) & 1), 2 * j + ((c >> 1) & 1), 2 * k + (c & 1)
                            if _living(level - 1, a, b, d, counts, alive, offsets, dims, tolerance):
                                stack[n, 0], stack[n, 1], stack[n, 2], stack[n, 3], stack[n, 4] = level - 1, a, b, d, 0
                                n += 1
    return removed[0]
