"""Camera rain: falling drops as motion-blurred streaks plus a far-field veil (models.md §2.2, §2.9)."""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from numbers import Real
from typing import Any, ClassVar

from ...errors import ModelError
from ...model import Model, Stage, param
from ...physics.particles import rain_classes, rain_fall_speed_m_per_s, render_precipitation
from ...physics.photometry import raindrop_radiance
from ...registry import register


@dataclass(frozen=True)
class PrecipitationCamera(Model):
    """Parameters and apply() shared by the particle weather models (not registered: rain and snow are)."""

    stage: ClassVar[Stage] = Stage.MEDIUM
    sensor: ClassVar[str] = "camera"
    needs_depth: ClassVar[bool] = True
    uses_camera_geometry: ClassVar[bool] = True

    exposure_time_s: Any = param(None, unit="s", doc="exposure; null = the camera profile's (Lucid: 5 ms)")
    min_distance_m: float = param(0.5, unit="m", gt=0,
                                  doc="nearest explicit particle (planar depth); nearer ones join the veil")
    max_particle_distance_m: float = param(30.0, unit="m", gt=0,
                                           doc="farthest explicit particle (planar depth); beyond: veil only")
    min_streak_opacity: float = param(0.02, unit="1", gt=0, le=1,
                                      doc="a particle is drawn only if its peak pixel opacity reaches this; fainter "
                                          "ones (changing a pixel by < 2 % of its contrast with the particle) are "
                                          "rendered by their mean, in the veil; lower = more texture, slower")
    min_explicit_extent_px: float = param(1.0, unit="px", ge=0,
                                          doc="a visible particle is drawn one by one only if its streak (motion + "
                                              "footprint) spans this many pixels; shorter (unresolved) ones add "
                                              "their opacity per pixel, a compound-Poisson draw with their mean and "
                                              "variance; 0 = all one by one (slower)")

    def validate(self) -> None:
        e = self.exposure_time_s
        if e is not None and (isinstance(e, bool) or not isinstance(e, Real) or not e > 0):
            raise ModelError(f"must be null or a number > 0, got {e!r}", model=self.id, field="exposure_time_s")
        if self.min_distance_m >= self.max_particle_distance_m:
            raise ModelError(f"must be > min_distance_m ({self.min_distance_m} m)", model=self.id,
                             field="max_particle_distance_m")

    # what distinguishes rain from snow
    @abstractmethod
    def size_classes(self):
        """Particle size classes (diameters in mm and number densities in m⁻³)."""

    @abstractmethod
    def fall_speed(self, d_mm):
        """Terminal fall speed (m/s) of particles of diameter ``d_mm``."""

    @abstractmethod
    def radiance(self, layout, signal, depth_m, depth_valid):
        """Particle radiance per colour channel in the frame's linear scale."""

    def apply(self, data, *, state, drawn, rng):
        exposure = data.profile.exposure_time_s if self.exposure_time_s is None else float(self.exposure_time_s)
        return render_precipitation(data, self.id, classes=self.size_classes(), fall_speed=self.fall_speed,
                                    radiance=self.radiance, exposure_s=exposure, d_min_m=self.min_distance_m,
                                    d_max_m=self.max_particle_distance_m, min_opacity=self.min_streak_opacity,
                                    min_extent_px=self.min_explicit_extent_px, rng=rng)


@register
@dataclass(frozen=True)
class RainCamera(PrecipitationCamera):
    """Rain (models.md §2.2, wind §2.9): Marshall & Palmer (1948) drops 0.5–6 mm falling at the Atlas & Ulbrich
    (1977) speed ``3.778 D^0.67`` m/s, rendered as streaks with Garg & Nayar (2007) exposure-fraction photometry,
    plus the far-field veil (see :mod:`roadview_noise.physics.particles` for the hybrid and for the §7 fixes:
    metric occlusion test, τ ≤ T, per-class Poisson counts without floor bias, defocus disk, ego motion and wind
    in the streaks, radiance from the image, no box-volume density error).

    Per site: ``I' = S + (1 − M)·t·(I − S)``, M the streak opacity, t the veil transmission, S the drop radiance
    ``0.94 E_env + 0.06 E_sky`` estimated from the frame (E_sky, also standing for the sky inside E_env: the rain's
    overcast sky, sky luminance in the illuminant's colour), so darker scenes (low light before the weather, Eq. 1)
    get darker streaks. Sky sites (range inf) look through the whole rain layer and take the drop radiance.
    Wind and ego motion come from ``conditions`` (wind.camera, Eq. 2). Runs per CFA site on raw mosaics.
    Diagnostics: particles expected / drawn (explicit) / visible (in front of the scene where their streak starts),
    mean streak opacity, veil extinction (all particles, shadow cross-section), particle radiance, exposure."""

    id: ClassVar[str] = "rain.camera"
    summary: ClassVar[str] = "rain: motion-blurred drop streaks (Marshall–Palmer, Garg–Nayar) and far-field veil"

    rain_rate_mm_per_h: float = param(50.0, unit="mm/h", gt=0, le=500, doc="rain rate (D3.5 camera: 50 mm/h)")

    def size_classes(self):
        return rain_classes(float(self.rain_rate_mm_per_h))

    def fall_speed(self, d_mm):
        return rain_fall_speed_m_per_s(d_mm)

    def radiance(self, layout, signal, depth_m, depth_valid):
        return raindrop_radiance(layout, signal, depth_m, depth_valid)
