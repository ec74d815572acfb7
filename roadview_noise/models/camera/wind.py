"""Camera wind: the D3.5 Eq. 2 modifier of the particle weather models (models.md §2.9; CNF16–18)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

from ...model import Model, Stage, param
from ...registry import register


@register
@dataclass(frozen=True)
class WindCamera(Model):
    """Steady, uniform wind acting on the falling particles (models.md §2.9, D3.5 Eq. 2).

    Changes no pixel: it returns the frame with ``conditions.wind_velocity_m_per_s`` set, and the weather model
    after it (rain.camera, snow.camera) moves every particle with it. A particle's horizontal velocity relaxes
    to the wind with the time constant ``τ_p ≈ v_t/g`` (0.6 s for a 2 mm drop, < 0.1 s for snow), far shorter
    than its fall, so in steady state ``v_p = (u_x, u_y, −v_t)``; with ego motion the streak follows
    ``v_rel = v_p − v_ego``. A 3 m/s crosswind tilts a 2 mm drop's streak by ``atan(3/6.014) = 26.5°`` at the
    image centre. Fog is unchanged (small, nearly static droplets in a homogeneous medium; D3.5, models.md §2.9).

    Direction: the wind blows TOWARDS ``wind_direction_deg``, counter-clockwise from the sensor's forward axis
    x (ISO 8855: x forward, y left): 0° blows forward (tailwind, along the optical axis), 90° towards the left
    (a crosswind from the right: streaks lean left at their lower end), 180° towards the camera, 270° towards
    the right. ``lateral_response`` < 1 scales the particles' drift below the wind speed, only to reproduce
    D3.5's figures, whose "snow drifts less than rain" contradicts drag physics (light particles follow the air
    more closely; models.md §2.9 pitfall); 1 is the physics."""

    id: ClassVar[str] = "wind.camera"
    stage: ClassVar[Stage] = Stage.MODIFIER
    sensor: ClassVar[str] = "camera"
    summary: ClassVar[str] = "wind: steady wind drifting the rain/snow particles (Eq. 2, set before the weather)"

    wind_speed_m_per_s: float = param(3.0, unit="m/s", ge=0, le=60, doc="wind speed (D3.5: 3 m/s crosswind)")
    wind_direction_deg: float = param(90.0, unit="deg", ge=-360, le=360,
                                      doc="direction the wind blows towards, counter-clockwise from forward "
                                          "(sensor frame): 0 forward, 90 left (crosswind), 180 towards the camera")
    lateral_response: float = param(1.0, unit="1", ge=0, le=1,
                                     doc="particle drift / wind speed; 1 = physics (steady state), < 1 only to "
                                         "reproduce D3.5's figures")

    def apply(self, data, *, state, drawn, rng):
        speed = float(self.wind_speed_m_per_s) * float(self.lateral_response)
        th = math.radians(self.wind_direction_deg)
        # exact zeros for the cardinal directions (cos 90° is 6e-17 in floating point)
        wind = tuple(0.0 if abs(c) < 1e-12 else speed * c for c in (math.cos(th), math.sin(th))) + (0.0,)
        conditions = dataclasses.replace(data.conditions, wind_velocity_m_per_s=wind)
        return dataclasses.replace(data, conditions=conditions), {
            "wind_velocity_m_per_s": list(wind),
            "wind_speed_m_per_s": float(self.wind_speed_m_per_s),
            "lateral_response": float(self.lateral_response),
        }
