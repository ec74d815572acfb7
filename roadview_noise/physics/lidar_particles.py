"""The particle medium of the LiDAR weather pipeline: discrete precipitation particles in LiDAR beams (models.md
§3.3–§3.4 correct versions; Hahner et al., CVPR 2022).

Particles form a Poisson process along each beam with density ``n π w(r)²`` (n from the exponential DSD in melted
diameter D_m, ``w(r) = w0 + r θ/2`` the beam radius, θ the full divergence angle). A particle of geometric diameter
``D = size(D_m)`` (:class:`dsd.SizeLaw`: the drop itself for rain, the flake for snow) at range r covers the beam
fraction ``f = min(1, (D / 2w(r))²)`` and returns ``K ρ f ξ(r) e^{−2αr} / r²`` (carried in units of the sensor
constant K, :func:`lidar_medium.particle_signal`; ξ with the profile's overlap R1, R2, part of :class:`Beam`).

Only particles that can change a return are drawn one by one; the rest are replaced by their mean.
- Base level ``ℓ``: particles whose own return reaches a fraction of the detection threshold
  (``visible_fraction``, default ``VISIBLE_FRACTION`` = ½, so that two overlapping ones can reach it; lowered if
  needed so that the background below stays under half the threshold, :func:`draw_level`).
- :func:`sample_particles` draws every particle above ``ℓ`` (the first return, and the reference of the strongest
  return, which draws only each ray's brightest particles: :mod:`lidar_strongest`), an exact thinning of the
  Poisson process — positions follow the cumulative visible density ``Λ(r) = ∫ π w² N(D ≥ D_c(r)) dr`` (cached
  tables) and diameters the truncated exponential above the visibility diameter ``D_c(r)`` — so a frame costs a
  few operations per *visible* particle (an empty 120 m ray at 20 mm/h holds ~10 drops of which ~0.2 are visible to
  an OS1-128). Placing them on their rays is one compiled pass (:func:`_place`), as is the return selection
  (:func:`lidar_echo.select_returns`).
- The undrawn ones act through their means: extinction α and backscatter — a soft target like fog
  (:func:`faint_background`, :class:`lidar_echo.SoftBackground`) added to every summed pulse profile; what remains
  approximate is their fluctuation (e.g. three sub-level flakes summing over the threshold: weather returns are
  ~1 % below the converged count for snow at ½, ``bench/bench_lidar_weather.py`` prints the convergence). Their
  beam cover per metre, :func:`faint_cross_section_per_m`, shadows a target when a ray leaves particles above ℓ
  undrawn.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from . import dsd
from .compiled import jit
from .lidar_echo import SoftBackground
from .lidar_medium import particle_signal
from ..table_cache import disk_cached

VISIBLE_FRACTION = 0.5        # default: particles returning less than this fraction of the threshold are not drawn
TABLE_STEP_M = 0.01
TABLE_MAX_RANGE_M = 1000.0
BACKGROUND_STEP_M = 0.05


@dataclass(frozen=True)
class ParticleMedium:
    """Exponential DSD ``N(D_m) = N0 e^{−Λ D_m}`` in melted diameter on [Dmin, Dmax] (m⁻³ mm⁻¹, mm⁻¹, mm), the
    particles' geometric size ``size`` (:class:`dsd.SizeLaw`, identity for drops), effective Lambertian reflectance
    ρ, and the medium's extinction α (m⁻¹)."""

    n0_per_m3_mm: float
    lam_per_mm: float
    d_min_mm: float
    d_max_mm: float
    reflectance: float
    alpha_per_m: float
    size: dsd.SizeLaw = dsd.SizeLaw()

    def count_above(self, d_mm: np.ndarray) -> np.ndarray:
        """Particles per m³ with melted diameter ≥ d (and within [Dmin, Dmax])."""
        lo = np.clip(d_mm, self.d_min_mm, self.d_max_mm)
        return self.n0_per_m3_mm / self.lam_per_mm * (np.exp(-self.lam_per_mm * lo)
                                                      - math.exp(-self.lam_per_mm * self.d_max_mm))


@dataclass(frozen=True)
class Beam:
    """Beam radius ``w(r) = w0 + r θ/2`` (m), θ the full divergence angle (rad), and the receiver overlap ξ: 0 up to
    ``overlap_start_m`` (R1), linear to 1 at ``overlap_full_m`` (R2). Hashable: the cached tables key on it."""

    radius_m: float
    divergence_rad: float
    overlap_start_m: float
    overlap_full_m: float

    @classmethod
    def of(cls, profile) -> Beam:
        """The beam of a :class:`LidarProfile`."""
        return cls(profile.beam_radius_m, profile.beam_divergence_rad, profile.overlap_start_m,
                   profile.overlap_full_m)

    def radius_at(self, r_m):
        return self.radius_m + np.asarray(r_m) * (self.divergence_rad / 2)

    def full_beam_signal(self, medium: ParticleMedium, r_m) -> np.ndarray:
        """Return of a beam-filling particle of the medium at range r, ``ρ ξ(r) e^{−2αr}/r²`` (units of K)."""
        return particle_signal(medium.reflectance, 1.0, r_m, medium.alpha_per_m, self.overlap_start_m,
                               self.overlap_full_m)


def visibility_diameter_mm(medium: ParticleMedium, beam: Beam, level: float, r_m) -> np.ndarray:
    """Smallest melted diameter (mm) whose return at range r reaches ``level`` (units of K): the geometric diameter
    ``2 w sqrt(level / ρ ξ e^{−2αr} r⁻²)`` through the size law; inf where even a beam-filling particle stays below
    it (and below the overlap range R1)."""
    r = np.asarray(r_m, dtype=float)
    full_beam = beam.full_beam_signal(medium, r)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 2e3 * beam.radius_at(r) * np.sqrt(level / full_beam)
    return np.where(full_beam >= level, medium.size.melted_mm(np.where(full_beam >= level, d, 1.0)), np.inf)


@dataclass(frozen=True, eq=False)
class VisibleTable:
    """Per-beam tables on the regular range grid ``r_k = R1 + k·step`` (``start_m`` = R1, the beam's overlap start;
    cached per medium, beam and level):
    cumulative visible count Λ(r_k), the lower diameter bound ``max(Dmin, D_c(r_k))`` (mm) and the beam-filling
    return ``ρ ξ e^{−2αr}/r²`` (units of K); plus ``Λ⁻¹`` on a regular grid of Λ (step ``inv_step``). Lookups
    (:func:`_ray_measures`, :func:`_place`) interpolate linearly, clamped to the tables."""

    start_m: float
    step_m: float
    cum: np.ndarray
    d_low_mm: np.ndarray
    full_beam: np.ndarray
    inv_step: float
    inv_range_m: np.ndarray


@lru_cache(maxsize=16)
def visible_table(medium: ParticleMedium, beam: Beam, level: float) -> VisibleTable:
    """Expected visible particles ``Λ(r) = ∫_{R1}^{r} π w² N(D ≥ D_c) dr`` (trapezoid, 0.01 m) up to the range where
    no particle reaches ``level`` any more (at most 1000 m), with its inverse on 4× as many points."""
    r_end = min(TABLE_MAX_RANGE_M, math.sqrt(medium.reflectance / level) + 1.0)   # bound with ξ = f = 1, α = 0
    span = max(r_end - beam.overlap_start_m, TABLE_STEP_M)
    r = beam.overlap_start_m + np.arange(0.0, span + TABLE_STEP_M, TABLE_STEP_M)
    d_c = visibility_diameter_mm(medium, beam, level, r)
    density = np.pi * beam.radius_at(r) ** 2 * medium.count_above(d_c)
    last = int(np.flatnonzero(density > 0)[-1]) + 2 if np.any(density > 0) else 2
    r, density, d_c = r[:last], density[:last], d_c[:last]
    cum = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * TABLE_STEP_M)])
    d_low = np.clip(d_c, medium.d_min_mm, medium.d_max_mm)
    full_beam = beam.full_beam_signal(medium, r)
    grid = np.linspace(0.0, cum[-1], 4 * len(cum))
    inverse = np.interp(grid, cum, r) if cum[-1] > 0 else np.full(len(grid), r[0])
    return VisibleTable(beam.overlap_start_m, TABLE_STEP_M, cum, d_low, full_beam,
                        grid[1] - grid[0] if cum[-1] > 0 else 1.0, inverse)


def faint_cross_section_per_m(medium: ParticleMedium, beam: Beam, level: float, r_m) -> np.ndarray:
    """Expected beam cover per metre of range (m⁻¹) of the particles whose own return at r is below ``level``:
    ``∫_{Dmin}^{min(D_c, Dmax)} N(D_m) π w² f(D, r) dD_m`` with ``π w² f = min(π D²/4, π w²)`` (closed form: the
    moment of D² below the beam-filling size, :meth:`dsd.SizeLaw.moment`, the count above)."""
    r = np.asarray(r_m, dtype=float)
    hi = np.clip(visibility_diameter_mm(medium, beam, level, r), medium.d_min_mm, medium.d_max_mm)
    w = beam.radius_at(r)
    filling = np.clip(medium.size.melted_mm(2e3 * w), medium.d_min_mm, hi)    # beam-filling melted diameter (mm)
    n0, lam = medium.n0_per_m3_mm, medium.lam_per_mm
    return (np.pi / 4 * 1e-6 * medium.size.moment(n0, lam, 2, medium.d_min_mm, filling)
            + np.pi * w * w * dsd.exponential_moment(n0, lam, 0, filling, np.maximum(hi, filling)))


def faint_backscatter_per_m(medium: ParticleMedium, beam: Beam, level: float, r_m) -> np.ndarray:
    """Mean return per metre of range (units of K per m) of the particles whose own return is below ``level``:
    ``b(r) = ρ ξ(r) e^{−2αr}/r² ·`` :func:`faint_cross_section_per_m`."""
    return beam.full_beam_signal(medium, r_m) * faint_cross_section_per_m(medium, beam, level, r_m)


@disk_cached(maxsize=16)
def faint_background(medium: ParticleMedium, beam: Beam, level: float, length_m: float) -> SoftBackground:
    """The undrawn particles as a soft target: their mean backscatter :func:`faint_backscatter_per_m` (0.05 m grid
    to 1000 m; compact for the cache) under the pulse window of length ``L = c τ_H``
    (:class:`lidar_echo.SoftBackground`), cached."""
    r = np.arange(0.0, TABLE_MAX_RANGE_M + BACKGROUND_STEP_M / 2, BACKGROUND_STEP_M)
    with np.errstate(divide="ignore", invalid="ignore"):
        b = np.nan_to_num(faint_backscatter_per_m(medium, beam, level, r), nan=0.0, posinf=0.0)
    return SoftBackground.of_density(b, BACKGROUND_STEP_M, length_m)


def draw_level(medium: ParticleMedium, beam: Beam, threshold: float, visible_fraction: float,
               length_m: float) -> tuple[float, SoftBackground]:
    """(level, background): particles returning at least ``visible_fraction × threshold`` are drawn, the rest is the
    mean background; the level is halved until the background's peak stays below half the threshold, so the
    background alone never makes a return and its fluctuations stay small next to the drawn particles."""
    level = visible_fraction * threshold
    background = faint_background(medium, beam, level, length_m)
    while background.peak > threshold / 2:
        level /= 2
        background = faint_background(medium, beam, level, length_m)
    return level, background


@dataclass(frozen=True, eq=False)
class Particles:
    """Drawn particles, sorted by ray then range: ray index, range (m), melted diameter (mm), beam fraction,
    signal."""

    ray: np.ndarray
    range_m: np.ndarray
    diameter_mm: np.ndarray
    beam_fraction: np.ndarray
    signal: np.ndarray


@jit(inline="always")
def table_lerp(table, j, x):       # pragma: no cover - compiled
    """Row j of the 2-D ``table`` at fractional index x, linear, clamped to [0, last]."""
    x = min(max(x, 0.0), table.shape[1] - 1.000001)
    k = int(x)
    return lerp_at(table, j, k, x - k)


@jit(inline="always")
def lerp_at(table, j, k, t):       # pragma: no cover - compiled
    """``table[j, k]`` and ``table[j, k + 1]`` interpolated at fraction t (j, k ≥ 0). The indices are unsigned:
    numba then compiles no negative-index wraparound (a compare and a conditional move per access; with the
    other table reads of the strongest-return kernel made unsigned too: −5 to −8 % of it)."""
    row, a, b = np.uintp(j), np.uintp(k), np.uintp(k + 1)
    return table[row, a] + (table[row, b] - table[row, a]) * t


@jit
def _ray_measures(ray_range_m, r0_m, step_m, cum):       # pragma: no cover - compiled
    """Running sum over the rays of their expected drawn particles Λ(R) (``cum``: the visible table as one row; 0 up
    to R1, constant beyond the table)."""
    n = len(ray_range_m)
    total_out = np.empty(n)
    total = 0.0
    for i in range(n):
        r = ray_range_m[i]
        if r > r0_m:
            total += table_lerp(cum, 0, (r - r0_m) / step_m)
        total_out[i] = total
    return total_out


@jit
def _place(spacing, exp_d, cum_ray, ray_range_m, inv_range_m, inv_step, r0_m, step_m, d_low_mm, full_beam, lam_per_mm,
           d_max_mm, w0_m, half_divergence_rad, size_c, size_p, size_k):      # pragma: no cover
    """The particles of :func:`sample_particles` from their random draws, in one merge walk over rays and particles.

    Particle i sits at ``u_i = (e_1 + … + e_i) · Λ_tot / (e_1 + … + e_{n+1})`` (``spacing``: the n + 1 exponentials)
    on the concatenated per-ray intervals (``cum_ray``: their ends; :func:`_ray_measures`): ray k at range
    ``Λ⁻¹(u_i − start of ray k)`` (at most R_k); from the tables (rows of one; linear interpolation, clamped) its
    melted diameter ``D_m = max(Dmin, D_c(r)) + exp_d_i / Λ``, beam fraction ``min(1, (D / 2w(r))²)`` of its
    geometric diameter ``D = max(k D_m, c D_m^p)`` (``size_*``, :class:`dsd.SizeLaw`) and signal (units of K).
    Returns ray, range, diameter, beam fraction, signal, and the indices of the diameters above Dmax, which are left
    at their lower bound with the beam-filling return as signal for the caller to redraw."""
    n = len(exp_d)
    ray = np.empty(n, np.intp)
    r = np.empty(n)
    d = np.empty(n)
    f = np.empty(n)
    signal = np.empty(n)
    over = np.empty(n, np.intp)
    n_over = 0
    acc = 0.0
    for i in range(n):
        acc += spacing[i]
    scale = cum_ray[len(cum_ray) - 1] / (acc + spacing[n])
    per_m = 1.0 / step_m
    per_count = 1.0 / inv_step
    mean_d = 1.0 / lam_per_mm
    acc = 0.0
    start = 0.0
    k = 0
    for i in range(n):
        acc += spacing[i]
        u = acc * scale
        while cum_ray[k] <= u:
            start = cum_ray[k]
            k += 1
        ri = min(table_lerp(inv_range_m, 0, (u - start) * per_count), ray_range_m[k])
        x = (ri - r0_m) * per_m
        d_low = table_lerp(d_low_mm, 0, x)
        full = table_lerp(full_beam, 0, x)
        di = d_low + exp_d[i] * mean_d
        ray[i] = k
        r[i] = ri
        if di > d_max_mm:
            over[n_over] = i
            n_over += 1
            d[i] = d_low
            f[i] = 0.0
            signal[i] = full
        else:
            optical = max(size_k * di, size_c * di ** size_p)
            fi = min(1.0, (optical * 0.5e-3 / (w0_m + ri * half_divergence_rad)) ** 2)
            d[i] = di
            f[i] = fi
            signal[i] = full * fi
    return ray, r, d, f, signal, over[:n_over]


_scratch = threading.local()


def scratch_buffer(name: str, size: int, dtype=np.float64) -> np.ndarray:
    """A per-thread scratch buffer of ``size`` entries, reused across frames (fresh pages are expensive); for
    temporaries only."""
    buf = getattr(_scratch, name, None)
    if buf is None or len(buf) < size:
        buf = np.empty(max(size, size + size // 4), dtype)
        setattr(_scratch, name, buf)
    return buf[:size]


def sample_particles(rng: np.random.Generator, ray_range_m: np.ndarray, medium: ParticleMedium, beam: Beam,
                     threshold: float, visible_fraction: float = VISIBLE_FRACTION) -> Particles:
    """Particles in front of each ray's range (0 for none) whose return reaches ``visible_fraction × threshold``,
    vectorised over the frame.

    One Poisson draw gives the frame's total; sorted uniform order statistics (normalised exponential spacings) on
    the concatenated per-ray intervals give each particle its ray and, through ``Λ⁻¹``, its range — already sorted by
    ray and range (:func:`_place`). Diameters: ``max(Dmin, D_c(r))`` plus an exponential of rate Λ
    (memorylessness); the few above Dmax are redrawn by inverse CDF of the truncated exponential, which keeps the law
    exact."""
    table = visible_table(medium, beam, visible_fraction * threshold)
    ranges = np.ascontiguousarray(ray_range_m, dtype=np.float64)
    cum_ray = _ray_measures(ranges, table.start_m, table.step_m, table.cum[None, :])
    total = float(cum_ray[-1]) if len(cum_ray) else 0.0
    n = int(rng.poisson(total)) if total > 0 else 0
    if n == 0:
        empty = np.zeros(0)
        return Particles(np.zeros(0, dtype=np.intp), empty, empty, empty, empty)
    spacing = rng.standard_exponential(out=scratch_buffer("spacing", n + 1))     # inputs only: reused buffers
    exp_d = rng.standard_exponential(out=scratch_buffer("exp_d", n))
    ray, r, d, f, signal, over = _place(spacing, exp_d, cum_ray, ranges, table.inv_range_m[None, :], table.inv_step,
                                        table.start_m, table.step_m, table.d_low_mm[None, :],
                                        table.full_beam[None, :], medium.lam_per_mm, medium.d_max_mm, beam.radius_m,
                                        beam.divergence_rad / 2, medium.size.coefficient, medium.size.exponent,
                                        medium.size.solid)
    if len(over):                                     # rare: redraw from the truncated law (inverse CDF)
        d[over] = dsd.sample_truncated_exponential(rng, medium.lam_per_mm, d[over], medium.d_max_mm, len(over))
        f[over] = np.minimum(1.0, (medium.size.optical_mm(d[over]) * (0.5e-3 / beam.radius_at(r[over]))) ** 2)
        signal[over] *= f[over]
    return Particles(ray, r, d, f, signal)
