"""Depth-map readers/writers → range along the pixel ray (m): OpenEXR, NumPy ``.npy``, CARLA's 24-bit depth PNG,
KITTI depth PNG and Cityscapes disparity PNG.

Models need the Euclidean range along each pixel ray, ``inf`` for sky (models.md §0.2). Holes — pixels without a
valid measurement — are returned as NaN and handled by the recipe's ``depth_holes`` policy
(:mod:`roadview_noise.depth.holes`); a reader never guesses them. Per format:

- ``exr``, ``npy``: float depth in metres, range unless ``planar=True``; NaN, 0 and negative values are holes.
  An EXR's depth is its channel named ``Z``, ``Y``, ``R`` or ``depth`` (in that order), also as the last part of a
  layered name (Blender's multilayer ``ViewLayer.Depth.Z``), else its first channel.
- ``carla``: 8-bit BGR(A) PNG, planar ``z = 1000 m · (R + 256 G + 65536 B) / (2²⁴ − 1)``; the far plane (1000 m)
  is the sky marker and becomes ``inf``. A grey PNG (R = G = B on every pixel) is one of CARLA's depth
  visualisations (``ColorConverter.Depth``, ``LogarithmicDepth``: 8 bits, not metres) and is refused.
- ``kitti``: KITTI depth-completion PNG, uint16 planar ``z = p / 256`` m, ``p = 0`` invalid (KITTI devkit).
- ``cityscapes``: Cityscapes disparity PNG, uint16, disparity ``d = (p − 1) / 256`` px for ``p > 0``, ``p = 0``
  invalid (cityscapesScripts README); planar ``z = B f_x / d`` with the stereo baseline B and f_x of the image's
  ``camera/*.json``; ``d = 0`` (p = 1) is infinitely far: sky.

``auto`` picks the format from the suffix and, for PNG, the sample type: 8-bit colour is CARLA, 16-bit grey is
Cityscapes when the file name contains ``disparity`` and KITTI otherwise. Planar depth is converted to range with
the camera profile's intrinsics, which must match the depth grid.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..types import CameraProfile
from ..units import planar_depth_to_range
from .atomic import atomic_path, write_bytes_atomic
from .image import PNG_SIGNATURE, check_structure, decode_codes, read_exr_channels, write_exr_channels

CARLA_FAR_M = 1000.0
CARLA_MAX_CODE = 2 ** 24 - 1
KITTI_UNITS_PER_M = 256.0
CITYSCAPES_UNITS_PER_PX = 256.0
EXR_CHANNELS = ("Z", "Y", "R", "depth")       # preferred channel names, in order; else the first channel
DEPTH_FORMATS = ("auto", "exr", "npy", "carla", "kitti", "cityscapes")
PLANAR_FORMATS = ("carla", "kitti", "cityscapes")
_SUFFIX_FORMATS = {".exr": "exr", ".npy": "npy"}


def read_depth(path: str | os.PathLike, *, fmt: str = "auto", profile: CameraProfile | None = None,
               expected_shape: tuple[int, int] | None = None, planar: bool = False,
               baseline_m: float | None = None) -> np.ndarray:
    """(H, W) float32 range along the pixel ray in metres, ``inf`` for sky, NaN for holes (see module docstring).

    ``planar`` applies to ``exr``/``npy`` (the PNG formats are planar by definition). Planar depth is converted with
    ``profile``'s intrinsics; Cityscapes disparity also needs ``baseline_m`` and takes f_x from ``profile``."""
    path = Path(path)
    depth, fmt = _decode(path, fmt, profile, baseline_m)
    if expected_shape is not None and depth.shape != tuple(expected_shape):
        raise InputError(f"depth map is {depth.shape[0]}×{depth.shape[1]} (H×W) but the image is "
                         f"{expected_shape[0]}×{expected_shape[1]}", file=str(path))
    if planar or fmt in PLANAR_FORMATS:
        profile = _check_profile(profile, depth.shape, path, "planar depth needs a camera profile (intrinsics) to "
                                                             "convert to range along the ray")
        depth = planar_depth_to_range(depth, profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px)
    return np.ascontiguousarray(depth, dtype=np.float32)


def depth_format(path: str | os.PathLike, fmt: str = "auto") -> str:
    """The format a depth file is read as (see module docstring); reads a PNG's header for ``auto``."""
    if fmt != "auto":
        if fmt not in DEPTH_FORMATS:
            raise ValueError(f"unknown depth format {fmt!r}; expected one of {DEPTH_FORMATS}")
        return fmt
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in _SUFFIX_FORMATS:
        return _SUFFIX_FORMATS[suffix]
    if suffix != ".png":
        raise InputError(f"unknown depth suffix {path.suffix!r}; expected .exr, .npy or a depth .png (CARLA, "
                         f"KITTI, Cityscapes disparity)", file=str(path))
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError as exc:
        raise InputError(f"cannot read depth PNG: {exc.strerror or exc}", file=str(path)) from exc
    if not head.startswith(PNG_SIGNATURE) or len(head) < 26:
        raise InputError("not a PNG file (bad signature)", file=str(path))
    bit_depth, colour_type = head[24], head[25]                    # IHDR (PNG spec §11.2.2)
    if bit_depth == 8 and colour_type in (2, 6):
        return "carla"
    if bit_depth == 16 and colour_type == 0:
        return "cityscapes" if "disparity" in path.name.lower() else "kitti"
    raise InputError(f"a depth PNG is 8-bit colour (CARLA) or 16-bit grey (KITTI depth, Cityscapes disparity); got "
                     f"bit depth {bit_depth}, colour type {colour_type}", file=str(path))


def _decode(path: Path, fmt: str, profile: CameraProfile | None, baseline_m: float | None
            ) -> tuple[np.ndarray, str]:
    fmt = depth_format(path, fmt)
    if fmt == "exr":
        return _holes_as_nan(_read_exr(path)), fmt
    if fmt == "npy":
        return _holes_as_nan(_read_npy(path)), fmt
    img = _read_png(path)
    if fmt == "carla":
        return _carla_planar(img, path), fmt
    if img.dtype != np.uint16 or img.ndim != 2:
        raise InputError(f"a {fmt} depth PNG is 16-bit grey; got {img.dtype} with shape {img.shape}", file=str(path))
    if fmt == "kitti":
        z = img.astype(np.float32) / np.float32(KITTI_UNITS_PER_M)
        z[img == 0] = np.nan
        return z, fmt
    if baseline_m is None or profile is None:
        raise InputError("a Cityscapes disparity map needs the stereo baseline and f_x of its camera: give "
                         "inputs.calibration (the image's camera/*.json)", file=str(path))
    profile = _check_profile(profile, img.shape, path, "")
    disparity = (img.astype(np.float32) - np.float32(1.0)) / np.float32(CITYSCAPES_UNITS_PER_PX)
    with np.errstate(divide="ignore"):
        z = np.float32(baseline_m * profile.fx_px) / disparity      # d = 0 → inf (infinitely far)
    z[img == 0] = np.nan
    return z, fmt


def _holes_as_nan(depth: np.ndarray) -> np.ndarray:
    """Float depth with every value that is not a valid range (NaN, ≤ 0) as NaN; ``inf`` (sky) is kept. In place
    when ``depth`` is writable float32 (the readers' own fresh arrays), else on a float32 copy."""
    if depth.dtype != np.float32 or not depth.flags.writeable:
        depth = depth.astype(np.float32)
    if not depth.size or not depth.min() > 0:            # NaN propagates through min: one pass when there is no hole
        np.copyto(depth, np.float32(np.nan), where=~(depth > 0))
    return depth


def _check_profile(profile: CameraProfile | None, shape: tuple[int, int], path: Path, missing: str
                   ) -> CameraProfile:
    if profile is None:
        raise InputError(missing, file=str(path))
    if (profile.height_px, profile.width_px) != tuple(shape):
        raise InputError(f"depth map is {shape[0]}×{shape[1]} (H×W) but camera profile {profile.name!r} is "
                         f"{profile.height_px}×{profile.width_px}", file=str(path))
    return profile


def write_depth_exr(path: str | os.PathLike, depth_m: np.ndarray) -> None:
    """Single float32 channel ``Z``, ZIP compression."""
    write_exr_channels(path, {"Z": np.asarray(_check_2d(depth_m), dtype=np.float32)})


def write_depth_npy(path: str | os.PathLike, depth_m: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        np.save(tmp, np.ascontiguousarray(_check_2d(depth_m), dtype=np.float32))


def write_carla_depth_png(path: str | os.PathLike, planar_z_m: np.ndarray) -> None:
    """CARLA depth encoding of planar depth (BGRA, alpha 255); ``inf`` and values ≥ 1000 m become the far plane."""
    z = np.asarray(_check_2d(planar_z_m), dtype=np.float64)
    if np.isnan(z).any() or (z < 0).any():
        raise ValueError("planar depth must be ≥ 0 m and not NaN")
    code = np.rint(np.minimum(z, CARLA_FAR_M) / CARLA_FAR_M * CARLA_MAX_CODE).astype(np.uint32)
    bgra = np.stack([(code >> 16) & 255, (code >> 8) & 255, code & 255, np.full_like(code, 255)], axis=-1)
    ok, buf = cv2.imencode(".png", bgra.astype(np.uint8))
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode the depth PNG")
    write_bytes_atomic(path, buf.tobytes())


def _check_2d(depth: np.ndarray) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be a 2-D (H, W) array, got shape {depth.shape}")
    return depth


def _read_png(path: Path) -> np.ndarray:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read depth PNG: {exc.strerror or exc}", file=str(path)) from exc
    check_structure(data, "png", path)
    return decode_codes(data, "png", source=path)


def _carla_planar(img: np.ndarray, path: Path) -> np.ndarray:
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4):
        raise InputError(f"a CARLA depth PNG is 8-bit colour; got {img.dtype} with shape {img.shape}", file=str(path))
    r, g, b = (img[..., k] for k in range(3))
    if np.array_equal(r, g) and np.array_equal(g, b) and ((r > 0) & (r < 255)).any():
        raise InputError("this CARLA depth PNG is grey (R = G = B on every pixel): a depth visualisation saved with "
                         "carla.ColorConverter.Depth or LogarithmicDepth, whose 8 bits are not metres; save the "
                         "depth camera's images with carla.ColorConverter.Raw (24-bit depth)", file=str(path))
    r, g, b = (c.astype(np.uint32) for c in (r, g, b))
    code = r + (g << 8) + (b << 16)
    z = (code * (CARLA_FAR_M / CARLA_MAX_CODE)).astype(np.float32)
    z[z >= CARLA_FAR_M] = np.inf
    z[code == 0] = np.nan
    return z


def _read_exr(path: Path) -> np.ndarray:
    channels, order = read_exr_channels(path)
    layered = [(c.rpartition(".")[2], c) for c in order]             # "ViewLayer.Depth.Z" → "Z"
    name = next((c for want in EXR_CHANNELS for last, c in layered if last == want), order[0] if order else None)
    if name is None:
        raise InputError("EXR file has no channels", file=str(path))
    pixels = channels[name]
    if pixels.ndim != 2 or pixels.dtype.kind != "f":
        raise InputError(f"EXR channel {name!r} is {pixels.dtype} with shape {pixels.shape}; expected float depth",
                         file=str(path))
    return pixels.astype(np.float32, copy=False)                     # our own array: a float32 channel as it is


def _read_npy(path: Path) -> np.ndarray:
    try:
        depth = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"cannot read .npy: {exc}", file=str(path)) from exc
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2 or depth.dtype.kind != "f":
        raise InputError(f".npy depth must be a 2-D float array in metres, got {depth.dtype} with shape "
                         f"{depth.shape}", file=str(path))
    return depth.astype(np.float32, copy=False)
