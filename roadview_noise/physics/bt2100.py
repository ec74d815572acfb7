"""BT.2100 HDR transfer functions, PQ (SMPTE ST 2084) and HLG (ITU-R BT.2100-2 Table 4 and Table 5).

The linear scale of both is **reference white at 1.0**: the diffuse white of ITU-R BT.2408 (203 cd/m² on a PQ
display, 75 % HLG signal), the level an 8-bit sRGB photo's full scale stands for, so a model's absolute levels
(fog's airlight estimate, low light's ADC full scale, the JPEG step's 8-bit sRGB) mean the same on an HDR photo:

- PQ (display light): ``x = L / 203 cd/m²`` with ``L = 10 000 cd/m² · EOTF(E')``; the full code is
  10 000 / 203 = 49.26 (no inverse OOTF: the display light stands for the scene's).
- HLG (scene light): ``x = E / E_ref`` with ``E = OETF⁻¹(E')`` (0 … 1) and ``E_ref = OETF⁻¹(0.75) = 0.2650``; the
  full code is 3.774.

The curves; their tables, and the other transfers camera files state, are :mod:`.transfers`.
"""

from __future__ import annotations

import numpy as np

REFERENCE_WHITE_CD_PER_M2 = 203.0      # ITU-R BT.2408-7 §2.1: HDR reference white (PQ), 75 % HLG signal
PQ_PEAK_CD_PER_M2 = 10000.0
# BT.2100 Table 4 (PQ)
PQ_M1, PQ_M2 = 2610 / 16384, 2523 / 4096 * 128
PQ_C1, PQ_C2, PQ_C3 = 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
# BT.2100 Table 5 (HLG)
HLG_A = 0.17883277
HLG_B = 1 - 4 * HLG_A
HLG_C = 0.5 - HLG_A * np.log(4 * HLG_A)
HLG_REFERENCE_SIGNAL = 0.75


def pq_eotf(signal: np.ndarray) -> np.ndarray:
    """Display luminance (cd/m²) of PQ signal E' (0–1), float64."""
    n = np.asarray(signal, dtype=float) ** (1 / PQ_M2)
    return PQ_PEAK_CD_PER_M2 * (np.maximum(n - PQ_C1, 0.0) / (PQ_C2 - PQ_C3 * n)) ** (1 / PQ_M1)


def pq_inverse_eotf(luminance_cd_per_m2: np.ndarray) -> np.ndarray:
    """PQ signal E' (0–1) of display luminance (cd/m², 0 … 10 000), float64."""
    y = (np.asarray(luminance_cd_per_m2, dtype=float) / PQ_PEAK_CD_PER_M2) ** PQ_M1
    return ((PQ_C1 + PQ_C2 * y) / (1 + PQ_C3 * y)) ** PQ_M2


def hlg_inverse_oetf(signal: np.ndarray) -> np.ndarray:
    """Normalised scene light E (0–1) of HLG signal E' (0–1), float64."""
    e = np.asarray(signal, dtype=float)
    return np.where(e <= 0.5, e * e / 3, (np.exp((e - HLG_C) / HLG_A) + HLG_B) / 12)


def hlg_oetf(light: np.ndarray) -> np.ndarray:
    """HLG signal E' (0–1) of normalised scene light E (0–1), float64."""
    e = np.asarray(light, dtype=float)
    return np.where(e <= 1 / 12, np.sqrt(3 * e), HLG_A * np.log(np.maximum(12 * e - HLG_B, 1e-300)) + HLG_C)


HLG_REFERENCE_LIGHT = float(hlg_inverse_oetf(HLG_REFERENCE_SIGNAL))
