"""Particle size distributions of rain, snow and fog (models.md §0.1, §2.1–§2.3, §3.3–§3.4).

Rain/snow: per unit diameter, D in mm, N(D) in m⁻³ mm⁻¹. Fog: per unit radius, r in µm, n(r) in cm⁻³ µm⁻¹.
Exponential laws have closed-form moments, so no grid integration is needed on hot paths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import gamma as gamma_fn
from scipy.special import gammainc

from .fall_speed import snow_power_law_m_per_s

# --- exponential laws N(D) = N0 exp(-Λ D) ------------------------------------------------------------------------

MARSHALL_PALMER_N0_PER_M3_MM = 8000.0


def marshall_palmer(rain_rate_mm_per_h: float) -> tuple[float, float]:
    """Marshall & Palmer (1948): ``(N0 [m⁻³ mm⁻¹], Λ [mm⁻¹])`` with ``Λ = 4.1 R^−0.21``."""
    if rain_rate_mm_per_h <= 0:
        raise ValueError(f"rain rate must be > 0 mm/h, got {rain_rate_mm_per_h}")
    return MARSHALL_PALMER_N0_PER_M3_MM, 4.1 * rain_rate_mm_per_h ** -0.21


def gunn_marshall(snowfall_rate_mm_per_h: float) -> tuple[float, float]:
    """Gunn & Marshall (1958) snow, liquid-equivalent rate S: ``N0 = 3.8e3 S^−0.87``, ``Λ = 2.55 S^−0.48``."""
    s = snowfall_rate_mm_per_h
    if s <= 0:
        raise ValueError(f"snowfall rate must be > 0 mm/h, got {s}")
    return 3.8e3 * s ** -0.87, 2.55 * s ** -0.48


def sekhon_srivastava(snowfall_rate_mm_per_h: float) -> tuple[float, float]:
    """Sekhon & Srivastava (1970) snow: ``N0 = 2.5e3 S^−0.94``, ``Λ = 2.29 S^−0.45`` (S liquid equivalent)."""
    s = snowfall_rate_mm_per_h
    if s <= 0:
        raise ValueError(f"snowfall rate must be > 0 mm/h, got {s}")
    return 2.5e3 * s ** -0.94, 2.29 * s ** -0.45


SNOW_LAWS = {"gunn_marshall": gunn_marshall, "sekhon_srivastava": sekhon_srivastava}

#: Trace snow (Gunn 1965, McGill Stormy Weather Group, "Measurements on new-fallen snow", DTIC AD0621153): over a
#: season of Montreal snowfalls the number of crystals reaching the ground is proportional to the rate, R/m̄ =
#: 1.5 R cm⁻² s⁻¹ (R in mm/h of water; two thirds of the samples within a factor 2): a mean mass per crystal
#: m̄ = 18.5 µg whatever the rate. The optical attenuation by falling snow is proportional to the rate as well
#: (Warner & Gunn 1969, J. Appl. Meteor. 8: 11 dB/km per mm/h at 0.45 µm, 20 storms). Extrapolated to trace rates,
#: the exponential laws' Λ ∝ S^−0.48 instead give ever more, ever lighter crystals (6.1e4 m⁻³ of mean melted
#: diameter 0.014 mm at 0.001 mm/h; ASSUMPTION, not checked against the papers here: their fits rest on snowfalls
#: of tenths of a mm/h and more). Their slope is therefore capped where their mean crystal mass ``π ρ_w / Λ³``
#: (melted spheres) falls to m̄: Λ = (π · 1e-3 g mm⁻³ / m̄)^{1/3} = 5.536 mm⁻¹, reached at 0.199 mm/h
#: (Gunn–Marshall) and 0.141 mm/h (Sekhon–Srivastava), below every D3.5 rate. Lighter snowfalls are fewer crystals
#: of that kind (18 m⁻³ at 0.001 mm/h).
TRACE_SNOW_CRYSTAL_MASS_G = 0.1 / 3600 / 1.5      # 1 mm/h of water = 0.1/3600 g cm⁻² s⁻¹, over 1.5 crystals cm⁻² s⁻¹
TRACE_SNOW_SLOPE_PER_MM = (math.pi * 1e-3 / TRACE_SNOW_CRYSTAL_MASS_G) ** (1 / 3)


def capped_snow_law(snowfall_rate_mm_per_h: float, law: str = "gunn_marshall") -> tuple[float, float]:
    """``(N0, Λ)`` of a snow law (:data:`SNOW_LAWS`) with its slope capped at :data:`TRACE_SNOW_SLOPE_PER_MM`: the
    law's own values down to the rate S_c where it reaches the cap; below, the same flakes (Λ at the cap) with their
    number ∝ S, ``N0 = N0(S_c) · S / S_c`` (continuous at S_c; the radar's snow, whose N0 is the law's)."""
    n0, lam = SNOW_LAWS[law](snowfall_rate_mm_per_h)
    if lam <= TRACE_SNOW_SLOPE_PER_MM:
        return n0, lam
    from scipy.optimize import brentq       # here only: below every D3.5 rate (≈ 0.2 s of each process's start-up)

    s_c = brentq(lambda s: math.log(SNOW_LAWS[law](s)[1] / TRACE_SNOW_SLOPE_PER_MM), snowfall_rate_mm_per_h, 1e3,
                 xtol=1e-15, rtol=1e-14)
    return SNOW_LAWS[law](s_c)[0] * snowfall_rate_mm_per_h / s_c, TRACE_SNOW_SLOPE_PER_MM


def exponential_moment(n0: float, lam: float, k: int, d_min_mm, d_max_mm):
    """``∫_{Dmin}^{Dmax} D^k N0 e^{−ΛD} dD`` in m⁻³ mm^k (closed form via the regularised incomplete gamma); float
    for scalar bounds, elementwise for arrays."""
    full = n0 * gamma_fn(k + 1) / lam ** (k + 1)
    moment = full * (gammainc(k + 1, np.multiply(lam, d_max_mm)) - gammainc(k + 1, np.multiply(lam, d_min_mm)))
    return float(moment) if np.ndim(moment) == 0 else moment


def exponential_number_density(n0: float, lam: float, d_min_mm: float, d_max_mm: float) -> float:
    """Particles per m³ with diameters in [Dmin, Dmax] mm."""
    return n0 / lam * (math.exp(-lam * d_min_mm) - math.exp(-lam * d_max_mm))


def geometric_extinction_per_m(n0: float, lam: float, d_min_mm: float, d_max_mm: float,
                               q_ext: float = 2.0) -> float:
    """Optical extinction of large particles, ``α = (π/4) Q_ext ∫ D² N(D) dD`` in m⁻¹ (D² in mm² → 1e-6 m²).

    Geometric-optics limit Q_ext = 2 (models.md §3.3, Appendix A): error < 2 % for every raindrop/flake at
    visible and 865 nm wavelengths."""
    return math.pi / 4 * q_ext * exponential_moment(n0, lam, 2, d_min_mm, d_max_mm) * 1e-6


def liquid_water_content_g_per_m3(n0: float, lam: float, d_min_mm: float, d_max_mm: float) -> float:
    """``LWC = ρ_w (π/6) ∫ D³ N dD`` for liquid-equivalent spheres (ρ_w = 1e6 g/m³, D³ in mm³ → 1e-9 m³)."""
    return 1e6 * math.pi / 6 * exponential_moment(n0, lam, 3, d_min_mm, d_max_mm) * 1e-9


def sample_truncated_exponential(rng: np.random.Generator, lam: float, d_min_mm: float, d_max_mm: float,
                                 size: int) -> np.ndarray:
    """Diameters (mm) by inverse CDF of ``e^{−ΛD}`` truncated to [Dmin, Dmax] (models.md §3.3 correct version);
    the bounds may be arrays broadcastable to ``size``."""
    u = rng.random(size)
    span = -np.expm1(-lam * (np.asarray(d_max_mm, dtype=float) - np.asarray(d_min_mm, dtype=float)))
    return d_min_mm - np.log1p(-u * span) / lam



# --- optical size of a particle from its melted size ----------------------------------------------------------------

ICE_DENSITY_G_PER_CM3 = 0.917
WATER_DENSITY_G_PER_CM3 = 1.0


@dataclass(frozen=True)
class SizeLaw:
    """Geometric (optical) diameter D of a particle of melted (liquid-equivalent) diameter D_m, both in mm:
    ``D = max(k D_m, c D_m^p)`` — a power law from a density–size relation ``ρ = a D^b`` (mass conservation
    ``ρ_w D_m³ = ρ(D) D³`` gives ``c = (ρ_w/a)^{1/(3+b)}``, ``p = 3/(3+b)``), never denser than ``ρ_max``
    (``k = (ρ_w/ρ_max)^{1/3}``). The default is the identity (raindrops)."""

    coefficient: float = 1.0
    exponent: float = 1.0
    solid: float = 1.0

    @classmethod
    def of_density(cls, a_g_per_cm3: float, b: float, max_density_g_per_cm3: float = ICE_DENSITY_G_PER_CM3
                   ) -> SizeLaw:
        """From ``ρ(D) = a D^b`` g/cm³ (D in mm), capped at ``max_density_g_per_cm3``."""
        return cls((WATER_DENSITY_G_PER_CM3 / a_g_per_cm3) ** (1 / (3 + b)), 3 / (3 + b),
                   (WATER_DENSITY_G_PER_CM3 / max_density_g_per_cm3) ** (1 / 3))

    @property
    def crossover_mm(self) -> float:
        """Melted diameter above which the power law holds (``k D_m = c D_m^p``); 0 when it holds everywhere."""
        if self.exponent == 1.0:
            return 0.0 if self.coefficient >= self.solid else math.inf
        return (self.solid / self.coefficient) ** (1 / (self.exponent - 1))

    def optical_mm(self, d_melted_mm):
        d = np.asarray(d_melted_mm, dtype=float)
        return np.maximum(self.solid * d, self.coefficient * d ** self.exponent)

    def melted_mm(self, d_optical_mm):
        d = np.asarray(d_optical_mm, dtype=float)
        return np.minimum(d / self.solid, (d / self.coefficient) ** (1 / self.exponent))

    def moment(self, n0: float, lam: float, k_optical: float, d_min_mm, d_max_mm, k_melted: float = 0.0):
        """``∫ D^k_optical D_m^k_melted N0 e^{−Λ D_m} dD_m`` over melted diameters [Dmin, Dmax] (closed form per piece
        of the law, :func:`exponential_moment`; elementwise for array bounds)."""
        x = self.crossover_mm
        lo, hi = np.asarray(d_min_mm, dtype=float), np.asarray(d_max_mm, dtype=float)
        solid_hi = np.clip(hi, lo, x)
        power_lo = np.clip(lo, x, np.maximum(hi, x))
        out = (self.coefficient ** k_optical
               * exponential_moment(n0, lam, self.exponent * k_optical + k_melted, power_lo, np.maximum(hi, power_lo)))
        if x > 0:
            out = out + self.solid ** k_optical * exponential_moment(n0, lam, k_optical + k_melted, lo, solid_hi)
        return float(out) if np.ndim(out) == 0 else out


# --- snowflakes (models.md §2.3 correction, §3.4) -------------------------------------------------------------------


@dataclass(frozen=True)
class SnowHabit:
    """What kind of snow falls: bulk density ``ρ = a D^b`` (g/cm³, D the flake diameter in mm, at most
    ``max_density``) and fall speed ``v = a_v D^b_v`` (m/s)."""

    density_coefficient_g_per_cm3: float
    density_exponent: float
    fall_speed_coefficient_m_per_s: float
    fall_speed_exponent: float
    max_density_g_per_cm3: float
    source: str

    @property
    def size(self) -> SizeLaw:
        return SizeLaw.of_density(self.density_coefficient_g_per_cm3, self.density_exponent,
                                  self.max_density_g_per_cm3)

    def fall_speed_m_per_s(self, d_mm):
        """Terminal speed of flakes of diameter D (mm); float32 stays float32."""
        return snow_power_law_m_per_s(d_mm, self.fall_speed_coefficient_m_per_s, self.fall_speed_exponent)


SNOW_HABITS = {
    "dry_aggregates": SnowHabit(0.178, -0.922, 0.8, 0.16, ICE_DENSITY_G_PER_CM3,
                                "density Brandes et al. 2007 (J. Appl. Meteor. Climatol. 46), fall speed Locatelli & "
                                "Hobbs 1974 (unrimed aggregates)"),
    "rimed": SnowHabit(0.356, -0.922, 0.79, 0.27, ICE_DENSITY_G_PER_CM3,
                       "fall speed Locatelli & Hobbs 1974 (densely rimed aggregates); ASSUMPTION: riming doubles the "
                       "density of Brandes et al. 2007"),
    "wet": SnowHabit(0.712, -0.922, 1.5, 0.0, WATER_DENSITY_G_PER_CM3,
                     "ASSUMPTION: melting aggregates four times as dense as Brandes et al. 2007 (at most water), "
                     "falling at 1.5 m/s (melting flakes: 1–2 m/s)"),
}


@dataclass(frozen=True)
class Snowfall:
    """Falling snow at a liquid-equivalent rate S: an exponential law ``N0 e^{−Λ D_m}`` in *melted* diameter D_m
    (Λ from Gunn–Marshall or Sekhon–Srivastava, at most :data:`TRACE_SNOW_SLOPE_PER_MM`), flakes of geometric
    diameter ``D = size(D_m)`` from the habit's density–size law (models.md §2.3 correction), each falling at the
    habit's ``v(D)``, and N0 such that the liquid-equivalent mass flux ``∫ (π/6) D_m³ v(D) N dD_m`` equals S. One
    distribution for camera and LiDAR.

    ``d_min_mm``, ``d_max_mm``: bounds in melted diameter (mm)."""

    n0_per_m3_mm: float
    lam_per_mm: float
    d_min_mm: float
    d_max_mm: float
    habit: SnowHabit

    @property
    def size(self) -> SizeLaw:
        return self.habit.size

    def number_per_m3(self) -> float:
        return exponential_number_density(self.n0_per_m3_mm, self.lam_per_mm, self.d_min_mm, self.d_max_mm)

    def flake_density(self, d_mm):
        """Flakes per m³ and mm of flake diameter D: ``N(D_m(D)) dD_m/dD`` (m⁻³ mm⁻¹)."""
        d = np.asarray(d_mm, dtype=float)
        law = self.size
        dm = law.melted_mm(d)
        with np.errstate(divide="ignore", invalid="ignore"):
            slope = np.where(d / law.solid <= (d / law.coefficient) ** (1 / law.exponent), 1 / law.solid,
                             dm / (law.exponent * d))
        inside = (dm >= self.d_min_mm) & (dm <= self.d_max_mm)
        return np.where(inside, self.n0_per_m3_mm * np.exp(-self.lam_per_mm * dm) * slope, 0.0)

    def extinction_per_m(self, q_ext: float = 2.0) -> float:
        """``α = (π/4) Q_ext ∫ D² N dD_m`` (geometric optics: Q_ext = 2, flakes ≫ λ)."""
        return math.pi / 4 * q_ext * 1e-6 * self.size.moment(self.n0_per_m3_mm, self.lam_per_mm, 2, self.d_min_mm,
                                                             self.d_max_mm)

    def visibility_m(self) -> float:
        """Meteorological optical range ``ln 20 / α`` (5 % contrast, WMO)."""
        return math.log(20.0) / self.extinction_per_m()

    def mass_flux_mm_per_h(self) -> float:
        """Liquid-equivalent precipitation rate ``∫ (π/6) D_m³ v(D) N dD_m`` (mm/h)."""
        return _flux_per_n0(self.habit, self.lam_per_mm, self.d_min_mm, self.d_max_mm) * self.n0_per_m3_mm * 3.6e6


def _flux_per_n0(habit: SnowHabit, lam: float, d_min_mm: float, d_max_mm: float) -> float:
    """Liquid-equivalent flux (m/s) of ``e^{−Λ D_m}`` (N0 = 1 m⁻³ mm⁻¹): ``(π/6) 10⁻⁹ a_v ∫ D_m³ D^b_v e^{−Λ D_m}``."""
    return (math.pi / 6 * 1e-9 * habit.fall_speed_coefficient_m_per_s
            * habit.size.moment(1.0, lam, habit.fall_speed_exponent, d_min_mm, d_max_mm, k_melted=3))


def snowfall(rate_mm_per_h: float, law: str = "gunn_marshall", habit: str = "dry_aggregates",
             d_min_flake_mm: float = 0.0, d_max_flake_mm: float = 20.0) -> Snowfall:
    """The :class:`Snowfall` of a liquid-equivalent rate (mm/h): Λ from ``law`` (:data:`SNOW_LAWS`), at most
    :data:`TRACE_SNOW_SLOPE_PER_MM`, flakes from ``habit`` (:data:`SNOW_HABITS`) between the flake diameters given
    (mm), N0 from the mass flux — so in trace snow (below 0.2 mm/h) the flakes keep their sizes while their number,
    α and the mass flux scale with S and go to zero with it."""
    if habit not in SNOW_HABITS:
        raise ValueError(f"unknown snow habit {habit!r}; one of {sorted(SNOW_HABITS)}")
    lam = min(SNOW_LAWS[law](rate_mm_per_h)[1], TRACE_SNOW_SLOPE_PER_MM)
    h = SNOW_HABITS[habit]
    lo, hi = float(h.size.melted_mm(d_min_flake_mm)), float(h.size.melted_mm(d_max_flake_mm))
    return Snowfall(rate_mm_per_h / 3.6e6 / _flux_per_n0(h, lam, lo, hi), lam, lo, hi, h)

# --- measured gamma snow table (Brandes et al. 2007) ----------------------------------------------------------------

BRANDES_SNOW_GAMMA = {  # liquid-equivalent S (mm/h) → (N0 [m⁻³ mm^(−1−μ)], μ, Λ [mm⁻¹]), models.md §2.3
    3.03: (2.33e4, 1.23, 2.25),
    2.70: (1.39e3, -0.90, 1.40),
    2.59: (7.18e1, -0.78, 0.35),
}


def gamma_dsd(d_mm: np.ndarray, n0: float, mu: float, lam: float) -> np.ndarray:
    """``N(D) = N0 D^μ e^{−ΛD}`` in m⁻³ mm⁻¹."""
    d = np.asarray(d_mm, dtype=float)
    return n0 * d ** mu * np.exp(-lam * d)


# --- fog: log-normal CE chamber distributions (models.md §2.1) ---------------------------------------------------

CE_FOG_LOGNORMAL = {  # visibility (m) → (N [cm⁻³], s, μ = ln r̃ with r̃ in µm)
    10.0: (6108.486, 0.74651233, 0.484235252),
    20.0: (3559.641, 0.777099786, 0.362382125),
    30.0: (2754.154, 0.742155699, 0.334042672),
    50.0: (3189.711, 0.656240841, 0.118386081),
}


def lognormal_fog(r_um: np.ndarray, n_cm3: float, s: float, mu: float) -> np.ndarray:
    """``n(r) = N/(r s √(2π)) exp(−(ln r − μ)²/(2 s²))`` in cm⁻³ µm⁻¹ (r in µm)."""
    r = np.asarray(r_um, dtype=float)
    return n_cm3 / (r * s * math.sqrt(2 * math.pi)) * np.exp(-((np.log(r) - mu) ** 2) / (2 * s * s))


def lognormal_fog_lwc_g_per_m3(n_cm3: float, s: float, mu: float) -> float:
    """``LWC = (4/3)π ρ_w N r̃³ exp(9 s²/2)``: N cm⁻³ → m⁻³ (1e6), r̃ µm → m (1e-6), ρ_w = 1e6 g/m³."""
    return 4 / 3 * math.pi * 1e6 * n_cm3 * 1e6 * (math.exp(mu) * 1e-6) ** 3 * math.exp(4.5 * s * s)
