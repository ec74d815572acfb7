"""Radar link budget in weather: specific attenuation of rain, fog/cloud and snow, two-way loss, noise floor
(models.md §4.1, §4.2).

Specific attenuations γ are in dB/km (never nepers); the two-way loss of a target at range R is ``2 γ R / 1000`` dB.

- Rain: ITU-R P.838-3 ``γ = k R^α`` with the frequency-dependent Gaussian-sum fits of k and α in log10 f (valid
  1–1000 GHz, any polarisation tilt); Sander (1975) ``γ = 1.07 R^0.69`` (fitted at 90 GHz) as the ROADVIEW option.
- Fog/cloud: ITU-R P.840 Rayleigh model ``γ = K_l(f, T) · LWC`` with the double-Debye permittivity of water
  (Liebe et al. 1991); LWC from visibility via the CE chamber log-normal table (physics/dsd.py).
- Dry snow: ROADVIEW linear law ``γ = 0.8205 S`` (Norouzian et al. 2018, measured above 100 GHz): an
  extrapolation at 77 GHz, probably an overestimate.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.special import lambertw

from .dsd import CE_FOG_LOGNORMAL, lognormal_fog_lwc_g_per_m3

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0
THERMAL_NOISE_DBM_PER_HZ = -174.0          # k_B T_0 at T_0 = 290 K

# --- ITU-R P.838-3 (03/2005), Tables 1–4: log10 k = Σ a_j exp(−((log10 f − b_j)/c_j)²) + m log10 f + c -------------
# (a_j, b_j, c_j) rows, then (m, c); f in GHz. α uses the same form without the log10 on the left.
_P838 = {
    "k_h": (((-5.33980, -0.10008, 1.13098), (-0.35351, 1.26970, 0.45400), (-0.23789, 0.86036, 0.15354),
             (-0.94158, 0.64552, 0.16817)), (-0.18961, 0.71147)),
    "k_v": (((-3.80595, 0.56934, 0.81061), (-3.44965, -0.22911, 0.51059), (-0.39902, 0.73042, 0.11899),
             (0.50167, 1.07319, 0.27195)), (-0.16398, 0.63297)),
    "alpha_h": (((-0.14318, 1.82442, -0.55187), (0.29591, 0.77564, 0.19822), (0.32177, 0.63773, 0.13164),
                 (-5.37610, -0.96230, 1.47828), (16.1721, -3.29980, 3.43990)), (0.67849, -1.95537)),
    "alpha_v": (((-0.07771, 2.33840, -0.76284), (0.56727, 0.95545, 0.54039), (-0.20238, 1.14520, 0.26809),
                 (-48.2991, 0.791669, 0.116226), (48.5833, 0.791459, 0.116479)), (-0.053739, 0.83433)),
}
POLARISATION_TILT_DEG = {"horizontal": 0.0, "vertical": 90.0, "circular": 45.0}


def _p838_fit(name: str, log_f: float) -> float:
    rows, (m, c) = _P838[name]
    return sum(a * math.exp(-(((log_f - b) / cw) ** 2)) for a, b, cw in rows) + m * log_f + c


@lru_cache(maxsize=32)
def p838_coefficients(frequency_hz: float, polarisation: str = "horizontal",
                      path_elevation_deg: float = 0.0) -> tuple[float, float]:
    """ITU-R P.838-3 ``(k, α)`` at ``frequency_hz`` (1–1000 GHz) for a polarisation tilt τ (horizontal 0°,
    vertical 90°, circular 45°) on a path of elevation θ (0 for a road radar):
    ``k = [k_H + k_V + (k_H − k_V) cos²θ cos 2τ]/2``,
    ``α = [k_H α_H + k_V α_V + (k_H α_H − k_V α_V) cos²θ cos 2τ]/(2k)``."""
    f_ghz = frequency_hz / 1e9
    if not 1.0 <= f_ghz <= 1000.0:
        raise ValueError(f"ITU-R P.838-3 is defined for 1–1000 GHz, got {f_ghz:g} GHz")
    if polarisation not in POLARISATION_TILT_DEG:
        raise ValueError(f"polarisation must be one of {sorted(POLARISATION_TILT_DEG)}, got {polarisation!r}")
    log_f = math.log10(f_ghz)
    k_h, k_v = 10 ** _p838_fit("k_h", log_f), 10 ** _p838_fit("k_v", log_f)
    a_h, a_v = _p838_fit("alpha_h", log_f), _p838_fit("alpha_v", log_f)
    tau = math.radians(POLARISATION_TILT_DEG[polarisation])
    w = math.cos(math.radians(path_elevation_deg)) ** 2 * math.cos(2 * tau)
    k = (k_h + k_v + (k_h - k_v) * w) / 2
    alpha = (k_h * a_h + k_v * a_v + (k_h * a_h - k_v * a_v) * w) / (2 * k)
    return k, alpha


def rain_attenuation_itu_db_per_km(rain_rate_mm_per_h: float, frequency_hz: float = 77e9,
                                   polarisation: str = "horizontal") -> float:
    """ITU-R P.838-3 specific attenuation ``γ = k R^α`` (dB/km); 77 GHz, 20 mm/h, horizontal → 9.72."""
    k, alpha = p838_coefficients(frequency_hz, polarisation)
    return k * rain_rate_mm_per_h ** alpha if rain_rate_mm_per_h > 0 else 0.0


def rain_attenuation_sander_db_per_km(rain_rate_mm_per_h: float) -> float:
    """Sander (1975), fitted at 90 GHz and used by ROADVIEW for 77 GHz: ``γ = 1.07 R^0.69`` dB/km (20 mm/h → 8.455)."""
    return 1.07 * rain_rate_mm_per_h ** 0.69 if rain_rate_mm_per_h > 0 else 0.0


# --- ITU-R P.840 liquid water (Rayleigh), double-Debye permittivity ---------------------------------------------


def water_permittivity(frequency_hz: float, temperature_c: float) -> complex:
    """Complex permittivity of liquid water ``ε' − i ε''`` (engineering sign) from the double-Debye model of
    ITU-R P.840 (Liebe et al. 1991): θ = 300/T, ε₀ = 77.66 + 103.3(θ−1), ε₁ = 0.0671 ε₀, ε₂ = 3.52,
    f_p = 20.20 − 146(θ−1) + 316(θ−1)² GHz, f_s = 39.8 f_p. 77 GHz, 20 °C → 8.81 − 15.91 i."""
    f = frequency_hz / 1e9
    theta = 300.0 / (temperature_c + 273.15)
    e0 = 77.66 + 103.3 * (theta - 1)
    e1, e2 = 0.0671 * e0, 3.52
    fp = 20.20 - 146 * (theta - 1) + 316 * (theta - 1) ** 2
    fs = 39.8 * fp
    eps_loss = f * (e0 - e1) / (fp * (1 + (f / fp) ** 2)) + f * (e1 - e2) / (fs * (1 + (f / fs) ** 2))
    eps_real = (e0 - e1) / (1 + (f / fp) ** 2) + (e1 - e2) / (1 + (f / fs) ** 2) + e2
    return complex(eps_real, -eps_loss)


def liquid_water_coefficient_db_per_km_per_g_m3(frequency_hz: float, temperature_c: float) -> float:
    """ITU-R P.840 specific attenuation coefficient ``K_l = 0.819 f / (ε''(1 + η²))``, ``η = (2 + ε')/ε''``
    in (dB/km)/(g/m³), f in GHz. 77 GHz: 3.537 / 3.147 / 2.713 at 0 / 10 / 20 °C."""
    eps = water_permittivity(frequency_hz, temperature_c)
    eps_real, eps_loss = eps.real, -eps.imag
    eta = (2 + eps_real) / eps_loss
    return 0.819 * (frequency_hz / 1e9) / (eps_loss * (1 + eta ** 2))


# Exponent of the reference LiDAR code's empirical relation LWC = 36.489 V^−1.1407 (V in m, origin undocumented).
EMPIRICAL_LWC_VISIBILITY_EXPONENT = -1.1407


@lru_cache(maxsize=1)
def _ce_lwc_table() -> tuple[np.ndarray, np.ndarray]:
    vis = np.array(sorted(CE_FOG_LOGNORMAL))
    lwc = np.array([lognormal_fog_lwc_g_per_m3(*CE_FOG_LOGNORMAL[v]) for v in vis])
    return np.log(vis), np.log(lwc)


def fog_lwc_from_visibility_g_per_m3(visibility_m: float) -> float:
    """Liquid water content of fog from visibility: log–log interpolation of the CE chamber log-normal fogs
    (10/20/30/50 m → 1.343/0.670/0.3747/0.1323 g/m³); outside 10–50 m the empirical power law ``LWC ∝ V^−1.1407``
    anchored at the nearest table end. (The reference relation ``36.489 V^−1.1407`` itself is about 2–3× the CE
    values at the table ends; anchoring keeps LWC(V) continuous and decreasing.)"""
    if visibility_m <= 0:
        raise ValueError(f"visibility must be > 0 m, got {visibility_m}")
    log_v, log_lwc = _ce_lwc_table()
    x = math.log(visibility_m)
    if x < log_v[0]:
        return float(math.exp(log_lwc[0] + EMPIRICAL_LWC_VISIBILITY_EXPONENT * (x - log_v[0])))
    if x > log_v[-1]:
        return float(math.exp(log_lwc[-1] + EMPIRICAL_LWC_VISIBILITY_EXPONENT * (x - log_v[-1])))
    return float(math.exp(np.interp(x, log_v, log_lwc)))


def fog_attenuation_db_per_km(visibility_m: float, frequency_hz: float = 77e9, temperature_c: float = 10.0) -> float:
    """ITU-R P.840 fog attenuation ``γ = K_l(f, T) LWC(V)`` (dB/km); 30 m at 77 GHz, 10 °C → 1.18 (the ROADVIEW
    reference's ``0.182 LWC f²`` gives 404 dB/km, §4.1)."""
    return liquid_water_coefficient_db_per_km_per_g_m3(frequency_hz, temperature_c) * \
        fog_lwc_from_visibility_g_per_m3(visibility_m)


def snow_attenuation_db_per_km(snowfall_rate_mm_per_h: float) -> float:
    """Dry snow, ROADVIEW linear law ``γ = 0.8205 S`` dB/km (S liquid equivalent, mm/h; 2.5 → 2.051).

    Extrapolated from measurements above 100 GHz (Norouzian et al. 2018), likely an overestimate at 77 GHz."""
    return 0.8205 * max(snowfall_rate_mm_per_h, 0.0)


# --- link budget ------------------------------------------------------------------------------------------------


def two_way_loss_db(gamma_db_per_km: float, range_m) -> np.ndarray:
    """Two-way path loss ``L = 2 γ R / 1000`` dB of a target at range R (m)."""
    return 2.0 * gamma_db_per_km * np.asarray(range_m, dtype=float) / 1000.0


def noise_floor_dbm(if_bandwidth_hz: float, noise_figure_db: float) -> float:
    """Receiver noise floor ``N = −174 dBm/Hz + 10 log10 B + NF`` (models.md §4.2; kTB at 290 K, not 4kTRB)."""
    return THERMAL_NOISE_DBM_PER_HZ + 10 * math.log10(if_bandwidth_hz) + noise_figure_db


@lru_cache(maxsize=64)                  # a frame's diagnostic: scipy's lambertw ≈ 5 µs a call
def detection_range_in_weather_m(clear_range_m: float, gamma_db_per_km: float) -> float:
    """Range at which a target detected just at ``clear_range_m`` in clear air is detected in weather: solves
    ``40 log10(R0/R) = 2 γ R / 1000`` (radar equation R⁻⁴ plus two-way loss). With ``k = γ ln 10 / 20000`` per m
    that is ``k R e^{k R} = k R0``, so ``R = W0(k R0) / k`` (Lambert W, principal branch: ``k R0 > 0``)."""
    if gamma_db_per_km <= 0:
        return float(clear_range_m)
    k = gamma_db_per_km * math.log(10.0) / 20000.0
    return float(lambertw(k * clear_range_m).real) / k
