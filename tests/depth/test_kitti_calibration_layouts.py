"""KITTI-style calibration files as the datasets ship them: KITTI's object benchmark ``calib/*.txt`` (the values of
the 2011_09_26 drives, as mmdetection3d's KITTI test infos state them), Waymo converted to KITTI format by
mmdetection3d (``P0``–``P4``, ``Tr_velo_to_cam_0``–``_4``), and mmdetection3d's demo ``000008.txt`` (P2 as a bare
4 × 4, not a calibration file)."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.depth.calibration import load_calibration
from roadview_noise.errors import InputError
from roadview_noise.recipe import parse_recipe

P2 = np.array([[721.5377, 0.0, 609.5593, 44.85728], [0.0, 721.5377, 172.854, 0.2163791], [0.0, 0.0, 1.0, 0.002745884]])
R0 = np.array([[0.9999239, 0.00983776, -0.007445048], [-0.009869795, 0.9999421, -0.004278459],
               [0.007402527, 0.004351614, 0.9999631]])
TR = np.array([[0.007533745, -0.9999714, -0.000616602, -0.004069766],
               [0.01480249, 0.0007280733, -0.9998902, -0.07631618],
               [0.9998621, 0.00752379, 0.01480755, -0.2717806]])


def _line(key, m) -> str:
    return f"{key}: " + " ".join(f"{v:.9e}" for v in np.ravel(m)) + "\n"


def _pixel(cal, point):
    fx, fy, cx, cy = cal.intrinsics_px
    p = cal.lidar_to_camera @ np.r_[point, 1.0]
    return np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy])


def test_kitti_object_calib_projects_like_the_devkit(tmp_path):
    path = tmp_path / "000008.txt"
    path.write_text(_line("P0", np.c_[P2[:, :3], [0, 0, 0]]) + _line("P2", P2) + _line("R0_rect", R0)
                    + _line("Tr_velo_to_cam", TR) + _line("Tr_imu_to_velo", TR))
    cal = load_calibration(path)
    for point in ([10.0, 2.0, -1.5], [30.0, -5.0, 0.5], [6.0, 0.0, -1.7]):
        x = P2 @ np.r_[R0 @ (TR @ np.r_[point, 1.0]), 1.0]          # the devkit: P2 · R0_rect · Tr_velo_to_cam · X
        np.testing.assert_allclose(_pixel(cal, point), x[:2] / x[2], atol=1e-6)


def test_waymo_kitti_format_takes_the_camera_s_own_transform(tmp_path):
    k = np.array([[2055.6, 0, 939.7, 0], [0, 2055.6, 641.1, 0], [0, 0, 1, 0]])
    text = "".join(_line(f"P{i}", k) for i in range(5)) + _line("R0_rect", np.eye(3))
    rotations = {}
    for i in range(5):
        yaw = np.radians(45.0 * i)
        r = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        rotations[i] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]]) @ r.T      # vehicle → camera i
        text += _line(f"Tr_velo_to_cam_{i}", np.c_[rotations[i], [0.0, -1.5, 0.3 * i]])
    path = tmp_path / "0000000.txt"
    path.write_text(text)
    for i in (0, 3, 4):
        cal = load_calibration(path, kitti_camera=i)
        np.testing.assert_allclose(cal.lidar_to_camera[:3, :3], rotations[i], atol=1e-9)
        np.testing.assert_allclose(cal.lidar_to_camera[:3, 3], [0.0, -1.5, 0.3 * i], atol=1e-9)
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "chain": [{"model": "fog.camera"}],
                           "inputs": {"camera": "**/image_4/*.png", "kitti_camera": 4}}, source="r.yaml")
    assert recipe.spec.inputs.kitti_camera == 4


def test_a_bare_matrix_file_is_not_taken_for_a_calibration(tmp_path):
    path = tmp_path / "000008.txt"
    path.write_text(" ".join(f"{v}" for v in np.r_[P2.ravel(), [0, 0, 0, 1]]) + "\n")
    with pytest.raises(InputError, match="KITTI calibration has none of P2, P_rect_02"):
        load_calibration(path)
