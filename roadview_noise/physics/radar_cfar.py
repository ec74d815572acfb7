"""Detectors of distributed (precipitation) clutter: fixed threshold and cell-averaging CFAR (models.md §4.3 [PROP]).

Both act on one resolution cell whose clutter RCS is exponential with mean μ (many random-phase drops, models.md
§4.3) and are written in ``y = μ/σ_t``, the mean clutter RCS over ``σ_t``, the RCS that reaches the sensor's clear-air
threshold t at that range (``σ_t = 10^{(t − C + L)/10} r⁴``, radar constant C, two-way loss L).

- :class:`FixedThreshold` (models.md §4.3): the cell is declared when ``σ > σ_t``: ``P = e^{−1/y}``. The clutter
  count grows without bound with the margin ``C − t``.
- :class:`CaCfar`: cell-averaging CFAR. The threshold is ``T = (α/N) Σ x_i`` over N reference cells (range–Doppler
  neighbours, guard cells excluded). In homogeneous exponentially distributed interference (square-law detected
  Gaussian noise and clutter, χ²₂, Swerling-like) of mean I, ``T ~ Gamma(N, αI/N)`` and ``P_fa = (1 + α/N)^{−N}``,
  so ``α = N (P_fa^{−1/N} − 1)`` (Richards, *Fundamentals of Radar Signal Processing*, McGraw-Hill, §6.5.3
  "Analysis of Cell-Averaging CFAR"; Finn & Johnson 1968). Rohling's OS-CFAR ("Radar CFAR thresholding in clutter
  and multiple target situations", IEEE Trans. AES-19(4), 1983), which takes the k-th ordered reference sample and
  so resists interfering targets, holds the false-alarm rate in homogeneous clutter the same way (with its own α);
  it is not modelled separately.

CA-CFAR model of a rain cell ([PROP]):

- the noise n is the level at which the clear-air CFAR threshold equals the sensor threshold, ``α n = σ_t``, so the
  clutter-to-noise ratio is ``x = μ/n = α y`` (with SNR data and t ≈ 10 log10 α, n is the 0 dB of SNR);
- the reference window is homogeneous: its cells hold the cell's own mean interference ``I = μ + n`` (rain changes
  slowly over the few range/Doppler bins of a window; clutter edges are not modelled);
- a clutter point is declared when the cell's clutter echo alone exceeds both the CFAR threshold and the sensor's
  clear-air threshold: ``σ > max(T, α n)`` (never below the input's weakest detection). With ``θ = α(1 + x)/N``
  (the scale of T, noise units) and P, Q the regularised incomplete gamma functions::

      P(x) = e^{−α/x} P(N, N/(1 + x)) + (1 + θ/x)^{−N} Q(N, N/(1 + x) + α/x)

  (first term: T below the floor; second: ``E[e^{−T/x}; T ≥ α]``). ``P ≤ (1 + θ/x)^{−N} ≤ P_fa``: in clutter the
  CFAR holds its false-alarm rate, so the count stays ≈ P_fa × (clutter-dominated cells) whatever ``C − t``; and
  ``P ≤ e^{−α/x}``, the fixed-threshold probability, so CFAR never adds more clutter than the fixed threshold.
  Given a detection, ``σ = max(T, α) + Exp(x)`` (memorylessness), where T ≥ α with probability (second term)/P and
  then follows its posterior, ``Gamma(N, θ')`` truncated to ``[α, ∞)``, ``θ' = θx/(θ + x)``;
- a point target in a cell of clutter-to-noise ratio x faces the mean threshold ``α(n + μ)``: its detection
  threshold rises by ``10 log10(1 + x)`` dB (the CFAR's sensitivity loss in clutter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import gammainc, gammaincc, gammainccinv

from ..table_cache import disk_cached

PROBABILITY_TIERS = 30      # cells are sampled in tiers P ∈ (2^{−j−1}, 2^{−j}] P_max; below 2^{−30} P_max neglected


def ca_cfar_multiplier(false_alarm_probability: float, reference_cells: int) -> float:
    """``α = N (P_fa^{−1/N} − 1)`` of a CA-CFAR in exponential interference (P_fa 1e-4, N 16 → 12.45, 10.95 dB)."""
    return reference_cells * (false_alarm_probability ** (-1.0 / reference_cells) - 1.0)


@dataclass(frozen=True)
class FixedThreshold:
    """Fixed threshold: a cell is declared when its clutter RCS exceeds σ_t (models.md §4.3)."""

    max_probability = 1.0

    def probability(self, y) -> np.ndarray:
        """``P = e^{−1/y}``."""
        y = np.asarray(y, dtype=float)
        with np.errstate(divide="ignore"):
            return np.exp(-1.0 / y)

    def rcs_over_threshold(self, rng: np.random.Generator, y: np.ndarray) -> np.ndarray:
        """σ/σ_t of detected cells: ``1 + Exp(y)``."""
        return 1.0 + y * rng.standard_exponential(len(y))

    def threshold_rise_db(self, y) -> np.ndarray:
        return np.zeros(np.shape(y))


@dataclass(frozen=True)
class CaCfar:
    """Cell-averaging CFAR with ``reference_cells`` reference cells and per-cell ``false_alarm_probability``
    (module docstring)."""

    false_alarm_probability: float
    reference_cells: int

    def __post_init__(self) -> None:
        if not 0 < self.false_alarm_probability < 1:
            raise ValueError(f"false_alarm_probability must be in (0, 1), got {self.false_alarm_probability}")
        if self.reference_cells < 1:
            raise ValueError(f"reference_cells must be ≥ 1, got {self.reference_cells}")

    @property
    def multiplier(self) -> float:
        return ca_cfar_multiplier(self.false_alarm_probability, self.reference_cells)

    @property
    def max_probability(self) -> float:
        return self.false_alarm_probability

    def _terms(self, y) -> tuple[np.ndarray, np.ndarray]:
        """(T below the floor, T above it) parts of P at CNR ``x = α y``."""
        a, n = self.multiplier, self.reference_cells
        x = a * np.asarray(y, dtype=float)
        with np.errstate(divide="ignore", over="ignore"):
            inv = 1.0 / x
            c = n / (1.0 + x)
            below = np.exp(-a * inv) * gammainc(n, c)
            above = (1.0 + a * (1.0 + x) * inv / n) ** (-n) * gammaincc(n, c + a * inv)
        return below, above

    def probability(self, y) -> np.ndarray:
        """P(clutter echo > max(T, α n)) of a cell with ``y = μ/σ_t`` (module docstring)."""
        below, above = self._terms(y)
        return below + above

    def rcs_over_threshold(self, rng: np.random.Generator, y: np.ndarray) -> np.ndarray:
        """σ/σ_t of detected cells: ``(max(T, α) + Exp(x))/α`` with T from its posterior given the detection."""
        a, n = self.multiplier, self.reference_cells
        x = a * np.asarray(y, dtype=float)
        below, above = self._terms(y)
        u = rng.random((2, len(x)))
        theta = a * (1.0 + x) / n
        theta_post = theta * x / (theta + x)
        tail = gammaincc(n, n / (1.0 + x) + a / x)                 # Q(N, α/θ')
        t = theta_post * gammainccinv(n, u[1] * tail)
        t = np.where(u[0] * (below + above) < below, a, np.maximum(t, a))
        return (t + x * rng.standard_exponential(len(x))) / a

    def threshold_rise_db(self, y) -> np.ndarray:
        """Rise of a point target's detection threshold, ``10 log10(1 + α y)`` dB."""
        return 10.0 * np.log10(1.0 + self.multiplier * np.asarray(y, dtype=float))


Detector = FixedThreshold | CaCfar


@disk_cached(maxsize=32)
def tier_ratios(detector: Detector) -> np.ndarray:
    """``y_j`` with ``P(y_j) = 2^{−j} P_max``, j = 1 … 30 (decreasing): a cell with ``y_{j+1} ≤ y < y_j`` has
    ``P ≤ 2^{−j} P_max``; cells below ``y_30`` (P < 9.3·10⁻¹⁰ P_max) are neglected."""
    j = np.arange(1, PROBABILITY_TIERS + 1)
    if isinstance(detector, FixedThreshold):
        out = 1.0 / (j * math.log(2.0))
    else:
        from scipy.optimize import brentq  # here, not at import (≈ 0.2 s); the result is cached

        target = np.log(detector.max_probability) - j * math.log(2.0)
        out = np.array([math.exp(brentq(lambda v: math.log(float(detector.probability(math.exp(v))) + 1e-300) - t,
                                        -40.0, 40.0, xtol=1e-12)) for t in target])
    out.flags.writeable = False
    return out
