"""Low-light photon-transfer model (models.md §2.8 physical back-end; EMVA 1288): identity without noise, mean
scaled by k·g, variance linear in the signal (shot-noise regime), exact Poisson option, inverse-CDF normals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from roadview_noise.physics.sensor_noise import SensorSettings, expose, normal_table, uniform_bits


def settings(k=1e-3, g=8.0, fw=10000.0, read=3.0, dark=0.0, bits=12, black=64.0):
    return SensorSettings(k, g, fw, read, dark, float((1 << bits) - 1), black)


def test_normal_table_is_a_standard_normal():
    rng = np.random.default_rng(0)
    z = normal_table()[uniform_bits(rng, 2_000_000)]
    assert abs(z.mean()) < 2e-3 and z.var() == pytest.approx(1.0, abs=3e-3)
    assert stats.kstest(z[:200_000], "norm").statistic < 5e-3
    assert normal_table()[-1] == pytest.approx(4.325, abs=1e-3)       # tails clipped at ±4.3σ


def test_ratio_one_without_noise_is_identity_within_quantisation():
    rng = np.random.default_rng(1)
    img = rng.random((64, 80, 3)).astype(np.float32)
    out = expose(img, settings(k=1.0, g=1.0), rng, noise=False)
    step = 1.0 / ((1 << 12) - 1 - 64)
    assert np.abs(out - img).max() <= 0.5 * step + 1e-6
    mosaic = img[..., 1]
    assert np.abs(expose(mosaic, settings(k=1.0, g=1.0), rng, shot_noise="off", noise=False) - mosaic).max() <= \
        0.5 * step + 1e-6



@pytest.mark.parametrize("shot_noise", ["off", "gaussian", "poisson"])
def test_values_below_black_are_scaled_not_clipped(shot_noise):
    """A raw mosaic's codes below black (its recorded read noise, x < 0) are a measurement: at k = g = 1 without
    noise they come back, at k = ½ halved (before: raised to black)."""
    rng = np.random.default_rng(4)
    x = np.linspace(-0.02, 0.02, 81, dtype=np.float32)[None, :]
    step = 1.0 / ((1 << 16) - 1 - 2048)
    same = expose(x, settings(k=1.0, g=1.0, bits=16, black=2048.0), rng, shot_noise=shot_noise, noise=False)
    assert np.abs(same - x).max() <= 0.5 * step + 1e-7
    half = expose(np.repeat(x, 20_000, axis=0), settings(k=0.5, g=1.0, read=0.0, bits=16, black=2048.0), rng,
                  shot_noise=shot_noise)
    np.testing.assert_allclose(half.mean(axis=0), 0.5 * x[0], atol=2e-5)

@pytest.mark.parametrize("shot_noise", ["gaussian", "poisson"])
def test_mean_scales_by_k_g_and_variance_grows_linearly(shot_noise):
    """Flat patches at 8 levels: mean = k·g·x; variance = (g/FW)²(k x FW + σ_r²) + q²/12, slope g² k / FW."""
    rng = np.random.default_rng(2)
    s = settings(k=0.02, g=4.0, read=1.0, bits=16)
    levels = np.linspace(0.1, 0.8, 8, dtype=np.float32)
    img = np.repeat(levels[:, None], 200_000, axis=1)                     # one row per level (mosaic layout)
    out = expose(img, s, rng, shot_noise=shot_noise)
    mean, var = out.mean(axis=1), out.var(axis=1)
    np.testing.assert_allclose(mean, s.luminance_factor * levels, rtol=2e-3)
    slope, intercept = np.polyfit(levels, var, 1)
    assert slope == pytest.approx(s.gain ** 2 * s.illuminance_ratio / s.full_well_e, rel=0.10)
    q = 1.0 / s.adc_levels
    assert intercept == pytest.approx((s.gain / s.full_well_e) ** 2 * s.read_noise_e ** 2 + q * q / 12, rel=0.5)


def test_read_noise_floor_and_black_offset_keep_the_mean_unbiased():
    rng = np.random.default_rng(3)
    dark = np.zeros((500, 500), np.float32)
    out = expose(dark, settings(k=1e-3, g=8.0, read=3.0), rng)
    assert abs(out.mean()) < 2e-5                                         # negative excursions kept
    assert out.std() == pytest.approx(8 * 3 / 10000, rel=0.05)           # g σ_r / FW


def test_white_balance_is_undone_and_redone():
    rng = np.random.default_rng(4)
    img = np.full((300, 300, 3), 0.5, np.float32)
    out = expose(img, settings(k=0.01, g=4.0, read=0.0), rng, white_balance=(2.0, 1.0, 1.5))
    np.testing.assert_allclose(out.reshape(-1, 3).mean(axis=0), 0.04 * 0.5, rtol=5e-3)
    var = out.reshape(-1, 3).var(axis=0)                                  # fewer electrons in R and B: noisier
    np.testing.assert_allclose(var / var[1], [2.0, 1.0, 1.5], rtol=0.06)


def test_bad_shot_noise_name():
    with pytest.raises(ValueError, match="shot_noise"):
        expose(np.zeros((2, 2), np.float32), settings(), np.random.default_rng(0), shot_noise="exact")
