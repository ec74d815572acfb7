"""Camera snow: falling flakes as short streaks plus a far-field veil (models.md §2.3, §2.9)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...errors import ModelError
from ...model import param
from ...physics.dsd import BRANDES_SNOW_GAMMA
from ...physics.fall_speed import snow_power_law_m_per_s
from ...physics.particles import SNOW_DSDS, snow_classes
from ...physics.photometry import sky_radiance
from ...registry import register
from .rain import PrecipitationCamera


@register
@dataclass(frozen=True)
class SnowCamera(PrecipitationCamera):
    """Snow (models.md §2.3, wind §2.9): the rain renderer with a snow size distribution, a slow fall speed and
    Lambertian flakes.

    - Size distribution (liquid-equivalent rate S, flakes 0.1–10 mm): Gunn & Marshall (1958) by default,
      Sekhon & Srivastava (1970), or the Brandes et al. (2007) measured gamma fits (3.03, 2.70, 2.59 mm/h only).
      As in models.md §2.3/§3.4 the distributions' D is used as the flake diameter.
    - Fall speed ``v = a D^b`` (D in mm; default 0.8 m/s, 0.16: unrimed aggregates, models.md §2.3 [PROP]),
      replacing the reference's garbled constant 0.65 m/s.
    - Flake radiance ``S_c = ρ_s E_sky,c`` with ρ_s = 0.9 (Hahner et al. 2022) and the sky radiance estimated
      from the frame, instead of the reference's constant 255 (emissive-looking flakes at night).
    With wind, flakes drift with the air (short relaxation time), so their streaks tilt more than rain's —
    the physics; D3.5's opposite statement is discussed in models.md §2.9 (see wind.camera lateral_response)."""

    id: ClassVar[str] = "snow.camera"
    summary: ClassVar[str] = "snow: slow Lambertian flakes (Gunn–Marshall/Brandes), streaks and far-field veil"

    snowfall_rate_mm_per_h: float = param(3.03, unit="mm/h", gt=0, le=50,
                                          doc="liquid-equivalent snowfall rate (D3.5 camera: 3.03 mm/h)")
    snow_dsd: str = param("gunn_marshall", choices=SNOW_DSDS, doc="flake size distribution")
    fall_speed_coefficient_m_per_s: float = param(0.8, unit="m/s", gt=0, doc="a in v = a·D[mm]^b")
    fall_speed_exponent: float = param(0.16, unit="1", ge=0, le=1, doc="b in v = a·D[mm]^b")
    flake_reflectance: float = param(0.9, unit="1", gt=0, le=1, doc="ρ_s: flake radiance = ρ_s × sky radiance")

    def validate(self) -> None:
        super().validate()
        if self.snow_dsd == "brandes" and self.snowfall_rate_mm_per_h not in BRANDES_SNOW_GAMMA:
            raise ModelError(f"the Brandes measured distributions exist for {sorted(BRANDES_SNOW_GAMMA)} mm/h "
                             f"only, got {self.snowfall_rate_mm_per_h}; use gunn_marshall or sekhon_srivastava",
                             model=self.id, field="snowfall_rate_mm_per_h")

    def size_classes(self):
        return snow_classes(float(self.snowfall_rate_mm_per_h), self.snow_dsd)

    def fall_speed(self, d_mm):
        return snow_power_law_m_per_s(d_mm, self.fall_speed_coefficient_m_per_s, self.fall_speed_exponent)

    def radiance(self, layout, signal, depth_m):
        return self.flake_reflectance * sky_radiance(layout, signal, depth_m)
