"""Snow at trace rates (physics/dsd.py, ``TRACE_SNOW_SLOPE_PER_MM``; issue 14: continuous at zero strength): below
about 0.2 mm/h the exponential laws' slope stays where their mean crystal mass is the 18.5 µg that Gunn (1965)
measured to be independent of the rate, so the number of flakes, α and the mass flux go to zero with S; above it
the laws are untouched (every D3.5 rate). Oracles: Gunn's number-flux locus, Warner & Gunn's (1969) attenuation per
unit rate, the mass flux by quad, and the LiDAR's changed points on a synthetic Velodyne-like scan and the real
scans (skipped when absent)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate

from roadview_noise.compound import apply_models
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.models.lidar.snow import SnowLidar
from roadview_noise.physics import dsd
from roadview_noise.profiles.lidar import kitti_hdl64, load_lidar_profile, os1_128
from tests.models.test_lidar_real_scan import changed, scan
from tests.physics.test_firing_grid_laser_order import kitti_scan
from tests.physics.test_snow import _flake_mm

HABITS = sorted(dsd.SNOW_HABITS)
LAWS = sorted(dsd.SNOW_LAWS)
TRACE_RATES = (1e-5, 1e-4, 1e-3, 0.01, 0.1)
D35_RATES = (0.25, 0.5, 0.835, 2.5, 3.03)          # D3.5 / models.md validation and CNF rates (mm/h)
GUNN_NUMBER_FLUX_PER_CM2_S_PER_MM_H = 1.5         # Gunn (1965): R/m̄ = 1.5 R cm⁻² s⁻¹, R in mm/h of water
WARNER_GUNN_PER_M_PER_MM_H = 11.0 / (10 * math.log10(math.e)) / 1e3     # 11 dB/km per mm/h → m⁻¹ per mm/h
KITTI_DEMO = Path("/work/realdata/mmdet3d/demo/data/kitti/000008.bin")
SLOPE_LAWS = {"gunn_marshall": (2.55, 0.48), "sekhon_srivastava": (2.29, 0.45)}    # Λ = c S^−e (mm⁻¹, S in mm/h)


def crossover_mm_per_h(law: str) -> float:
    """The rate at which the published slope reaches the cap."""
    c, e = SLOPE_LAWS[law]
    return (c / dsd.TRACE_SNOW_SLOPE_PER_MM) ** (1 / e)


def test_slope_cap_is_gunns_mean_crystal_mass():
    """Gunn's locus: a mass flux of R mm/h of water (R · 0.1 cm / 3600 s · 1 g cm⁻³) carried by 1.5 R crystals
    cm⁻² s⁻¹ is m̄ = 18.5 µg per crystal; the exponential in melted diameter whose mean crystal mass (quad) is m̄."""
    m_g = 0.1 / 3600 / GUNN_NUMBER_FLUX_PER_CM2_S_PER_MM_H
    lam = dsd.TRACE_SNOW_SLOPE_PER_MM
    mean_mass = (integrate.quad(lambda d: 1e-3 * math.pi / 6 * d ** 3 * math.exp(-lam * d), 0, 50)[0]
                 / integrate.quad(lambda d: math.exp(-lam * d), 0, 50)[0])
    assert mean_mass == pytest.approx(m_g, rel=1e-6) and m_g == pytest.approx(18.5e-6, rel=2e-3)
    crossover = {law: crossover_mm_per_h(law) for law in LAWS}
    assert crossover["gunn_marshall"] == pytest.approx(0.199, abs=1e-3)
    assert crossover["sekhon_srivastava"] == pytest.approx(0.141, abs=1e-3)
    assert max(crossover.values()) < min(D35_RATES)


@pytest.mark.parametrize("law", LAWS)
def test_the_fitted_range_is_untouched(law):
    """From the crossover up (every D3.5 rate) the slope is the published law's, bit for bit."""
    for rate in (0.2, *D35_RATES, 8.0):
        for habit in HABITS:
            assert dsd.snowfall(rate, law, habit).lam_per_mm == dsd.SNOW_LAWS[law](rate)[1]


@pytest.mark.parametrize("habit", HABITS)
@pytest.mark.parametrize("law", LAWS)
def test_trace_snow_scales_with_the_rate(law, habit):
    """Below the crossover: the same flakes, their number, α and N0 ∝ S (so all → 0 with S); the mass flux
    ∫ (π/6) D_m³ v(D) N dD_m by quad equals S within 1 % at every rate; continuous across the crossover."""
    ref = dsd.snowfall(0.1, law, habit)
    for rate in TRACE_RATES:
        snow = dsd.snowfall(rate, law, habit)
        assert snow.lam_per_mm == dsd.TRACE_SNOW_SLOPE_PER_MM
        k = rate / 0.1
        assert snow.n0_per_m3_mm == pytest.approx(k * ref.n0_per_m3_mm, rel=1e-12)
        assert snow.number_per_m3() == pytest.approx(k * ref.number_per_m3(), rel=1e-12)
        assert snow.extinction_per_m() == pytest.approx(k * ref.extinction_per_m(), rel=1e-12)
        h = snow.habit
        flux = integrate.quad(lambda dm: math.pi / 6 * (dm * 1e-3) ** 3 * h.fall_speed_coefficient_m_per_s
                              * _flake_mm(dm, habit) ** h.fall_speed_exponent * snow.n0_per_m3_mm
                              * math.exp(-snow.lam_per_mm * dm), snow.d_min_mm, snow.d_max_mm, limit=200)[0]
        assert flux * 3.6e6 == pytest.approx(rate, rel=0.01)
    s_star = crossover_mm_per_h(law)
    assert dsd.SNOW_LAWS[law](s_star)[1] == pytest.approx(dsd.TRACE_SNOW_SLOPE_PER_MM, rel=1e-12)
    below, above = (dsd.snowfall(s_star * f, law, habit) for f in (1 - 1e-7, 1 + 1e-7))
    assert above.extinction_per_m() == pytest.approx(below.extinction_per_m(), rel=1e-5)
    assert above.number_per_m3() == pytest.approx(below.number_per_m3(), rel=1e-5)


@pytest.mark.parametrize("habit", HABITS)
def test_trace_snow_matches_the_measured_fluxes(habit):
    """The crystals reaching the ground, ∫ v N dD_m (quad), lie within Gunn's factor 2 of his 1.5 S cm⁻² s⁻¹
    (dry aggregates 0.70×: the fall speed weights the heavier crystals); the extinction per unit rate within a
    factor 2.5 of Warner & Gunn's transmissometer, 11 dB/km per mm/h (dry 2.2×, rimed 1.3×, wet 0.44×: a
    transmissometer also receives some of the forward-scattered light, Q_ext = 2 counts it as lost)."""
    rate = 1e-3
    snow = dsd.snowfall(rate, habit=habit)
    h = snow.habit
    number_flux_m2_s = integrate.quad(lambda dm: h.fall_speed_coefficient_m_per_s
                                      * _flake_mm(dm, habit) ** h.fall_speed_exponent * snow.n0_per_m3_mm
                                      * math.exp(-snow.lam_per_mm * dm), snow.d_min_mm, snow.d_max_mm, limit=200)[0]
    ratio = number_flux_m2_s * 1e-4 / (GUNN_NUMBER_FLUX_PER_CM2_S_PER_MM_H * rate)
    assert 0.5 <= ratio <= 2.0
    assert 1 / 2.5 <= snow.extinction_per_m() / rate / WARNER_GUNN_PER_M_PER_MM_H <= 2.5


def _changed_points(cloud, rates, seeds):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.array([sum(changed(cloud, apply_models([SnowLidar(snowfall_rate_mm_per_h=r)], cloud, seed=s,
                                                         key="k", sequence_id="s", metrics=False)[0])
                             for s in seeds) for r in rates])


def _assert_monotone(counts):
    """Non-decreasing within the Poisson noise of the counts (3 standard deviations)."""
    for lo, hi in zip(counts[:-1], counts[1:]):
        assert hi >= lo - 3 * math.sqrt(lo) - 2, counts


def test_velodyne_like_scan_goes_to_the_input():
    """Synthetic KITTI-order HDL-64E scan (117 k points, datasheet threshold), two seeds: the changed points grow
    monotonically with the rate from 10⁻⁵ to 1 mm/h, in proportion to S below the crossover, and at 0.001 mm/h are
    0.21 % (the extrapolated law: 0.30 %; issue 14's 0.1 % is not reached: each of Gunn's ~18 crystals per m³ is seen
    by the beam within a few metres)."""
    cloud, *_ = kitti_scan(0)
    rates = (1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 0.01, 0.03, 0.1, 0.3, 1.0)
    counts = _changed_points(cloud, rates, (1, 2))
    _assert_monotone(counts)
    per_rate = counts[:6] / np.array(rates[:6])
    assert np.all(np.abs(per_rate[2:] / per_rate[4] - 1) < 0.5), per_rate      # flakes ∝ S (noise aside) up to 3e-3
    assert counts[0] <= 2e-4 * 2 * len(cloud) and counts[4] < 0.003 * 2 * len(cloud)


def test_real_scans_go_to_the_input(shared_data):
    """The real OS1-128 scan as reflectivity (built-in profile and the unit's JSON metadata) and as photons, and
    mmdet3d's KITTI 000008 crop when present: monotone in the rate and ∝ S below the crossover; < 0.02 % changed at
    10⁻⁵ mm/h. At 0.001 mm/h 0.60 % / 0.57 % (Ouster reflectivity / photons) and 0.22 % (KITTI) — issue 14's 0.1 %
    is not met (see README, "Snow at trace rates")."""
    clouds = [scan(shared_data), scan(shared_data, load_lidar_profile(str(shared_data / "os1-128" /
                                                                          "beam_intrinsics.json"))),
              scan(shared_data, os1_128())]
    if KITTI_DEMO.is_file():
        clouds.append(read_pointcloud(KITTI_DEMO, profile=kitti_hdl64()))
    rates = (1e-5, 1e-4, 1e-3, 1e-2, 0.1, 1.0)
    for cloud in clouds:
        counts = _changed_points(cloud, rates, (3,))
        _assert_monotone(counts)
        assert counts[0] < 2e-4 * len(cloud)
        assert 4 <= counts[2] / max(counts[1], 1) <= 25, counts
