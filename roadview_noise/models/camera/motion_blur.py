"""Motion blur of the exposure: D3.5's radial blur and a physical mode from ego motion and depth (models.md §2.6;
D3.5 CNF7–9, Eq. 3)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Stage, param
from ...param_checks import optional_number, point_px
from ...physics.mosaic import phases
from ...physics.motion_blur import flow_blur, zoom_blur
from ...registry import register
from ...types import RawFrame

MODES = ("reference", "physical")


def vehicle_to_camera(v) -> tuple[float, float, float]:
    """A vector in the vehicle frame (x forward, y left, z up) in the frame of a forward-looking camera (x right,
    y down, z forward)."""
    return (-float(v[1]), -float(v[2]), float(v[0]))


@register
@dataclass(frozen=True)
class MotionBlurCamera(Model):
    """Blur of a moving camera during the exposure (models.md §2.6; D3.5: "blur 0.002, 7 iterations").

    ``reference`` (default): D3.5's radial blur around the focus of expansion ``c`` (default the principal point;
    the reference hard-coded one THI image's vanishing point with swapped height and width):
    ``J = Σ_j C(n, j)/2ⁿ · I(c + (1+b)^j (1−b)^(n−j) (p − c))``, the closed form of D3.5's n iterations of
    ``½ I(c + (1+b)(p−c)) + ½ I(c + (1−b)(p−c))`` (:func:`~roadview_noise.physics.motion_blur.zoom_blur`). The
    radial standard deviation is ``b·r·√n`` (5.3 px at 1000 px for the D3.5 values), the centre stays sharp, and
    borders reflect (the reference averaged in black).

    ``physical``: a box blur along the optical flow of the exposure (models.md §2.6 [PROP];
    :func:`~roadview_noise.physics.motion_blur.flow_blur`), for the ego velocity (``ego_speed_m_per_s`` forward,
    or the recipe's ``ego_velocity_m_per_s``), the exposure time (profile or parameter), the depth map (or a
    constant ``scene_depth_m``) and an optional yaw rate; near, peripheral objects smear most, the sky only by the
    yaw. The camera is taken to look forward along the vehicle's x axis.

    Raw Bayer mosaics are blurred per CFA sub-lattice (each colour from its own sites, no demosaic): the same
    kernels on the four 2×2 phases with their image coordinates. Diagnostics: radial SD at the farthest corner
    (reference) or the mean and largest blur length in px (physical)."""

    id: ClassVar[str] = "motion_blur.camera"
    stage: ClassVar[Stage] = Stage.EXPOSURE
    sensor: ClassVar[str] = "camera"
    uses_camera_geometry: ClassVar[bool] = True
    summary: ClassVar[str] = "motion blur: D3.5 radial blur (b 0.002, 7 iterations) or ego motion + depth"

    mode: str = param("reference", choices=MODES, doc="reference: D3.5 radial blur; physical: flow of ego motion")
    blur: float = param(0.002, unit="1", ge=0, lt=0.5, doc="reference: relative radial scale per iteration (D3.5)")
    iterations: int = param(7, unit="1", ge=0, le=64, doc="reference: number of iterations n (D3.5: 7)")
    focus_of_expansion_px: Any = param(None, unit="px", doc="reference: blur centre [x, y]; null = principal point")
    ego_speed_m_per_s: Any = param(None, unit="m/s", doc="physical: forward speed; null = the recipe's "
                                                         "ego_velocity_m_per_s (vehicle frame)")
    yaw_rate_deg_per_s: float = param(0.0, unit="deg/s", ge=-360, le=360, doc="physical: yaw rate, positive "
                                                                              "turning left")
    exposure_time_s: Any = param(None, unit="s", doc="physical: exposure time; null = the camera profile's")
    scene_depth_m: Any = param(None, unit="m", doc="physical: planar depth Z of a fronto-parallel scene, used "
                                                   "when the frame has no depth map")
    sample_step_px: float = param(1.0, unit="px", gt=0, le=8, doc="physical: largest spacing of the samples along "
                                                                  "the blur")

    def validate(self) -> None:
        object.__setattr__(self, "focus_of_expansion_px",
                           point_px(self.focus_of_expansion_px, self.id, "focus_of_expansion_px"))
        for name, above in (("ego_speed_m_per_s", None), ("exposure_time_s", 0.0), ("scene_depth_m", 0.0)):
            object.__setattr__(self, name, optional_number(getattr(self, name), self.id, name, above=above))

    def apply(self, data, *, state, drawn, rng):
        h, w = data.shape
        mosaic = isinstance(data, RawFrame)
        if min(h, w) < (4 if mosaic else 2):
            raise ModelError(f"needs at least {'4×4' if mosaic else '2×2'} pixels, got {w}×{h}", model=self.id)
        signal = data.signal()
        stats = np.zeros(2)
        blur = self._reference(data) if self.mode == "reference" else self._physical(data, stats)
        if mosaic:
            out = np.empty_like(signal)
            for i, j in phases(h, w):
                out[i::2, j::2] = blur(signal[i::2, j::2, None], stride=2, offset=(j, i))[..., 0]
        else:
            out = blur(signal)
        if self.mode == "reference":
            cx, cy = self._centre(data)
            r = max(math.hypot(x - cx, y - cy) for x in (0, w - 1) for y in (0, h - 1))
            diagnostics = {"radial_sd_at_corner_px": float(self.blur * math.sqrt(self.iterations) * r),
                           "centre_px": [float(cx), float(cy)]}
        else:
            diagnostics = {"blur_length_mean_px": float(stats[0] / (h * w)), "blur_length_max_px": float(stats[1])}
        return data.with_signal(out), diagnostics

    def _centre(self, data) -> tuple[float, float]:
        return self.focus_of_expansion_px or (data.profile.cx_px, data.profile.cy_px)

    def _reference(self, data):
        centre = self._centre(data)
        return lambda plane, stride=1, offset=(0, 0): zoom_blur(plane, centre, self.blur, self.iterations,
                                                                stride=stride, offset=offset)

    def _physical(self, data, stats):
        """The flow blur for this frame's ego motion (camera-frame velocity), exposure and depth."""
        prof = data.profile
        if self.ego_speed_m_per_s is None:
            vel = vehicle_to_camera(data.conditions.ego_velocity_m_per_s)
        else:
            vel = (0.0, 0.0, float(self.ego_speed_m_per_s))
        exposure = prof.exposure_time_s if self.exposure_time_s is None else float(self.exposure_time_s)
        if data.depth_m is None and self.scene_depth_m is None:
            raise ModelError("physical mode needs a depth map (range along each pixel ray; loaded when the chain "
                             "has a weather model, or give a depth source) or a constant scene_depth_m",
                             model=self.id, field="scene_depth_m")
        intrinsics = (prof.fx_px, prof.fy_px, prof.cx_px, prof.cy_px)
        return lambda plane, stride=1, offset=(0, 0): flow_blur(
            plane, data.depth_m, scene_depth_m=self.scene_depth_m or 0.0, intrinsics=intrinsics,
            velocity_m_per_s=vel, yaw_rate_rad_per_s=math.radians(self.yaw_rate_deg_per_s),
            exposure_time_s=exposure, step_px=self.sample_step_px, stride=stride, offset=offset, stats=stats)
