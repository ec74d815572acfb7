"""LiDAR clouds as ROS drivers lay them out, built synthetically: ouster-ros' organised ``ouster_ros::Point``
clouds (``x y z intensity t reflectivity ring ambient range``, NaN or zero x/y/z for no-return cells) saved by
PCL with its ``_`` padding fields (COUNT > 1)."""

from __future__ import annotations

import numpy as np

from roadview_noise.compound import apply_models
from roadview_noise.io.pointcloud import read_pointcloud, write_pointcloud
from roadview_noise.profiles.lidar import load_lidar_profile
from roadview_noise.registry import get_model

OUSTER_POINT = np.dtype({"names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
                         "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
                         "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32], "itemsize": 48})
PCL_HEADER = ("VERSION 0.7\nFIELDS x y z _ intensity t reflectivity ring ambient _ range _\n"
              "SIZE 4 4 4 1 4 4 2 2 2 1 4 1\nTYPE F F F U F U U U U U U U\nCOUNT 1 1 1 4 1 1 1 1 1 2 1 12\n"
              "WIDTH {w}\nHEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")


def ouster_ros_pcd(path, beams: int = 16, columns: int = 256, no_return: float = np.nan, seed: int = 0):
    """An organised ouster-ros cloud (a row per beam, staggered columns) saved as PCL saves it; ~30 % no-return
    cells (range 0, x/y/z ``no_return``). Returns the stored records."""
    rng = np.random.default_rng(seed)
    el = np.deg2rad(np.linspace(16.6, -16.6, beams))[:, None]
    az = -2 * np.pi * np.arange(columns)[None, :] / columns
    r = rng.uniform(3, 60, (beams, columns))
    hit = rng.random((beams, columns)) > 0.3
    rec = np.zeros((beams, columns), OUSTER_POINT)
    for name, v in zip("xyz", (np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0 * az)):
        rec[name] = np.where(hit, r * v, no_return)
    rec["intensity"] = np.where(hit, rng.uniform(2, 40, hit.shape), 0)          # signal photons: faint returns
    rec["t"] = np.arange(columns)[None, :] * 97_656                            # ns since the scan began
    rec["reflectivity"] = np.where(hit, rng.integers(1, 100, hit.shape), 0)
    rec["ring"] = np.arange(beams)[:, None]
    rec["range"] = np.where(hit, np.rint(r * 1000), 0)
    path.write_bytes(PCL_HEADER.format(w=columns, h=beams, n=rec.size).encode() + rec.tobytes())
    return rec


def test_organised_cloud_with_pcl_padding_fields_loses_returns_to_rain(tmp_path):
    """Returns rain removes from an organised cloud are emptied in every field, PCL's multi-byte ``_`` padding
    (COUNT 4, read as an N × 4 field) included. Before: every such ouster-ros PCD failed rain or snow with
    ``internal error ValueError: operands could not be broadcast together with shapes (N,) () (N,4)``."""
    rec = ouster_ros_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd")
    cloud = cloud.replace(profile=load_lidar_profile("os1-128"))
    out, records = apply_models([get_model("rain.lidar")(rain_rate_mm_per_h=50.0)], cloud, seed=1, key="k",
                                sequence_id="s", metrics=False)
    assert records[0].diagnostics["removed"] > 0 and out.grid_shape == rec.shape
    write_pointcloud(tmp_path / "out.pcd", out)
    back = read_pointcloud(tmp_path / "out.pcd")
    assert back.grid_shape == rec.shape
    np.testing.assert_array_equal(back.fields["ring"], rec["ring"].ravel())


def test_empty_cells_of_another_sensors_grid_take_its_beams_directions(tmp_path):
    """A 16-beam organised cloud (±16.6°) read with the default OS1-128 profile (128 beams, warned): fog's returns
    on its no-return cells lie on the cloud's own beams, measured from its returns (elevation and column azimuth
    within 0.01°). Before: on the profile's first 16 beams (+22° … +17°, up to 33° off; a real OS-0-32 ouster-ros
    cloud's fog points up to 56° off)."""
    rec = ouster_ros_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd").replace(profile=load_lidar_profile("os1-128"))
    out, records = apply_models([get_model("fog.lidar")(visibility_m=30.0)], cloud, seed=1, key="k",
                                sequence_id="s", metrics=False)
    empty = np.isnan(rec["x"]).ravel()
    filled = empty & out.positions_m.any(axis=1)
    assert filled.sum() > 0.5 * empty.sum()
    p = out.positions_m[filled]
    beams, columns = rec.shape
    el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    cell = np.flatnonzero(filled)
    want_el = np.linspace(16.6, -16.6, beams)[cell // columns]
    want_az = -360.0 * (cell % columns) / columns
    np.testing.assert_allclose(el, want_el, atol=0.01)
    np.testing.assert_allclose((az - want_az + 180) % 360 - 180, 0, atol=0.01)
