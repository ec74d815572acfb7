"""Unit conversions used at the edges (SI inside): planar depth → range along the ray."""

from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=4)
def ray_factor(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Range / planar depth per pixel, ``sqrt(1 + ((u−c_x)/f_x)² + ((v−c_y)/f_y)²)`` (read-only float32)."""
    u = (np.arange(width) - cx) / fx
    v = (np.arange(height) - cy) / fy
    k = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2).astype(np.float32)
    k.flags.writeable = False
    return k


def planar_depth_to_range(z_m: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Euclidean range along each pixel ray from planar depth z (models.md §0.2):
    ``d = z·sqrt(1 + ((u−c_x)/f_x)² + ((v−c_y)/f_y)²)``."""
    h, w = z_m.shape
    return (z_m * ray_factor(w, h, fx, fy, cx, cy)).astype(z_m.dtype, copy=False)
