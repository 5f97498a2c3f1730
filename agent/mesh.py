"""Surface of a voxel occupancy grid: marching cubes on a smoothed, sign-constrained field; export.

The grid is sampled at voxel centres ``x_ijk = origin + pitch * (i, j, k)``. The occupancy b (1 inside,
0 outside) is padded by two empty voxels on every side so the iso-surface always closes.

Smooth field with the voxels' signs. Marching cubes on b itself puts every vertex at an edge's
midpoint: voxel stairs. Instead the field is the Gaussian-smoothed occupancy (sigma in voxels),
clamped so that each voxel keeps its side of the iso-level 1/2::

    f = G_sigma * b,    f <- max(f, 1/2 + eps) where b = 1,    f <- min(f, 1/2 - eps) where b = 0

The sign pattern of f at the grid points is that of b, so marching cubes makes exactly the same
triangles (same topology: no voxel lost, however thin, and the same closed surface) and only moves
each vertex along its edge, to where the smooth field crosses 1/2: a plane seen as stairs in b
becomes a plane again. scikit-image's classic (Lorensen) marching cubes extracts it: on these sign
patterns its surface is watertight, where the Lewiner variant leaves non-manifold edges where
voxels touch diagonally (tests/test_carving.py checks both facts). Vertices map back to the world by

    x = origin + pitch * (v - 2)        (v in padded index coordinates)

Faces are oriented outwards (normals point from occupied to empty space).

Vertex colours. Each vertex v with outward normal n takes its colour from the keyframe that faces it
best: among the views whose camera centre C sees v inside the image and on the silhouette (grown by
one pixel, so an occluded or background pixel is not sampled), the one maximising the cosine
n . (C - v) / |C - v| > 0; the pixel is sampled at the projection (nearest pixel). Vertices no
view faces stay grey.

Orientation on export. The world is metres, z up (floor z = 0): PLY, STL and OBJ keep it. glTF is
y up (and metres), so GLB files get the rotation (x, y, z) -> (x, z, -y), which keeps the floor
under the object in a glTF viewer.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence, Tuple, Union

import cv2
import numpy as np
import trimesh
from scipy.ndimage import gaussian_filter
from skimage.measure import marching_cubes

MESH_FORMATS = (".ply", ".stl", ".obj", ".glb")
_EPS = 1e-3  # how far the clamped field stays from the iso-level at a grid point
_PAD = 2  # empty voxels around the grid
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
"""The glTF convention: (x, y, z) world, z up -> (x, z, -y), y up."""


def smoothed_field(occupancy: np.ndarray, sigma: float) -> np.ndarray:
    """f of the module docstring on the grid padded by two empty voxels (float32)."""
    padded = np.pad(occupancy.astype(np.float32), _PAD)
    if sigma <= 0.0:
        return padded
    field = gaussian_filter(padded, sigma, mode="constant")
    inside = padded > 0.5
    return np.where(inside, np.maximum(field, 0.5 + _EPS), np.minimum(field, 0.5 - _EPS)).astype(np.float32)


def occupancy_to_mesh(occupancy: np.ndarray, origin: np.ndarray, pitch: float, smoothing: float = 1.0) -> trimesh.Trimesh:
    """Closed triangle mesh of the occupancy (bool X x Y x Z) in world units; ``smoothing`` is sigma in
    voxels (0: the binary field, vertices at edge midpoints)."""
    if occupancy.ndim != 3:
        raise ValueError(f"occupancy: expected a 3-D grid, got shape {occupancy.shape}")
    if not (np.isfinite(smoothing) and smoothing >= 0.0):
        raise ValueError(f"smoothing: expected a sigma >= 0 in voxels, got {smoothing}")
    if not occupancy.any():
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
    verts, faces, _, _ = marching_cubes(smoothed_field(occupancy, smoothing), level=0.5, method="lorensen")
    verts = np.asarray(origin, dtype=np.float64) + pitch * (verts.astype(np.float64) - _PAD)
    # skimage orients faces towards increasing values (inwards here): flip them outwards.
    return trimesh.Trimesh(vertices=verts, faces=faces[:, ::-1], process=True)


ColourView = Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(BGR image HxWx3 uint8, silhouette HxW, K 3x3 of the undistorted image, T_WC 4x4 optical)."""
_GREY = (160, 160, 160, 255)


def colour_vertices(mesh: trimesh.Trimesh, views: Sequence[ColourView]) -> trimesh.Trimesh:
    """``mesh`` with RGBA vertex colours sampled from the best-facing view (module docstring)."""
    n_vertices = len(mesh.vertices)
    if not n_vertices:
        return mesh  # an empty model (all carved away) has nothing to colour; empty colours break trimesh's PLY export
    colours = np.tile(np.array(_GREY, dtype=np.uint8), (n_vertices, 1))
    if not views:
        mesh.visual.vertex_colors = colours
        return mesh
    best = np.zeros(n_vertices)
    normals = mesh.vertex_normals
    points = np.column_stack([mesh.vertices, np.ones(n_vertices)])
    for image, silhouette, K, T_WC in views:
        to_camera = T_WC[:3, 3] - mesh.vertices
        facing = np.einsum("ij,ij->i", normals, to_camera) / np.maximum(np.linalg.norm(to_camera, axis=1), 1e-12)
        a, b, w = K @ (np.linalg.inv(T_WC)[:3] @ points.T)
        front = w > 1e-6
        u = np.floor(np.where(front, a / np.where(front, w, 1.0), -1.0) + 0.5).astype(np.int64)
        v = np.floor(np.where(front, b / np.where(front, w, 1.0), -1.0) + 0.5).astype(np.int64)
        height, width = silhouette.shape
        usable = front & (u >= 0) & (u < width) & (v >= 0) & (v < height) & (facing > best)
        grown = cv2.dilate((np.asarray(silhouette) > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
        usable[usable] = grown[v[usable], u[usable]] > 0
        colours[usable, :3] = image[v[usable], u[usable], ::-1]  # BGR -> RGB
        best[usable] = facing[usable]
    mesh.visual.vertex_colors = colours
    return mesh


def save_mesh(mesh: trimesh.Trimesh, path: Union[str, Path]) -> Path:
    """Write ``mesh`` (world frame, z up) as PLY, STL or OBJ (z up) or GLB (y up), chosen by the suffix."""
    path = Path(path)
    if path.suffix.lower() not in MESH_FORMATS:
        raise ValueError(f"mesh path {path}: unsupported suffix {path.suffix!r}; expected one of {MESH_FORMATS}")
    if path.suffix.lower() == ".glb":
        mesh = mesh.copy()
        mesh.apply_transform(Z_UP_TO_Y_UP)
    mesh.export(path)
    return path
