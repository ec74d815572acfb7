"""Discrete precipitation particles in LiDAR beams (models.md §3.3–§3.4 correct versions; Hahner et al., CVPR 2022).

Particles form a Poisson process along each beam with density ``n π w(r)²`` (n from the exponential DSD,
``w(r) = w0 + r θ/2`` the beam radius, θ the full divergence angle). A particle of diameter D at range r covers the
beam fraction ``f = min(1, (D / 2w(r))²)`` and returns ``K ρ f ξ(r) e^{−2αr} / r²`` (carried in units of the
sensor constant K, :func:`lidar_link.particle_signal`; ξ with the profile's overlap R1, R2, part of :class:`Beam`).

Only particles whose own return reaches a fraction of the detection threshold are drawn (``visible_fraction``,
default ``VISIBLE_FRACTION`` = ½, so that two overlapping ones can reach it). The drawn ones are an exact thinning of
the Poisson process — positions follow the cumulative visible density ``Λ(r) = ∫ π w² N(D ≥ D_c(r)) dr`` (a cached
table) and diameters the truncated exponential above the visibility diameter ``D_c(r)`` — so a frame costs a few
operations per *visible* particle instead of per particle (an empty 120 m ray at 20 mm/h holds ~10 drops of which ~0.2
are visible to an OS1-128). The fainter remainder acts only through the mean extinction α (its shadowing); its summed
backscatter is neglected — the model's one approximation, which lowers the number of weather returns slightly
(``bench/bench_lidar_weather.py`` prints the convergence as the fraction decreases). Placing the particles on their
rays is one compiled pass (:func:`_place`), as is the return selection (:func:`lidar_link.select_returns`).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from . import dsd, lidar_link
from .compiled import jit

VISIBLE_FRACTION = 0.5        # default: particles returning less than this fraction of the threshold are not drawn
TABLE_STEP_M = 0.01
TABLE_MAX_RANGE_M = 1000.0


@dataclass(frozen=True)
class ParticleMedium:
    """Exponential DSD ``N(D) = N0 e^{−ΛD}`` on [Dmin, Dmax] (m⁻³ mm⁻¹, mm⁻¹, mm), the particles' effective
    Lambertian reflectance ρ, and the medium's extinction α (m⁻¹)."""

    n0_per_m3_mm: float
    lam_per_mm: float
    d_min_mm: float
    d_max_mm: float
    reflectance: float
    alpha_per_m: float

    def count_above(self, d_mm: np.ndarray) -> np.ndarray:
        """Particles per m³ with diameter ≥ d (and within [Dmin, Dmax])."""
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
        return lidar_link.particle_signal(medium.reflectance, 1.0, r_m, medium.alpha_per_m, self.overlap_start_m,
                                          self.overlap_full_m)


def visibility_diameter_mm(medium: ParticleMedium, beam: Beam, level: float, r_m) -> np.ndarray:
    """Smallest diameter (mm) whose return at range r reaches ``level`` (units of K); inf where even a
    beam-filling particle stays below it (and below the overlap range R1)."""
    r = np.asarray(r_m, dtype=float)
    full_beam = beam.full_beam_signal(medium, r)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 2e3 * beam.radius_at(r) * np.sqrt(level / full_beam)
    return np.where(full_beam >= level, d, np.inf)


@dataclass(frozen=True, eq=False)
class VisibleTable:
    """Per-beam tables on the regular range grid ``r_k = R1 + k·step`` (``start_m`` = R1, the beam's overlap start;
    cached per medium, beam and level):
    cumulative visible count Λ(r_k), the lower diameter bound ``max(Dmin, D_c(r_k))`` (mm) and the beam-filling
    return ``ρ ξ e^{−2αr}/r²`` (units of K); plus ``Λ⁻¹`` on a regular grid of Λ (step ``inv_step``). Lookups
    (:func:`_expected_counts`, :func:`_place`) interpolate linearly, clamped to the tables."""

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


@dataclass(frozen=True, eq=False)
class Particles:
    """Drawn particles, sorted by ray then range: ray index, range (m), diameter (mm), beam fraction, signal."""

    ray: np.ndarray
    range_m: np.ndarray
    diameter_mm: np.ndarray
    beam_fraction: np.ndarray
    signal: np.ndarray


@jit
def _expected_counts(ray_range_m, r0_m, step_m, cum):      # pragma: no cover - compiled
    """Cumulative sum over the rays of their expected visible particles ``Λ(R_i)`` (the table ``cum`` on the grid
    ``r0 + k·step`` interpolated linearly; Λ = 0 up to R1 and constant beyond the table)."""
    n = len(ray_range_m)
    last = len(cum) - 1
    r_end = r0_m + last * step_m
    out = np.empty(n)
    total = 0.0
    for i in range(n):
        if ray_range_m[i] >= r_end:
            total += cum[last]
        else:
            x = min(max((ray_range_m[i] - r0_m) / step_m, 0.0), last - 0.000001)
            k = int(x)
            total += cum[k] + (cum[k + 1] - cum[k]) * (x - k)
        out[i] = total
    return out


@jit
def _place(spacing, exp_d, cum_ray, ray_range_m, inv_range_m, inv_step, r0_m, step_m, d_low_mm, full_beam,
           lam_per_mm, d_max_mm, w0_m, half_divergence_rad):      # pragma: no cover - compiled
    """The particles of :func:`sample_particles` from their random draws, in one merge walk over rays and particles.

    Particle i sits at ``u_i = (e_1 + … + e_i) · Λ_tot / (e_1 + … + e_{n+1})`` (``spacing``: the n + 1 exponentials)
    on the concatenated per-ray intervals ``[0, Λ(R_k))`` (``cum_ray``: their ends): ray k, range
    ``Λ⁻¹(u_i − start of ray k)`` (at most R_k); from the tables at that range (linear interpolation, clamped) its
    diameter ``max(Dmin, D_c(r)) + exp_d_i / Λ``, beam fraction ``min(1, (D / 2w(r))²)`` and signal (units of K).
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
    last_inv = len(inv_range_m) - 1
    last = len(d_low_mm) - 1
    per_count = 1.0 / inv_step
    per_m = 1.0 / step_m
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
        x = min((u - start) * per_count, last_inv - 0.000001)
        j = int(x)
        ri = min(inv_range_m[j] + (inv_range_m[j + 1] - inv_range_m[j]) * (x - j), ray_range_m[k])
        x = min(max((ri - r0_m) * per_m, 0.0), last - 0.000001)
        j = int(x)
        d_low = d_low_mm[j] + (d_low_mm[j + 1] - d_low_mm[j]) * (x - j)
        full = full_beam[j] + (full_beam[j + 1] - full_beam[j]) * (x - j)
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
            fi = min(1.0, (di * 0.5e-3 / (w0_m + ri * half_divergence_rad)) ** 2)
            d[i] = di
            f[i] = fi
            signal[i] = full * fi
    return ray, r, d, f, signal, over[:n_over]


_scratch = threading.local()


def _buffer(name: str, size: int) -> np.ndarray:
    """A per-thread float64 scratch buffer of ``size`` entries, reused across frames (fresh pages are expensive);
    for temporaries only."""
    buf = getattr(_scratch, name, None)
    if buf is None or len(buf) < size:
        buf = np.empty(max(size, size + size // 4))
        setattr(_scratch, name, buf)
    return buf[:size]


def sample_particles(rng: np.random.Generator, ray_range_m: np.ndarray, medium: ParticleMedium, beam: Beam,
                     threshold: float, visible_fraction: float = VISIBLE_FRACTION) -> Particles:
    """Particles in front of each ray's range (0 for none) whose return reaches ``visible_fraction × threshold``,
    vectorised over the frame.

    One Poisson draw gives the frame's total; sorted uniform order statistics (normalised exponential spacings) on
    the concatenated per-ray intervals ``[0, Λ(R_i))`` give each particle its ray and, through ``Λ⁻¹``, its range —
    already sorted by ray and range (:func:`_place`). Diameters: ``max(Dmin, D_c(r))`` plus an exponential of rate Λ
    (memorylessness); the few above Dmax are redrawn by inverse CDF of the truncated exponential, which keeps the law
    exact."""
    table = visible_table(medium, beam, visible_fraction * threshold)
    ranges = np.ascontiguousarray(ray_range_m, dtype=np.float64)
    cum_ray = _expected_counts(ranges, table.start_m, table.step_m, table.cum)
    total = float(cum_ray[-1]) if len(cum_ray) else 0.0
    n = int(rng.poisson(total)) if total > 0 else 0
    if n == 0:
        empty = np.zeros(0)
        return Particles(np.zeros(0, dtype=np.intp), empty, empty, empty, empty)
    spacing = rng.standard_exponential(out=_buffer("spacing", n + 1))     # inputs only: reused buffers
    exp_d = rng.standard_exponential(out=_buffer("exp_d", n))
    ray, r, d, f, signal, over = _place(spacing, exp_d, cum_ray, ranges, table.inv_range_m, table.inv_step,
                                        table.start_m, table.step_m, table.d_low_mm, table.full_beam,
                                        medium.lam_per_mm, medium.d_max_mm, beam.radius_m, beam.divergence_rad / 2)
    if len(over):                                     # rare: redraw from the truncated law (inverse CDF)
        d[over] = dsd.sample_truncated_exponential(rng, medium.lam_per_mm, d[over], medium.d_max_mm, len(over))
        f[over] = np.minimum(1.0, (d[over] * (0.5e-3 / beam.radius_at(r[over]))) ** 2)
        signal[over] *= f[over]
    return Particles(ray, r, d, f, signal)


def precipitation_returns(rng: np.random.Generator, rays: lidar_link.Rays, medium: ParticleMedium, tau_h_s: float,
                          mode: str, visible_fraction: float = VISIBLE_FRACTION) -> tuple[lidar_link.RayReturns, int]:
    """Rain/snow on every ray (models.md §3.3–§3.4 correct versions): visible particles in front of the target,
    target ``I e^{−2αR}(1 − Σ f)`` (shadowing by the drawn particles), summed pulse profiles, return selection.
    Returns the per-ray returns and the number of particles drawn."""
    profile = rays.profile
    beam = Beam.of(profile)
    particles = sample_particles(rng, rays.range_m, medium, beam, rays.threshold, visible_fraction)
    target = lidar_link.hard_target_signal(rays.signal, medium.alpha_per_m, rays.range_m)
    returns = lidar_link.select_returns(particles.ray, particles.range_m, particles.signal, rays.range_m, target,
                                        rays.has_target, tau_h_s, rays.threshold, mode, particles.beam_fraction)
    return returns, len(particles.ray)


def apply_precipitation(model_id: str, cloud, medium: ParticleMedium | None, mode: str, rng: np.random.Generator,
                        visible_fraction: float = VISIBLE_FRACTION) -> tuple[object, dict]:
    """Run rain or snow (``medium`` None: zero rate, identity) on a cloud; returns (cloud, diagnostics)."""
    rays = lidar_link.cloud_rays(cloud, model_id)
    if medium is None:
        out, counts = lidar_link.unchanged(cloud, rays)
        return out, {**counts, "alpha_per_m": 0.0, "particles_per_m3": 0.0, "particles_drawn": 0}
    returns, drawn = precipitation_returns(rng, rays, medium, rays.profile.pulse_half_power_width_s, mode,
                                           visible_fraction)
    out, counts = lidar_link.assemble(cloud, rays, returns)
    density = medium.count_above(np.float64(medium.d_min_mm))
    return out, {**counts, "alpha_per_m": float(medium.alpha_per_m), "particles_per_m3": float(density),
                 "particles_drawn": int(drawn)}
