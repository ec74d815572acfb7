"""Visibility and extinction: the meteorological optical range (models.md §2.1, §3.2)."""

from __future__ import annotations

import math

LN_MOR = -math.log(0.05)      # 2.9957: σ · MOR, the WMO meteorological optical range (5 % contrast)


def extinction_from_visibility_per_m(visibility_m: float) -> float:
    """``σ = −ln(0.05)/MOR = ln 20 / MOR`` (m⁻¹)."""
    return LN_MOR / visibility_m
