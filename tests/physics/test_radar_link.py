"""Radar link budget oracles (models.md §4.1, §4.2, §8), cross-checked against the itur package (ITU-R P.838-3,
P.840) where it covers the quantity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roadview_noise.physics.radar_link import (
    detection_range_in_weather_m, fog_attenuation_db_per_km, fog_lwc_from_visibility_g_per_m3,
    liquid_water_coefficient_db_per_km_per_g_m3, noise_floor_dbm, p838_coefficients, rain_attenuation_itu_db_per_km,
    rain_attenuation_sander_db_per_km, snow_attenuation_db_per_km, two_way_loss_db, water_permittivity)

itu838 = pytest.importorskip("itur.models.itu838")
itu840 = pytest.importorskip("itur.models.itu840")


def test_p838_at_77ghz_matches_models_md():
    k, a = p838_coefficients(77e9, "horizontal")
    assert k == pytest.approx(1.132, abs=5e-4) and a == pytest.approx(0.7177, abs=5e-5)
    assert rain_attenuation_itu_db_per_km(20.0) == pytest.approx(9.72, rel=1e-3)
    for rate, gamma in [(10, 5.91), (11, 6.33), (25, 11.41), (50, 18.76)]:
        assert rain_attenuation_itu_db_per_km(rate) == pytest.approx(gamma, abs=6e-3)


@pytest.mark.parametrize("f_ghz", [1.0, 5.0, 10.0, 24.0, 35.0, 60.0, 77.0, 79.0, 94.0, 140.0, 300.0, 1000.0])
@pytest.mark.parametrize("pol, tau_deg", [("horizontal", 0.0), ("vertical", 90.0), ("circular", 45.0)])
def test_p838_coefficients_match_itur(f_ghz, pol, tau_deg):
    k_ref, a_ref = itu838.rain_specific_attenuation_coefficients(f_ghz, 0.0, tau_deg)
    k, a = p838_coefficients(f_ghz * 1e9, pol)
    assert k == pytest.approx(float(k_ref), rel=1e-6) and a == pytest.approx(float(a_ref), rel=1e-6)
    ref = itu838.rain_specific_attenuation(20.0, f_ghz, 0.0, tau_deg).value
    assert rain_attenuation_itu_db_per_km(20.0, f_ghz * 1e9, pol) == pytest.approx(float(ref), rel=1e-6)


def test_p838_rejects_out_of_range():
    with pytest.raises(ValueError):
        p838_coefficients(0.5e9)
    with pytest.raises(ValueError):
        p838_coefficients(77e9, "diagonal")


def test_sander_reference_values():
    for rate, gamma in [(10, 5.241), (20, 8.455), (25, 9.862), (50, 15.91)]:
        assert rain_attenuation_sander_db_per_km(rate) == pytest.approx(gamma, rel=1e-3)
    assert rain_attenuation_sander_db_per_km(0.0) == 0.0 and rain_attenuation_itu_db_per_km(0.0) == 0.0


def test_liquid_water_coefficient_oracle_and_itur():
    for t, kl in [(0, 3.537), (10, 3.147), (20, 2.713)]:
        assert liquid_water_coefficient_db_per_km_per_g_m3(77e9, t) == pytest.approx(kl, rel=1e-3)
    for f in (10.0, 35.0, 77.0, 94.0, 200.0):
        for t in (-5.0, 10.0, 25.0):
            ref = float(itu840.specific_attenuation_coefficients(f, t))
            assert liquid_water_coefficient_db_per_km_per_g_m3(f * 1e9, t) == pytest.approx(ref, rel=1e-9)


def test_water_permittivity_limits():
    theta = 300 / 293.15
    static = 77.66 + 103.3 * (theta - 1)
    assert water_permittivity(1e3, 20.0).real == pytest.approx(static, rel=1e-6)   # Debye: ε → ε0 as f → 0
    assert water_permittivity(1e15, 20.0).real == pytest.approx(3.52, rel=1e-6)    # and ε → ε2 as f → ∞
    assert water_permittivity(77e9, 20.0).imag < 0                                 # engineering sign, lossy


def test_ce_fog_lwc_table_and_continuity():
    for v, lwc in [(10, 1.343), (20, 0.670), (30, 0.3747), (50, 0.1323)]:
        assert fog_lwc_from_visibility_g_per_m3(v) == pytest.approx(lwc, rel=1e-3)
    v = np.geomspace(2, 2000, 400)
    lwc = np.array([fog_lwc_from_visibility_g_per_m3(x) for x in v])
    assert np.all(np.diff(lwc) < 0)                                        # denser fog, shorter visibility
    for edge in (10.0, 50.0):                                              # continuous at the table ends
        assert fog_lwc_from_visibility_g_per_m3(edge * (1 - 1e-9)) == pytest.approx(
            fog_lwc_from_visibility_g_per_m3(edge * (1 + 1e-9)), rel=1e-6)
    assert fog_lwc_from_visibility_g_per_m3(100.0) == pytest.approx(0.1323 * 2 ** -1.1407, rel=1e-3)


def test_fog_attenuation_fixes_reference():
    assert fog_attenuation_db_per_km(30.0) == pytest.approx(1.18, abs=2e-3)
    for v, gamma in [(10, 4.23), (20, 2.11), (50, 0.42)]:
        assert fog_attenuation_db_per_km(v) == pytest.approx(gamma, abs=6e-3)
    reference = 0.182 * fog_lwc_from_visibility_g_per_m3(30.0) * 77 ** 2  # the reference's coefficient
    assert reference == pytest.approx(404.3, rel=1e-3)
    assert 300 < reference / fog_attenuation_db_per_km(30.0) < 380


def test_snow_linear_law():
    assert snow_attenuation_db_per_km(2.5) == pytest.approx(2.051, rel=1e-3)
    assert snow_attenuation_db_per_km(3.03) == pytest.approx(2.486, rel=1e-3)


def test_two_way_loss_oracles():
    assert two_way_loss_db(rain_attenuation_itu_db_per_km(20.0), 100.0) == pytest.approx(1.94, abs=5e-3)
    assert two_way_loss_db(rain_attenuation_sander_db_per_km(20.0), 100.0) == pytest.approx(1.69, abs=5e-3)
    assert two_way_loss_db(fog_attenuation_db_per_km(30.0), 100.0) == pytest.approx(0.24, abs=5e-3)
    np.testing.assert_allclose(two_way_loss_db(5.0, [0.0, 1000.0]), [0.0, 10.0])


def test_noise_floor():
    assert noise_floor_dbm(1.0, 0.0) == pytest.approx(-174.0)
    assert noise_floor_dbm(20e6, 12.0) == pytest.approx(-174 + 10 * math.log10(20e6) + 12)


def test_detection_range_in_weather_solves_radar_equation():
    r0 = 200.0
    assert detection_range_in_weather_m(r0, 0.0) == r0
    ranges = [detection_range_in_weather_m(r0, g) for g in (1.0, 5.0, 9.72, 20.0)]
    assert all(a > b for a, b in zip(ranges, ranges[1:]))
    for g, r in zip((1.0, 5.0, 9.72, 20.0), ranges):
        assert 40 * math.log10(r0 / r) == pytest.approx(2 * g * r / 1000, abs=1e-6)


def test_detection_range_in_weather_matches_a_bracketing_root_finder():
    """The Lambert-W closed form against scipy's brentq on the same equation, over 8 decades of attenuation."""
    from scipy.optimize import brentq

    for r0 in (3.0, 200.0, 1000.0):
        for g in (1e-6, 1e-3, 1.17, 30.0, 1e3, 1e4):
            f = lambda r: 40 * math.log10(r0 / r) - 2 * g * r / 1000
            root = brentq(f, r0 * 1e-12, r0, xtol=1e-14 * r0, rtol=1e-15)
            assert detection_range_in_weather_m(r0, g) == pytest.approx(root, rel=1e-12)
