"""Precipitation backscatter and clutter generator (models.md §4.3): η oracles, Doppler of falling drops,
cell Doppler spectra and the expected clutter count."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, stats

from roadview_noise.physics.dsd import SNOW_LAWS, TRACE_SNOW_SLOPE_PER_MM
from roadview_noise.physics.radar_cfar import CaCfar, FixedThreshold, ca_cfar_multiplier
from roadview_noise.physics.radar_clutter import (
    Hydrometeors, ResolutionGrid, angular_cell_index, angular_edges_rad, backscatter_cross_section_m2,
    backscatter_per_volume_per_m, cell_doppler_probabilities, clutter_cells, fresnel_reflectivity,
    generate_clutter, particle_radial_velocity_m_per_s, rain_drops, refractive_index, snow_flakes)

RISE_LAMBDA_M = 3e8 / 77e9                  # RISE uses c = 3e8 m/s: λ = 3.896 mm
RISE_WATER = complex(12.0, -25.0)


def rise_rain(rate: float, scattering: str = "analytic") -> Hydrometeors:
    return Hydrometeors("rain", 8000.0, 4.1 * rate ** -0.21, 10.0, RISE_WATER, scattering)


def hemisphere(rng, n):
    az = rng.uniform(-np.pi / 2, np.pi / 2, n)
    z = rng.uniform(-1, 1, n)
    c = np.sqrt(1 - z * z)
    return np.stack([c * np.cos(az), c * np.sin(az), z], axis=1)


def test_water_constants_of_rise():
    assert fresnel_reflectivity(RISE_WATER) == pytest.approx(0.5264, rel=1e-3)
    n = refractive_index(RISE_WATER)
    assert (n.real, n.imag) == pytest.approx((4.457, 2.805), abs=1e-3)


@pytest.mark.parametrize("rate, eta", [(11.0, 7.665e-4), (20.0, 1.108e-3), (50.0, 1.878e-3)])
def test_eta_analytic_oracle(rate, eta):
    assert backscatter_per_volume_per_m(rise_rain(rate), RISE_LAMBDA_M) == pytest.approx(eta, rel=1e-3)


@pytest.mark.parametrize("rate, eta", [(11.0, 8.826e-4), (20.0, 1.295e-3), (50.0, 2.239e-3)])
def test_eta_mie_oracle(rate, eta):
    assert backscatter_per_volume_per_m(rise_rain(rate, "mie"), RISE_LAMBDA_M) == pytest.approx(eta, rel=2e-3)


def test_mie_cross_section_tends_to_the_dielectric_rayleigh_law():
    d_mm = np.array([0.02, 0.05])                      # x ≤ 0.04
    k2 = abs((RISE_WATER - 1) / (RISE_WATER + 2)) ** 2
    rayleigh = np.pi ** 5 * k2 * (d_mm * 1e-3) ** 6 / RISE_LAMBDA_M ** 4
    np.testing.assert_allclose(backscatter_cross_section_m2(d_mm, RISE_LAMBDA_M, RISE_WATER, "mie"), rayleigh,
                               rtol=0.01)


def test_eta_closed_form_equals_numerical_integral():
    for h in (rain_drops(7.0, scattering="analytic"), snow_flakes(2.5, scattering="analytic")):
        d = np.linspace(0, h.d_max_mm, 400_001)
        integrand = h.n0_per_m3_mm * np.exp(-h.lam_per_mm * d) * backscatter_cross_section_m2(
            d, RISE_LAMBDA_M, h.permittivity, "analytic")
        numeric = np.trapezoid(integrand, d)
        assert backscatter_per_volume_per_m(h, RISE_LAMBDA_M) == pytest.approx(numeric, rel=1e-4)


def test_eta_grows_with_rain_and_snow_is_weaker():
    etas = [backscatter_per_volume_per_m(rain_drops(r), RISE_LAMBDA_M) for r in (1, 5, 20, 50)]
    assert all(a < b for a, b in zip(etas, etas[1:]))
    assert backscatter_per_volume_per_m(snow_flakes(2.5), RISE_LAMBDA_M) < etas[0] * 50


def test_stationary_radar_sees_uniform_doppler():
    """Archimedes: one coordinate of a point uniform on the (half-)sphere is uniform, so v = −v_t z ~ U[−v_t, v_t]."""
    v_t = 6.014
    v = particle_radial_velocity_m_per_s(hemisphere(np.random.default_rng(1), 20000), v_t, (0, 0, 0))
    assert np.abs(v).max() <= v_t
    assert stats.kstest(v, stats.uniform(loc=-v_t, scale=2 * v_t).cdf).pvalue > 0.01


def test_moving_radar_without_fall_sees_uniform_negative_doppler():
    v = particle_radial_velocity_m_per_s(hemisphere(np.random.default_rng(2), 20000), 0.0, (10.0, 0, 0))
    assert stats.kstest(v, stats.uniform(loc=-10.0, scale=10.0).cdf).pvalue > 0.01
    v_wind = particle_radial_velocity_m_per_s(np.array([[0.0, 1.0, 0.0]]), 5.0, (10.0, 0, 0), (0, 3.0, 0))
    assert v_wind == pytest.approx([3.0])  # crosswind seen on the left ray; no fall or ego component there


def test_cell_doppler_probabilities_sum_to_one_per_cell():
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1035, 1.0, 20.0)
    for u in [(0.0, 0.0, 0.0), (-20.0, 3.0, 0.0), (-5.0, -2.0, 1.0)]:
        cell, m, p = cell_doppler_probabilities(rain_drops(20.0), grid, RISE_LAMBDA_M, u)
        np.testing.assert_allclose(np.bincount(cell, p, minlength=1800), 1.0, atol=1e-6)


def test_hemisphere_doppler_spectrum_is_the_size_weighted_uniform_mixture():
    """Stationary radar, front half-space: each drop size gives U[−v_t, v_t]; weights N(D) σ_b(D); v_t from
    Atlas–Srivastava–Sekhon (levels off at 9.65 m/s)."""
    h = rain_drops(20.0)
    dv = 0.5
    grid = ResolutionGrid(180, 180, 6, 6, 0.2, dv, 1.0, 2.0)
    cell, m, p = cell_doppler_probabilities(h, grid, RISE_LAMBDA_M, (0.0, 0.0, 0.0))
    az, z = grid.azimuth_edges_rad(), np.sin(grid.elevation_edges_rad())
    solid = (np.diff(az)[:, None] * np.diff(z)[None, :]).ravel()
    assert solid.sum() == pytest.approx(2 * np.pi)
    spectrum = np.bincount(m - m.min(), p * solid[cell]) / (2 * np.pi)
    bins = np.arange(m.min(), m.max() + 1)

    d = (np.arange(4000) + 0.5) * h.d_max_mm / 4000
    w = np.exp(-h.lam_per_mm * d) * backscatter_cross_section_m2(d, RISE_LAMBDA_M, h.permittivity, h.scattering)
    w /= w.sum()
    v_t = np.maximum(9.65 - 10.3 * np.exp(-0.6 * d), 1e-9)        # Atlas, Srivastava & Sekhon (1973)
    lo, hi = (bins - 0.5) * dv, (bins + 0.5) * dv
    overlap = np.clip(np.minimum(hi[:, None], v_t[None]) - np.maximum(lo[:, None], -v_t[None]), 0, None)
    expected = (overlap / (2 * v_t[None])) @ w
    np.testing.assert_allclose(spectrum, expected, atol=2e-3)
    assert spectrum.sum() == pytest.approx(1.0, abs=1e-6)


def test_expected_count_matches_independent_formula_and_draws():
    """One elevation row around 0° and 2 m/s Doppler bins: each angular cell's clutter falls in the zero bin, so
    μ_k = η ΔΩ (r_hi³ − r_lo³)/3 with η the models.md oracle, and E[count] = Σ 120 exp(−σ_t,k/μ_k)."""
    h = rise_rain(20.0)
    gamma, c_db, t_db = 9.72, 85.0, 10.0
    grid = ResolutionGrid(120, 2, 1, 2, 0.2, 2.0, 1.0, 6.0)
    cells = clutter_cells(h, grid, RISE_LAMBDA_M, (0.0, 0.0, 0.0), c_db, t_db, gamma)

    r_e = 1.0 + 0.2 * np.arange(26)
    r_c = 0.5 * (r_e[1:] + r_e[:-1])
    omega = math.radians(1.0) * 2 * math.sin(math.radians(1.0))
    mu = 1.108e-3 * omega * (r_e[1:] ** 3 - r_e[:-1] ** 3) / 3
    sigma_t = 10 ** ((t_db - c_db + 2 * gamma * r_c / 1000) / 10) * r_c ** 4
    expected = 120 * np.exp(-sigma_t / mu).sum()
    assert 100 < expected < 2000
    assert cells.expected_count == pytest.approx(expected, rel=2e-3)

    counts = [len(generate_clutter(np.random.default_rng(s), cells).v_r_m_per_s) for s in range(40)]
    assert np.mean(counts) == pytest.approx(expected, rel=0.1)


def _cfar_probability(mu_over_sigma_t: np.ndarray, pfa: float, n: int) -> np.ndarray:
    """Independent CA-CFAR clutter probability: P(Exp(μ) > max(T, α n)), T ~ Gamma(N, α(μ + n)/N), n = σ_t/α
    (noise units: x = μ/n), by numerical integration over T."""
    alpha = ca_cfar_multiplier(pfa, n)
    out = []
    for x in alpha * np.asarray(mu_over_sigma_t, dtype=float):
        t = stats.gamma(n, scale=alpha * (1 + x) / n)
        hi = t.ppf(1 - 1e-16)
        above = integrate.quad(lambda v: t.pdf(v) * math.exp(-v / x), alpha, hi, points=[t.mean()], epsabs=0,
                               epsrel=1e-10, limit=400)[0] if hi > alpha else 0.0
        out.append(t.cdf(alpha) * math.exp(-alpha / x) + above)
    return np.array(out)


@pytest.mark.parametrize("pfa", [5e-2, 1e-4])
def test_cfar_expected_count_matches_independent_formula_and_draws(pfa):
    """The grid of the fixed-threshold oracle above (all clutter of an angular cell in one Doppler bin, so
    μ_k = η ΔΩ (r_hi³ − r_lo³)/3): E[count] = Σ_k 120 P_cfar(μ_k/σ_t,k), and the mean of many draws."""
    h = rise_rain(20.0)
    gamma, c_db, t_db = 9.72, 85.0, 10.0
    grid = ResolutionGrid(120, 2, 1, 2, 0.2, 2.0, 1.0, 6.0)
    cells = clutter_cells(h, grid, RISE_LAMBDA_M, (0.0, 0.0, 0.0), c_db, t_db, gamma, CaCfar(pfa, 16))

    r_e = 1.0 + 0.2 * np.arange(26)
    r_c = 0.5 * (r_e[1:] + r_e[:-1])
    omega = math.radians(1.0) * 2 * math.sin(math.radians(1.0))
    mu = 1.108e-3 * omega * (r_e[1:] ** 3 - r_e[:-1] ** 3) / 3
    sigma_t = 10 ** ((t_db - c_db + 2 * gamma * r_c / 1000) / 10) * r_c ** 4
    expected = 120 * _cfar_probability(mu / sigma_t, pfa, 16).sum()
    assert expected < 120 * 25 * pfa                               # at most P_fa per cell
    assert cells.expected_count == pytest.approx(expected, rel=2e-3)
    if pfa >= 5e-2:                                                # enough points for a 10 % check
        assert expected > 10
        counts = [len(generate_clutter(np.random.default_rng(s), cells).v_r_m_per_s) for s in range(100)]
        assert np.mean(counts) == pytest.approx(expected, rel=0.1)


def test_cfar_clutter_count_does_not_explode_with_the_margin():
    """Full 120° × 30° grid, rain 20 mm/h, 1–20 m, car at 10 m/s: the fixed-threshold count grows by orders of
    magnitude from C − t = 68 to 83 dB; the CA-CFAR count stays below P_fa × (number of cells) and below the fixed
    count, in expectation and in the draws."""
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1035, 1.0, 20.0)
    h, rel, t_db, gamma, pfa = rain_drops(20.0), (-10.0, 0.0, 0.0), 12.0, 9.72, 1e-4
    n_cells = len(cell_doppler_probabilities(h, grid, RISE_LAMBDA_M, rel)[0]) * (len(grid.range_edges_m()) - 1)
    bound = pfa * n_cells
    fixed, cfar = [], []
    for margin in (68.0, 76.0, 83.0, 95.0):
        f = clutter_cells(h, grid, RISE_LAMBDA_M, rel, t_db + margin, t_db, gamma)
        c = clutter_cells(h, grid, RISE_LAMBDA_M, rel, t_db + margin, t_db, gamma, CaCfar(pfa, 16))
        fixed.append(f.expected_count)
        cfar.append(c.expected_count)
        drawn = [len(generate_clutter(np.random.default_rng(s), c).v_r_m_per_s) for s in range(10)]
        assert max(drawn) <= bound
    assert fixed[2] > 300 * fixed[0] and fixed[2] > 10_000
    assert all(a <= b for a, b in zip(cfar, fixed)) and all(a < b for a, b in zip(cfar, cfar[1:]))
    assert cfar[-1] < bound and cfar[2] < 0.05 * bound and cfar[2] < 1e-3 * fixed[2]


def test_target_cell_ratio():
    """μ/σ_t of the resolution cell of a point: its angular cell's clutter fraction in its Doppler bin times η ΔΩ
    and a range bin centred on it; 0 outside the clutter spectrum."""
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1035, 1.0, 20.0)
    h, rel, c_db, t_db, gamma = rain_drops(20.0), (-10.0, 0.0, 0.0), 88.0, 12.0, 9.72
    cells = clutter_cells(h, grid, RISE_LAMBDA_M, rel, c_db, t_db, gamma, CaCfar(1e-4, 16))
    cell_ids, m, p = cell_doppler_probabilities(h, grid, RISE_LAMBDA_M, rel)
    i = int(np.argmax(p))
    i_az, i_el = divmod(int(cell_ids[i]), 15)
    az = math.radians(-60 + i_az + 0.5)
    el = math.radians(-15 + 2 * i_el + 1)
    r = np.array([3.0, 50.0])
    pos = r[:, None] * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    omega = math.radians(1.0) * (math.sin(math.radians(-15 + 2 * i_el + 2)) - math.sin(math.radians(-15 + 2 * i_el)))
    mu = backscatter_per_volume_per_m(h, RISE_LAMBDA_M) * omega * p[i] * ((r + 0.1) ** 3 - (r - 0.1) ** 3) / 3
    sigma_t = 10 ** ((t_db - c_db + 2 * gamma * r / 1000) / 10) * r ** 4
    v = np.full(2, m[i] * 0.1035)
    np.testing.assert_allclose(cells.ratio_at(pos, v), mu / sigma_t, rtol=1e-9)
    assert np.all(cells.ratio_at(pos, v + 40.0) == 0.0) and np.all(cells.ratio_at(pos, v - 40.0) == 0.0)


def test_target_cell_ratio_reads_every_doppler_bin_of_the_spectrum_and_none_beyond():
    """At a cell's centre, ``ratio_at`` reads η ΔΩ P of its pair in each Doppler bin, from the lowest to the highest
    bin of the spectrum, and 0 one bin below and one above (the lookup table's edges)."""
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1035, 1.0, 20.0)
    h, rel, c_db, t_db = rain_drops(20.0), (-10.0, 0.0, 0.0), 88.0, 12.0
    cells = clutter_cells(h, grid, RISE_LAMBDA_M, rel, c_db, t_db, 0.0, CaCfar(1e-4, 16))
    cell_ids, m, p = cell_doppler_probabilities(h, grid, RISE_LAMBDA_M, rel)
    i_az, i_el = divmod(int(cell_ids[np.argmax(p)]), 15)
    az, el = math.radians(-60 + i_az + 0.5), math.radians(-15 + 2 * i_el + 1)
    pos = 5.0 * np.array([[math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]])
    omega = math.radians(1.0) * (math.sin(math.radians(-15 + 2 * i_el + 2)) - math.sin(math.radians(-15 + 2 * i_el)))
    mine = cell_ids == i_az * 15 + i_el
    want = dict(zip(m[mine].tolist(), p[mine].tolist()))
    sigma_t = 10 ** ((t_db - c_db) / 10) * 5.0 ** 4
    volume = (5.1 ** 3 - 4.9 ** 3) / 3
    eta = backscatter_per_volume_per_m(h, RISE_LAMBDA_M)
    for b in range(int(m.min()) - 1, int(m.max()) + 2):
        got = cells.ratio_at(pos, np.array([b * 0.1035]))[0]
        assert got == pytest.approx(eta * omega * want.get(b, 0.0) * volume / sigma_t, rel=1e-9, abs=0.0), b


@pytest.mark.parametrize("detector", [FixedThreshold(), CaCfar(1e-2, 16)])
def test_drawn_clutter_is_consistent(detector):
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1035, 1.0, 20.0)
    ego, wind = np.array([12.0, 0.0, 0.0]), np.array([0.0, 3.0, 0.0])
    c_db, t_db, gamma = 86.0, 12.0, 9.72
    h = rain_drops(20.0)
    cells = clutter_cells(h, grid, RISE_LAMBDA_M, wind - ego, c_db, t_db, gamma, detector)
    draws = [generate_clutter(np.random.default_rng(s), cells) for s in range(30)]
    assert np.mean([len(d.v_r_m_per_s) for d in draws]) == pytest.approx(cells.expected_count, rel=0.1)
    pts = draws[0]
    assert len(pts.v_r_m_per_s) > 20
    assert np.all(pts.detection_db >= t_db)
    r = np.linalg.norm(pts.positions_m, axis=1)
    assert r.min() >= 1.0 and r.max() <= 20.0
    az = np.degrees(np.arctan2(pts.positions_m[:, 1], pts.positions_m[:, 0]))
    el = np.degrees(np.arcsin(pts.positions_m[:, 2] / r))
    assert np.abs(az).max() <= 60 and np.abs(el).max() <= 15
    # Doppler and direction agree: v_r − (wind − ego)·r̂ = −v_t z, opposite in sign to z (cell spread tolerated)
    fall = pts.v_r_m_per_s - pts.positions_m @ (wind - ego) / r
    assert np.all(fall * np.sign(pts.positions_m[:, 2]) <= 0.1035 + 12.4 * math.radians(2.0))
    assert np.abs(fall).max() <= 9.65 * math.sin(math.radians(15)) + 0.6      # ASS fall speed ≤ 9.65 m/s
    again = generate_clutter(np.random.default_rng(0), cells)
    np.testing.assert_array_equal(again.positions_m, pts.positions_m)


def test_expected_count_monotone_in_threshold_and_rate():
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1035, 1.0, 20.0)
    counts_t = [clutter_cells(rain_drops(20.0), grid, RISE_LAMBDA_M, (0, 0, 0), 80.0, t, 0.0).expected_count
                for t in (5.0, 10.0, 15.0, 20.0)]
    assert all(a > b for a, b in zip(counts_t, counts_t[1:]))
    counts_r = [clutter_cells(rain_drops(r), grid, RISE_LAMBDA_M, (0, 0, 0), 80.0, 12.0, 0.0).expected_count
                for r in (2.0, 10.0, 50.0)]
    assert all(a < b for a, b in zip(counts_r, counts_r[1:]))


def test_angular_cells():
    az_e, el_e = angular_edges_rad(120, 1), angular_edges_rad(30, 2)
    assert (len(az_e) - 1) * (len(el_e) - 1) == 1800
    pts = np.array([[10.0, 0.0, 0.0], [1.0, -100.0, 0.0], [5.0, 0.0, 5.0], [10.0, 0.05, -0.01]])
    idx = angular_cell_index(pts, az_e, el_e)
    assert idx[0] == 60 * 15 + 7                 # boresight: az cell 60, el cell 7 (both edges at 0 → upper cell)
    assert idx[1] == 0 * 15 + 7                  # far right of the FOV: clipped to the edge cell
    assert idx[2] == 60 * 15 + 14                # 45° up: clipped to the top row


@pytest.mark.parametrize("law", ["gunn_marshall", "sekhon_srivastava"])
def test_radar_snow_below_the_fitted_range_is_fewer_of_the_same_crystals(law):
    """Below the rate where the law's slope reaches Gunn's crystal mass (physics/dsd.py), the radar's snow keeps its
    crystals (Λ at the cap) and their number falls ∝ S, continuous at the crossover; above it the law's own N0, Λ."""
    lam_law = SNOW_LAWS[law]
    s_c = (lam_law(1.0)[1] / TRACE_SNOW_SLOPE_PER_MM) ** (1 / {"gunn_marshall": 0.48, "sekhon_srivastava": 0.45}[law])
    assert lam_law(s_c)[1] == pytest.approx(TRACE_SNOW_SLOPE_PER_MM, rel=1e-12)
    for s in (1.02 * s_c, 0.5, 2.5):
        h = snow_flakes(s, law)
        assert (h.n0_per_m3_mm, h.lam_per_mm) == lam_law(s)
    eta = [backscatter_per_volume_per_m(snow_flakes(s, law), RISE_LAMBDA_M) for s in (1e-3, 1e-2, 0.999 * s_c)]
    assert eta[1] / eta[0] == pytest.approx(10, rel=1e-9) and eta[2] / eta[1] == pytest.approx(99.9 * s_c, rel=1e-9)
    just_above = backscatter_per_volume_per_m(snow_flakes(1.001 * s_c, law), RISE_LAMBDA_M)
    assert just_above / eta[2] == pytest.approx(1.0, abs=0.01)
