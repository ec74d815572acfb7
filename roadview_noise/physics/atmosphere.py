"""Homogeneous-medium optics: extinction from visibility, Beer–Lambert (models.md §2.1, §3.1)."""

from __future__ import annotations

import math

import numpy as np

LN_MOR = -math.log(0.05)      # 2.9957: σ · MOR, the WMO meteorological optical range (5 % contrast)


def extinction_from_visibility_per_m(visibility_m: float) -> float:
    """``σ = −ln(0.05)/MOR = ln 20 / MOR`` (m⁻¹)."""
    return LN_MOR / visibility_m


def transmission(sigma_per_m, distance_m) -> np.ndarray:
    """One-way Beer–Lambert transmission ``exp(−σ d)``; ``d = inf`` (sky) gives 0."""
    with np.errstate(invalid="ignore", over="ignore"):
        t = np.exp(-np.asarray(sigma_per_m) * np.asarray(distance_m))
    return np.nan_to_num(t, nan=0.0)


def two_way_transmission(alpha_per_m, range_m) -> np.ndarray:
    """Two-way (active sensor) transmission ``exp(−2 α R)``."""
    return transmission(2.0 * np.asarray(alpha_per_m), range_m)
