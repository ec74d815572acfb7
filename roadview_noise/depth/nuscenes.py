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

``sample_data.json`` of v1.0-trainval holds millions of records (≈ 1 GB): it is memory-mapped, and once per
process and sensor folder (``samples/CAM_FRONT/``, …) the records of that folder's files are found by their
``filename`` and only those are read (``calibrated_sensor_token``, ``sample_token``, ``is_key_frame``).
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

_SENSOR = re.compile(rb'"calibrated_sensor_token"\s*:\s*"(\w+)"')
_SAMPLE = re.compile(rb'"sample_token"\s*:\s*"(\w+)"')
_KEY_FRAME = re.compile(rb'"is_key_frame"\s*:\s*true')
LIDAR_FOLDER = "samples/LIDAR_TOP/"


def nuscenes_calibration(tables_dir: Path, image_rel: str, *, lidar: bool = False,
                         scan_rel: str | None = None) -> Calibration:
    """The calibration of the image ``image_rel`` (path relative to the dataroot, the folder above
    ``tables_dir``); with ``lidar``, the LiDAR → camera transform of the scan ``scan_rel`` (relative to the
    dataroot), by default the LIDAR_TOP key frame of the image's sample (module docstring)."""
    tables = str(Path(tables_dir).resolve())
    camera = _calibrated_sensor(tables, image_rel)
    if not camera.get("camera_intrinsic"):
        raise InputError(f"the calibrated_sensor record of {image_rel!r} has no camera_intrinsic (not a camera)",
                         file=str(Path(tables) / "calibrated_sensor.json"))
    k = np.asarray(camera["camera_intrinsic"], dtype=float).reshape(3, 3)
    ego_from_camera = _pose(camera)
    axis = ego_from_camera[:3, :3] @ [0.0, 0.0, 1.0]                    # optical axis in the ego frame
    pitch = -math.asin(max(-1.0, min(1.0, float(axis[2]))))
    lidar_to_camera = None
    if lidar:
        if scan_rel is None:
            sample = _folder_records(tables, _folder(image_rel))[image_rel][1]
            scan_rel = _lidar_key_frames(tables).get(sample)
            if scan_rel is None:
                raise InputError(f"no {LIDAR_FOLDER} key frame in the sample of {image_rel!r}",
                                 file=str(Path(tables) / "sample_data.json"))
        lidar_to_camera = np.linalg.inv(ego_from_camera) @ _pose(_calibrated_sensor(tables, scan_rel))
    return Calibration(str(Path(tables) / "calibrated_sensor.json"),
                       intrinsics_px=(k[0, 0], k[1, 1], k[0, 2], k[1, 2]), lidar_to_camera=lidar_to_camera,
                       height_above_ground_m=float(camera["translation"][2]), pitch_rad=pitch, paired_scan=scan_rel)


def _folder(rel: str) -> str:
    return rel.rsplit("/", 1)[0] + "/" if "/" in rel else ""


def _calibrated_sensor(tables: str, rel: str) -> dict:
    """The calibrated_sensor record of the sample_data file ``rel``; InputError naming the table."""
    found = _folder_records(tables, _folder(rel)).get(rel)
    if found is None:
        raise InputError(f"no sample_data record with filename {rel!r} (the file's path relative to the "
                         f"dataroot {str(Path(tables).parent)!r})", file=str(Path(tables) / "sample_data.json"))
    try:
        return _sensors(tables)[found[0]]
    except KeyError:
        raise InputError(f"calibrated_sensor {found[0]} of {rel!r} is missing",
                         file=str(Path(tables) / "calibrated_sensor.json")) from None


def _pose(record: dict) -> np.ndarray:
    """4×4 sensor → ego transform of a calibrated_sensor record (quaternion w, x, y, z)."""
    w, x, y, z = (float(v) for v in record["rotation"])
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 0:
        raise InputError(f"calibrated_sensor {record.get('token')}: zero rotation quaternion",
                         file="calibrated_sensor.json")
    w, x, y, z = w / n, x / n, y / n, z / n
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [float(v) for v in record["translation"]]
    return m


@lru_cache(maxsize=2)
def _sensors(tables: str) -> dict[str, dict]:
    """calibrated_sensor token → record."""
    try:
        return {r["token"]: r for r in json.loads((Path(tables) / "calibrated_sensor.json").read_text())}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read the nuScenes tables ({exc})", file=tables) from None


@lru_cache(maxsize=16)
def _folder_records(tables: str, folder: str) -> dict[str, tuple[str, str, bool]]:
    """filename → (calibrated_sensor token, sample token, key frame) of the sample_data records of the files in
    ``folder`` (one sensor's folder, e.g. ``samples/CAM_FRONT/``): a search for those filenames in the
    memory-mapped table, then the record around each."""
    pattern = re.compile(rb'"filename"\s*:\s*"(' + re.escape(folder.encode()) + rb'[^"/]+)"')
    out: dict[str, tuple[str, str, bool]] = {}
    try:
        with open(Path(tables) / "sample_data.json", "rb") as fh, \
                mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            for m in pattern.finditer(mm):
                record = mm[mm.rfind(b"{", 0, m.start()):mm.find(b"}", m.end()) + 1]
                c, s = _SENSOR.search(record), _SAMPLE.search(record)
                if c and s:
                    out[m.group(1).decode()] = (c.group(1).decode(), s.group(1).decode(),
                                                _KEY_FRAME.search(record) is not None)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the nuScenes tables ({exc})", file=tables) from None
    return out


@lru_cache(maxsize=2)
def _lidar_key_frames(tables: str) -> dict[str, str]:
    """sample token → filename of its LIDAR_TOP key frame."""
    return {sample: name for name, (_, sample, key) in _folder_records(tables, LIDAR_FOLDER).items() if key}
