"""Terminal fall speeds of hydrometeors (models.md §2.2, §2.3, §4.3)."""

from __future__ import annotations

import numpy as np


def _floats(x) -> np.ndarray:
    """float32 input stays float32 (particle arrays on hot paths); anything else becomes float64."""
    a = np.asarray(x)
    return a if a.dtype == np.float32 else a.astype(np.float64)


def atlas_ulbrich_m_per_s(d_mm) -> np.ndarray:
    """Raindrop terminal speed, Atlas & Ulbrich (1977): ``v = 3.778 D^0.67`` m/s, D in mm (valid 0.5–5 mm)."""
    d = _floats(d_mm)
    return d.dtype.type(3.778) * d ** d.dtype.type(0.67)


def atlas_srivastava_sekhon_m_per_s(d_mm) -> np.ndarray:
    """Raindrop terminal speed, Atlas, Srivastava & Sekhon (1973): ``v = 9.65 − 10.3 e^{−0.6 D}`` m/s (D in mm);
    levels off at 9.65 m/s for large drops (valid 0.1–6 mm, clipped at 0 for tiny drops)."""
    return np.maximum(9.65 - 10.3 * np.exp(-0.6 * np.asarray(d_mm, dtype=float)), 0.0)


def snow_power_law_m_per_s(d_mm, a_m_per_s: float = 0.8, b: float = 0.16) -> np.ndarray:
    """Snowflake terminal speed ``v = a D^b`` (D in mm); default a = 0.8 m/s, b = 0.16 for unrimed aggregates
    (models.md §2.3 [PROP]; replaces the reference's garbled constant 0.65 m/s)."""
    d = _floats(d_mm)
    return d.dtype.type(a_m_per_s) * d ** d.dtype.type(b)
