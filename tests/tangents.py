"""Bearing and apparent width of a silhouette from its two extreme pixels (docs/estimation.md), for tests."""

from __future__ import annotations

import numpy as np

from agent.camera import CameraModel, optical_axis_heading, ray_azimuths
from nao_core.geometry import wrap_angle


def bearing_width_from_pixels(
    camera: CameraModel, left_px: np.ndarray, right_px: np.ndarray, T_WC: np.ndarray
) -> tuple[float, float, float]:
    """Centre azimuth (world), bearing relative to the optical-axis heading, and apparent width.

    ``left_px``/``right_px`` are the silhouette's extreme left and right pixels (u, v). Returns
    (azimuth_W, phi, delta) with phi = wrap(azimuth_W - psi) and delta = a_l - a_r (wrapped).
    """
    a_l, a_r = ray_azimuths(camera.pixels_to_rays(np.vstack([left_px, right_px])), T_WC)
    delta = wrap_angle(a_l - a_r)
    azimuth = wrap_angle(a_r + 0.5 * delta)
    return azimuth, wrap_angle(azimuth - optical_axis_heading(T_WC)), delta
