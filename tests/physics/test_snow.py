"""Snowflakes of geometric size (physics/dsd.py, models.md §2.3 correction): the density–size law, the mass flux
``∫ m v N dD = S`` and the meteorological visibility, against integrals written out here independently."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, optimize

from roadview_noise.physics import dsd

HABITS = sorted(dsd.SNOW_HABITS)


def _flake_mm(d_melted, habit):
    """Flake diameter from mass conservation ρ_w D_m³ = ρ(D) D³, ρ(D) = a D^b, at most the habit's maximum density
    (solved with brentq, not with the closed form of the module)."""
    h = dsd.SNOW_HABITS[habit]
    rho = lambda d: min(h.density_coefficient_g_per_cm3 * d ** h.density_exponent, h.max_density_g_per_cm3)  # noqa
    return optimize.brentq(lambda d: rho(d) * d ** 3 - d_melted ** 3, d_melted * 0.99, d_melted * 100 + 1)


@pytest.mark.parametrize("habit", HABITS)
def test_size_law_conserves_mass_and_inverts(habit):
    law = dsd.SNOW_HABITS[habit].size
    for dm in (0.02, 0.1, 0.3, 1.0, 2.5, 5.0):
        d = float(law.optical_mm(dm))
        assert d == pytest.approx(_flake_mm(dm, habit), rel=1e-7)
        assert float(law.melted_mm(d)) == pytest.approx(dm, rel=1e-12)
    assert dsd.SizeLaw().optical_mm(1.7) == 1.7 and dsd.SizeLaw().crossover_mm == 0.0      # raindrops


def test_brandes_flake_of_one_melted_millimetre():
    """Dry aggregates: ρ = 0.178 D^−0.922 (Brandes et al. 2007) ⇒ D = (D_m³/0.178)^(1/2.078) = 2.295 mm."""
    assert float(dsd.SNOW_HABITS["dry_aggregates"].size.optical_mm(1.0)) == pytest.approx(2.2947, abs=1e-4)


@pytest.mark.parametrize("habit", HABITS)
@pytest.mark.parametrize("law", sorted(dsd.SNOW_LAWS))
@pytest.mark.parametrize("rate", [0.3, 1.0, 2.5, 8.0])
def test_liquid_equivalent_mass_flux_equals_the_rate(rate, law, habit):
    """∫ (π/6) D_m³ ρ_w v(D) N(D_m) dD_m = S within 1 % (quad over the melted diameters, fall speed of the flake)."""
    snow = dsd.snowfall(rate, law, habit)
    h = dsd.SNOW_HABITS[habit]

    def integrand(dm):
        v = h.fall_speed_coefficient_m_per_s * _flake_mm(dm, habit) ** h.fall_speed_exponent
        return math.pi / 6 * (dm * 1e-3) ** 3 * v * snow.n0_per_m3_mm * math.exp(-snow.lam_per_mm * dm)

    flux = integrate.quad(integrand, snow.d_min_mm, snow.d_max_mm, limit=200, points=[0.2, 1.0])[0]   # m/s of water
    assert flux * 3.6e6 == pytest.approx(rate, rel=0.01)
    assert snow.mass_flux_mm_per_h() == pytest.approx(rate, rel=1e-9)
    assert snow.lam_per_mm == dsd.SNOW_LAWS[law](rate)[1]


def test_heavy_snow_visibility_oracle():
    """2.5 mm/h liquid equivalent (heavy snow, US NWS), dry aggregates: meteorological visibility ln 20/α in
    [0.3, 1.2] km (Rasmussen et al. 1999), α = (π/4) 2 ∫ D² N dD_m by quad; the melted-drop model gave 2.5 km."""
    snow = dsd.snowfall(2.5)
    alpha = integrate.quad(lambda dm: math.pi / 2 * (_flake_mm(dm, "dry_aggregates") * 1e-3) ** 2
                           * snow.n0_per_m3_mm * math.exp(-snow.lam_per_mm * dm), 0.0, snow.d_max_mm,
                           limit=200)[0]
    assert snow.extinction_per_m() == pytest.approx(alpha, rel=1e-4)
    assert 300.0 <= math.log(20) / alpha <= 1200.0
    assert snow.visibility_m() == pytest.approx(318.5, abs=0.5)
    melted = dsd.geometric_extinction_per_m(*dsd.gunn_marshall(2.5), 0.0, 50.0)
    assert math.log(20) / melted == pytest.approx(2468, rel=1e-3)


def test_habits_span_the_documented_spread():
    """Heavier flakes are smaller and fall faster: rimed and wet snow of the same liquid-equivalent rate see
    farther (Rasmussen et al. 1999: a factor 3–10 between storms)."""
    vis = {h: dsd.snowfall(2.5, habit=h).visibility_m() for h in HABITS}
    assert vis["dry_aggregates"] < vis["rimed"] < vis["wet"]
    assert 3 <= vis["wet"] / vis["dry_aggregates"] <= 10


def test_flake_density_integrates_to_the_number_of_flakes():
    snow = dsd.snowfall(1.0)
    d_lo, d_hi = (float(snow.size.optical_mm(d)) for d in (snow.d_min_mm, snow.d_max_mm))
    n = integrate.quad(snow.flake_density, d_lo, d_hi, limit=400, points=[0.1, 0.2, 1.0])[0]
    assert n == pytest.approx(snow.number_per_m3(), rel=1e-4)
    assert float(snow.flake_density(d_hi * 1.5)) == 0.0


def test_flux_fixes_n0_close_to_gunn_marshall():
    """The mass-flux N0 with dry aggregates is within 10 % of Gunn & Marshall's fitted intercept at 1–5 mm/h:
    their distribution and these flakes carry about the snowfall they were measured with."""
    for rate in (1.0, 2.5, 5.0):
        assert dsd.snowfall(rate).n0_per_m3_mm == pytest.approx(dsd.gunn_marshall(rate)[0], rel=0.1)


def test_flake_bounds_are_geometric():
    snow = dsd.snowfall(2.5, d_min_flake_mm=1.0, d_max_flake_mm=10.0)
    assert float(snow.size.optical_mm(snow.d_min_mm)) == pytest.approx(1.0)
    assert float(snow.size.optical_mm(snow.d_max_mm)) == pytest.approx(10.0)
    assert np.isclose(snow.mass_flux_mm_per_h(), 2.5)
