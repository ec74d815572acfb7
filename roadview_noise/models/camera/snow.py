"""Camera snow: falling flakes as short streaks plus a far-field veil (models.md §2.3, §2.9)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...errors import ModelError
from ...model import param
from ...physics.dsd import BRANDES_SNOW_GAMMA, SNOW_HABITS
from ...physics.particles import SNOW_DSDS, snow_classes
from ...physics.photometry import airlight_radiance
from ...registry import register
from .rain import PrecipitationCamera


@register
@dataclass(frozen=True)
class SnowCamera(PrecipitationCamera):
    """Snow (models.md §2.3, wind §2.9): the rain renderer with a snow size distribution, a slow fall speed and
    Lambertian flakes.

    - Size distribution (liquid-equivalent rate S, flakes of 0.1–20 mm geometric diameter): the snowfall of the LiDAR
      model (:func:`dsd.snowfall`, models.md §2.3 correction) — Gunn & Marshall (1958, default) or Sekhon &
      Srivastava (1970) slope in *melted* diameter, flakes from the ``snow_habit``'s density–size law (dry
      aggregates: Brandes et al. 2007), N0 from the liquid-equivalent mass flux — or the Brandes et al. (2007)
      measured gamma fits, already in flake diameter (3.03, 2.70, 2.59 mm/h only). Using the melted diameter as the
      flake made the haze of 3.03 mm/h as thin as a 5.8 km visibility; the flakes give 0.54 km
      (dry aggregates; imaging extinction, Q = 1: the diffraction lobe stays in the pixel).
    - Fall speed of the habit, ``v = a D^b`` (dry aggregates 0.8 D^0.16 m/s, Locatelli & Hobbs 1974), replacing the
      reference's garbled constant 0.65 m/s.
    - Flake radiance ``S_c = ρ_s E_sky,c`` with ρ_s = 0.9 (Hahner et al. 2022) and ``E_sky`` the snow's overcast
      sky estimated from the frame (sky luminance, illuminant colour: white flakes lit by the scene's light, not
      tinted by a clear blue sky), instead of the reference's constant 255 (emissive-looking flakes at night).
    With wind, flakes drift with the air (short relaxation time), so their streaks tilt more than rain's —
    the physics; D3.5's opposite statement is discussed in models.md §2.9 (see wind.camera lateral_response)."""

    id: ClassVar[str] = "snow.camera"
    summary: ClassVar[str] = "snow: slow Lambertian flakes (Gunn–Marshall/Brandes), streaks and far-field veil"

    snowfall_rate_mm_per_h: float = param(3.03, unit="mm/h", gt=0, le=50,
                                          doc="liquid-equivalent snowfall rate (D3.5 camera: 3.03 mm/h)")
    snow_dsd: str = param("gunn_marshall", choices=SNOW_DSDS, doc="flake size distribution")
    snow_habit: str = param("dry_aggregates", choices=tuple(SNOW_HABITS),
                            doc="kind of flakes (density–size law and fall speed): dry_aggregates, rimed, wet")
    flake_reflectance: float = param(0.9, unit="1", gt=0, le=1, doc="ρ_s: flake radiance = ρ_s × sky radiance")

    def validate(self) -> None:
        super().validate()
        if self.snow_dsd == "brandes" and self.snowfall_rate_mm_per_h not in BRANDES_SNOW_GAMMA:
            raise ModelError(f"the Brandes measured distributions exist for {sorted(BRANDES_SNOW_GAMMA)} mm/h "
                             f"only, got {self.snowfall_rate_mm_per_h}; use gunn_marshall or sekhon_srivastava",
                             model=self.id, field="snowfall_rate_mm_per_h")

    def size_classes(self):
        return snow_classes(float(self.snowfall_rate_mm_per_h), self.snow_dsd, self.snow_habit)

    def fall_speed(self, d_mm):
        return SNOW_HABITS[self.snow_habit].fall_speed_m_per_s(d_mm)

    def radiance(self, layout, signal, depth_m, depth_valid):
        return self.flake_reflectance * airlight_radiance(layout, signal, depth_m, depth_valid)
