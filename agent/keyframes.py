"""Keyframes for the carve: a bounded set spread around the object, of precise poses and clean silhouettes.

Quality of a candidate view, every factor in [0, 1]::

    q = q_pose q_sil q_sharp
    q_pose  = 1 / (1 + sigma^2 / sigma_0^2),  sigma^2 = lambda_max(Sigma_xy) + d^2 Sigma_thth
    q_sil   = 1, or ``keyframe_cut`` when the silhouette touches an image border
    q_sharp = min(1, 2 g / c)

sigma is the localizer's pose uncertainty at capture seen at the object: its position std plus its
heading std times the camera-object distance d (a heading error theta moves the object's image as a
lateral shift of d theta); sigma_0 = ``keyframe_pose_std``. A silhouette cut by a border has lost
its extent there (the top or base of the object out of view, or a side): it carves less and its
border edge says nothing. Sharpness: g is the mean grey-level gradient (central difference, per
pixel) on the silhouette's contour and c the contrast between the bands 2-4 px inside and outside it;
a step edge gives g = c / 2, an edge blurred over w pixels about c / w, so 2 g / c ~ 1 / w. Without
contrast (c < ``_MIN_CONTRAST``) sharpness cannot be told and q_sharp = 1.

Pool (live, :class:`KeyframePool`): a frame is offered with its viewing azimuth a = atan2(C - o)
around the current estimate o; it is kept when its azimuth differs by >= ``min_angle`` from every
kept one (a new direction), or when its quality is at least twice that of every kept view within
``min_angle`` (a better view of a direction seen: a fresh fix, an uncut silhouette). Quality is at
most 1, so a direction gains at most log2(1 / q_min) such views: the pool is bounded.

Consistency with the final estimate (final carve, :func:`axis_in_view`): the object's vertical axis
through the estimated centre o, {(o_x, o_y, z), 0 <= z <= z_max}, lies inside the object, so with a
right pose its image crosses the silhouette. A keyframe whose axis image misses its silhouette
entirely has a pose off by more than the object's half-width (a wrong landmark association): with
the carve's tolerance of a few views, a handful of such keyframes would carve the whole object
away, so they are left out.

Selection (final carve, :func:`select_keyframes`): azimuths around the *final* estimate; greedy
gap filling weighted by quality. Start with the best view; then repeatedly add the view i that
maximises q_i g_i, g_i = min_{j in S} |wrap(a_i - a_j)| (the largest gap it fills), until
``keyframes`` views are chosen or the best remaining g_i < ``keyframe_gap``.
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np

from agent.camera import CameraModel
from nao_core.geometry import wrap_angle

_MIN_CONTRAST = 8.0  # grey levels: below this a contour's sharpness is not measurable
_PAD = 6  # px around the silhouette's bounding box: beyond its bands' 4 px and the gradient's 1


def pose_quality(covariance: np.ndarray, distance: float, sigma_0: float) -> float:
    """q_pose from the localizer's (x, y, theta) covariance at capture (module docstring); 0 when unknown."""
    cov = np.asarray(covariance, dtype=float)
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        return 0.0
    variance = float(np.linalg.eigvalsh(cov[:2, :2])[-1]) + distance**2 * max(float(cov[2, 2]), 0.0)
    return 1.0 / (1.0 + max(variance, 0.0) / sigma_0**2)


def silhouette_quality(mask: np.ndarray, image: Optional[np.ndarray], cut_weight: float) -> float:
    """q_sil q_sharp of a silhouette (HxW bool/uint8) in its BGR or grey ``image`` (module docstring;
    without an image, q_sil alone)."""
    m = np.asarray(mask).astype(np.uint8)
    if not m.any():
        return 0.0
    q_sil = cut_weight if (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()) else 1.0
    if image is None:
        return q_sil
    # every step below reaches at most 4 px from the silhouette: work on its padded bounding box
    x, y, w, h = cv2.boundingRect(m)
    window = (slice(max(0, y - _PAD), y + h + _PAD), slice(max(0, x - _PAD), x + w + _PAD))
    m = m[window]
    grey = np.asarray(image, dtype=np.uint8)[window]
    grey = cv2.cvtColor(grey, cv2.COLOR_BGR2GRAY) if grey.ndim == 3 else grey
    grey = grey.astype(np.float32)
    disc = lambda r: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))  # noqa: E731
    inner = (cv2.erode(m, disc(2)) > 0) & ~(cv2.erode(m, disc(4)) > 0)
    outer = (cv2.dilate(m, disc(4)) > 0) & ~(cv2.dilate(m, disc(2)) > 0)
    contour = (m > 0) & ~(cv2.erode(m, disc(1)) > 0)
    sharp = 1.0
    if inner.any() and outer.any():
        contrast = abs(float(grey[inner].mean()) - float(grey[outer].mean()))
        if contrast >= _MIN_CONTRAST:
            gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=1) * 0.5  # central difference per pixel
            gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=1) * 0.5
            g = float(np.hypot(gx, gy)[contour].mean())
            sharp = min(1.0, 2.0 * g / contrast)
    return q_sil * sharp


class KeyframePool:
    """The live candidates: a new direction, or a view twice as good as every kept one near it."""

    def __init__(self, min_angle: float):
        self.min_angle = min_angle
        self._kept: List[Tuple[float, float]] = []  # (azimuth, quality)

    def offer(self, azimuth: float, quality: float) -> bool:
        """Keep this view (True) or not (module docstring)."""
        near = [q for a, q in self._kept if abs(wrap_angle(azimuth - a)) < self.min_angle]
        if near and (quality <= 0.0 or quality < 2.0 * max(near)):
            return False
        self._kept.append((azimuth, quality))
        return True


def select_keyframes(azimuths: Sequence[float], qualities: Sequence[float], count: int, min_gap: float) -> List[int]:
    """Indices (ascending) of at most ``count`` views by quality-weighted gap filling (module docstring)."""
    a = np.asarray(azimuths, dtype=float)
    q = np.asarray(qualities, dtype=float)
    if a.shape != q.shape or a.ndim != 1:
        raise ValueError(f"azimuths and qualities: expected two equal-length lists, got shapes {a.shape} and {q.shape}")
    if not np.all(np.isfinite(a)) or not np.all(np.isfinite(q)):
        raise ValueError("azimuths and qualities must be finite")
    usable = np.flatnonzero(q > 0.0)
    if not usable.size or count < 1:
        return []
    chosen = [int(usable[np.argmax(q[usable])])]
    gap = np.abs(np.angle(np.exp(1j * (a - a[chosen[0]]))))
    while len(chosen) < count:
        score = np.where(q > 0.0, q * gap, -1.0)
        score[chosen] = -1.0
        best = int(np.argmax(score))
        if score[best] < 0.0 or gap[best] < min_gap:
            break
        chosen.append(best)
        gap = np.minimum(gap, np.abs(np.angle(np.exp(1j * (a - a[best])))))
    return sorted(chosen)


def view_azimuth(T_WC: np.ndarray, centre_xy: Sequence[float]) -> float:
    """Viewing azimuth atan2(C - o) of a camera pose around the object centre o."""
    c = np.asarray(T_WC, dtype=float)[:3, 3]
    return math.atan2(c[1] - float(centre_xy[1]), c[0] - float(centre_xy[0]))


def axis_in_view(mask: np.ndarray, camera: CameraModel, T_WC: np.ndarray, centre_xy: Sequence[float], top: float,
                 samples: int = 200) -> bool:
    """Does the image of the vertical axis through ``centre_xy`` (0 <= z <= ``top``) cross the
    silhouette ``mask`` of a keyframe seen with ``camera`` from ``T_WC`` (module docstring)?"""
    points = np.column_stack([np.full(samples, centre_xy[0]), np.full(samples, centre_xy[1]), np.linspace(0.0, top, samples)])
    uv, in_front = camera.project_world(points, T_WC)
    pixels = np.round(uv[in_front]).astype(int)
    height, width = mask.shape[:2]
    inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < height)
    pixels = pixels[inside]
    return bool(pixels.size) and bool(np.any(mask[pixels[:, 1], pixels[:, 0]]))
