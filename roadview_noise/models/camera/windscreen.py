"""Windscreen distortion: Brown–Conrady pull map around the principal point (models.md §2.5; D3.5 CNF4–6, Eq. 3)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any, ClassVar

import cv2
import numpy as np

from ...errors import ModelError
from ...model import Model, Stage, param
from ...param_checks import point_px
from ...physics.brown_conrady import COEFFICIENTS, BrownConrady, LensWarp
from ...physics.mosaic import remap_mosaic, sublattice_warps
from ...registry import register
from ...types import RawFrame

BORDERS = {"constant": cv2.BORDER_CONSTANT, "reflect": cv2.BORDER_REFLECT_101, "replicate": cv2.BORDER_REPLICATE}
UNITS = ("reference_px", "normalised")


@lru_cache(maxsize=4)
def _lens_warp(distortion: BrownConrady, height: int, width: int) -> LensWarp:
    warp = distortion.pull_map(height, width)
    warp.map_x.flags.writeable = False
    warp.map_y.flags.writeable = False
    return warp


@lru_cache(maxsize=4)
def _diagnostics(distortion: BrownConrady, height: int, width: int) -> dict[str, float]:
    """Fraction of output pixels whose source lies outside the input, largest displacement (px), on a sample grid
    of about 256 px across (properties of the map alone, so computed once per map)."""
    warp = _lens_warp(distortion, height, width)
    step = max(1, min(height, width) // 256)
    sx, sy = warp.map_x[::step, ::step], warp.map_y[::step, ::step]
    outside = (sx < -0.5) | (sx > width - 0.5) | (sy < -0.5) | (sy > height - 0.5)
    v, u = np.mgrid[0:height:step, 0:width:step]
    return {"outside_fraction": float(outside.mean()), "max_displacement_px": float(np.hypot(sx - u, sy - v).max())}


@lru_cache(maxsize=4)
def _mosaic_warps(distortion: BrownConrady, height: int, width: int) -> list:
    warp = _lens_warp(distortion, height, width)
    return sublattice_warps(warp.map_x, warp.map_y)


@register
@dataclass(frozen=True)
class WindscreenCamera(Model):
    """Residual distortion of a camera behind a curved windscreen: the full Brown–Conrady model (models.md §2.5,
    D3.5 "BCP"; :mod:`roadview_noise.physics.brown_conrady`) — rational radial k1–k6, tangential p1–p2 (the terms
    D3.5 says windscreens need), thin prism s1–s4 (windscreen wedge) — computed for every pixel around the principal
    point, resampled bilinearly, output the size of the input.

    Coefficients in ``reference_px`` units are D3.5's: pixel offsets of a ``reference_width_px`` (1936) wide image,
    so k1 = 1e-7 px⁻² (the D3.5 default) pulls a pixel 500 px from the centre from 512.5 px, 1000 px from 1100 px
    (models.md §2.5 oracle), and the same distortion appears on a resized copy of the image. ``normalised`` units
    divide by the focal length instead (OpenCV's convention; k1 = 1e-7 px⁻² ≈ 0.129 at f_x = 1137.4 px).
    With k1 > 0 the picture is compressed towards the border and the corners sample outside the input: they get
    ``border`` (constant black as in D3.5's canvas, or reflect/replicate). D3.5's hacks are not reproduced: no
    quadrant mirroring (it breaks p1, p2), no 100-px bottom padding that moved the centre 50 px down (set
    ``distortion_centre_px`` to reproduce it), no fixed 1311×1726 crop, no nearest-neighbour truncation.

    Geometric model: :meth:`warp` returns the pull map (a :class:`~roadview_noise.physics.brown_conrady.LensWarp`,
    whose ``forward`` inverts the closed form by Newton's method for boxes and points), and :meth:`apply`
    resamples the image with exactly that map. Raw Bayer mosaics are resampled per CFA sub-lattice: each site
    interpolates the sites of its own 2×2 phase (:mod:`roadview_noise.physics.mosaic`), no demosaic.
    Diagnostics: fraction of output pixels whose source lies outside the input, largest displacement (px)."""

    id: ClassVar[str] = "windscreen.camera"
    stage: ClassVar[Stage] = Stage.WINDSCREEN
    sensor: ClassVar[str] = "camera"
    uses_camera_geometry: ClassVar[bool] = True
    summary: ClassVar[str] = "windscreen: Brown–Conrady radial/tangential/prism distortion (D3.5: k1 = 1e-7 px⁻²)"

    k1: float = param(1e-7, unit="px⁻² | 1", doc="radial r² (D3.5: 1e-7 px⁻²)")
    k2: float = param(0.0, unit="px⁻⁴ | 1", doc="radial r⁴")
    k3: float = param(0.0, unit="px⁻⁶ | 1", doc="radial r⁶")
    k4: float = param(0.0, unit="px⁻² | 1", doc="radial denominator r²")
    k5: float = param(0.0, unit="px⁻⁴ | 1", doc="radial denominator r⁴")
    k6: float = param(0.0, unit="px⁻⁶ | 1", doc="radial denominator r⁶")
    p1: float = param(0.0, unit="px⁻¹ | 1", doc="tangential (decentring), y")
    p2: float = param(0.0, unit="px⁻¹ | 1", doc="tangential (decentring), x")
    s1: float = param(0.0, unit="px⁻¹ | 1", doc="thin prism x, r²")
    s2: float = param(0.0, unit="px⁻³ | 1", doc="thin prism x, r⁴")
    s3: float = param(0.0, unit="px⁻¹ | 1", doc="thin prism y, r²")
    s4: float = param(0.0, unit="px⁻³ | 1", doc="thin prism y, r⁴")
    coefficient_units: str = param("reference_px", choices=UNITS,
                                   doc="reference_px: D3.5 pixel units of a reference_width_px wide image; "
                                       "normalised: coordinates divided by the focal length (OpenCV)")
    reference_width_px: int = param(1936, unit="px", ge=1, doc="image width the px coefficients refer to "
                                                               "(D3.5: 1936, Lucid Triton)")
    distortion_centre_px: Any = param(None, unit="px", doc="[x, y] centre of distortion; null = principal point")
    border: str = param("constant", choices=tuple(BORDERS),
                        doc="what corners sampling outside the input get: constant (black, D3.5), reflect, replicate")

    def validate(self) -> None:
        object.__setattr__(self, "distortion_centre_px",
                           point_px(self.distortion_centre_px, self.id, "distortion_centre_px"))

    def distortion(self, data) -> BrownConrady:
        """The distortion of this model for a frame (its size and principal point)."""
        h, w = data.shape
        prof = data.profile
        centre = self.distortion_centre_px or (prof.cx_px, prof.cy_px)
        if self.coefficient_units == "normalised":
            unit = (prof.fx_px, prof.fy_px)
        else:
            unit = (w / self.reference_width_px,) * 2
        coefficients = tuple(float(getattr(self, k)) for k in COEFFICIENTS)
        return BrownConrady(coefficients, (float(centre[0]), float(centre[1])), (float(unit[0]), float(unit[1])))

    def warp(self, data, *, state, drawn) -> LensWarp:
        h, w = data.shape
        return _lens_warp(self.distortion(data), h, w)

    def apply(self, data, *, state, drawn, rng):
        h, w = data.shape
        if min(h, w) < 2:
            raise ModelError(f"needs an image of at least 2×2 pixels, got {w}×{h}", model=self.id)
        distortion = self.distortion(data)
        border = BORDERS[self.border]
        if isinstance(data, RawFrame):
            out = remap_mosaic(data.signal(), _mosaic_warps(distortion, h, w), border=border)
        else:
            out = _lens_warp(distortion, h, w).apply(data.signal(), border=border)
        return data.with_signal(out), dict(_diagnostics(distortion, h, w))
