"""Shared single-scattering LiDAR equation of the weather models (models.md §3.1; Hahner et al., ICCV 2021 fog and
CVPR 2022 snow), and the ray bookkeeping every LiDAR weather model shares.

Intensities are handled as *signals*: the input intensity divided by the profile's ``intensity_full_scale``. The
detection threshold is the profile's ``detection_threshold`` (in the input unit) divided by the same full scale, and
the particles' sensor constant is one full scale: a ρ = 1 Lambertian target filling the beam at 1 m returns full
scale (Hahner 2022; fog keeps Hahner 2021's per-point scale ``I R²/β0``). Every decision (weather return vs
target, detection) therefore compares quantities of one unit and gives the same result for a cloud in photons,
8-bit or [0, 1] intensities described by a matching profile; :func:`cloud_rays` refuses intensities that contradict
the profile instead of guessing.

Conventions
- Apparent range of a return = position of the received pulse peak minus ``c τ_H / 2`` (Hahner's shift), so a hard
  target at R appears at R.
- Pulse ``P(t) = sin²(π t / (2 τ_H))`` on ``0 ≤ t ≤ 2 τ_H``; in range it spans ``L = c τ_H``.
- Overlap (crossover) function ξ(r): 0 below R1 = 0.9 m, linear to 1 at R2 = 1.0 m (Hahner 2021).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import ModelError
from ..types import IntensityUnit, LidarProfile, PointCloud, PointLabel

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0
OVERLAP_R1_M = 0.9
OVERLAP_R2_M = 1.0
HAHNER_FOG_PULSE_S = 20e-9              # half-power pulse width of Hahner et al. 2021
SOFT_TABLE_STEP_M = 0.01                # range step of the fog pulse-integral table
SAME_TARGET_TOLERANCE_M = 0.2           # a summed peak this close to the target keeps the target (Hahner 2022)

NO_RETURN, TARGET, WEATHER = 0, 1, 2     # what a ray returns after the weather


# ---------------------------------------------------------------------------------------------------------------
# LiDAR equation


def overlap(r_m, r1_m: float = OVERLAP_R1_M, r2_m: float = OVERLAP_R2_M) -> np.ndarray:
    """Receiver overlap ξ(r): 0 for r ≤ R1, linear to 1 at R2, 1 beyond."""
    return np.clip((np.asarray(r_m, dtype=float) - r1_m) / (r2_m - r1_m), 0.0, 1.0)


def pulse_power(t_s, tau_h_s: float) -> np.ndarray:
    """Normalised transmitted power ``sin²(π t/(2 τ_H))`` for 0 ≤ t ≤ 2 τ_H, else 0 (peak 1, energy τ_H)."""
    t = np.asarray(t_s, dtype=float)
    return np.where((t >= 0) & (t <= 2 * tau_h_s), np.sin(np.pi * t / (2 * tau_h_s)) ** 2, 0.0)


def pulse_length_m(tau_h_s: float) -> float:
    """Range extent ``c τ_H`` of a received pulse (2 τ_H long in time, c/2 metres per second of delay)."""
    return SPEED_OF_LIGHT_M_PER_S * tau_h_s


def hard_target_signal(signal, alpha_per_m: float, range_m) -> np.ndarray:
    """Two-way Beer–Lambert loss of a hard target, ``I e^{−2αR}`` (same unit as ``signal``; finite ranges, so
    :func:`atmosphere.two_way_transmission`'s sky handling is not needed)."""
    t = np.exp(np.multiply(range_m, -2.0 * alpha_per_m))
    return np.multiply(signal, t, out=t) if isinstance(t, np.ndarray) else signal * t


def particle_signal(reflectance: float, beam_fraction, range_m, alpha_per_m: float) -> np.ndarray:
    """Return of a particle in full-scale units, ``K ρ f ξ(r) e^{−2αr} / r²`` with K = 1 full scale · m²."""
    r = np.asarray(range_m, dtype=float)
    return reflectance * beam_fraction * overlap(r) * np.exp(-2.0 * alpha_per_m * r) / (r * r)


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
def soft_target_table(alpha_per_m: float, tau_h_s: float, r1_m: float = OVERLAP_R1_M,
                      r2_m: float = OVERLAP_R2_M) -> SoftTargetTable:
    """Pulse-integral table of a homogeneous soft target (Hahner 2021 Eq. 8–10), cached per (α, τ_H, R1, R2).

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


def dominance_factor(length_m: float) -> float:
    """κ such that a target ≥ κ × (sum of the pulses overlapping it) keeps its summed peak within half the 0.2 m
    tolerance of its own crest: ``L asin(1/κ)/2π ≤ tol/2`` (and κ ≥ 5, so its value is at most 2 % low)."""
    return max(5.0, 1.0 / math.sin(math.pi * min(0.5, SAME_TARGET_TOLERANCE_M / length_m)))


def select_returns(particle_ray: np.ndarray, particle_range_m: np.ndarray, particle_signal_: np.ndarray,
                   target_range_m: np.ndarray, target_signal: np.ndarray, has_target: np.ndarray,
                   tau_h_s: float, threshold: float, mode: str) -> RayReturns:
    """Returns of rays crossing discrete particles (§3.1, Hahner 2022): pulses closer than ``c τ_H`` add in power.

    ``particle_*`` are sorted by ray, then range (as :func:`lidar_particles.sample_particles` makes them). Per ray the
    contributions (particles, then the target) form clusters of overlapping pulses; an isolated contribution peaks
    at its own range, a cluster's summed profile is maximised exactly (:func:`_summed_peaks`; Hahner samples it on
    a 0.1 m grid). The ray returns its strongest cluster (``mode='strongest'``) or the first one above threshold
    (``'first'``); a cluster holding the target whose peak lies within 0.2 m of it keeps the target in place with
    the summed intensity.

    Shortcut (exact up to a stated bound), taken per ray before any clustering: if all its particles together are
    weaker than the target (for 'first': than the threshold), no profile outside the target's pulse can be chosen;
    if moreover the target is at least κ times the sum of the particles overlapping its pulse
    (:func:`dominance_factor`), the ray returns the target in place with the summed profile at its crest (at most
    2 % low)."""
    n_rays = len(target_range_m)
    tgt_sig = np.where(has_target, target_signal, 0.0)
    base = RayReturns((tgt_sig >= threshold).view(np.uint8) * np.uint8(TARGET), target_range_m.copy(), tgt_sig)
    if len(particle_ray) == 0:
        return base
    length = pulse_length_m(tau_h_s)
    # --- rays resolved by their target ---------------------------------------------------------------------------
    s = target_range_m[particle_ray] + length / 2 - particle_range_m        # crest of the target pulse − r_j
    near = (s <= 1.5 * length) & has_target[particle_ray]                      # pulse overlaps the target's
    near_sum = np.bincount(particle_ray, weights=np.where(near, particle_signal_, 0.0), minlength=n_rays)
    far_sum = np.bincount(particle_ray, weights=np.where(near, 0.0, particle_signal_), minlength=n_rays)
    resolved = has_target & (far_sum + near_sum < (tgt_sig if mode == "strongest" else threshold))
    resolved &= tgt_sig >= dominance_factor(length) * near_sum
    p_res = resolved[particle_ray]
    if p_res.any():
        crest = np.where(p_res & near & (s >= 0), np.sin(np.pi * np.minimum(s, length) / length) ** 2, 0.0)
        value = tgt_sig + np.bincount(particle_ray, weights=particle_signal_ * crest, minlength=n_rays)
        rr = np.flatnonzero(resolved & ((near_sum > 0) | (far_sum > 0)))
        base.signal[rr] = value[rr]
        base.kind[rr] = np.where(value[rr] >= threshold, TARGET, NO_RETURN)
        keep = ~p_res
        particle_ray, particle_range_m, particle_signal_ = (particle_ray[keep], particle_range_m[keep],
                                                            particle_signal_[keep])
    n_p = len(particle_ray)
    if n_p == 0:
        return base
    # --- contributions: per remaining ray with particles, its particles then its target -------------------------
    first_of_slot = np.empty(n_p, dtype=bool)
    first_of_slot[0] = True
    np.not_equal(particle_ray[1:], particle_ray[:-1], out=first_of_slot[1:])
    slot_start = np.flatnonzero(first_of_slot)
    slot_ray = particle_ray[slot_start]
    slot_count = np.diff(np.append(slot_start, n_p))
    slot_of_particle = np.cumsum(first_of_slot) - 1
    slot_tgt = has_target[slot_ray]
    tgt_before = np.cumsum(slot_tgt) - slot_tgt
    n_c = n_p + int(slot_tgt.sum())
    c_range = np.empty(n_c)
    c_signal = np.empty(n_c)
    c_slot = np.empty(n_c, dtype=np.intp)
    c_is_target = np.zeros(n_c, dtype=bool)
    p_pos = np.arange(n_p) + tgt_before[slot_of_particle]
    c_range[p_pos], c_signal[p_pos], c_slot[p_pos] = particle_range_m, particle_signal_, slot_of_particle
    t_slots = np.flatnonzero(slot_tgt)
    t_pos = slot_start[t_slots] + slot_count[t_slots] + tgt_before[t_slots]
    t_rays = slot_ray[t_slots]
    c_range[t_pos], c_signal[t_pos], c_slot[t_pos] = target_range_m[t_rays], target_signal[t_rays], t_slots
    c_is_target[t_pos] = True
    # --- clusters of overlapping pulses -------------------------------------------------------------------------
    linked = (c_slot[1:] == c_slot[:-1]) & (np.diff(c_range) < length)
    starts = np.ones(n_c, dtype=bool)
    starts[1:] = ~linked
    cl_first = np.flatnonzero(starts)
    cl_size = np.diff(np.append(cl_first, n_c))
    cl_signal = c_signal[cl_first]
    cl_range = c_range[cl_first]
    cl_is_target = c_is_target[cl_first] & (cl_size == 1)
    multi = np.flatnonzero(cl_size > 1)
    if len(multi):
        _resolve_clusters(multi, cl_first, cl_size, c_range, c_signal, c_slot, c_is_target, cl_signal, cl_range,
                          cl_is_target, length, threshold, mode)
    # --- per ray: strongest cluster, or first above threshold ---------------------------------------------------
    cl_slot = c_slot[cl_first]
    slot_first_cl = np.flatnonzero(np.r_[True, cl_slot[1:] != cl_slot[:-1]])
    idx = np.arange(len(cl_first))
    strongest = np.maximum.reduceat(cl_signal, slot_first_cl)
    big = len(cl_first)
    chosen = np.minimum.reduceat(np.where(cl_signal == strongest[cl_slot], idx, big), slot_first_cl)
    if mode == "first":
        first = np.minimum.reduceat(np.where(cl_signal >= threshold, idx, big), slot_first_cl)
        chosen = np.where(first < big, first, chosen)
    sig = cl_signal[chosen]
    base.kind[slot_ray] = np.where(sig >= threshold, np.where(cl_is_target[chosen], TARGET, WEATHER), NO_RETURN)
    base.range_m[slot_ray] = cl_range[chosen]
    base.signal[slot_ray] = sig
    return base


def _resolve_clusters(multi, cl_first, cl_size, c_range, c_signal, c_slot, c_is_target, cl_signal, cl_range,
                      cl_is_target, length: float, threshold: float, mode: str) -> None:
    """Value, range and target flag (written in place) of the clusters ``multi`` of ≥ 2 overlapping pulses.

    Triage, exact where it can change the outcome:
    - the target dominates (``A_t ≥ κ Σ others``, :func:`dominance_factor`): by ``A_t (π/L) sin(2π(x−R)/L) = −E'(x)``
      the peak lies within ``L asin(1/κ)/2π`` (≤ ½ of the 0.2 m tolerance) of the target's crest, so the target
      stays; value = the sum at that crest (low by at most ``asin(1/κ)/2 · Σ others`` ≤ 2 % of ``A_t``);
    - the cluster cannot be chosen (``Σ a`` below threshold, or, for strongest, not above the best single return of
      its ray): represented by its strongest member (the target if that lies within the tolerance of it);
    - otherwise the exact maximum of the summed profile (:func:`_summed_peaks`)."""
    first, size = cl_first[multi], cl_size[multi]
    last = first + size - 1
    total = np.add.reduceat(c_signal, cl_first)[multi]
    strongest = np.maximum.reduceat(c_signal, cl_first)[multi]
    # strongest member (lower bound): index of the first member reaching it
    member_cl = np.repeat(np.arange(len(multi)), size)
    member = np.arange(len(member_cl)) + np.repeat(first - (np.cumsum(size) - size), size)
    hit = np.minimum.reduceat(np.where(c_signal[member] == strongest[member_cl], member, len(c_signal)),
                              np.cumsum(size) - size)
    near_target = c_is_target[last] & (np.abs(c_range[hit] - c_range[last]) <= SAME_TARGET_TOLERANCE_M)
    cl_signal[multi] = strongest
    cl_range[multi] = np.where(near_target, c_range[last], c_range[hit])
    cl_is_target[multi] = near_target
    kappa = dominance_factor(length)
    t_amp = np.where(c_is_target[last], c_signal[last], 0.0)
    dominated = c_is_target[last] & (t_amp >= kappa * (total - t_amp))
    if dominated.any():
        dm = dominated[member_cl] & ~c_is_target[member]
        s = c_range[last][member_cl[dm]] + length / 2 - c_range[member[dm]]
        extra = np.bincount(member_cl[dm], weights=c_signal[member[dm]] * np.where(
            (s >= 0) & (s <= length), np.sin(np.pi * s / length) ** 2, 0.0), minlength=len(multi))
        d = multi[dominated]
        cl_signal[d], cl_range[d], cl_is_target[d] = (t_amp + extra)[dominated], c_range[last[dominated]], True
    open_ = ~dominated & (total >= threshold)
    if mode == "strongest":
        slot = c_slot[cl_first]
        slot_first = np.flatnonzero(np.r_[True, slot[1:] != slot[:-1]])
        best_single = np.maximum.reduceat(np.maximum.reduceat(c_signal, cl_first), slot_first)
        slot_rank = np.cumsum(np.r_[True, slot[1:] != slot[:-1]]) - 1
        open_ &= total > best_single[slot_rank[multi]]
    if open_.any():
        o = multi[open_]
        peak, peak_range = _summed_peaks(cl_first[o], cl_size[o], c_range, c_signal, length)
        t_last = cl_first[o] + cl_size[o] - 1
        own = c_is_target[t_last] & (np.abs(peak_range - c_range[t_last]) <= SAME_TARGET_TOLERANCE_M)
        cl_signal[o] = peak
        cl_range[o] = np.where(own, c_range[t_last], peak_range)
        cl_is_target[o] = own


def _summed_peaks(first: np.ndarray, size: np.ndarray, c_range: np.ndarray, c_signal: np.ndarray,
                  length: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact maximum of ``S(x) = Σ a_k sin²(π (x − r_k)/L)`` (each term on ``r_k ≤ x ≤ r_k + L``) over each cluster
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


# ---------------------------------------------------------------------------------------------------------------
# Rays of a cloud and the output cloud


@dataclass(frozen=True, eq=False)
class Rays:
    """The rays of a cloud as a weather model sees them (one per point of the cloud).

    ``range_m``: hard-target range, the profile's max range on empty rays of a full grid, 0 on rays without a
    direction (zero points of a point list). ``signal``: target intensity / full scale. ``threshold``: detection
    threshold / full scale."""

    range_m: np.ndarray
    signal: np.ndarray
    has_target: np.ndarray
    threshold: float
    profile: LidarProfile

    @property
    def empty(self) -> np.ndarray:
        """Rays without a target that can still return weather (no-return cells of a full grid)."""
        return ~self.has_target & (self.range_m > 0)


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


def cloud_rays(cloud: PointCloud, model_id: str) -> Rays:
    """Validate a LiDAR cloud for a weather model and return its rays (signals in full-scale units)."""
    profile = cloud.profile
    if cloud.sensor != "lidar" or not isinstance(profile, LidarProfile):
        raise ModelError("needs a LiDAR point cloud with a LidarProfile (intensity unit, full scale, threshold)",
                         model=model_id)
    if "intensity" not in cloud.fields:
        raise ModelError("needs an intensity field (the LiDAR equation scales weather returns by it)",
                         model=model_id, field="intensity")
    intensity = np.asarray(cloud.fields["intensity"])
    check_intensity_scale(intensity, profile, model_id)
    if not profile.detection_threshold > 0:
        raise ModelError(f"profile {profile.name!r} has detection_threshold {profile.detection_threshold}; it must "
                         "be > 0 (in the intensity unit)", model=model_id, field="detection_threshold")
    p = cloud.positions_m
    r = np.sqrt(np.einsum("ij,ij->i", p, p))
    has_target = r > 0
    if cloud.grid_shape is not None:
        r = np.where(has_target, r, profile.max_range_m)
    signal = np.where(has_target, intensity / profile.intensity_full_scale, 0.0)
    return Rays(r, signal, has_target, profile.detection_threshold / profile.intensity_full_scale, profile)


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


def _to_dtype(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    return (np.rint(values) if np.issubdtype(dtype, np.integer) else values).astype(dtype)


def assemble(cloud: PointCloud, rays: Rays, returns: RayReturns) -> tuple[PointCloud, dict]:
    """Build the output cloud: targets stay (KEPT, or ATTENUATED if their intensity changed), weather returns move
    the point along its ray (MOVED) or fill an empty ray (ADDED), rays without a return lose their point (removed
    from a point list, zeroed in a full grid like :meth:`PointCloud.drop`). Intensities are written back in the
    input's unit and dtype, clipped to full scale; the ``label`` field (uint8) is created if absent."""
    kind, has = returns.kind, rays.has_target
    intensity_in = np.asarray(cloud.fields["intensity"])
    active = kind != NO_RETURN
    new = _to_dtype(np.minimum(returns.signal, 1.0) * rays.profile.intensity_full_scale, intensity_in.dtype)
    intensity = np.where(active, new, intensity_in)
    weather = kind == WEATHER
    moved, added = weather & has, weather & ~has
    removed = ~active & has
    attenuated = (kind == TARGET) & (intensity != intensity_in)
    grid = cloud.grid_shape is not None
    positions = cloud.positions_m.copy()
    idx = np.flatnonzero(moved)
    positions[idx] *= (returns.range_m[idx] / rays.range_m[idx])[:, None]
    if grid:
        positions[removed] = 0.0
    idx = np.flatnonzero(added)
    if len(idx):
        positions[idx] = empty_ray_directions(cloud, has, idx) * returns.range_m[idx, None]
    base = cloud.fields.get("label")
    base = np.zeros(len(cloud), np.uint8) if base is None else np.asarray(base)
    label = np.where(moved, PointLabel.MOVED, np.where(added, PointLabel.ADDED, np.where(
        attenuated, PointLabel.ATTENUATED, base))).astype(base.dtype)
    fields = {**cloud.fields, "intensity": intensity, "label": label}
    n_removed = int(np.count_nonzero(removed))
    if n_removed and grid:
        fields = {k: (v if k == "ring" else np.where(removed, np.zeros((), v.dtype), v)) for k, v in fields.items()}
    elif n_removed:
        keep = ~removed
        positions = positions[keep]
        fields = {k: np.asarray(v)[keep] for k, v in fields.items()}
    out = dataclasses.replace(cloud, positions_m=positions, fields=fields)
    n_target = int(np.count_nonzero(kind == TARGET))
    n_att = int(np.count_nonzero(attenuated))
    counts = {"points_in": int(np.count_nonzero(has)), "kept": n_target - n_att, "attenuated": n_att,
              "moved": int(np.count_nonzero(moved)), "removed": n_removed, "added": len(idx)}
    return out, counts


def unchanged(cloud: PointCloud, rays: Rays) -> tuple[PointCloud, dict]:
    """The identity result of a zero-strength weather model: same points, every label KEPT (label field added)."""
    label = cloud.fields.get("label")
    label = np.zeros(len(cloud), np.uint8) if label is None else np.array(label, copy=True)
    counts = {"points_in": int(rays.has_target.sum()), "kept": int(rays.has_target.sum()), "attenuated": 0,
              "moved": 0, "removed": 0, "added": 0}
    return cloud.with_fields(label=label), counts
