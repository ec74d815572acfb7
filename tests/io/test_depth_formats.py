"""Depth formats users have: KITTI depth PNG and Cityscapes disparity PNG against hand-made files with known values,
format recognition, and the calibration files that come with them (Cityscapes JSON, KITTI calib, rvnoise YAML)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from roadview_noise.depth.calibration import load_calibration
from roadview_noise.errors import InputError
from roadview_noise.io.depth import depth_format, read_depth, write_carla_depth_png, write_depth_exr
from roadview_noise.types import CameraProfile

# a 6×8 camera whose principal point is the pixel (row 2, column 3): the ray factor there is exactly 1
PROFILE = CameraProfile("t", 8, 6, fx_px=4.0, fy_px=5.0, cx_px=3.0, cy_px=2.0)


def _png16(path, values):
    assert cv2.imwrite(str(path), np.asarray(values, dtype=np.uint16))
    return path


def _ray(u, v, p=PROFILE):
    return math.sqrt(1 + ((u - p.cx_px) / p.fx_px) ** 2 + ((v - p.cy_px) / p.fy_px) ** 2)


def test_kitti_depth_png_known_values(tmp_path):
    p = np.zeros((6, 8), np.uint16)
    p[2, 3] = 256 * 10            # 10 m at the principal point
    p[2, 4] = 2560 + 128          # 10.5 m
    p[5, 7] = 65535               # 255.996 m, the largest code
    p[0, 0] = 1                   # 1/256 m
    got = read_depth(_png16(tmp_path / "0000000005.png", p), fmt="kitti", profile=PROFILE)
    assert got[2, 3] == pytest.approx(10.0, rel=1e-7)
    assert got[2, 4] == pytest.approx(10.5 * _ray(4, 2), rel=1e-6)
    assert got[5, 7] == pytest.approx(65535 / 256 * _ray(7, 5), rel=1e-6)
    assert got[0, 0] == pytest.approx(_ray(0, 0) / 256, rel=1e-6)
    assert np.isnan(got).sum() == p.size - 4                          # 0 = no LiDAR return = hole


def test_cityscapes_disparity_known_values(tmp_path):
    baseline, fx = 0.209313, 4.0
    p = np.zeros((6, 8), np.uint16)
    p[2, 3] = 1 + 256 * 2         # disparity 2 px → z = B·fx/2
    p[2, 4] = 1 + 64              # disparity 0.25 px
    p[1, 1] = 1                   # disparity 0: infinitely far (sky)
    got = read_depth(_png16(tmp_path / "x_disparity.png", p), fmt="cityscapes", profile=PROFILE,
                     baseline_m=baseline)
    assert got[2, 3] == pytest.approx(baseline * fx / 2, rel=1e-6)
    assert got[2, 4] == pytest.approx(baseline * fx / 0.25 * _ray(4, 2), rel=1e-6)
    assert np.isinf(got[1, 1])
    assert np.isnan(got).sum() == p.size - 3                          # p = 0 is an invalid measurement
    with pytest.raises(InputError, match="baseline"):
        read_depth(tmp_path / "x_disparity.png", fmt="cityscapes", profile=PROFILE)


@settings(max_examples=40, deadline=None)
@given(arrays(np.uint16, st.tuples(st.integers(1, 20), st.integers(1, 20))))
def test_png16_decoders_property(tmp_path_factory, codes):
    """Any size, any codes: KITTI z = p/256 and Cityscapes z = B·fx/((p − 1)/256), 0 → NaN (planar: K = identity
    scale, the ray factor is checked above)."""
    path = _png16(tmp_path_factory.mktemp("d") / "d.png", codes)
    h, w = codes.shape
    flat = CameraProfile("flat", w, h, fx_px=1e9, fy_px=1e9, cx_px=0.0, cy_px=0.0)   # ray factor 1 to 1e-16
    kitti = read_depth(path, fmt="kitti", profile=flat)
    valid = codes > 0
    np.testing.assert_array_equal(np.isnan(kitti), ~valid)
    np.testing.assert_allclose(kitti[valid], codes[valid] / 256.0, rtol=1e-6)
    city = read_depth(path, fmt="cityscapes", profile=flat, baseline_m=2e-9)         # B·fx = 2
    np.testing.assert_array_equal(np.isnan(city), ~valid)
    with np.errstate(divide="ignore"):
        expected = 2.0 / ((codes[valid].astype(float) - 1) / 256.0)
    np.testing.assert_allclose(city[valid], expected, rtol=1e-6)


def test_format_recognition(tmp_path):
    _png16(tmp_path / "a_disparity.png", np.ones((2, 2)))
    _png16(tmp_path / "0000000005.png", np.ones((2, 2)))
    write_carla_depth_png(tmp_path / "carla.png", np.ones((2, 2)))
    write_depth_exr(tmp_path / "d.exr", np.ones((2, 2), np.float32))
    assert depth_format(tmp_path / "a_disparity.png") == "cityscapes"
    assert depth_format(tmp_path / "0000000005.png") == "kitti"
    assert depth_format(tmp_path / "carla.png") == "carla"
    assert depth_format(tmp_path / "d.exr") == "exr"
    assert depth_format(tmp_path / "0000000005.png", "cityscapes") == "cityscapes"    # stated wins
    cv2.imwrite(str(tmp_path / "grey8.png"), np.ones((2, 2), np.uint8))
    with pytest.raises(InputError, match="16-bit grey"):
        depth_format(tmp_path / "grey8.png")


def test_cityscapes_json_calibration(tmp_path):
    cam = {"extrinsic": {"baseline": 0.209313, "pitch": 0.038, "roll": 0.0, "x": 1.7, "y": 0.1, "yaw": -0.0195,
                         "z": 1.22},
           "intrinsic": {"fx": 2262.52, "fy": 2265.3017905988554, "u0": 1096.98, "v0": 513.137}}
    (tmp_path / "c_camera.json").write_text(json.dumps(cam))
    cal = load_calibration(tmp_path / "c_camera.json")
    assert cal.intrinsics_px == (2262.52, 2265.3017905988554, 1096.98, 513.137)
    assert (cal.baseline_m, cal.height_above_ground_m, cal.pitch_rad) == (0.209313, 1.22, 0.038)
    assert cal.lidar_to_camera is None


def test_kitti_calibration_matches_the_devkit_projection(tmp_path):
    """x = P2 · R0_rect · Tr_velo_to_cam · X (KITTI devkit) equals K · (lidar_to_camera · X) with the camera-2 centre
    as origin, and the range is measured from that centre."""
    rng = np.random.default_rng(0)
    k = np.array([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]])
    t2 = np.array([0.06, -0.0003, 0.0027])                          # camera 2 centre offset (rectified frame)
    p2 = np.hstack([k, (k @ t2)[:, None]])
    r0 = cv2.Rodrigues(np.array([0.01, -0.004, 0.002]))[0]
    tr = np.hstack([cv2.Rodrigues(np.array([1.2, -1.2, 1.2]))[0], [[-0.004], [-0.076], [-0.27]]])
    def row(name, m):
        return f"{name}: {' '.join(f'{v:.17e}' for v in np.ravel(m))}"

    lines = [row("P0", np.zeros(12)), row("P2", p2), row("R0_rect", r0), row("Tr_velo_to_cam", tr)]
    (tmp_path / "000123.txt").write_text("\n".join(lines) + "\n")
    cal = load_calibration(tmp_path / "000123.txt")
    pts = rng.uniform(-20, 20, (50, 3)) + [30, 0, 0]
    homog = np.hstack([pts, np.ones((50, 1))])
    devkit = (p2 @ np.vstack([np.hstack([r0, [[0], [0], [0]]]), [0, 0, 0, 1]]) @ np.vstack([tr, [0, 0, 0, 1]])
              @ homog.T)
    devkit_px = devkit[:2] / devkit[2]
    pc = (cal.lidar_to_camera @ homog.T)[:3]
    fx, fy, cx, cy = cal.intrinsics_px
    np.testing.assert_allclose(fx * pc[0] / pc[2] + cx, devkit_px[0], rtol=1e-9)
    np.testing.assert_allclose(fy * pc[1] / pc[2] + cy, devkit_px[1], rtol=1e-9)
    expected_range = np.linalg.norm((r0 @ (tr @ homog.T)) + t2[:, None], axis=0)
    np.testing.assert_allclose(np.linalg.norm(pc, axis=0), expected_range, rtol=1e-12)


def test_kitti_cam_to_cam_gives_intrinsics_and_size(tmp_path):
    (tmp_path / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\nS_rect_02: 1.242000e+03 3.750000e+02\n"
        "P_rect_02: 7.215377e+02 0 6.095593e+02 4.485728e+01 0 7.215377e+02 1.728540e+02 2.163791e-01 0 0 1 "
        "2.745884e-03\n")
    cal = load_calibration(tmp_path / "calib_cam_to_cam.txt")
    assert cal.size_px == (1242, 375) and cal.lidar_to_camera is None
    fx, fy, cx, cy = cal.intrinsics_for(621, 187.5)                 # half size: f and (c + ½) halve
    assert (fx, cx) == pytest.approx((721.5377 / 2, (609.5593 + 0.5) / 2 - 0.5))


def test_yaml_calibration_and_errors(tmp_path):
    (tmp_path / "c.yaml").write_text("K: [[100, 0, 50], [0, 100, 40], [0, 0, 1]]\nwidth_px: 101\nheight_px: 81\n"
                                     "lidar_to_camera: {rotation: [[0, -1, 0], [0, 0, -1], [1, 0, 0]], "
                                     "translation_m: [0, -0.9, -0.3]}\npitch_deg: 2\n")
    cal = load_calibration(tmp_path / "c.yaml")
    assert cal.intrinsics_px == (100, 100, 50, 40) and cal.pitch_rad == pytest.approx(math.radians(2))
    np.testing.assert_allclose(cal.lidar_to_camera @ [1, 2, 3, 1], [-2, -3.9, 0.7, 1])
    (tmp_path / "bad.yaml").write_text("lidar_to_camera: {rotation: [[1, 1, 0], [0, 1, 0], [0, 0, 1]], "
                                       "translation_m: [0, 0, 0]}\n")
    with pytest.raises(InputError, match="not a rigid transform"):
        load_calibration(tmp_path / "bad.yaml")
    (tmp_path / "typo.yaml").write_text("lidar_to_cam: []\n")
    with pytest.raises(InputError, match="unknown calibration keys"):
        load_calibration(tmp_path / "typo.yaml")
