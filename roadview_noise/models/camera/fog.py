"""Camera fog: Koschmieder's law with per-channel Mie extinction of the CE fog distributions (models.md §2.1)."""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Real
from typing import Any, ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Stage, param
from ...physics.cfa import SiteLayout
from ...physics.fog_optics import FOG_TABLES, fog_extinction_per_m
from ...physics.photometry import (FrameSample, absolute_radiance, airlight_radiance, composite, frame_depth_m,
                                      site_transmission)
from ...registry import register


def check_radiance(value: Any, model_id: str, field: str) -> Any:
    """None, a number ≥ 0, or three numbers ≥ 0 (R, G, B) → the same as a tuple; ModelError otherwise."""
    if value is None:
        return None
    vals = (value,) if isinstance(value, Real) else tuple(value) if isinstance(value, (list, tuple)) else None
    if (vals is None or len(vals) not in (1, 3) or
            not all(isinstance(v, Real) and not isinstance(v, bool) and v >= 0 for v in vals)):
        raise ModelError(f"must be null (estimate from the image), a number ≥ 0 or [R, G, B] ≥ 0 in linear "
                         f"full-scale units, got {value!r}", model=model_id, field=field)
    return float(vals[0]) if len(vals) == 1 else tuple(float(v) for v in vals)


@register
@dataclass(frozen=True)
class FogCamera(Model):
    """Homogeneous fog (models.md §2.1; D3.4 physics model, Koschmieder 1924; Mie over the CE chamber DSDs).

    Per site of colour c at range d: ``t_c = exp(−σ_c d)``, ``I' = t_c I + (1 − t_c) A_c``; sky (d = inf) becomes
    the airlight. ``σ_c(V)`` comes from :mod:`roadview_noise.physics.fog_optics`. Default table ``corrected``
    (right Mie size parameter): the physics, since models.md §7.2 lists the reference's halved size parameter as
    a bug; ``reference`` reproduces the D3.5 library's table (≈ 6 % more extinction) for comparisons with D3.5.
    With the default table a black target at d = V = 30 m keeps 5.3 % (R 5.2, G 5.3, B 5.5 %), the MOR
    definition's 5 %; the reference table gives 4.4 % (G).
    Airlight ``A_c``: estimated from the frame, so it follows an earlier low-light step: its luminance from the sky
    sites (else the brightest 0.1 % of pixels), its colour from the illuminant (grey pixels of the scene), since fog
    droplets scatter all wavelengths alike (Narasimhan & Nayar 2002; ``physics.photometry.airlight_radiance``);
    never from pixels whose depth is not valid, e.g. filled holes. A user value is in linear full-scale units of
    the undarkened scene and is scaled by ``conditions.luminance_factor``. Runs per CFA site on raw mosaics with
    the site's wavelength. Wind does not change fog (models.md §2.9: small, nearly static droplets in a homogeneous
    medium).
    Diagnostics: extinction per channel, airlight used, mean transmission per channel over the non-sky sites.
    """

    id: ClassVar[str] = "fog.camera"
    stage: ClassVar[Stage] = Stage.MEDIUM
    sensor: ClassVar[str] = "camera"
    needs_depth: ClassVar[bool] = True
    summary: ClassVar[str] = "fog: Koschmieder contrast loss with per-channel Mie extinction (CE DSDs)"

    visibility_m: float = param(30.0, unit="m", gt=0, doc="meteorological optical range (D3.5 camera: 30 m)")
    airlight: Any = param(None, unit="1", doc="fog radiance at infinity in linear full-scale units, scalar or "
                                              "[R, G, B]; null = estimate from the image")
    fog_table: str = param("corrected", choices=FOG_TABLES,
                           doc="corrected (right Mie size parameter) or reference (D3.5 shipped table, ≈6 % more)")

    def validate(self) -> None:
        object.__setattr__(self, "airlight", check_radiance(self.airlight, self.id, "airlight"))

    def apply(self, data, *, state, drawn, rng):
        depth = frame_depth_m(data, self.id)
        layout = SiteLayout.of(data)
        signal = data.signal()
        sigma = fog_extinction_per_m(self.visibility_m, self.fog_table)
        if self.airlight is None:
            airlight = airlight_radiance(layout, signal, depth, data.depth_valid)
        else:
            airlight = absolute_radiance(self.airlight, data.conditions.luminance_factor)
        t = site_transmission(layout, depth, sigma)
        mean_t = [float(s.mean()) if s.size else None
                  for s in FrameSample(layout, t, depth).values(np.isfinite)]
        out = composite(layout, signal, t, airlight, out=t)
        return data.with_signal(out), {
            "extinction_per_m": [float(s) for s in sigma],
            "airlight": [float(a) for a in airlight],
            "mean_transmission": mean_t,
        }
