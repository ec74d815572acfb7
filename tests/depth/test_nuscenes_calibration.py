"""nuScenes photos with the dataset's own tables (`calibration: {nuscenes: VERSION}`): intrinsics, camera height
and pitch from calibrated_sensor.json, and the LIDAR_TOP key frame of the same sample as the paired scan. The
tables are written here in nuScenes' layout with the calibration of log n015-2018-07-24-11-22-45 (v1.0-mini,
scene-0061), the intrinsics scaled to a 160 × 90 image."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image
from scipy.spatial.transform import Rotation

from roadview_noise.depth.nuscenes import nuscenes_calibration
from roadview_noise.errors import InputError, RecipeError
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import run

CAM = {"token": "cam0", "sensor_token": "s-cam", "translation": [1.70079118954, 0.0159456324149, 1.51095763913],
       "rotation": [0.4998015430569128, -0.5030316162024876, 0.4997798114386805, -0.49960984002925593],
       "camera_intrinsic": [[126.6417203046554, 0.0, 81.58], [0.0, 126.6417203046554, 49.10], [0.0, 0.0, 1.0]]}
LIDAR = {"token": "lid0", "sensor_token": "s-lid", "translation": [0.985793, 0.0, 1.84019],
         "rotation": [0.706749235646644, -0.015300993788500868, 0.01739745181256607, -0.7070846669051719],
         "camera_intrinsic": []}
IMAGE = "samples/CAM_FRONT/n015-2018-07-24-11-22-45+0800__CAM_FRONT__1532402927612460.jpg"
SCAN = "samples/LIDAR_TOP/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
ROOT = Path(__file__).resolve().parents[2]
SWEEP = "sweeps/LIDAR_TOP/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927597000.pcd.bin"


def _pose(record) -> np.ndarray:
    """Sensor → ego by scipy (quaternion x, y, z, w order): the oracle of rvnoise's own conversion."""
    w, x, y, z = record["rotation"]
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    m[:3, 3] = record["translation"]
    return m


def _dataroot(tmp_path: Path) -> Path:
    root = tmp_path / "nuscenes"
    tables = root / "v1.0-mini"
    tables.mkdir(parents=True)
    records = [
        {"token": "sd-cam", "sample_token": "smp1", "ego_pose_token": "e1", "calibrated_sensor_token": "cam0",
         "timestamp": 1532402927612460, "fileformat": "jpg", "is_key_frame": True, "height": 90, "width": 160,
         "filename": IMAGE, "prev": "", "next": ""},
        {"token": "sd-sweep", "sample_token": "smp1", "ego_pose_token": "e2", "calibrated_sensor_token": "lid0",
         "timestamp": 1532402927597000, "fileformat": "pcd", "is_key_frame": False, "height": 0, "width": 0,
         "filename": SWEEP, "prev": "", "next": ""},
        {"token": "sd-lid", "sample_token": "smp1", "ego_pose_token": "e3", "calibrated_sensor_token": "lid0",
         "timestamp": 1532402927647951, "fileformat": "pcd", "is_key_frame": True, "height": 0, "width": 0,
         "filename": SCAN, "prev": "", "next": ""},
    ]
    (tables / "sample_data.json").write_text(json.dumps(records, indent=0))
    (tables / "calibrated_sensor.json").write_text(json.dumps([CAM, LIDAR], indent=0))
    (root / IMAGE).parent.mkdir(parents=True)
    y, x = np.mgrid[0:90, 0:160]
    Image.fromarray(np.dstack([x % 200, y * 2, (x + y) % 250]).astype(np.uint8)).save(root / IMAGE, quality=92)
    # the scan: flat ground (ego z = 0) 4…60 m ahead and a wall 25 m ahead, in the LiDAR frame
    gx, gy = np.meshgrid(np.linspace(4, 60, 120), np.linspace(-20, 20, 81))
    ground = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    wy, wz = np.meshgrid(np.linspace(-20, 20, 161), np.linspace(0.1, 3.0, 30))
    wall = np.c_[np.full(wy.size, 25.0), wy.ravel(), wz.ravel()]
    ego = np.vstack([ground, wall])
    lidar = (np.linalg.inv(_pose(LIDAR)) @ np.c_[ego, np.ones(len(ego))].T).T[:, :3]
    pts = np.c_[lidar, np.full(len(lidar), 10.0), np.zeros(len(lidar))].astype(np.float32)   # x y z i ring
    (root / SCAN).parent.mkdir(parents=True)
    pts.tofile(root / SCAN)
    return root


def test_calibration_from_the_tables(tmp_path):
    root = _dataroot(tmp_path)
    cal = nuscenes_calibration(root / "v1.0-mini", IMAGE)
    assert cal.intrinsics_px == pytest.approx((126.6417203046554, 126.6417203046554, 81.58, 49.10))
    assert cal.height_above_ground_m == pytest.approx(1.51095763913)
    axis = _pose(CAM)[:3, :3] @ [0, 0, 1]
    assert cal.pitch_rad == pytest.approx(-np.arcsin(axis[2]), abs=1e-9) and abs(cal.pitch_rad) < np.radians(1)
    assert cal.lidar_to_camera is None and cal.paired_scan is None
    paired = nuscenes_calibration(root / "v1.0-mini", IMAGE, lidar=True)
    assert paired.paired_scan == SCAN                                  # the key frame, not the sweep
    expected = np.linalg.inv(_pose(CAM)) @ _pose(LIDAR)
    np.testing.assert_allclose(paired.lidar_to_camera, expected, atol=1e-9)
    # a point on the road 10 m ahead of the camera projects below the image centre, near the centre column
    p = paired.lidar_to_camera @ np.linalg.inv(_pose(LIDAR)) @ [1.70079118954 + 10, 0, 0, 1]
    fx, fy, cx, cy = paired.intrinsics_px
    u, v = fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy
    assert abs(u - cx) < 2 and v - cy == pytest.approx(fy * 1.511 / 10, rel=0.05)


def test_unknown_image_names_the_table(tmp_path):
    root = _dataroot(tmp_path)
    with pytest.raises(InputError, match="no sample_data record with filename 'samples/CAM_BACK/x.jpg'"):
        nuscenes_calibration(root / "v1.0-mini", "samples/CAM_BACK/x.jpg")


def _recipe(tmp_path, inputs) -> Path:
    p = tmp_path / "r.yaml"
    p.write_text(yaml.safe_dump({"schema": "rvnoise.recipe/1", "seed": 1,
                                 "chain": [{"model": "fog.camera", "params": {"visibility_m": 50}}],
                                 "inputs": {"camera": "samples/CAM_*/*.jpg", **inputs}}))
    return p


def test_lidar_depth_with_the_tables_pairing(tmp_path):
    """The shipped example recipe, on a dataroot in nuScenes' layout (its tables' folder renamed)."""
    root = _dataroot(tmp_path)
    (root / "v1.0-mini").rename(root / "v1.0-trainval")
    recipe = ROOT / "recipes" / "examples" / "depth-lidar-nuscenes.yaml"
    s = run(load_recipe(recipe), root, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None,
            warn=lambda *_: None)
    assert s.failed == 0 and s.done == 1, s.failures
    line = next(e for e in read_manifest(tmp_path / "out" / "manifest.jsonl") if e.get("status") == "ok")
    depth = line["inputs"]["depth"]
    assert depth["source"] == "lidar" and depth["scan"] == SCAN and depth["returns_used"] > 500
    assert depth["ground_plane"]["camera_height_m"] == pytest.approx(1.51095763913)
    assert line["inputs"]["camera"]["fx_px"] == pytest.approx(126.6417, abs=1e-3)


def test_ground_plane_takes_the_camera_height_from_the_tables(tmp_path):
    root = _dataroot(tmp_path)
    recipe = _recipe(tmp_path, {"depth_source": "ground_plane", "calibration": {"nuscenes": "v1.0-mini"}})
    s = run(load_recipe(recipe), root, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None,
            warn=lambda *_: None)
    assert s.failed == 0
    line = next(e for e in read_manifest(tmp_path / "out" / "manifest.jsonl") if e.get("status") == "ok")
    assert line["inputs"]["depth"]["camera_height_m"] == pytest.approx(1.51095763913)


def test_a_scan_pattern_is_needed_without_the_tables(tmp_path):
    with pytest.raises(RecipeError, match="lidar_depth needs `scan:`"):
        load_recipe(_recipe(tmp_path, {"depth_source": "lidar", "lidar_depth": {},
                                       "calibration": "../calib/{stem}.txt"}))
