"""The strongest-return sampler of main before round 13 (``physics/lidar_strongest.py`` at d7fc0af), kept as the
reference that tests/physics/test_strongest_sampler.py checks the package's sampler against (in place of
:func:`lidar_strongest._strongest`, whose arguments it takes): each ray drawn after the previous one (no
look-ahead), its table reads where it needs them. Test code only: main's draw verbatim; the package's
:func:`lidar_strongest.ray_outcome` as main's before round 14 (the peaks' backgrounds evaluated exactly, three
uniforms drawn per decision)."""

from __future__ import annotations

import math

import numpy as np

from roadview_noise.physics.compiled import jit
from roadview_noise.physics.lidar_particles import lerp_at, table_lerp
from roadview_noise.physics.lidar_strongest import CUT_OCTAVES, LEVELS_PER_OCTAVE, MAX_DRAWN, _octave_near, \
    _outcome_arguments, _own_level, _row_lerp, _sort_by_range, particle_at, ray_outcome


@jit(error_model="numpy", _nrt=False)
def _strongest(rng, ray_range, signal, has_target, alpha, threshold, weakest, base, r1, step, lam, inv, band_scale,
               s_level, full, cover, bg_cum, bg_uncut, bg_peak, bg_at_target, bg_far, bg_inv_step, length, min_range,
               rise_m, spad, gain, floor, excess, rx_threshold, background, detect_count, background_cdf, below_k,
               kind, out_range, out_signal, p_range, p_signal, p_fraction, cr, ca, cos_buf,
               sin_buf):       # pragma: no cover - compiled
    """:func:`strongest_returns` ray by ray: the particles (:func:`draw_ray`, each ray after the previous one), then
    :func:`lidar_strongest.ray_outcome` as main's (the candidate and the receiver's decision), written to ``kind``,
    ``out_range``, ``out_signal`` (``kind`` zeroed); the rest scratch space. Returns the number of particles drawn.
    Compiled as the package's (no reference counting, no contracted multiply-adds)."""
    n = len(ray_range)
    inv_step = 1.0 / step
    drawn = 0
    bg, rx, out, drawn_p, scratch = _outcome_arguments(
        bg_cum, bg_uncut[:0, :0], bg_peak, bg_at_target, bg_far, bg_inv_step, min_range, rise_m, spad, gain, floor, excess,
        rx_threshold, background, detect_count, background_cdf, below_k, kind, out_range, out_signal, p_range,
        p_signal, p_fraction, cr, ca, cos_buf, sin_buf)
    e = rng.standard_exponential()                     # rank of the next brightest particle over the rays to come
    for i in range(n):
        big_r = ray_range[i]
        tgt = has_target[i]
        t_att = signal[i] * math.exp(-2.0 * alpha * big_r) if tgt else 0.0
        e, m, level, shadow = draw_ray(rng, e, big_r, t_att, threshold, r1, inv_step, 1.0 / base, lam, inv,
                                       band_scale, s_level, full, cover, p_range, p_signal, p_fraction, 0)
        drawn += m
        ray_outcome(rng, i, m, level, shadow, big_r, tgt, t_att, weakest, length, bg, rx, out, drawn_p, scratch,
                    three_draws)
    return drawn


@jit(inline="always")
def draw_ray(rng, e, big_r, t_att, threshold, r1, inv_step, inv_base, lam, inv, band_scale, s_level, full, cover,
             p_range, p_signal, p_fraction, first):       # pragma: no cover - compiled
    """The particles of one ray of range ``big_r`` and attenuated target ``t_att`` (0: none), written to ``p_*`` from
    index ``first`` on, sorted by range: its own level; the rank of its brightest particle against Λ at that level
    (``e``: one exponential shared by the rays until one holds a particle — a ray without one leaves it ``E − Λ``,
    again exponential); the brightest particle's level band, walked up from the own level by octaves, then quarter
    octaves; the particles down to the cut (rank spacings, bands walked down), sorted by range once drawn. Octaves
    by comparisons, not frexp (:func:`_own_level`, :func:`_octave_near`). Returns (the exponential left for the next
    ray, the end of its particles, its draw level in octaves above the base, the mean beam cover of its undrawn
    particles)."""
    rows, levels = lam.shape
    octaves = cover.shape[0]
    level = _own_level(t_att / threshold)
    m = first
    x = (big_r - r1) * inv_step
    if not x > 0.0:
        return e, m, min(level, octaves - 1), 0.0
    x = min(x, rows - 1.000001)
    k = int(x)
    t = x - k
    g = min(level * LEVELS_PER_OCTAVE, levels - 1)
    own = _row_lerp(lam, k, t, g)
    u = e
    e -= own                                           # memoryless: what is left of it is the next ray's rank
    if u < own:
        e = rng.standard_exponential()
        hi = levels - 2                                # the brightest's band: the last g with Λ_g(R) > u
        while g + LEVELS_PER_OCTAVE <= hi and _row_lerp(lam, k, t, g + LEVELS_PER_OCTAVE) > u:
            g += LEVELS_PER_OCTAVE                     # by octaves (Λ decreases with the level), then by quarters
        while g < hi and _row_lerp(lam, k, t, g + 1) > u:
            g += 1
        g_cut = 0
        while True:
            la = _row_lerp(lam, k, t, g)
            lb = _row_lerp(lam, k, t, g + 1)
            band = np.uintp(g)
            r = min(table_lerp(inv, band, rng.random() * (la - lb) * band_scale[band]), big_r)
            s, f = particle_at(r, g, u, la, lb, r1, inv_step, rows, s_level, full)
            p_range[m], p_signal[m], p_fraction[m] = r, s, f
            if m == first:
                level = max(_octave_near(s * inv_base, g // LEVELS_PER_OCTAVE) - CUT_OCTAVES, 0)
                g_cut = level * LEVELS_PER_OCTAVE
            m += 1
            if m - first == MAX_DRAWN:
                break
            u += rng.standard_exponential()
            while g >= g_cut and _row_lerp(lam, k, t, g) <= u:
                g -= 1
            if g < g_cut:
                break
        _sort_by_range(p_range, p_signal, p_fraction, first, m)
    level = min(level, octaves - 1)
    return e, m, level, lerp_at(cover, level, k, t)



@jit(inline="always")
def three_draws(rng):       # pragma: no cover - compiled
    """Main's three uniforms of a weather candidate: three draws."""
    return rng.random(), rng.random(), rng.random()
