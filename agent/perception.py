"""Object silhouette and its bearing/width measurement from one top-camera frame.

Segmentation (per colour class, OpenCV HSV: H in [0, 180), S, V in [0, 255])::

    M = [h_lo <= H <= h_hi] & [S in s] & [V in v]          (h_lo > h_hi wraps: H >= h_lo or H <= h_hi)
    M <- close(open(M, disc(r_open)), disc(r_close))         (drop speckle, fill pinholes)

M is computed only in the box where every f-th pixel of every f-th row (the frame at 160 px) is
of the colour, padded by f and the morphology's reach (``color_region``).
The object is one 8-connected component of M (found by its outer contour) with area >= min_area:
the largest, or the one whose centroid is nearest a predicted pixel. Its mask (0/255) is what the carver intersects.

Sub-pixel outline (per row v, left side; the right side is its mirror). The binary mask's first
pixel u0 is only within a pixel of the edge: an anti-aliased or blurred edge has mixed pixels, and
whether they pass the colour threshold depends on the threshold, not on the geometry. The edge is
located where the pixel colours cross from the background's to the object's. With the reference
colours B = I(u0 - w, v) (background) and O = I(u0 + w, v) (object), w = ``edge_window``, each
pixel between them is unmixed into its object coverage. The object's shade at the edge is not its
shade w pixels in (a cylinder's side turns away from the light; measured on rendered frames, that
difference biased the width by up to 2 arcmin on a dark floor), so a mixed pixel is
I_i = c_i k O + (1 - c_i) B with the shade k free: by least squares over the three channels,

    [O.O  O.B] [a_i]   [O.I_i]
    [O.B  B.B] [b_i] = [B.I_i],     c_i = clip(1 - b_i, 0, 1),   i = u0 - w + 1 .. u0 + w - 1,

when O and B are more than 11.5 deg apart as colour vectors (``UNMIX_MIN_SIN2``); otherwise (one
hue, two brightnesses), or with ``edge_unmixing: projection`` (the shade fixed at O's), by the
projection c_i = clip((I_i - B) . (O - B) / |O - B|^2, 0, 1).
Since pixel i spans [i - 1/2, i + 1/2], the coverages sum to the object's length in the window:

    e_left(v) = u0 + w - 1/2 - sum_i c_i.

This is exact for area-sampled (anti-aliased) edges and, for a symmetric blur, puts the edge at
the half-way crossing; it needs no threshold tuning. Rows with too little contrast
(|O - B| < ``edge_min_contrast``), too short a run or a reference outside the image keep the
mask's outer pixel edge u0 - 1/2.

Measurement (docs/perception.md). Every row's left and right outline edge (u, v) is
back-projected (distortion removed), rotated into W with T_WC and reduced to a horizontal azimuth
a(v). For a vertical cylinder the left/right outline rows lie in the two vertical tangent planes, so

    a_l = mean{ a_left(v)  : a_left(v)  >= max_v a_left  - band },
    a_r = mean{ a_right(v) : a_right(v) <= min_v a_right + band },   band = edge_band / f_x,

averages the rows' noise (and, on the binary fallback, the +-1/2 pixel quantization along a slanted
outline, where the extreme row alone is biased outwards by about half a pixel a side), and
delta = a_l - a_r, azimuth_W = (a_l + a_r) / 2, phi = wrap(azimuth_W - psi(T_WC)).
A silhouette within ``border_margin`` of any image border is cut (``ObjectMeasurement.cut`` names
the borders) and gives no width, never a wrong one: the visible part of a box, a mug or a figure is
narrower or wider than its whole, and a sliver of a can leaving the image is as wide as the rows
that remain. Cut at the top or bottom it still gives the bearing (the tangent-plane bisector of the
visible rows); cut at a side the visible part's bisector is pulled towards the image by up to half
the width, so the bearing is reported for display but flagged unusable (``bearing_valid``).
The silhouette's top and bottom rows (``top_row``, ``bottom_row``) give its vertical extent.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Literal, Optional, Tuple

import cv2
import numpy as np

from agent.camera import CameraModel, optical_axis_heading, ray_azimuths
from nao_core.config import bounds
from nao_core.geometry import wrap_angle

MIN_IMAGE_SIDE = 16  # px: anything smaller is not a camera frame
UNMIX_MIN_SIN2 = 0.04  # sin^2 of the least angle between the object's and the background's colours (11.5 deg) for
                       # unmixing with the object's shade free; nearer (one hue, two brightnesses) the projection does
COARSE_WIDTH = 160  # px: the object's colour is first looked for on the frame reduced to this width
BORDERS = ("left", "right", "top", "bottom")


class ImageError(ValueError):
    """The input is not a usable camera image (the message says what is wrong)."""


@dataclass(frozen=True)
class ColorClass:
    """An HSV box in OpenCV units; ``hue[0] > hue[1]`` wraps through 0 (red)."""

    hue: Tuple[int, int] = field(metadata=bounds(0, 179))
    saturation: Tuple[int, int] = field(metadata=bounds(0, 255))
    value: Tuple[int, int] = field(metadata=bounds(0, 255))


@dataclass(frozen=True)
class PerceptionParams:
    """Colour classes, morphology and component choice (config/perception.yaml, section ``perception``)."""

    colors: Dict[str, ColorClass]
    object_color: str
    open_radius: int = field(metadata=bounds(0, 20))  # px, 0 = no opening
    close_radius: int = field(metadata=bounds(0, 20))  # px, 0 = no closing
    min_area: int = field(metadata=bounds(1, 10**7))  # px, smallest object silhouette
    landmark_min_area: int = field(metadata=bounds(1, 10**7))  # px, smallest colour-landmark blob
    component: Literal["largest", "nearest"]  # "nearest" needs a predicted pixel, else largest
    border_margin: int = field(metadata=bounds(0, 100))  # px from a border within which the silhouette is cut by it
    edge_band: float = field(metadata=bounds(0.0, 10.0))  # tangent-row band, in pixels' angles
    edge_window: int = field(metadata=bounds(0, 10))  # px: sub-pixel edge references this far out/in (0 = mask edge)
    edge_min_contrast: float = field(metadata=bounds(0.0, 442.0))  # BGR distance object-background for a sub-pixel edge
    edge_unmixing: Literal["free_shade", "projection"]  # the object's shade free (module docstring), or fixed

    def __post_init__(self) -> None:
        if self.object_color not in self.colors:
            raise ValueError(f"object_color {self.object_color!r} is not a colour class ({sorted(self.colors)})")


@dataclass(frozen=True)
class Silhouette:
    """One connected component of a colour class. Pixel coordinates are (u, v) = (column, row)."""

    mask: np.ndarray  # uint8 H x W, 255 on the component, 0 elsewhere
    bbox: Tuple[int, int, int, int]  # x, y, width, height
    area: int  # px
    centroid: Tuple[float, float]  # (u, v)
    left_px: Tuple[int, int]  # leftmost outline pixel (u, v) (median row among ties)
    right_px: Tuple[int, int]  # rightmost outline pixel (u, v)
    touches_left: bool  # within border_margin of the left border: cut by it
    touches_right: bool
    touches_top: bool
    touches_bottom: bool
    left_edge: np.ndarray  # N x 2 sub-pixel outline (u, v): each row's left edge
    right_edge: np.ndarray  # N x 2, each row's right edge

    @property
    def cut(self) -> Tuple[str, ...]:
        """The image borders that cut the silhouette, of "left", "right", "top", "bottom"."""
        flags = (self.touches_left, self.touches_right, self.touches_top, self.touches_bottom)
        return tuple(name for name, flag in zip(BORDERS, flags) if flag)

    @property
    def side_cut(self) -> bool:
        """Cut by the left or right border: neither the width nor the bearing is observable."""
        return self.touches_left or self.touches_right

    @property
    def width_valid(self) -> bool:
        """Not cut by any border: the whole silhouette, so its width is the object's."""
        return not self.cut

    @property
    def spans_image(self) -> bool:
        """Cut by both the left and the right border: the object's colour fills the view from side to
        side, a floor or a wall of that colour (the mission never comes that close to its object)."""
        return self.touches_left and self.touches_right


@dataclass(frozen=True)
class ObjectMeasurement:
    """Bearing and apparent width of the object in one frame (docs/perception.md, "Measurement")."""

    azimuth: float  # world azimuth of the centre, rad
    phi: float  # bearing relative to the optical-axis heading, rad (of the visible part when side-cut)
    delta: Optional[float]  # apparent width, rad; None when the silhouette is cut by any border
    a_left: float  # world azimuths of the two tangent planes, rad
    a_right: float
    cut: Tuple[str, ...]  # the image borders that cut the silhouette ("left", "right", "top", "bottom")
    top_row: int  # the silhouette's topmost and bottommost image rows v, px
    bottom_row: int

    @property
    def bearing_valid(self) -> bool:
        """False when a side border cuts the silhouette: phi is then that of the visible part only."""
        return "left" not in self.cut and "right" not in self.cut


def check_image(image: object, size: Optional[Tuple[int, int]] = None) -> np.ndarray:
    """The image as an H x W x 3 uint8 array, or ``ImageError`` saying what is wrong with it.

    ``size`` = (width, height) the frame must have (the camera's), if given.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"expected an image as a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ImageError(f"expected a uint8 image, got dtype {image.dtype}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ImageError(f"expected an H x W x 3 BGR image, got shape {image.shape}")
    h, w = image.shape[:2]
    if min(h, w) < MIN_IMAGE_SIDE:
        raise ImageError(f"image of {w} x {h} px is too small (each side >= {MIN_IMAGE_SIDE} px)")
    if size is not None and (w, h) != tuple(size):
        raise ImageError(f"image is {w} x {h} px, the camera's is {size[0]} x {size[1]}")
    return image


def color_mask(hsv: np.ndarray, color: ColorClass) -> np.ndarray:
    """Binary mask (0/255) of the pixels of an HSV image inside a colour class."""
    (h_lo, h_hi), (s_lo, s_hi), (v_lo, v_hi) = color.hue, color.saturation, color.value
    if h_lo <= h_hi:
        return cv2.inRange(hsv, (h_lo, s_lo, v_lo), (h_hi, s_hi, v_hi))
    return cv2.inRange(hsv, (h_lo, s_lo, v_lo), (179, s_hi, v_hi)) | cv2.inRange(hsv, (0, s_lo, v_lo), (h_hi, s_hi, v_hi))


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def clean_mask(mask: np.ndarray, params: PerceptionParams) -> np.ndarray:
    """Morphological opening then closing with discs of the configured radii.

    Only the bounding box of the mask's pixels, padded by the structuring elements' reach, is
    processed: outside it the result is zero anyway, and a small object in a VGA frame costs a
    fraction of the full-frame operations.
    """
    radius = max(params.open_radius, params.close_radius)
    if radius == 0:
        return mask
    x, y, w, h = cv2.boundingRect(mask)
    if w == 0:
        return mask
    pad = 2 * radius + 1
    x0, y0 = max(x - pad, 0), max(y - pad, 0)
    x1, y1 = min(x + w + pad, mask.shape[1]), min(y + h + pad, mask.shape[0])
    roi = mask[y0:y1, x0:x1]
    if params.open_radius > 0:
        roi = cv2.morphologyEx(roi, cv2.MORPH_OPEN, _disc(params.open_radius))
    if params.close_radius > 0:
        roi = cv2.morphologyEx(roi, cv2.MORPH_CLOSE, _disc(params.close_radius))
    out = np.zeros_like(mask)
    out[y0:y1, x0:x1] = roi
    return out


def blobs(mask: np.ndarray, min_area: int) -> Tuple[list, np.ndarray, np.ndarray]:
    """Outer contours of a binary mask whose pixel area (approximated by the contour's polygon area
    plus half its perimeter, the pixels its outline passes through) is >= min_area.

    Returns (contours, areas, centroids (N x 2, (u, v))). Contours are far cheaper than labelling
    the whole image with statistics; the chosen blob is labelled exactly in its bounding box.
    """
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    kept, areas, centroids = [], [], []
    for contour in contours:
        area = cv2.contourArea(contour) + 0.5 * cv2.arcLength(contour, True) + 1.0
        if area < min_area:
            continue
        m = cv2.moments(contour)
        centre = (m["m10"] / m["m00"], m["m01"] / m["m00"]) if m["m00"] > 0 else tuple(contour.reshape(-1, 2).mean(axis=0))
        kept.append(contour)
        areas.append(area)
        centroids.append(centre)
    return kept, np.asarray(areas, dtype=float), np.asarray(centroids, dtype=float).reshape(-1, 2)


def color_region(image_bgr: np.ndarray, color: ColorClass, margin: int) -> Optional[Tuple[int, int, int, int]]:
    """Bounds (x0, y0, x1, y1) of the part of a frame that holds a colour class's pixels, or None.

    The colour is looked for on every f-th pixel of every f-th row, f the integer factor that
    brings the frame to at most ``COARSE_WIDTH`` wide (sampling: a fifth of the cost of block
    means); the box of the hits, mapped back and padded by f + ``margin`` px, is where the
    full-resolution mask is computed. A blob with no f x f square of the colour (thinner than
    f px), or thin parts reaching more than f px beyond its thick ones, can be missed or cut;
    everything else is found exactly as on the whole frame.
    """
    height, width = image_bgr.shape[:2]
    f = max(1, -(-width // COARSE_WIDTH))
    if f == 1:
        return 0, 0, width, height
    samples = cv2.resize(image_bgr, (-(-width // f), -(-height // f)), interpolation=cv2.INTER_NEAREST)  # = image[::f, ::f]
    x, y, w, h = cv2.boundingRect(color_mask(cv2.cvtColor(samples, cv2.COLOR_BGR2HSV), color))
    if w == 0:
        return None
    pad = f + margin
    return max(x * f - pad, 0), max(y * f - pad, 0), min((x + w - 1) * f + 1 + pad, width), min((y + h - 1) * f + 1 + pad, height)


def extract_silhouette(
    image_bgr: np.ndarray,
    params: PerceptionParams,
    predicted_uv: Optional[Tuple[float, float]] = None,
    color: Optional[str] = None,
    size: Optional[Tuple[int, int]] = None,
) -> Optional[Silhouette]:
    """The object's silhouette in a BGR frame, or None when no component is large enough.

    ``color`` defaults to ``params.object_color``; ``predicted_uv`` picks the component nearest it
    when ``params.component`` is "nearest"; ``size`` = (width, height) the frame must have.
    Raises ``ImageError`` on anything that is not an H x W x 3 uint8 image.
    """
    image = check_image(image_bgr, size)
    found = _components(image, params, params.object_color if color is None else color)
    if found is None:
        return None
    (x0, y0), cleaned, contours, areas, centroids = found
    if params.component == "nearest" and predicted_uv is not None:
        best = int(np.argmin(np.hypot(*(centroids + (x0, y0) - np.asarray(predicted_uv, dtype=float)).T)))
    else:
        best = int(np.argmax(areas))
    x, y, w, h = cv2.boundingRect(contours[best])
    # Label the bounding box only: the component is the one under the contour's first point
    # (holes stay holes; other blobs reaching into the box are left out).
    _, labels = cv2.connectedComponents(cleaned[y:y + h, x:x + w], connectivity=8)
    u0, v0 = contours[best][0, 0]
    component = labels == labels[v0 - y, u0 - x]
    x, y = x + x0, y + y0
    mask = np.zeros(image.shape[:2], np.uint8)
    mask[y:y + h, x:x + w][component] = 255
    rows, cols = np.nonzero(component)
    left_rows, right_rows = rows[cols == 0], rows[cols == w - 1]
    band_rows = np.flatnonzero(component.any(axis=1))
    first = component[band_rows].argmax(axis=1)
    last = w - 1 - component[band_rows, ::-1].argmax(axis=1)
    left_edge, right_edge = outline_edges(image, y + band_rows, x + first, x + last, params)
    height, width = image.shape[:2]
    m = params.border_margin
    return Silhouette(
        mask=mask,
        bbox=(x, y, w, h),
        area=int(rows.size),
        centroid=(x + float(cols.mean()), y + float(rows.mean())),
        left_px=(x, y + int(np.median(left_rows))),
        right_px=(x + w - 1, y + int(np.median(right_rows))),
        touches_left=x <= m,
        touches_right=x + w - 1 >= width - 1 - m,
        touches_top=y <= m,
        touches_bottom=y + h - 1 >= height - 1 - m,
        left_edge=left_edge,
        right_edge=right_edge,
    )


def largest_area(image_bgr: np.ndarray, params: PerceptionParams, color: str) -> int:
    """px: the largest component of colour class ``color`` a frame holds (as ``extract_silhouette`` finds
    them, at least ``min_area``), 0 when none."""
    found = _components(check_image(image_bgr), params, color)
    return 0 if found is None else int(found[3].max())


def free_classes(params: PerceptionParams, taken: Iterable[str] = ()) -> List[str]:
    """The colour classes neither the object's nor in ``taken`` (the map's balls'), sorted."""
    return sorted(set(params.colors) - {params.object_color} - set(taken))


class ColourTally:
    """The frames without the object's colour in which another colour class filled a silhouette: what a
    mission that never saw its object names in its reason (agent/mission.py, ``object_note``), since a
    room's object of another colour than ``object_color`` is otherwise "not seen" in plain view. Every
    ``every``-th frame it is asked about, each class that is neither the object's nor in ``taken`` (the
    map's balls) is searched (``largest_area``)."""

    def __init__(self, params: PerceptionParams, taken: Iterable[str] = (), every: int = 5):
        self.params, self.every = params, every
        self.free = free_classes(params, taken)
        self.frames = 0
        self.seen: Counter = Counter()

    def look(self, image_bgr: np.ndarray) -> None:
        """A frame without a silhouette of the object's colour."""
        self.frames += 1
        if self.frames % self.every == 0:
            self.seen.update(c for c in self.free if largest_area(image_bgr, self.params, c))

    def note(self, min_frames: int = 3) -> str:
        """The classes seen in at least ``min_frames`` searched frames, most first, and what to do; "" when none."""
        seen = [(c, n) for c, n in self.seen.most_common() if n >= min_frames]
        if not seen:
            return ""
        listed = ", ".join(f"{c} in {n}" for c, n in seen)
        return (f"silhouettes of other colour classes were seen where none of {self.params.object_color} was ({listed} of "
                f"{self.frames // self.every} frames searched): if the object has one of them, set perception.object_color "
                f"(docs/perception.md)")


def _components(image: np.ndarray, params: PerceptionParams, name: str):
    """((x0, y0) of the searched region, its cleaned mask, and the components of at least ``min_area``
    in it: contours, areas, centroids) of colour class ``name``, or None when there is none."""
    if name not in params.colors:
        raise ValueError(f"unknown colour class {name!r} (known: {sorted(params.colors)})")
    color_class = params.colors[name]
    region = color_region(image, color_class, 2 * max(params.open_radius, params.close_radius) + 1)
    if region is None:
        return None
    x0, y0, x1, y1 = region
    cleaned = clean_mask(color_mask(cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_BGR2HSV), color_class), params)
    contours, areas, centroids = blobs(cleaned, params.min_area)
    return ((x0, y0), cleaned, contours, areas, centroids) if contours else None


def outline_edges(
    image: np.ndarray, rows: np.ndarray, first: np.ndarray, last: np.ndarray, params: PerceptionParams
) -> Tuple[np.ndarray, np.ndarray]:
    """Sub-pixel left and right outline edges (N x 2, (u, v)) of mask rows ``rows`` whose first and
    last object pixels are ``first`` and ``last`` (module docstring: linear unmixing between the
    background and object colours ``edge_window`` pixels out and in)."""
    n = len(rows)
    # Both sides at once: the left edges (background towards -u) then the right ones (towards +u).
    outwards = np.repeat([-1, 1], n)
    edge_px, far_px = np.concatenate([first, last]), np.concatenate([last, first])
    u = edge_px + 0.5 * outwards  # the mask's outer pixel edges
    w = params.edge_window
    if w > 0:
        cols = edge_px[:, None] - outwards[:, None] * np.arange(-w, w + 1)  # background reference first, object's last
        usable = (cols.min(axis=1) >= 0) & (cols.max(axis=1) < image.shape[1]) & (np.abs(far_px - edge_px) >= w)
        pixels = image[np.tile(rows, 2)[:, None], np.clip(cols, 0, image.shape[1] - 1)].astype(np.float32)
        background = pixels[:, 0]
        axis = pixels[:, -1] - background
        contrast2 = np.einsum("nc,nc->n", axis, axis)
        usable &= contrast2 >= params.edge_min_contrast**2
        mixed, obj = pixels[:, 1:-1], pixels[:, -1]
        projected = np.einsum("nkc,nc->nk", mixed - background[:, None], axis) / np.maximum(contrast2, 1.0)[:, None]
        # I_i = a_i O + b_i B by least squares over the channels (the object's shade free), c_i = 1 - b_i (Cramer's rule)
        oo, ob, bb = (np.einsum("nc,nc->n", x, y) for x, y in ((obj, obj), (obj, background), (background, background)))
        det = oo * bb - ob * ob
        apart = (det > UNMIX_MIN_SIN2 * oo * bb) & (params.edge_unmixing == "free_shade")
        b = (oo[:, None] * np.einsum("nkc,nc->nk", mixed, background) - ob[:, None] * np.einsum("nkc,nc->nk", mixed, obj))
        coverage = np.where(apart[:, None], 1.0 - b / np.where(apart, det, 1.0)[:, None], projected)
        # The object's length in the window, measured outwards from the object reference's inner pixel edge.
        subpixel = edge_px - outwards * (w - 0.5) + outwards * np.clip(coverage, 0.0, 1.0).sum(axis=1)
        u = np.where(usable, subpixel, u)
    v = np.tile(rows, 2).astype(float)
    return np.column_stack([u[:n], v[:n]]), np.column_stack([u[n:], v[n:]])


def measure_object(
    silhouette: Silhouette, camera: CameraModel, T_WC: np.ndarray, params: PerceptionParams
) -> Optional[ObjectMeasurement]:
    """Centre azimuth, bearing phi and apparent width delta of a silhouette seen from T_WC.

    None when the silhouette has no outline pixels; ``delta`` is None when it is cut by any border.
    """
    if silhouette.area <= 0 or len(silhouette.left_edge) == 0:
        return None
    left, right = silhouette.left_edge, silhouette.right_edge
    a_left = ray_azimuths(camera.pixels_to_rays(left), T_WC)
    a_right = ray_azimuths(camera.pixels_to_rays(right), T_WC)
    # Unwrap around the left tangent so that the comparisons below never straddle +-pi.
    ref = float(a_left[np.argmin(left[:, 0])])
    a_left = ref + wrap_angle(a_left - ref)
    a_right = ref + wrap_angle(a_right - ref)
    band = params.edge_band / camera.K[0, 0]
    a_l = float(np.mean(a_left[a_left >= a_left.max() - band]))
    a_r = float(np.mean(a_right[a_right <= a_right.min() + band]))
    azimuth = wrap_angle(0.5 * (a_l + a_r))
    phi = wrap_angle(azimuth - optical_axis_heading(T_WC))
    delta = a_l - a_r if silhouette.width_valid else None
    _, y, _, h = silhouette.bbox
    return ObjectMeasurement(azimuth=azimuth, phi=phi, delta=delta, a_left=wrap_angle(a_l), a_right=wrap_angle(a_r),
                             cut=silhouette.cut, top_row=y, bottom_row=y + h - 1)


def object_pixel_direction(camera: CameraModel, uv: Tuple[float, float]) -> Tuple[float, float]:
    """Horizontal and vertical angles (rad) of a pixel's ray from the optical axis: (atan2(x, z), atan2(y, z))."""
    x, y, z = camera.pixels_to_rays(np.asarray(uv, dtype=float))[0]
    return math.atan2(x, z), math.atan2(y, z)
