"""The LiDAR receiver (physics/receiver.py): noise, detection probability, measured values of new returns, range
jitter and the threshold calibrated from the data — against scipy and independent Monte Carlo."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import optimize
from scipy.constants import speed_of_light
from scipy.special import ndtri
from scipy.stats import norm, poisson

from roadview_noise.physics import receiver as R
from roadview_noise.profiles.lidar import os1_128, vls_128

SPAD = R.Receiver.of(os1_128())                    # threshold 3.28 photons, one background photon per pulse window
APD = R.Receiver.of(vls_128())                     # threshold 1, 100 photo-electrons there, F = 3, T = 4 σ0


@R.jit
def _quantiles(p):       # pragma: no cover - compiled
    out = np.empty(len(p))
    for i in range(len(p)):
        out[i] = R.normal_quantile(p[i])
    return out


@R.jit
def _poisson(mean, u):       # pragma: no cover - compiled
    out = np.empty(len(u))
    for i in range(len(u)):
        out[i] = R.poisson_quantile(mean[i], u[i])
    return out


def test_normal_quantile_against_scipy():
    p = np.concatenate([np.geomspace(1e-12, 0.5, 400), 1 - np.geomspace(1e-12, 0.5, 400)])
    np.testing.assert_allclose(_quantiles(p), ndtri(p), rtol=2e-9, atol=1e-9)


def test_poisson_quantile_is_exact_below_the_normal_branch_and_close_above():
    rng = np.random.default_rng(0)
    u = rng.random(20000)
    small = rng.uniform(0.0, R.LARGE_COUNT - 1e-9, len(u))
    np.testing.assert_array_equal(_poisson(small, u), poisson.ppf(u, small))
    large = rng.uniform(R.LARGE_COUNT, 500.0, len(u))
    assert np.max(np.abs(_poisson(large, u) - poisson.ppf(u, large))) <= 2 + 0.3 * np.sqrt(500)
    assert np.mean(_poisson(large, u) - large) == pytest.approx(0.0, abs=0.2)


def test_profiles_receivers():
    assert SPAD.photon_counting and SPAD.counts_photons and SPAD.background_photons == pytest.approx(1.0)
    assert SPAD.detection_count == 5 and SPAD.photons_per_signal == pytest.approx(1.0)
    assert not APD.photon_counting and APD.noise_floor == pytest.approx(0.25) and APD.excess_noise_factor == 3.0
    k = 65535.0
    assert R.Receiver.of(os1_128(), k).threshold == pytest.approx(3.28 / k)
    assert R.Receiver.of(os1_128(), k).photons_per_signal == pytest.approx(k)       # photons are what they are


def test_rise_time_of_the_sin2_pulse():
    t10 = optimize.brentq(lambda t: math.sin(math.pi * t / 2) ** 2 - 0.1, 0, 1)
    t90 = optimize.brentq(lambda t: math.sin(math.pi * t / 2) ** 2 - 0.9, 0, 1)
    assert R.RISE_TIME_PER_TAU == pytest.approx(t90 - t10, rel=1e-9)
    assert R.RISE_TIME_PER_TAU == pytest.approx(0.5903, abs=1e-4)


def test_range_jitter_closed_form():
    """σ_R = (c/2) t_r / SNR with SNR = S/σ(S): 3 cm at SNR 30 for a 10 ns pulse."""
    s = np.array([3.28, 30.0, 300.0, 3000.0])
    snr = s / np.sqrt(1.0 + s)                                        # Poisson: σ² = B + S, B = 1 photon
    np.testing.assert_allclose(SPAD.range_sd_m(s), speed_of_light / 2 * 0.5903345 * 10e-9 / snr, rtol=1e-6)
    s30 = optimize.brentq(lambda x: x / math.sqrt(1 + x) - 30, 10, 2000)
    assert float(SPAD.range_sd_m(s30)) == pytest.approx(0.0295, abs=2e-4)


@pytest.mark.parametrize("signal", [0.5, 2.0, 3.28, 6.0, 20.0])
def test_spad_detection_probability_against_monte_carlo(signal):
    """P(N_s + N_b ≥ ⌈B + gT⌉), N_s ~ Poisson(S), N_b ~ Poisson(1): the closed form against direct draws."""
    rng = np.random.default_rng(1)
    n = 200_000
    counts = rng.poisson(signal, n) + rng.poisson(1.0, n)
    p = float(SPAD.detection_probability(signal))
    assert np.mean(counts >= 5) == pytest.approx(p, abs=4 * math.sqrt(p * (1 - p) / n) + 1e-6)


@pytest.mark.parametrize("signal", [0.3, 1.0, 1.5, 3.0])
def test_linear_detection_probability_against_monte_carlo(signal):
    rng = np.random.default_rng(2)
    n = 200_000
    measured = signal + 0.25 * rng.standard_normal(n) + math.sqrt(3 * signal / 100) * rng.standard_normal(n)
    p = float(APD.detection_probability(signal))
    assert np.mean(measured >= 1.0) == pytest.approx(p, abs=4 * math.sqrt(p * (1 - p) / n) + 1e-6)


@pytest.mark.parametrize("rx", [SPAD, APD], ids=["spad", "apd"])
def test_new_returns_add_only_the_detections_their_signal_causes(rx):
    """The background is drawn conditioned on not detecting by itself: no return at S = 0, and at S > 0 the detected
    fraction is the conditioned probability (SPAD: summed directly; APD: Monte Carlo with rejection)."""
    rng = np.random.default_rng(3)
    n = 100_000
    for s in (0.0, 0.3 * rx.threshold, rx.threshold, 3 * rx.threshold):
        measured, detected, jitter = rx.measure(np.full(n, s), rng.random((n, 3)))
        if rx.photon_counting:
            m = rx.detection_count
            nb = np.arange(m)
            w = poisson.pmf(nb, rx.background_photons)
            p = float(np.sum(w * poisson.sf(m - nb - 1, s)) / w.sum())
        else:
            b = rng.standard_normal(4 * n) * rx.noise_floor
            b = b[b < rx.threshold][:n]
            total = s + b + math.sqrt(3 * s / 100) * rng.standard_normal(len(b))
            p = float(np.mean(total >= rx.threshold))
        got = np.mean(detected)
        assert got == pytest.approx(p, abs=4 * math.sqrt(max(p * (1 - p), 1e-6) / n) + 2e-4), s
        if s == 0:
            assert not detected.any()
        np.testing.assert_array_equal(detected, measured >= rx.threshold * (1 - 1e-12))
        assert abs(np.mean(jitter)) < 0.02 and np.std(jitter) == pytest.approx(1.0, abs=0.02)


def test_measured_signal_is_unbiased_above_the_noise():
    rng = np.random.default_rng(4)
    for rx, s in ((SPAD, 50.0), (APD, 5.0)):
        measured, detected, _ = rx.measure(np.full(100_000, s), rng.random((100_000, 3)))
        assert detected.all()
        assert np.mean(measured) == pytest.approx(s, rel=0.01)
        assert np.std(measured) == pytest.approx(float(rx.noise_sd(s)), rel=0.03)


def test_rows_tie_draws_to_rays():
    u = np.random.default_rng(5).random((10, 3))
    a = SPAD.measure(np.array([5.0, 7.0]), u, np.array([3, 8]))
    b = SPAD.measure(np.array([5.0, 7.0]), u[[3, 8]])
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_weakest_return_is_where_detections_start():
    for rx in (SPAD, APD):
        w = rx.weakest_return
        base = float(rx.detection_probability(0.0))
        assert 0 < w < rx.threshold
        assert float(rx.detection_probability(w)) - base == pytest.approx(R.NEGLIGIBLE_DETECTION, rel=1e-3)


@pytest.mark.parametrize("weakest", [5.0, 3.28, 1.0, 0.07, 1e-4])
def test_calibrated_threshold_lies_below_every_recorded_return_on_a_fixed_grid(weakest):
    cal = SPAD.calibrated(weakest)
    if weakest >= SPAD.threshold:
        assert cal == SPAD
        return
    assert cal.threshold < weakest <= cal.threshold * 2 ** 0.25 * (1 + 1e-12)
    j = -4 * math.log2(cal.threshold / SPAD.threshold)
    assert j == pytest.approx(round(j), abs=1e-9)
    # the same photons at the threshold: the detector's statistics relative to its threshold are the profile's
    assert cal.photons_at_threshold == SPAD.photons_at_threshold and "calibrated" in cal.source
    assert float(cal.detection_probability(2 * cal.threshold)) == pytest.approx(
        float(SPAD.detection_probability(2 * SPAD.threshold)), rel=1e-12)
    nearby = SPAD.calibrated(weakest * 1.01).threshold / cal.threshold      # a similar frame: the same or next step
    assert min(abs(nearby - 1), abs(nearby - 2 ** 0.25)) < 1e-9


def test_large_photon_counts_fall_back_to_gaussian_noise():
    big = dataclasses.replace(SPAD, photons_at_threshold=1e6)
    assert big.photon_counting and not big.counts_photons
    s = 2 * big.threshold
    assert float(big.detection_probability(s)) == pytest.approx(norm.cdf((s - big.threshold) / big.noise_sd(s)))
