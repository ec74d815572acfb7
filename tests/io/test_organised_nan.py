"""Organised clouds that mark no-return cells with NaN x/y/z (PCL, ouster-ros ≥ 0.10, velodyne_pointcloud): read as
the grid's no-return cells, weather fills them like zero-marked cells, and cells still empty are written back NaN."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.errors import InputError
from roadview_noise.io.pointcloud import read_pointcloud, write_pointcloud
from roadview_noise.profiles.lidar import load_lidar_profile
from roadview_noise.registry import get_model

GRID = Path(__file__).resolve().parents[2] / "sample_data" / "lidar" / "os1-128-grid" / "seq0"


def _records(path: Path) -> tuple[bytes, np.ndarray]:
    """The header bytes and the binary records of the sample grid PCD (fields x y z intensity ring time)."""
    data = path.read_bytes()
    end = data.index(b"DATA binary\n") + len(b"DATA binary\n")
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2"), ("time", "<f4")])
    return data[:end], np.frombuffer(data[end:], dt).copy()


def _nan_marked(tmp_path: Path) -> tuple[Path, Path, np.ndarray]:
    """The sample grid scan as stored (zero-marked) and the same scan with NaN x/y/z (and NaN intensity, as
    velodyne_pointcloud writes) in its no-return cells."""
    zero = GRID / "000000.pcd"
    header, rec = _records(zero)
    empty = (rec["x"] == 0) & (rec["y"] == 0) & (rec["z"] == 0)
    assert 0 < empty.sum() < len(rec)
    for name in ("x", "y", "z", "intensity"):
        rec[name][empty] = np.nan
    marked = tmp_path / "nan.pcd"
    marked.write_bytes(header + rec.tobytes())
    return zero, marked, empty


def test_nan_cells_are_no_return_cells_and_written_back_as_nan(tmp_path):
    profile = load_lidar_profile(str(GRID / "lidar.yaml"))
    zero, marked, empty = _nan_marked(tmp_path)
    a = read_pointcloud(zero, sensor="lidar", profile=profile)
    b = read_pointcloud(marked, sensor="lidar", profile=profile)
    assert b.grid_shape == a.grid_shape and b.layout.no_return == "nan" and a.layout.no_return == "zero"
    np.testing.assert_array_equal(b.positions_m, a.positions_m)
    np.testing.assert_array_equal(b.fields["intensity"], a.fields["intensity"])

    model = get_model("rain.lidar")(rain_rate_mm_per_h=25)
    out_a, _ = apply_models([model], a, seed=3, key="f", sequence_id="s")
    out_b, _ = apply_models([model], b, seed=3, key="f", sequence_id="s")
    np.testing.assert_array_equal(out_b.positions_m, out_a.positions_m)
    filled = empty & out_b.positions_m.any(axis=1)
    assert filled.sum() > 0                                     # drop returns on the NaN-marked empty rays

    write_pointcloud(tmp_path / "a.pcd", out_a, effect="none")
    write_pointcloud(tmp_path / "b.pcd", out_b, effect="none")
    _, ra = _records(tmp_path / "a.pcd")
    _, rb = _records(tmp_path / "b.pcd")
    still_empty = ~out_b.positions_m.any(axis=1)
    assert still_empty.any()
    assert np.isnan(rb["x"][still_empty]).all() and (ra["x"][still_empty] == 0).all()
    np.testing.assert_array_equal(rb[~still_empty], ra[~still_empty])


def test_nan_marked_grid_round_trips_byte_for_byte(tmp_path):
    header, rec = _records(GRID / "000000.pcd")
    empty = (rec["x"] == 0) & (rec["y"] == 0) & (rec["z"] == 0)
    for name in ("x", "y", "z"):
        rec[name][empty] = np.nan
    (tmp_path / "in.pcd").write_bytes(header + rec.tobytes())
    cloud = read_pointcloud(tmp_path / "in.pcd", sensor="lidar")
    write_pointcloud(tmp_path / "out.pcd", cloud, effect="none")
    assert (tmp_path / "out.pcd").read_bytes() == (tmp_path / "in.pcd").read_bytes()


def test_nan_in_a_point_list_is_still_refused(tmp_path):
    header, rec = _records(GRID / "000000.pcd")
    rec = rec[rec["x"] != 0][:100]
    rec["z"][5] = np.nan
    header = header.replace(b"WIDTH 256\n", b"WIDTH 100\n").replace(b"HEIGHT 128\n", b"HEIGHT 1\n")
    header = header.replace(b"POINTS 32768\n", b"POINTS 100\n")
    (tmp_path / "list.pcd").write_bytes(header + rec.tobytes())
    with pytest.raises(InputError, match=r"1 of 100 points have NaN.*organised cloud"):
        read_pointcloud(tmp_path / "list.pcd", sensor="lidar")
