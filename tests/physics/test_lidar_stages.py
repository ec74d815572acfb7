"""Oracles of the shared LiDAR-equation core and the particle sampler (models.md §3.1–§3.4, §8)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import integrate

from roadview_noise.errors import ModelError
from roadview_noise.physics import dsd, lidar_echo, lidar_intensity, lidar_medium, lidar_particles
from roadview_noise.physics.lidar_echo import NO_RETURN, TARGET, WEATHER
from roadview_noise.profiles.lidar import carla_64, kitti_hdl64, os1_128, os1_128_reflectivity, vls_128

C = 299_792_458.0


def test_overlap_function_hahner_and_os1():
    r = np.array([0.0, 0.5, 0.9, 0.95, 1.0, 1.5, 50.0])
    np.testing.assert_allclose(lidar_medium.overlap(r, 0.9, 1.0), [0, 0, 0, 0.5, 1, 1, 1])
    np.testing.assert_allclose(lidar_medium.overlap(r, 0.5, 5.0), [0, 0, 0.4 / 4.5, 0.45 / 4.5, 0.5 / 4.5, 1 / 4.5, 1])


def test_profiles_state_their_overlap():
    """OS1: ξ from the datasheet minimum range 0.5 m, full at 5 m (assumption for the biaxial optics); the others
    Hahner's 0.9 m / 1.0 m."""
    for profile in (os1_128(), os1_128_reflectivity()):
        assert (profile.overlap_start_m, profile.overlap_full_m) == (0.5, 5.0)
    for profile in (vls_128(), kitti_hdl64()):
        assert (profile.overlap_start_m, profile.overlap_full_m) == (0.9, 1.0)


def test_pulse_peak_one_and_energy_tau():
    tau = 10e-9
    t = np.linspace(-tau, 3 * tau, 400001)
    p = lidar_medium.pulse_power(t, tau)
    assert p.max() == pytest.approx(1.0, abs=1e-9)
    assert np.trapezoid(p, t) == pytest.approx(tau, rel=1e-6)
    assert lidar_medium.pulse_length_m(tau) == pytest.approx(2.99792458)


def _direct_soft_peak(alpha, tau, r0, r1=0.9, r2=1.0):
    """max over R of G(R; R0) by brute force: trapezoid in t on a dense (R, t) grid (independent of the table);
    overlap ξ from r1 to r2."""
    t = np.linspace(0, 2 * tau, 4001)
    best = (0.0, 0.0)
    for big_r in np.arange(r1, r0 + C * tau + 0.01, 0.005):
        r = big_r - C * t / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where((r > r1) & (r <= r0), np.exp(-2 * alpha * r) * np.clip((r - r1) / (r2 - r1), 0, 1) / r ** 2,
                         0)
        g = np.trapezoid(np.sin(np.pi * t / (2 * tau)) ** 2 * f, t)
        if g > best[0]:
            best = (g, big_r - C * tau / 2)
    return best


@pytest.mark.parametrize("tau, r1, r2", [(10e-9, 0.9, 1.0), (20e-9, 0.9, 1.0), (10e-9, 0.5, 5.0)])
@pytest.mark.parametrize("r0", [1.3, 2.5, 30.0])
def test_soft_target_table_matches_direct_integration(tau, r1, r2, r0):
    alpha = math.log(20) / 30
    g_direct, range_direct = _direct_soft_peak(alpha, tau, r0, r1, r2)
    g, fog_range = lidar_medium.soft_target_table(alpha, tau, r1, r2).lookup(np.array([r0]))
    assert g[0] == pytest.approx(g_direct, rel=5e-3)
    assert fog_range[0] == pytest.approx(range_direct, abs=0.02)


def test_soft_target_table_saturates_beyond_r2_plus_pulse():
    table = lidar_medium.soft_target_table(0.1, 10e-9, 0.9, 1.0)
    g, r = table.lookup(np.array([4.5, 20.0, 200.0, 1e4]))
    assert np.all(g == g[0]) and np.all(r == r[0])
    assert table.saturated == (g[0], r[0])
    assert 1.0 < r[0] < 2.0                      # fog peak a little beyond the overlap range
    # a slow overlap (full at 5 m): its own table, up to R2 + L, with a weaker peak (ξ(r) ≤ (r − R1)/(R2 − R1))
    slow = lidar_medium.soft_target_table(0.1, 10e-9, 0.5, 5.0)
    assert len(slow.g_max_s_per_m2) > len(table.g_max_s_per_m2) and slow.lookup(np.array([8.1]))[0][0] == \
        slow.saturated[0]
    assert slow.saturated[0] < 0.5 * table.saturated[0]


def test_soft_target_signal_far_from_the_sensor_closed_form():
    """Sensor-constant fog return K π β ∫ sin²(πt/2τ) ξ e^{−2αr}/r² (c dt/2) → K π β (c τ_H/2) e^{−2αR}/R² for
    R ≫ c τ_H and ξ = 1 (here: the overlap placed at 60 m, light fog, so the peak of the profile lies there)."""
    alpha, beta, tau = math.log(20) / 3000, 0.046 / 3000, 10e-9
    table = lidar_medium.soft_target_table(alpha, tau, 60.0, 60.001)
    g, at = table.saturated
    fog = lidar_medium.soft_target_signal(g, beta)
    # the peak: the window just past the overlap, centred at R ≈ 60 m + L/2 (second-order terms: 0.5 %)
    big_r = 60.0 + C * tau / 2
    expected = math.pi * beta * C * tau / 2 * math.exp(-2 * alpha * big_r) / big_r ** 2
    assert fog == pytest.approx(expected, rel=1e-2)
    assert at == pytest.approx(big_r, abs=0.3)


@pytest.mark.parametrize("r1, r2, lo, hi", [(0.9, 1.0, 100, 160), (0.5, 5.0, 25, 40)], ids=["hahner", "os1"])
def test_soft_target_signal_matches_direct_integration(r1, r2, lo, hi):
    """Empty ray, V = 30 m, OS1 (τ_H = 10 ns, K = 65535): the peak of K π β ∫ … (c dt/2), integrated directly in t
    (independent of the table), is the model's fog return; ~131 photons at ~1.4 m with Hahner's overlap, ~32 photons
    with the OS1 profile's (full at 5 m)."""
    alpha, beta = math.log(20) / 30, 0.046 / 30
    g_direct, range_direct = _direct_soft_peak(alpha, 10e-9, r2 + 7.0, r1, r2)    # the peak stops beyond R2 + L
    g, at = lidar_medium.soft_target_table(alpha, 10e-9, r1, r2).saturated
    fog = lidar_medium.soft_target_signal(g, beta) * 65535
    assert fog == pytest.approx(65535 * math.pi * beta * C / 2 * g_direct, rel=5e-3)
    assert at == pytest.approx(range_direct, abs=0.02)
    assert lo < fog < hi and 1.0 < at < 2.0


# --- one intensity scale -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("factory", [os1_128, os1_128_reflectivity, vls_128, kitti_hdl64], ids=lambda f: f.__name__)
def test_received_signal_and_reported_intensity_are_inverse(factory):
    profile = factory()
    rng = np.random.default_rng(0)
    r = rng.uniform(0.5, 150, 1000)
    i = rng.uniform(0, profile.intensity_full_scale, 1000)
    s = lidar_intensity.received_signal(i, r, profile)
    np.testing.assert_allclose(lidar_intensity.reported_intensity(s, r, profile), i, rtol=1e-12)
    k = lidar_intensity.sensor_constant(profile)
    if profile.intensity_kind == "signal":
        np.testing.assert_array_equal(s, i)
    else:                                   # range-compensated: S = (I / W) · K / R², W the white (ρ = 1) reading
        w = {"os1-128-reflectivity": 100.0, "vls-128": 110.0}.get(profile.name, profile.intensity_full_scale)
        assert lidar_intensity.white_reading(profile) == w
        np.testing.assert_allclose(s, i / w * k / r ** 2, rtol=1e-12)
        # a diffuse white target (ρ = 1, normal incidence) reads W at every range, and its signal is K / R²
        np.testing.assert_allclose(lidar_intensity.reported_intensity(k / r ** 2, r, profile), w, rtol=1e-12)
    # a reflectivity reading of zero range is no return
    if profile.intensity_kind == "reflectivity":
        assert lidar_intensity.received_signal(np.array([10.0]), np.array([0.0]), profile)[0] == 0


def test_sensor_constant_defaults_to_full_scale_and_kinds_are_checked():
    p = dataclasses.replace(os1_128(), sensor_constant=None, intensity_full_scale=4095.0)
    assert lidar_intensity.sensor_constant(p) == 4095.0
    # ρ = 1 constants: the OS1 in either channel 65535 photons·m², the VLS-128 245²/0.8 (80 % at 245 m)
    assert lidar_intensity.sensor_constant(os1_128_reflectivity()) == lidar_intensity.sensor_constant(os1_128()) == 65535.0
    assert lidar_intensity.sensor_constant(vls_128()) == pytest.approx(245.0 ** 2 / 0.8)
    # no white reading: the file reads ρ × full scale
    refl = dataclasses.replace(os1_128_reflectivity(), reflectivity_white_reading=None)
    assert lidar_intensity.white_reading(refl) == 255.0
    assert lidar_intensity.received_signal(255.0, 2.0, refl) == pytest.approx(65535 / 4)
    with pytest.raises(ModelError, match="intensity_kind"):
        lidar_intensity.received_signal(np.ones(3), np.ones(3), dataclasses.replace(p, intensity_kind="power"))


def test_builtin_profiles_reach_their_datasheet_ranges():
    """Detection range of a Lambertian target ``sqrt(K ρ / threshold)`` (ρ in terms of the stored scale)."""
    os1 = os1_128()
    k, thr = lidar_intensity.sensor_constant(os1), os1.detection_threshold
    assert 40 <= math.sqrt(k * 0.1 / thr) <= 45.5 and 115 <= math.sqrt(k * 0.8 / thr) <= 130   # OS1: 10 % 40-45 m
    # the reflectivity channel is the same sensor: a diffuse target reads 100 ρ, same signal, same threshold
    refl = os1_128_reflectivity()
    assert lidar_intensity.received_signal(100 * 0.1, 44.0, refl) == pytest.approx(k * 0.1 / 44.0 ** 2)
    assert refl.detection_threshold == thr
    vls = vls_128()                         # 80 % (reads 0.8 × 110) at 245 m is at the threshold
    assert lidar_intensity.received_signal(0.8 * 110, 245.0, vls) == pytest.approx(vls.detection_threshold)
    kitti = kitti_hdl64()                   # HDL-64E: pavement (10 %) to 50 m
    assert lidar_intensity.received_signal(0.1, 50.0, kitti) == pytest.approx(kitti.detection_threshold)


def test_intensity_resolution_per_unit():
    assert lidar_intensity.intensity_resolution(os1_128()) == 1.0
    assert lidar_intensity.intensity_resolution(vls_128()) == 1.0
    assert lidar_intensity.intensity_resolution(kitti_hdl64()) == pytest.approx(0.01)     # KITTI's stored step
    assert lidar_intensity.intensity_resolution(carla_64()) == pytest.approx(1 / 255)      # continuous: 1/255 visible
    assert lidar_intensity.intensity_step(carla_64()) == 0.0


@pytest.mark.parametrize("faint, expected", [("zero", [0, 0, 1, 3, 255]), ("lowest", [0, 1, 1, 3, 255]),
                                             ("no_return", [0, 0, 1, 3, 255])])
def test_stored_intensity_rounds_to_the_sensor_step_and_follows_its_faint_reading(faint, expected):
    profile = dataclasses.replace(os1_128_reflectivity(), faint_reading=faint)
    reported = np.array([0.0, 0.3, 0.7, 3.2, 400.0])
    np.testing.assert_array_equal(lidar_intensity.stored_intensity(reported, profile), expected)
    np.testing.assert_array_equal(lidar_intensity.too_faint(reported, profile),
                                  [faint == "no_return"] * 2 + [False] * 3)
    kitti = lidar_intensity.stored_intensity(np.array([0.123, 0.996, 2.0]), kitti_hdl64())
    np.testing.assert_allclose(kitti, [0.12, 1.0, 1.0])
    np.testing.assert_array_equal(lidar_intensity.stored_intensity(np.array([0.1234]), carla_64()), [0.1234])


@pytest.mark.parametrize("factory", [os1_128, os1_128_reflectivity, vls_128, kitti_hdl64, carla_64])
@pytest.mark.parametrize("faint", ["zero", "lowest", "no_return"])
def test_stored_signal_is_stored_intensity_of_reported_intensity(factory, faint):
    """The compiled one-pass :func:`stored_signal` gives exactly the values of the NumPy stages it fuses (values
    rounding to 0, clipped at full scale, zero signals)."""
    profile = dataclasses.replace(factory(), faint_reading=faint)
    k = lidar_intensity.sensor_constant(profile)
    rng = np.random.default_rng(5)
    r = np.concatenate([rng.uniform(0.5, 200.0, 3000), [0.0, 3.0, 3.0]])
    reported = np.concatenate([rng.uniform(0.0, 1.5, 3000) * profile.intensity_full_scale, [0.0, 0.0, 1e-9]])
    signal = lidar_intensity.received_signal(reported, r, profile) / k
    expected = lidar_intensity.stored_intensity(lidar_intensity.reported_intensity(signal * k, r, profile), profile)
    assert np.any(expected == 0) and np.any(expected == profile.intensity_full_scale)
    np.testing.assert_array_equal(lidar_intensity.stored_signal(signal, r, profile), expected)


def test_hard_target_two_way_transmission():
    # models.md §3.2 oracle: e^{-2} = 0.1353 at 10 m with the reference α = 0.1
    assert lidar_medium.hard_target_signal(1.0, 0.1, 10.0) == pytest.approx(0.1353, rel=1e-3)


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
    assert lidar_medium.hard_target_signal(100.0, alpha, r_max) == pytest.approx(2.42, rel=1e-9)


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


def test_snow_medium_is_the_flake_snowfall_not_melted_drops():
    """models.md §3.4's oracles of the Gunn–Marshall law (N0 = 1712, Λ = 1.643, N0/Λ = 1042 m⁻³, melted-drop
    α = 1.21e-3 m⁻¹) hold for the law; the LiDAR medium uses flakes (models.md §2.3 correction,
    tests/physics/test_snow.py): N0 from the mass flux, extinction of the flakes' geometric size."""
    from roadview_noise.models.lidar.snow import SnowLidar

    n0, lam = dsd.gunn_marshall(2.5)
    assert n0 == pytest.approx(1712, rel=1e-3) and lam == pytest.approx(1.643, rel=1e-3)
    assert n0 / lam == pytest.approx(1042, rel=1e-3)
    assert dsd.geometric_extinction_per_m(n0, lam, 0.0, 50.0) == pytest.approx(1.21e-3, abs=0.005e-3)
    medium, snow = SnowLidar().medium(), dsd.snowfall(2.5)
    assert (medium.n0_per_m3_mm, medium.lam_per_mm, medium.d_max_mm) == (snow.n0_per_m3_mm, lam, snow.d_max_mm)
    assert medium.alpha_per_m == pytest.approx(snow.extinction_per_m(), rel=1e-12)
    assert medium.alpha_per_m > 7 * 1.21e-3
    assert medium.size.optical_mm(1.0) == pytest.approx((1 / 0.178) ** (1 / 2.078), rel=1e-9)   # ρ_w D_m³ = ρ D³


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


def _summed_peaks_numpy(first: np.ndarray, size: np.ndarray, c_range: np.ndarray, c_signal: np.ndarray,
                  length: float) -> tuple[np.ndarray, np.ndarray]:
    """NumPy reference of the compiled :func:`lidar_echo.cluster_peak`, vectorised over clusters (the implementation
    the package used before the compiled kernel).

    Exact maximum of ``S(x) = Σ a_k sin²(π (x − r_k)/L)`` (each term on ``r_k ≤ x ≤ r_k + L``) over each cluster
    (contributions ``first … first+size−1``, sorted by range); returns (peak, apparent range = x − L/2).

    Between consecutive pulse starts/ends the active set is fixed and ``S(x) = A/2 − Re(Z e^{iωx})/2`` with
    ``A = Σ a_k``, ``Z = Σ a_k e^{−iω r_k}``, ``ω = 2π/L``: on each piece the maximum is the crest ``(A + |Z|)/2``
    if the phasor ``Z e^{iωx}`` passes the negative real axis inside the piece, else an end value. Pieces come from
    one linear merge of the sorted starts and ends (``e^{iωx}`` at an end equals that at its start: period L)."""
    n = int(size.sum())
    clusters = len(first)
    block = np.cumsum(size) - size                         # first member of each cluster (member numbering)
    member_cluster = np.repeat(np.arange(clusters), size)
    member = np.arange(n) + np.repeat(first - block, size)
    r, a = c_range[member], c_signal[member]
    omega = 2 * np.pi / length
    cos_r, sin_r = np.cos(omega * r), np.sin(omega * r)    # e^{iωr} = cos + i sin
    span = 2.0 ** math.ceil(math.log2(float(r.max()) + 2 * length + 1))
    start_key = member_cluster * span + r                  # sorted: by cluster, then range
    order = np.argsort(np.concatenate([start_key, start_key + length]), kind="stable")   # merge of two runs
    ev_member = np.where(order < n, order, order - n)
    is_start = order < n
    x = r[ev_member] + np.where(is_start, 0.0, length)
    step = np.where(is_start, a[ev_member], -a[ev_member])   # +a at a pulse start, −a at its end
    cu, su = cos_r[ev_member], sin_r[ev_member]            # e^{iωx_i}
    amp = np.cumsum(step)                                  # A, Re Z, Im Z on [x_i, x_{i+1}]
    z_re = np.cumsum(step * cu)
    z_im = -np.cumsum(step * su)
    q_re, q_im = z_re * cu - z_im * su, z_re * su + z_im * cu          # Z e^{iωu}
    cv, sv = np.append(cu[1:], 1.0), np.append(su[1:], 0.0)            # e^{iωx_{i+1}}
    p_re, p_im = z_re * cv - z_im * sv, z_re * sv + z_im * cv          # Z e^{iωv}
    sweep = np.append(np.diff(x), 0.0) * omega
    upper_u = (q_im > 0) | ((q_im == 0) & (q_re < 0))
    upper_v = (p_im > 0) | ((p_im == 0) & (p_re < 0))
    crosses = np.where(sweep <= np.pi, upper_u & ~upper_v & (sweep > 0), ~(upper_v & ~upper_u))
    mod = np.sqrt(z_re * z_re + z_im * z_im)
    s_u, s_v = (amp - q_re) / 2, (amp - p_re) / 2
    val = np.where(crosses, (amp + mod) / 2, np.maximum(s_u, s_v))
    last = 2 * (block + size) - 1                          # the last event of a cluster opens no piece
    val[last] = -np.inf
    starts = 2 * block
    peak = np.maximum.reduceat(val, starts)
    ev_cluster = np.repeat(np.arange(clusters), 2 * size)
    best = np.minimum.reduceat(np.where(val == peak[ev_cluster], np.arange(2 * n), 2 * n), starts)
    delta = np.mod(np.pi - np.arctan2(q_im[best], q_re[best]), 2 * np.pi) / omega
    at = np.where(crosses[best], x[best] + delta, np.where(s_u[best] >= s_v[best], x[best], x[best + 1]))
    return peak, at - length / 2


def test_phasor_matches_libm_cos_and_sin():
    theta = np.concatenate([np.random.default_rng(4).uniform(0, 60, 20000), np.arange(0, 40) * np.pi / 8,
                            [0.0, 1e-300, 2 * np.pi - 1e-15]])
    got = np.array([lidar_echo.phasor(t) for t in theta])
    assert np.max(np.abs(got[:, 0] - np.cos(theta))) < 1e-14
    assert np.max(np.abs(got[:, 1] - np.sin(theta))) < 1e-14


def test_cluster_peak_compiled_against_numpy_reference_and_dense_grid():
    rng = np.random.default_rng(3)
    length = 3.0
    sizes = rng.integers(2, 9, 400)
    ranges, amps = [], []
    for s in sizes:
        ranges.append(np.sort(rng.uniform(1, 100) + np.cumsum(rng.uniform(0, 0.99 * length, s))))
        amps.append(rng.uniform(0, 1, s) * (rng.random(s) < 0.9))
    first = np.cumsum(sizes) - sizes
    r_all, a_all = np.concatenate(ranges), np.concatenate(amps)
    peak_np, at_np = _summed_peaks_numpy(first, sizes, r_all, a_all, length)
    cos, sin = np.cos(2 * np.pi * r_all / length), np.sin(2 * np.pi * r_all / length)
    for i, (r, a) in enumerate(zip(ranges, amps)):
        peak, at = lidar_echo.cluster_peak(r_all, a_all, cos, sin, first[i], first[i] + sizes[i], length)
        assert peak == pytest.approx(peak_np[i], rel=1e-9, abs=1e-12)
        if i < 150:
            x = np.linspace(r[0], r[-1] + length, 60001)
            dense = _profile(x, r, a, length)
            assert dense.max() - 1e-12 <= peak <= dense.max() + 1e-6
        assert _profile(np.array([at + length / 2]), r, a, length)[0] == pytest.approx(peak, rel=1e-9, abs=1e-12)
        assert _profile(np.array([at_np[i] + length / 2]), r, a, length)[0] == pytest.approx(peak, rel=1e-9, abs=1e-12)
        if sizes[i] == 2:                                  # the closed form of a pair
            pair, at2, _ = lidar_echo.pair_peak(r[0], a[0], r[1], a[1], length)
            assert pair == pytest.approx(peak, rel=1e-9, abs=1e-12)
            assert _profile(np.array([at2 + length / 2]), r, a, length)[0] == pytest.approx(peak, rel=1e-9, abs=1e-12)
            near, at3, own = lidar_echo.pair_peak(r[0], a[0], r[1], a[1], length, 0.2)   # no arc tangent when near
            assert near == pair and own == (abs(at2 - r[1]) <= 0.2) and at3 == (r[1] if own else at2)


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
        x = np.linspace(r[0], r[-1] + length, 4001)
        k = int(np.argmax(_profile(x, r, a, length)))
        x = np.linspace(x[max(k - 2, 0)], x[min(k + 2, len(x) - 1)], 4001)      # refine around the coarse maximum
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


@pytest.mark.parametrize("shadowing", [False, True])
@pytest.mark.parametrize("mode", ["strongest", "first"])
def test_select_returns_against_per_ray_reference(mode, shadowing):
    rng = np.random.default_rng((11 if mode == "strongest" else 12) + 2 * shadowing)
    n_rays, length, thr = 800, 2.99792458, 0.05
    t_range = rng.uniform(2, 30, n_rays)
    has_target = rng.random(n_rays) < 0.8
    t_sig = np.where(has_target, rng.uniform(0, 0.5, n_rays) * (rng.random(n_rays) < 0.8), 0.0)
    counts = rng.poisson(1.5, n_rays)
    ray = np.repeat(np.arange(n_rays), counts)
    p_range = np.concatenate([np.sort(rng.uniform(1, t_range[i], c)) for i, c in enumerate(counts)])
    p_sig = rng.uniform(0, 0.3, len(ray)) * (rng.random(len(ray)) < 0.9)
    p_frac = rng.uniform(0, 0.6, len(ray)) if shadowing else None
    out = lidar_echo.select_returns(ray, p_range, p_sig, t_range, t_sig, has_target, length / C, thr, mode, p_frac)
    for i in range(n_rays):
        sel = ray == i
        if not sel.any():
            continue
        shadowed = t_sig[i] * (1 - min(1.0, p_frac[sel].sum())) if shadowing else t_sig[i]
        kind, rng_, sig = _brute_force_ray(p_range[sel], p_sig[sel], t_range[i], shadowed, has_target[i],
                                           length, thr, mode)
        assert out.kind[i] == kind, i
        if kind != NO_RETURN:
            assert out.signal[i] == pytest.approx(sig, rel=1e-3), i
            assert out.range_m[i] == pytest.approx(rng_, abs=0.005), i


def test_select_returns_simple_cases():
    length = lidar_medium.pulse_length_m(10e-9)
    t_range = np.array([20.0, 20.0, 20.0, 120.0])
    t_sig = np.array([0.5, 0.01, 0.5, 0.0])
    has = np.array([True, True, True, False])
    # ray 0: weak far drop → target; ray 1: drop stronger than the target → drop; ray 2: drop 0.5 m in front of a
    # strong target → same target, summed; ray 3: empty ray with a drop → weather return
    ray = np.array([0, 1, 2, 3])
    p_range = np.array([5.0, 5.0, 19.5, 3.0])
    p_sig = np.array([0.02, 0.02, 0.04, 0.02])
    out = lidar_echo.select_returns(ray, p_range, p_sig, t_range, t_sig, has, 10e-9, 0.005, "strongest")
    assert list(out.kind) == [TARGET, WEATHER, TARGET, WEATHER]
    assert out.range_m[1] == 5.0 and out.range_m[3] == 3.0 and out.range_m[2] == 20.0
    assert 0.5 < out.signal[2] < 0.54
    first = lidar_echo.select_returns(ray, p_range, p_sig, t_range, t_sig, has, 10e-9, 0.005, "first")
    assert list(first.kind) == [WEATHER, WEATHER, TARGET, WEATHER]
    assert length == pytest.approx(2.998, abs=1e-3)


# --- particle sampler -------------------------------------------------------------------------------------------


def _medium(rate=20.0):
    n0, lam = dsd.marshall_palmer(rate)
    return lidar_particles.ParticleMedium(n0, lam, 0.5, 6.0, 0.0199, dsd.geometric_extinction_per_m(n0, lam, 0.5, 6))


def _table_at(table, values, r):
    """A per-range table of :class:`lidar_particles.VisibleTable` interpolated at ranges r (clamped)."""
    grid = table.start_m + np.arange(len(table.cum)) * table.step_m
    return np.interp(r, grid, values)


def _place_numpy(spacing, exp_d, cum_ray, ray_range_m, table, medium, beam):
    """NumPy reference of the compiled ``lidar_particles._place`` (the package's former vectorised version)."""
    n = len(exp_d)
    u = np.cumsum(spacing[:n])
    u *= cum_ray[-1] / (u[-1] + spacing[n])
    ray = np.searchsorted(cum_ray, u, side="right")
    start = np.where(ray > 0, cum_ray[np.maximum(ray - 1, 0)], 0.0)
    x = np.minimum((u - start) * (1 / table.inv_step), len(table.inv_range_m) - 1.000001)
    k = x.astype(np.intp)
    r = table.inv_range_m[k] + (table.inv_range_m[k + 1] - table.inv_range_m[k]) * (x - k)
    r = np.minimum(r, ray_range_m[ray])
    x = np.clip((r - table.start_m) * (1 / table.step_m), 0.0, len(table.cum) - 1.000001)
    k = x.astype(np.intp)
    lerp = lambda t: t[k] + (t[k + 1] - t[k]) * (x - k)                        # noqa: E731
    d_low, full = lerp(table.d_low_mm), lerp(table.full_beam)
    d = d_low + exp_d * (1 / medium.lam_per_mm)
    over = np.flatnonzero(d > medium.d_max_mm)
    d[over] = d_low[over]
    f = np.minimum(1.0, (medium.size.optical_mm(d) * 0.5e-3 / beam.radius_at(r)) ** 2)
    f[over] = 0.0
    signal = np.where(f > 0, full * f, full)
    return ray, r, d, f, signal, over


HAHNER = (0.9, 1.0)            # Hahner's receiver overlap R1, R2 (m)


@pytest.mark.parametrize("flakes", [False, True], ids=["drops", "flakes"])
def test_compiled_particle_placement_against_numpy_reference(flakes):
    medium, beam = _medium(50.0), lidar_particles.Beam(4.75e-3, 3e-3, *HAHNER)
    medium = dataclasses.replace(medium, d_max_mm=2.5)                          # some diameters above Dmax
    if flakes:                                                                  # geometric size of dry snowflakes
        medium = dataclasses.replace(medium, size=dsd.SNOW_HABITS["dry_aggregates"].size, reflectance=0.9)
    level = 0.5 * 3.28 / 65535
    table = lidar_particles.visible_table(medium, beam, level)
    rng = np.random.default_rng(5)
    ranges = np.where(rng.random(5000) < 0.1, 0.0, rng.uniform(0.5, 150.0, 5000))
    cum_ray = lidar_particles._ray_measures(ranges, table.start_m, table.step_m, table.cum[None, :])
    lam = np.where(ranges > 0, _table_at(table, table.cum, ranges), 0.0)
    np.testing.assert_allclose(np.diff(cum_ray, prepend=0.0), lam, rtol=1e-9, atol=1e-12)
    n = 20000
    spacing, exp_d = rng.standard_exponential(n + 1), rng.standard_exponential(n)
    got = lidar_particles._place(spacing, exp_d, cum_ray, ranges, table.inv_range_m[None, :], table.inv_step,
                                 table.start_m, table.step_m, table.d_low_mm[None, :], table.full_beam[None, :],
                                 medium.lam_per_mm, medium.d_max_mm, beam.radius_m, beam.divergence_rad / 2,
                                 medium.size.coefficient, medium.size.exponent, medium.size.solid)
    ref = _place_numpy(spacing, exp_d, cum_ray, ranges, table, medium, beam)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[5], ref[5])
    assert 0 < len(ref[5]) < n / 10
    for g, e in zip(got[1:5], ref[1:5]):
        np.testing.assert_allclose(g, e, rtol=1e-12)


@pytest.mark.parametrize("r1, r2", [HAHNER, (0.5, 5.0)], ids=["hahner", "os1"])
def test_visible_count_table_matches_integration(r1, r2):
    """Λ(r) of the cached table against quad of the visible density, with the beam's own overlap ξ (R1, R2)."""
    medium, beam, level = _medium(), lidar_particles.Beam(4.75e-3, 3e-3, r1, r2), 2.0 / 65535
    table = lidar_particles.visible_table(medium, beam, level)
    assert table.start_m == r1

    def density(r):                                       # written out independently of the module
        w = 4.75e-3 + r * 1.5e-3
        full = 0.0199 * min(1.0, (r - r1) / (r2 - r1)) * math.exp(-2 * medium.alpha_per_m * r) / r ** 2
        if full < level:
            return 0.0
        d_c = max(0.5, 2e3 * w * math.sqrt(level / full))
        if d_c >= 6.0:
            return 0.0
        return math.pi * w * w * medium.n0_per_m3_mm / medium.lam_per_mm * (
            math.exp(-medium.lam_per_mm * d_c) - math.exp(-medium.lam_per_mm * 6.0))

    for r in (1.5, 3.0, 6.0, 10.0):
        expected = integrate.quad(density, r1, r, limit=400)[0]
        assert _table_at(table, table.cum, r) == pytest.approx(expected, rel=2e-3)


def test_particle_tables_and_draws_follow_the_beam_overlap():
    """The cached visible table keys on the overlap: a slow overlap (OS1, full at 5 m) starts the table at R1 = 0.5 m
    and holds fewer visible drops near the sensor; drawn particles lie beyond its R1."""
    medium, level = _medium(50.0), 1.0 / 65535
    fast = lidar_particles.visible_table(medium, lidar_particles.Beam(4.75e-3, 0.0, *HAHNER), level)
    slow = lidar_particles.visible_table(medium, lidar_particles.Beam(4.75e-3, 0.0, 0.5, 5.0), level)
    assert slow is not fast and (fast.start_m, slow.start_m) == (0.9, 0.5)
    assert _table_at(slow, slow.cum, 3.0) < _table_at(fast, fast.cum, 3.0) and slow.cum[-1] < fast.cum[-1]
    ranges = np.full(20000, 30.0)
    p = lidar_particles.sample_particles(np.random.default_rng(1), ranges, medium,
                                         lidar_particles.Beam(4.75e-3, 0.0, 0.5, 5.0), 2 * level)
    assert len(p.ray) > 100 and p.range_m.min() >= 0.5 and np.mean(p.range_m < 0.9) > 0


def test_sampler_statistics_and_order():
    medium, beam = _medium(50.0), lidar_particles.Beam(4.75e-3, 0.0, *HAHNER)
    threshold = 1.0 / 65535
    ranges = np.tile(np.array([0.5, 2.0, 5.0, 12.0, 120.0]), 4000)
    rng = np.random.default_rng(7)
    p = lidar_particles.sample_particles(rng, ranges, medium, beam, threshold)
    table = lidar_particles.visible_table(medium, beam, lidar_particles.VISIBLE_FRACTION * threshold)
    expected = float(np.sum(np.where(ranges > 0.9, _table_at(table, table.cum, ranges), 0.0)))
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
    cdf = _table_at(table, table.cum, np.array([1.2, 1.5, 2.0, 3.0])) / table.cum[-1]
    emp = np.array([np.mean(p.range_m[far] <= x) for x in (1.2, 1.5, 2.0, 3.0)])
    assert np.all(np.abs(emp - cdf) < 4 * np.sqrt(cdf * (1 - cdf) / far.sum()) + 1e-3)


def test_faint_cross_section_and_backscatter_against_quadrature():
    """The undrawn particles' beam cover per metre, ``∫_{D < D_c} N(D) min(πD²/4, πw²) dD``, and their backscatter
    density ``ρ ξ e^{−2αr}/r²`` times it, against quad over the DSD written out here (a wide beam makes the
    beam-filling branch matter)."""
    medium = dataclasses.replace(_medium(50.0), reflectance=0.9)
    beam, level = lidar_particles.Beam(1.0e-3, 2e-4, 0.5, 5.0), 2.0 / 65535
    for r in (0.7, 3.0, 12.0, 60.0, 400.0):
        w = 1.0e-3 + r * 1e-4
        full = 0.9 * min(1.0, (r - 0.5) / 4.5) * math.exp(-2 * medium.alpha_per_m * r) / r ** 2
        d_c = 2e3 * w * math.sqrt(level / full) if full >= level else math.inf

        def cover(d):
            return medium.n0_per_m3_mm * math.exp(-medium.lam_per_mm * d) * min(math.pi * (d * 1e-3) ** 2 / 4,
                                                                                 math.pi * w * w)
        hi = min(d_c, 6.0)
        expected = integrate.quad(cover, 0.5, hi, points=[2e3 * w] if 0.5 < 2e3 * w < hi else None)[0] if hi > 0.5 \
            else 0.0
        got = lidar_particles.faint_cross_section_per_m(medium, beam, level, r)
        assert got == pytest.approx(expected, rel=1e-9, abs=1e-15)
        assert lidar_particles.faint_backscatter_per_m(medium, beam, level, r) == pytest.approx(full * expected,
                                                                                                rel=1e-9, abs=1e-18)


def test_soft_background_against_direct_pulse_integral():
    """``B(x; R0) = ∫_{x−L}^{min(x, R0)} sin²(π(x − r)/L) b(r) dr`` from the cumulative tables (compiled evaluator and
    the target-crest table) against quad, for the continuous b(r) = (r − 1) e^{−r/7} (r ≥ 1) on a 0.05 m grid."""
    length, step = 3.0, 0.05
    r = np.arange(0.0, 200.0, step)
    b = np.where(r >= 1.0, (r - 1.0) * np.exp(-r / 7.0), 0.0)
    bg = lidar_echo.SoftBackground.of_density(b, step, length)

    def direct(x, r0):
        lo, hi = max(x - length, 1.0), min(x, r0)
        return integrate.quad(lambda s: np.sin(np.pi * (x - s) / length) ** 2 * (s - 1) * math.exp(-s / 7.0),
                              lo, hi)[0] \
            if hi > lo else 0.0

    at = lidar_echo.background_at.py_func if hasattr(lidar_echo.background_at, "py_func") else lidar_echo.background_at
    for x, r0 in ((2.0, 50.0), (3.7, 50.0), (10.0, 50.0), (10.0, 8.5), (9.0, 9.2), (0.5, 50.0), (250.0, 300.0)):
        assert at(x, r0, bg.cum[None], 0, 1 / step, length) == pytest.approx(direct(x, r0), rel=5e-3, abs=1e-7)
    for r0 in (2.0, 6.05, 30.0):
        assert bg.at_target[round(r0 / step)] == pytest.approx(direct(r0 + length / 2, r0), rel=5e-3, abs=1e-7)
    xs = np.arange(0.0, 20.0, 0.01)
    assert bg.peak == pytest.approx(max(direct(x, np.inf) for x in xs), rel=2e-3)
    peak = lidar_echo.peak_background.py_func if hasattr(lidar_echo.peak_background, "py_func") \
        else lidar_echo.peak_background
    for x, r0 in ((2.0, 50.0), (3.71, 50.0), (10.02, 50.0), (10.0, 8.5), (9.0, 9.2), (0.5, 50.0), (250.0, 300.0)):
        exact = at(x, r0, bg.cum[None], 0, 1 / step, length)          # the uncut table where no target cuts it
        assert peak(x, r0, bg.cum[None], bg.uncut[None], 0, 1 / step, length) == pytest.approx(exact, rel=2e-3,
                                                                                               abs=1e-6)
        assert peak(x, r0, bg.cum[None], bg.uncut[None, :0], 0, 1 / step, length) == exact


def test_background_adds_to_clusters_and_targets():
    """With a background, a lone particle returns ``a + B(r + L/2)``, a target ``S_t + B`` at its crest, and a
    particle that alone is below the threshold is detected when the background lifts it over."""
    length, step = 3.0, 0.05
    b = np.where(np.arange(0.0, 200.0, step) >= 1.0, 2e-3, 0.0)            # B ≈ 3e-3 (L/2 · b) away from edges
    bg = lidar_echo.SoftBackground.of_density(b, step, length)
    thr = 0.01
    ray, p_range, p_sig = np.array([0, 1, 2]), np.array([10.0, 10.0, 10.0]), np.array([0.02, 0.008, 0.006])
    t_range, t_sig, has = np.array([40.0, 40.0, 40.0]), np.array([0.005, 0.005, 0.02]), np.array([True, True, True])
    out = lidar_echo.select_returns(ray, p_range, p_sig, t_range, t_sig, has, length / C, thr, "strongest",
                                    background=bg)
    np.testing.assert_allclose(out.signal[:2], [0.02 + 3e-3, 0.008 + 3e-3], rtol=1e-6)
    assert list(out.kind) == [WEATHER, WEATHER, TARGET]
    assert out.signal[2] == pytest.approx(0.02 + 1.5e-3, rel=1e-3)           # half the window in front of R0
    plain = lidar_echo.select_returns(ray, p_range, p_sig, t_range, t_sig, has, length / C, thr, "strongest")
    assert list(plain.kind) == [WEATHER, NO_RETURN, TARGET]


def test_sampler_diameters_follow_truncated_exponential_above_visibility_bound():
    medium, beam = _medium(20.0), lidar_particles.Beam(4.75e-3, 0.0, *HAHNER)
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


@pytest.mark.parametrize("block_rows", [7, 64, 1 << 20])
def test_lambda_table_does_not_depend_on_its_blocks(block_rows):
    """The Λ tables of the strongest-return draw are summed in range blocks (bounded memory); every block size gives
    the values of one cumulative sum over the whole range."""
    from roadview_noise.physics.lidar_particles import Beam, ParticleMedium
    from roadview_noise.physics.lidar_strongest import SUBSTEPS, RANGE_STEP_M, _tabled_lambda

    medium = ParticleMedium(n0_per_m3_mm=8000.0, lam_per_mm=2.0, d_min_mm=0.1, d_max_mm=6.0, reflectance=0.9,
                            alpha_per_m=0.005)
    beam = Beam(radius_m=0.005, divergence_rad=3e-3, overlap_start_m=0.5, overlap_full_m=5.0)
    fine = RANGE_STEP_M / SUBSTEPS
    r = 0.5 + np.arange(0.0, 60.0, fine)
    levels = 1e-7 * 2.0 ** (np.arange(40) / 4)
    whole, last_whole = _tabled_lambda(medium, beam, levels, r, fine, block_rows=len(r) + 1)
    blocks, last_blocks = _tabled_lambda(medium, beam, levels, r, fine, block_rows=block_rows)
    assert last_blocks == last_whole and np.array_equal(blocks, whole)
    assert np.all(np.diff(whole, axis=0) >= 0) and whole[-1, 0] > 0
