"""LiDAR fog (models.md §3.2 correct version; Hahner et al., "Fog Simulation on Real LiDAR Point Clouds for 3D Object
Detection in Adverse Weather", ICCV 2021)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ...model import Model, Stage, param
from ...physics import lidar_link
from ...physics.atmosphere import extinction_from_visibility_per_m
from ...registry import register
from . import empty_rays_param


def fog_coefficients(visibility_m: float, backscatter_times_visibility_per_sr: float = 0.046) -> tuple[float, float]:
    """Hahner 2021: extinction ``α = ln 20 / MOR`` (m⁻¹) and backscatter ``β = 0.046 / MOR`` (m⁻¹ sr⁻¹)."""
    return extinction_from_visibility_per_m(visibility_m), backscatter_times_visibility_per_sr / visibility_m


@register
@dataclass(frozen=True)
class FogLidar(Model):
    """Homogeneous fog on a LiDAR scan: Hahner et al. 2021 on the shared LiDAR-equation core (models.md §3.1–§3.2).

    - Hard target at R: ``S_hard = S e^{−2αR}``, α = ln 20 / MOR (S: received signal, :func:`lidar_link.cloud_rays`).
    - Soft target (the fog in front of it), strongest point of its received profile
      ``S_fog(R) = K π β ∫_0^{2τ_H} sin²(πt/2τ_H) ξ(r_t) e^{−2α r_t} / r_t² (c dt/2)``, ``r_t = R − ct/2`` (fog only
      in front of the target), β = 0.046/MOR (m⁻¹ sr⁻¹, π β = the fog's equivalent Lambertian reflectance per metre):
      ``S_fog = K π β (c/2) G_max(R0)`` at the apparent range of the peak, with the cached pulse-integral table
      :func:`lidar_link.soft_target_table` and the profile's sensor constant K — the same scale as rain and snow
      (``fog_scale='sensor_constant'``, default). Range and strength follow the receiver overlap ξ of the profile
      (``overlap_start_m`` R1, ``overlap_full_m`` R2; Hahner: 0.9 m, 1.0 m). With an OS1-128 (K = 65535 photons·m²,
      τ_H = 10 ns, ξ from 0.5 m to full at 5 m) at MOR 30 m the fog returns 32 photons at 1.4 m on every empty ray
      and replaces the targets weaker than that, so dense fog shows as near returns around the sensor, as in real
      data; the strength scales with β (6.2 photons at MOR 200 m, 1.3 at 1 km: below the 3.28-photon threshold).
      With Hahner's overlap the same sensor would see 131 photons at MOR 30 m and fog on every sky ray up to MOR
      1.6 km.
      ``fog_scale='hahner'`` keeps Hahner's per-point calibration ``K_i = S_i R_i² / β0``, β0 = γ/π, γ = 10⁻⁶ (every
      clear point treated as one effective reflector, G in seconds; ~150/ρ times weaker than the sensor-constant form,
      so it rarely produces fog returns); its empty rays use the frame median of ``S R²``.
    - strongest mode: the point moves to the fog if ``S_fog > S_hard``; first mode: if ``S_fog`` is above threshold.
      Whatever wins must pass the profile's detection threshold (signal units), else the point is removed.
    - Rays without a return get ``R0 = ∞`` (``empty_rays``: the no-return cells of a full range image, or of a point
      list's firing grid, :mod:`firing_grid`), so fog also appears where the clear scan saw nothing (the reference's
      zero-range branch was dead code).
    - Fixes vs the reference (§3.2, §7): input intensity unit and kind kept (no W/m² output, no 10 fs pulse), the
      overlap function replaces the [0.1 R, R] droplet hack, deterministic attenuation (no "n = 0 → clear" lottery).
    ``visibility_m = inf`` is the identity (every label KEPT).
    """

    id: ClassVar[str] = "fog.lidar"
    stage: ClassVar[Stage] = Stage.MEDIUM
    sensor: ClassVar[str] = "lidar"
    summary: ClassVar[str] = "fog: two-way extinction and soft-target fog returns (Hahner et al. 2021)"

    visibility_m: float = param(30.0, unit="m", gt=0, doc="meteorological optical range (MOR); inf = no fog")
    backscatter_times_visibility_per_sr: float = param(
        0.046, unit="sr⁻¹", ge=0, doc="β·MOR: fog backscatter β = value / MOR (Hahner: 0.046, admissible 0.023–0.092)")
    fog_scale: str = param("sensor_constant", choices=("sensor_constant", "hahner"),
                           doc="strength of the fog return: the profile's sensor constant K (LiDAR equation, as rain "
                               "and snow) or Hahner 2021's per-point calibration K_i = S_i R_i²/β0")
    target_reflectivity: float = param(
        1e-6, unit="1", gt=0, doc="fog_scale hahner: γ of clear-weather points, β0 = γ/π (Hahner's calibration)")
    pulse_width: str = param("profile", choices=("profile", "hahner_20ns"),
                             doc="half-power pulse width: the sensor profile's, or Hahner's 20 ns")
    return_mode: str = param("strongest", choices=("strongest", "first"), doc="which echo the sensor reports")
    empty_rays: str = empty_rays_param()

    def apply(self, data, *, state, drawn, rng):
        rays = lidar_link.cloud_rays(data, self.id, "ignore" if math.isinf(self.visibility_m) else self.empty_rays)
        if math.isinf(self.visibility_m):
            out, counts = lidar_link.unchanged(data, rays)
            return out, {**counts, "alpha_per_m": 0.0, "beta_per_m_sr": 0.0}
        alpha, beta = fog_coefficients(self.visibility_m, self.backscatter_times_visibility_per_sr)
        tau_h = (lidar_link.HAHNER_FOG_PULSE_S if self.pulse_width == "hahner_20ns"
                 else rays.profile.pulse_half_power_width_s)
        table = lidar_link.soft_target_table(alpha, tau_h, rays.profile.overlap_start_m,
                                             rays.profile.overlap_full_m)
        r = rays.range_m
        g, fog_range = table.lookup(r)
        if self.fog_scale == "sensor_constant":
            fog = lidar_link.soft_target_signal(g, beta)
        else:
            gain = beta / (self.target_reflectivity / math.pi)
            fog = g * rays.signal * (r * r) * gain
            empty = rays.empty
            if empty.any() and rays.has_target.any():
                t = rays.has_target
                fog[empty] = table.saturated[0] * float(np.median(rays.signal[t] * r[t] ** 2)) * gain
        hard = lidar_link.hard_target_signal(rays.signal, alpha, r)
        returns = lidar_link.pick(hard, r, fog, fog_range, rays.threshold, self.return_mode)
        out, counts = lidar_link.assemble(data, rays, returns)
        return out, {**counts, "alpha_per_m": float(alpha), "beta_per_m_sr": float(beta),
                     "pulse_half_power_width_s": float(tau_h)}
