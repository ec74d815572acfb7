"""Depth from what users have: the paired LiDAR scan of the sample drive against its rendered depth, the ground
plane against its closed form, and a monocular ONNX model built here (onnxruntime at full resolution)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from roadview_noise.depth.calibration import load_calibration
from roadview_noise.depth.ground_plane import ground_plane_range
from roadview_noise.depth.lidar import lidar_depth, project_returns
from roadview_noise.io.depth import read_depth
from roadview_noise.io.image import read_image
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.physics import srgb
from roadview_noise.profiles.camera import load_camera_profile

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_data"
CALIBRATION = ROOT / "recipes" / "examples" / "calibration" / "sample-drive.yaml"


def _sample_frame(stem):
    if not SAMPLE.is_dir():
        pytest.skip("sample_data/ missing")
    profile = load_camera_profile(str(SAMPLE / "camera" / "seq0" / "camera.yaml"))
    cloud = read_pointcloud(SAMPLE / "lidar" / "os1-128" / "seq0" / f"{stem}.pcd")
    reference = read_depth(SAMPLE / "camera" / "seq0" / f"{stem}_depth.exr")
    image, _, _ = read_image(SAMPLE / "camera" / "seq0" / f"{stem}.png")
    return profile, cloud.positions_m, reference, image


@pytest.mark.parametrize("densify", ["nearest", "bilateral"])
@pytest.mark.parametrize("stem", ["000000", "000001", "000002"])
def test_lidar_depth_agrees_with_the_rendered_depth(stem, densify):
    """Acceptance: the OS1-128 scan projected into the camera with the documented calibration YAML agrees with the
    rendered range, median relative error < 5 % where LiDAR returns exist (measured ≈ 0.2 %); over every pixel with
    a finite depth in both it stays < 5 % too (≈ 0.4–0.5 %), and sky agrees on > 85 % of the pixels."""
    profile, points, reference, image = _sample_frame(stem)
    cal = load_calibration(CALIBRATION)
    k = (profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px)
    depth, valid, notes = lidar_depth(points, cal.lidar_to_camera, k, profile.width_px, profile.height_px,
                                      densify=densify, guide_srgb=srgb.encode(image).astype(np.float32),
                                      ground=(profile.height_above_ground_m, 0.0))
    rows, cols, _, _ = project_returns(points, cal.lidar_to_camera, k, profile.width_px, profile.height_px)
    ref = reference[rows, cols]
    finite = np.isfinite(ref)
    at_returns = np.abs(depth[rows, cols][finite] - ref[finite]) / ref[finite]
    assert finite.sum() > 4000 and np.median(at_returns) < 0.05
    both = np.isfinite(reference) & np.isfinite(depth)
    assert np.median(np.abs(depth[both] - reference[both]) / reference[both]) < 0.05
    assert np.mean(np.isinf(depth) == np.isinf(reference)) > 0.85
    assert notes["returns_used"] > 4000 and 0.5 < notes["valid_fraction"] < 1


def test_lidar_projection_oracle():
    """A point 10 m ahead and 1 m left of a camera looking along x projects where the pinhole says, with its range
    from the camera centre; points behind the camera or off the image are dropped; the nearest of two wins."""
    to_cam = np.eye(4)
    to_cam[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    to_cam[:3, 3] = [0.0, -0.5, 0.0]
    # camera frame (x right, y down, z forward) of the first point: (−1, −0.5 − 0.5, 10); the last one is on the same
    # ray twice as far: hidden
    pts = np.array([[10.0, 1.0, 0.5], [-5.0, 0.0, 0.0], [1.0, 50.0, 0.0], [20.0, 2.0, 1.5]])
    rows, cols, rng, elev = project_returns(pts, to_cam, (100.0, 100.0, 50.0, 40.0), 101, 81)
    assert list(zip(rows, cols)) == [(30, 40)] and rng[0] == pytest.approx(math.sqrt(1 + 1 + 100), rel=1e-6)
    assert elev[0] == pytest.approx(math.atan2(0.5, math.hypot(10, 1)))


def test_ground_plane_closed_form():
    """Centre column: ``h / sin(atan((v − c_y)/f_y) + θ)``; any pixel: the intersection of its ray, rotated by the
    pitch, with the plane 1.4 m below the camera; at and above the horizon: the constant distance."""
    fx, fy, cx, cy, w, h = 500.0, 520.0, 199.0, 150.0, 399, 300
    height, pitch = 1.4, math.radians(3.0)
    d = ground_plane_range((fx, fy, cx, cy), w, h, camera_height_m=height, pitch_rad=pitch, sky_distance_m=80.0)
    u = 199
    for v in (160, 200, 299):
        expected = height / math.sin(math.atan((v - cy) / fy) + pitch)
        assert d[v, u] == pytest.approx(min(expected, 80.0), rel=1e-5)
    horizon = cy - fy * math.tan(pitch)                              # the horizon row
    assert (d[: int(math.floor(horizon)) + 1] == 80.0).all()
    c, s = math.cos(pitch), math.sin(pitch)
    rotation = np.array([[1, 0, 0], [0, c, s], [0, -s, c]])           # camera → level frame (y down)
    for v, u in ((250, 10), (180, 390), (299, 0)):
        ray = rotation @ np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
        t = height / ray[1]
        assert d[v, u] == pytest.approx(min(t * np.linalg.norm(ray), 80.0), rel=1e-5)


# --- ONNX monocular model ------------------------------------------------------------------------------------------


def test_onnx_model_depth_full_resolution(tmp_path, tiny_depth_model):
    pytest.importorskip("onnxruntime")
    from roadview_noise.depth.monocular import model_depth

    model = tiny_depth_model(tmp_path / "m.onnx")
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (37, 53, 3)).astype(np.float32)
    mean, std = (0.5, 0.4, 0.3), (0.2, 0.25, 0.5)
    depth, notes = model_depth(str(model), image, mean=mean, std=std, scale_m=0.5)
    norm = (image - np.array(mean)) / np.array(std)
    expected = 0.5 * (20 * norm[..., 0] + 10 * norm[..., 1] + 5 * norm[..., 2] + 2)
    expected[expected <= 0] = np.nan                                  # non-positive output = hole
    np.testing.assert_allclose(depth, expected, rtol=1e-5, atol=1e-5)
    assert notes["output_px"] == [53, 37] and "resized_to_image" not in notes


def test_onnx_model_with_a_fixed_input_size_is_resized(tmp_path, tiny_depth_model):
    pytest.importorskip("onnxruntime")
    from roadview_noise.depth.monocular import model_depth

    model = tiny_depth_model(tmp_path / "fixed.onnx", weights=(0.0, 0.0, 0.0), bias=7.0, fixed_hw=(16, 16))
    depth, notes = model_depth(str(model), np.zeros((30, 40, 3), np.float32))
    assert depth.shape == (30, 40) and np.allclose(depth, 7.0) and notes["resized_to_image"]
