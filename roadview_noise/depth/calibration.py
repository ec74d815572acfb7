"""Per-image calibration files (recipe ``inputs.calibration``): camera intrinsics, stereo baseline, camera height
and pitch, and the LiDAR → camera transform, from the file formats datasets ship.

Camera frame: OpenCV (x right, y down, z forward); a pixel (u, v) looks along ``K⁻¹ (u, v, 1)``.

- Cityscapes ``camera/*.json`` (cityscapesScripts, csCalibration): ``intrinsic: {fx, fy, u0, v0}`` (px),
  ``extrinsic: {baseline, x, y, z, yaw, pitch, roll}`` (m, rad; z = camera height above the ground, pitch > 0
  looks down).
- KITTI calibration text (object benchmark ``calib/*.txt``: ``P0``–``P3``, ``R0_rect``, ``Tr_velo_to_cam``; or the
  raw recordings' ``P_rect_0N``, ``R_rect_00`` with ``R``/``T`` of ``calib_velo_to_cam.txt`` in one file; or
  Waymo in mmdetection3d's KITTI format: ``P0``–``P4``, ``R0_rect`` and one ``Tr_velo_to_cam_N`` per camera): the
  rectified camera N (default 2, the left colour camera) has ``K = P_N[:, :3]`` and sits at ``t_N = K⁻¹ P_N[:, 3]``
  in the rectified frame, so a Velodyne point maps to ``[I | t_N] · R_rect · Tr_velo_to_cam · X``; ``S_rect_0N``
  (if present) is the image size K refers to. A file without the Velodyne transform gives the intrinsics only, as
  does the depth-completion benchmark's ``depth_selection/*/intrinsics/*.txt`` (K alone: 9 numbers).
- rvnoise YAML (every key optional; see ``recipes/examples/calibration/sample-drive.yaml``)::

      K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]   # px, for an image of width_px × height_px (scaled to the image)
      width_px: 1936
      height_px: 1464
      lidar_to_camera:                           # maps LiDAR-frame points into the camera frame: R·p + t
        rotation: [[0, -1, 0], [0, 0, -1], [1, 0, 0]]   # or a 4×4 matrix instead of this mapping
        translation_m: [0.0, -0.9, -0.3]         # the LiDAR origin in the camera frame
      baseline_m: 0.22
      height_above_ground_m: 1.2
      pitch_deg: 2.0                             # > 0: looks down
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import yaml

from ..errors import InputError

_YAML_KEYS = {"K", "width_px", "height_px", "lidar_to_camera", "baseline_m", "height_above_ground_m", "pitch_deg"}


@dataclass(frozen=True, eq=False)
class Calibration:
    """What a calibration file states; None where it says nothing."""

    source: str
    intrinsics_px: tuple[float, float, float, float] | None = None   # fx, fy, cx, cy
    size_px: tuple[int, int] | None = None                             # (W, H) the intrinsics refer to
    lidar_to_camera: np.ndarray | None = None                          # (4, 4)
    baseline_m: float | None = None
    height_above_ground_m: float | None = None
    pitch_rad: float | None = None
    paired_scan: str | None = None                                     # the LiDAR scan the tables pair (nuScenes)

    def intrinsics_for(self, width_px: int, height_px: int) -> tuple[float, float, float, float] | None:
        """The intrinsics on an image of this size (pixel centres at integer coordinates; scaled when the
        calibration states another size)."""
        if self.intrinsics_px is None or self.size_px is None or self.size_px == (width_px, height_px):
            return self.intrinsics_px
        sx, sy = width_px / self.size_px[0], height_px / self.size_px[1]
        fx, fy, cx, cy = self.intrinsics_px
        return fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5


def load_calibration(path: str | Path, *, kitti_camera: int = 2) -> Calibration:
    """Read a Cityscapes ``.json``, KITTI ``.txt`` or rvnoise ``.yaml`` calibration (module docstring)."""
    path = Path(path)
    return _load_cached(str(path.resolve()), path.stat().st_mtime_ns if path.is_file() else 0, kitti_camera)


@lru_cache(maxsize=64)
def _load_cached(path: str, mtime_ns: int, kitti_camera: int) -> Calibration:
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise InputError(f"cannot read calibration: {exc.strerror or exc}", file=path) from exc
    suffix = p.suffix.lower()
    try:
        if suffix == ".json":
            return _cityscapes(json.loads(text), path)
        if suffix == ".txt":
            return _kitti(text, path, kitti_camera)
        if suffix in (".yaml", ".yml"):
            return _rvnoise_yaml(yaml.safe_load(text), path)
    except (KeyError, TypeError, ValueError, IndexError, yaml.YAMLError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"invalid calibration ({type(exc).__name__}: {exc})", file=path) from None
    raise InputError(f"unknown calibration suffix {p.suffix!r}; expected Cityscapes .json, KITTI .txt or .yaml",
                     file=path)


def _cityscapes(data: dict, path: str) -> Calibration:
    intr, extr = data["intrinsic"], data["extrinsic"]
    return Calibration(path, intrinsics_px=(float(intr["fx"]), float(intr["fy"]), float(intr["u0"]),
                                            float(intr["v0"])),
                       baseline_m=float(extr["baseline"]), height_above_ground_m=float(extr["z"]),
                       pitch_rad=float(extr["pitch"]))


def kitti_rows(text: str) -> dict[str, np.ndarray]:
    """The numeric ``KEY: values`` lines of a KITTI calibration text, and ``KEY values`` lines without the colon
    (KITTI tracking's ``R_rect`` and ``Tr_velo_cam``); others (e.g. ``calib_time: 09-Jan-2012 13:57:47`` or an empty
    ``Tr_imu_to_velo:`` as View-of-Delft writes it) skipped."""
    rows = {}
    for line in text.splitlines():
        key, sep, values = line.partition(":")
        if not sep:
            key, sep, values = line.strip().partition(" ")
            sep = sep if key[:1].isalpha() else ""           # (a line of numbers: no key)
        if sep and values.strip():
            try:
                rows[key.strip()] = np.array(values.split(), dtype=float)
            except ValueError:
                continue
    return rows


def kitti_lidar_to_rectified(rows: dict[str, np.ndarray], camera: int,
                             path: str) -> tuple[np.ndarray, np.ndarray] | None:
    """``(R_rect, Tr_velo_to_cam)`` (4 × 4 each; their product maps a Velodyne point into the rectified camera
    frame): camera N's ``Tr_velo_to_cam_N`` (Waymo in mmdetection3d's KITTI format), else ``Tr_velo_to_cam`` (or
    ``Tr_velo_cam``), else the raw recordings' ``R``/``T``; ``R0_rect``, ``R_rect_00`` or ``R_rect`` (tracking). None without a Velodyne
    transform."""
    velo_key = next((k for k in (f"Tr_velo_to_cam_{camera}", "Tr_velo_to_cam", "Tr_velo_cam") if k in rows), None)
    if velo_key is not None:
        velo = np.vstack([rows[velo_key].reshape(3, 4), [0, 0, 0, 1]])
    elif "R" in rows and "T" in rows:
        velo = np.eye(4)
        velo[:3, :3], velo[:3, 3] = rows["R"].reshape(3, 3), rows["T"]
    else:
        return None
    r_rect = np.eye(4)
    r_rect[:3, :3] = _first(rows, ("R0_rect", "R_rect_00", "R_rect"), path).reshape(3, 3)
    return r_rect, velo


def _kitti(text: str, path: str, camera: int) -> Calibration:
    rows = kitti_rows(text)
    if not rows and len(text.split()) == 9:                # KITTI depth_selection's intrinsics/*.txt: K, 9 numbers
        k = np.array(text.split(), dtype=float).reshape(3, 3)
        if not np.allclose(k[2], (0, 0, 1)):
            raise InputError(f"9 numbers but not a camera matrix K (last row {k[2].tolist()}, expected 0 0 1)",
                             file=path)
        return Calibration(path, intrinsics_px=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
    p = _first(rows, (f"P{camera}", f"P_rect_{camera:02d}"), path).reshape(3, 4)
    k = p[:, :3]
    intrinsics = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    size = rows.get(f"S_rect_{camera:02d}")
    size = (int(size[0]), int(size[1])) if size is not None else None
    transforms = kitti_lidar_to_rectified(rows, camera, path)
    if transforms is None:
        return Calibration(path, intrinsics_px=intrinsics, size_px=size)   # camera only (calib_cam_to_cam.txt)
    r_rect, velo = transforms
    shift = np.eye(4)
    shift[:3, 3] = np.linalg.solve(k, p[:, 3])
    return Calibration(path, intrinsics_px=intrinsics, size_px=size, lidar_to_camera=shift @ r_rect @ velo)


def _first(rows: dict, keys: tuple[str, ...], path: str) -> np.ndarray:
    for k in keys:
        if k in rows:
            return rows[k]
    raise InputError(f"KITTI calibration has none of {', '.join(keys)} (expected the devkit's 'KEY: values' lines, "
                     f"as in calib/*.txt)", file=path)


def _rvnoise_yaml(data, path: str) -> Calibration:
    if not isinstance(data, dict):
        raise InputError("a calibration YAML holds a mapping", file=path)
    unknown = set(data) - _YAML_KEYS
    if unknown:
        raise InputError(f"unknown calibration keys {sorted(unknown)} (allowed: {sorted(_YAML_KEYS)})", file=path)
    intrinsics = size = extrinsic = pitch = None
    if "K" in data:
        k = np.asarray(data["K"], dtype=float).reshape(3, 3)
        intrinsics = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    if "width_px" in data or "height_px" in data:
        size = (int(data["width_px"]), int(data["height_px"]))
    if "lidar_to_camera" in data:
        extrinsic = _transform(data["lidar_to_camera"], path)
    if "pitch_deg" in data:
        pitch = math.radians(float(data["pitch_deg"]))
    opt = {k: float(data[k]) for k in ("baseline_m", "height_above_ground_m") if k in data}
    return Calibration(path, intrinsics_px=intrinsics, size_px=size, lidar_to_camera=extrinsic, pitch_rad=pitch, **opt)


def _transform(spec, path: str) -> np.ndarray:
    """A 4×4 matrix, or ``{rotation: 3×3, translation_m: 3}``; the rotation must be orthonormal."""
    if isinstance(spec, dict):
        unknown = set(spec) - {"rotation", "translation_m"}
        if unknown:
            raise InputError(f"lidar_to_camera has unknown keys {sorted(unknown)}; expected rotation and "
                             f"translation_m", file=path)
        m = np.eye(4)
        m[:3, :3] = np.asarray(spec["rotation"], dtype=float).reshape(3, 3)
        m[:3, 3] = np.asarray(spec["translation_m"], dtype=float).reshape(3)
    else:
        m = np.asarray(spec, dtype=float).reshape(4, 4)
    if not np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-4) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise InputError("lidar_to_camera is not a rigid transform (the rotation must be orthonormal, the last row "
                         "0 0 0 1)", file=path)
    return m
