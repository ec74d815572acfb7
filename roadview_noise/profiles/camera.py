"""Camera profiles (models.md §2.0): the ROADVIEW Lucid Triton default, CARLA-style pinholes, YAML files.

The Lucid numbers of the reference are mutually inconsistent (FoV gives f_x = 1137.4 px, 6 mm / 4.5 µm gives
1333 px). Geometry uses one K from the horizontal FoV with square pixels (models.md §2.0 [PROP]); the stated optics
(6 mm, f/2.1, 4.5 µm) are kept only for defocus.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import yaml

from ..errors import InputError
from ..types import CameraProfile


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


def camera_profile_from_mapping(d: dict, *, source: str = "profile") -> CameraProfile:
    """Build a profile from a mapping: either ``K: [[fx,0,cx],[0,fy,cy],[0,0,1]]`` or ``fov_h_deg`` (+ optional
    ``fov_v_deg``), plus ``width_px``, ``height_px`` and any other :class:`CameraProfile` field."""
    d = dict(d)
    allowed = {f.name for f in dataclasses.fields(CameraProfile)} | {"K", "fov_h_deg", "fov_v_deg"}
    unknown = set(d) - allowed
    if unknown:
        raise InputError(f"unknown camera profile keys {sorted(unknown)} (allowed: {sorted(allowed)})", file=source)
    try:
        name = str(d.pop("name", Path(source).stem))
        w, h = int(d.pop("width_px")), int(d.pop("height_px"))
        if "K" in d:
            k = d.pop("K")
            d.update(fx_px=float(k[0][0]), fy_px=float(k[1][1]), cx_px=float(k[0][2]), cy_px=float(k[1][2]))
            return CameraProfile(name, w, h, **d)
        if "fov_h_deg" in d:
            return CameraProfile.from_fov(name, w, h, float(d.pop("fov_h_deg")), d.pop("fov_v_deg", None), **d)
        return CameraProfile(name, w, h, **d)
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise InputError(f"invalid camera profile ({e})", file=source) from None


def load_camera_profile(spec: str | dict | None, *, base_dir: Path | None = None) -> CameraProfile:
    """A built-in name, a YAML file path, or a mapping; default the Lucid Triton."""
    if spec is None:
        return lucid_triton_028s()
    if isinstance(spec, dict):
        return camera_profile_from_mapping(spec)
    if spec in BUILTIN:
        return BUILTIN[spec]()
    path = Path(spec) if base_dir is None or Path(spec).is_absolute() else base_dir / spec
    if not path.is_file():
        raise InputError(f"no camera profile {spec!r}: not a built-in ({', '.join(BUILTIN)}) nor a file",
                         file=str(path))
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise InputError(f"not valid YAML ({e})", file=str(path)) from None
    if not isinstance(data, dict):
        raise InputError("a camera profile file must hold a mapping", file=str(path))
    return camera_profile_from_mapping(data, source=str(path))


def fit_to_image(profile: CameraProfile, width_px: int, height_px: int, *, source: str = "") -> CameraProfile:
    """The profile resampled to the image size; refuses an aspect ratio that differs by more than 1 %."""
    if (profile.width_px, profile.height_px) == (width_px, height_px):
        return profile
    if abs(width_px / height_px - profile.width_px / profile.height_px) > 0.01 * width_px / height_px:
        raise InputError(f"image is {width_px}×{height_px} but camera profile {profile.name!r} is "
                         f"{profile.width_px}×{profile.height_px} (aspect ratio differs); give a matching profile",
                         file=source or None)
    return profile.resized(width_px, height_px)
