"""Shared single-scattering LiDAR equation of the weather models (models.md §3.1; Hahner et al., ICCV 2021 fog and
CVPR 2022 snow), the one intensity scale of every LiDAR, and the ray bookkeeping every LiDAR weather model shares.

Intensity scale (one conversion layer for all models, :func:`received_signal` / :func:`reported_intensity`)
- The physics works on the *received signal* S, in the unit of the profile's ``sensor_constant`` K per m² (K: the
  signal of a ρ = 1 Lambertian target filling the beam at 1 m; None → the intensity full scale): a target of
  reflectance ρ at range R returns ``S = K ρ cos θ / R²``, a particle ``K ρ_p f ξ(r) e^{−2αr} / r²``, fog
  ``K π β ∫ …`` (:func:`soft_target_signal`). The detection threshold (``detection_threshold``) is in signal units.
- ``intensity_kind`` says how a file stores it: ``signal`` (∝ received power, e.g. Ouster ``signal`` photons): I = S;
  ``reflectivity`` (range-compensated, e.g. Ouster ``reflectivity``, Velodyne 8-bit, KITTI and CARLA [0, 1]):
  ``I = W · S R² / K`` with W the profile's ``reflectivity_white_reading``, the reading of a ρ = 1 diffuse target
  (Ouster 100, Velodyne VLS-128 110; None → the full scale, i.e. the file reads ρ × full scale). Every output
  intensity goes back through the same layer, so a range-compensated file gets range-compensated weather returns
  (a fog return of signal S at apparent range r reads ``W S r² / K``).
- Inside the models signals are carried in units of K (``S / K``, m⁻²); the decisions (weather return vs target,
  detection) compare quantities of that one unit, so the same scene stored as photons, 8-bit or [0, 1] intensities
  with matching profiles gives the same result, and :func:`cloud_rays` refuses intensities that contradict the
  profile instead of guessing.

Conventions
- Apparent range of a return = position of the received pulse peak minus ``c τ_H / 2`` (Hahner's shift), so a hard
  target at R appears at R.
- Pulse ``P(t) = sin²(π t / (2 τ_H))`` on ``0 ≤ t ≤ 2 τ_H``; in range it spans ``L = c τ_H``.
- Overlap (crossover) function ξ(r): 0 below R1, linear to 1 at R2, the profile's ``overlap_start_m`` and
  ``overlap_full_m`` (Hahner 2021: R1 = 0.9 m, R2 = 1.0 m); every use of ξ (particles, fog tables) takes them from
  the profile.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import ModelError
from ..provenance import NEW, Effect
from ..types import IntensityUnit, LidarProfile, PointCloud
from .compiled import jit
from .firing_grid import FiringGrid, firing_grid

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0
HAHNER_FOG_PULSE_S = 20e-9              # half-power pulse width of Hahner et al. 2021
SOFT_TABLE_STEP_M = 0.01                # range step of the fog pulse-integral table
SAME_TARGET_TOLERANCE_M = 0.2           # a summed peak this close to the target keeps the target (Hahner 2022)
SIGNAL, REFLECTIVITY = "signal", "reflectivity"    # LidarProfile.intensity_kind
#: units stored in whole counts (resolution 1); [0, 1] floats get 1/255 of full scale (KITTI stores multiples of 0.01)
COUNT_UNITS = (IntensityUnit.PHOTONS, IntensityUnit.UINT8)

NO_RETURN, TARGET, WEATHER = 0, 1, 2     # what a ray returns after the weather
ATTENUATED, MOVED, ADDED, REMOVED = (int(e) for e in (Effect.ATTENUATED, Effect.MOVED, Effect.ADDED, Effect.REMOVED))


# ---------------------------------------------------------------------------------------------------------------
# Intensity scale


def sensor_constant(profile: LidarProfile) -> float:
    """K: received signal of a ρ = 1 Lambertian target filling the beam at 1 m (signal units · m²); None in the
    profile → the intensity full scale."""
    return float(profile.intensity_full_scale if profile.sensor_constant is None else profile.sensor_constant)


def white_reading(profile: LidarProfile) -> float:
    """W: the stored reading of a ρ = 1 diffuse target in a ``reflectivity`` file (Ouster 100, VLS-128 110); None in
    the profile → the intensity full scale (KITTI, CARLA: the reading is ρ × full scale)."""
    w = profile.reflectivity_white_reading
    return float(profile.intensity_full_scale if w is None else w)


def _unknown_kind(profile: LidarProfile) -> ModelError:
    return ModelError(f"profile {profile.name!r} has intensity_kind {profile.intensity_kind!r}; expected "
                      f"{SIGNAL!r} or {REFLECTIVITY!r}", field="intensity_kind")


def received_signal(intensity, range_m, profile: LidarProfile) -> np.ndarray:
    """Received signal S (signal units) of stored intensities at their ranges: I for ``signal`` profiles,
    ``(I / W) · K / R²`` for range-compensated ``reflectivity`` profiles (W: :func:`white_reading`; 0 where R ≤ 0:
    no return)."""
    i = np.asarray(intensity, dtype=np.float64)
    if profile.intensity_kind == SIGNAL:
        return i
    if profile.intensity_kind == REFLECTIVITY:
        r = np.asarray(range_m, dtype=np.float64)
        scale = sensor_constant(profile) / white_reading(profile)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(r > 0, i * scale / (r * r), 0.0)
    raise _unknown_kind(profile)


def reported_intensity(signal, range_m, profile: LidarProfile) -> np.ndarray:
    """Inverse of :func:`received_signal`: the intensity a profile stores for a return of signal S at apparent range
    R (S for ``signal``, ``W · S R² / K`` for ``reflectivity``); not clipped."""
    s = np.asarray(signal, dtype=np.float64)
    if profile.intensity_kind == SIGNAL:
        return s
    if profile.intensity_kind == REFLECTIVITY:
        r = np.asarray(range_m, dtype=np.float64)
        return s * (r * r) * (white_reading(profile) / sensor_constant(profile))
    raise _unknown_kind(profile)


def intensity_resolution(profile: LidarProfile) -> float:
    """One step of the stored intensity: 1 for count units (photons, 8-bit), full scale / 255 for [0, 1] floats."""
    return 1.0 if profile.intensity_unit in COUNT_UNITS else profile.intensity_full_scale / 255.0


# ---------------------------------------------------------------------------------------------------------------
# LiDAR equation (signals in units of the sensor constant K)


def overlap(r_m, r1_m: float, r2_m: float) -> np.ndarray:
    """Receiver overlap ξ(r): 0 for r ≤ R1, linear to 1 at R2, 1 beyond (R1, R2: the profile's ``overlap_start_m``,
    ``overlap_full_m``)."""
    return np.clip((np.asarray(r_m, dtype=float) - r1_m) / (r2_m - r1_m), 0.0, 1.0)


def pulse_power(t_s, tau_h_s: float) -> np.ndarray:
    """Normalised transmitted power ``sin²(π t/(2 τ_H))`` for 0 ≤ t ≤ 2 τ_H, else 0 (peak 1, energy τ_H)."""
    t = np.asarray(t_s, dtype=float)
    return np.where((t >= 0) & (t <= 2 * tau_h_s), np.sin(np.pi * t / (2 * tau_h_s)) ** 2, 0.0)


def pulse_length_m(tau_h_s: float) -> float:
    """Range extent ``c τ_H`` of a received pulse (2 τ_H long in time, c/2 metres per second of delay)."""
    return SPEED_OF_LIGHT_M_PER_S * tau_h_s


def hard_target_signal(signal, alpha_per_m: float, range_m) -> np.ndarray:
    """Two-way Beer–Lambert loss of a hard target, ``S e^{−2αR}`` (same unit as ``signal``; R finite)."""
    t = np.exp(np.multiply(range_m, -2.0 * alpha_per_m))
    return np.multiply(signal, t, out=t) if isinstance(t, np.ndarray) else signal * t


def particle_signal(reflectance: float, beam_fraction, range_m, alpha_per_m: float, r1_m: float,
                    r2_m: float) -> np.ndarray:
    """Return of a particle in units of K, ``ρ f ξ(r) e^{−2αr} / r²`` (m⁻²; ξ with overlap R1, R2)."""
    r = np.asarray(range_m, dtype=float)
    return reflectance * beam_fraction * overlap(r, r1_m, r2_m) * np.exp(-2.0 * alpha_per_m * r) / (r * r)


def soft_target_signal(g_s_per_m2, beta_per_m_sr: float) -> np.ndarray:
    """Return of a homogeneous soft target (fog) in units of K from its pulse integral G (s m⁻²):
    ``π β (c/2) G`` — the fog as a Lambertian reflector of ρ = π β per metre of depth (Hahner 2021 Eq. 6–10 with the
    sensor constant). For R ≫ c τ_H and ξ = 1: ``π β (c τ_H/2) e^{−2αR}/R²``."""
    return np.multiply(g_s_per_m2, math.pi * beta_per_m_sr * SPEED_OF_LIGHT_M_PER_S / 2)


@dataclass(frozen=True, eq=False)
class SoftTargetTable:
    """Peak of the soft-target (fog) pulse integral per hard-target range R0, on a regular grid from 0.

    ``g_max_s_per_m2[k] = max_R G(R; R0 = k·step)`` with
    ``G(R; R0) = ∫_0^{2τ_H} sin²(πt/2τ_H) e^{−2α(R−ct/2)} ξ(R−ct/2)/(R−ct/2)² H(R0 − R + ct/2) dt`` (s m⁻²), and
    ``fog_range_m[k]`` the apparent range of that peak. Beyond the last entry both are constant."""

    step_m: float
    g_max_s_per_m2: np.ndarray
    fog_range_m: np.ndarray

    def lookup(self, r0_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = np.minimum(np.rint(np.asarray(r0_m) / self.step_m), len(self.g_max_s_per_m2) - 1).astype(np.intp)
        return self.g_max_s_per_m2[k], self.fog_range_m[k]

    @property
    def saturated(self) -> tuple[float, float]:
        """(G_max, fog range) of a target beyond the table, e.g. an empty ray."""
        return float(self.g_max_s_per_m2[-1]), float(self.fog_range_m[-1])


@lru_cache(maxsize=32)
def soft_target_table(alpha_per_m: float, tau_h_s: float, r1_m: float, r2_m: float) -> SoftTargetTable:
    """Pulse-integral table of a homogeneous soft target (Hahner 2021 Eq. 8–10), cached per (α, τ_H, R1, R2) with the
    overlap R1, R2 of the profile.

    In range form ``G(R; R0) = (2/c) ∫_{R−L}^{min(R, R0)} w(R − r) f(r) dr`` with ``w(s) = sin²(π s/L)``,
    ``f(r) = e^{−2αr} ξ(r)/r²`` and ``L = c τ_H``. For ``R ≤ R0`` it does not depend on R0, and beyond
    ``R2 + L`` f decreases over the whole window, so the peak stops moving once ``R0 ≥ R2 + L``: the table ends
    there. The integral uses the midpoint rule on a 0.01 m grid."""
    h = SOFT_TABLE_STEP_M
    length = pulse_length_m(tau_h_s)
    nw = int(math.ceil(length / h))                       # window samples
    s = (np.arange(nw) + 0.5) * length / nw               # midpoints of the window (R − r)
    w = np.sin(np.pi * s / length) ** 2 * (2.0 / SPEED_OF_LIGHT_M_PER_S) * (length / nw)
    m_max = int(math.ceil((r2_m + length) / h))           # last R0 index of the table
    n_r = m_max + nw + 1                                  # apparent ranges R_n = n h, n < n_r
    r_n = np.arange(n_r) * h
    r = r_n[:, None] - s[None, :]                         # (n_r, nw) scatterer ranges
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(r > r1_m, np.exp(-2 * alpha_per_m * r) * overlap(r, r1_m, r2_m) / (r * r), 0.0)
    terms = w[None, :] * f
    # suffix[n, j] = Σ_{j' ≥ j} terms[n, j'] : window samples with r = R_n − s_j' ≤ R_n − s_j
    suffix = np.cumsum(terms[:, ::-1], axis=1)[:, ::-1]
    full = suffix[:, 0]                                   # G(R_n) with no target cut (R_n − s ≤ R0 for all s)
    m = np.arange(m_max + 1)
    # for R_n ≤ R0: running maximum of the uncut integral (and where it was reached)
    head = full[: m_max + 1]
    best_n = np.maximum.accumulate(np.where(head == np.maximum.accumulate(head), m, 0))
    best_val = head[best_n]
    # for R0 < R_n ≤ R0 + L: only scatterers with r ≤ R0, i.e. s_j ≥ R_n − R0 (first such j = ceil((R_n−R0)/ds − ½))
    d = np.arange(1, nw + 1)
    n_idx = m[:, None] + d[None, :]
    j0 = np.ceil(d * h / (length / nw) - 0.5).astype(np.intp)
    cut = np.where(j0[None, :] < nw, suffix[n_idx, np.minimum(j0, nw - 1)[None, :]], 0.0)
    k = np.argmax(cut, axis=1)
    cut_val = cut[m, k]
    better = cut_val > best_val
    best_val = np.where(better, cut_val, best_val)
    best_n = np.where(better, m + d[k], best_n)
    fog_range = np.clip(best_n * h - length / 2, 0.0, m * h)   # Hahner's shift; never behind the target
    return SoftTargetTable(h, best_val, fog_range)


@dataclass(frozen=True, eq=False)
class SoftBackground:
    """Mean received profile of a soft scatterer with backscatter density b(r) (units of K per metre of range):
    ``B(x; R0) = ∫_{x−L}^{min(x, R0)} sin²(π (x − r)/L) b(r) dr`` at pulse position x (apparent range x − L/2) in
    front of a target at R0. Since ``sin²(π s/L) = ½ − ½ cos ωs`` (ω = 2π/L), B needs only the cumulative integrals
    of b, b cos ωr and b sin ωr (``cum[k, 0–2]`` at ``r_k = k·step``, side by side for one cache line per lookup;
    constant beyond the table, where b = 0).
    ``peak``: the largest B of an uncut window; ``at_target[k]``: B at the crest of a target at ``r_k``
    (``x = r_k + L/2``). Evaluated by :func:`background_at`; an empty ``cum`` means no background."""

    step_m: float
    length_m: float
    cum: np.ndarray
    peak: float
    at_target: np.ndarray

    @classmethod
    def none(cls, length_m: float) -> SoftBackground:
        return cls(1.0, length_m, np.zeros((0, 3)), 0.0, np.zeros(0))

    @classmethod
    def of_density(cls, b_per_m: np.ndarray, step_m: float, length_m: float) -> SoftBackground:
        """From b(r_k) on ``r_k = k·step`` (trapezoid cumulative integrals; b = 0 beyond the last sample)."""
        omega = 2 * math.pi / length_m
        r = np.arange(len(b_per_m)) * step_m
        terms = np.stack([b_per_m, b_per_m * np.cos(omega * r), b_per_m * np.sin(omega * r)])
        cum = np.concatenate([np.zeros((3, 1)), np.cumsum((terms[:, 1:] + terms[:, :-1]) * (step_m / 2), axis=1)],
                             axis=1)

        def window(x, u):                                  # B(x) over scatterers in [x − L, u]
            lo = np.clip(x - length_m, 0.0, None)
            u = np.maximum(u, lo)
            c = [np.interp(u, r, row) - np.interp(lo, r, row) for row in cum]
            return 0.5 * c[0] - 0.5 * (np.cos(omega * x) * c[1] + np.sin(omega * x) * c[2])

        uncut = window(r, r)
        return cls(step_m, length_m, np.ascontiguousarray(cum.T), float(uncut.max(initial=0.0)),
                   np.maximum(window(r + length_m / 2, r), 0.0))


@jit(inline="always")
def _cumulative(cum, x):       # pragma: no cover - compiled
    """The three integrals of :attr:`SoftBackground.cum` at grid coordinate x ≥ 0 (linear; constant beyond)."""
    last = cum.shape[0] - 1
    if x >= last:
        return cum[last, 0], cum[last, 1], cum[last, 2]
    k = int(x)
    t = x - k
    return (cum[k, 0] + (cum[k + 1, 0] - cum[k, 0]) * t, cum[k, 1] + (cum[k + 1, 1] - cum[k, 1]) * t,
            cum[k, 2] + (cum[k + 1, 2] - cum[k, 2]) * t)


@jit(inline="always")
def background_at(x, r0, cum, inv_step, length):       # pragma: no cover - compiled
    """:class:`SoftBackground` value B(x; R0) from its cumulative tables ``cum`` (0 when they are empty)."""
    lo = max(x - length, 0.0)
    u = min(x, r0)
    if cum.shape[0] == 0 or u <= lo:
        return 0.0
    u0, uc, us = _cumulative(cum, u * inv_step)
    l0, lc, ls = _cumulative(cum, lo * inv_step)
    c, s = phasor(x * (2.0 * math.pi / length))
    return max(0.5 * ((u0 - l0) - c * (uc - lc) - s * (us - ls)), 0.0)


# ---------------------------------------------------------------------------------------------------------------
# Return selection


@dataclass(frozen=True, eq=False)
class RayReturns:
    """Per ray: what it returns (NO_RETURN, TARGET at its own position, WEATHER return), apparent range, signal."""

    kind: np.ndarray
    range_m: np.ndarray
    signal: np.ndarray


def pick(target_signal: np.ndarray, target_range_m: np.ndarray, weather_signal: np.ndarray,
         weather_range_m: np.ndarray, threshold: float, mode: str) -> RayReturns:
    """One weather candidate in front of the target per ray: strongest, or first (weather) above threshold."""
    if mode == "strongest":
        use_weather = weather_signal > target_signal
    else:
        use_weather = weather_signal >= threshold
    signal = np.where(use_weather, weather_signal, target_signal)
    kind = (signal >= threshold).view(np.uint8) * (use_weather.view(np.uint8) + np.uint8(TARGET))
    return RayReturns(kind, np.where(use_weather, weather_range_m, target_range_m), signal)


def select_returns(particle_ray: np.ndarray, particle_range_m: np.ndarray, particle_signal_: np.ndarray,
                   target_range_m: np.ndarray, target_signal: np.ndarray, has_target: np.ndarray,
                   tau_h_s: float, threshold: float, mode: str,
                   particle_beam_fraction: np.ndarray | None = None,
                   background: SoftBackground | None = None, target_shadow: np.ndarray | None = None) -> RayReturns:
    """Returns of rays crossing discrete particles (§3.1, Hahner 2022): pulses closer than ``c τ_H`` add in power.

    ``particle_*`` are sorted by ray, then range (as :func:`lidar_particles.sample_particles` makes them). With
    ``particle_beam_fraction`` each target is first shadowed by the particles in front of it,
    ``S_t (1 − min(1, Σ f))`` (§3.3). Per ray the contributions (particles, then the target) form clusters of
    overlapping pulses; each cluster's summed received profile is maximised exactly (:func:`pair_peak`,
    :func:`cluster_peak`; Hahner samples it on a 0.1 m grid). The ray returns its strongest cluster
    (``mode='strongest'``, ties: the nearest) or the first one above threshold (``'first'``); a cluster holding the
    target whose peak lies within 0.2 m of it keeps the target in place with the summed intensity. Rays without
    particles return their target. ``background`` (the undrawn particles' mean backscatter, a
    :class:`SoftBackground` smaller than the threshold) adds to every cluster at its peak and to every target at its
    crest. ``target_shadow``: a mean beam cover per ray added to the particles' Σ f (undrawn particles).
    One compiled pass over the rays with particles."""
    length = pulse_length_m(tau_h_s)
    background = SoftBackground.none(length) if background is None else background
    shadow = np.zeros(0) if target_shadow is None else np.ascontiguousarray(target_shadow, dtype=np.float64)
    target_signal, tgt_bg, out_signal, kind, out_range = _target_returns(
        np.ascontiguousarray(target_signal, dtype=np.float64), np.ascontiguousarray(target_range_m, dtype=np.float64),
        np.ascontiguousarray(has_target), shadow, background.at_target, 1.0 / background.step_m, float(threshold))
    if len(particle_ray):
        fraction = np.zeros(0) if particle_beam_fraction is None else np.ascontiguousarray(particle_beam_fraction,
                                                                                            dtype=np.float64)
        _select_kernel(np.ascontiguousarray(particle_ray, dtype=np.intp),
                       np.ascontiguousarray(particle_range_m, dtype=np.float64),
                       np.ascontiguousarray(particle_signal_, dtype=np.float64), fraction, out_range, target_signal,
                       shadow, tgt_bg, np.ascontiguousarray(has_target), length, float(threshold), mode == "first",
                       background.cum, 1.0 / background.step_m, background.peak, kind, out_range, out_signal)
    return RayReturns(kind, out_range, out_signal)


@jit
def _target_returns(target_signal, target_range_m, has_target, shadow, at_target, inv_step,
                    threshold):       # pragma: no cover - compiled
    """Per ray, the result without particles: the target's pulse (0 without a target), the background at its crest
    (nearest entry of ``at_target``, none when empty), the return signal ``S_t (1 − min(1, shadow)) + B`` (no
    shadow when ``shadow`` is empty), its kind (TARGET at or above the threshold) and range."""
    n = len(target_signal)
    pulse = np.zeros(n)
    background = np.zeros(n)
    signal = np.zeros(n)
    kind = np.zeros(n, np.uint8)
    out_range = target_range_m.copy()
    last = len(at_target) - 1
    for i in range(n):
        if not has_target[i]:
            continue
        pulse[i] = target_signal[i]
        s = target_signal[i] * (1.0 - min(shadow[i], 1.0)) if len(shadow) else target_signal[i]
        if last >= 0:
            background[i] = at_target[min(int(target_range_m[i] * inv_step + 0.5), last)]
            s += background[i]
        signal[i] = s
        if s >= threshold:
            kind[i] = TARGET
    return pulse, background, signal, kind, out_range


# Phase factors e^{iθ} of the pulse sums: a 256-entry table of e^{i k 2π/256} times the Taylor series of the
# remainder (|δ| < 2π/256, truncation error < 2e-15): a third of the cost of math.cos + math.sin.
PHASOR_TABLE_SIZE = 256
_PHASOR_STEP = 2.0 * math.pi / PHASOR_TABLE_SIZE
_PHASOR_COS = np.cos(np.arange(PHASOR_TABLE_SIZE) * _PHASOR_STEP)
_PHASOR_SIN = np.sin(np.arange(PHASOR_TABLE_SIZE) * _PHASOR_STEP)


@jit(inline="always")
def phasor(theta):       # pragma: no cover - compiled
    """(cos θ, sin θ) for θ ≥ 0, within 1e-14 for θ ≤ 60 (a cluster of m pulses spans θ < 2πm); the table entry
    e^{ik·2π/256} below θ rotated by the Taylor series of the rest."""
    t = theta * (1.0 / _PHASOR_STEP)
    k = int(t)
    d = (t - k) * _PHASOR_STEP
    d2 = d * d
    cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0 - d2 * (1.0 / 720.0)))
    sd = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0 - d2 * (1.0 / 5040.0))))
    j = k & (PHASOR_TABLE_SIZE - 1)
    return _PHASOR_COS[j] * cd - _PHASOR_SIN[j] * sd, _PHASOR_SIN[j] * cd + _PHASOR_COS[j] * sd


@jit(inline="always")
def cluster_peak(r, a, cs, sn, lo, hi, length):       # pragma: no cover - compiled
    """Exact maximum of ``S(x) = Σ_k a_k sin²(π (x − r_k)/L)`` (each term on ``r_k ≤ x ≤ r_k + L``) over the
    contributions ``lo … hi−1`` (sorted by range; ``cs``, ``sn``: cos and sin of ``2π (r_k − r_0) / L`` for any
    common origin r_0); returns (peak, apparent range ``x − L/2``).

    Between consecutive pulse starts/ends the active set is fixed and ``S(x) = A/2 − Re(Z e^{iωx})/2`` with
    ``A = Σ a_k``, ``Z = Σ a_k e^{−iω r_k}``, ``ω = 2π/L``: on each piece the maximum is the crest ``(A + |Z|)/2`` if
    the phasor ``Z e^{iωx}`` reaches the negative real axis inside the piece, else an end value. Starts and ends are
    visited in one merge of the two sorted lists; ``e^{iωx}`` at an end equals that at its start (period L)."""
    omega = 2.0 * math.pi / length
    m = hi - lo
    cs = cs[lo:hi]
    sn = sn[lo:hi]
    amp = 0.0
    z_re = 0.0
    z_im = 0.0
    s = 0
    e = 0
    best = -1.0
    best_x = r[lo]
    while e < m:
        if s < m and r[lo + s] <= r[lo + e] + length:     # next event: a pulse start (first on ties) ...
            x = r[lo + s]
            step = a[lo + s]
            cu = cs[s]
            su = sn[s]
            s += 1
        else:                                              # ... or a pulse end
            x = r[lo + e] + length
            step = -a[lo + e]
            cu = cs[e]
            su = sn[e]
            e += 1
        amp += step
        z_re += step * cu
        z_im -= step * su
        if e >= m:                                         # the last end opens no piece
            break
        if s < m and r[lo + s] <= r[lo + e] + length:
            x_next = r[lo + s]
            cv = cs[s]
            sv = sn[s]
        else:
            x_next = r[lo + e] + length
            cv = cs[e]
            sv = sn[e]
        q_re = z_re * cu - z_im * su                       # Z e^{iωx} at both ends of the piece
        q_im = z_re * su + z_im * cu
        p_re = z_re * cv - z_im * sv
        p_im = z_re * sv + z_im * cv
        sweep = omega * (x_next - x)
        upper_u = q_im > 0 or (q_im == 0 and q_re < 0)     # angle in (0, π]
        upper_v = p_im > 0 or (p_im == 0 and p_re < 0)
        if sweep <= math.pi:
            crest = upper_u and not upper_v and sweep > 0
        else:
            crest = not (upper_v and not upper_u)
        if crest:
            val = (amp + math.sqrt(z_re * z_re + z_im * z_im)) / 2.0
            if val > best:
                best = val
                best_x = x + (math.pi - math.atan2(q_im, q_re)) / omega      # phase to the crest, in [0, 2π]
        else:
            val_u = (amp - q_re) / 2.0
            val_v = (amp - p_re) / 2.0
            if val_u > best or val_v > best:
                if val_v > val_u:
                    best = val_v
                    best_x = x_next
                else:
                    best = val_u
                    best_x = x
    return best, best_x - length / 2.0


@jit(inline="always")
def pair_peak(r1, a1, r2, a2, length, near_m=-1.0):       # pragma: no cover - compiled
    """:func:`cluster_peak` of two overlapping pulses (``r1 ≤ r2 < r1 + L``) in closed form; returns (peak, apparent
    range ``x − L/2``, whether that range lies within ``near_m`` of r2 — it is then returned as r2, without the arc
    tangent of the exact position).

    On the overlap ``[r2, r1 + L]`` the sum is ``A/2 − |B| cos(2π (x − r1)/L + arg B)/2`` with
    ``B = a1 + a2 e^{−iθ}``, ``θ = 2π (r2 − r1)/L``. For ``θ ≤ π`` arg B lies in ``[−θ, 0]``, so the crest
    ``(A + |B|)/2`` (at ``2π (x − r1)/L = π − arg B``) falls inside the overlap and is the maximum; for ``θ > π``
    arg B lies in ``[0, 2π − θ]``, the crest falls outside it, and the maximum is the stronger pulse at its own crest.
    The crest lies ``arg(B e^{iθ}) · L/2π`` (in [0, θ]) in front of r2: within δ = ``near_m`` iff
    ``Im(B e^{iθ} e^{−iωδ}) ≤ 0`` (ω = 2π/L, ωδ ≤ π)."""
    theta = 2.0 * math.pi * (r2 - r1) / length
    if theta > math.pi:
        if a1 >= a2:
            return a1, r1, r2 - r1 <= near_m
        return a2, r2, near_m >= 0.0
    c, s = phasor(theta)
    b_re = a1 + a2 * c
    b_im = -a2 * s
    peak = (a1 + a2 + math.sqrt(b_re * b_re + b_im * b_im)) / 2.0
    if near_m >= 0.0:
        cd, sd = phasor(min(2.0 * math.pi * near_m / length, math.pi))
        if a1 * s * cd - (a2 + a1 * c) * sd <= 0.0:       # Im(C e^{−iωδ}) with C = B e^{iθ} = a2 + a1 e^{iθ}
            return peak, r2, True
    return peak, r1 + (math.pi - math.atan2(b_im, b_re)) * length / (2.0 * math.pi) - length / 2.0, False


@jit(inline="always")
def _cluster_value(r, a, cos_buf, sin_buf, lo, hi, length):      # pragma: no cover - compiled
    """(peak, apparent range) of the cluster ``lo … hi−1``: a single pulse, :func:`pair_peak` or :func:`cluster_peak`
    (``cos_buf``/``sin_buf``: scratch space as long as ``r``)."""
    if hi - lo == 1:
        return a[lo], r[lo]
    if hi - lo == 2:
        peak, at, _ = pair_peak(r[lo], a[lo], r[lo + 1], a[lo + 1], length)
        return peak, at
    omega = 2.0 * math.pi / length
    for k in range(lo, hi):                            # phases relative to the first pulse (small arguments)
        cos_buf[k], sin_buf[k] = phasor(omega * (r[k] - r[lo]))
    return cluster_peak(r, a, cos_buf, sin_buf, lo, hi, length)


@jit(inline="always")
def _one_particle(r, a, t_range, t_raw, t_sig, t_bg, tgt, length, threshold, first_mode, bg,
                  inv_step):       # pragma: no cover - compiled
    """(value, apparent range, is the target) of a ray with one particle in front of its target (if any; ``t_raw``
    its pulse, ``t_sig`` with ``t_bg``, the background at its crest; ``bg``: :attr:`SoftBackground.cum`). A pair
    that keeps the target takes the background at the target's crest (its peak is within 0.2 m of it)."""
    if tgt and t_range - r < length:                   # one cluster: the pair
        val, at, own = pair_peak(r, a, t_range, t_raw, length, SAME_TARGET_TOLERANCE_M)
        if own:
            return val + t_bg, t_range, True
        return val + background_at(at + length / 2, t_range, bg, inv_step, length), at, False
    a += background_at(r + length / 2, t_range, bg, inv_step, length)
    if not tgt or (a >= threshold if first_mode else a >= t_sig):
        return a, r, False
    return t_sig, t_range, True


@jit
def _select_kernel(p_ray, p_range, p_signal, p_fraction, t_range, t_signal, t_shadow, t_background, has_target, length,
                   threshold, first_mode, bg, inv_step, bg_peak, kind, out_range, out_signal):  # pragma: no cover
    """:func:`select_returns` on the rays with particles, written in place into ``kind``, ``out_range``,
    ``out_signal`` (``t_range`` may be ``out_range``: each ray reads its target first; no shadowing when
    ``p_fraction`` is empty). ``t_signal``: the targets' pulses before shadowing, ``t_shadow`` a mean beam cover per
    ray (or empty), ``t_background`` the background at their crests;
    ``bg``, ``inv_step``, ``bg_peak``: the :class:`SoftBackground`.

    A cluster's peak lies between its strongest member and the sum of its members plus the background's peak: a ray
    whose particles sum below what they must beat (the target or the threshold) and do not overlap the target's pulse
    keeps the target result, and only clusters whose sum reaches the threshold and (strongest) the best lower bound
    of the ray are maximised exactly."""
    n = len(p_ray)
    shadowing = len(p_fraction) > 0
    mean_shadow = len(t_shadow) > 0
    cr = np.empty(n + 1)                               # one ray's contributions (particles, target): range, signal
    ca = np.empty(n + 1)
    cos_buf = np.empty(n + 1)
    sin_buf = np.empty(n + 1)
    c_lo = np.empty(n + 2, np.intp)                    # its clusters: first contribution, sum, strongest member
    c_sum = np.empty(n + 1)
    c_max = np.empty(n + 1)
    i = 0
    while i < n:
        ray = p_ray[i]
        total = p_signal[i]
        shadow = p_fraction[i] if shadowing else 0.0
        if mean_shadow:
            shadow += t_shadow[ray]
        j = i + 1
        while j < n and p_ray[j] == ray:               # one pass: the ray's end, total signal and shadowing
            total += p_signal[j]
            if shadowing:
                shadow += p_fraction[j]
            j += 1
        tgt = has_target[ray]
        r0 = t_range[ray]
        t_raw = t_signal[ray] * (1.0 - min(1.0, shadow)) if tgt else 0.0
        t_sig = t_raw + t_background[ray] if tgt else 0.0
        bar = max(t_sig, threshold) if tgt and not first_mode else threshold
        total += bg_peak
        if total < bar and not (tgt and r0 - p_range[j - 1] < length):
            out_signal[ray] = t_sig                    # the particles change nothing but the shadowing
            kind[ray] = TARGET if tgt and t_sig >= threshold else NO_RETURN
            i = j
            continue
        m = j - i
        if m == 1:                                     # one particle (the most common case)
            best_val, best_at, best_tgt = _one_particle(p_range[i], p_signal[i], r0, t_raw, t_sig, t_background[ray],
                                                        tgt, length, threshold, first_mode, bg, inv_step)
        else:
            for k in range(m):
                cr[k] = p_range[i + k]
                ca[k] = p_signal[i + k]
            if tgt:
                cr[m] = r0
                ca[m] = t_raw
                m += 1
            n_cl = 0                                   # clusters: consecutive contributions closer than L
            for k in range(m):
                if k == 0 or cr[k] - cr[k - 1] >= length:
                    c_lo[n_cl] = k
                    c_sum[n_cl] = 0.0
                    c_max[n_cl] = 0.0
                    n_cl += 1
                c_sum[n_cl - 1] += ca[k]
                c_max[n_cl - 1] = max(c_max[n_cl - 1], ca[k])
            c_lo[n_cl] = m
            need = threshold
            if not first_mode:
                for c in range(n_cl):
                    need = max(need, c_max[c])
            best_val = -1.0
            best_at = 0.0
            best_tgt = False
            for c in range(n_cl):
                if c_sum[c] + bg_peak < need:
                    continue                           # can neither be detected first nor win a detection
                val, at = _cluster_value(cr, ca, cos_buf, sin_buf, c_lo[c], c_lo[c + 1], length)
                val += background_at(at + length / 2, r0, bg, inv_step, length)
                own = tgt and c_lo[c + 1] == m and abs(at - cr[m - 1]) <= SAME_TARGET_TOLERANCE_M
                if own:
                    at = cr[m - 1]
                if val > best_val or (first_mode and val >= threshold):
                    best_val, best_at, best_tgt = val, at, own
                    if first_mode and val >= threshold:
                        break
        if best_val >= threshold:
            kind[ray] = TARGET if best_tgt else WEATHER
            out_range[ray] = best_at
            out_signal[ray] = best_val
        else:
            kind[ray] = NO_RETURN
        i = j


# ---------------------------------------------------------------------------------------------------------------
# Rays of a cloud and the output cloud


EMPTY_RAYS = ("fill", "ignore")       # what a weather model does with rays that returned nothing (cloud_rays)


@dataclass(frozen=True, eq=False)
class Rays:
    """The rays of a cloud as a weather model sees them: one per point of the cloud, then (point lists) one per
    empty cell of the list's firing grid (``listed``).

    ``range_m``: hard-target range, the profile's max range on empty rays, 0 on rays without a direction (zero points
    of a point list; every no-return ray with ``empty_rays='ignore'``). ``signal``: received signal of the target in
    units of the sensor constant K (m⁻², :func:`received_signal` / K). ``threshold``: detection threshold / K.
    ``empty_source``: where the empty rays came from, for the diagnostics."""

    range_m: np.ndarray
    signal: np.ndarray
    has_target: np.ndarray
    threshold: float
    profile: LidarProfile
    listed: FiringGrid | None = None
    empty_source: str = ""

    @property
    def n_points(self) -> int:
        """Rays that are points of the input cloud (the first ``n_points`` rays)."""
        return len(self.range_m) - (0 if self.listed is None else len(self.listed.ring))

    @property
    def empty(self) -> np.ndarray:
        """Rays without a target that can still return weather (no-return cells of a grid or a list)."""
        return ~self.has_target & (self.range_m > 0)

    @property
    def below_threshold(self) -> int:
        """Input returns whose signal is already below the detection threshold: the profile is less sensitive than
        the sensor that recorded them (any weather removes them unless a weather return takes their place); reported,
        with how many of them were removed (``removed_below_threshold_in``), so that such a mismatch is visible."""
        return int(np.count_nonzero(self.has_target & (self.signal < self.threshold)))


def check_intensity_scale(intensity: np.ndarray, profile: LidarProfile, model_id: str) -> None:
    """Refuse intensities that contradict the profile (the classic "0–1 cloud read as photons" mistake)."""
    if len(intensity) == 0:
        return
    top = float(np.max(intensity))
    fs = profile.intensity_full_scale
    if top > fs * (1 + 1e-6):
        raise ModelError(f"intensities reach {top:g} but profile {profile.name!r} says full scale {fs:g} "
                         f"({profile.intensity_unit}); give the profile matching the data", model=model_id,
                         field="intensity")
    if (profile.intensity_unit != IntensityUnit.UNIT and np.issubdtype(intensity.dtype, np.floating)
            and len(intensity) >= 100 and 0 < top <= 1.0):
        raise ModelError(f"all intensities are within [0, 1] but profile {profile.name!r} expects "
                         f"{profile.intensity_unit} up to {fs:g}; use a profile with intensity_unit 'unit' "
                         f"(e.g. kitti-hdl64, carla-64)", model=model_id, field="intensity")


def cloud_rays(cloud: PointCloud, model_id: str, empty_rays: str = "fill") -> Rays:
    """Validate a LiDAR cloud for a weather model and return its rays (signals in units of K).

    ``empty_rays='fill'``: rays without a return get the profile's max range, so weather can return on them — the
    no-return cells of a full grid, and for a point list the empty cells of its firing grid
    (:func:`firing_grid.firing_grid`), appended after the points; a list without a regular firing grid keeps only its
    points, and ``empty_source`` says why. ``'ignore'``: only the input's returns."""
    profile = cloud.profile
    if cloud.sensor != "lidar" or not isinstance(profile, LidarProfile):
        raise ModelError("needs a LiDAR point cloud with a LidarProfile (intensity unit, kind, sensor constant, "
                         "threshold)", model=model_id)
    if "intensity" not in cloud.fields:
        raise ModelError("needs an intensity field (the LiDAR equation scales weather returns by it)",
                         model=model_id, field="intensity")
    intensity = np.asarray(cloud.fields["intensity"])
    check_intensity_scale(intensity, profile, model_id)
    k = sensor_constant(profile)
    if not (profile.detection_threshold > 0 and k > 0):
        raise ModelError(f"profile {profile.name!r} has detection_threshold {profile.detection_threshold} and sensor "
                         f"constant {k}; both must be > 0 (signal units)", model=model_id, field="detection_threshold")
    if profile.intensity_kind not in (SIGNAL, REFLECTIVITY):
        raise _unknown_kind(profile)
    compensated = profile.intensity_kind == REFLECTIVITY
    scale = 1.0 / white_reading(profile) if compensated else 1.0 / k
    if empty_rays not in EMPTY_RAYS:
        raise ModelError(f"empty_rays {empty_rays!r} is not one of {EMPTY_RAYS}", model=model_id, field="empty_rays")
    fill = empty_rays == "fill"
    grid = cloud.grid_shape is not None
    r, signal, has_target = _ray_signals(np.ascontiguousarray(cloud.positions_m, dtype=np.float64), intensity,
                                         compensated, scale, profile.max_range_m if grid and fill else 0.0)
    rays = Rays(r, signal, has_target, profile.detection_threshold / k, profile,
                empty_source="none (empty_rays: ignore)" if not fill else "no-return cells of the grid")
    if fill and not grid:
        listed = firing_grid(cloud, profile, r)
        if isinstance(listed, str):
            return dataclasses.replace(rays, empty_source=f"none: {listed}")
        m = len(listed.ring)
        rays = Rays(np.concatenate([r, np.full(m, profile.max_range_m)]), np.concatenate([signal, np.zeros(m)]),
                    np.concatenate([has_target, np.zeros(m, dtype=bool)]), rays.threshold, profile, listed,
                    listed.describe())
    return rays


@jit
def _ray_signals(positions, intensity, compensated, scale, empty_range_m):       # pragma: no cover - compiled
    """Per point: range (``empty_range_m`` where the point is zero), received signal in units of K
    (:func:`received_signal` / K: ``I·scale`` or, range-compensated, ``I·scale / R²``; 0 without a return) and
    whether it is a return."""
    n = len(intensity)
    r = np.empty(n)
    signal = np.empty(n)
    has = np.empty(n, np.bool_)
    for i in range(n):
        ri = math.sqrt(positions[i, 0] ** 2 + positions[i, 1] ** 2 + positions[i, 2] ** 2)
        has[i] = ri > 0
        if ri > 0:
            r[i] = ri
            signal[i] = intensity[i] * scale / (ri * ri) if compensated else intensity[i] * scale
        else:
            r[i] = empty_range_m
            signal[i] = 0.0
    return r, signal, has


def _column_azimuth_model(cloud: PointCloud, has_return: np.ndarray) -> tuple[float, float, bool]:
    """(φ0, sign, offsets): azimuth of grid column c is ``φ0 + sign·2πc/W − [beam azimuth offset of the ring]``.

    Fitted on a subsample of the grid's returns (staggered Ouster grids carry the per-beam offsets, destaggered ones
    not); an empty grid gets the Ouster convention (φ0 = π, sign = −1, staggered)."""
    profile = cloud.profile
    cols = cloud.grid_shape[1]
    stride = 127                                           # < 1 % of the cells, spread over rows and columns
    valid = np.flatnonzero(has_return[::stride]) * stride
    if len(valid) == 0:
        return math.pi, -1.0, True
    p = cloud.positions_m[valid]
    phi = np.arctan2(p[:, 1], p[:, 0])
    col = valid % cols
    offs = np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[_rings(cloud, valid, profile)]
    best = None
    for sign in (-1.0, 1.0):
        for staggered in (True, False):
            e = np.exp(1j * (phi + (offs if staggered else 0.0) - sign * 2 * np.pi * col / cols)).mean()
            if best is None or abs(e) > best[0]:
                best = (abs(e), float(np.angle(e)), sign, staggered)
    return best[1], best[2], best[3]


def _rings(cloud: PointCloud, idx: np.ndarray, profile: LidarProfile) -> np.ndarray:
    rows, cols = cloud.grid_shape
    ring = np.asarray(cloud.fields["ring"])[idx].astype(np.intp) if "ring" in cloud.fields else idx // cols
    if len(ring) and (ring.min() < 0 or ring.max() >= profile.channels):
        raise ModelError(f"grid rows/rings up to {int(ring.max())} do not fit the {profile.channels} beams of "
                         f"profile {profile.name!r}")
    return ring


def empty_ray_directions(cloud: PointCloud, has_return: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Unit vectors of no-return cells ``idx`` of a full grid: elevation of the cell's beam (ring field or row),
    azimuth of its column (:func:`_column_azimuth_model`). The mm-scale beam-origin offsets are neglected."""
    profile = cloud.profile
    phi0, sign, staggered = _column_azimuth_model(cloud, has_return)
    ring = _rings(cloud, idx, profile)
    cols = cloud.grid_shape[1]
    az = phi0 + sign * 2 * np.pi * (idx % cols) / cols
    if staggered:
        az = az - np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring]
    el = np.deg2rad(np.asarray(profile.beam_elevation_deg))[ring]
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)


@jit
def _place_returns(kind, has, return_range_m, ray_range_m, reported, full_scale, integer, half_step, grid, positions,
                   intensity_in, positions_out, intensity_out, effect_out, origin_out):   # pragma: no cover - compiled
    """Per point of :func:`assemble`: position, stored intensity (the reported one clipped to full scale, rounded for
    integer dtypes), effect code (provenance.Effect) and origin (the input point), written to the outputs. A point
    list's removed points are left out (outputs filled from the start), a grid's are zeroed (REMOVED). Returns the
    removed mask, the number of outputs written and the counts (kept, attenuated, moved, removed, added)."""
    n = len(kind)
    removed = np.zeros(n, np.bool_)
    kept = attenuated = moved = n_removed = added = 0
    o = 0                                              # output index
    for i in range(n):
        scale = 1.0                                    # of the position
        effect = 0                                     # KEPT
        if kind[i] == NO_RETURN:
            value = intensity_in[i]
            if has[i]:
                removed[i] = True
                n_removed += 1
                if not grid:
                    continue
                scale = 0.0
                value = 0
                effect = REMOVED
        else:
            v = min(reported[i], full_scale)
            value = round(v) if integer else v
            if kind[i] == WEATHER:
                if has[i]:
                    scale = return_range_m[i] / ray_range_m[i]
                    effect = MOVED
                    moved += 1
                else:
                    scale = 0.0                        # filled by the caller (directions of empty cells)
                    effect = ADDED
                    added += 1
            else:
                intensity_out[o] = value               # the stored (converted) value decides
                if abs(float(intensity_out[o]) - float(intensity_in[i])) >= half_step:
                    effect = ATTENUATED
                    attenuated += 1
                else:
                    kept += 1
        intensity_out[o] = value
        effect_out[o] = effect
        origin_out[o] = i
        for c in range(3):
            positions_out[o, c] = positions[i, c] * scale if scale != 0.0 else 0.0     # no −0.0
        o += 1
    return removed, o, kept, attenuated, moved, n_removed, added


def assemble(cloud: PointCloud, rays: Rays, returns: RayReturns) -> tuple[PointCloud, dict]:
    """Build the output cloud: targets stay in place, weather returns move the point along its ray (MOVED) or fill an
    empty ray of a full grid (ADDED), rays without a return lose their point (removed from a point list, zeroed in a
    full grid like :meth:`PointCloud.drop`). Intensities are written back in the input's unit, kind and dtype
    (:func:`reported_intensity` at the return's range), clipped to full scale; every other field is the ray's.

    Provenance (:mod:`roadview_noise.provenance`): ``origin`` is the input point of the output's ray (NEW for the
    empty rays of a point list), ``effect`` the Effect code; targets in place are ATTENUATED when the stored
    intensity changed by at least half a step of the input's resolution (:func:`intensity_resolution`: 1 photon,
    1 count, 1/255 of a [0, 1] scale), else KEPT (a change below the file's resolution is no visible change; the
    sub-step value is still written). Attributes follow the fields."""
    profile = rays.profile
    intensity_in = np.asarray(cloud.fields["intensity"])
    reported = reported_intensity(returns.signal * sensor_constant(profile), returns.range_m, profile)
    n = rays.n_points
    cells = np.flatnonzero(returns.kind[n:] == WEATHER)          # a list's empty rays that return weather
    size = n + len(cells)                                         # outputs at most (a list's removed points go)
    effect = np.empty(size, np.uint8)
    origin = np.empty(size, np.int64)
    positions = np.empty((size, 3))
    intensity = np.empty(size, intensity_in.dtype)
    grid = cloud.grid_shape is not None
    integer = bool(np.issubdtype(intensity_in.dtype, np.integer))
    removed, n_out, kept, attenuated, moved, n_removed, added = _place_returns(
        returns.kind[:n], rays.has_target[:n], returns.range_m[:n], rays.range_m[:n], reported[:n],
        float(profile.intensity_full_scale), integer, 0.5 * intensity_resolution(profile), grid,
        np.ascontiguousarray(cloud.positions_m, dtype=np.float64), intensity_in, positions, intensity, effect, origin)
    if added:                                          # only full grids have empty rays with a direction
        idx = np.flatnonzero((returns.kind == WEATHER) & ~rays.has_target)
        positions[idx] = empty_ray_directions(cloud, rays.has_target, idx) * returns.range_m[idx, None]
    total = n_out + len(cells)
    fields = {**cloud.fields, "intensity": intensity[:total]}
    origin, attributes = origin[:total], cloud.attributes
    if n_removed and grid:
        fields = {k: (v if k in ("ring", "intensity") else np.where(removed, np.zeros((), v.dtype), v))
                  for k, v in fields.items()}
    if not (n_removed or len(cells)) or grid:
        origin = None                                  # point i is input point i
    else:
        index = origin                                 # the ray each output takes its other fields from
        if len(cells):
            _write_listed(rays.listed, cells, returns.range_m[n:], reported[n:], float(profile.intensity_full_scale),
                          integer, positions[n_out:total], intensity[n_out:total], effect[n_out:total])
            origin[n_out:] = NEW
            index = np.concatenate([index[:n_out], rays.listed.like[cells]])
            added += len(cells)
        fields = {k: (v if k == "intensity" else np.asarray(v).take(index, axis=0)) for k, v in fields.items()}
        attributes = {k: np.asarray(v).take(index, axis=0) for k, v in attributes.items()}
        if len(cells) and "ring" in fields:
            fields["ring"][n_out:] = rays.listed.ring[cells]
    out = dataclasses.replace(cloud, positions_m=positions[:total], fields=fields, origin=origin,
                              effect=effect[:total], attributes=attributes)
    faint = rays.has_target[:n] & (rays.signal[:n] < rays.threshold)
    counts = {"points_in": int(np.count_nonzero(rays.has_target)), "kept": kept, "attenuated": attenuated,
              "moved": moved, "removed": n_removed, "added": added, "below_threshold_in": rays.below_threshold,
              "removed_below_threshold_in": int(np.count_nonzero(removed & faint)), **empty_ray_counts(rays)}
    return out, counts


def _write_listed(listed: FiringGrid, cells: np.ndarray, range_m: np.ndarray, reported: np.ndarray,
                  full_scale: float, integer: bool, positions: np.ndarray, intensity: np.ndarray,
                  effect: np.ndarray) -> None:
    """The weather returns of a point list's empty rays ``cells`` as ADDED points, written to the given output
    slices: along the cell's direction at the return's range, intensity as :func:`_place_returns` stores it (the
    caller gives them the cell's ``ring`` and copies every other field from a return of the same firing column, same
    firing time)."""
    value = np.minimum(reported[cells], full_scale)
    intensity[:] = np.round(value) if integer else value
    effect[:] = ADDED
    positions[:] = listed.directions(cells, range_m[cells])


def empty_ray_counts(rays: Rays) -> dict:
    """Diagnostics of the empty rays: how many could return weather, the firing grid's columns of a point list
    (0: none) and where they came from (or why a list has none)."""
    return {"empty_rays": int(np.count_nonzero(rays.empty)),
            "firing_grid_columns": 0 if rays.listed is None else rays.listed.columns,
            "empty_rays_source": rays.empty_source}


def unchanged(cloud: PointCloud, rays: Rays) -> tuple[PointCloud, dict]:
    """The identity result of a zero-strength weather model: same points, every effect KEPT."""
    n = int(rays.has_target.sum())
    counts = {"points_in": n, "kept": n, "attenuated": 0, "moved": 0, "removed": 0, "added": 0,
              "below_threshold_in": rays.below_threshold, "removed_below_threshold_in": 0, **empty_ray_counts(rays)}
    return dataclasses.replace(cloud, effect=np.zeros(len(cloud), np.uint8)), counts
