"""Oracles of the shared LiDAR-equation core and the particle sampler (models.md §3.1–§3.4, §8)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from roadview_noise.physics import dsd, lidar_link, lidar_particles
from roadview_noise.physics.lidar_link import NO_RETURN, TARGET, WEATHER

C = 299_792_458.0


def test_overlap_function_hahner():
    r = np.array([0.0, 0.5, 0.9, 0.95, 1.0, 1.5, 50.0])
    np.testing.assert_allclose(lidar_link.overlap(r), [0, 0, 0, 0.5, 1, 1, 1])


def test_pulse_peak_one_and_energy_tau():
    tau = 10e-9
    t = np.linspace(-tau, 3 * tau, 400001)
    p = lidar_link.pulse_power(t, tau)
    assert p.max() == pytest.approx(1.0, abs=1e-9)
    assert np.trapezoid(p, t) == pytest.approx(tau, rel=1e-6)
    assert lidar_link.pulse_length_m(tau) == pytest.approx(2.99792458)


def _direct_soft_peak(alpha, tau, r0):
    """max over R of G(R; R0) by brute force: trapezoid in t on a dense (R, t) grid (independent of the table)."""
    t = np.linspace(0, 2 * tau, 4001)
    best = (0.0, 0.0)
    for big_r in np.arange(0.9, r0 + C * tau + 0.01, 0.005):
        r = big_r - C * t / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where((r > 0.9) & (r <= r0), np.exp(-2 * alpha * r) * np.clip((r - 0.9) / 0.1, 0, 1) / r ** 2, 0)
        g = np.trapezoid(np.sin(np.pi * t / (2 * tau)) ** 2 * f, t)
        if g > best[0]:
            best = (g, big_r - C * tau / 2)
    return best


@pytest.mark.parametrize("tau", [10e-9, 20e-9])
@pytest.mark.parametrize("r0", [1.3, 2.5, 30.0])
def test_soft_target_table_matches_direct_integration(tau, r0):
    alpha = math.log(20) / 30
    g_direct, range_direct = _direct_soft_peak(alpha, tau, r0)
    g, fog_range = lidar_link.soft_target_table(alpha, tau).lookup(np.array([r0]))
    assert g[0] == pytest.approx(g_direct, rel=5e-3)
    assert fog_range[0] == pytest.approx(range_direct, abs=0.02)


def test_soft_target_table_saturates_beyond_r2_plus_pulse():
    table = lidar_link.soft_target_table(0.1, 10e-9)
    g, r = table.lookup(np.array([4.5, 20.0, 200.0, 1e4]))
    assert np.all(g == g[0]) and np.all(r == r[0])
    assert table.saturated == (g[0], r[0])
    assert 1.0 < r[0] < 2.0                      # fog peak a little beyond the overlap range


def test_hard_target_two_way_transmission():
    # models.md §3.2 oracle: e^{-2} = 0.1353 at 10 m with the reference α = 0.1
    assert lidar_link.hard_target_signal(1.0, 0.1, 10.0) == pytest.approx(0.1353, rel=1e-3)


def test_fog_coefficients_oracle():
    from roadview_noise.models.lidar.fog import fog_coefficients

    alpha, beta = fog_coefficients(30.0)
    assert alpha == pytest.approx(0.09986, rel=1e-3)
    assert beta == pytest.approx(1.533e-3, rel=1e-3)


def test_surviving_range_closed_form():
    """R_max = ln(I/I_thr)/(2α): I = 100, threshold 2.42 photons, V = 30 m → 18.6 m (models.md §3.2)."""
    alpha = math.log(20) / 30
    r_max = math.log(100 / 2.42) / (2 * alpha)
    assert r_max == pytest.approx(18.6, abs=0.05)
    assert lidar_link.hard_target_signal(100.0, alpha, r_max) == pytest.approx(2.42, rel=1e-9)


@pytest.mark.parametrize("rate, n_expected, alpha_expected", [
    (20.0, 1227.2, 2.171e-3), (10.0, 894.0, 1.346e-3), (25.0, 1352.1, 2.525e-3), (50.0, 1801.1, 4.011e-3)])
def test_rain_oracles(rate, n_expected, alpha_expected):
    from roadview_noise.models.lidar.rain import RainLidar

    medium = RainLidar(rain_rate_mm_per_h=rate).medium()
    assert medium.count_above(np.float64(0.5)) == pytest.approx(n_expected, rel=1e-3)
    assert medium.alpha_per_m == pytest.approx(alpha_expected, rel=1e-3)
    # independent: numerical integration of (π/4)·2·D² N(D)
    n0, lam = 8000.0, 4.1 * rate ** -0.21
    direct = integrate.quad(lambda d: math.pi / 2 * d * d * n0 * math.exp(-lam * d), 0.5, 6.0)[0] * 1e-6
    assert medium.alpha_per_m == pytest.approx(direct, rel=1e-9)


def test_snow_oracles_gunn_marshall():
    from roadview_noise.models.lidar.snow import SnowLidar

    medium = SnowLidar().medium()                       # 2.5 mm/h liquid equivalent, whole DSD
    assert medium.n0_per_m3_mm == pytest.approx(1712, rel=1e-3)
    assert medium.lam_per_mm == pytest.approx(1.643, rel=1e-3)
    assert medium.count_above(np.float64(0.0)) == pytest.approx(1042, rel=1e-3)
    assert medium.alpha_per_m == pytest.approx(1.21e-3, abs=0.005e-3)       # stated to 3 digits
    assert medium.alpha_per_m == pytest.approx(math.pi / 4 * 2 * 2 * 1712.28 / 1.64259 ** 3 * 1e-6, rel=1e-4)


@pytest.mark.parametrize("s, r_eq", [(0.25, 2.42), (0.835, 14.77), (2.5, 76.53), (3.03, 102.1)])
def test_hahner_snow_rate_conversion(s, r_eq):
    from roadview_noise.models.lidar.snow import liquid_equivalent_rate_mm_per_h

    assert liquid_equivalent_rate_mm_per_h(s, "hahner") == pytest.approx(r_eq, rel=2e-3)
    assert liquid_equivalent_rate_mm_per_h(s, "snow_depth", 0.1) == pytest.approx(s / 10)
    assert liquid_equivalent_rate_mm_per_h(s, "liquid_equivalent") == s


# --- summed pulse profiles and return selection ---------------------------------------------------------------


def _profile(x, r, a, length):
    s = x[:, None] - r[None, :]
    return np.sum(a * np.where((s >= 0) & (s <= length), np.sin(np.pi * s / length) ** 2, 0.0), axis=1)


def test_summed_peaks_exact_against_dense_grid():
    rng = np.random.default_rng(3)
    length = 3.0
    sizes = rng.integers(2, 6, 150)
    ranges, amps = [], []
    for s in sizes:
        ranges.append(np.sort(rng.uniform(1, 100) + np.cumsum(rng.uniform(0, 0.99 * length, s))))
        amps.append(rng.uniform(0, 1, s))
    first = np.cumsum(sizes) - sizes
    peak, at = lidar_link._summed_peaks(first, sizes, np.concatenate(ranges), np.concatenate(amps), length)
    for i, (r, a) in enumerate(zip(ranges, amps)):
        x = np.linspace(r[0], r[-1] + length, 60001)
        dense = _profile(x, r, a, length)
        assert peak[i] == pytest.approx(dense.max(), abs=1e-6)
        assert peak[i] >= dense.max() - 1e-12
        assert _profile(np.array([at[i] + length / 2]), r, a, length)[0] == pytest.approx(peak[i], rel=1e-9)


def _brute_force_ray(p_range, p_sig, t_range, t_sig, has_target, length, thr, mode):
    """Plain per-ray reference of §3.1 return selection: clusters of overlapping pulses, each at its dense-grid
    maximum; strongest or first cluster above threshold."""
    contrib = list(zip(p_range, p_sig, [False] * len(p_range)))
    if has_target:
        contrib.append((t_range, t_sig, True))
    clusters, cur = [], [contrib[0]]
    for c in contrib[1:]:
        if c[0] - cur[-1][0] < length:
            cur.append(c)
        else:
            clusters.append(cur)
            cur = [c]
    clusters.append(cur)
    cands = []
    for cl in clusters:
        r = np.array([c[0] for c in cl])
        a = np.array([c[1] for c in cl])
        x = np.linspace(r[0], r[-1] + length, 20001)
        prof = _profile(x, r, a, length)
        k = int(np.argmax(prof))
        rng_ = x[k] - length / 2
        own = cl[-1][2] and abs(rng_ - cl[-1][0]) <= 0.2
        cands.append((prof[k], cl[-1][0] if own else rng_, own))
    if mode == "first" and any(c[0] >= thr for c in cands):
        best = next(c for c in cands if c[0] >= thr)
    else:
        best = max(cands, key=lambda c: c[0])
    if best[0] < thr:
        return NO_RETURN, None, None
    return (TARGET if best[2] else WEATHER), best[1], best[0]


@pytest.mark.parametrize("mode", ["strongest", "first"])
def test_select_returns_against_per_ray_reference(mode):
    rng = np.random.default_rng(11 if mode == "strongest" else 12)
    n_rays, length, thr = 400, 2.99792458, 0.05
    t_range = rng.uniform(2, 30, n_rays)
    has_target = rng.random(n_rays) < 0.8
    t_sig = np.where(has_target, rng.uniform(0, 0.5, n_rays) * (rng.random(n_rays) < 0.8), 0.0)
    counts = rng.poisson(1.5, n_rays)
    ray = np.repeat(np.arange(n_rays), counts)
    p_range = np.concatenate([np.sort(rng.uniform(1, t_range[i], c)) for i, c in enumerate(counts)])
    p_sig = rng.uniform(0, 0.3, len(ray)) * (rng.random(len(ray)) < 0.9)
    out = lidar_link.select_returns(ray, p_range, p_sig, t_range, t_sig, has_target, length / C, thr, mode)
    for i in range(n_rays):
        sel = ray == i
        if not sel.any():
            continue
        kind, rng_, sig = _brute_force_ray(p_range[sel], p_sig[sel], t_range[i], t_sig[i], has_target[i],
                                           length, thr, mode)
        assert out.kind[i] == kind, i
        if kind != NO_RETURN:
            assert out.signal[i] == pytest.approx(sig, rel=0.02), i
            assert out.range_m[i] == pytest.approx(rng_, abs=0.05), i


def test_select_returns_simple_cases():
    length = lidar_link.pulse_length_m(10e-9)
    t_range = np.array([20.0, 20.0, 20.0, 120.0])
    t_sig = np.array([0.5, 0.01, 0.5, 0.0])
    has = np.array([True, True, True, False])
    # ray 0: weak far drop → target; ray 1: drop stronger than the target → drop; ray 2: drop 0.5 m in front of a
    # strong target → same target, summed; ray 3: empty ray with a drop → weather return
    ray = np.array([0, 1, 2, 3])
    p_range = np.array([5.0, 5.0, 19.5, 3.0])
    p_sig = np.array([0.02, 0.02, 0.04, 0.02])
    out = lidar_link.select_returns(ray, p_range, p_sig, t_range, t_sig, has, 10e-9, 0.005, "strongest")
    assert list(out.kind) == [TARGET, WEATHER, TARGET, WEATHER]
    assert out.range_m[1] == 5.0 and out.range_m[3] == 3.0 and out.range_m[2] == 20.0
    assert 0.5 < out.signal[2] < 0.54
    first = lidar_link.select_returns(ray, p_range, p_sig, t_range, t_sig, has, 10e-9, 0.005, "first")
    assert list(first.kind) == [WEATHER, WEATHER, TARGET, WEATHER]
    assert length == pytest.approx(2.998, abs=1e-3)


# --- particle sampler -------------------------------------------------------------------------------------------


def _medium(rate=20.0):
    n0, lam = dsd.marshall_palmer(rate)
    return lidar_particles.ParticleMedium(n0, lam, 0.5, 6.0, 0.0199, dsd.geometric_extinction_per_m(n0, lam, 0.5, 6))


def test_visible_count_table_matches_integration():
    medium, beam, level = _medium(), lidar_particles.Beam(4.75e-3, 3e-3), 2.0 / 65535
    table = lidar_particles.visible_table(medium, beam, level)

    def density(r):                                       # written out independently of the module
        w = 4.75e-3 + r * 1.5e-3
        full = 0.0199 * min(1.0, (r - 0.9) / 0.1) * math.exp(-2 * medium.alpha_per_m * r) / r ** 2
        if full < level:
            return 0.0
        d_c = max(0.5, 2e3 * w * math.sqrt(level / full))
        if d_c >= 6.0:
            return 0.0
        return math.pi * w * w * medium.n0_per_m3_mm / medium.lam_per_mm * (
            math.exp(-medium.lam_per_mm * d_c) - math.exp(-medium.lam_per_mm * 6.0))

    for r in (1.5, 3.0, 6.0, 10.0):
        expected = integrate.quad(density, 0.9, r, limit=400)[0]
        k, frac = table.position(np.array([r]))
        assert table.lerp(table.cum, k, frac)[0] == pytest.approx(expected, rel=2e-3)


def test_sampler_statistics_and_order():
    medium, beam = _medium(50.0), lidar_particles.Beam(4.75e-3, 0.0)
    threshold = 1.0 / 65535
    ranges = np.tile(np.array([0.5, 2.0, 5.0, 12.0, 120.0]), 4000)
    rng = np.random.default_rng(7)
    p = lidar_particles.sample_particles(rng, ranges, medium, beam, threshold)
    table = lidar_particles.visible_table(medium, beam, lidar_particles.VISIBLE_FRACTION * threshold)
    k, frac = table.position(ranges)
    expected = float(np.sum(np.where(ranges > 0.9, table.lerp(table.cum, k, frac), 0.0)))
    assert abs(len(p.ray) - expected) < 4 * math.sqrt(expected)
    # sorted by ray, then range; in front of the target; beyond the overlap range
    assert np.all(np.diff(p.ray) >= 0)
    same = np.diff(p.ray) == 0
    assert np.all(np.diff(p.range_m)[same] >= 0)
    assert np.all(p.range_m <= ranges[p.ray]) and np.all(p.range_m >= 0.9)
    assert not np.any(ranges[p.ray] <= 0.9)
    # every drawn particle is visible (up to the 0.01 m table discretisation at the overlap onset), diameters in the
    # DSD's range
    level = lidar_particles.VISIBLE_FRACTION * threshold
    assert np.mean(p.signal >= level * 0.98) > 0.999
    assert np.all((p.diameter_mm >= 0.5) & (p.diameter_mm <= 6.0))
    np.testing.assert_allclose(p.beam_fraction, np.minimum(1, (p.diameter_mm / 9.5) ** 2))
    # positions follow Λ(r)/Λ(R) on the 120 m rays: compare the empirical CDF at a few ranges
    far = ranges[p.ray] == 120.0
    kk, ff = table.position(np.array([1.2, 1.5, 2.0, 3.0]))
    cdf = table.lerp(table.cum, kk, ff) / table.cum[-1]
    emp = np.array([np.mean(p.range_m[far] <= x) for x in (1.2, 1.5, 2.0, 3.0)])
    assert np.all(np.abs(emp - cdf) < 4 * np.sqrt(cdf * (1 - cdf) / far.sum()) + 1e-3)


def test_sampler_diameters_follow_truncated_exponential_above_visibility_bound():
    medium, beam = _medium(20.0), lidar_particles.Beam(4.75e-3, 0.0)
    ranges = np.full(200000, 1.5)
    p = lidar_particles.sample_particles(np.random.default_rng(2), ranges, medium, beam, 1e-9)
    # at a tiny threshold every drop beyond the overlap ramp is visible: diameters follow the DSD on [0.5, 6] mm
    d = p.diameter_mm[p.range_m > 1.0]
    lam = medium.lam_per_mm
    mean_expected = 0.5 + 1 / lam - 5.5 * math.exp(-lam * 5.5) / (1 - math.exp(-lam * 5.5))
    assert d.mean() == pytest.approx(mean_expected, abs=4 * d.std() / math.sqrt(len(d)))
    assert np.mean(d > 3.0) == pytest.approx(math.exp(-lam * 2.5) - math.exp(-lam * 5.5), abs=0.003)
    # in the overlap ramp only larger drops are visible
    assert p.diameter_mm[p.range_m < 0.905].min() > 0.5
