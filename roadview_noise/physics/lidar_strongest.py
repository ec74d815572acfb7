"""The strongest return of rain and snow drawn from each ray's brightest particle down (models.md §3.3–§3.4 correct
versions; Hahner et al., CVPR 2022) — how :func:`lidar_weather.particle_returns` draws the strongest return.

Along a ray of range R the particles whose own return reaches s (units of the sensor constant K) are Poisson with
mean Λ(s; R), the visible count of :mod:`lidar_particles` at level s. Ordered from the brightest down, their ranks
``u = Λ(s; R)`` form a unit-rate Poisson process (mapping theorem): the brightest particle returns
``s1 = Λ⁻¹(E1; R)``, the next ``Λ⁻¹(E1 + E2; R)``, … (E_i standard exponentials), so each ray draws its brightest
particle directly, by inverse transform, and none of the fainter ones it would otherwise have to search through.

- Tables (:func:`brightest_tables`, cached per medium, beam, base level ℓ and pulse length): Λ(s_g; r) on the levels
  ``s_g = ℓ 2^(g/4)`` (quarter octaves) and ranges ``r_k = R1 + k·2 cm``, range-major (one ray's levels side by
  side). A particle of level band g takes its range from the band's range density (inverse-CDF tables, truncated
  at R) and its return within the band from its rank (Λ linear in s between the levels), at most what the largest
  particle returns at that range; its beam fraction is ``f = s / F(r)`` (F: a beam-filling particle's return).
- Drawn per ray: the brightest if it reaches the ray's own level ``ℓ 2^j`` (a target of attenuated signal S_t:
  ``j = ⌊log2(S_t/T)⌋`` ≤ 11, T the threshold — one or two weaker particles cannot outshine it; 0 without a target),
  then every particle down to the cut ``c = ℓ 2^(⌊log2(s1/ℓ)⌋ − 1)``, between s1/4 and s1/2: those can change the
  brightest's summed peak by a quarter or more, or, two together, outshine it.
- Undrawn (below c, or below the own level when nothing reaches it): their means, as :mod:`lidar_particles` treats
  the particles below ℓ — backscatter as a soft target (the :class:`lidar_echo.SoftBackground` of every particle
  below the ray's level, added to each cluster's peak and to the target's crest) and beam cover (the mean cover of
  those between ℓ and the level shadows the target; below ℓ the extinction α carries it).
The drawn particles and the target then give the ray's return exactly as :func:`lidar_echo.select_returns` does for
every particle above ℓ (summed pulses, exact peaks). Against that exhaustive draw
(``tests/models/test_lidar_weather.py``): the same weather-return counts, ranges and intensities within Monte-Carlo
noise, targets kept in place within 1 % — for one or two particles per ray instead of a dozen on the real OS1-128
scan in snow (151 k flakes instead of 1.08 M; the two-pass draw it replaces drew 300 k). What a target in place
loses is the fluctuation of the faint particles in front of it (their mean backscatter stays).

Speed (:func:`_strongest`): each ray's head — own level, rank, brightest band, the uniform of its range — is drawn
a ray ahead (:func:`ray_head`), and the table entries it will read are prefetched (:func:`compiled.prefetch`: the
range quantile, the cover), so that those cache misses overlap the previous ray's work; its brightest band is
counted, not walked to; the targets' attenuation is a pass of its own (no libm call in the per-ray loop); the
tables are float32 (:data:`TABLE_DTYPE`); the fainter particles stop at one comparison of Λ at the cut (read once
per ray) and read a band's ends only when they walk down to a new band; a cluster peak's background is read from
the uncut windows (:func:`lidar_echo.peak_background`) and the receiver's three uniforms come from one
(:func:`lidar_detection.three_uniforms`); a ray without a target decides with its uniforms, before its particles'
pulses are summed, whether even their total plus the largest background could be detected
(:func:`lidar_detection.undetectable`: half the empty rays of the real scan in rain cannot) — exact, the same draws in
the same order. The realization differs from drawing each ray after the previous one
(the draws come in another order), the law does not (``tests/physics/test_strongest_sampler.py`` against main's
sampler).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .compiled import jit, prefetch
from .lidar_detection import outshone, stored_returns, three_uniforms, undetectable, weather_decision
from .lidar_echo import NO_RETURN, TARGET, WEATHER, BackgroundLevels, RayReturns, SoftBackground, cluster_scratch, \
    crest_background, ray_return
from .lidar_medium import pulse_length_m
from .lidar_particles import BACKGROUND_STEP_M, TABLE_MAX_RANGE_M, Beam, ParticleMedium, faint_background, \
    faint_backscatter_per_m, faint_cross_section_per_m, lerp_at, scratch_buffer, table_lerp, visibility_diameter_mm
from .lidar_rays import Rays
from ..table_cache import disk_cached

LEVELS_PER_OCTAVE = 4           # Λ tables: levels ℓ 2^(g/4)
RANGE_STEP_M = 0.02             # Λ tables: range step
SUBSTEPS = 4                    # … integrated on a 4× finer grid
QUANTILES = 1024                # range quantiles per level band
OWN_LEVELS = 12                 # a target's own level ℓ 2^j, j < 12
CUT_OCTAVES = 1                 # a ray draws down to ℓ 2^(⌊log2(s1/ℓ)⌋ − 1)
MAX_DRAWN = 256                 # particles drawn on one ray at most (a safety bound; a ray draws a few)
TABLE_DTYPE = np.float32        # Λ, range quantiles, cover: half the cache footprint of float64 (relative error 6e-8)
SURE_UPPER = 1.0 + 1e-9         # a margin against rounding on the bounds of a candidate (ray_outcome)


@dataclass(frozen=True, eq=False)
class BrightestTables:
    """What the compiled sampler reads (module doc). ``lam[k, g]``: Λ(s_g; r_k), r_k = ``start_m + k·step_m``,
    s_g = ``base_level · 2^(g/4)`` (the last level lies above every particle's return); ``inv[g]``: range quantiles
    of the band [s_g, s_g+1) (``band_total[g]`` particles per ray in all); ``full[0]``: F(r_k), ``full[1]``: the
    return of the largest particle at r_k. Per octave level
    ℓ 2^l: ``cover[l, k]``, the mean beam cover ∫ of the particles between ℓ and that level up to r_k, and the
    ``background`` of every particle below it (:class:`lidar_echo.BackgroundLevels`, to 2 pulse lengths and 1 m
    beyond the tables' end: the cluster peaks lie within; farther targets take the base level's)."""

    base_level: float
    start_m: float
    step_m: float
    lam: np.ndarray
    inv: np.ndarray
    band_total: np.ndarray
    full: np.ndarray
    cover: np.ndarray
    background: BackgroundLevels

    @property
    def level_signal(self) -> np.ndarray:
        """The levels ``s_g = ℓ 2^(g/4)``."""
        return self.base_level * 2.0 ** (np.arange(self.lam.shape[1]) / LEVELS_PER_OCTAVE)

    @property
    def band_scale(self) -> np.ndarray:
        """Per level band, quantile index of :attr:`inv` per unit of Λ."""
        q = self.inv.shape[1] - 1
        return np.where(self.band_total > 0, q / np.maximum(self.band_total, 1e-300), 0.0)


@disk_cached(maxsize=4)
def brightest_tables(medium: ParticleMedium, beam: Beam, base_level: float, length_m: float) -> BrightestTables:
    """The tables of :class:`BrightestTables` for particles returning at least ``base_level`` (units of K) and pulses
    of length ``length_m`` = c τ_H (trapezoid integrals on 5 mm, tabulated every 2 cm; backgrounds:
    :func:`lidar_particles.faint_background`)."""
    m = LEVELS_PER_OCTAVE
    r_end = min(TABLE_MAX_RANGE_M, math.sqrt(medium.reflectance / base_level) + 1.0)   # bound with ξ = f = 1, α = 0
    fine = RANGE_STEP_M / SUBSTEPS
    r = beam.overlap_start_m + np.arange(0.0, max(r_end - beam.overlap_start_m, RANGE_STEP_M) + RANGE_STEP_M, fine)
    full = beam.full_beam_signal(medium, r)
    largest = full * np.minimum(1.0, (medium.size.optical_mm(medium.d_max_mm) * 0.5e-3 / beam.radius_at(r)) ** 2)
    levels = int(math.ceil(m * math.log2(max(largest.max(), base_level) / base_level))) + 2
    s = base_level * 2.0 ** (np.arange(levels) / m)
    lam, last = _tabled_lambda(medium, beam, s, r, fine)
    r, full, largest = (a[:SUBSTEPS * last:SUBSTEPS] for a in (r, full, largest))
    lam = lam[:len(r)]
    band = lam[:, :-1] - lam[:, 1:]
    band_total = band[-1].copy()
    inv = np.empty((levels - 1, QUANTILES))
    for g in range(levels - 1):
        inv[g] = np.interp(np.linspace(0.0, band_total[g], QUANTILES), band[:, g], r) if band_total[g] > 0 else r[0]
    octaves = (levels - 1) // m + 1
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = [faint_cross_section_per_m(medium, beam, base_level * 2.0 ** j, r) for j in range(octaves)]
    cover = np.array([np.concatenate([[0.0], np.cumsum((x[1:] + x[:-1] - sigma[0][1:] - sigma[0][:-1]) / 2
                                                       * RANGE_STEP_M)]) for x in sigma])
    near = np.arange(0.0, r[-1] + 2 * length_m + 1.0, BACKGROUND_STEP_M)     # beyond, every level's is the base's
    with np.errstate(divide="ignore", invalid="ignore"):
        backgrounds = [SoftBackground.of_density(np.nan_to_num(faint_backscatter_per_m(
            medium, beam, base_level * 2.0 ** j, near), nan=0.0, posinf=0.0), BACKGROUND_STEP_M, length_m)
            for j in range(octaves)]
    background = BackgroundLevels.of(backgrounds, faint_background(medium, beam, base_level, length_m))
    return BrightestTables(base_level, float(r[0]), RANGE_STEP_M, lam.astype(TABLE_DTYPE), inv.astype(TABLE_DTYPE),
                           band_total, np.stack([full, largest]), cover.astype(TABLE_DTYPE), background)


def _tabled_lambda(medium: ParticleMedium, beam: Beam, level_signal: np.ndarray, r: np.ndarray, fine: float,
                   block_rows: int = 8192) -> tuple[np.ndarray, int]:
    """Λ(s_g; r) = ∫ π w² N(≥ D_c(s_g, r)) dr by the trapezoid rule on the fine range grid ``r``, kept every
    ``SUBSTEPS`` rows (``fine``: the grid's step, m), and the table length (in kept rows) up to the last range where the base level is visible plus
    2. Computed in blocks of ``block_rows`` ranges (the whole fine table of a low base level is 10⁵ × 60 values per
    temporary), summed in the same order as one cumulative sum, so the values do not depend on the block size."""
    kept = np.empty(((len(r) + SUBSTEPS - 1) // SUBSTEPS, len(level_signal)))
    running = np.zeros((1, len(level_signal)))
    previous = None
    last_visible = -1
    for a in range(0, len(r), block_rows):
        rb = r[a:a + block_rows]
        with np.errstate(divide="ignore", invalid="ignore"):
            d_c = visibility_diameter_mm(medium, beam, level_signal[None, :], rb[:, None])
        density = np.pi * beam.radius_at(rb)[:, None] ** 2 * np.maximum(medium.count_above(d_c), 0.0)
        visible = np.flatnonzero(density[:, 0] > 0)
        if len(visible):
            last_visible = a + int(visible[-1])
        if previous is None:
            steps = np.concatenate([running, (density[1:] + density[:-1]) / 2 * fine])
        else:
            steps = np.concatenate([running, (density[:1] + previous) / 2 * fine,
                                    (density[1:] + density[:-1]) / 2 * fine])
        lam = np.cumsum(steps, axis=0)[0 if previous is None else 1:]
        first = -a % SUBSTEPS
        kept[(a + first) // SUBSTEPS:(a + len(rb) + SUBSTEPS - 1) // SUBSTEPS] = lam[first::SUBSTEPS]
        running, previous = lam[-1:], density[-1:]
    last = last_visible // SUBSTEPS + 2 if last_visible >= 0 else 2
    return kept, last


def strongest_returns(rng: np.random.Generator, rays: Rays, medium: ParticleMedium, beam: Beam,
                      base_level: float) -> tuple[RayReturns, int]:
    """Per ray of ``rays`` its strongest return among its particles and its target, detected (module doc): what
    :func:`draw_particles`, :func:`lidar_echo.select_returns` (candidates weaker than the receiver's
    :attr:`~receiver.Receiver.weakest_return` are none) and :func:`lidar_detection.detect` give, in one compiled pass
    over the rays (:func:`_strongest`: no particle arrays, each ray's noise drawn when its candidate is known).
    ``base_level``: ℓ (units of K). Returns the returns and the number of particles drawn."""
    tau_h_s = rays.profile.pulse_half_power_width_s
    length = float(pulse_length_m(tau_h_s))
    tables = brightest_tables(medium, beam, float(base_level), length)
    bg = tables.background
    rx = rays.receiver
    n = len(rays.range_m)
    kind, out_range, out_signal = np.zeros(n, np.uint8), np.empty(n), np.empty(n)
    drawn = _strongest(
        rng, np.ascontiguousarray(rays.range_m, dtype=np.float64),
        np.ascontiguousarray(rays.decision_signal, dtype=np.float64),
        np.ascontiguousarray(rays.has_target, dtype=bool), medium.alpha_per_m, float(rx.threshold),
        float(rx.weakest_return), tables.base_level, tables.start_m, tables.step_m, tables.lam, tables.inv,
        tables.band_scale, tables.level_signal, tables.full, tables.cover, bg.cum, bg.uncut, bg.peak, bg.at_target,
        bg.far_at_target, 1.0 / bg.step_m, length, float(rays.profile.overlap_start_m), rx.pulse_rise_m,
        *rx.kernel_params, kind, out_range, out_signal, np.empty(MAX_DRAWN), np.empty(MAX_DRAWN), np.empty(MAX_DRAWN),
        *cluster_scratch(MAX_DRAWN))
    return stored_returns(rays, RayReturns(kind, out_range, out_signal)), int(drawn)


@jit(error_model="numpy", _nrt=False)
def _strongest(rng, ray_range, signal, has_target, alpha, threshold, weakest, base, r1, step, lam, inv, band_scale,
               s_level, full, cover, bg_cum, bg_uncut, bg_peak, bg_at_target, bg_far, bg_inv_step, length, min_range,
               rise_m, spad, gain, floor, excess, rx_threshold, background, detect_count, background_cdf, below_k,
               kind, out_range, out_signal, p_range, p_signal, p_fraction, cr, ca, cos_buf,
               sin_buf):       # pragma: no cover - compiled
    """:func:`strongest_returns` ray by ray: the particles (:func:`ray_head` a ray ahead, :func:`draw_ray`), then
    the ray's candidate and the receiver's decision (:func:`ray_outcome`), written to ``kind``, ``out_range``,
    ``out_signal`` (``kind`` zeroed); the rest scratch space. Returns the number of particles drawn.
    The targets' ``exp(−2αR)`` are taken in a pass of their own before the rays' (``out_signal`` holds them until each
    ray's outcome is written): a call to libm inside the per-ray loop spills the loop's live registers (−3 to −10 %
    of the kernel, the same values). Compiled without reference counting (it allocates nothing): the inlined per-ray
    functions cost no atomic operations on their array arguments. Not compiled with contracted multiply-adds: 3–4 %
    faster, but a realization would then depend on whether the CPU has FMA."""
    n = len(ray_range)
    inv_step = 1.0 / step
    drawn = 0
    bg, rx, out, drawn_p, scratch = _outcome_arguments(
        bg_cum, bg_uncut, bg_peak, bg_at_target, bg_far, bg_inv_step, min_range, rise_m, spad, gain, floor, excess,
        rx_threshold, background, detect_count, background_cdf, below_k, kind, out_range, out_signal, p_range,
        p_signal, p_fraction, cr, ca, cos_buf, sin_buf)
    for i in range(n):                                 # the attenuated targets first, in out_signal (read before ray
        out_signal[i] = _attenuated(signal, has_target, ray_range, alpha, i)    # i's outcome overwrites it)
    e = rng.standard_exponential()                     # rank of the next brightest particle over the rays to come
    t_next = out_signal[0] if n else 0.0
    head = ray_head(rng, e, ray_range[0] if n else 0.0, t_next, threshold, r1, inv_step, lam, inv, band_scale, cover)
    for i in range(n):
        big_r = ray_range[i]
        tgt = has_target[i]
        t_att = t_next
        if i + 1 < n:                                  # the next ray's head: its table reads overlap this ray's work
            t_next = out_signal[i + 1]
            ahead = ray_head(rng, head[0], ray_range[i + 1], t_next, threshold, r1, inv_step, lam, inv, band_scale,
                             cover)
        else:
            ahead = head
        m, level, shadow = draw_ray(rng, head, big_r, r1, inv_step, 1.0 / base, lam, inv, band_scale, s_level, full,
                                    cover, p_range, p_signal, p_fraction, 0)
        head = ahead
        drawn += m
        ray_outcome(rng, i, m, level, shadow, big_r, tgt, t_att, weakest, length, bg, rx, out, drawn_p, scratch,
                    split_uniforms)
    return drawn


@jit(inline="always")
def _outcome_arguments(bg_cum, bg_uncut, bg_peak, bg_at_target, bg_far, bg_inv_step, min_range, rise_m, spad,
                       gain, floor, excess, rx_threshold, background, detect_count, background_cdf, below_k, kind,
                       out_range, out_signal, p_range, p_signal, p_fraction, cr, ca, cos_buf,
                       sin_buf):       # pragma: no cover - compiled
    """:func:`_strongest`'s arguments grouped for :func:`ray_outcome` (a compiled call inlines at most 30 arguments):
    the background tables, the receiver's parameters, the outputs, the drawn particles, the pulse-sum scratch."""
    return ((bg_cum, bg_uncut, bg_peak, bg_at_target, bg_far, bg_inv_step),
            (min_range, rise_m, spad, gain, floor, excess, rx_threshold, background, detect_count, background_cdf,
             below_k), (kind, out_range, out_signal), (p_range, p_signal, p_fraction),
            (cr, ca, cos_buf, sin_buf))


@jit(inline="always")
def ray_outcome(rng, i, m, level, shadow, big_r, tgt, t_att, weakest, length, bg, rx, out, drawn_p, scratch,
                uniforms):       # pragma: no cover - compiled
    """Ray i's return from its ``m`` drawn particles (draw level ``level``, mean cover ``shadow`` of the undrawn ones)
    and its attenuated target ``t_att`` (when ``tgt``), written to the outputs: the candidate
    (:func:`lidar_echo.ray_return`; without particles the target shadowed by the undrawn ones plus the background at
    its crest) and the receiver's decision (:func:`lidar_detection.outshone`, :func:`lidar_detection.weather_decision`;
    three uniforms per measured candidate, drawn by the compiled function ``uniforms(rng)``: :func:`split_uniforms`).
    ``bg``, ``rx``, ``out``, ``drawn_p``, ``scratch``: as :func:`_outcome_arguments` groups :func:`_strongest`'s
    arguments (an empty ``bg_uncut``: the peaks' backgrounds evaluated exactly, :func:`lidar_echo.peak_background`).
    A ray without a target whose brightest particle is a candidate draws its uniforms first (it draws them anyway, at
    the same point of the stream) and, when :func:`lidar_detection.undetectable` says that its particles' total plus
    the level's largest background cannot be detected with them, returns nothing (range and signal of a NO_RETURN
    are not read) without summing their pulses."""
    bg_cum, bg_uncut, bg_peak, bg_at_target, bg_far, bg_inv_step = bg
    min_range, rise_m, spad, gain, floor, excess, rx_threshold, background, detect_count, background_cdf, below_k = rx
    kind, out_range, out_signal = out
    p_range, p_signal, p_fraction = drawn_p
    cr, ca, cos_buf, sin_buf = scratch
    t_bg = crest_background(big_r, level, bg_at_target, bg_far, bg_inv_step) if tgt else 0.0
    early = not tgt and m > 0 and _sure_candidate(p_signal, m, weakest)
    u0 = u1 = u2 = 0.5
    if early:                                          # its candidate is measured: the uniforms it draws anyway
        u0, u1, u2 = uniforms(rng)
        if undetectable((_total(p_signal, m) + bg_peak[np.uintp(level)]) * SURE_UPPER, u0, u1, spad, gain,
                        detect_count, background_cdf):
            out_range[i], out_signal[i] = big_r, 0.0
            return
    if m == 0:
        value = t_att * (1.0 - min(shadow, 1.0)) + t_bg if tgt else 0.0
        c, at, t_value = (TARGET if tgt and value >= weakest else NO_RETURN), big_r, value
    else:
        c, at, value, t_value = ray_return(p_range, p_signal, p_fraction, 0, m, tgt, big_r, t_att, shadow, t_bg,
                                           length, weakest, False, bg_cum, bg_uncut, level, bg_inv_step,
                                           bg_peak[np.uintp(level)], cr, ca, cos_buf, sin_buf)
    out_range[i], out_signal[i] = at, value
    if c == WEATHER:
        t = t_value if tgt else 0.0
        target_ok = tgt and t >= rx_threshold
        if target_ok and outshone(value, t, gain, floor, excess):
            kind[i], out_range[i], out_signal[i] = TARGET, big_r, t
        else:
            if not early:
                u0, u1, u2 = uniforms(rng)
            k, r, v = weather_decision(value, at, t, target_ok, big_r, u0, u1, u2, True, min_range, rise_m, spad,
                                       gain, floor, excess, rx_threshold, background, detect_count, background_cdf,
                                       below_k)
            if k != NO_RETURN:
                kind[i], out_range[i], out_signal[i] = k, r, v
    elif c == TARGET and value >= rx_threshold:
        kind[i] = TARGET


@jit(inline="always")
def _sure_candidate(p_signal, m, weakest):       # pragma: no cover - compiled
    """Whether a ray without a target whose ``m`` ≥ 1 drawn particles have the returns ``p_signal`` surely has a
    weather candidate: its summed peak is at least its brightest particle's return, kept when it reaches
    ``weakest`` (with a margin against rounding)."""
    top = 0.0
    for k in range(m):
        top = max(top, p_signal[k])
    return top >= weakest * SURE_UPPER


@jit(inline="always")
def _total(p_signal, m):       # pragma: no cover - compiled
    """The sum of the first ``m`` drawn returns."""
    total = 0.0
    for k in range(m):
        total += p_signal[k]
    return total


@jit(inline="always")
def split_uniforms(rng):       # pragma: no cover - compiled
    """The receiver's three uniforms of a weather candidate from one draw (:func:`lidar_detection.three_uniforms`)."""
    return three_uniforms(rng.random())


@dataclass(frozen=True, eq=False)
class Drawn:
    """The particles :func:`draw_particles` drew, sorted by ray then range (ray, range m, signal in units of K, beam
    fraction), and per ray its attenuated target (0 without one), draw level (octaves above the base) and the mean
    beam cover of its undrawn particles above the base."""

    ray: np.ndarray
    range_m: np.ndarray
    signal: np.ndarray
    beam_fraction: np.ndarray
    target: np.ndarray
    level: np.ndarray
    shadow: np.ndarray


def draw_particles(rng: np.random.Generator, ray_range_m: np.ndarray, signal: np.ndarray, has_target: np.ndarray,
                   alpha_per_m: float, tables: BrightestTables, threshold: float) -> Drawn:
    """Each ray's brightest particles (module doc) with the extinction ``alpha_per_m`` and the receiver's
    ``threshold`` (units of K); one compiled pass (:func:`_draw`) in scratch buffers, repeated from where they
    filled up (rarely)."""
    ranges = np.ascontiguousarray(ray_range_m, dtype=np.float64)
    n = len(ranges)
    target, level, shadow = np.empty(n), np.empty(n, np.intp), np.empty(n)
    parts = []
    start, size = 0, 2 * n + MAX_DRAWN
    while start < n:
        buf = [scratch_buffer(name, size, np.intp if name == "ray" else np.float64)
               for name in ("ray", "range", "signal", "fraction")]
        start, m = _draw(rng, start, ranges, np.ascontiguousarray(signal, dtype=np.float64),
                         np.ascontiguousarray(has_target, dtype=bool), alpha_per_m, float(threshold),
                         tables.base_level, tables.start_m, tables.step_m, tables.lam, tables.inv, tables.band_scale,
                         tables.level_signal, tables.full, tables.cover, target, level, shadow, *buf)
        parts.append([b[:m] for b in buf] if start == n and not parts else [b[:m].copy() for b in buf])
        size *= 2
    columns = parts[0] if len(parts) == 1 else [np.concatenate(p) for p in zip(*parts)]
    return Drawn(*columns, target, level, shadow)


@jit(inline="always")
def _row_lerp(table, k, t, g):       # pragma: no cover - compiled
    """``table[k, g]`` and ``table[k + 1, g]`` interpolated at fraction t (unsigned indices, as
    :func:`lidar_particles.lerp_at`)."""
    a, b, col = np.uintp(k), np.uintp(k + 1), np.uintp(g)
    return table[a, col] + (table[b, col] - table[a, col]) * t


@jit(error_model="numpy", _nrt=False)
def _draw(rng, start, ray_range, signal, has_target, alpha, threshold, base, r1, step, lam, inv, band_scale, s_level,
          full, cover, target, ray_level, shadow, p_ray, p_range, p_signal, p_fraction):       # pragma: no cover - compiled
    """The particles of :func:`draw_particles` from ray ``start`` on (:func:`draw_ray`), written to ``p_*`` (sorted by
    ray, then range) until they are full; per ray its attenuated target ``target``, draw level ``ray_level`` and the
    mean beam cover of its undrawn particles ``shadow``. Returns the next ray to draw (len: all) and the number of
    particles written."""
    n = len(ray_range)
    capacity = len(p_ray)
    inv_step = 1.0 / step
    m = 0
    e = rng.standard_exponential()                     # rank of the next brightest particle over the rays to come
    for i in range(start, n):
        if m + MAX_DRAWN > capacity:
            return i, m
        target[i] = signal[i] * math.exp(-2.0 * alpha * ray_range[i]) if has_target[i] else 0.0
        head = ray_head(rng, e, ray_range[i], target[i], threshold, r1, inv_step, lam, inv, band_scale, cover)
        e = head[0]
        end, ray_level[i], shadow[i] = draw_ray(rng, head, ray_range[i], r1, inv_step, 1.0 / base, lam, inv,
                                                band_scale, s_level, full, cover, p_range, p_signal, p_fraction, m)
        p_ray[m:end] = i
        m = end
    return n, m


@jit(inline="always")
def _attenuated(signal, has_target, ray_range, alpha, i):       # pragma: no cover - compiled
    """The attenuated target ``S_t e^{−2αR}`` of ray i (0 without one, or past the last ray)."""
    if i >= len(ray_range) or not has_target[i]:
        return 0.0
    return signal[i] * math.exp(-2.0 * alpha * ray_range[i])


@jit(inline="always")
def ray_head(rng, e, big_r, t_att, threshold, r1, inv_step, lam, inv, band_scale,
             cover):       # pragma: no cover - compiled
    """The start of the draw of one ray of range ``big_r`` and attenuated target ``t_att`` (0: none), which
    :func:`_strongest` makes a ray ahead, so that its table reads (Λ at the ray's range, the range quantiles of its
    brightest particle: cache misses) overlap the previous ray's work: its own level; the rank of its brightest
    particle against Λ at that level (``e``: one exponential shared by the rays until one holds a particle — a ray
    without one leaves it ``E − Λ``, again exponential); the brightest particle's level band, the levels above the own
    level where Λ exceeds the rank counted (no branch per level: −5 to −8 % against walking up by octaves, then
    quarters); the range quantile its uniform falls at, prefetched. Octaves by comparisons, not frexp
    (:func:`_own_level`). Returns (the exponential left for the next ray, own level, table
    row k (−1: the ray ends before the overlap) and fraction t, band g (−1: no particle reaches the own level),
    rank u, Λ at both ends of the band, the quantile index and the fraction past it)."""
    rows, levels = lam.shape
    level = _own_level(t_att / threshold)
    x = (big_r - r1) * inv_step
    if not x > 0.0:
        return e, level, -1, 0.0, -1, 0.0, 0.0, 0.0, 0, 0.0
    x = min(x, rows - 1.000001)
    k = int(x)
    t = x - k
    g = min(level * LEVELS_PER_OCTAVE, levels - 1)
    own = _row_lerp(lam, k, t, g)
    prefetch(cover, np.uintp(min(level, cover.shape[0] - 1)), np.uintp(k))    # the cover of a ray without particles
    u = e
    if not u < own:
        return e - own, level, k, t, -1, u, 0.0, 0.0, 0, 0.0    # memoryless: E − Λ is the next ray's rank
    above = 0                                          # the brightest's band: the last g with Λ_g(R) > u (Λ
    for j in range(g + 1, levels - 1):                 # decreases with the level): counted, no branch per level
        above += _row_lerp(lam, k, t, j) > u
    g += above
    la = _row_lerp(lam, k, t, g)
    lb = _row_lerp(lam, k, t, g + 1)
    e = rng.standard_exponential()
    band = np.uintp(g)
    q = min(max(rng.random() * (la - lb) * band_scale[band], 0.0), inv.shape[1] - 1.000001)
    kq = int(q)
    prefetch(inv, band, np.uintp(kq))
    return e, level, k, t, g, u, la, lb, kq, q - kq


@jit(inline="always")
def draw_ray(rng, head, big_r, r1, inv_step, inv_base, lam, inv, band_scale, s_level, full, cover, p_range, p_signal,
             p_fraction, first):       # pragma: no cover - compiled
    """The particles of one ray of range ``big_r`` from its :func:`ray_head` ``head``, written to ``p_*`` from index
    ``first`` on, sorted by range: the brightest at its range quantile, then the particles down to the cut (rank
    spacings, bands walked down), sorted by range once drawn. Octaves by comparisons, not frexp
    (:func:`_octave_near`). Returns (the end of its particles, its draw level in octaves above the base, the mean beam
    cover of its undrawn particles)."""
    _, level, k, t, g, u, la, lb, kq, tq = head
    rows = lam.shape[0]
    octaves = cover.shape[0]
    m = first
    if k < 0:
        return m, min(level, octaves - 1), 0.0
    if g >= 0:
        r = min(lerp_at(inv, g, kq, tq), big_r)
        lam_cut = 0.0
        while True:
            s, f = particle_at(r, g, u, la, lb, r1, inv_step, rows, s_level, full)
            p_range[m], p_signal[m], p_fraction[m] = r, s, f
            if m == first:
                level = max(_octave_near(s * inv_base, g // LEVELS_PER_OCTAVE) - CUT_OCTAVES, 0)
                lam_cut = _row_lerp(lam, k, t, level * LEVELS_PER_OCTAVE)
            m += 1
            if m - first == MAX_DRAWN:
                break
            u += rng.standard_exponential()
            if lam_cut <= u:                           # none left above the cut (Λ decreases with the level)
                break
            while la <= u:                             # the band down (its ends read once per band)
                g -= 1
                lb = la
                la = _row_lerp(lam, k, t, g)
            band = np.uintp(g)
            r = min(table_lerp(inv, band, rng.random() * (la - lb) * band_scale[band]), big_r)
        _sort_by_range(p_range, p_signal, p_fraction, first, m)
    level = min(level, octaves - 1)
    return m, level, lerp_at(cover, level, k, t)


@jit(inline="always")
def particle_at(r, g, u, la, lb, r1, inv_step, rows, s_level, full):       # pragma: no cover - compiled
    """A particle of level band g at range ``r`` with rank ``u`` (Λ ``la``, ``lb`` at the band's ends at its ray's
    range): its return s (units of K; Λ linear in s between the levels ``s_level``, at most the largest particle's
    return at r) and its beam fraction s / F(r) (``full``: :attr:`BrightestTables.full`, ``rows`` entries from
    ``r1`` every 1 / ``inv_step`` m)."""
    xr = min(max((r - r1) * inv_step, 0.0), rows - 1.000001)
    kr = int(xr)
    tr = xr - kr
    top = min(s_level[np.uintp(g + 1)], lerp_at(full, 1, kr, tr))
    s_lo = s_level[np.uintp(g)]
    s = min(s_lo + (top - s_lo) * (la - u) / (la - lb), top)
    return s, s / lerp_at(full, 0, kr, tr)


@jit(inline="always")
def _sort_by_range(p_range, p_signal, p_fraction, lo, hi):       # pragma: no cover - compiled
    """Stable insertion sort of the particles ``lo … hi−1`` by range (a ray's few, after its draw: the draw does not
    wait for each range)."""
    for i in range(lo + 1, hi):
        r, s, f = p_range[i], p_signal[i], p_fraction[i]
        j = i
        while j > lo and p_range[j - 1] > r:
            p_range[j], p_signal[j], p_fraction[j] = p_range[j - 1], p_signal[j - 1], p_fraction[j - 1]
            j -= 1
        p_range[j], p_signal[j], p_fraction[j] = r, s, f


@jit(inline="always")
def _own_level(v):       # pragma: no cover - compiled
    """``⌊log2 v⌋`` clamped to [0, OWN_LEVELS − 1] (0 for v < 2 and NaN), by comparisons: no call to frexp."""
    level = 0
    for j in range(1, OWN_LEVELS):
        level += v >= float(1 << j)
    return level


@jit(inline="always")
def _octave_near(v, octave):       # pragma: no cover - compiled
    """``max(⌊log2 v⌋, 0)`` for v below ``2^(octave + 2)`` (octave ≥ 0; the octave of the band v was drawn in: v lies
    in it or below, where the largest particle caps it), by comparisons from there: no call to frexp."""
    while octave > 0 and v < float(1 << octave):
        octave -= 1
    return octave + 1 if v >= float(1 << (octave + 1)) else octave
