"""Space carving (Kutulakos & Seitz): the visual hull of silhouettes in a voxel volume, conservative.

Volume. Around the object estimate (centre (x, y), radius r, covariance Sigma of (x, y, r)) the
volume is the box [x - rho, x + rho] x [y - rho, y + rho] x [0, h] with

    rho = r + margin + kappa (sqrt(lambda_max(Sigma_xy)) + sqrt(Sigma_rr)),

the floor at z = 0 and h = min(max_height, min_v h_v). A view's top silhouette row v_top bounds the
object from above: every object point p projects at a row v >= v_top - 1/2, i.e. m_W . (p - C) >= 0
with m_W = R_WC (0, 1, -(v_top - 1/2 - c_y) / f_y) and C the camera centre; over the disk of radius
rho this gives (when m_W,z < 0, an upright camera)

    h_v = C_z + (m_x (x - C_x) + m_y (y - C_y) + rho hypot(m_x, m_y)) / (-m_z).

Voxels. Cubes of edge ``pitch``; voxel (i, j, k) spans corner0 + pitch [i, i+1] x [j, j+1] x [k, k+1]
and its centre is origin + pitch (i, j, k) with origin = corner0 + pitch / 2.

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

Lens distortion. The mask is first resampled to the ideal pinhole with the same K (nearest
neighbour, then a 3 x 3 dilation so no silhouette pixel is lost); pixels that map outside the
original image are set to silhouette (unknown, hence kept).

Coarse to fine. Cells of 2^l x 2^l x 2^l voxels form an octree over the grid. Q_child is inside
Q_parent, so B_child is inside B_parent: a parent that is empty in a view has only empty children;
a parent whose B is all silhouette (S = area) has none; only the other cells are split, and only
their living children are tested. The result equals testing every voxel in every view.

Incremental = batch. A voxel's fate depends only on how many views say it is empty, whatever
their order, so adding views one at a time (live) or all at once (offline) gives the same grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence, Tuple, Union

import cv2
import numpy as np
import trimesh

from agent.camera import CameraModel, invert
from agent.mesh import occupancy_to_mesh
from nao_bridge.config import CONFIG_DIR, bounds, load

View = Tuple[np.ndarray, CameraModel, np.ndarray]
"""(silhouette mask HxW bool/uint8, camera, T_WC 4x4 in the optical convention)."""

_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
_CHILD_OFFSETS = ((_CORNER_SIGNS + 1) // 2).astype(np.int32)
_MIN_DEPTH = 1e-6  # m: corners nearer than this to the camera plane count as behind it


@dataclass(frozen=True)
class CarvingParams:
    """Carving parameters (config/carving.yaml, section ``carving``)."""

    pitch: float = field(default=0.002, metadata=bounds(1e-4, 1.0))
    cells: Optional[int] = field(default=None, metadata=bounds(1, 4096))
    margin: float = field(default=0.05, metadata=bounds(0.0, 5.0))
    sigma_scale: float = field(default=3.0, metadata=bounds(0.0, 10.0))
    max_height: float = field(default=0.60, metadata=bounds(1e-3, 10.0))
    tolerance: int = field(default=0, metadata=bounds(0, 200))
    octree_levels: int = field(default=5, metadata=bounds(0, 10))
    max_voxels: int = field(default=1 << 26, metadata=bounds(1, 1 << 31))


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
        spread = math.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)) + math.sqrt(max(cov[2, 2], 0.0))
    rho = radius + params.margin + params.sigma_scale * spread
    top = params.max_height
    for mask, camera, T_WC in views:
        silhouette = _pinhole_mask(*_checked_view(mask, camera, T_WC))
        top = min(top, _height_bound(silhouette, camera, np.asarray(T_WC, dtype=float), (x, y), rho))
    top = max(top, params.pitch)
    return np.array([x - rho, y - rho, 0.0]), np.array([x + rho, y + rho, top])


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
    m = np.asarray(mask)
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
    return (m != 0).astype(np.uint8), camera


def _pinhole_mask(mask01: np.ndarray, camera: CameraModel) -> np.ndarray:
    """The silhouette as seen by the ideal pinhole with the same K (see the module docstring)."""
    dist = np.asarray(camera.dist, dtype=float).ravel()
    if not np.any(dist):
        return mask01
    K = np.asarray(camera.K, dtype=float)
    size = (camera.width, camera.height)
    map_x, map_y = cv2.initUndistortRectifyMap(K, dist, None, K, size, cv2.CV_32FC1)
    ideal = cv2.remap(mask01, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=1)
    return cv2.dilate(ideal, np.ones((3, 3), np.uint8))


class VoxelCarver:
    """A voxel volume carved by silhouettes, one view at a time (see the module docstring).

    ``bounds_min``/``bounds_max`` are the world box corners (m); ``pitch`` the voxel edge (m),
    defaulting to ``params.pitch`` or to the longest extent / ``params.cells``.
    """

    def __init__(
        self,
        bounds_min: Sequence[float],
        bounds_max: Sequence[float],
        pitch: Optional[float] = None,
        params: CarvingParams = CarvingParams(),
    ):
        lo, hi = np.asarray(bounds_min, dtype=float), np.asarray(bounds_max, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError(f"bounds: expected two finite 3-vectors, got {lo.tolist()} and {hi.tolist()}")
        if np.any(hi <= lo):
            raise ValueError(f"bounds: max {hi.tolist()} must exceed min {lo.tolist()} on every axis")
        if pitch is None:
            pitch = params.pitch if params.cells is None else float(np.max(hi - lo)) / params.cells
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
        self._dead = params.tolerance + 1
        # Per voxel: how many views said "empty", saturated at k + 1 (dead). The padding is dead.
        self._counts = np.full(padded, self._dead, dtype=np.uint8)
        self._counts[: shape[0], : shape[1], : shape[2]] = 0
        # Per octree level l >= 1: does the cell of 2^l voxels hold any living voxel?
        self._alive = [np.empty(0, dtype=bool)]
        for level in range(1, self._levels + 1):
            self._alive.append(_pool_any(self._counts <= params.tolerance, 1 << level))

    @classmethod
    def from_estimate(
        cls,
        centre_xy: Sequence[float],
        radius: float,
        params: CarvingParams = CarvingParams(),
        covariance: Optional[np.ndarray] = None,
        views: Iterable[View] = (),
    ) -> "VoxelCarver":
        """A carver whose volume surrounds the object estimate (:func:`volume_bounds`)."""
        return cls(*volume_bounds(centre_xy, radius, params, covariance, views), params=params)

    @property
    def occupancy(self) -> np.ndarray:
        """Bool grid X x Y x Z: True where the voxel survives."""
        nx, ny, nz = self.shape
        return self._counts[:nx, :ny, :nz] <= self.params.tolerance

    def add_view(self, mask: np.ndarray, camera: CameraModel, T_WC: np.ndarray) -> int:
        """Carve with one silhouette; returns the number of voxels it removed."""
        silhouette = _pinhole_mask(*_checked_view(mask, camera, T_WC))
        table = cv2.integral(silhouette, sdepth=cv2.CV_32S)
        P = np.asarray(camera.K, dtype=float) @ invert(np.asarray(T_WC, dtype=float))[:3]
        empty_cells = []
        cells = np.argwhere(self._alive[self._levels]) if self._levels else np.argwhere(self.occupancy)
        cells = cells.astype(np.int32)
        for level in range(self._levels, -1, -1):
            empty, split = self._classify(cells, level, P, table)
            empty_cells.append((level, cells[empty]))
            if level == 0 or not split.any():
                break
            children = (2 * cells[split][:, None, :] + _CHILD_OFFSETS[None]).reshape(-1, 3)
            cells = children[self._living(level - 1, children)]
        self.views_added += 1
        return self._remove(empty_cells)

    def _classify(self, cells: np.ndarray, level: int, P: np.ndarray, table: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Per cell: empty in this view, and whether its children need testing."""
        edge = self.pitch * (1 << level)
        A = (P[:, :3] * edge).astype(np.float32)
        b = (P[:, :3] @ (self.corner + 0.5 * edge) + P[:, 3]).astype(np.float32)
        centre = (cells.astype(np.float32) @ A.T + b).T  # (3, N): a, b, w of the cell centres
        offsets = (P[:, :3] @ (0.5 * edge * _CORNER_SIGNS.T)).astype(np.float32)[:, :, None]  # (3, 8, 1)
        w = centre[2] + offsets[2]  # (8, N): corner-major, so the reductions below are element-wise
        w_min, w_max = w.min(axis=0), w.max(axis=0)
        w = np.maximum(w, _MIN_DEPTH)
        u = (centre[0] + offsets[0]) / w
        v = (centre[1] + offsets[1]) / w
        height, width = table.shape[0] - 1, table.shape[1] - 1
        u0 = np.floor(np.clip(u.min(axis=0) + 0.5, -1, width)).astype(np.int32)
        u1 = np.floor(np.clip(u.max(axis=0) + 0.5, -1, width)).astype(np.int32)
        v0 = np.floor(np.clip(v.min(axis=0) + 0.5, -1, height)).astype(np.int32)
        v1 = np.floor(np.clip(v.max(axis=0) + 0.5, -1, height)).astype(np.int32)
        in_front = w_min > _MIN_DEPTH
        inside = in_front & (u0 >= 0) & (v0 >= 0) & (u1 < width) & (v1 < height)
        off_image = in_front & ((u1 < 0) | (v1 < 0) | (u0 >= width) | (v0 >= height))
        flat = table.ravel()
        stride = width + 1
        c0, c1 = np.clip(u0, 0, width - 1), np.clip(u1, 0, width - 1) + 1
        r0, r1 = np.clip(v0, 0, height - 1) * stride, (np.clip(v1, 0, height - 1) + 1) * stride
        count = flat[r1 + c1] - flat[r0 + c1] - flat[r1 + c0] + flat[r0 + c0]
        empty = inside & (count == 0)
        full = inside & (count == (c1 - c0) * (r1 - r0) // stride)
        split = ~(empty | full | off_image | (w_max <= _MIN_DEPTH))
        return empty, split

    def _living(self, level: int, cells: np.ndarray) -> np.ndarray:
        if level == 0:
            return self._counts[cells[:, 0], cells[:, 1], cells[:, 2]] < self._dead
        return self._alive[level][cells[:, 0], cells[:, 1], cells[:, 2]]

    def _remove(self, empty_cells: Sequence[Tuple[int, np.ndarray]]) -> int:
        """Count one more "empty" vote for every voxel under the empty cells; refresh the octree."""
        k, removed = self.params.tolerance, 0
        touched = {}
        for level, cells in empty_cells:
            if not len(cells):
                continue
            i, j, l = cells.T
            size = 1 << level
            grid = _blocks(self._counts, size)
            votes = grid[i, :, j, :, l, :]
            removed += int(np.count_nonzero(votes == k))
            votes = np.minimum(votes + 1, self._dead).astype(np.uint8)
            grid[i, :, j, :, l, :] = votes
            for finer in range(1, level):
                _blocks(self._alive[finer], size >> finer)[i, :, j, :, l, :] = _pool_any(votes <= k, 1 << finer, batched=True)
            touched[level] = cells
        # Re-derive "any living voxel" for every ancestor of a touched cell, finest level first.
        dirty = touched.get(0, np.empty((0, 3), np.int32))
        for level in range(1, self._levels + 1):
            parents = dirty // 2
            if level in touched:
                parents = np.vstack([parents, touched[level]])
            if not len(parents):
                dirty = parents
                continue
            shape = self._alive[level].shape
            parents = np.column_stack(np.unravel_index(np.unique(np.ravel_multi_index(parents.T, shape)), shape)).astype(np.int32)
            children = (2 * parents[:, None, :] + _CHILD_OFFSETS[None]).reshape(-1, 3)
            self._alive[level][parents[:, 0], parents[:, 1], parents[:, 2]] = (
                self._living(level - 1, children).reshape(-1, 8).any(axis=1)
            )
            dirty = parents
        return removed

    def to_mesh(self) -> trimesh.Trimesh:
        """Closed mesh of the hull (marching cubes at 0.5 on the padded occupancy), world units."""
        return occupancy_to_mesh(self.occupancy, self.origin, self.pitch)

    def save_npz(self, path: Union[str, Path]) -> Path:
        """Write ``occupancy`` (bool), ``origin`` (centre of voxel 0, m) and ``pitch`` (m)."""
        path = Path(path)
        np.savez_compressed(path, occupancy=self.occupancy, origin=self.origin, pitch=np.float64(self.pitch))
        return path

    def metrics(self) -> HullMetrics:
        """Volume (voxel count x pitch^3), axis extents of the occupied voxels, centroid of their centres."""
        idx = np.argwhere(self.occupancy)
        if not len(idx):
            return HullMetrics(0.0, 0.0, 0.0, 0.0, None, None, None)
        lo = self.corner + self.pitch * idx.min(axis=0)
        hi = self.corner + self.pitch * (idx.max(axis=0) + 1)
        width, depth, height = (float(e) for e in hi - lo)
        centroid = self.origin + self.pitch * idx.mean(axis=0)
        return HullMetrics(
            volume=len(idx) * self.pitch**3,
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
    pitch: Optional[float] = None,
    params: CarvingParams = CarvingParams(),
) -> VoxelCarver:
    """Offline carving of all ``views`` (same grid as adding them one by one, in any order)."""
    carver = VoxelCarver(bounds_min, bounds_max, pitch, params)
    for mask, camera, T_WC in views:
        carver.add_view(mask, camera, T_WC)
    return carver


def load_npz(path: Union[str, Path]) -> Tuple[np.ndarray, np.ndarray, float]:
    """(occupancy, origin, pitch) written by :meth:`VoxelCarver.save_npz`."""
    with np.load(Path(path)) as data:
        return data["occupancy"].astype(bool), data["origin"].astype(float), float(data["pitch"])


def _blocks(grid: np.ndarray, size: int) -> np.ndarray:
    """View of a 3-D grid as (X, size, Y, size, Z, size) blocks."""
    X, Y, Z = grid.shape
    return grid.reshape(X // size, size, Y // size, size, Z // size, size)


def _pool_any(grid: np.ndarray, factor: int, batched: bool = False) -> np.ndarray:
    """Any-pooling of a 3-D grid (or a batch N x a x a x a of them) by ``factor`` on each axis."""
    if batched:
        n, a = grid.shape[0], grid.shape[1] // factor
        return grid.reshape(n, a, factor, a, factor, a, factor).any(axis=(2, 4, 6))
    return _blocks(grid, factor).any(axis=(1, 3, 5))
