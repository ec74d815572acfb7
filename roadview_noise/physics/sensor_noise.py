"""Photon-transfer model of an image sensor in low light (models.md §2.8 [PROP] ``physical``; EMVA 1288 noise
model): linear signal → electrons → shot, dark and read noise → gain → ADC → linear signal.

Per site, with x the linear signal (1 = full scale of the input, taken to be the full well at the reference
exposure), k the illuminance ratio, g the gain, FW the full well:

    λ = k · x / wb · FW                               mean photo-electrons (wb: white balance undone, RGB only)
    e = λ + n,  Var(n) = max(λ, 0) + D·T + σ_r²       shot (Poisson), dark current D over T (mean clamped by the
                                                      optical black, variance kept), read noise σ_r
    code = clip(round(b + g e / FW · (M − b)), 0, M)  ADC with black offset b and top code M (2^bits − 1)
    x' = (code − b) / (M − b) · wb

so the mean output is ``k·g·x`` (the luminance factor) and the variance grows linearly with the signal
(shot-noise regime) above the read-noise floor. The black offset keeps negative noise excursions, so the mean stays
unbiased. The fast default draws n as a Gaussian of exactly that variance — the true Poisson + Gaussian sum has a
skewness λ/(λ + σ_r²)^1.5 ≤ 0.13 for σ_r = 3 e⁻ — by inversion: a 16-bit uniform from the generator's raw output
indexes a table of scipy's inverse normal CDF (:func:`normal_table`; variance 1.0003, tails beyond ±4.3σ,
probability 2·10⁻⁵, clipped); ``poisson`` draws the shot and dark electrons exactly (≈ 10× slower).

A recorded value below black (x < 0: a raw mosaic's own read noise around its black level) is a measurement like
any other: it is scaled by k as it stands, only the shot-noise variance of a negative mean is 0 — so at k = g = 1
without noise the output is the input (issue 14: continuous at zero strength).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import ndtri

from .compiled import jit

NORMAL_TABLE_BITS = 16
SHOT_NOISE = ("gaussian", "poisson", "off")


@lru_cache(maxsize=1)
def normal_table() -> np.ndarray:
    """Inverse normal CDF at the centres of the 2^16 intervals of a 16-bit uniform, ``ndtri((j + ½)/2^16)``: a
    16-bit uniform indexes a standard normal variate (±4.3σ at the ends)."""
    n = 1 << NORMAL_TABLE_BITS
    table = ndtri((np.arange(n, dtype=np.float64) + 0.5) / n).astype(np.float32)
    table.flags.writeable = False
    return table


def uniform_bits(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` independent 16-bit uniforms from the generator's raw 64-bit output (four per draw)."""
    return rng.bit_generator.random_raw(-(-count // 4)).view(np.uint16)


@dataclass(frozen=True)
class SensorSettings:
    """Exposure and sensor constants of one low-light frame."""

    illuminance_ratio: float        # k = E_low / E_ref
    gain: float                     # g (auto-exposure, capped)
    full_well_e: float
    read_noise_e: float
    dark_e: float                   # dark-current electrons over the exposure, D·T
    adc_max_dn: float               # M, the ADC's top code (2^bits − 1; a raw mosaic's white level)
    adc_black_dn: float

    @property
    def luminance_factor(self) -> float:
        return self.illuminance_ratio * self.gain

    @property
    def adc_levels(self) -> float:
        return float(self.adc_max_dn) - self.adc_black_dn


@jit(fastmath=True)
def _sensor(values, given_electrons, inv_wb, wb, k_fw, floor_e2, shot, bits, table, scale, black, inv_levels, top,
            out):                                                          # pragma: no cover - compiled
    """Per site of (N, C) ``values`` (linear signal, or electrons when ``given_electrons``): electrons with
    Gaussian noise indexed by the 16-bit uniforms ``bits`` (N·C, or empty for none), then the ADC and back to
    linear signal (``scale`` = g/FW · ADC levels)."""
    zero = np.float32(0.0)
    nc = values.shape[1]
    noisy = bits.shape[0] > 0
    for i in range(values.shape[0]):
        for c in range(nc):
            if given_electrons:
                e = values[i, c]
            else:
                e = values[i, c] * inv_wb[c] * k_fw
                if noisy:
                    var = floor_e2 + max(e, zero) if shot else floor_e2
                    e += np.sqrt(var) * table[bits[i * nc + c]]
            code = min(max(np.floor(black + e * scale + np.float32(0.5)), zero), top)
            out[i, c] = (code - black) * inv_levels * wb[c]


def expose(signal: np.ndarray, settings: SensorSettings, rng: np.random.Generator, *, shot_noise: str = "gaussian",
           noise: bool = True, white_balance=(1.0, 1.0, 1.0)) -> np.ndarray:
    """The low-light frame of a linear signal, (H, W, 3) RGB or (H, W) mosaic, float32 (module docstring).
    ``noise=False`` leaves only the ADC quantisation; ``white_balance`` (R, G, B) is undone before and redone
    after the sensor (RGB only; a mosaic is already in sensor space)."""
    if shot_noise not in SHOT_NOISE:
        raise ValueError(f"shot_noise must be one of {SHOT_NOISE}, got {shot_noise!r}")
    sig = np.asarray(signal, np.float32)
    values = sig.reshape(-1, 3) if sig.ndim == 3 else sig.reshape(-1, 1)
    wb = np.asarray(white_balance if sig.ndim == 3 else (1.0,), np.float32)
    s = settings
    k_fw = np.float32(s.illuminance_ratio * s.full_well_e)
    given = False
    bits = np.empty(0, np.uint16)
    if noise and shot_noise == "poisson":
        mean_e = (values / wb).astype(np.float64) * float(k_fw)
        shot = rng.poisson(np.maximum(mean_e, 0.0) + s.dark_e) - s.dark_e + np.minimum(mean_e, 0.0)
        values = (shot + rng.normal(0.0, s.read_noise_e, values.shape)).astype(np.float32)
        given = True
    elif noise:
        bits = uniform_bits(rng, values.size)
    out = np.empty(values.shape, np.float32)
    _sensor(values, given, (1 / wb).astype(np.float32), wb, k_fw, np.float32(s.read_noise_e ** 2 + s.dark_e),
            shot_noise == "gaussian", bits, normal_table(), np.float32(s.gain / s.full_well_e * s.adc_levels),
            np.float32(s.adc_black_dn), np.float32(1 / s.adc_levels), np.float32(s.adc_max_dn), out)
    return out.reshape(sig.shape)
