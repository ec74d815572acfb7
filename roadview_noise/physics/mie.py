"""Mie efficiencies of homogeneous spheres (models.md Appendix A), wrapping the maintained ``miepython`` package.

Physics sign convention here: ``m = n + iκ`` with κ ≥ 0 for an absorbing sphere (models.md, Appendix B).
miepython uses ``n − iκ``; the conversion happens once, in :func:`efficiencies`.
Size parameter ``x = 2π r/λ = π D/λ`` (medium index 1). Results are constants of the physics: build tables once
with :func:`efficiency_table` (cached), never per frame.
"""

from __future__ import annotations

import math
from functools import lru_cache

import miepython
import numpy as np


def size_parameter(radius_m, wavelength_m) -> np.ndarray:
    """``x = 2π r/λ`` (dimensionless); radius and wavelength in the same unit."""
    return 2.0 * math.pi * np.asarray(radius_m, dtype=float) / wavelength_m


def efficiencies(m: complex, x) -> tuple[np.ndarray, np.ndarray]:
    """Extinction and backscatter efficiencies ``(Q_ext, Q_back)`` of spheres of index ``m = n + iκ``.

    ``x`` is a scalar or an array of size parameters; the result has its shape."""
    m = complex(m)
    if m.imag < 0:
        raise ValueError(f"give the index as n + iκ with κ ≥ 0 (absorbing), got {m}")
    x = np.asarray(x, dtype=float)
    if np.any(x <= 0):
        raise ValueError("size parameters must be > 0")
    q_ext, _q_sca, q_back, _g = miepython.efficiencies_mx(m.conjugate(), x.ravel())
    return np.asarray(q_ext, dtype=float).reshape(x.shape), np.asarray(q_back, dtype=float).reshape(x.shape)


@lru_cache(maxsize=64)
def efficiency_table(m: complex, x_values: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Cached, read-only ``(Q_ext, Q_back)`` over a fixed grid of size parameters (pass the grid as a tuple)."""
    q_ext, q_back = efficiencies(m, np.asarray(x_values))
    q_ext.flags.writeable = False
    q_back.flags.writeable = False
    return q_ext, q_back
