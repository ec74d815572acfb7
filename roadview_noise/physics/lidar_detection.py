"""The detection stage of the LiDAR weather pipeline (models.md §3.1; :mod:`receiver`): the receiver's decision on
every ray between its weather candidate and its target.

A ray's candidate weather return (fog, a cluster of particle pulses) is measured in the receiver's noise — drawn, so
weather returns spread in intensity and range and their number varies smoothly with the weather's strength — and
competes with the ray's target, which keeps its recorded noise (its stored value times the transmission: zero
weather strength gives the input back; a recorded return of an unreliable reading counts at least the receiver's
floor, :meth:`receiver.Receiver.recorded_floor`). Strongest return: the larger detected value wins; first return: a
detected weather return in front wins. A return whose stored value would fall below the sensor's lowest reading is
dropped when the profile says the sensor drops it (``faint_reading: no_return``).
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import jit
from .lidar_echo import NO_RETURN, TARGET, WEATHER, RayReturns
from .lidar_intensity import reported_intensity, sensor_constant, too_faint
from .lidar_rays import Rays
from .receiver import LARGE_COUNT, background_count, measure_one, normal_quantile, poisson_quantile, range_sd_one

SURE_MARGIN_SD = 8.0       # a weather candidate this many of its noise SDs below the target cannot win (strongest)
SURE_MARGIN_P = 1e-12      # a Poisson probability this far above its uniform decides against rounding (undetectable)


def detect(rays: Rays, candidates: RayReturns, mode: str, uniforms: np.ndarray, per_ray: bool,
           rise_m: float | None = None) -> RayReturns:
    """The receiver's decision on every ray (module doc). ``candidates``: per ray a WEATHER candidate (measured here
    with :func:`receiver.measure_one`, its range jittered by :func:`receiver.range_sd_one` — leading edge ``rise_m``,
    default the pulse's — within the overlap start and the ray's range), a TARGET (its value frozen) or nothing;
    ``target_signal``: the target's own value, the fallback when the weather candidate is not detected or weaker.
    ``uniforms``: three per ray (``per_ray``: row = ray index, common random numbers across weather strengths) or
    per weather candidate, in ray order."""
    rx = rays.receiver
    kind, out_range, out_signal = _detect(
        candidates.kind, candidates.range_m, candidates.signal, candidates.target_signal, rays.has_target,
        rays.range_m, np.ascontiguousarray(uniforms, dtype=np.float64), per_ray, mode == "strongest",
        float(rays.profile.overlap_start_m), rx.pulse_rise_m if rise_m is None else float(rise_m),
        *rx.kernel_params)
    return stored_returns(rays, RayReturns(kind, out_range, out_signal))


def stored_returns(rays: Rays, returns: RayReturns) -> RayReturns:
    """``returns`` as the sensor stores them: a target in place gets back its reading times what the weather left of
    its signal (decided with :attr:`Rays.decision_signal`), the returns the sensor would not store are set to
    NO_RETURN (``faint_reading: no_return``)."""
    if rays.floor > 0:
        target = np.flatnonzero(returns.kind == TARGET)
        returns.signal[target] *= rays.signal[target] / rays.decision_signal[target]
    if rays.profile.faint_reading == "no_return":
        k = sensor_constant(rays.profile)
        returns.kind[(returns.kind != NO_RETURN) & too_faint(
            reported_intensity(returns.signal * k, returns.range_m, rays.profile), rays.profile)] = NO_RETURN
    return returns


@jit
def _detect(cand_kind, cand_range, cand_signal, target_signal, has_target, ray_range, u, per_ray, strongest,
            min_range, rise_m, spad, gain, floor, excess, threshold, background, detect_count, background_cdf,
            below_k):       # pragma: no cover - compiled
    """:func:`detect` in one pass: kind, range and signal per ray (from ``spad``: :attr:`Receiver.kernel_params`)."""
    n = len(cand_kind)
    kind = np.zeros(n, np.uint8)
    out_range = cand_range.copy()
    out_signal = cand_signal.copy()
    j = 0
    for i in range(n):
        c = cand_kind[i]
        if c == WEATHER:
            row = i if per_ray else j
            j += 1
            t = target_signal[i] if has_target[i] else 0.0
            target_ok = has_target[i] and t >= threshold
            if strongest and target_ok and outshone(cand_signal[i], t, gain, floor, excess):
                kind[i], out_range[i], out_signal[i] = TARGET, ray_range[i], t
                continue
            k, r, s = weather_decision(cand_signal[i], cand_range[i], t, target_ok, ray_range[i], u[row, 0],
                                       u[row, 1], u[row, 2], strongest, min_range, rise_m, spad, gain, floor, excess,
                                       threshold, background, detect_count, background_cdf, below_k)
            if k != NO_RETURN:
                kind[i], out_range[i], out_signal[i] = k, r, s
        elif c == TARGET and cand_signal[i] >= threshold:
            kind[i] = TARGET
    return kind, out_range, out_signal


@jit(inline="always")
def three_uniforms(u):       # pragma: no cover - compiled
    """Three independent uniforms on (0, 1) from one uniform ``u`` of 53 random bits (``Generator.random``): its top
    18, next 18 and last 17 bits, each at the midpoint of its cell (exact: scaling by powers of 2). One draw for the
    three of :func:`weather_decision` (a third of the generator calls); their resolution 2⁻¹⁸, 2⁻¹⁷ bounds the normal
    deviates drawn from them to ±4.4 SD (a tail of 1e-5)."""
    a = u * 262144.0
    i0 = math.floor(a)
    b = (a - i0) * 262144.0
    i1 = math.floor(b)
    i2 = math.floor((b - i1) * 131072.0)
    return (i0 + 0.5) * (1.0 / 262144.0), (i1 + 0.5) * (1.0 / 262144.0), (i2 + 0.5) * (1.0 / 131072.0)


@jit(inline="always")
def outshone(s, t, gain, floor, excess):       # pragma: no cover - compiled
    """Whether a weather candidate of expected signal s lies :data:`SURE_MARGIN_SD` of its noise SDs below a
    detected target t: it cannot win the strongest return (nothing to draw)."""
    return t > s + SURE_MARGIN_SD * math.sqrt(floor * floor + excess * s / gain)


@jit(inline="always")
def undetectable(s_max, u0, u1, spad, gain, detect_count, background_cdf):       # pragma: no cover - compiled
    """Whether a new return of expected signal at most ``s_max`` is surely not detected with the uniforms u0, u1 of
    :func:`receiver.measure_one` — decided without its signal: a photon-counting receiver counts at most as many
    photons at s ≤ ``s_max`` as at ``s_max`` with the same uniforms, and none reaches ``detect_count`` when
    ``P(Poisson(gain s_max) < detect_count − background) > u1`` (with a margin against rounding), i.e. when
    :func:`receiver.poisson_quantile` at ``u1`` plus that margin stays below it. False when unsure (Gaussian
    receivers, large counts, whose quantile is the normal approximation)."""
    mean = gain * s_max
    if not spad or mean >= LARGE_COUNT:
        return False
    return poisson_quantile(mean, u1 + SURE_MARGIN_P) + background_count(u0, background_cdf) < detect_count


@jit(inline="always")
def weather_decision(s, cand_range, t, target_ok, ray_range, u0, u1, u2, strongest, min_range, rise_m, spad, gain,
                     floor, excess, threshold, background, detect_count, background_cdf,
                     below_k):       # pragma: no cover - compiled
    """(kind, range, signal) of a ray whose weather candidate (expected signal s at ``cand_range``) is measured with
    the uniforms u0, u1 (:func:`receiver.measure_one`) against its target (value t, ``target_ok``: detected): the
    candidate when detected and (strongest) brighter, its range jittered by u2 within the overlap start and the
    ray's range; else the target, else NO_RETURN."""
    measured, detected = measure_one(s, u0, u1, spad, gain, floor, excess, threshold, background, detect_count,
                                     background_cdf, below_k)
    if detected and (not target_ok or not strongest or measured > t):
        r = cand_range + range_sd_one(s, rise_m, gain, floor, excess) * normal_quantile(u2)
        return WEATHER, min(max(r, min_range), ray_range), measured
    if target_ok:
        return TARGET, ray_range, t
    return NO_RETURN, cand_range, s
