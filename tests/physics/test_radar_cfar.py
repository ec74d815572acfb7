"""Clutter detectors (physics/radar_cfar.py): CA-CFAR multiplier, per-cell clutter detection probability against
numerical integration and a Monte-Carlo CA-CFAR, the conditional RCS of detected cells, the threshold rise."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, stats

from roadview_noise.physics.radar_cfar import CaCfar, FixedThreshold, ca_cfar_multiplier, tier_ratios


@pytest.mark.parametrize("pfa, n", [(1e-4, 16), (1e-6, 16), (1e-3, 8), (1e-2, 32)])
def test_multiplier_gives_the_false_alarm_probability(pfa, n):
    """Richards (2014) §6.5.3: P_fa = (1 + α/N)^(−N) in exponential noise."""
    alpha = ca_cfar_multiplier(pfa, n)
    assert (1 + alpha / n) ** (-n) == pytest.approx(pfa, rel=1e-12)
    assert ca_cfar_multiplier(1e-4, 16) == pytest.approx(16 * (10 ** 0.25 - 1), rel=1e-12)   # 12.4525, 10.95 dB


def test_monte_carlo_ca_cfar_false_alarm_rate():
    """Noise-only cells: cell under test and N reference cells i.i.d. exponential; declared when x > α mean(ref)."""
    rng = np.random.default_rng(3)
    pfa, n, trials = 1e-2, 16, 400_000
    alpha = ca_cfar_multiplier(pfa, n)
    ref = rng.standard_exponential((trials, n)).mean(axis=1)
    rate = np.mean(rng.standard_exponential(trials) > alpha * ref)
    assert rate == pytest.approx(pfa, abs=5 * math.sqrt(pfa / trials))


def _probability_by_quadrature(y: float, pfa: float, n: int) -> float:
    """E[exp(−max(T, α)/x)], T ~ Gamma(N, α(1 + x)/N), x = α y (noise units), by numerical integration."""
    alpha = ca_cfar_multiplier(pfa, n)
    x = alpha * y
    t = stats.gamma(n, scale=alpha * (1 + x) / n)
    below = t.cdf(alpha) * math.exp(-alpha / x)
    hi = t.ppf(1 - 1e-16)
    above = integrate.quad(lambda s: t.pdf(s) * math.exp(-s / x), alpha, max(hi, alpha), points=[t.mean()],
                           epsabs=0, epsrel=1e-11, limit=400)[0] if hi > alpha else 0.0
    return below + above


@pytest.mark.parametrize("y", [0.05, 0.2, 1.0, 3.0, 30.0, 1e4])
def test_probability_against_quadrature(y):
    cfar = CaCfar(1e-4, 16)
    assert float(cfar.probability(y)) == pytest.approx(_probability_by_quadrature(y, 1e-4, 16), rel=1e-7)


def test_probability_against_a_simulated_cfar_in_rain():
    """Reference cells: power of clutter + noise, |c + w|², exponential with mean μ + n (complex Gaussian sum).
    Declared as clutter when the cell's clutter echo alone, Exp(μ), exceeds max(α · mean(ref), α n)."""
    rng = np.random.default_rng(4)
    pfa, n, trials = 0.05, 8, 400_000
    cfar = CaCfar(pfa, n)
    alpha = cfar.multiplier
    for y in (0.1, 0.5, 4.0):
        mu, noise = alpha * y, 1.0
        ref = np.abs(rng.normal(0, math.sqrt(mu / 2), (trials, n, 2))
                     + rng.normal(0, math.sqrt(noise / 2), (trials, n, 2))) ** 2
        ref = ref.sum(axis=2).mean(axis=1)
        hits = rng.exponential(mu, trials) > np.maximum(alpha * ref, alpha * noise)
        p = float(cfar.probability(y))
        assert hits.mean() == pytest.approx(p, abs=5 * math.sqrt(p / trials) + 1e-6)


def test_limits_bounds_and_monotonicity():
    cfar = CaCfar(1e-4, 16)
    y = np.geomspace(1e-3, 1e9, 4000)
    p = cfar.probability(y)
    assert np.all(np.diff(p) >= 0)
    assert np.all(p <= 1e-4 * (1 + 1e-12)) and np.all(p <= FixedThreshold().probability(y) * (1 + 1e-12))
    assert p[-1] == pytest.approx(1e-4, rel=1e-6)          # clutter-dominated cell: the CFAR keeps P_fa
    assert float(cfar.probability(0.0)) == 0.0 and float(FixedThreshold().probability(0.0)) == 0.0
    assert FixedThreshold().probability(2.0) == pytest.approx(math.exp(-0.5))


@pytest.mark.parametrize("detector", [CaCfar(1e-4, 16), CaCfar(1e-2, 4), FixedThreshold()])
def test_tiers(detector):
    y = tier_ratios(detector)
    assert np.all(np.diff(y) < 0) and len(y) == 30
    np.testing.assert_allclose(detector.probability(y), detector.max_probability * 0.5 ** np.arange(1, 31),
                               rtol=1e-8)


def test_detected_rcs_follows_the_conditional_law():
    """σ given a detection, drawn in closed form, against rejection sampling of the simulated detector."""
    pfa, n = 0.05, 6
    cfar = CaCfar(pfa, n)
    alpha = cfar.multiplier
    rng = np.random.default_rng(5)
    for y in (0.3, 3.0):
        x = alpha * y
        trials = 600_000
        t = np.maximum(rng.gamma(n, alpha * (1 + x) / n, trials), alpha)
        sigma = rng.exponential(x, trials)
        simulated = sigma[sigma > t] / alpha
        drawn = cfar.rcs_over_threshold(np.random.default_rng(6), np.full(20_000, y))
        assert drawn.min() >= 1.0 and len(simulated) > 2000
        assert stats.ks_2samp(drawn, simulated).pvalue > 1e-3
    fixed = FixedThreshold().rcs_over_threshold(np.random.default_rng(7), np.full(20_000, 2.0))
    assert stats.kstest(fixed - 1, stats.expon(scale=2.0).cdf).pvalue > 1e-3


def test_threshold_rise():
    cfar = CaCfar(1e-4, 16)
    assert float(cfar.threshold_rise_db(0.0)) == 0.0
    assert float(cfar.threshold_rise_db(1.0)) == pytest.approx(10 * math.log10(1 + 12.452470560622764))
    assert np.all(FixedThreshold().threshold_rise_db(np.array([0.0, 5.0])) == 0.0)
    with pytest.raises(ValueError):
        CaCfar(0.0, 16)
