"""Named unit conversions used at the edges of physics code (SI inside)."""

from __future__ import annotations

import numpy as np

MM_PER_H_TO_M_PER_S = 1e-3 / 3600.0


def deg_to_rad(x):
    return np.deg2rad(x)


def rad_to_deg(x):
    return np.rad2deg(x)


def db_to_linear(x_db):
    """Power ratio from decibels."""
    return 10.0 ** (np.asarray(x_db, dtype=float) / 10.0)


def linear_to_db(x):
    """Decibels from a power ratio."""
    return 10.0 * np.log10(x)


def planar_depth_to_range(z_m: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Euclidean range along each pixel ray from planar depth z (models.md §0.2):
    ``d = z·sqrt(1 + ((u−c_x)/f_x)² + ((v−c_y)/f_y)²)``."""
    h, w = z_m.shape
    u = (np.arange(w, dtype=np.float64) - cx) / fx
    v = (np.arange(h, dtype=np.float64) - cy) / fy
    factor = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)
    return (z_m * factor).astype(z_m.dtype, copy=False)


def range_to_planar_depth(d_m: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Inverse of :func:`planar_depth_to_range`."""
    h, w = d_m.shape
    u = (np.arange(w, dtype=np.float64) - cx) / fx
    v = (np.arange(h, dtype=np.float64) - cy) / fy
    factor = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)
    return (d_m / factor).astype(d_m.dtype, copy=False)
