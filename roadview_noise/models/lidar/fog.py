"""LiDAR fog (models.md §3.2 correct version; Hahner et al., "Fog Simulation on Real LiDAR Point Clouds for 3D Object
Detection in Adverse Weather", ICCV 2021)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from ...model import Model, Stage, param
from ...physics import lidar_weather
from ...physics.atmosphere import extinction_from_visibility_per_m
from ...physics.lidar_medium import HAHNER_FOG_PULSE_S
from ...registry import register
from . import empty_rays_param


def fog_coefficients(visibility_m: float, backscatter_times_visibility_per_sr: float = 0.046) -> tuple[float, float]:
    """Hahner 2021: extinction ``α = ln 20 / MOR`` (m⁻¹) and backscatter ``β = 0.046 / MOR`` (m⁻¹ sr⁻¹)."""
    return extinction_from_visibility_per_m(visibility_m), backscatter_times_visibility_per_sr / visibility_m


@register
@dataclass(frozen=True)
class FogLidar(Model):
    """Homogeneous fog on a LiDAR scan: Hahner et al. 2021 on the shared LiDAR-equation core (models.md §3.1–§3.2).

    - Hard target at R: ``S_hard = S e^{−2αR}``, α = ln 20 / MOR (S: received signal, :func:`lidar_rays.cloud_rays`).
    - Soft target (the fog in front of it), strongest point of its received profile
      ``S_fog(R) = K π β ∫_0^{2τ_H} sin²(πt/2τ_H) ξ(r_t) e^{−2α r_t} / r_t² (c dt/2)``, ``r_t = R − ct/2`` (fog only
      in front of the target), β = 0.046/MOR (m⁻¹ sr⁻¹, π β = the fog's equivalent Lambertian reflectance per metre):
      ``S_fog = K π β (c/2) G_max(R0)`` at the apparent range of the peak, with the cached pulse-integral table
      :func:`lidar_medium.soft_target_table` and the profile's sensor constant K — the same scale as rain and snow
      (``fog_scale='sensor_constant'``, default). Range and strength follow the receiver overlap ξ of the profile
      (``overlap_start_m`` R1, ``overlap_full_m`` R2; Hahner: 0.9 m, 1.0 m). With an OS1-128 (K = 65535 photons·m²,
      τ_H = 10 ns, ξ from 0.5 m to full at 5 m) at MOR 30 m the fog returns 32 photons at 1.4 m on every empty ray
      and replaces the targets weaker than that, so dense fog shows as near returns around the sensor, as in real
      data; the strength scales with β (6.2 photons at MOR 200 m, 1.3 at 1 km).
    - Detection in the receiver's noise (:mod:`receiver`, :func:`lidar_weather.detect`): the fog return is measured
      (SPAD photon counts for an Ouster), so fog returns spread in intensity and range (jitter ``(c/2) t_r / SNR``)
      and their number falls smoothly with visibility around the threshold instead of every sky ray switching off
      at once. Strongest mode: the larger detected value wins (the target keeps its recorded value × e^{−2αR});
      first mode: a detected fog return wins. A target below the threshold is removed.
    - ``fog_scale='hahner'`` reproduces Hahner's released simulation (LiDAR_fog_sim): per-point calibration
      ``K_i = I_i R_i² / β0``, β0 = γ/π, γ = 10⁻⁶, his overlap (0.9 → 1.0 m), no detection threshold, no empty rays,
      and his decision against the attenuated intensity as stored (:func:`lidar_weather.hahner_fog`). On the real
      OS1-128 scan at α = 0.1 m⁻¹ it moves 50.9 % of the points to the fog, as his code (54 818 of 107 647), and
      removes none; two thirds of them only because the attenuated 8-bit value rounds to 0.
    - Rays without a return get ``R0 = ∞`` (``empty_rays``: the no-return cells of a full range image, or of a point
      list's firing grid, :mod:`firing_grid`), so fog also appears where the clear scan saw nothing (the reference's
      zero-range branch was dead code).
    - Fixes vs the reference (§3.2, §7): input intensity unit and kind kept (no W/m² output, no 10 fs pulse), the
      overlap function replaces the [0.1 R, R] droplet hack, deterministic attenuation (no "n = 0 → clear" lottery).
    ``visibility_m = inf`` is the identity (every effect KEPT).
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
                               "and snow, detection in the receiver's noise) or Hahner 2021's released simulation "
                               "(per-point calibration K_i = I_i R_i²/β0, no threshold, returns only)")
    target_reflectivity: float = param(
        1e-6, unit="1", gt=0, doc="fog_scale hahner: γ of clear-weather points, β0 = γ/π (Hahner's calibration)")
    pulse_width: str = param("profile", choices=("profile", "hahner_20ns"),
                             doc="half-power pulse width: the sensor profile's, or Hahner's 20 ns")
    return_mode: str = param("strongest", choices=("strongest", "first"), doc="which echo the sensor reports")
    empty_rays: str = empty_rays_param()

    def apply(self, data, *, state, drawn, rng):
        if math.isinf(self.visibility_m):
            return lidar_weather.fog(data, self.id, alpha_per_m=0.0, beta_per_m_sr=0.0, tau_h_s=None,
                                     mode=self.return_mode, empty_rays=self.empty_rays, rng=rng)
        alpha, beta = fog_coefficients(self.visibility_m, self.backscatter_times_visibility_per_sr)
        tau_h = HAHNER_FOG_PULSE_S if self.pulse_width == "hahner_20ns" else None      # None: the profile's
        if self.fog_scale == "hahner":
            return lidar_weather.hahner_fog(data, self.id, alpha_per_m=alpha, beta_per_m_sr=beta, tau_h_s=tau_h,
                                            target_reflectivity=self.target_reflectivity)
        return lidar_weather.fog(data, self.id, alpha_per_m=alpha, beta_per_m_sr=beta, tau_h_s=tau_h,
                                 mode=self.return_mode, empty_rays=self.empty_rays, rng=rng)
