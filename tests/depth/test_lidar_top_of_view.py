"""Sky above a LiDAR-depth column only where the scan saw nothing above it: a synthetic KITTI-like scan (HDL-64E
beams −24.8°…+2°, the lasers 0.2 m above the scanner origin, as KITTI's velodyne points show) of a near wall
(8 m), a far wall (30 m, taller than the scan sees) and an open road between them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadview_noise.depth.calibration import load_calibration
from roadview_noise.depth.lidar import at_top_of_view, column_spacing_px, lidar_depth

LASER_HEIGHT_M = 0.2         # the laser above the point-cloud origin
LIDAR_HEIGHT_M = 1.73        # KITTI's Velodyne above the road
W, H, F = 400, 150, 300.0    # camera: 67° horizontal field of view, optical axis level


def _scan() -> np.ndarray:
    elevation = np.radians(np.linspace(-24.8, 2.0, 64))[:, None]
    azimuth = np.radians(np.arange(-40.0, 40.0, 0.09))[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                     np.sin(elevation)), axis=-1).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, -(LIDAR_HEIGHT_M + LASER_HEIGHT_M) / d[:, 2], np.inf)
        wall_x = np.where(d[:, 1] > np.sin(np.radians(5)), 8.0,                       # left: near wall
                          np.where(d[:, 1] < -np.sin(np.radians(5)), 30.0, np.inf))  # right: far wall
        t_wall = wall_x / d[:, 0]
    t = np.minimum(t_ground, t_wall)
    keep = t < 120.0                                                   # the scanner's reach
    return np.array([0.0, 0.0, LASER_HEIGHT_M]) + d[keep] * t[keep, None]


def _camera_depth():
    to_camera = np.eye(4)
    to_camera[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]          # LiDAR x fwd, y left, z up → OpenCV
    return lidar_depth(_scan(), to_camera, (F, F, W / 2 - 0.5, H / 2 - 0.5), W, H)


def test_far_top_beam_returns_are_the_top_of_the_view():
    """The +2° beam reaches atan(tan 2° + 0.2/r): 3.43° on the wall at 8 m, 2.38° on the one at 30 m — both are
    the top of the view, a lower beam on the road is not."""
    r = np.array([8.0, 30.0, 110.0, 10.0, 12.0, 16.0, 20.0, 25.0, 9.0, 35.0, 60.0])
    beam_deg = np.array([2.0, 2.0, -1.0, 2.0, 2.0, 2.0, 2.0, 2.0, -5.0, -5.0, -5.0])
    e = np.arctan(np.tan(np.radians(beam_deg)) + LASER_HEIGHT_M / r)
    assert at_top_of_view(r, e, np.radians(0.5)).tolist() == (beam_deg == 2.0).tolist()
    assert (e[:2] < e[:2].max() - np.radians(0.5)).tolist() == [False, True]    # one threshold misses 30 m


def test_no_sky_above_a_wall_the_scan_does_not_see_the_top_of():
    depth, valid, notes = _camera_depth()
    top_rows = slice(0, 20)                                            # > 10° above the axis: above every beam
    far_wall = depth[top_rows, W - 60:W - 10]                           # right: the 30 m wall
    near_wall = depth[top_rows, 10:60]
    road = depth[top_rows, W // 2 - 10:W // 2 + 10]                   # ±2°: open road, nothing above it
    assert np.isfinite(far_wall).all() and np.isfinite(near_wall).all()
    assert not valid[top_rows, W - 60:W - 10].any()                    # extended upwards, not measured
    assert np.isinf(road).all()
    assert notes["sky_fraction"] < 0.2


# KITTI object benchmark calibration of the 2011_09_26 drives (the devkit's calib/*.txt layout); P2 equals the
# first three rows of mmdetection3d's demo/data/kitti/000008.txt.
KITTI_CALIB = """P2: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 \
2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03
R0_rect: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 \
4.351614e-03 9.999631e-01
Tr_velo_to_cam: 7.533745e-03 -9.999714e-01 -6.166020e-04 -4.069766e-03 1.480249e-02 7.280733e-04 -9.998902e-01 \
-7.631618e-02 9.998621e-01 7.523790e-03 1.480755e-02 -2.717806e-01
"""
REAL_KITTI = Path("/work/realdata/mmdet3d/demo/data/kitti")


def test_real_kitti_scan_puts_no_sky_over_the_houses(tmp_path):
    """mmdetection3d's KITTI 000008 (houses and trees above the HDL-64E's +2° all along the street): sky on < 5 %
    of the image (the old single threshold: 25 %)."""
    if not (REAL_KITTI / "000008.bin").is_file():
        pytest.skip("/work/realdata (mmdetection3d's KITTI demo frame) absent")
    (tmp_path / "000008.txt").write_text(KITTI_CALIB)
    cal = load_calibration(tmp_path / "000008.txt")
    points = np.fromfile(REAL_KITTI / "000008.bin", np.float32).reshape(-1, 4)[:, :3]
    depth, valid, notes = lidar_depth(points, cal.lidar_to_camera, cal.intrinsics_for(1242, 375), 1242, 375)
    assert notes["returns_used"] > 10000
    assert notes["sky_fraction"] < 0.05


def test_sparse_scan_lines_crossing_the_rows_keep_the_sky():
    """nuScenes-like: 32 beams (−30°…+10.67°) whose scan lines cross the image rows (camera rolled 4° against
    the LiDAR), a building at 6 m on the left, open road elsewhere. Neighbours in an image row are mostly other
    beams (real CAM_FRONT frame: 90th-percentile gap 711 px): the column spacing must not spread the building's
    top over the frame."""
    elevation = np.radians(np.linspace(-30.67, 10.67, 32))[:, None]
    azimuth = np.radians(np.arange(-40.0, 40.0, 0.16))[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                     np.sin(elevation)), axis=-1).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, -1.84 / d[:, 2], np.inf)
        t_wall = np.where(d[:, 1] > np.sin(np.radians(25)), 6.0 / d[:, 0], np.inf)
    t = np.minimum(t_ground, t_wall)
    points = d[t < 70] * t[t < 70, None]
    roll = np.radians(4.0)
    to_camera = np.eye(4)
    to_camera[:3, :3] = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]]) \
        @ [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    depth, _, notes = lidar_depth(points, to_camera, (F, F, W / 2 - 0.5, H / 2 - 0.5), W, H)
    assert np.isinf(depth[:10, W // 2:]).mean() > 0.9                   # open road: sky above
    assert np.isfinite(depth[12:40, :30]).all()                        # the building


def test_column_spacing_is_bounded_by_the_median_gap():
    """Rows of a sparse scan (the real nuScenes CAM_FRONT frame: gaps 9 px median, 711 px 90th percentile): the
    beams' own neighbours set the spacing, not the crossings of other beams far along the row."""
    rows = np.repeat(np.arange(50), 4)
    cols = np.tile([100, 109, 118, 900], 50)                           # gaps 9, 9, 782 per row
    assert column_spacing_px(rows, cols) == 36
    dense = np.tile(np.arange(0, 400, 8), 20), np.repeat(np.arange(20), 50)
    assert column_spacing_px(dense[1], dense[0]) == 8
