"""ArUco markers found under motion smear by tracking them from a pose prior (docs/landmarks.md
"Markers under smear").

A camera turning at omega (rad/s, its optical frame) during an exposure T moves the image of a
point at normalized coordinates (x, y) by (the image motion of a rotating camera, P' = P x omega)

    x' = x y w_x - (1 + x^2) w_y + y w_z,    y' = (1 + y^2) w_x - x y w_y - x w_z,

so a marker is smeared along s = T (f_x x', f_y y') px. A few pixels of smear round the marker's
black square into a blob the detector's quadrilateral test rejects: on rendered stress frames
(8 cm markers, 10-40 px) detection fell from 76 % of the markers in view to 11 % at 6 px of smear
and to none at 10 px, which is what a NAO's torso sway gives in a dim room.

A marker the prior predicts in view keeps its pattern, only smeared. Its template is rendered where
the prior puts it: the marker (``cv2.aruco.generateImageMarker``) with one module of white quiet
zone, warped by the homography of its predicted corners, smeared by the kernel of c s (a line of
length c |s|, bilinear taps) and blurred by a Gaussian of ``sigma`` px. The image is aligned to it
by ECC (``cv2.findTransformECCWithMask``, Evangelidis and Psarakis 2008) over a translation t,
which maximises the correlation of the zero-mean, unit-norm template and image window inside the
template's mask (the marker and its quiet zone: the wall around it is not the template's), started
from the best whole-pixel shift of a normalized cross-correlation (``cv2.matchTemplate``) over the
window (ECC alone converges only within about a module of the pattern: a prior 10 mrad off lost
most markers). The marker's centre is then seen at pi(centre) + t.

Only the translation is measured: an affine or homography fit on smeared images wandered (corner
errors of 1-2 px median with tails of hundreds of px on the same frames), and the four corners of
the prior's shape moved together would bring the prior's distance into the fit as if it were
measured. The exposure is not known (a NAO sets it by itself), so the smear c s is tried at the
factors c of ``smear_factors`` and the most correlated one is kept. Too long a smear loses the
lock (on the same frames at 10 px: tracked 42 % with the true smear, 64 % with half of it), so the
factors stay below 1 of a smear reckoned with a long exposure.

Off by default (``localization.track_smear_factors: []``): tracked fixes came more often but the
missions' poses were worse. The same logged frames re-run through the pilot with and without it
(nine stress and one-wall worlds, true camera poses recorded): the camera's position error median
rose in seven of them (up to 15.0 -> 34.7 mm), its p95 in six (up to 33 -> 72 mm) and fell in
three (59 -> 33 mm at most). Two tracked centres and a prior, or many tracked markers frame after
frame, pull the pose with errors the fit cannot see (docs/landmarks.md "Markers under smear").
``SMEAR_FACTORS`` turns it on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import cv2
import numpy as np

SMEAR_FACTORS = (0.6, 0.3, 0.0)  # localization.track_smear_factors that track (measured on still poses, docs/landmarks.md)
_TEXELS = 96  # marker texture side, px (a tracked marker is smaller in the image: the detector finds large ones)
_ECC_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)


@dataclass(frozen=True)
class TrackedMarker:
    shift: np.ndarray  # px (2,), the image minus the prediction
    correlation: float  # ECC's correlation coefficient, in [-1, 1]


def rotation_flow(normalized: np.ndarray, rate: Sequence[float], focal: Sequence[float]) -> np.ndarray:
    """px/s (N x 2) of image points at ``normalized`` (N x 2) coordinates, camera turning at ``rate``
    (rad/s, optical frame), focal lengths (f_x, f_y) (module docstring)."""
    x, y = np.asarray(normalized, dtype=float).reshape(-1, 2).T
    wx, wy, wz = (float(v) for v in rate)
    return np.stack([focal[0] * (x * y * wx - (1.0 + x * x) * wy + y * wz),
                     focal[1] * ((1.0 + y * y) * wx - x * y * wy - x * wz)], axis=1)


def smear_kernel(smear: np.ndarray) -> Optional[np.ndarray]:
    """Normalized kernel of a uniform line of the vector ``smear`` (px) centred on the kernel's middle
    pixel; None below a pixel."""
    length = float(np.hypot(*smear))
    if length < 1.0:
        return None
    k = int(math.ceil(length)) | 1
    kernel = np.zeros((k + 2, k + 2), np.float32)
    c = (k + 1) / 2.0
    for s in np.linspace(-0.5, 0.5, 4 * k):
        x, y = c + s * smear[0], c + s * smear[1]
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0:y0 + 2, x0:x0 + 2] += np.array([[(1 - fx) * (1 - fy), fx * (1 - fy)], [(1 - fx) * fy, fx * fy]], np.float32)
    return kernel / kernel.sum()


def marker_texture(dictionary: cv2.aruco.Dictionary, marker_id: int) -> tuple[np.ndarray, np.ndarray]:
    """The marker with one module of white quiet zone (uint8), and the texture pixels of its four
    corners in cv2.aruco order (4 x 2)."""
    module = _TEXELS // (dictionary.markerSize + 2)
    texture = np.full((_TEXELS + 2 * module,) * 2, 255, np.uint8)
    texture[module:module + _TEXELS, module:module + _TEXELS] = cv2.aruco.generateImageMarker(dictionary, int(marker_id), _TEXELS, borderBits=1)
    a, b = module - 0.5, module + _TEXELS - 0.5
    return texture, np.array([[a, a], [b, a], [b, b], [a, b]], np.float32)


def track_marker(gray: np.ndarray, texture: np.ndarray, texture_corners: np.ndarray, quad: np.ndarray,
                 smear: np.ndarray, smear_factors: Sequence[float], sigma: float, max_shift: float,
                 ) -> Optional[TrackedMarker]:
    """The marker whose corners the prior predicts at ``quad`` (4 x 2 px), aligned in ``gray`` by ECC
    (module docstring); None when its window leaves the image or no factor converges."""
    quad = np.asarray(quad, dtype=np.float32)
    quiet_zone = (texture_corners[0, 0] + 0.5) / (texture_corners[1, 0] - texture_corners[0, 0])  # of the marker's side
    pad = (quad.max(axis=0) - quad.min(axis=0)) * quiet_zone + np.abs(smear).max() / 2 + max_shift
    lo = np.floor(quad.min(axis=0) - pad).astype(int)
    hi = np.ceil(quad.max(axis=0) + pad).astype(int)
    if lo.min() < 0 or hi[0] > gray.shape[1] or hi[1] > gray.shape[0]:
        return None
    size = (int(hi[0] - lo[0]), int(hi[1] - lo[1]))
    H = cv2.getPerspectiveTransform(texture_corners, quad - lo.astype(np.float32))
    inside = cv2.warpPerspective(np.full(texture.shape, 255, np.uint8), H, size, flags=cv2.INTER_NEAREST)
    x, y, w, h = cv2.boundingRect(inside)
    if min(w, h) < 4:  # a degenerate predicted quad
        return None
    sharp = cv2.warpPerspective(texture, H, size, flags=cv2.INTER_AREA).astype(np.float32)
    window = gray[lo[1]:hi[1], lo[0]:hi[0]].astype(np.float32)
    valid = np.full(window.shape, 255, np.uint8)  # the whole window is image
    best: Optional[TrackedMarker] = None
    for factor in smear_factors:
        kernel = smear_kernel(factor * np.asarray(smear, dtype=float))
        template = sharp if kernel is None else cv2.filter2D(sharp, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        if sigma > 0.0:
            template = cv2.GaussianBlur(template, (0, 0), sigma)
        try:
            # coarse: the best whole-pixel shift by normalized cross-correlation over the window
            scores = np.nan_to_num(cv2.matchTemplate(window, template[y:y + h, x:x + w], cv2.TM_CCOEFF_NORMED,
                                                     mask=inside[y:y + h, x:x + w]), nan=-1.0, posinf=-1.0, neginf=-1.0)
            row, col = np.unravel_index(int(np.argmax(scores)), scores.shape)
            start = np.array([[1.0, 0.0, col - x], [0.0, 1.0, row - y]], np.float32)
            correlation, warp = cv2.findTransformECCWithMask(template, window, inside, valid, start,
                                                             cv2.MOTION_TRANSLATION, _ECC_CRITERIA, 3)
        except cv2.error:  # ECC did not converge, or a flat window
            continue
        shift = warp[:, 2].astype(float)
        if np.all(np.isfinite(shift)) and np.hypot(*shift) <= max_shift and (best is None or correlation > best.correlation):
            best = TrackedMarker(shift, float(correlation))
    return best
