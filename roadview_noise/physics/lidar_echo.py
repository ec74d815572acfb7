"""The received-signal stage of the LiDAR weather pipeline: what a ray's receiver sees when the pulses of particles,
of the undrawn particles' mean backscatter and of the target add up (models.md §3.1, §3.3–§3.4; Hahner et al.,
CVPR 2022): per ray its candidate return — the strongest (or first) peak of the summed received profile, exactly
maximised — and what the target alone returns. Whether a candidate is detected is the receiver's decision
(:mod:`receiver`, :mod:`lidar_weather`). Signals in units of the sensor constant K.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..provenance import Effect
from .compiled import jit
from .lidar_medium import pulse_length_m

SAME_TARGET_TOLERANCE_M = 0.2           # a summed peak this close to the target keeps the target (Hahner 2022)
NO_RETURN, TARGET, WEATHER = 0, 1, 2     # what a ray returns after the weather
ATTENUATED, MOVED, ADDED, REMOVED = (int(e) for e in (Effect.ATTENUATED, Effect.MOVED, Effect.ADDED, Effect.REMOVED))


@dataclass(frozen=True, eq=False)
class RayReturns:
    """Per ray: what it returns (NO_RETURN, TARGET at its own position, WEATHER return), apparent range, signal; and
    ``target_signal``, what its target alone returns (after shadowing), the fallback when a weather candidate is not
    detected (empty when not known)."""

    kind: np.ndarray
    range_m: np.ndarray
    signal: np.ndarray
    target_signal: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True, eq=False)
class SoftBackground:
    """Mean received profile of a soft scatterer with backscatter density b(r) (units of K per metre of range):
    ``B(x; R0) = ∫_{x−L}^{min(x, R0)} sin²(π (x − r)/L) b(r) dr`` at pulse position x (apparent range x − L/2) in
    front of a target at R0. Since ``sin²(π s/L) = ½ − ½ cos ωs`` (ω = 2π/L), B needs only the cumulative integrals
    of b, b cos ωr and b sin ωr (``cum[k, 0–2]`` at ``r_k = k·step``, side by side for one cache line per lookup;
    constant beyond the table, where b = 0).
    ``peak``: the largest B of an uncut window; ``at_target[k]``: B at the crest of a target at ``r_k``
    (``x = r_k + L/2``); ``uncut[k]``: B(r_k; ∞), the window no target cuts. Evaluated by :func:`background_at`
    (stacked, :class:`BackgroundLevels`; or :func:`peak_background`, from ``uncut`` where it can); an empty ``cum``
    means no background."""

    step_m: float
    length_m: float
    cum: np.ndarray
    peak: float
    at_target: np.ndarray
    uncut: np.ndarray

    @classmethod
    def none(cls, length_m: float) -> SoftBackground:
        return cls(1.0, length_m, np.zeros((0, 3)), 0.0, np.zeros(0), np.zeros(0))

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
                   np.maximum(window(r + length_m / 2, r), 0.0), np.maximum(uncut, 0.0))


@dataclass(frozen=True, eq=False)
class BackgroundLevels:
    """:class:`SoftBackground` s of the same grid stacked, one per draw level (the mean backscatter of the particles
    below each level), for rays that each draw down to their own level: ``cum`` (levels, K, 3), ``peak`` (levels,),
    ``at_target`` and ``uncut`` (levels, K). The levels may stop at a range beyond which they all equal one background
    (no particle there returns as much as the lowest level): targets farther than K steps take their crest value from
    ``far_at_target``; cluster peaks must lie within the tables."""

    step_m: float
    length_m: float
    cum: np.ndarray
    peak: np.ndarray
    at_target: np.ndarray
    far_at_target: np.ndarray
    uncut: np.ndarray

    @classmethod
    def of(cls, backgrounds: list[SoftBackground], far: SoftBackground | None = None) -> BackgroundLevels:
        """Stacked ``backgrounds`` (one grid length), beyond which ``far`` (default: the first) holds."""
        first = backgrounds[0]
        far = far or first
        return cls(first.step_m, first.length_m, np.ascontiguousarray([b.cum for b in backgrounds]),
                   np.maximum(np.array([b.peak for b in backgrounds]), far.peak),
                   np.ascontiguousarray([b.at_target for b in backgrounds]), far.at_target,
                   np.ascontiguousarray([b.uncut for b in backgrounds]))


@jit(inline="always")
def _cumulative(cum, j, x):       # pragma: no cover - compiled
    """The three integrals of level j of :attr:`BackgroundLevels.cum` at grid coordinate x ≥ 0 (linear; constant
    beyond)."""
    last = cum.shape[1] - 1
    level = np.uintp(j)                                # (unsigned indices: no negative-index wraparound)
    if x >= last:
        end = np.uintp(last)
        return cum[level, end, 0], cum[level, end, 1], cum[level, end, 2]
    k = int(x)
    t = x - k
    a, b = np.uintp(k), np.uintp(k + 1)
    return (cum[level, a, 0] + (cum[level, b, 0] - cum[level, a, 0]) * t,
            cum[level, a, 1] + (cum[level, b, 1] - cum[level, a, 1]) * t,
            cum[level, a, 2] + (cum[level, b, 2] - cum[level, a, 2]) * t)


@jit(inline="always")
def background_at(x, r0, cum, j, inv_step, length):       # pragma: no cover - compiled
    """:class:`SoftBackground` value B(x; R0) of level j of the stacked cumulative tables ``cum``
    (:attr:`BackgroundLevels.cum`; 0 when they are empty)."""
    lo = max(x - length, 0.0)
    u = min(x, r0)
    if cum.shape[1] == 0 or u <= lo:
        return 0.0
    u0, uc, us = _cumulative(cum, j, u * inv_step)
    l0, lc, ls = _cumulative(cum, j, lo * inv_step)
    c, s = phasor(x * (2.0 * math.pi / length))
    return max(0.5 * ((u0 - l0) - c * (uc - lc) - s * (us - ls)), 0.0)


@jit(inline="always")
def peak_background(x, r0, cum, uncut, j, inv_step, length):       # pragma: no cover - compiled
    """:func:`background_at`, read from the uncut windows ``uncut`` (:attr:`BackgroundLevels.uncut`, linear between
    its entries: within 2e-3 of B's range of variation over a step, B < the threshold) where no target cuts the window
    (x ≤ R0) inside the table; elsewhere, or with an empty ``uncut``, evaluated exactly."""
    xg = x * inv_step
    if x <= r0 and 0.0 <= xg < uncut.shape[1] - 1:
        k = int(xg)
        a, b, level = np.uintp(k), np.uintp(k + 1), np.uintp(j)
        return uncut[level, a] + (uncut[level, b] - uncut[level, a]) * (xg - k)
    return background_at(x, r0, cum, j, inv_step, length)


def select_returns(particle_ray: np.ndarray, particle_range_m: np.ndarray, particle_signal_: np.ndarray,
                   target_range_m: np.ndarray, target_signal: np.ndarray, has_target: np.ndarray,
                   tau_h_s: float, threshold: float, mode: str,
                   particle_beam_fraction: np.ndarray | None = None,
                   background: SoftBackground | BackgroundLevels | None = None,
                   target_shadow: np.ndarray | None = None, ray_level: np.ndarray | None = None) -> RayReturns:
    """Returns of rays crossing discrete particles (§3.1, Hahner 2022): pulses closer than ``c τ_H`` add in power.

    ``particle_*`` are sorted by ray, then range (as :func:`lidar_particles.sample_particles` makes them). With
    ``particle_beam_fraction`` each target is first shadowed by the particles in front of it,
    ``S_t (1 − min(1, Σ f))`` (§3.3). Per ray the contributions (particles, then the target) form clusters of
    overlapping pulses; each cluster's summed received profile is maximised exactly (:func:`pair_peak`,
    :func:`cluster_peak`; Hahner samples it on a 0.1 m grid). The ray returns its strongest cluster
    (``mode='strongest'``, ties: the nearest) or the first one above ``threshold`` (``'first'``); a cluster holding
    the target whose peak lies within 0.2 m of it keeps the target in place with the summed intensity. Rays without
    particles return their target. ``threshold``: the weakest candidate worth returning (the detection threshold, or
    the weakest signal the receiver can detect in its noise, :attr:`receiver.Receiver.weakest_return`); whether a
    candidate is detected is decided later. ``background`` (the undrawn particles' mean backscatter, a
    :class:`SoftBackground` smaller than the threshold) adds to every cluster at its peak and to every target at its
    crest; with :class:`BackgroundLevels`, the level ``ray_level`` of each ray. ``target_shadow``: a mean beam cover
    per ray added to the particles' Σ f (undrawn particles). One compiled pass over the rays with particles."""
    length = pulse_length_m(tau_h_s)
    background = SoftBackground.none(length) if background is None else background
    if isinstance(background, SoftBackground):
        background = BackgroundLevels.of([background])
    level = np.zeros(0, np.intp) if ray_level is None else np.ascontiguousarray(ray_level, dtype=np.intp)
    shadow = np.zeros(0) if target_shadow is None else np.ascontiguousarray(target_shadow, dtype=np.float64)
    target_signal, tgt_bg, out_signal, kind, out_range = _target_returns(
        np.ascontiguousarray(target_signal, dtype=np.float64), np.ascontiguousarray(target_range_m, dtype=np.float64),
        np.ascontiguousarray(has_target), shadow, background.at_target, background.far_at_target, level,
        1.0 / background.step_m, float(threshold))
    target_value = out_signal.copy()
    if len(particle_ray):
        fraction = np.zeros(0) if particle_beam_fraction is None else np.ascontiguousarray(particle_beam_fraction,
                                                                                            dtype=np.float64)
        _select_kernel(np.ascontiguousarray(particle_ray, dtype=np.intp),
                       np.ascontiguousarray(particle_range_m, dtype=np.float64),
                       np.ascontiguousarray(particle_signal_, dtype=np.float64), fraction, out_range, target_signal,
                       shadow, tgt_bg, np.ascontiguousarray(has_target), length, float(threshold), mode == "first",
                       background.cum, np.zeros((0, 0)), level, 1.0 / background.step_m, background.peak, kind,
                       out_range, out_signal, target_value, *cluster_scratch(len(particle_ray)))
    return RayReturns(kind, out_range, out_signal, target_value)


@jit(inline="always")
def crest_background(r0, level, at_target, far_at_target, inv_step):       # pragma: no cover - compiled
    """The background at the crest of a target at range r0: the nearest entry of level ``level`` of ``at_target``
    (:attr:`BackgroundLevels.at_target`), of ``far_at_target`` beyond it; 0 when that is empty."""
    last = len(far_at_target) - 1
    if last < 0:
        return 0.0
    crest = int(r0 * inv_step + 0.5)
    if crest < at_target.shape[1]:
        return at_target[np.uintp(level), np.uintp(crest)]
    return far_at_target[np.uintp(min(crest, last))]


@jit
def _target_returns(target_signal, target_range_m, has_target, shadow, at_target, far_at_target, ray_level,
                    inv_step, threshold):       # pragma: no cover - compiled
    """Per ray, the result without particles: the target's pulse (0 without a target), the background at its crest
    (:func:`crest_background` at the ray's level — 0 when ``ray_level`` is empty), the return signal
    ``S_t (1 − min(1, shadow)) + B`` (no shadow when ``shadow`` is empty), its kind (TARGET at or above the
    threshold) and range."""
    n = len(target_signal)
    pulse = np.zeros(n)
    background = np.zeros(n)
    signal = np.zeros(n)
    kind = np.zeros(n, np.uint8)
    out_range = target_range_m.copy()
    levels = len(ray_level) > 0
    for i in range(n):
        if not has_target[i]:
            continue
        pulse[i] = target_signal[i]
        s = target_signal[i] * (1.0 - min(shadow[i], 1.0)) if len(shadow) else target_signal[i]
        background[i] = crest_background(target_range_m[i], ray_level[i] if levels else 0, at_target, far_at_target,
                                         inv_step)
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
    at_crest = False                                   # the best is a crest: its arc tangent taken once, at the end
    crest_re = crest_im = 0.0
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
                best_x, crest_re, crest_im, at_crest = x, q_re, q_im, True
        else:
            val_u = (amp - q_re) / 2.0
            val_v = (amp - p_re) / 2.0
            if val_u > best or val_v > best:
                at_crest = False
                if val_v > val_u:
                    best = val_v
                    best_x = x_next
                else:
                    best = val_u
                    best_x = x
    if at_crest:                                       # phase to the crest, in [0, 2π]
        best_x = best_x + (math.pi - math.atan2(crest_im, crest_re)) / omega
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
def _one_particle(r, a, t_range, t_raw, t_sig, t_bg, tgt, length, threshold, first_mode, bg, uncut, level,
                  inv_step):       # pragma: no cover - compiled
    """(value, apparent range, is the target) of a ray with one particle in front of its target (if any; ``t_raw``
    its pulse, ``t_sig`` with ``t_bg``, the background at its crest; ``bg``, ``uncut``, ``level``:
    :attr:`BackgroundLevels.cum` and ``uncut`` (:func:`peak_background`) and the ray's level). A pair
    that keeps the target takes the background at the target's crest (its peak is within 0.2 m of it)."""
    if tgt and t_range - r < length:                   # one cluster: the pair
        val, at, own = pair_peak(r, a, t_range, t_raw, length, SAME_TARGET_TOLERANCE_M)
        if own:
            return val + t_bg, t_range, True
        return val + peak_background(at + length / 2, t_range, bg, uncut, level, inv_step, length), at, False
    a += peak_background(r + length / 2, t_range, bg, uncut, level, inv_step, length)
    if not tgt or (a >= threshold if first_mode else a >= t_sig):
        return a, r, False
    return t_sig, t_range, True


@jit(error_model="numpy", _nrt=False)
def _select_kernel(p_ray, p_range, p_signal, p_fraction, t_range, t_signal, t_shadow, t_background, has_target, length,
                   threshold, first_mode, bg_levels, exact_background, ray_level, inv_step, bg_peaks, kind, out_range,
                   out_signal, t_value, cr, ca, cos_buf, sin_buf):  # pragma: no cover
    """:func:`select_returns` on the rays with particles (:func:`ray_return` per ray), written in place into
    ``kind``, ``out_range``, ``out_signal`` and ``t_value`` (``t_range`` may be ``out_range``: each ray reads its
    target first). ``t_signal``: the targets' pulses before shadowing, ``t_shadow`` a mean beam cover per ray (or
    empty), ``t_background`` the background at their crests; ``bg_levels``, ``inv_step``, ``bg_peaks``: the
    :class:`BackgroundLevels` (``exact_background``: an empty table, the peaks' backgrounds evaluated exactly,
    :func:`peak_background`), ``ray_level`` each ray's (empty: 0); the rest scratch space
    (:func:`cluster_scratch`). Compiled without reference counting (``_nrt=False``: it allocates nothing), so that
    the inlined per-ray functions cost no atomic operations on their array arguments."""
    n = len(p_ray)
    mean_shadow = len(t_shadow) > 0
    levels = len(ray_level) > 0
    i = 0
    while i < n:
        ray = p_ray[i]
        j = i + 1
        while j < n and p_ray[j] == ray:
            j += 1
        level = ray_level[ray] if levels else 0
        kind[ray], out_range[ray], out_signal[ray], t_value[ray] = ray_return(
            p_range, p_signal, p_fraction, i, j, has_target[ray], t_range[ray], t_signal[ray],
            t_shadow[ray] if mean_shadow else 0.0, t_background[ray], length, threshold, first_mode, bg_levels,
            exact_background, level, inv_step, bg_peaks[level], cr, ca, cos_buf, sin_buf)
        i = j


def cluster_scratch(particles: int) -> tuple[np.ndarray, ...]:
    """Scratch space of :func:`ray_return` for rays of up to ``particles`` particles: contributions (range, signal,
    phase cosine and sine)."""
    size = particles + 1
    return np.empty(size), np.empty(size), np.empty(size), np.empty(size)


@jit(inline="always")
def ray_return(p_range, p_signal, p_fraction, lo, hi, tgt, r0, t_pulse, shadow, t_bg, length, threshold, first_mode,
               bg_levels, bg_uncut, level, inv_step, bg_peak, cr, ca, cos_buf, sin_buf
               ):       # pragma: no cover - compiled
    """:func:`select_returns` on one ray: (kind, range, value, the target's value) from its particles ``lo … hi−1``
    (sorted by range; beam fractions ``p_fraction``, or none when empty) in front of its target (``tgt``: whether it
    has one, at ``r0`` with pulse ``t_pulse``, mean beam cover ``shadow`` of undrawn particles, background ``t_bg`` at
    its crest); ``bg_levels``, ``bg_uncut``, ``level``, ``bg_peak``: the ray's :class:`BackgroundLevels` entry
    (``bg_uncut`` empty: the background evaluated exactly, :func:`peak_background`); the rest scratch space
    (:func:`cluster_scratch`). The target's value is its shadowed pulse plus background, or the summed peak when its
    cluster keeps it in place.

    A cluster's peak lies between its strongest member and the sum of its members plus the background's peak: a ray
    whose particles sum below what they must beat (the target or the threshold) and do not overlap the target's pulse
    keeps the target result, and only clusters whose sum reaches the threshold and (strongest) the best lower bound
    of the ray are maximised exactly."""
    total = 0.0
    shadowing = len(p_fraction) > 0
    for k in range(lo, hi):                            # the ray's total signal and shadowing
        total += p_signal[k]
        if shadowing:
            shadow += p_fraction[k]
    t_raw = t_pulse * (1.0 - min(1.0, shadow)) if tgt else 0.0
    t_sig = t_raw + t_bg if tgt else 0.0
    bar = max(t_sig, threshold) if tgt and not first_mode else threshold
    total += bg_peak
    if total < bar and not (tgt and r0 - p_range[hi - 1] < length):
        return (TARGET if tgt and t_sig >= threshold else NO_RETURN), r0, t_sig, t_sig   # only the shadowing changes
    m = hi - lo
    if m == 1:                                         # one particle (the most common case)
        best_val, best_at, best_tgt = _one_particle(p_range[lo], p_signal[lo], r0, t_raw, t_sig, t_bg, tgt, length,
                                                    threshold, first_mode, bg_levels, bg_uncut, level, inv_step)
    else:
        top = 0.0                                      # the strongest contribution
        for k in range(m):
            cr[k] = p_range[lo + k]
            ca[k] = p_signal[lo + k]
            top = max(top, ca[k])
        if tgt:
            cr[m] = r0
            ca[m] = t_raw
            top = max(top, t_raw)
            m += 1
        need = threshold if first_mode else max(threshold, top)
        best_val = -1.0
        best_at = 0.0
        best_tgt = False
        first = 0                                      # clusters: consecutive contributions closer than L, each
        cluster_sum = 0.0                              # taken when it ends
        for k in range(1, m + 1):
            cluster_sum += ca[k - 1]
            if k < m and cr[k] - cr[k - 1] < length:
                continue
            if not cluster_sum + bg_peak < need:       # else it can neither be detected first nor win a detection
                val, at = _cluster_value(cr, ca, cos_buf, sin_buf, first, k, length)
                val += peak_background(at + length / 2, r0, bg_levels, bg_uncut, level, inv_step, length)
                own = tgt and k == m and abs(at - cr[m - 1]) <= SAME_TARGET_TOLERANCE_M
                if own:
                    at = cr[m - 1]
                if val > best_val or (first_mode and val >= threshold):
                    best_val, best_at, best_tgt = val, at, own
                    if first_mode and val >= threshold:
                        break
            first = k
            cluster_sum = 0.0
    if best_val < threshold:
        return NO_RETURN, r0, t_sig, t_sig
    return (TARGET if best_tgt else WEATHER), best_at, best_val, best_val if best_tgt else t_sig
