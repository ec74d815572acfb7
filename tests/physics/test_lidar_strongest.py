"""The brightest-first draw of the strongest return (physics/lidar_strongest.py): its tables against the visible
counts of lidar_particles, the law of each ray's brightest particle, the draw levels, and physical bounds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import stats

from roadview_noise.models.lidar.snow import SnowLidar
from roadview_noise.physics import dsd, lidar_echo, lidar_particles, lidar_strongest
from roadview_noise.physics.lidar_detection import detect, three_uniforms, undetectable
from roadview_noise.physics.receiver import measure_one
from roadview_noise.physics.lidar_medium import pulse_length_m
from roadview_noise.physics.lidar_particles import Beam, ParticleMedium
from roadview_noise.physics.lidar_rays import cloud_rays
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.types import PointCloud

OS1_BEAM = Beam(4.75e-3, math.pi / 1000, 0.5, 5.0)
LENGTH_M = 3.0


def rain(rate: float = 50.0) -> ParticleMedium:
    n0, lam = 8000.0, 4.1 * rate ** -0.21                   # Marshall–Palmer
    return ParticleMedium(n0, lam, 0.5, 6.0, 0.02, 2 * math.pi / 4 * 1e-6 * n0 * 2 / lam ** 3)


def snow() -> ParticleMedium:
    return ParticleMedium(1600.0, 2.5, 0.1, 5.0, 0.9, 9.4e-3, dsd.SNOW_HABITS["dry_aggregates"].size)


def lam_at(table, r):
    """Λ(R) of a :class:`lidar_particles.VisibleTable` (linear between its 1 cm samples, 0 below R1)."""
    x = np.clip((np.asarray(r) - table.start_m) / table.step_m, 0, len(table.cum) - 1.000001)
    k = x.astype(int)
    return np.where(np.asarray(r) > table.start_m, table.cum[k] + (table.cum[k + 1] - table.cum[k]) * (x - k), 0.0)


@pytest.mark.parametrize("medium", [rain(), snow()], ids=["rain", "snow"])
def test_tables_count_what_the_visible_tables_count(medium):
    """Λ(s_g; r) of the quarter-octave tables (2 cm grid) equals the visible count of lidar_particles (1 cm grid) at
    the octave levels, and decreases with the level."""
    base = 2e-7
    t = lidar_strongest.brightest_tables(medium, OS1_BEAM, base, LENGTH_M)
    assert np.all(np.diff(t.lam, axis=1) <= 1e-12) and np.all(np.diff(t.lam, axis=0) >= -1e-12)
    assert np.all(np.abs(t.lam[:, -1]) < 1e-15)              # the top level lies above every particle's return
    for octave in (0, 3, 6):
        table = lidar_particles.visible_table(medium, OS1_BEAM, base * 2.0 ** octave)
        for r in (1.0, 4.0, 15.0, 40.0):
            k = (r - t.start_m) / t.step_m
            got = np.interp(k, np.arange(len(t.lam)), t.lam[:, 4 * octave])
            assert got == pytest.approx(float(lam_at(table, r)), rel=5e-3, abs=1e-9)


@pytest.mark.parametrize("medium, big_r", [(rain(), 30.0), (snow(), 8.0), (snow(), 60.0)], ids=["rain", "snow-8m",
                                                                                                 "snow-60m"])
def test_brightest_particle_follows_its_poisson_law(medium, big_r):
    """On rays without a target the brightest drawn particle has P(s1 < s) = exp(−Λ(s; R)), Λ from the visible
    tables of lidar_particles at each s (an independent quadrature, not the sampler's tables): empirical CDF within
    4 binomial SDs + 0.005 at six levels; rays whose brightest lies below the base level draw nothing."""
    base = 2e-7
    n = 40000
    t = lidar_strongest.brightest_tables(medium, OS1_BEAM, base, LENGTH_M)
    drawn = lidar_strongest.draw_particles(np.random.default_rng(1), np.full(n, big_r), np.zeros(n),
                                           np.zeros(n, bool), medium.alpha_per_m, t, 4 * base)
    brightest = np.zeros(n)
    np.maximum.at(brightest, drawn.ray, drawn.signal)
    assert np.all(drawn.range_m <= big_r) and np.all(drawn.range_m >= OS1_BEAM.overlap_start_m)
    assert np.mean(brightest == 0) == pytest.approx(math.exp(-lam_at(lidar_particles.visible_table(
        medium, OS1_BEAM, base), big_r)), abs=4 / math.sqrt(n) + 0.005)
    top = float(np.quantile(brightest[brightest > 0], 0.99))
    for s in base * (top / base) ** np.linspace(0.1, 0.9, 6):
        p = math.exp(-float(lam_at(lidar_particles.visible_table(medium, OS1_BEAM, s), big_r)))
        assert np.mean(brightest < s) == pytest.approx(p, abs=4 * math.sqrt(p * (1 - p) / n) + 0.005), s


def test_a_ray_draws_down_to_its_cut_and_against_its_target():
    """Below its first-drawn (highest-ranked) particle s1 a ray draws down to ℓ 2^(⌊log2(s1/ℓ)⌋ − 1) (between s1/4
    and s1/2) and no further — s1 is the brightest drawn but where the largest particle at its range caps it (a
    range from the last cells of a band's inverse table: < 0.1 %); a ray with a bright target draws only when a
    particle reaches its own level ℓ 2^⌊log2(S_t/T)⌋ (at most ℓ 2^11)."""
    medium, base, threshold = snow(), 2e-7, 4e-7
    t = lidar_strongest.brightest_tables(medium, OS1_BEAM, base, LENGTH_M)
    n = 20000
    ranges = np.full(n, 40.0)
    target = np.where(np.arange(n) % 2 == 0, 0.0, 3e-3 * np.exp(2 * medium.alpha_per_m * 40.0))  # S_t = 3e-3
    drawn = lidar_strongest.draw_particles(np.random.default_rng(2), ranges, target, target > 0,
                                           medium.alpha_per_m, t, threshold)
    brightest = np.zeros(n)
    np.maximum.at(brightest, drawn.ray, drawn.signal)
    cut = base * 2.0 ** (np.floor(np.log2(brightest[drawn.ray] / base)) - 1)
    assert np.mean(drawn.signal >= cut * (1 - 1e-9)) > 0.999
    j = min(math.floor(math.log2(3e-3 / threshold)), lidar_strongest.OWN_LEVELS - 1)        # 11
    with_target = np.flatnonzero(target > 0)
    assert np.mean(brightest[with_target][brightest[with_target] > 0] >= base * 2.0 ** j) > 0.999
    assert np.all(drawn.level[with_target][brightest[with_target] == 0] == j)
    assert 0 < np.mean(brightest[with_target] > 0) < 0.5 * np.mean(brightest[target == 0] > 0)
    assert np.all(np.diff(drawn.ray) >= 0) and np.all(np.diff(drawn.range_m)[np.diff(drawn.ray) == 0] >= 0)


def test_a_drop_covers_at_most_what_the_largest_drop_covers():
    """Drops never fill the OS1's beam (6 mm against ≥ 9.5 mm): every drawn drop's beam fraction stays below
    (Dmax / 2w(r))², so a drop in front of a target never hides it."""
    medium = rain(150.0)
    t = lidar_strongest.brightest_tables(medium, OS1_BEAM, 1e-8, LENGTH_M)
    n = 20000
    drawn = lidar_strongest.draw_particles(np.random.default_rng(3), np.full(n, 80.0), np.zeros(n), np.zeros(n, bool),
                                           medium.alpha_per_m, t, 1e-7)
    assert len(drawn.ray) > 1000
    largest = (medium.d_max_mm * 0.5e-3 / OS1_BEAM.radius_at(drawn.range_m)) ** 2
    assert np.all(drawn.beam_fraction <= largest * (1 + 1e-4)) and drawn.beam_fraction.max() < 0.4


def test_mean_cover_of_the_undrawn_band_against_quadrature():
    """The shadow of a ray's undrawn particles between ℓ and its level: ∫ (σ_level − σ_ℓ) dr over [R1, R]
    (:func:`lidar_particles.faint_cross_section_per_m`, by trapezoids on 1 mm) at the ray's level."""
    medium, base = snow(), 2e-7
    t = lidar_strongest.brightest_tables(medium, OS1_BEAM, base, LENGTH_M)
    target = np.array([5e-2, 1e-3, 3e-6])
    ranges = np.array([20.0, 35.0, 12.0])
    drawn = lidar_strongest.draw_particles(np.random.default_rng(4), ranges, target * np.exp(2 * medium.alpha_per_m
                                                                                            * ranges),
                                           np.ones(3, bool), medium.alpha_per_m, t, 2 * base)
    r = np.arange(OS1_BEAM.overlap_start_m, 40.0, 0.001)
    for i in range(3):
        level = base * 2.0 ** drawn.level[i]
        sigma = (lidar_particles.faint_cross_section_per_m(medium, OS1_BEAM, level, r)
                 - lidar_particles.faint_cross_section_per_m(medium, OS1_BEAM, base, r))
        inside = r <= ranges[i]
        expected = np.trapezoid(sigma[inside], r[inside])
        assert drawn.shadow[i] == pytest.approx(expected, rel=2e-3, abs=1e-9)


def test_medium_changes_give_new_tables():
    """The cached tables key on the medium, beam, base level and pulse length."""
    a = lidar_strongest.brightest_tables(snow(), OS1_BEAM, 2e-7, LENGTH_M)
    assert lidar_strongest.brightest_tables(snow(), OS1_BEAM, 2e-7, LENGTH_M) is a
    assert lidar_strongest.brightest_tables(dataclasses.replace(snow(), reflectance=0.5), OS1_BEAM, 2e-7,
                                            LENGTH_M) is not a


@pytest.mark.parametrize("octave", range(0, 16))
def test_octaves_by_comparison_equal_frexp(octave):
    """The draw's octaves without frexp (:func:`lidar_strongest._own_level`, :func:`_octave_near`) give what
    ``frexp`` gives, at and next to every power of two and on random values of and below the band's octave."""
    rng = np.random.default_rng(octave)
    two = 2.0 ** np.arange(-3, octave + 2)
    values = np.concatenate([two, np.nextafter(two, 0), np.nextafter(two, np.inf),
                             2.0 ** rng.uniform(-4, octave + 1, 500), [0.0, 1e-300]])
    for v in values:
        exponent = math.frexp(v)[1] - 1
        assert lidar_strongest._own_level(v) == min(max(exponent, 0), lidar_strongest.OWN_LEVELS - 1), v
        if v < 2.0 ** (octave + 1):
            assert lidar_strongest._octave_near(v, octave) == max(exponent, 0), v


def test_table_reads_with_unsigned_indices_interpolate_the_right_entries():
    """The kernel's table reads (unsigned indices: no negative-index wraparound) against NumPy: a row of a 2-D table
    at fractional positions, clamped at both ends (:func:`lidar_particles.table_lerp`), a column between two rows
    (:func:`lidar_strongest._row_lerp`), the three background integrals of a level (:func:`lidar_echo._cumulative`)
    and a target's crest background, in the table and beyond it (:func:`lidar_echo.crest_background`)."""
    rng = np.random.default_rng(3)
    table = rng.uniform(size=(5, 40))
    x = np.concatenate([rng.uniform(-2.0, 42.0, 200), [0.0, 38.999, 39.0, 40.0]])
    for j in range(5):
        want = np.interp(np.clip(x, 0.0, 38.999999), np.arange(40), table[j])
        assert np.allclose([lidar_particles.table_lerp(table, j, v) for v in x], want, rtol=0, atol=1e-12)
    for k, t, g in ((0, 0.25, 3), (38, 0.9, 0), (17, 0.0, 4)):
        assert lidar_strongest._row_lerp(table.T, k, t, g) == pytest.approx(table[g, k] + (table[g, k + 1]
                                                                                           - table[g, k]) * t)
    cum = rng.uniform(size=(3, 20, 3))
    for j, v in ((0, 0.0), (2, 7.5), (1, 18.25), (1, 19.0), (2, 30.0)):
        want = [np.interp(min(v, 19.0), np.arange(20), cum[j, :, c]) for c in range(3)]
        assert np.allclose(lidar_echo._cumulative(cum, j, v), want, rtol=0, atol=1e-12)
    at_target, far = rng.uniform(size=(3, 10)), rng.uniform(size=25)
    assert lidar_echo.crest_background(2.2, 2, at_target, far, 2.0) == at_target[2, 4]
    assert lidar_echo.crest_background(7.0, 1, at_target, far, 2.0) == far[14]
    assert lidar_echo.crest_background(70.0, 1, at_target, far, 2.0) == far[24]


def _scan_rays(n: int = 6000):
    """A 1 × n OS1-128 range image in photons: Lambertian 2–90 % targets at 2–60 m on three rays in four, sky on the
    rest (empty rays the weather fills)."""
    rng = np.random.default_rng(0)
    r = rng.uniform(2.0, 60.0, n)
    az, el = rng.uniform(-np.pi, np.pi, n), rng.uniform(-0.3, 0.3, n)
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    sky = np.arange(n) % 4 == 0
    intensity = np.where(sky, 0.0, 65535 * rng.uniform(0.02, 0.9, n) / r ** 2)
    cloud = PointCloud(np.where(sky[:, None], 0.0, pos), {"intensity": intensity}, "lidar",
                       dataclasses.replace(os1_128(), detection_threshold=2.42), grid_shape=(1, n))
    return cloud_rays(cloud, "snow.lidar")


@pytest.mark.parametrize("rate", [0.5, 5.0], ids=["light", "heavy"])
def test_fused_pass_has_the_law_of_the_staged_pipeline(rate):
    """The strongest return's one compiled pass (:func:`strongest_returns`: draw, summed pulses and detection per ray,
    its uniforms interleaved with the draws) against the same stages run one
    after the other on the same rays (:func:`draw_particles`, :func:`lidar_echo.select_returns`,
    :func:`lidar_detection.detect`), 24 frames each of a 6000-ray scan of targets and sky in snow:
    - per outcome (no return / target / weather) and ray group (sky, targets below and above 20 m, faint and bright),
      a χ² test of homogeneity of the two 2 × 15 tables of counts, p > 0.001;
    - ranges and received signals of the weather returns and signals of the targets: two-sample Kolmogorov–Smirnov,
      p > 0.001.
    The drawn particles: the same mean within 4 Poisson SDs."""
    rays = _scan_rays()
    model = SnowLidar(snowfall_rate_mm_per_h=rate)
    medium, beam = model.medium(), Beam.of(rays.profile)
    tau_h = rays.profile.pulse_half_power_width_s
    level, _ = lidar_particles.draw_level(medium, beam, rays.threshold, model.draw_fraction_of_threshold,
                                          pulse_length_m(tau_h))
    tables = lidar_strongest.brightest_tables(medium, beam, float(level), float(pulse_length_m(tau_h)))
    group = ray_groups(rays, medium)
    results = []
    for fused in (True, False):
        frames = []
        for seed in range(24):
            rng = np.random.default_rng(seed)
            if fused:
                frames.append(lidar_strongest.strongest_returns(rng, rays, medium, beam, level))
                continue
            d = lidar_strongest.draw_particles(rng, rays.range_m, rays.signal, rays.has_target, medium.alpha_per_m,
                                               tables, rays.threshold)
            candidates = lidar_echo.select_returns(d.ray, d.range_m, d.signal, rays.range_m, d.target,
                                                   rays.has_target, tau_h, rays.receiver.weakest_return, "strongest",
                                                   d.beam_fraction, tables.background, d.shadow, d.level)
            n_weather = int(np.count_nonzero(candidates.kind == lidar_echo.WEATHER))
            frames.append((detect(rays, candidates, "strongest", rng.random((n_weather, 3)), per_ray=False),
                           len(d.ray)))
        results.append(tally(frames, group))
    assert_same_law(*results)


def ray_groups(rays, medium) -> np.ndarray:
    """Per ray of :func:`_scan_rays` its group: sky 0; targets below / above 20 m 1 / 2, +2 when their attenuated
    signal is more than 8 thresholds."""
    strong = rays.has_target & (rays.signal * np.exp(-2 * medium.alpha_per_m * rays.range_m) > 8 * rays.threshold)
    return np.where(~rays.has_target, 0, 1 + (rays.range_m > 20.0) + 2 * strong)


def tally(frames, group) -> tuple:
    """Of frames (returns, particles drawn) of the same rays: the counts per (outcome, ray group), the weather
    returns' ranges and signals, the kept targets' signals, the particles drawn."""
    counts, weather_range, weather_signal, target_signal, drawn = np.zeros((3, 5)), [], [], [], 0
    for returns, m in frames:
        np.add.at(counts, (returns.kind, group), 1)
        weather = returns.kind == lidar_echo.WEATHER
        weather_range.append(returns.range_m[weather])
        weather_signal.append(returns.signal[weather])
        target_signal.append(returns.signal[returns.kind == lidar_echo.TARGET])
        drawn += m
    return counts, *map(np.concatenate, (weather_range, weather_signal, target_signal)), drawn


def assert_same_law(a, b, p_min: float = 1e-3) -> None:
    """Two :func:`tally` s of the same rays have one law: χ² homogeneity of the counts and two-sample KS of the
    weather ranges and signals and the target signals, p > ``p_min``; particles drawn within 4 Poisson SDs."""
    (c_a, r_a, s_a, t_a, n_a), (c_b, r_b, s_b, t_b, n_b) = a, b
    assert len(r_a) > 2000 and len(t_a) > 2000
    table = np.stack([c_a.ravel(), c_b.ravel()])
    table = table[:, table.sum(axis=0) > 0]
    assert stats.chi2_contingency(table).pvalue > p_min
    for x, y in ((r_a, r_b), (s_a, s_b), (t_a, t_b)):
        assert stats.ks_2samp(x, y).pvalue > p_min
    assert abs(n_a - n_b) < 4 * math.sqrt(n_a + n_b)


def test_three_uniforms_are_the_bit_fields_of_one_draw():
    """:func:`lidar_detection.three_uniforms`: a uniform of 53 random bits ``(a·2³⁵ + b·2¹⁷ + c) / 2⁵³`` gives the
    cell midpoints ``(a + ½) / 2¹⁸, (b + ½) / 2¹⁸, (c + ½) / 2¹⁷`` exactly, and over many draws three uncorrelated
    uniforms."""
    split = three_uniforms.py_func if hasattr(three_uniforms, "py_func") else three_uniforms
    rng = np.random.default_rng(7)
    a, b, c = rng.integers(0, 2 ** 18, 200), rng.integers(0, 2 ** 18, 200), rng.integers(0, 2 ** 17, 200)
    a[:2], b[:2], c[:2] = (0, 2 ** 18 - 1), (0, 2 ** 18 - 1), (0, 2 ** 17 - 1)       # the extreme cells
    for ai, bi, ci in zip(a.tolist(), b.tolist(), c.tolist()):
        u = (ai * 2 ** 35 + bi * 2 ** 17 + ci) / 2 ** 53
        assert split(u) == ((ai + 0.5) / 2 ** 18, (bi + 0.5) / 2 ** 18, (ci + 0.5) / 2 ** 17)
    draws = np.array([split(u) for u in rng.random(20000)])
    assert np.all((draws > 0) & (draws < 1))
    assert np.allclose(draws.mean(axis=0), 0.5, atol=4 * np.sqrt(1 / 12 / len(draws)))
    assert np.abs(np.corrcoef(draws.T)[np.triu_indices(3, 1)]).max() < 4 / np.sqrt(len(draws))


def test_undetectable_never_hides_a_detection():
    """:func:`lidar_detection.undetectable` (the sampler's early decision on a ray without a target, before its
    candidate is summed): whenever it says a return of at most ``s_max`` is surely not detected, the receiver's
    :func:`receiver.measure_one` with the same uniforms detects no return of any s ≤ s_max (the photon counting
    receiver of the OS1 profile: 5 counts to detect, with background); it decides most of the undetected returns
    near the threshold; a Gaussian receiver is never decided early."""
    rx = _scan_rays(200).receiver
    params = rx.kernel_params
    spad, gain, detect_count, background_cdf = params[0], params[1], params[6], params[7]
    assert spad
    early, measure = (f.py_func if hasattr(f, "py_func") else f for f in (undetectable, measure_one))
    rng = np.random.default_rng(11)
    decided = undecided = 0
    for s_max in rx.threshold * np.concatenate([rng.uniform(0.0, 4.0, 3000), [1e-9, 1.0, 2.0]]):
        u0, u1 = rng.random(2)
        sure = early(s_max, u0, u1, spad, gain, detect_count, background_cdf)
        for s in (s_max, s_max * rng.random(), s_max * (1 - 1e-12)):
            if sure:
                assert not measure(s, u0, u1, *params)[1]
        if not measure(s_max, u0, u1, *params)[1]:
            decided += sure
            undecided += not sure
        assert not early(s_max, u0, u1, False, gain, detect_count, background_cdf)
    assert decided > 0.95 * (decided + undecided)
