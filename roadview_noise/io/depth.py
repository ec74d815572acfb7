"""Depth-map reader/writers: OpenEXR, NumPy ``.npy`` and CARLA's 24-bit depth PNG → range along the ray (m).

Models need the Euclidean range along each pixel ray, ``inf`` for sky (models.md §0.2). CARLA depth PNGs hold planar
depth ``z = 1000 m · (R + 256 G + 65536 B) / (2²⁴ − 1)`` with the far plane (1000 m) as the sky marker: planar values
≥ 1000 m become ``inf`` and the rest is converted to range with the camera intrinsics. EXR and ``.npy`` files hold
range unless ``planar=True``.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import OpenEXR

from ..errors import InputError
from ..types import CameraProfile
from ..units import planar_depth_to_range
from .atomic import atomic_path, write_bytes_atomic
from .image import check_structure

CARLA_FAR_M = 1000.0
CARLA_MAX_CODE = 2 ** 24 - 1
EXR_CHANNELS = ("Z", "Y", "R", "depth")       # preferred channel names, in order; else the first channel


def read_depth(path: str | os.PathLike, *, profile: CameraProfile | None = None,
               expected_shape: tuple[int, int] | None = None, planar: bool = False) -> np.ndarray:
    """(H, W) float32 range along the pixel ray in metres, ``inf`` where there is no depth (sky).

    ``.exr`` (channel Z, Y, R, depth or the first one), ``.npy`` (2-D float array) or CARLA depth ``.png`` (always
    planar). Planar depth is converted with ``profile``'s intrinsics, which must match the depth grid."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".png":
        depth, planar = _read_carla_png(path), True
    elif suffix == ".exr":
        depth = _read_exr(path)
    elif suffix == ".npy":
        depth = _read_npy(path)
    else:
        raise InputError(f"unknown depth suffix {path.suffix!r}; expected .exr, .npy or a CARLA depth .png",
                         file=str(path))
    if expected_shape is not None and depth.shape != tuple(expected_shape):
        raise InputError(f"depth map is {depth.shape[0]}×{depth.shape[1]} (H×W) but the image is "
                         f"{expected_shape[0]}×{expected_shape[1]}", file=str(path))
    n_nan = int(np.count_nonzero(np.isnan(depth)))
    n_neg = int(np.count_nonzero(depth < 0))
    if n_nan or n_neg:
        raise InputError(f"depth has {n_nan} NaN and {n_neg} negative values; depth must be ≥ 0 m "
                         f"(inf for sky)", file=str(path))
    if planar:
        if profile is None:
            raise InputError("planar depth needs a camera profile (intrinsics) to convert to range along the ray",
                             file=str(path))
        if (profile.height_px, profile.width_px) != depth.shape:
            raise InputError(f"depth map is {depth.shape[0]}×{depth.shape[1]} (H×W) but camera profile "
                             f"{profile.name!r} is {profile.height_px}×{profile.width_px}", file=str(path))
        depth = planar_depth_to_range(depth, profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px)
    return np.ascontiguousarray(depth, dtype=np.float32)


def write_depth_exr(path: str | os.PathLike, depth_m: np.ndarray) -> None:
    """Single float32 channel ``Z``, ZIP compression."""
    depth = np.ascontiguousarray(_check_2d(depth_m), dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(header, {"Z": depth}) as exr:
        exr.write(str(tmp))


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


def _read_carla_png(path: Path) -> np.ndarray:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read depth PNG: {exc.strerror or exc}", file=str(path)) from exc
    check_structure(data, "png", path)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("cannot read or decode the CARLA depth PNG", file=str(path))
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4):
        raise InputError(f"a CARLA depth PNG is 8-bit BGR(A); got {img.dtype} with shape {img.shape}", file=str(path))
    b, g, r = (img[..., k].astype(np.uint32) for k in range(3))
    code = r + (g << 8) + (b << 16)
    z = (code * (CARLA_FAR_M / CARLA_MAX_CODE)).astype(np.float32)
    z[z >= CARLA_FAR_M] = np.inf
    return z


def _read_exr(path: Path) -> np.ndarray:
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            order = [c.name for c in exr.header()["channels"]]
            channels = exr.channels()
            name = next((c for c in EXR_CHANNELS if c in channels), order[0] if order else None)
            if name is None:
                raise InputError("EXR file has no channels", file=str(path))
            pixels = np.asarray(channels[name].pixels)
    except (RuntimeError, OSError, ValueError) as exc:      # OpenEXR raises all three for damaged files
        raise InputError(f"corrupt or truncated EXR, OpenEXR cannot read it ({exc})", file=str(path)) from exc
    if pixels.ndim != 2 or pixels.dtype.kind != "f":
        raise InputError(f"EXR channel {name!r} is {pixels.dtype} with shape {pixels.shape}; expected float depth",
                         file=str(path))
    return pixels.astype(np.float32)


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
    return depth.astype(np.float32)
