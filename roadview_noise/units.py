"""Unit conversions used at the edges (SI inside): planar depth → range along the ray."""

from __future__ import annotations

import numpy as np


def planar_depth_to_range(z_m: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Euclidean range along each pixel ray from planar depth z (models.md §0.2):
    ``d = z·sqrt(1 + ((u−c_x)/f_x)² + ((v−c_y)/f_y)²)``."""
    h, w = z_m.shape
    u = (np.arange(w, dtype=np.float64) - cx) / fx
    v = (np.arange(h, dtype=np.float64) - cy) / fy
    factor = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)
    return (z_m * factor).astype(z_m.dtype, copy=False)
