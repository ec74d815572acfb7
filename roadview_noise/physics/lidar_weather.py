"""The LiDAR weather pipeline shared by fog, rain and snow (models.md §3.1–§3.4), one stage per module:

    cloud → rays (:mod:`lidar_rays`) → medium (:mod:`lidar_medium`, :mod:`lidar_particles`)
          → received signal (:mod:`lidar_echo`) → detection (:mod:`lidar_detection`, :mod:`receiver`)
          → cloud (:mod:`lidar_output`)
"""

from __future__ import annotations

import math

import numpy as np

from ..types import PointCloud
from .compiled import jit
from .lidar_detection import detect
from .lidar_echo import NO_RETURN, TARGET, WEATHER, RayReturns, select_returns
from .lidar_intensity import reported_intensity, rounded_intensity, sensor_constant
from .lidar_medium import HAHNER_OVERLAP_M, hard_target_signal, pulse_length_m, soft_target_signal, soft_target_table
from .lidar_output import assemble, unchanged
from .lidar_particles import VISIBLE_FRACTION, Beam, ParticleMedium, draw_level, sample_particles
from .lidar_rays import Rays, cloud_rays
from .lidar_strongest import strongest_returns


def diagnostics(counts: dict, rays: Rays, **extra) -> dict:
    """The manifest's diagnostics of a weather step: the counts, how intensities and threshold were read, extras."""
    return {**counts, **rays.notes, **{k: float(v) if isinstance(v, (float, np.floating)) else v
                                       for k, v in extra.items()}}


# ---------------------------------------------------------------------------------------------------------------
# Fog


def fog(cloud: PointCloud, model_id: str, *, alpha_per_m: float, beta_per_m_sr: float, tau_h_s: float | None,
        mode: str, empty_rays: str, rng: np.random.Generator) -> tuple[PointCloud, dict]:
    """Homogeneous fog with the profile's sensor constant (``fog.lidar``): per ray the soft-target return
    ``K π β (c/2) G_max(R0)`` at the apparent range of its peak (:func:`lidar_medium.soft_target_table`) as the weather
    candidate, the target attenuated by ``e^{−2αR0}``; detection in the receiver's noise with one row of uniforms
    per ray (the same draws at every visibility), range jitter from the leading edge of the fog's profile. ``tau_h_s`` None: the profile's pulse; ``alpha_per_m = 0``: the
    identity."""
    rays = cloud_rays(cloud, model_id, "ignore" if alpha_per_m == 0 else empty_rays)
    if alpha_per_m == 0:
        out, counts = unchanged(cloud, rays)
        return out, diagnostics(counts, rays, alpha_per_m=0.0, beta_per_m_sr=0.0)
    p = rays.profile
    tau_h_s = tau_h_s or p.pulse_half_power_width_s
    table = soft_target_table(alpha_per_m, tau_h_s, p.overlap_start_m, p.overlap_full_m)
    g, fog_range = table.lookup(rays.range_m)
    fog_signal = soft_target_signal(g, beta_per_m_sr)
    hard = hard_target_signal(rays.decision_signal, alpha_per_m, rays.range_m)
    candidates = RayReturns(*_fog_candidates(fog_signal, fog_range, hard, rays.range_m, rays.has_target,
                                             rays.receiver.weakest_return), hard)
    returns = detect(rays, candidates, mode, rng.random((len(rays.range_m), 3)), per_ray=True, rise_m=table.rise_m)
    out, counts = assemble(cloud, rays, returns)
    return out, diagnostics(counts, rays, alpha_per_m=alpha_per_m, beta_per_m_sr=beta_per_m_sr,
                            pulse_half_power_width_s=tau_h_s)


@jit
def _fog_candidates(fog_signal, fog_range_m, hard, range_m, has_target, weakest):       # pragma: no cover - compiled
    """Per ray, in one pass: the fog's return as the candidate (WEATHER) where it can be detected (above ``weakest``,
    on a ray with a direction), else the attenuated target (TARGET) or nothing (NO_RETURN); (kind, range, signal)."""
    n = len(range_m)
    kind = np.empty(n, np.uint8)
    candidate_range_m = np.empty(n)
    signal = np.empty(n)
    for i in range(n):
        weather = fog_signal[i] > weakest and range_m[i] > 0
        kind[i] = WEATHER if weather else (TARGET if has_target[i] else NO_RETURN)
        candidate_range_m[i] = fog_range_m[i] if weather else range_m[i]
        signal[i] = fog_signal[i] if weather else hard[i]
    return kind, candidate_range_m, signal


def hahner_fog(cloud: PointCloud, model_id: str, *, alpha_per_m: float, beta_per_m_sr: float,
               tau_h_s: float | None, target_reflectivity: float) -> tuple[PointCloud, dict]:
    """Hahner et al. 2021's released fog simulation (LiDAR_fog_sim, ``fog_scale: hahner``) on the cloud's returns:
    per-point calibration — the fog return of point i is ``G_max(R0) · I_i R0² · β/β0``, β0 = γ/π, with I_i its
    stored value read as received signal (for a range-compensated file, at the target's range) — Hahner's overlap
    (R1 = 0.9 m, R2 = 1.0 m), no detection threshold and no empty rays. The point moves to the fog when that value
    exceeds its attenuated intensity rounded to the sensor's step (Hahner's ``np.round``), which is how most of
    Hahner's fog points arise on an 8-bit scan; no point is removed."""
    rays = cloud_rays(cloud, model_id, "ignore")
    p, r = rays.profile, rays.range_m
    tau_h_s = tau_h_s or p.pulse_half_power_width_s
    g, fog_range = soft_target_table(alpha_per_m, tau_h_s, *HAHNER_OVERLAP_M).lookup(r)
    fog_signal = g * rays.signal * (r * r) * (beta_per_m_sr / (target_reflectivity / math.pi))
    hard = hard_target_signal(rays.signal, alpha_per_m, r)
    k = sensor_constant(p)
    weather = rays.has_target & (reported_intensity(fog_signal * k, r, p)
                                 > rounded_intensity(reported_intensity(hard * k, r, p), p))
    kind = np.where(weather, WEATHER, np.where(rays.has_target, TARGET, NO_RETURN)).astype(np.uint8)
    returns = RayReturns(kind, np.where(weather, fog_range, r), np.where(weather, fog_signal, hard))
    out, counts = assemble(cloud, rays, returns)
    return out, diagnostics(counts, rays, empty_rays_source="none (fog_scale hahner: returns only, as Hahner's "
                                                            "simulation)", alpha_per_m=alpha_per_m,
                            beta_per_m_sr=beta_per_m_sr, pulse_half_power_width_s=tau_h_s)


# ---------------------------------------------------------------------------------------------------------------
# Rain and snow


def particle_returns(rng: np.random.Generator, rays: Rays, medium: ParticleMedium, mode: str,
                     visible_fraction: float = VISIBLE_FRACTION, exhaustive: bool = False) -> tuple[RayReturns, int]:
    """Rain/snow on every ray (models.md §3.3–§3.4 correct versions): particles in front of the target, target
    ``I e^{−2αR}(1 − Σ f)``, summed pulse profiles (:func:`lidar_echo.select_returns`), detection (:func:`detect`).

    Particles returning less than the base level ``ℓ`` (:func:`lidar_particles.draw_level`, a fraction of the
    threshold) act through their means (extinction α, backscatter as a soft target). The strongest return draws per
    ray its brightest particle and those that can change its return, and replaces the fainter ones by their means
    too (:mod:`lidar_strongest`); the first return (or ``exhaustive``: the reference the strongest return is tested
    against) draws every particle above ``ℓ`` (:func:`lidar_particles.sample_particles`). Candidates weaker than the
    receiver can detect are not returned. Returns the per-ray returns and the number of particles drawn."""
    profile = rays.profile
    tau_h = profile.pulse_half_power_width_s
    beam = Beam.of(profile)
    level, background = draw_level(medium, beam, rays.threshold, visible_fraction, pulse_length_m(tau_h))
    if mode == "strongest" and not exhaustive:
        return strongest_returns(rng, rays, medium, beam, level)
    particles = sample_particles(rng, rays.range_m, medium, beam, level, 1.0)
    weakest = rays.receiver.weakest_return if mode == "strongest" else rays.threshold
    candidates = select_returns(particles.ray, particles.range_m, particles.signal, rays.range_m,
                                hard_target_signal(rays.decision_signal, medium.alpha_per_m, rays.range_m),
                                rays.has_target, tau_h, weakest, mode, particles.beam_fraction, background)
    n_weather = int(np.count_nonzero(candidates.kind == WEATHER))
    return detect(rays, candidates, mode, rng.random((n_weather, 3)), per_ray=False), len(particles.ray)


def precipitation(cloud: PointCloud, model_id: str, medium: ParticleMedium | None, mode: str,
                  rng: np.random.Generator, visible_fraction: float = VISIBLE_FRACTION,
                  empty_rays: str = "fill", exhaustive: bool = False) -> tuple[PointCloud, dict]:
    """Run rain or snow (``medium`` None: zero rate, identity) on a cloud; returns (cloud, diagnostics)."""
    rays = cloud_rays(cloud, model_id, "ignore" if medium is None else empty_rays)
    if medium is None:
        out, counts = unchanged(cloud, rays)
        return out, diagnostics(counts, rays, alpha_per_m=0.0, particles_per_m3=0.0, particles_drawn=0)
    returns, drawn = particle_returns(rng, rays, medium, mode, visible_fraction, exhaustive)
    out, counts = assemble(cloud, rays, returns)
    return out, diagnostics(counts, rays, alpha_per_m=medium.alpha_per_m,
                            particles_per_m3=medium.count_above(np.float64(medium.d_min_mm)),
                            particles_drawn=int(drawn))
