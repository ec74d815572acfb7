"""Per-channel fog extinction from Mie theory over the CE chamber droplet distributions (models.md §2.1, App. A).

``σ_c = ∫ π r² Q_ext(2π r/λ_c, m_c) n(r) dr`` by the trapezoid rule over radii 0.1–10 µm (199 points, the D3.4
grid), with the CE log-normal distributions of :data:`roadview_noise.physics.dsd.CE_FOG_LOGNORMAL`.

Two tables (models.md §2.1, §7.2):
- ``corrected``: the right size parameter ``x = 2π r/λ``. At 30 m: σ = 0.0986, 0.0977, 0.0968 m⁻¹ (R, G, B).
- ``reference``: the values shipped with the D3.5 library, which the reference computed with the radius where
  the Mie routine expects the diameter (``x = π r/λ``); ≈ 6 % higher (0.1061, 0.1043, 0.1024 m⁻¹ at 30 m).

Other visibilities [PROP, models.md §2.1]: ``σ_c·V`` varies slowly (2.75–3.33 for the corrected table), so it is
interpolated linearly in ``log V`` between the four CE visibilities and held at the end values outside
10–50 m. This replaces the reference's ``σ = 3/V`` fallback, which ignores the measured distributions.
Note: the CE distributions are not exactly consistent with the MOR definition ``σ·V = ln 20 = 2.996``: with the
corrected table the transmission of a black target at ``d = V`` (green) is 0.053 at 30 m, but 0.063 at 10 m and
0.037 at 50 m. The D3.4 grid stops at 10 µm and so leaves out the large-droplet tail of the fitted log-normals
(integrating to 60 µm would add 13 % at 30 m); it is kept as specified, with the §2.1/§8 oracles.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from .cfa import CHANNEL_WAVELENGTH_M, WATER_INDEX
from .dsd import CE_FOG_LOGNORMAL, lognormal_fog

FOG_RADIUS_GRID_UM = tuple(np.linspace(0.1, 10.0, 199))
FOG_TABLES = ("corrected", "reference")

# The corrected table as :func:`mie_extinction_table` computes it, V (m) → σ (m⁻¹) in R, G, B order: stored, as
# the Mie integrals cost ≈ 0.3 s of every process that runs camera fog (miepython compiles on first call);
# tests/physics/test_fog_optics.py recomputes it and fails when an input (distributions, grid, indices) changes
CORRECTED_FOG_EXTINCTION_PER_M = {
    10.0: (0.27922036848816995, 0.27699576417240457, 0.2747665102673743),
    20.0: (0.14050051969076488, 0.1393152185563323, 0.13812612902904714),
    30.0: (0.09855382133570577, 0.09768575165619714, 0.0968067553832276),
    50.0: (0.06663970886417574, 0.06585409851185306, 0.06505576323687524),
}
# D3.5 library table (models.md §2.1), V (m) → σ (m⁻¹) in R, G, B order
REFERENCE_FOG_EXTINCTION_PER_M = {
    10.0: (0.2989, 0.2934, 0.2889),
    20.0: (0.1504, 0.1481, 0.1457),
    30.0: (0.1061, 0.1043, 0.1024),
    50.0: (0.0740, 0.0723, 0.0705),
}


def mie_fog_extinction_per_m(n_cm3: float, s: float, mu: float, wavelength_m: float, m: complex) -> float:
    """Extinction (m⁻¹) of a log-normal droplet population at one wavelength, over the 0.1–10 µm radius grid.

    Units: r² in µm² (10⁻¹² m²) × n(r) dr in cm⁻³ (10⁶ m⁻³) → 10⁻⁶ m⁻¹."""
    from .mie import efficiency_table, size_parameter          # miepython: only where the table is computed

    r_um = np.asarray(FOG_RADIUS_GRID_UM)
    x = size_parameter(r_um * 1e-6, wavelength_m)
    q_ext, _ = efficiency_table(complex(m), tuple(x))
    integrand = math.pi * r_um ** 2 * q_ext * lognormal_fog(r_um, n_cm3, s, mu)
    return float(np.trapezoid(integrand, r_um) * 1e-6)


@lru_cache(maxsize=None)
def ce_extinction_table(table: str) -> tuple[np.ndarray, np.ndarray]:
    """``(visibilities (4,), σ (4, 3) R, G, B)`` of a fog table (both stored; ``corrected``: see
    :data:`CORRECTED_FOG_EXTINCTION_PER_M`)."""
    if table not in FOG_TABLES:
        raise ValueError(f"unknown fog table {table!r}; expected one of {FOG_TABLES}")
    vis = np.array(sorted(CE_FOG_LOGNORMAL))
    stored = REFERENCE_FOG_EXTINCTION_PER_M if table == "reference" else CORRECTED_FOG_EXTINCTION_PER_M
    sigma = np.array([stored[v] for v in vis])
    vis.flags.writeable = False
    sigma.flags.writeable = False
    return vis, sigma


def mie_extinction_table() -> tuple[np.ndarray, np.ndarray]:
    """The corrected table computed by Mie theory: ``(visibilities (4,), σ (4, 3) R, G, B)``."""
    vis = np.array(sorted(CE_FOG_LOGNORMAL))
    return vis, np.array([[mie_fog_extinction_per_m(*CE_FOG_LOGNORMAL[v], lam, m)
                           for lam, m in zip(CHANNEL_WAVELENGTH_M, WATER_INDEX)] for v in vis])


def fog_extinction_per_m(visibility_m: float, table: str = "corrected") -> np.ndarray:
    """Per-channel extinction (R, G, B) in m⁻¹ at any visibility: ``σ_c·V`` interpolated in ``log V``, ends held."""
    if not visibility_m > 0:
        raise ValueError(f"visibility must be > 0 m, got {visibility_m}")
    vis, sigma = ce_extinction_table(table)
    log_v = np.log(vis)
    sigma_v = sigma * vis[:, None]
    x = math.log(visibility_m)
    return np.array([np.interp(x, log_v, sigma_v[:, c]) for c in range(3)]) / visibility_m
