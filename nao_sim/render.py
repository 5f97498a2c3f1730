"""Camera renderer of the simulated room: a pinhole camera, numpy/OpenCV only.

Background, per pixel by ray casting (rays precomputed once, distortion removed)::

    d_W = R_WC [x_n, y_n, 1]^T,   floor:  t_f = -c_z / d_z  (d_z < 0),
    walls:  t_x = (sign(d_x) h - c_x) / d_x,  t_y = (sign(d_y) h - c_y) / d_y,  t_w = min(t_x, t_y),

a pixel shows the floor when t_f < t_w, else the wall (the ceiling above ``wall_height``); the hit
point c + t d indexes a periodic texture (1 m floor tiles, painted walls with a skirting board), in
the room's ``floor_color`` and ``wall_color``. Shading is Lambert's law under the room's ``light``
(``Light``): k = ambient + (1 - ambient) max(0, n . l).

Foreground, in painter's order (farthest first, by the distance from the camera to each item's
centre), each polygon projected with ``cv2.projectPoints`` and filled with sub-pixel precision:

* boxes (object parts): the silhouette is the convex hull of the projected corners, after clipping
  the solid at the near plane z_C = NEAR (the hull of the vertices in front plus the near-plane
  crossings of every segment joining a vertex in front to one behind); flat shading: each face
  facing the camera coloured by Lambert's law;
* vertical cylinders: the same clipped hull of their two end circles, each pixel Lambert-shaded by
  the side's normal where its ray meets the side, so the light varies across the side as on a
  real can; the top cap over it in its own shade;
* triangle meshes (parts of shape ``mesh``, need not be convex): every triangle facing the camera,
  Lambert-shaded, farthest first (by its centroid's distance), filled on one shared supersampled
  buffer, so the silhouette is the exact union of the projected triangles; triangles reaching
  behind the near plane are dropped (the object is never that close to the camera);
* ArUco markers: a white board standing on the floor (the quiet zone) and the marker image of
  ``cv2.aruco.generateImageMarker`` mapped onto the projected corners by ``cv2.warpPerspective``;
* colour landmarks: balls on posts, ray-cast on a sub-pixel grid (area-weighted anti-aliasing, so the
  outline is the exact ellipse a sphere projects to); each sub-pixel whose ray meets the sphere
  |c + t d - s| = r at t = -d.(c - s) - sqrt((d.(c - s))^2 - |c - s|^2 + r^2) (unit d) takes the
  Lambert shade of the normal n = (c + t d - s) / r plus a Blinn-Phong highlight of white,
  ``BALL_GLOSS`` max(0, n . h)^``BALL_SHININESS``, h the unit half-vector of l and -d;
* the object's finish (``Material``: its scenario's ``finish``, gloss and shininess) adds the same
  highlight, 255 gloss max(0, n . h)^shininess, to every pixel of a cylinder's side and to each face
  of a box or a mesh (flat: n the face's normal, d the ray to its centre); no finish: matte.

Motion blur: the shutter is open from the camera orientation R_0 (``R_open``) to R_1 (the pose
drawn). The camera's translation over an exposure (a few mm) is neglected; its rotation maps the
image drawn at R_1 to the one at R_s = R_1 exp(s [w]_x), w = log(R_1^T R_0), by the homography

    I_s(u) = I_1(H_s u),   H_s = K R_1^T R_s K^-1,   s in [0, 1],

and the frame is the mean of I_s over n = ceil(max pixel displacement) + 1 evenly spaced s (at most
``MOTION_SAMPLES``): a box blur along the image motion, as a rotating camera integrates light.

Lens distortion: with a non-zero model (k1, k2, p1, p2, k3), the scene and its motion blur are drawn
by an ideal pinhole with the same focal lengths on a canvas that holds the whole distorted field
(``Canvas``), then resampled (bicubic) to the distorted image: pixel u_d shows the canvas at

    u_p = K' undistort(u_d),   K' = K with the principal point moved by the canvas's origin,

undistort OpenCV's model inverted to convergence. So straight edges bend as the lens bends them, and
every item stays exact on the canvas (polygon edges are straight only in a pinhole image). The
resampling blurs a little, more than a lens would (a sensor samples the optical image once):
marker corners found 0.13 px from their projection at the median without a lens, 0.19 / 0.16 px
through k1 = +-0.12 bicubic, 0.24 / 0.20 px bilinear (Lanczos: 0.17 / 0.14 px at six times the cost).

Finally the sensor: a Gaussian optical blur of ``blur_sigma`` px at VGA (scaled to the resolution),
the scene's ``exposure`` times a per-frame gain jitter, the camera's tone curve (a pixel of light L
in 0-255 reads 255 (L / 255)^``response_gamma``, as a camera's image processor encodes it: about
0.45 for sRGB, 1 linear; after the blur and the anti-aliasing, which mix light, not pixel values),
and Gaussian pixel noise (a seeded pool).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from nao_core.landmark_map import Landmark, LandmarkMap
from nao_core.robot_model import CameraIntrinsics, tone_curve
from nao_sim.scenarios import Room, Scenario

NEAR = 0.02  # m, near clipping plane
SHIFT = 4  # sub-pixel bits of cv2 polygon filling
SUPERSAMPLE = 8  # sub-pixels per pixel side for the area-exact anti-aliasing of polygons
TEXELS_PER_M = 256  # floor and wall textures repeat every metre
MOTION_SAMPLES = 24  # most shifted copies averaged for the motion blur
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)  # to convergence
BOARD_MARGIN = 0.25  # white quiet zone around a marker, fraction of its side
BOARD_AMBIENT = 0.85  # a matte white board facing into the room is lit from all round
POST_RADIUS = 0.01  # m
BALL_SUPERSAMPLE = 4  # sub-pixels per pixel side of a ball's outline
BALL_GLOSS, BALL_SHININESS = 0.4, 40.0  # a plastic ball's highlight (Blinn-Phong), a share of white
COLOURS_BGR = {
    "green": (60, 170, 40),
    "yellow": (30, 210, 230),
    "magenta": (200, 50, 200),
    "cyan": (210, 200, 40),
    "blue": (200, 90, 30),
}


@dataclass(frozen=True)
class Light:
    """One distant light and an ambient share (the room's ``light`` and ``ambient``), by Lambert's law."""

    direction: np.ndarray  # unit, towards the light, world
    ambient: float

    @classmethod
    def of(cls, room: Room) -> "Light":
        direction = np.asarray(room.light, dtype=float)
        return cls(direction / np.linalg.norm(direction), room.ambient)

    def factor(self, normals: np.ndarray) -> np.ndarray:
        """ambient + (1 - ambient) max(0, n . l) of unit normals (..., 3), or of horizontal ones (..., 2)."""
        return self.ambient + (1.0 - self.ambient) * np.maximum(0.0, normals @ self.direction[: normals.shape[-1]])

    def highlight(self, normals: np.ndarray, rays: np.ndarray, material: "Material") -> np.ndarray:
        """Blinn-Phong: gloss max(0, n . h)^shininess, h the unit half-vector of l and -d, of unit
        normals and unit ray directions d (from the camera), both (..., 3); the share of white added."""
        halfway = _unit(self.direction - rays)
        return material.gloss * np.maximum(0.0, np.sum(normals * halfway, axis=-1)) ** material.shininess

    def shade(self, color: Sequence[int], normal: np.ndarray) -> Tuple[int, int, int]:
        """The colour times its Lambert factor."""
        k = float(self.factor(np.asarray(normal, dtype=float)))
        return tuple(int(min(255, round(c * k))) for c in color)  # type: ignore[return-value]


@dataclass(frozen=True)
class Material:
    """A surface's highlight (``Light.highlight``): a share ``gloss`` of white, ``shininess`` its exponent."""

    gloss: float
    shininess: float


MATTE = Material(0.0, 1.0)
BALL = Material(BALL_GLOSS, BALL_SHININESS)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _whitened(color: Tuple[int, ...], white: float) -> Tuple[int, ...]:
    """A flat colour plus a share ``white`` of white (a highlight), clipped at 255."""
    return tuple(int(min(255, round(c + 255.0 * white))) for c in color)


def _pixel_box(uv: np.ndarray, shape: Tuple[int, ...], pad: int) -> Optional[Tuple[int, int, int, int]]:
    """(x0, y0, x1, y1): the pixels (end exclusive) that cover the points ``uv`` grown by ``pad``
    pixels a side, clipped to the image; None when nothing of it is inside."""
    h, w = shape[:2]
    x0, y0 = (max(int(np.floor(v)) - pad, 0) for v in uv.min(axis=0))
    x1, y1 = min(int(np.ceil(uv[:, 0].max())) + 1 + pad, w), min(int(np.ceil(uv[:, 1].max())) + 1 + pad, h)
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1)


def _blend(roi: np.ndarray, alpha: np.ndarray, covered: np.ndarray) -> None:
    """Over-composites a supersampled layer onto ``roi`` in place: roi (1 - alpha) + covered, with
    alpha its coverage per pixel and covered its colour times that coverage (premultiplied)."""
    roi[...] = np.clip(np.rint(roi * (1.0 - alpha) + covered), 0, 255)


class _View:
    """One camera pose: world-to-camera transform and projection."""

    def __init__(self, T_WC: np.ndarray, intrinsics: CameraIntrinsics, rays: Tuple[np.ndarray, np.ndarray]):
        self.R_CW = T_WC[:3, :3].T
        self.t_CW = -self.R_CW @ T_WC[:3, 3]
        self.centre = T_WC[:3, 3]
        self.K = intrinsics.K  # a pinhole's (the canvas's: no distortion)
        self.ray_x, self.ray_y = rays  # H x W: each pixel's ray (x, y, 1) in the optical frame

    def to_camera(self, points_W: np.ndarray) -> np.ndarray:
        return points_W @ self.R_CW.T + self.t_CW

    def project(self, points_C: np.ndarray) -> np.ndarray:
        uv, _ = cv2.projectPoints(points_C.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, None)
        return uv.reshape(-1, 2)


def _fixed(uv: np.ndarray) -> np.ndarray:
    return np.round(uv * (1 << SHIFT)).astype(np.int32)


Paint = Union[Tuple[int, ...], Callable[[int, int, int, int], np.ndarray]]  # a colour, or one per pixel of a ROI


def fill_convex_polygon(image: np.ndarray, uv: np.ndarray, color: Paint) -> None:
    """Fill a convex polygon with area-exact anti-aliasing: each pixel takes the colour in proportion to
    the part of its area inside the polygon (rasterized on SUPERSAMPLE x SUPERSAMPLE sub-pixels, then
    averaged). cv2's LINE_AA would paint about 0.7 px outside every edge, i.e. draw each silhouette
    ~1.4 px too wide. Pixel j covers [j - 1/2, j + 1/2]; sub-pixel J of the ROI has its centre at
    u = x0 - 1/2 + (J + 1/2) / SUPERSAMPLE. ``color``: one colour, or a function of the ROI
    (x0, y0, x1, y1) giving each of its pixels' colour (rows x columns x 3)."""
    h, w = image.shape[:2]
    x0, y0 = (max(int(np.floor(v)), 0) for v in uv.min(axis=0))
    x1, y1 = min(int(np.ceil(uv[:, 0].max())) + 1, w), min(int(np.ceil(uv[:, 1].max())) + 1, h)
    if x1 <= x0 or y1 <= y0:
        return
    cover = np.zeros(((y1 - y0) * SUPERSAMPLE, (x1 - x0) * SUPERSAMPLE), np.uint8)
    sub = (uv - np.float32([x0, y0]) + 0.5) * SUPERSAMPLE - 0.5
    cv2.fillConvexPoly(cover, _fixed(_inset(sub, 0.5)), 255, lineType=cv2.LINE_8, shift=SHIFT)
    alpha = cv2.resize(cover, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    roi = image[y0:y1, x0:x1]
    if roi.ndim == 3:
        alpha = alpha[..., None]
    paint = color(x0, y0, x1, y1) if callable(color) else np.float32(color[: roi.shape[-1] if roi.ndim == 3 else 1])
    roi[...] = np.rint(roi * (1.0 - alpha) + paint * alpha)


def _inset(polygon: np.ndarray, d: float) -> np.ndarray:
    """A convex polygon with every edge moved ``d`` inwards (the intersections of the moved edge lines).

    cv2.fillConvexPoly fills the pixels from round(x_left) to round(x_right) inclusive, half a pixel
    beyond the edges on average: on the sub-pixel grid, 1/16 px outside every edge, which drew a
    16 px marker 1 % too wide (docs/perception.md). Insetting by half a sub-pixel makes the filled
    sub-pixels those whose centre is inside. A polygon too small or too thin to inset is returned as is."""
    p = np.asarray(polygon, dtype=np.float64)
    if len(p) < 3:
        return polygon
    edges = np.roll(p, -1, axis=0) - p
    lengths = np.linalg.norm(edges, axis=1)
    if lengths.min() < 4.0 * d:
        return polygon
    orientation = np.sign(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
    if orientation == 0:
        return polygon
    inward = orientation * np.stack([-edges[:, 1], edges[:, 0]], axis=1) / lengths[:, None]
    offsets = np.sum(inward * p, axis=1) + d  # edge i: inward_i . x = offsets_i
    prev_n, prev_o = np.roll(inward, 1, axis=0), np.roll(offsets, 1)
    det = prev_n[:, 0] * inward[:, 1] - prev_n[:, 1] * inward[:, 0]
    if np.abs(det).min() < 1e-6:
        return polygon
    x = (prev_o * inward[:, 1] - prev_n[:, 1] * offsets) / det
    y = (prev_n[:, 0] * offsets - prev_o * inward[:, 0]) / det
    return np.stack([x, y], axis=1).astype(np.float32)


def _clip_near(points_C: np.ndarray) -> np.ndarray:
    """Vertices of the convex hull of ``points_C`` cut by the near plane (may be empty)."""
    front = points_C[:, 2] >= NEAR
    if front.all() or not front.any():
        return points_C[front]
    a, b = points_C[front], points_C[~front]
    s = (NEAR - a[:, None, 2]) / (b[None, :, 2] - a[:, None, 2])
    cuts = a[:, None, :] + s[..., None] * (b[None, :, :] - a[:, None, :])
    return np.vstack([a, cuts.reshape(-1, 3)])


def _fill_hull(image: np.ndarray, view: _View, points_W: np.ndarray, color: Paint) -> None:
    pts = _clip_near(view.to_camera(points_W))
    if len(pts) >= 3:
        uv = view.project(pts).astype(np.float32)
        fill_convex_polygon(image, cv2.convexHull(uv).reshape(-1, 2), color)


class _Solid:
    """A convex part with flat-shaded faces: a box (six faces)."""

    def __init__(self, points_W: np.ndarray, color: Tuple[int, int, int], light: Light, material: Material = MATTE):
        self.points_W = points_W  # the 4 bottom corners, then the 4 top ones
        self.centre = points_W.mean(axis=0)
        self.radius = float(np.linalg.norm(points_W - self.centre, axis=1).max())
        self.light, self.material = light, material
        bottom, top = points_W[:4], points_W[4:]
        self.hull_color = light.shade(color, np.zeros(3))
        self.faces = []
        for face in [top, bottom] + [np.array([bottom[i], bottom[(i + 1) % 4], top[(i + 1) % 4], top[i]]) for i in range(4)]:
            normal = np.cross(face[1] - face[0], face[2] - face[0])
            normal *= np.sign(np.dot(normal, face.mean(axis=0) - self.centre)) / np.linalg.norm(normal)
            self.faces.append((face, normal, light.shade(color, normal)))

    def draw(self, image: np.ndarray, view: _View) -> None:
        """The hull first (no seams between faces), then every face turned towards the camera, its
        highlight taken at the ray to its centre (flat shading)."""
        _fill_hull(image, view, self.points_W, self.hull_color)
        for face, normal, color in self.faces:
            if np.dot(normal, view.centre - face[0]) > 1e-9:
                white = float(self.light.highlight(normal, _unit(face.mean(axis=0) - view.centre), self.material))
                _fill_hull(image, view, face, _whitened(color, white))


class _MeshSolid:
    """A triangle mesh part (nao_sim/meshes.py), flat-shaded per triangle."""

    def __init__(self, vertices_W: np.ndarray, faces: np.ndarray, color: Tuple[int, int, int], light: Light,
                 material: Material = MATTE):
        self.vertices_W = vertices_W
        self.light, self.material = light, material
        self.faces = faces
        self.centre = 0.5 * (vertices_W.min(axis=0) + vertices_W.max(axis=0))
        self.radius = float(np.linalg.norm(vertices_W - self.centre, axis=1).max())
        tri = vertices_W[faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normals, axis=1)
        keep = length > 0.0  # degenerate triangles cover no pixel
        self.faces, tri, self.normals = faces[keep], tri[keep], normals[keep] / length[keep, None]
        self.centroids = tri.mean(axis=1)
        self.lambert = np.outer(light.factor(self.normals), color)

    def draw(self, image: np.ndarray, view: _View) -> None:
        facing = np.einsum("fi,fi->f", self.normals, view.centre - self.centroids) > 0.0
        points_C = view.to_camera(self.vertices_W)
        in_front = points_C[:, 2] >= NEAR
        facing &= in_front[self.faces].all(axis=1)
        if not facing.any():
            return
        uv = np.full((len(points_C), 2), np.nan)
        uv[in_front] = view.project(points_C[in_front])
        faces = self.faces[facing]
        order = np.argsort(np.linalg.norm(self.centroids[facing] - view.centre, axis=1))[::-1]
        box = _pixel_box(uv[np.unique(faces)], image.shape, 0)
        if box is None:
            return
        x0, y0, x1, y1 = box
        size = ((y1 - y0) * SUPERSAMPLE, (x1 - x0) * SUPERSAMPLE)
        paint, cover = np.zeros(size + (3,), np.uint8), np.zeros(size, np.uint8)
        sub = _fixed((uv - np.float64([x0, y0]) + 0.5) * SUPERSAMPLE - 0.5)
        white = 255.0 * self.light.highlight(self.normals[facing], _unit(self.centroids[facing] - view.centre), self.material)
        colors = np.minimum(255, np.rint(self.lambert[facing] + white[:, None])).astype(np.uint8)
        for i in order:
            polygon = sub[faces[i]]
            cv2.fillConvexPoly(paint, polygon, tuple(int(c) for c in colors[i]), lineType=cv2.LINE_8, shift=SHIFT)
            cv2.fillConvexPoly(cover, polygon, 255, lineType=cv2.LINE_8, shift=SHIFT)
        area = (x1 - x0, y1 - y0)
        alpha = cv2.resize(cover, area, interpolation=cv2.INTER_AREA).astype(np.float32)[..., None] / 255.0
        # the mean colour over covered sub-pixels: paint is black where uncovered
        colour = cv2.resize(paint, area, interpolation=cv2.INTER_AREA).astype(np.float32) / np.maximum(alpha, 1e-6)
        _blend(image[y0:y1, x0:x1], alpha, colour * alpha)


class _Cylinder:
    """A vertical cylinder: the hull of its two end circles (clipped at the near plane), each pixel
    in the Lambert shade of the side's normal where its ray meets the side (at the ray's closest
    approach to the axis for the rim's anti-aliased pixels whose ray misses it), so the light varies
    across the side as on a real can; the top cap over it, in its own shade, when seen from above."""

    def __init__(self, points_W: np.ndarray, color: Tuple[int, int, int], light: Light, material: Material = MATTE):
        self.points_W = points_W  # bottom ring, then top ring
        self.light, self.material = light, material
        self.centre = points_W.mean(axis=0)
        self.radius = float(np.linalg.norm(points_W - self.centre, axis=1).max())
        self.top = points_W[len(points_W) // 2:]
        self.axis = self.top[:, :2].mean(axis=0)
        self.r = float(np.linalg.norm(self.top[0, :2] - self.axis))
        self.color = np.float32(color)
        self.top_color = light.shade(color, np.array([0.0, 0.0, 1.0]))

    def draw(self, image: np.ndarray, view: _View) -> None:
        _fill_hull(image, view, self.points_W, lambda *roi: self._side(view, *roi))
        if view.centre[2] > self.top[0, 2]:
            up, centre = np.array([0.0, 0.0, 1.0]), self.top.mean(axis=0)
            white = float(self.light.highlight(up, _unit(centre - view.centre), self.material))
            _fill_hull(image, view, self.top, _whitened(self.top_color, white))

    def _side(self, view: _View, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """The shaded side's colour at each pixel of the ROI (rows x columns x 3)."""
        x, y = view.ray_x[y0:y1, x0:x1], view.ray_y[y0:y1, x0:x1]
        rays_C = np.stack([x, y, np.ones_like(x)], axis=-1)
        rays_W = rays_C.astype(np.float64) @ view.R_CW  # world directions (R_WC = R_CW^T)
        d = rays_W[..., :2]  # their horizontal part
        c = view.centre[:2] - self.axis
        a, b = np.maximum(np.sum(d * d, axis=-1), 1e-12), d @ c
        disc = b * b - a * (c @ c - self.r**2)
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a  # the nearer crossing, or the closest approach
        p = c + t[..., None] * d
        n = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
        k = self.light.factor(n)
        paint = self.color * k[..., None].astype(np.float32)
        if self.material.gloss > 0.0:
            normals = np.concatenate([n, np.zeros(n.shape[:-1] + (1,))], axis=-1)
            paint = paint + (255.0 * self.light.highlight(normals, _unit(rays_W), self.material))[..., None].astype(np.float32)
        return np.minimum(255.0, paint)


def _post(x: float, y: float, top: float) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * math.pi, 12, endpoint=False)
    ring = np.column_stack([x + POST_RADIUS * np.cos(a), y + POST_RADIUS * np.sin(a)])
    return np.vstack([np.column_stack([ring, np.full(12, z)]) for z in (0.0, top)])


@dataclass
class _MarkerBoard:
    """An ArUco marker on a white board standing on the floor, facing along the landmark's yaw."""

    landmark: Landmark
    corners_W: np.ndarray  # 4 x 3, cv2.aruco order
    board_W: np.ndarray  # 4 x 3
    texture: np.ndarray  # marker image, black square = whole image
    board_color: Tuple[int, int, int]  # the white board in its light

    @classmethod
    def build(cls, lm: Landmark, light: Light, texels: int = 120) -> "_MarkerBoard":
        corners = lm.aruco_corners()
        m = BOARD_MARGIN * lm.size
        right = (corners[1] - corners[0]) / lm.size
        top_left, top_right = corners[0] + m * (np.array([0, 0, 1.0]) - right), corners[1] + m * (np.array([0, 0, 1.0]) + right)
        floor = np.array([1.0, 1.0, 0.0])
        board = np.array([top_left, top_right, top_right * floor, top_left * floor])
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, lm.dictionary))
        texture = cv2.aruco.generateImageMarker(dictionary, int(lm.id), texels, borderBits=1)
        return cls(lm, corners, board, cv2.cvtColor(texture, cv2.COLOR_GRAY2BGR),
                   replace(light, ambient=max(light.ambient, BOARD_AMBIENT)).shade((240, 240, 240), lm.normal))

    @property
    def centre(self) -> np.ndarray:
        return self.board_W.mean(axis=0)

    @property
    def radius(self) -> float:
        return float(np.linalg.norm(self.board_W - self.centre, axis=1).max())

    def draw(self, image: np.ndarray, view: _View) -> None:
        front = np.dot(self.landmark.normal, view.centre - self.centre) > 0
        if not front:
            _fill_hull(image, view, self.board_W, (150, 150, 150))
            return
        _fill_hull(image, view, self.board_W, self.board_color)
        corners_C = view.to_camera(self.corners_W)
        if (corners_C[:, 2] < NEAR).any() or (view.to_camera(self.board_W)[:, 2] < NEAR).all():
            return
        uv = view.project(corners_C).astype(np.float32)
        x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 2
        h, w = image.shape[:2]
        x0c, y0c, x1c, y1c = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x0c >= x1c or y0c >= y1c:
            return
        s = self.texture.shape[0]
        src = np.float32([[-0.5, -0.5], [s - 0.5, -0.5], [s - 0.5, s - 0.5], [-0.5, s - 0.5]])
        H = cv2.getPerspectiveTransform(src, uv - np.float32([x0c, y0c]))
        size = (x1c - x0c, y1c - y0c)
        warped = cv2.warpPerspective(self.texture, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        mask = np.zeros((size[1], size[0]), np.uint8)
        fill_convex_polygon(mask, uv - np.float32([x0c, y0c]), (255,))
        roi = image[y0c:y1c, x0c:x1c]
        alpha = mask[..., None].astype(np.float32) * (1.0 / 255.0)
        roi[:] = (warped * alpha + roi * (1.0 - alpha)).astype(np.uint8)


class _ColourBall:
    """A coloured landmark: a ball on a thin grey post, ray-cast per sub-pixel (module docstring)."""

    def __init__(self, landmark: Landmark, color: Tuple[int, int, int], light: Light):
        self.landmark = landmark
        self.color = np.float32(color)
        self.light = light
        self.centre = np.asarray(landmark.position, dtype=float)
        self.r = 0.5 * landmark.diameter
        self.radius = float(self.centre[2]) + landmark.diameter  # bounds the ball and the post
        self.post_W = _post(*landmark.position)
        self.cube_W = self.centre + self.r * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])

    def draw(self, image: np.ndarray, view: _View) -> None:
        _fill_hull(image, view, self.post_W, (110, 110, 110))
        cube_C = view.to_camera(self.cube_W)
        if cube_C[:, 2].min() < NEAR:
            return
        box = _pixel_box(view.project(cube_C), image.shape, 1)  # the cube's projection holds the ball's
        if box is None:
            return
        x0, y0, x1, y1 = box
        S = BALL_SUPERSAMPLE
        size = ((x1 - x0) * S, (y1 - y0) * S)  # sub-pixel J's centre: x0 - 1/2 + (J + 1/2) / S, as cv2.resize maps
        x = cv2.resize(view.ray_x[y0:y1, x0:x1], size, interpolation=cv2.INTER_LINEAR).astype(np.float64)
        y = cv2.resize(view.ray_y[y0:y1, x0:x1], size, interpolation=cv2.INTER_LINEAR).astype(np.float64)
        d = np.stack([x, y, np.ones_like(x)], axis=-1) @ view.R_CW  # world directions (R_WC = R_CW^T)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        c = view.centre - self.centre
        b = d @ c
        disc = b * b - (c @ c - self.r**2)
        hit = disc >= 0.0
        if not hit.any():
            return
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        n = (c + t[..., None] * d) / self.r
        paint = self.color * self.light.factor(n)[..., None] + (255.0 * self.light.highlight(n, d, BALL))[..., None]
        area = (x1 - x0, y1 - y0)
        alpha = cv2.resize(hit.astype(np.float32), area, interpolation=cv2.INTER_AREA)[..., None]
        covered = cv2.resize((np.minimum(paint, 255.0) * hit[..., None]).astype(np.float32), area, interpolation=cv2.INTER_AREA)
        _blend(image[y0:y1, x0:x1], alpha, covered)


@dataclass(frozen=True)
class Canvas:
    """The pinhole image a distorted camera's frame is resampled from (module docstring, "Lens
    distortion"): its intrinsics and, per pixel of the distorted frame, where it lies on the canvas."""

    intrinsics: CameraIntrinsics  # no distortion; the frame's focal lengths, the canvas's size and principal point
    map_x: Optional[np.ndarray]  # H x W float32 canvas column of each frame pixel; None: no distortion, the canvas is the frame
    map_y: Optional[np.ndarray]

    @classmethod
    def of(cls, intr: CameraIntrinsics) -> "Canvas":
        if not np.any(intr.dist):
            return cls(intr, None, None)
        v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
        pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        n = cv2.undistortPoints(pix, intr.K, np.asarray(intr.dist, dtype=float), R=None, P=None, criteria=UNDISTORT_CRITERIA)
        pinhole = n.reshape(-1, 2) * (intr.fx, intr.fy) + (intr.cx, intr.cy)
        if not np.all(np.isfinite(pinhole)):
            raise ValueError(f"camera distortion {list(intr.dist)}: the lens model does not invert over the image")
        x0, y0 = np.floor(pinhole.min(axis=0)).astype(int) - 2  # margins for the bicubic lookup's 4 x 4 pixels
        x1, y1 = np.ceil(pinhole.max(axis=0)).astype(int) + 3
        canvas = replace(intr, width=int(x1 - x0), height=int(y1 - y0), cx=float(intr.cx - x0), cy=float(intr.cy - y0),
                         dist=(0.0, 0.0, 0.0, 0.0, 0.0))
        maps = (pinhole - (x0, y0)).astype(np.float32).reshape(intr.height, intr.width, 2)
        return cls(canvas, maps[..., 0].copy(), maps[..., 1].copy())

    def frame(self, image: np.ndarray) -> np.ndarray:
        """The distorted frame of a canvas image."""
        if self.map_x is None:
            return image
        return cv2.remap(image, self.map_x, self.map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def _frustum_normals(intr: CameraIntrinsics) -> np.ndarray:
    """Inward unit normals (optical frame) of the planes z = 0 and of the image borders.

    A point p is in view when n . p >= 0 for all five (of a pinhole: the renderer's canvas).
    """
    n = np.array([
        [0.0, 0.0, 1.0],
        [intr.fx, 0.0, intr.cx],
        [-intr.fx, 0.0, intr.width - intr.cx],
        [0.0, intr.fy, intr.cy],
        [0.0, -intr.fy, intr.height - intr.cy],
    ])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _textures(room: Room) -> Tuple[np.ndarray, int]:
    """A texture atlas: floor (1 m square, 0.5 m carpet tiles) above the wall (1 m wide, floor to top).

    Rows [0, S) are the floor, rows [S, S + wall rows) the wall from z = 0 upwards; the last row is
    the ceiling. Returns the atlas image and the number of wall rows.
    """
    S = TEXELS_PER_M
    rng = np.random.default_rng(12345)  # a fixed texture, not a per-run draw
    yy, xx = np.mgrid[0:S, 0:S]
    tile = ((xx // (S // 2)) + (yy // (S // 2))) % 2
    floor = np.empty((S, S, 3), np.float32)
    floor[:] = np.array(room.floor_color)
    floor += (tile * 14.0)[..., None] + rng.normal(0.0, 6.0, (S, S, 1))
    grout = (xx % (S // 2) < 2) | (yy % (S // 2) < 2)
    floor[grout] = (80.0, 80.0, 85.0)
    wall_rows = int(math.ceil(room.wall_height * S)) + 1
    wall = np.empty((wall_rows, S, 3), np.float32)
    wall[:] = np.array(room.wall_color)
    wall += rng.normal(0.0, 4.0, (1, S, 1)) + rng.normal(0.0, 2.0, (wall_rows, S, 1))
    wall[: int(0.08 * S)] = (70.0, 85.0, 100.0)  # skirting board
    wall[-1] = (235.0, 235.0, 235.0)  # ceiling
    return np.clip(np.vstack([floor, wall]), 0, 255).astype(np.uint8), wall_rows


class Renderer:
    """Renders BGR images of the room, landmarks and object from a camera pose T_WC (optical)."""

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        room: Room,
        landmarks: LandmarkMap,
        scenario: Scenario,
        pixel_sigma: float,
        gain_sigma: float,
        seed: int,
        blur_sigma: float = 0.0,
        exposure: float = 1.0,
        response_gamma: float = 1.0,
    ):
        """``blur_sigma``: optical blur, px at 640 px wide; ``exposure``: mean brightness factor;
        ``response_gamma``: the tone curve (module docstring)."""
        self.intrinsics = intrinsics
        self.room = room
        self._canvas = Canvas.of(intrinsics)
        canvas = self._canvas.intrinsics
        v, u = np.mgrid[0 : canvas.height, 0 : canvas.width].astype(np.float32)
        self._ray_x, self._ray_y = (u - canvas.cx) / canvas.fx, (v - canvas.cy) / canvas.fy  # rays (x, y, 1), optical frame
        self._atlas, self._wall_rows = _textures(room)
        light = Light.of(room)
        material = MATTE if scenario.finish is None else Material(*scenario.finish)
        self._items: List = [
            _MeshSolid(*p.world_mesh(scenario.position, scenario.yaw), scenario.color, light, material) if p.shape == "mesh"
            else _Cylinder(p.world_points(scenario.position, scenario.yaw), scenario.color, light, material)
            if p.shape == "cylinder" else _Solid(p.world_points(scenario.position, scenario.yaw), scenario.color, light, material)
            for p in scenario.parts
        ]
        for lm in landmarks.landmarks:
            if lm.kind == "aruco":
                self._items.append(_MarkerBoard.build(lm, light))
            else:
                if lm.color not in COLOURS_BGR:
                    known = sorted(COLOURS_BGR)
                    raise ValueError(f"landmark {lm.id!r}: the simulator has no colour {lm.color!r}; known: {known}")
                self._items.append(_ColourBall(lm, COLOURS_BGR[lm.color], light))
        self._centres = np.array([item.centre for item in self._items])
        self._frustum = _frustum_normals(canvas)
        self._radii = np.array([item.radius for item in self._items])
        w, h = intrinsics.width, intrinsics.height
        rng = np.random.default_rng(seed)
        self._noise = [rng.normal(0.0, pixel_sigma, (h + 16, w + 16, 3)).astype(np.int16) for _ in range(4)]
        self._pixel_sigma = pixel_sigma
        self._gain_sigma = gain_sigma
        self._seed = seed
        self._blur = blur_sigma * w / 640.0
        self._exposure = exposure
        self._tone = None if response_gamma == 1.0 else tone_curve(response_gamma)

    def background(self, T_WC: np.ndarray) -> np.ndarray:
        """Floor, walls and ceiling seen from T_WC (H x W x 3 BGR)."""
        S, hs = TEXELS_PER_M, np.float32(self.room.half_size)
        c = T_WC[:3, 3].astype(np.float32)
        R = T_WC[:3, :3].astype(np.float32)
        d = np.stack([(R[i, 0] * self._ray_x + R[i, 1] * self._ray_y + R[i, 2]).ravel() for i in range(3)])  # no BLAS threads
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # rays parallel to a wall or the floor
            t_wall = np.minimum((np.copysign(hs, d[0]) - c[0]) / d[0], (np.copysign(hs, d[1]) - c[1]) / d[1])
            t_floor = -c[2] / d[2]
        floor = (t_floor > 0) & (t_floor < t_wall)
        t = np.where(floor, t_floor, t_wall)
        hit = (t * d + c[:, None]) * np.float32(S)  # texels
        # on a wall one of x, y is +-half_size (a whole number of texture periods): x + y runs along it
        u = np.where(floor, hit[0], hit[0] + hit[1])
        v = np.where(floor, hit[1] - np.floor(hit[1] * (1.0 / S)) * S, np.clip(hit[2], 0, self._wall_rows - 1) + S)
        h, w = self._ray_x.shape
        return cv2.remap(self._atlas, u.reshape(h, w), v.reshape(h, w), cv2.INTER_NEAREST, borderMode=cv2.BORDER_WRAP)

    def render(self, T_WC: np.ndarray, frame_index: int, R_open: Optional[np.ndarray] = None) -> np.ndarray:
        """The camera image at T_WC; ``frame_index`` seeds this frame's noise (deterministic);
        ``R_open``: the camera's orientation (R_WC) when the shutter opened (motion blur), None: a still camera."""
        T_WC = np.asarray(T_WC, dtype=float)
        image = self.background(T_WC)
        view = _View(T_WC, self._canvas.intrinsics, (self._ray_x, self._ray_y))
        centres_C = view.to_camera(self._centres)
        in_view = (centres_C @ self._frustum.T > -self._radii[:, None]).all(axis=1)  # bounding spheres
        depth = np.linalg.norm(centres_C, axis=1)
        for i in np.argsort(depth)[::-1]:
            if in_view[i]:
                self._items[i].draw(image, view)
        if R_open is not None:
            image = self._motion_blur(image, T_WC[:3, :3], np.asarray(R_open, dtype=float))
        return self._sensor(self._canvas.frame(image), frame_index)

    def _motion_blur(self, image: np.ndarray, R_1: np.ndarray, R_0: np.ndarray) -> np.ndarray:
        """The mean of the image over the shutter's rotation from R_0 to R_1 (module docstring)."""
        w = cv2.Rodrigues(R_1.T @ R_0)[0].ravel()
        K = self._canvas.intrinsics.K
        K_inv = np.linalg.inv(K)
        h, wd = image.shape[:2]
        corners = np.array([[0.0, 0.0, 1.0], [wd, 0.0, 1.0], [0.0, h, 1.0], [wd, h, 1.0], [wd / 2, h / 2, 1.0]]).T
        H_0 = K @ cv2.Rodrigues(w)[0] @ K_inv  # R_1^T R_0 = exp([w]_x)
        moved = H_0 @ corners
        displacement = float(np.max(np.linalg.norm(moved[:2] / moved[2] - corners[:2], axis=0)))
        n = min(math.ceil(displacement) + 1, MOTION_SAMPLES)
        if n < 2:
            return image
        total = np.zeros(image.shape, np.float32)
        for s in np.linspace(0.0, 1.0, n):
            H_s = K @ cv2.Rodrigues(s * w)[0] @ K_inv
            total += cv2.warpPerspective(image, H_s, (wd, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                         borderMode=cv2.BORDER_REPLICATE)
        return np.clip(total / n + 0.5, 0, 255).astype(np.uint8)

    def _sensor(self, image: np.ndarray, frame_index: int) -> np.ndarray:
        """Optical blur, exposure and gain jitter, the tone curve, pixel noise."""
        if self._blur > 0.0:
            image = cv2.GaussianBlur(image, (0, 0), self._blur)
        rng = np.random.default_rng((self._seed, frame_index))
        gain = self._exposure * (1.0 + self._gain_sigma * float(rng.standard_normal()))
        if gain != 1.0:
            image = cv2.convertScaleAbs(image, alpha=gain)
        if self._tone is not None:
            image = cv2.LUT(image, self._tone)
        if self._pixel_sigma == 0.0:
            return image
        pool = self._noise[int(rng.integers(len(self._noise)))]
        oy, ox = rng.integers(0, 16, 2)
        h, w = image.shape[:2]
        return cv2.add(image, pool[oy : oy + h, ox : ox + w], dtype=cv2.CV_8U)
