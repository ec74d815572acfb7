"""LiDAR snow (models.md §3.4 correct version; Hahner et al., "LiDAR Snowfall Simulation for Robust 3D Object
Detection", CVPR 2022)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...errors import ModelError
from ...model import Model, Stage, param
from ...physics import dsd, lidar_weather
from ...physics.lidar_particles import VISIBLE_FRACTION, ParticleMedium
from ...registry import register
from . import empty_rays_param

# Hahner 2022 rain ↔ snow conversion S = 487 ρ D0 v_t R^{2/3} (ρ in g/cm³, D0 in m, v_t in m/s), with the
# reference's flake density 0.178 g/cm³ (Brandes et al. 2007 at D0 = 1 mm) and fall speed 1.6 m/s.
HAHNER_FLAKE_DENSITY_G_PER_CM3 = 0.178
HAHNER_MEDIAN_DIAMETER_M = 1e-3
HAHNER_FALL_SPEED_M_PER_S = 1.6


def liquid_equivalent_rate_mm_per_h(rate_mm_per_h: float, convention: str,
                                    snow_density_g_per_cm3: float = 0.1) -> float:
    """The rate that drives the snow DSD.

    ``liquid_equivalent``: as given. ``snow_depth``: fresh-snow depth rate × ρ_snow/ρ_water.
    ``hahner``: Hahner's snowfall rate S → equivalent rate ``(S / (487 ρ D0 v_t))^{3/2}`` (models.md §3.4; the
    reference's exponent 3/4 is a transcription error)."""
    if convention == "liquid_equivalent":
        return rate_mm_per_h
    if convention == "snow_depth":
        return rate_mm_per_h * snow_density_g_per_cm3 / dsd.WATER_DENSITY_G_PER_CM3
    if convention == "hahner":
        k = 487.0 * HAHNER_FLAKE_DENSITY_G_PER_CM3 * HAHNER_MEDIAN_DIAMETER_M * HAHNER_FALL_SPEED_M_PER_S
        return (rate_mm_per_h / k) ** 1.5
    raise ValueError(f"unknown snowfall rate convention {convention!r}")


@register
@dataclass(frozen=True)
class SnowLidar(Model):
    """Snowfall on a LiDAR scan: discrete flakes on the shared LiDAR-equation core (models.md §3.1, §3.4).

    - Snowflakes, not melted drops (models.md §2.3 correction; :func:`dsd.snowfall`, the camera's distribution too):
      an exponential law in melted diameter D_m with Λ from the liquid-equivalent rate S (Gunn–Marshall or
      Sekhon–Srivastava), flakes of geometric diameter D from the ``snow_habit``'s density–size law (dry aggregates:
      Brandes et al. 2007, ρ = 0.178 D^−0.922 g/cm³), falling at the habit's v(D), and N0 such that the
      liquid-equivalent mass flux ``∫ (π/6) D_m³ v N dD_m`` equals S. Extinction ``(π/4) 2 ∫ D² N dD_m`` (Q_ext = 2,
      x ≥ 363 for every flake): 9.41e-3 m⁻¹ at 2.5 mm/h, meteorological visibility 318 m (dry aggregates; rimed
      709 m, wet 1.67 km — the spread Rasmussen et al. 1999 report); the melted-drop model gave 1.21e-3 m⁻¹
      (2.5 km). No peak-600 renormalisation (it made flake density independent of the rate).
    - Flakes per beam: Poisson ``n π w(r)²`` from the profile's overlap start R1 to the target (or the max range on
      rays without a return, ``empty_rays``: a full grid's no-return cells, a point list's empty firing-grid cells;
      they then get ADDED flake returns), drawn when their return
      reaches ``draw_fraction_of_threshold`` (½) of the threshold — for the strongest return each ray's brightest
      flake directly and those within a factor 2–4 of it, in front of a bright target only when one can outshine it
      (:mod:`lidar_strongest`); the others act through their means: α, beam cover, backscatter
      (:mod:`lidar_particles`); flake
      return ``K ρ_s f ξ(r) e^{−2αr}/r²`` with the profile's sensor constant K (ρ = 1 at 1 m) and overlap ξ,
      ρ_s = 0.9, ``f = min(1, (D/2w)²)``; target ``I e^{−2αR}(1 − Σ f)``.
    - Summed received profiles (pulses closer than ``c τ_H`` add; exact maximum instead of Hahner's 0.1 m grid),
      strongest or first return detected in the receiver's noise (:func:`lidar_weather.particle_returns`); a peak
      within 0.2 m of the target only changes its intensity (Hahner 2022).
    ``snowfall_rate_mm_per_h = 0`` is the identity.
    """

    id: ClassVar[str] = "snow.lidar"
    stage: ClassVar[Stage] = Stage.MEDIUM
    sensor: ClassVar[str] = "lidar"
    summary: ClassVar[str] = "snow: extinction, flake shadowing and summed flake returns (Hahner et al. 2022)"

    snowfall_rate_mm_per_h: float = param(2.5, unit="mm/h", ge=0,
                                          doc="snowfall rate (liquid equivalent unless rate_convention says"
                                              " otherwise); 0 = no snow")
    rate_convention: str = param("liquid_equivalent", choices=("liquid_equivalent", "snow_depth", "hahner"),
                                 doc="meaning of the rate: melted water, fresh-snow depth, or Hahner's snowfall rate"
                                     " (converted with the 3/2 law)")
    snow_density_g_per_cm3: float = param(0.1, unit="g/cm³", gt=0, le=1,
                                          doc="fresh-snow density for rate_convention snow_depth")
    snow_dsd: str = param("gunn_marshall", choices=tuple(dsd.SNOW_LAWS),
                          doc="exponential law of the melted diameters (its slope Λ; N0 follows from the mass flux)")
    snow_habit: str = param("dry_aggregates", choices=tuple(dsd.SNOW_HABITS),
                            doc="kind of flakes (density–size law and fall speed): dry_aggregates (Brandes 2007), "
                                "rimed, wet — heavier flakes are smaller and fall faster: less extinction")
    min_flake_diameter_mm: float = param(0.0, unit="mm", ge=0, doc="smallest flake (geometric diameter; 0: all)")
    max_flake_diameter_mm: float = param(20.0, unit="mm", gt=0, doc="largest flake (geometric diameter)")
    flake_reflectance: float = param(0.9, unit="1", ge=0, doc="flake reflectance ρ_s (Hahner 2022)")
    return_mode: str = param("strongest", choices=("strongest", "first"), doc="which echo the sensor reports")
    empty_rays: str = empty_rays_param()
    draw_fraction_of_threshold: float = param(
        VISIBLE_FRACTION, unit="1", gt=0, le=1,
        doc="flakes whose own return is below this fraction of the detection threshold are not drawn one by one (they"
            " act through their means: extinction α, beam cover and backscatter as a soft background): smaller is"
            " closer to the full Poisson model and slower")

    def validate(self) -> None:
        if self.min_flake_diameter_mm >= self.max_flake_diameter_mm:
            raise ModelError("must be below max_flake_diameter_mm", model=self.id, field="min_flake_diameter_mm")

    def medium(self) -> ParticleMedium | None:
        """The flake population (None when it does not snow)."""
        s = liquid_equivalent_rate_mm_per_h(self.snowfall_rate_mm_per_h, self.rate_convention,
                                            self.snow_density_g_per_cm3)
        if s == 0:
            return None
        snow = dsd.snowfall(s, self.snow_dsd, self.snow_habit, self.min_flake_diameter_mm, self.max_flake_diameter_mm)
        return ParticleMedium(snow.n0_per_m3_mm, snow.lam_per_mm, snow.d_min_mm, snow.d_max_mm, self.flake_reflectance,
                              snow.extinction_per_m(), snow.size)

    def apply(self, data, *, state, drawn, rng):
        return lidar_weather.precipitation(data, self.id, self.medium(), self.return_mode, rng,
                                           self.draw_fraction_of_threshold, self.empty_rays)
