"""LiDAR rain (models.md §3.3 correct version; particle model after Hahner et al., "LiDAR Snowfall Simulation for
Robust 3D Object Detection", CVPR 2022)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...errors import ModelError
from ...model import Model, Stage, param
from ...physics import dsd, lidar_weather
from ...physics.lidar_particles import ParticleMedium
from ...registry import register
from . import empty_rays_param

# Drops are faint (Fresnel ρ = 0.02) and many fit in a wide beam; the undrawn ones act through their mean backscatter,
# but a drop below the threshold is also detected now and then in the receiver's noise, which a mean cannot carry.
# Weather returns at ½, ¼, 1/16, 1/64 of the threshold: 760 / 975 / 1130 / 1149 at 50 mm/h on 60 k synthetic rays
# (datasheet threshold, tests/models/test_lidar_weather.py), 8 560 / 9 208 / 9 379 / 9 300 at 20 mm/h on the real
# OS1-128 scan (its calibrated threshold; bench/bench_lidar_weather.py): 1/16 is converged in both.
RAIN_DRAW_FRACTION = 1 / 16


@register
@dataclass(frozen=True)
class RainLidar(Model):
    """Rain on a LiDAR scan: discrete drops on the shared LiDAR-equation core (models.md §3.1, §3.3).

    - Marshall–Palmer DSD on [Dmin, Dmax]; extinction ``α = (π/4)·2·∫D²N dD`` (geometric optics, Q_ext = 2; x > 1800
      for every drop at 865 nm) — 2.171e-3 m⁻¹ at 20 mm/h, not the reference's 1.085 m⁻¹ (500× too large).
    - Drops per beam: Poisson with density ``n π w(r)²`` (w grows with the profile's beam divergence) from the
      profile's overlap start R1 to the target, or to the profile's max range on rays without a return
      (``empty_rays``: a full grid's no-return cells, a point list's empty firing-grid cells; their weather returns
      are ADDED); diameters by inverse CDF of the
      truncated exponential (the reference set the *mean* to Λ). Only drops whose return reaches
      ``draw_fraction_of_threshold`` (1/16) of the threshold are drawn (an exact thinning); for the strongest
      return each ray draws its brightest drop directly and those within a factor 2–4 of it, in front of a bright
      target only when one can outshine it (:mod:`lidar_strongest`); the others act through their means (α, beam
      cover, backscatter as a soft background; :mod:`lidar_particles`).
    - Drop return ``K ρ f ξ(r) e^{−2αr}/r²`` with the profile's sensor constant K (ρ = 1 at 1 m) and overlap ξ,
      ρ = Fresnel 0.0199, ``f = min(1, (D/2w)²)``; target ``I e^{−2αR}(1 − Σ f)``; pulses closer than ``c τ_H``
      add; strongest or first return detected in the receiver's noise (:func:`lidar_weather.particle_returns`).
    ``rain_rate_mm_per_h = 0`` is the identity.
    """

    id: ClassVar[str] = "rain.lidar"
    stage: ClassVar[Stage] = Stage.MEDIUM
    sensor: ClassVar[str] = "lidar"
    summary: ClassVar[str] = "rain: extinction, drop shadowing and drop returns (Marshall–Palmer, Hahner et al. 2022)"

    rain_rate_mm_per_h: float = param(20.0, unit="mm/h", ge=0, doc="rain rate; 0 = no rain")
    min_drop_diameter_mm: float = param(0.5, unit="mm", gt=0, doc="smallest drop of the DSD")
    max_drop_diameter_mm: float = param(6.0, unit="mm", gt=0, doc="largest drop of the DSD")
    drop_reflectance: float = param(
        0.0199, unit="1", ge=0, doc="effective Lambertian reflectance of a drop: Fresnel |(m−1)/(m+1)|² of water at "
        "865 nm (reference); the Mie value Q_back/4 (≈1.5 averaged, strong glory) is an upper alternative")
    return_mode: str = param("strongest", choices=("strongest", "first"), doc="which echo the sensor reports")
    empty_rays: str = empty_rays_param()
    draw_fraction_of_threshold: float = param(
        RAIN_DRAW_FRACTION, unit="1", gt=0, le=1,
        doc="drops whose own return is below this fraction of the detection threshold are not drawn one by one (they"
            " act through their means: extinction α, beam cover and backscatter as a soft background): smaller is"
            " closer to the full Poisson model and slower")

    def validate(self) -> None:
        if self.min_drop_diameter_mm >= self.max_drop_diameter_mm:
            raise ModelError("must be below max_drop_diameter_mm", model=self.id, field="min_drop_diameter_mm")

    def medium(self) -> ParticleMedium | None:
        """The drop population (None when it does not rain)."""
        if self.rain_rate_mm_per_h == 0:
            return None
        n0, lam = dsd.marshall_palmer(self.rain_rate_mm_per_h)
        lo, hi = self.min_drop_diameter_mm, self.max_drop_diameter_mm
        return ParticleMedium(n0, lam, lo, hi, self.drop_reflectance, dsd.geometric_extinction_per_m(n0, lam, lo, hi))

    def apply(self, data, *, state, drawn, rng):
        return lidar_weather.precipitation(data, self.id, self.medium(), self.return_mode, rng,
                                           self.draw_fraction_of_threshold, self.empty_rays)
