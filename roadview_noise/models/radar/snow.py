"""Radar snow: ROADVIEW linear attenuation law, detection loss and snow clutter (models.md §4.1, §4.3;
CNF27 radar variant)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...model import param
from ...physics.dsd import SNOW_LAWS
from ...physics.radar_clutter import Hydrometeors, snow_flakes
from ...physics.radar_link import snow_attenuation_db_per_km
from ...registry import register
from ...types import RadarProfile
from .weather import MIN_PRECIPITATION_RATE_MM_PER_H, PrecipitationRadar


@register
@dataclass(frozen=True)
class SnowRadar(PrecipitationRadar):
    """Dry snow on a 4D radar point cloud (models.md §4.1, §4.3).

    γ = 0.8205 S dB/km (ROADVIEW, after Norouzian et al. 2018; 2.5 mm/h → 2.051 dB/km). Flagged: the law was
    measured above 100 GHz and is extrapolated to the radar frequency (likely an overestimate at 77 GHz); no ITU-R
    recommendation covers dry snow. Clutter: exponential snow DSD as solid ice spheres of the (melted) DSD diameter
    (ε = 3.15 − 0.005i, Mie; an upper-end estimate for low-density aggregates), fall speed ``0.8 D^0.16`` m/s;
    detector (CA-CFAR by default) as in models/radar/weather.py."""

    id: ClassVar[str] = "snow.radar"
    summary: ClassVar[str] = "dry-snow attenuation (0.8205 S dB/km, extrapolated), detection loss and clutter, 2.5 mm/h"

    snowfall_rate_mm_per_h: float = param(2.5, unit="mm/h", doc="liquid-equivalent snowfall rate (D3.5: 2.5)",
                                          ge=0)
    snow_dsd: str = param("gunn_marshall", doc="snow size distribution of the clutter", choices=tuple(SNOW_LAWS))

    def gamma_db_per_km(self, profile: RadarProfile) -> float:
        return snow_attenuation_db_per_km(self.snowfall_rate_mm_per_h)

    def hydrometeors(self, profile: RadarProfile) -> Hydrometeors | None:
        if self.snowfall_rate_mm_per_h < MIN_PRECIPITATION_RATE_MM_PER_H:
            return None
        return snow_flakes(self.snowfall_rate_mm_per_h, self.snow_dsd, self.backscatter)
