"""Camera calibration from the nuScenes tables (recipe ``inputs.calibration: {nuscenes: v1.0-trainval}``, the
folder of the tables under the input root = the dataroot).

An image ``samples/CAM_FRONT/….jpg`` is found in ``sample_data.json`` by its ``filename`` (relative to the
dataroot); its ``calibrated_sensor`` record (``calibrated_sensor.json``) gives ``camera_intrinsic`` (K of the
undistorted, rectified image) and the camera's pose in the ego frame — ``translation`` (m) and ``rotation`` (unit
quaternion w, x, y, z; sensor → ego). The ego frame is the centre of the rear axle projected onto the ground, x
forward, y left, z up (nuScenes schema, "calibrated_sensor"; devkit issues #161, #487), so the camera's height
above the ground is ``translation[2]`` and its pitch is the angle of the optical axis (camera z) below the ego
x–y plane.

The paired LiDAR scan is the ``lidar_depth.scan`` pattern's file or, without a pattern, the ``LIDAR_TOP`` key
frame of the image's sample (the ``sample_data`` record under ``samples/LIDAR_TOP/`` with the image's
``sample_token``); ``lidar_to_camera = T_cam←ego · T_ego←lidar`` with both sensors' static calibrations. The ego motion between the scan's and the image's time stamps is not
compensated: nuScenes triggers each camera when the top LiDAR sweeps across the centre of that camera's field of
view (Caesar et al. 2020, "nuScenes", §2 Sensor synchronization), so the points the image shows were measured
within a few milliseconds of it.

``sample_data.json`` of v1.0-trainval holds millions of records: it is scanned once per process for the
``filename``, ``calibrated_sensor_token`` and ``sample_token`` of each record (memory-mapped, not parsed whole).
"""

from __future__ import annotations

import json
import math
import mmap
import re
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import InputError
from .calibration import Calibration

_RECORD = re.compile(rb"\{[^{}]*\}")
_FILENAME = re.compile(rb'"filename"\s*:\s*"([^"]*)"')
_SENSOR = re.compile(rb'"calibrated_sensor_token"\s*:\s*"(\w+)"')
_SAMPLE = re.compile(rb'"sample_token"\s*:\s*"(\w+)"')
_KEY_FRAME = re.compile(rb'"is_key_frame"\s*:\s*true')
LIDAR_FOLDER = "samples/LIDAR_TOP/"


def nuscenes_calibration(tables_dir: Path, image_rel: str, *, lidar: bool = False,
                         scan_rel: str | None = None) -> Calibration:
    """The calibration of the image ``image_rel`` (path relative to the dataroot, the folder above
    ``tables_dir``); with ``lidar``, the LiDAR → camera transform of the scan ``scan_rel`` (relative to the
    dataroot), by default the LIDAR_TOP key frame of the image's sample (module docstring)."""
    tables_dir = Path(tables_dir).resolve()
    index, sensors, lidar_of_sample = _tables(str(tables_dir))
    camera = _record(index, sensors, image_rel, tables_dir)
    if not camera.get("camera_intrinsic"):
        raise InputError(f"the calibrated_sensor record of {image_rel!r} has no camera_intrinsic (not a camera)",
                         file=str(tables_dir / "calibrated_sensor.json"))
    k = np.asarray(camera["camera_intrinsic"], dtype=float).reshape(3, 3)
    ego_from_camera = _pose(camera)
    axis = ego_from_camera[:3, :3] @ [0.0, 0.0, 1.0]                    # optical axis in the ego frame
    pitch = -math.asin(max(-1.0, min(1.0, float(axis[2]))))
    lidar_to_camera = None
    if lidar:
        if scan_rel is None:
            scan_rel = lidar_of_sample.get(index[image_rel][1])
            if scan_rel is None:
                raise InputError(f"no {LIDAR_FOLDER} key frame in the sample of {image_rel!r}",
                                 file=str(tables_dir / "sample_data.json"))
        lidar_to_camera = np.linalg.inv(ego_from_camera) @ _pose(_record(index, sensors, scan_rel, tables_dir))
    return Calibration(str(tables_dir / "calibrated_sensor.json"),
                       intrinsics_px=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]), lidar_to_camera=lidar_to_camera,
                       height_above_ground_m=float(camera["translation"][2]), pitch_rad=pitch, paired_scan=scan_rel)


def _record(index: dict[str, tuple[str, str]], sensors: dict[str, dict], rel: str, tables_dir: Path) -> dict:
    if rel not in index:
        raise InputError(f"no sample_data record with filename {rel!r} (the file's path relative to the "
                         f"dataroot {str(tables_dir.parent)!r})", file=str(tables_dir / "sample_data.json"))
    token = index[rel][0]
    try:
        return sensors[token]
    except KeyError:
        raise InputError(f"calibrated_sensor {token} of {rel!r} is missing",
                         file=str(tables_dir / "calibrated_sensor.json")) from None


def _pose(record: dict) -> np.ndarray:
    """4×4 sensor → ego transform of a calibrated_sensor record (quaternion w, x, y, z)."""
    w, x, y, z = (float(v) for v in record["rotation"])
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 0:
        raise ValueError(f"calibrated_sensor {record.get('token')}: zero rotation quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [float(v) for v in record["translation"]]
    return m


@lru_cache(maxsize=2)
def _tables(tables: str) -> tuple[dict[str, tuple[str, str]], dict[str, dict], dict[str, str]]:
    """Of a tables folder: sample_data filename → (calibrated_sensor token, sample token); calibrated_sensor
    token → record; sample token → its LIDAR_TOP key frame's filename."""
    folder = Path(tables)
    index: dict[str, tuple[str, str]] = {}
    lidar_of_sample: dict[str, str] = {}
    try:
        sensors = {r["token"]: r for r in json.loads((folder / "calibrated_sensor.json").read_text())}
        with open(folder / "sample_data.json", "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            for m in _RECORD.finditer(mm):
                record = m.group()
                f, c, s = _FILENAME.search(record), _SENSOR.search(record), _SAMPLE.search(record)
                if not (f and c and s):
                    continue
                name, sample = f.group(1).decode(), s.group(1).decode()
                index[name] = (c.group(1).decode(), sample)
                if name.startswith(LIDAR_FOLDER) and _KEY_FRAME.search(record):
                    lidar_of_sample[sample] = name
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read the nuScenes tables ({exc})", file=tables) from None
    return index, sensors, lidar_of_sample
