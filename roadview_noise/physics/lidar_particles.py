"""Discrete precipitation particles in LiDAR beams (models.md §3.3–§3.4 correct versions; Hahner et al., CVPR 2022).

Particles form a Poisson process along each beam with density ``n π w(r)²`` (n from the exponential DSD,
``w(r) = w0 + r θ/2`` the beam radius, θ the full divergence angle). A particle of diameter D at range r covers the
beam fraction ``f = min(1, (D / 2w(r))²)`` and returns ``ρ f ξ(r) e^{−2αr} / r²`` full-scale units
(:func:`lidar_link.particle_signal`).

Only particles that can matter for detection are drawn: those whose return reaches half the detection threshold
(``VISIBLE_FRACTION``). This is an exact thinning of the Poisson process — positions follow the cumulative visible
density ``Λ(r) = ∫ π w² N(D ≥ D_c(r)) dr`` (a cached table) and diameters the truncated exponential above the
visibility diameter ``D_c(r)`` — so a frame costs a few operations per *visible* particle instead of per particle
(an empty 120 m ray at 20 mm/h holds ~10 drops of which ~0.2 are visible to an OS1-128). The statistical effect of
the invisible remainder (their shadowing) is carried by the mean extinction α.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from . import lidar_link

VISIBLE_FRACTION = 0.5        # particles returning less than this fraction of the threshold are not drawn
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
    """Beam radius ``w(r) = w0 + r θ/2`` (m), θ the full divergence angle (rad)."""

    radius_m: float
    divergence_rad: float = 0.0

    def radius_at(self, r_m):
        return self.radius_m + np.asarray(r_m) * (self.divergence_rad / 2)


def visibility_diameter_mm(medium: ParticleMedium, beam: Beam, level: float, r_m) -> np.ndarray:
    """Smallest diameter (mm) whose return at range r reaches ``level`` (full-scale units); inf where even a
    beam-filling particle stays below it (and below the overlap range R1)."""
    r = np.asarray(r_m, dtype=float)
    full_beam = lidar_link.particle_signal(medium.reflectance, 1.0, r, medium.alpha_per_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 2e3 * beam.radius_at(r) * np.sqrt(level / full_beam)
    return np.where(full_beam >= level, d, np.inf)


@dataclass(frozen=True, eq=False)
class VisibleTable:
    """Per-beam tables on the regular range grid ``r_k = R1 + k·step`` (cached per medium, beam and level):
    cumulative visible count Λ(r_k), the lower diameter bound ``max(Dmin, D_c(r_k))`` (mm) and the beam-filling
    return ``ρ ξ e^{−2αr}/r²``; plus ``Λ⁻¹`` on a regular grid of Λ. Lookups interpolate linearly."""

    step_m: float
    cum: np.ndarray
    d_low_mm: np.ndarray
    full_beam: np.ndarray
    inv_step: float
    inv_range_m: np.ndarray

    def position(self, r_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid cell and fraction of each range (clamped to the table)."""
        x = np.clip((r_m - lidar_link.OVERLAP_R1_M) * (1.0 / self.step_m), 0.0, len(self.cum) - 1.000001)
        k = x.astype(np.intp)
        return k, x - k

    @staticmethod
    def lerp(table: np.ndarray, k: np.ndarray, frac: np.ndarray) -> np.ndarray:
        lo = table[k]
        return lo + (table[k + 1] - lo) * frac

    def inverse(self, count: np.ndarray) -> np.ndarray:
        """Range r with Λ(r) = count."""
        x = np.minimum(count * (1.0 / self.inv_step), len(self.inv_range_m) - 1.000001)
        k = x.astype(np.intp)
        return self.lerp(self.inv_range_m, k, x - k)


@lru_cache(maxsize=16)
def visible_table(medium: ParticleMedium, beam: Beam, level: float) -> VisibleTable:
    """Expected visible particles ``Λ(r) = ∫_{R1}^{r} π w² N(D ≥ D_c) dr`` (trapezoid, 0.01 m) up to the range where
    no particle reaches ``level`` any more (at most 1000 m), with its inverse on 4× as many points."""
    r_end = min(TABLE_MAX_RANGE_M, math.sqrt(medium.reflectance / level) + 1.0)   # bound with ξ = f = 1, α = 0
    r = np.arange(lidar_link.OVERLAP_R1_M, r_end + TABLE_STEP_M, TABLE_STEP_M)
    d_c = visibility_diameter_mm(medium, beam, level, r)
    density = np.pi * beam.radius_at(r) ** 2 * medium.count_above(d_c)
    last = int(np.flatnonzero(density > 0)[-1]) + 2 if np.any(density > 0) else 2
    r, density, d_c = r[:last], density[:last], d_c[:last]
    cum = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * TABLE_STEP_M)])
    d_low = np.clip(d_c, medium.d_min_mm, medium.d_max_mm)
    full_beam = lidar_link.particle_signal(medium.reflectance, 1.0, r, medium.alpha_per_m)
    grid = np.linspace(0.0, cum[-1], 4 * len(cum))
    inverse = np.interp(grid, cum, r) if cum[-1] > 0 else np.full(len(grid), r[0])
    return VisibleTable(TABLE_STEP_M, cum, d_low, full_beam, grid[1] - grid[0] if cum[-1] > 0 else 1.0, inverse)


@dataclass(frozen=True, eq=False)
class Particles:
    """Drawn particles, sorted by ray then range: ray index, range (m), diameter (mm), beam fraction, signal."""

    ray: np.ndarray
    range_m: np.ndarray
    diameter_mm: np.ndarray
    beam_fraction: np.ndarray
    signal: np.ndarray

    def shadow(self, n_rays: int) -> np.ndarray:
        """Per ray, the beam fraction occluded by its particles ``min(1, Σ f)``."""
        return np.minimum(1.0, np.bincount(self.ray, weights=self.beam_fraction, minlength=n_rays))


def _interval_of(edges: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``searchsorted(edges, u, 'right')`` for sorted ``u``, as one linear merge (stable sort of two sorted runs)."""
    order = np.argsort(np.concatenate([u, edges]), kind="stable")
    return np.flatnonzero(order < len(u)) - np.arange(len(u))


def sample_particles(rng: np.random.Generator, ray_range_m: np.ndarray, medium: ParticleMedium, beam: Beam,
                     threshold: float) -> Particles:
    """Visible particles in front of each ray's range (0 for none), vectorised over the frame.

    One Poisson draw gives the frame's total; sorted uniform order statistics (normalised exponential spacings) on
    the concatenated per-ray intervals ``[0, Λ(R_i))`` give each particle its ray and, through ``Λ⁻¹``, its range —
    already sorted by ray and range. Diameters: ``max(Dmin, D_c(r))`` plus an exponential of rate Λ (memorylessness);
    the few above Dmax are redrawn by inverse CDF of the truncated exponential, which keeps the law exact."""
    table = visible_table(medium, beam, VISIBLE_FRACTION * threshold)
    r_end = lidar_link.OVERLAP_R1_M + (len(table.cum) - 1) * table.step_m
    lam_ray = np.full(len(ray_range_m), table.cum[-1])       # Λ is constant beyond the table, 0 up to R1
    short = np.flatnonzero(ray_range_m < r_end)
    k, frac = table.position(ray_range_m[short])
    lam_ray[short] = table.lerp(table.cum, k, frac)
    cum_ray = np.cumsum(lam_ray)
    total = float(cum_ray[-1]) if len(cum_ray) else 0.0
    n = int(rng.poisson(total)) if total > 0 else 0
    if n == 0:
        empty = np.zeros(0)
        return Particles(np.zeros(0, dtype=np.intp), empty, empty, empty, empty)
    spacing = rng.standard_exponential(n + 1)
    u = np.cumsum(spacing[:n])
    u *= total / (u[-1] + spacing[n])
    ray = _interval_of(cum_ray, u)
    r = np.minimum(table.inverse(u - (cum_ray[ray] - lam_ray[ray])), ray_range_m[ray])
    k, frac = table.position(r)
    d_low = table.lerp(table.d_low_mm, k, frac)
    d = d_low + rng.standard_exponential(n) / medium.lam_per_mm
    over = np.flatnonzero(d > medium.d_max_mm)           # rare: redraw those from the truncated law (inverse CDF)
    span = -np.expm1(-medium.lam_per_mm * (medium.d_max_mm - d_low[over]))
    d[over] = d_low[over] - np.log1p(-rng.random(len(over)) * span) / medium.lam_per_mm
    f = d * (0.5e-3 / beam.radius_at(r))
    f *= f
    np.minimum(f, 1.0, out=f)
    return Particles(ray, r, d, f, table.lerp(table.full_beam, k, frac) * f)


def precipitation_returns(rng: np.random.Generator, rays: lidar_link.Rays, medium: ParticleMedium, tau_h_s: float,
                          mode: str) -> tuple[lidar_link.RayReturns, int]:
    """Rain/snow on every ray (models.md §3.3–§3.4 correct versions): visible particles in front of the target,
    target ``I e^{−2αR}(1 − Σ f)`` (shadowing by the drawn particles), summed pulse profiles, return selection.
    Returns the per-ray returns and the number of particles drawn."""
    profile = rays.profile
    beam = Beam(profile.beam_radius_m, profile.beam_divergence_rad)
    particles = sample_particles(rng, rays.range_m, medium, beam, rays.threshold)
    target = lidar_link.hard_target_signal(rays.signal, medium.alpha_per_m, rays.range_m)
    if len(particles.ray):
        target = target * (1.0 - particles.shadow(len(rays.range_m)))
    returns = lidar_link.select_returns(particles.ray, particles.range_m, particles.signal, rays.range_m, target,
                                        rays.has_target, tau_h_s, rays.threshold, mode)
    return returns, len(particles.ray)


def apply_precipitation(model_id: str, cloud, medium: ParticleMedium | None, mode: str,
                        rng: np.random.Generator) -> tuple[object, dict]:
    """Run rain or snow (``medium`` None: zero rate, identity) on a cloud; returns (cloud, diagnostics)."""
    rays = lidar_link.cloud_rays(cloud, model_id)
    if medium is None:
        out, counts = lidar_link.unchanged(cloud, rays)
        return out, {**counts, "alpha_per_m": 0.0, "particles_per_m3": 0.0, "particles_drawn": 0}
    returns, drawn = precipitation_returns(rng, rays, medium, rays.profile.pulse_half_power_width_s, mode)
    out, counts = lidar_link.assemble(cloud, rays, returns)
    density = medium.count_above(np.float64(medium.d_min_mm))
    return out, {**counts, "alpha_per_m": float(medium.alpha_per_m), "particles_per_m3": float(density),
                 "particles_drawn": int(drawn)}
