"""Generate the synthetic "ideal drive" sample data set: camera, raw Bayer, LiDAR (OS1-128, VLS-128) and 4D radar.

``generate(out_dir, frames=…, seed=…)`` writes one sequence (``seq0``) per sensor, a README.md describing every file,
and SHA256SUMS (``sha256sum -c`` format). Output bytes depend only on the arguments (and library versions).
The committed ``sample_data/`` is regenerated with ``python -m roadview_noise.sampledata.generate sample_data``
(the reduced preset ``rig.COMMITTED``).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from ..io.atomic import write_bytes_atomic
from ..io.depth import write_depth_exr
from ..io.image import write_image
from ..io.pointcloud import write_pointcloud
from ..io.raw import write_dng
from ..profiles.camera import lucid_triton_028s
from ..profiles.lidar import os1_128, vls_128
from ..types import CameraProfile, CloudLayout, ImageEncoding, LidarProfile, PointCloud, RadarProfile
from . import camera, lidar, radar
from .readme import readme_text
from .rig import (CAMERA_MOUNT_XY_M, COMMITTED, LIDAR_MOUNT_M, RADAR_MOUNT_M, RAW_BLACK_DN, RAW_PATTERN, RAW_WHITE_DN,
                  SEQUENCE)
from .scene import build_scene

#: file layouts (canonical name, file name, dtype); ``time`` is float32 seconds since the start of the revolution
XYZ = (("x", "x", "<f4"), ("y", "y", "<f4"), ("z", "z", "<f4"))
LIDAR_FIELDS = XYZ + (("intensity", "intensity", "<f4"), ("ring", "ring", "<u2"), ("time_s", "time", "<f4"))
KITTI_FIELDS = XYZ + (("intensity", "intensity", "<f4"),)
RADAR_FIELDS = XYZ + (("v_r_m_per_s", "v_r", "<f4"), ("rcs_dbsm", "rcs", "<f4"), ("snr_db", "snr", "<f4"))


def camera_profile(camera_size: tuple[int, int] | None) -> CameraProfile:
    """The Lucid Triton default, resampled to ``camera_size`` = (width, height) when given."""
    p = lucid_triton_028s()
    return p if camera_size is None else p.resized(*camera_size)


def lidar_profiles(columns: int | None) -> tuple[LidarProfile, LidarProfile]:
    """OS1-128 and VLS-128, both with ``columns`` azimuth steps per revolution when given."""
    profiles = os1_128(), vls_128()
    return profiles if columns is None else tuple(dataclasses.replace(p, columns=columns) for p in profiles)


def _camera_yaml(p: CameraProfile) -> str:
    keys = ("name", "width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "exposure_time_s", "pixel_pitch_m",
            "focal_length_m", "f_number", "height_above_ground_m")
    return yaml.safe_dump({k: getattr(p, k) for k in keys}, sort_keys=False)


def _lidar_yaml(p: LidarProfile) -> str:
    return yaml.safe_dump({"base": p.name, "columns": p.columns}, sort_keys=False)


def _radar_yaml(p: RadarProfile) -> str:
    return yaml.safe_dump({"base": p.name, "snr_threshold_db": p.snr_threshold_db}, sort_keys=False)


def _write_cloud(path: Path, cloud: PointCloud, fmt: str, fields) -> None:
    """Write the layout's fields only (binary PCD, or the fixed KITTI layout)."""
    keep = {k for k, _, _ in fields}
    cloud = dataclasses.replace(cloud, fields={k: v for k, v in cloud.fields.items() if k in keep},
                                layout=CloudLayout(fmt=fmt, fields=fields, pcd_data="binary"))
    write_pointcloud(path, cloud)


def generate(out_dir: Path, *, frames: int = 3, seed: int = 0, camera_size: tuple[int, int] | None = None,
             lidar_columns: int | None = None, progress: bool = False) -> dict:
    """Write ``frames`` frames of every sensor under ``out_dir``; defaults are the sensors' full resolutions.

    Returns a summary: ``out_dir``, ``files`` (relative paths, sorted), ``bytes``, ``frames``, ``seed``,
    ``camera_size``, ``lidar_columns`` and ``seconds``."""
    t0 = time.perf_counter()
    out = Path(out_dir)
    if frames < 1:
        raise ValueError(f"frames must be ≥ 1, got {frames}")
    scene = build_scene(seed)
    centres = radar.sample_centres(scene, seed)
    cam = camera_profile(camera_size)
    os1, vls = lidar_profiles(lidar_columns)
    radar_profile = radar.sample_radar_profile()
    d = {"camera": out / "camera" / SEQUENCE, "raw": out / "raw" / SEQUENCE,
         "os1": out / "lidar" / "os1-128" / SEQUENCE, "kitti": out / "lidar" / "os1-128-kitti" / SEQUENCE,
         "grid": out / "lidar" / "os1-128-grid" / SEQUENCE, "vls": out / "lidar" / "vls-128" / SEQUENCE,
         "radar": out / "radar" / SEQUENCE}
    written: list[Path] = []

    def text(path: Path, content: str) -> None:
        write_bytes_atomic(path, content.encode("utf-8"))
        written.append(path)

    for key in ("camera", "raw"):
        text(d[key] / "camera.yaml", _camera_yaml(cam))
    for key, prof in (("os1", os1), ("kitti", os1), ("grid", os1), ("vls", vls)):
        text(d[key] / "lidar.yaml", _lidar_yaml(prof))
    text(d["radar"] / "radar.yaml", _radar_yaml(radar_profile))

    for k in tqdm(range(frames), desc="sample-data", unit="frame", disable=not progress, file=sys.stderr):
        stem = f"{k:06d}"
        snap = scene.snapshot(scene.frame_time_s(k))
        ego = scene.ego_position_m(snap.t_s)
        rgb, depth = camera.render(snap, cam, ego + np.array([*CAMERA_MOUNT_XY_M, cam.height_above_ground_m]))
        dn = camera.mosaic(rgb, RAW_PATTERN, RAW_BLACK_DN, RAW_WHITE_DN)
        paths = [d["camera"] / f"{stem}.png", d["camera"] / f"{stem}_depth.exr", d["raw"] / f"{stem}.dng",
                 d["raw"] / f"{stem}_depth.exr"]
        write_image(paths[0], rgb, ImageEncoding())
        write_depth_exr(paths[1], depth)
        write_dng(paths[2], dn, RAW_PATTERN, RAW_BLACK_DN, RAW_WHITE_DN)
        write_depth_exr(paths[3], depth)

        s = lidar.scan(snap, os1, ego + np.array(LIDAR_MOUNT_M))
        returns = lidar.to_cloud(s, grid=False)
        _write_cloud(d["os1"] / f"{stem}.pcd", returns, "pcd", LIDAR_FIELDS)
        _write_cloud(d["kitti"] / f"{stem}.bin", returns, "kitti_bin", KITTI_FIELDS)
        _write_cloud(d["grid"] / f"{stem}.pcd", lidar.to_cloud(s, grid=True), "pcd", LIDAR_FIELDS)
        s = lidar.scan(snap, vls, ego + np.array(LIDAR_MOUNT_M))
        _write_cloud(d["vls"] / f"{stem}.pcd", lidar.to_cloud(s, grid=False), "pcd", LIDAR_FIELDS)
        _write_cloud(d["radar"] / f"{stem}.pcd", radar.detect(snap, centres, ego + np.array(RADAR_MOUNT_M),
                                                             radar_profile), "pcd", RADAR_FIELDS)
        written += paths + [d[key] / f"{stem}{'.bin' if key == 'kitti' else '.pcd'}"
                            for key in ("os1", "kitti", "grid", "vls", "radar")]

    summary = {"out_dir": str(out), "frames": frames, "seed": seed,
               "camera_size": [cam.width_px, cam.height_px], "lidar_columns": {p.name: p.columns for p in (os1, vls)}}
    text(out / "README.md", readme_text(summary, scene, cam, os1, vls, radar_profile))
    sums = "".join(f"{hashlib.sha256(p.read_bytes()).hexdigest()}  {p.relative_to(out).as_posix()}\n"
                   for p in sorted(written, key=lambda p: p.relative_to(out).as_posix()))
    text(out / "SHA256SUMS", sums)
    files = sorted(p.relative_to(out).as_posix() for p in written)
    return {**summary, "files": files, "bytes": sum((out / f).stat().st_size for f in files),
            "seconds": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m roadview_noise.sampledata.generate",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--frames", type=int, default=COMMITTED["frames"])
    ap.add_argument("--seed", type=int, default=COMMITTED["seed"])
    ap.add_argument("--camera-size", default="x".join(map(str, COMMITTED["camera_size"])),
                    help="WIDTHxHEIGHT, or 'full' for the Lucid Triton's 1936x1464 (default: the committed preset)")
    ap.add_argument("--lidar-columns", default=str(COMMITTED["lidar_columns"]),
                    help="azimuth columns of both LiDARs, or 'full' for 2048 (OS1) / 1800 (VLS)")
    a = ap.parse_args(argv)
    size = None if a.camera_size == "full" else tuple(int(v) for v in a.camera_size.lower().split("x"))
    columns = None if a.lidar_columns == "full" else int(a.lidar_columns)
    summary = generate(a.out_dir, frames=a.frames, seed=a.seed, camera_size=size, lidar_columns=columns,
                       progress=True)
    print(f"{len(summary['files'])} files, {summary['bytes'] / 1e6:.2f} MB, {summary['seconds']:.1f} s "
          f"in {summary['out_dir']}")
    return summary


if __name__ == "__main__":
    main()
