"""A crude depth prior (recipe ``inputs.depth_source: ground_plane``): a flat road below the horizon and a constant
distance at and above it.

A camera at height h above a flat ground, pitched down by θ (optical axis below the horizontal), sees along the
pixel ray ``r = K⁻¹ (u, v, 1)`` (camera frame x right, y down, z forward). In a level frame the ray's downward
component is ``r_down = r_y cos θ + r_z sin θ``; the ray meets the ground at range ``h |r| / r_down`` when
``r_down > 0``. Rays at or above the horizon, and ground farther than ``sky_distance_m``, get ``sky_distance_m``:
buildings, trees and sky are all put at one distance, so this is a prior for frames with nothing better, not a
measurement (every pixel is marked valid: there is nothing better to estimate the airlight from). For the centre
column the range is ``h / sin(atan((v − c_y)/f_y) + θ)``: the closed form of the tests.
"""

from __future__ import annotations

import math

import numpy as np

from ..units import ray_factor


def ground_plane_range(intrinsics_px: tuple[float, float, float, float], width_px: int, height_px: int, *,
                       camera_height_m: float, pitch_rad: float = 0.0, sky_distance_m: float = 100.0) -> np.ndarray:
    """(H, W) float32 range along the pixel rays (m) of a flat ground, capped at ``sky_distance_m`` (above)."""
    if not camera_height_m > 0 or not sky_distance_m > 0:
        raise ValueError("camera_height_m and sky_distance_m must be > 0")
    fx, fy, cx, cy = intrinsics_px
    y = (np.arange(height_px) - cy) / fy
    down = y * math.cos(pitch_rad) + math.sin(pitch_rad)            # per row: the ray's downward component
    with np.errstate(divide="ignore"):
        per_row = np.where(down > 0, camera_height_m / down, np.inf).astype(np.float32)
    rng = ray_factor(width_px, height_px, fx, fy, cx, cy) * per_row[:, None]      # |r| · h / r_down
    return np.minimum(rng, np.float32(sky_distance_m), out=rng)
