"""LiDAR receiver: received signal plus noise, detection at a threshold, range jitter — one model shared by fog, rain
and snow (and by ray drop).

Noise (signal units of the profile, e.g. photons of an Ouster ``signal`` channel; the weather models use units of the
sensor constant K, :meth:`Receiver.of`):
- signal shot noise, variance ``F S / g`` (g = ``photons_at_threshold / threshold`` detected photo-electrons per
  signal unit, F the excess noise factor: 1 for a SPAD or PIN diode, 2–5 for an APD);
- ambient background and receiver (dark, thermal) noise: together the noise floor ``σ0 = T / k`` at S = 0, with k the
  threshold in units of that floor (``threshold_over_noise``, which sets the false-alarm rate of the detector).
Photon counting (``receiver: spad``, Ouster): ``N = N_s + N_b`` counts in the pulse window, ``N_s ~ Poisson(g S)``,
background ``N_b ~ Poisson(B)`` with ``B = (g σ0)²`` (Poisson: variance = mean); the reported signal is
``(N − B) / g`` and the return is detected iff ``N ≥ B + g T``. Linear receivers (``apd``):
``S + σ0 z_b + sqrt(F S / g) z_s`` with standard normal z, detected iff ≥ T.

Range jitter of a detected peak (leading-edge timing, σ_t = t_r / SNR; e.g. Spieler, "Semiconductor Detector
Systems", 2005, §6): ``σ_R = (c/2) t_r / SNR`` with t_r the 10–90 % rise time of the received peak — the ``sin²``
pulse's (0.590 τ_H) for a particle, the longer leading edge of the fog's profile for fog
(:attr:`lidar_medium.SoftTargetTable.rise_m`) — and
``SNR = S / σ(S)``: 3 cm at SNR 30 and 0.9 cm at SNR 100 for a 10 ns pulse, half a metre near the threshold of
a SPAD.

Weather returns add only the detections their signal causes (:meth:`Receiver.measure`): a ray's background noise is
drawn conditioned on not crossing the threshold by itself, because the sensor's own false alarms are already in the
recorded data; as S → 0 nothing is added. Recorded returns keep their recorded noise (the stored value is one draw):
the weather models scale it by the transmission, so zero weather strength gives the input back.

Threshold calibration (:meth:`Receiver.calibrated`): a profile's datasheet threshold is a worst case (full sunlight);
when the recorded returns of a frame reach below it, the sensor was more sensitive than the datasheet says (less
ambient light than the datasheet's, or a sensor constant K that undervalues its signal). The threshold is then lowered
to the weakest signal the recorded returns can have (their stored value minus half a step), floored on the fixed grid
``T_datasheet · 2^(−j/4)``: strictly below every recorded return, and the same for every frame of a sequence whose
weakest returns differ by less than a quarter octave (each frame is calibrated by itself — workers see frames in any
order — and the manifest records the value). The photons at the threshold stay, so the detector's statistics
relative to its threshold are the profile's (its stated SNR at the threshold), only the signal scale moves.
That reading of the data holds only where the stored values measure the received power down to the faintest return
(``threshold_calibration: data``, the default: Ouster's photon counts and calibrated reflectivity, whose real scan is
calibrated 11× below the datasheet).

Recorded returns of a non-radiometric low end (``threshold_calibration: datasheet``, :meth:`Receiver.recorded_floor`):
Velodyne units store a per-laser corrected, non-linear value (the HDL-64E S2's intensity correction with a focal
distance and slope per laser, ROS velodyne_pointcloud's ``LaserCorrection``; Levinson & Thrun, "Unsupervised
Calibration for Multi-beam Lasers", ISER 2010, fit each beam's remittance response for that reason; the HDL-32E's
calibrated reflectivity, firmware 2.0, is an integer 0–100 for diffuse targets). Such data hold readings no receiver
with the sensor's range could have detected: 20 % of a KITTI scan's returns store 0 (out to 80 m; 96 % of its
returns beyond 60 m), 9 % read below the HDL-64E's datasheet threshold (10 % at 50 m); calibrated from them the
threshold sat 215× below it — a receiver that detects a 10 % target at 730 m — and rain put a drop return on 99 %
of the empty rays (nuScenes' HDL-32E: readings of 1–2 at 20–40 m, 11× below the threshold its far returns fit). The
threshold then stays the datasheet's: the weather's particles are judged against it. A recorded return is still known
to have been detected, but its reading does not say by how much; for the weather's decisions its signal is at least
what a return detected at the threshold measures on average, ``E[M | M ≥ T] = T + σ(T)·√(2/π)`` for a measured value
``M ~ N(T, σ(T)²)`` (the mean of a normal truncated at its median; 1.243 T for the generic APD of the Velodyne
profiles); a reading above that counts as read, one below it (or a stored 0) as the median of the scan's readings
at its range, at least the floor (:mod:`reading_population`). The bound T itself would not do: a return exactly at the threshold
is lost to any trace of weather (the discontinuity of issue 14, item 2). With the floor zero strength gives the input
back, a faint return is lost only once the weather takes more than its margin (round-trip transmission below
``T / floor`` = 0.80), and a return in place is stored as its reading times the transmission (a 0 stays 0).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.constants import speed_of_light
from scipy.special import gammainc, gammaln, ndtr, pdtr, pdtrc, xlogy

from .compiled import jit

RECEIVERS = ("spad", "apd")
THRESHOLD_CALIBRATIONS = ("data", "datasheet")     # LidarProfile.threshold_calibration (module doc)
#: 10–90 % rise time of the pulse sin²(π t / 2τ_H), in units of τ_H
RISE_TIME_PER_TAU = 2 / math.pi * (math.asin(math.sqrt(0.9)) - math.asin(math.sqrt(0.1)))
CALIBRATION_STEPS_PER_OCTAVE = 4
NEGLIGIBLE_DETECTION = 1e-3     # a signal whose detection probability exceeds the false alarms by less is not a return
LARGE_COUNT = 30.0              # Poisson means above this are drawn from the normal approximation
MAX_EXACT_COUNT = 1000          # a photon-counting receiver with more counts at its threshold is treated as Gaussian


@dataclass(frozen=True)
class Receiver:
    """Detection statistics of a LiDAR receiver (module doc); ``threshold`` in the signal units in use."""

    threshold: float
    photons_at_threshold: float
    threshold_over_noise: float
    excess_noise_factor: float
    photon_counting: bool
    pulse_half_power_width_s: float
    source: str = "datasheet"

    @classmethod
    def of(cls, profile, unit: float = 1.0) -> Receiver:
        """The receiver of a :class:`LidarProfile`, with signals expressed in ``unit`` signal units (the weather models
        pass the sensor constant K)."""
        if profile.receiver not in RECEIVERS:
            raise ValueError(f"profile {profile.name!r} has receiver {profile.receiver!r}; expected one of {RECEIVERS}")
        return cls(profile.detection_threshold / unit, float(profile.photons_at_threshold),
                   float(profile.threshold_over_noise),
                   1.0 if profile.receiver == "spad" else float(profile.excess_noise_factor),
                   profile.receiver == "spad", float(profile.pulse_half_power_width_s))

    @property
    def counts_photons(self) -> bool:
        """Whether detection is computed with photon counts (a SPAD with at most :data:`MAX_EXACT_COUNT` counts at its
        threshold); else with Gaussian noise of the same variance."""
        return self.photon_counting and self.background_photons + self.photons_at_threshold <= MAX_EXACT_COUNT

    @property
    def photons_per_signal(self) -> float:
        """g: detected photo-electrons per signal unit."""
        return self.photons_at_threshold / self.threshold

    @property
    def noise_floor(self) -> float:
        """σ0: RMS of the ambient and receiver noise (signal units)."""
        return self.threshold / self.threshold_over_noise

    @property
    def background_photons(self) -> float:
        """B: mean background counts in a pulse window of a photon-counting receiver, ``(g σ0)²``."""
        return (self.photons_at_threshold / self.threshold_over_noise) ** 2

    @property
    def detection_count(self) -> int:
        """Smallest count a photon-counting receiver detects, ``ceil(B + g T)``."""
        return int(math.ceil(self.background_photons + self.photons_at_threshold - 1e-9))

    def noise_sd(self, signal) -> np.ndarray:
        """σ(S) = sqrt(σ0² + F S / g) (signal units)."""
        s = np.maximum(np.asarray(signal, dtype=float), 0.0)
        return np.sqrt(self.noise_floor ** 2 + self.excess_noise_factor * s / self.photons_per_signal)

    @property
    def pulse_rise_m(self) -> float:
        """``(c/2) t_r``: the 10–90 % rise of the pulse in metres of range."""
        return speed_of_light / 2 * RISE_TIME_PER_TAU * self.pulse_half_power_width_s

    def range_sd_m(self, signal, rise_m: float | None = None) -> np.ndarray:
        """Range jitter of a detected peak of signal S: ``rise · σ(S) / S`` (inf for S ≤ 0), with the leading edge
        ``rise_m`` of the received peak (default: the pulse's, :attr:`pulse_rise_m`)."""
        s = np.asarray(signal, dtype=float)
        with np.errstate(divide="ignore"):
            return (self.pulse_rise_m if rise_m is None else rise_m) * self.noise_sd(s) / s

    def detection_probability(self, signal) -> np.ndarray:
        """Probability that a return of expected signal S crosses the threshold (false alarms of the noise included:
        the value at S = 0 is the false-alarm probability of one pulse window)."""
        s = np.maximum(np.asarray(signal, dtype=float), 0.0)
        if self.counts_photons:
            m = self.detection_count
            nb = np.arange(m)
            weight = _poisson_pmf(nb, self.background_photons)
            need = m - nb                                       # ≥ 1
            p = gammainc(need[None, :], (self.photons_per_signal * s).reshape(-1, 1)) @ weight
            return (p + pdtrc(m - 1, self.background_photons)).reshape(s.shape)     # P(N_b ≥ m)
        return ndtr((s - self.threshold) / self.noise_sd(s))

    @property
    def weakest_return(self) -> float:
        """The signal below which a return is (almost) never detected: its detection probability exceeds the false
        alarms by less than 1e-3 (bisection, cached per receiver); used to skip candidates that cannot matter."""
        return _weakest_return(dataclasses.replace(self, source=""))

    def calibrated(self, weakest_recorded: float) -> Receiver:
        """This receiver with the threshold lowered below ``weakest_recorded`` (the smallest signal a recorded return
        of the frame can have) on the grid ``T · 2^(−j/4)`` when the datasheet threshold T lies above it (module
        doc); unchanged otherwise."""
        t = self.threshold
        if not (0 < weakest_recorded < t):
            return self
        j = math.ceil(CALIBRATION_STEPS_PER_OCTAVE * math.log2(t / weakest_recorded))
        while t * 2.0 ** (-j / CALIBRATION_STEPS_PER_OCTAVE) >= weakest_recorded:
            j += 1
        return dataclasses.replace(self, threshold=t * 2.0 ** (-j / CALIBRATION_STEPS_PER_OCTAVE),
                                   source=f"calibrated from the data: the weakest recorded return can be "
                                          f"{weakest_recorded:.4g}, below the datasheet threshold {t:.4g}")

    @property
    def recorded_floor(self) -> float:
        """The signal a recorded return of an unreliable reading counts as at least: the mean measured value of a
        return detected at the threshold, ``T + σ(T)·√(2/π)`` (module doc)."""
        return self.threshold + float(self.noise_sd(self.threshold)) * math.sqrt(2.0 / math.pi)

    def in_units(self, unit: float) -> Receiver:
        """The same receiver with signals expressed in ``unit`` of the current ones."""
        return dataclasses.replace(self, threshold=self.threshold / unit)

    @property
    def kernel_params(self) -> tuple:
        """What the compiled :func:`measure_one` and :func:`range_sd_one` take, in their order (cached tables)."""
        return _kernel_params(dataclasses.replace(self, source=""))

    def measure(self, signal: np.ndarray, uniforms: np.ndarray, rows: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Measured values of new (weather) returns of expected signals S (module doc): returns the measured signal,
        whether it is detected, and a standard normal deviate for the range jitter (times :meth:`range_sd_m`).

        ``uniforms``: (n, 3) uniform draws in [0, 1), row ``rows[i]`` (default i) for signal i — background, signal
        shot noise, range jitter — so that a caller can tie the noise of a ray to the ray (common random numbers
        across weather strengths). The background is conditioned on not detecting by itself."""
        s = np.ascontiguousarray(signal, dtype=np.float64)
        rows = np.arange(len(s)) if rows is None else np.ascontiguousarray(rows, dtype=np.intp)
        return _measure(s, np.ascontiguousarray(uniforms, dtype=np.float64), rows, *self.kernel_params)


def _poisson_pmf(k: np.ndarray, mean: float) -> np.ndarray:
    """Poisson probabilities P(N = k), as scipy.stats.poisson.pmf computes them (without importing scipy.stats,
    0.35 s per process)."""
    return np.exp(xlogy(k, mean) - gammaln(k + 1) - mean)


@lru_cache(maxsize=64)
def _weakest_return(receiver: Receiver) -> float:
    base = float(receiver.detection_probability(0.0))
    lo, hi = 0.0, receiver.threshold
    if float(receiver.detection_probability(hi)) - base < NEGLIGIBLE_DETECTION:
        return hi
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if float(receiver.detection_probability(mid)) - base < NEGLIGIBLE_DETECTION:
            lo = mid
        else:
            hi = mid
    return lo


@lru_cache(maxsize=64)
def _kernel_params(receiver: Receiver) -> tuple:
    """(photon counting, g, σ0, F, T, B, detection count, conditioned background CDF, Φ(k)): the background table is
    the cumulative law of N_b conditioned on ``N_b < detection_count`` (empty for Gaussian noise)."""
    counting = receiver.counts_photons
    table = np.zeros(0)
    if counting:
        cdf = pdtr(np.arange(receiver.detection_count), receiver.background_photons)      # Poisson CDF
        table = cdf / cdf[-1]
    return (counting, receiver.photons_per_signal, receiver.noise_floor, receiver.excess_noise_factor,
            receiver.threshold, receiver.background_photons, float(receiver.detection_count) if counting else 0.0,
            table, float(ndtr(receiver.threshold_over_noise)))


# ---------------------------------------------------------------------------------------------------------------
# Compiled sampling

# Acklam's rational approximation of the inverse normal CDF (relative error < 1.2e-9)
_A = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02, 1.383577518672690e+02,
      -3.066479806614716e+01, 2.506628277459239e+00)
_B = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02, 6.680131188771972e+01,
      -1.328068155288572e+01)
_C = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00, -2.549732539343734e+00,
      4.374664141464968e+00, 2.938163982698783e+00)
_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00, 3.754408661907416e+00)
_P_LOW = 0.02425


@jit(inline="always")
def _tail(q):       # pragma: no cover - compiled
    return ((((((_C[0] * q + _C[1]) * q + _C[2]) * q + _C[3]) * q + _C[4]) * q + _C[5])
            / ((((_D[0] * q + _D[1]) * q + _D[2]) * q + _D[3]) * q + 1.0))


@jit(inline="always")
def normal_quantile(p):       # pragma: no cover - compiled
    """Φ⁻¹(p) for 0 < p < 1 (Acklam's approximation; p is clamped to [1e-300, 1 − 1e-16])."""
    p = min(max(p, 1e-300), 1.0 - 1e-16)
    if p < _P_LOW:
        return _tail(math.sqrt(-2.0 * math.log(p)))
    if p > 1.0 - _P_LOW:
        return -_tail(math.sqrt(-2.0 * math.log(1.0 - p)))
    q = p - 0.5
    r = q * q
    return ((((((_A[0] * r + _A[1]) * r + _A[2]) * r + _A[3]) * r + _A[4]) * r + _A[5]) * q
            / (((((_B[0] * r + _B[1]) * r + _B[2]) * r + _B[3]) * r + _B[4]) * r + 1.0))


@jit(inline="always")
def poisson_quantile(mean, u):       # pragma: no cover - compiled
    """Smallest k with P(Poisson(mean) ≤ k) > u: exact (sequential search) below :data:`LARGE_COUNT`, else the
    normal approximation with continuity correction."""
    if mean <= 0.0:
        return 0.0
    if mean >= LARGE_COUNT:
        return max(math.floor(mean + math.sqrt(mean) * normal_quantile(u) + 0.5), 0.0)
    p = math.exp(-mean)
    c = p
    k = 0
    while u >= c and k < 200:
        k += 1
        p *= mean / k
        c += p
    return float(k)


@jit(inline="always")
def background_count(u0, background_cdf):       # pragma: no cover - compiled
    """The background photon count that the uniform u0 draws (table ``background_cdf``: its CDF conditioned on no
    detection; :func:`measure_one`)."""
    nb = 0
    nb_max = len(background_cdf) - 1
    while nb < nb_max and u0 >= background_cdf[nb]:
        nb += 1
    return nb


@jit(inline="always")
def measure_one(s, u0, u1, spad, gain, floor, excess, threshold, background, detect_count, background_cdf,
                below_k):       # pragma: no cover - compiled
    """(measured signal, detected) of one new return of expected signal s from two uniforms (background, shot
    noise) with :attr:`Receiver.kernel_params`: photon counts (``spad``) or Gaussian noise, the background conditioned
    on no detection (table ``background_cdf``, or the normal below k = T/σ0 with Φ(k) = ``below_k``)."""
    s = max(s, 0.0)
    if spad:
        counts = poisson_quantile(gain * s, u1) + background_count(u0, background_cdf)
        return (counts - background) / gain, counts >= detect_count
    noise = floor * normal_quantile(u0 * below_k) + math.sqrt(excess * s / gain) * normal_quantile(u1)
    return s + noise, s + noise >= threshold


@jit(inline="always")
def range_sd_one(s, rise_m, gain, floor, excess):       # pragma: no cover - compiled
    """:meth:`Receiver.range_sd_m` of one signal s > 0 with leading edge ``rise_m``."""
    return rise_m * math.sqrt(floor * floor + excess * s / gain) / s


@jit
def _measure(signal, u, rows, spad, gain, floor, excess, threshold, background, detect_count, background_cdf,
             below_k):       # pragma: no cover - compiled
    """:meth:`Receiver.measure` over the signals (:func:`measure_one`), with a normal deviate for the jitter."""
    n = len(signal)
    measured = np.empty(n)
    detected = np.empty(n, np.bool_)
    jitter = np.empty(n)
    for i in range(n):
        row = rows[i]
        measured[i], detected[i] = measure_one(signal[i], u[row, 0], u[row, 1], spad, gain, floor, excess, threshold,
                                               background, detect_count, background_cdf, below_k)
        jitter[i] = normal_quantile(u[row, 2])
    return measured, detected, jitter
