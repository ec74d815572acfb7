"""Camera profiles (models.md §2.0): the ROADVIEW Lucid Triton default, CARLA-style pinholes, YAML files.

The Lucid numbers of the reference are mutually inconsistent (FoV gives f_x = 1137.4 px, 6 mm / 4.5 µm gives
1333 px). Geometry uses one K from the horizontal FoV with square pixels (models.md §2.0 [PROP]); the stated optics
(6 mm, f/2.1, 4.5 µm) are kept only for defocus.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path


from ..errors import InputError
from ..types import CameraProfile
from . import check_keys, load_profile


def lucid_triton_028s() -> CameraProfile:
    """Lucid Triton TRI028S-CC + 6 mm lens (CARISSMA/THI): 1936×1464, 80.8° horizontal FoV, 5 ms exposure."""
    return CameraProfile.from_fov("lucid_triton_028s", 1936, 1464, 80.8, exposure_time_s=0.005,
                                  pixel_pitch_m=4.5e-6, focal_length_m=6.0e-3, f_number=2.1,
                                  height_above_ground_m=1.0)


def carla_pinhole(width_px: int = 1920, height_px: int = 1080, fov_deg: float = 90.0,
                  exposure_time_s: float = 0.005) -> CameraProfile:
    """CARLA RGB camera: square pixels, horizontal FoV ``fov_deg``."""
    return CameraProfile.from_fov(f"carla_{width_px}x{height_px}_fov{fov_deg:g}", width_px, height_px, fov_deg,
                                  exposure_time_s=exposure_time_s)


BUILTIN = {"lucid_triton_028s": lucid_triton_028s, "carla": carla_pinhole}


_INTRINSICS = ("K", "fov_h_deg", "fov_v_deg", "fx_px", "fy_px", "cx_px", "cy_px")


def _override(base: CameraProfile, fields: dict, source: str) -> CameraProfile:
    """Fields of ``base`` replaced by a mapping. Intrinsics may be given as ``K: [[fx,0,cx],[0,fy,cy],[0,0,1]]``,
    as ``fov_h_deg`` (+ optional ``fov_v_deg``, centred pinhole), or field by field; a new size without intrinsics
    resamples the base optics (:meth:`CameraProfile.resized`)."""
    check_keys(fields, {f.name for f in dataclasses.fields(CameraProfile)} | {"K", "fov_h_deg", "fov_v_deg"},
               "camera", source)
    fields = dict(fields)
    name = str(fields.pop("name", Path(source).stem if source.endswith((".yaml", ".yml")) else base.name))
    try:
        w, h = int(fields.pop("width_px", base.width_px)), int(fields.pop("height_px", base.height_px))
        if "K" in fields:
            k = fields.pop("K")
            fields.update(fx_px=float(k[0][0]), fy_px=float(k[1][1]), cx_px=float(k[0][2]), cy_px=float(k[1][2]))
        elif "fov_h_deg" in fields:
            pin = CameraProfile.from_fov(name, w, h, float(fields.pop("fov_h_deg")), fields.pop("fov_v_deg", None))
            fields.update(fx_px=pin.fx_px, fy_px=pin.fy_px, cx_px=pin.cx_px, cy_px=pin.cy_px)
        elif (w, h) != (base.width_px, base.height_px) and not any(k in fields for k in _INTRINSICS):
            base = base.resized(w, h)
        return dataclasses.replace(base, name=name, width_px=w, height_px=h, **fields)
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise InputError(f"invalid camera profile ({e})", file=source) from None


def load_camera_profile(spec: str | dict | None, *, base_dir: Path | None = None) -> CameraProfile:
    """A built-in name, a YAML file or a mapping (fields over ``base:``, default the Lucid Triton)."""
    return load_profile(spec, kind="camera", builtin=BUILTIN, default=lucid_triton_028s, override=_override,
                        base_dir=base_dir)


def fit_to_image(profile: CameraProfile, width_px: int, height_px: int, *, source: str = "") -> CameraProfile:
    """The profile resampled to the image size; refuses an aspect ratio that differs by more than 1 %."""
    if (profile.width_px, profile.height_px) == (width_px, height_px):
        return profile
    if abs(width_px / height_px - profile.width_px / profile.height_px) > 0.01 * width_px / height_px:
        raise InputError(f"image is {width_px}×{height_px} but camera profile {profile.name!r} is "
                         f"{profile.width_px}×{profile.height_px} (aspect ratio differs); give a matching profile",
                         file=source or None)
    return profile.resized(width_px, height_px)
