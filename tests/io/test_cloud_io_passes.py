"""Point-cloud reading and writing in fewer passes (issue 19): the fast checks agree with the plain ones on every
kind of value, a cloud read from bytes at hand equals one read from its file, a written cloud's bytes are the
packed records and are hashed from memory, and the runner reads a cloud once for its sha256 and its reader."""

from __future__ import annotations

import hashlib
import warnings

import numpy as np
import pytest

from roadview_noise import runner
from roadview_noise.io import pointcloud as pc
from roadview_noise.errors import InputError
from roadview_noise.io.atomic import staged_writes, write_bytes_atomic
from roadview_noise.manifest import sha256_file
from roadview_noise.types import CloudLayout, PointCloud

SPECIAL = [np.nan, np.inf, -np.inf, 1e308, -1e308, 0.0, -0.0, 3.5e38]


def _positions(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(0, 40, (n, 3))
    cells = rng.integers(0, n, 40), rng.integers(0, 3, 40)
    p[cells] = rng.choice(SPECIAL, 40)
    return p


@pytest.mark.parametrize("seed", range(6))
def test_non_finite_rows_are_the_rows_with_a_nan_or_infinite_coordinate(seed):
    p = _positions(500, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                      # no RuntimeWarning reaches the manifest's warnings
        assert np.array_equal(pc._non_finite_rows(p), ~np.isfinite(p).all(axis=1))
        finite = np.nan_to_num(p, nan=1.0, posinf=1e308, neginf=-1e308)  # finite, yet its total overflows
        assert not pc._non_finite_rows(finite).any()


@pytest.mark.parametrize("seed", range(6))
def test_farthest_coordinate_is_the_largest_finite_magnitude(seed):
    with np.errstate(over="ignore"):
        xyz = _positions(300, seed).astype(np.float32)
    expected = float(np.max(np.abs(np.nan_to_num(xyz, nan=0.0, posinf=0.0, neginf=0.0)), initial=0.0))
    assert pc._farthest_m(xyz) == expected
    clean = np.nan_to_num(xyz, nan=-7.0, posinf=-7.0, neginf=-7.0) - 1e3  # all finite: from the extremes
    assert pc._farthest_m(clean) == float(np.abs(clean).max())
    assert pc._farthest_m(np.zeros((0, 3), np.float32)) == 0.0


def _cloud(fmt: str, mode: str, n: int = 700) -> PointCloud:
    rng = np.random.default_rng(1)
    fields = {"intensity": rng.random(n).astype(np.float32) * 900}
    spec = [("x", "x", "<f4"), ("y", "y", "<f4"), ("z", "z", "<f4"), ("intensity", "intensity", "<f4")]
    if fmt != "kitti_bin":
        fields["ring"] = rng.integers(0, 128, n).astype(np.uint16)
        spec.append(("ring", "ring", "<u2" if mode != "binary_big_endian" else ">u2"))
    layout = CloudLayout(fmt=fmt, fields=tuple(spec), pcd_data=mode)
    return PointCloud(positions_m=rng.normal(0, 30, (n, 3)), fields=fields, sensor="lidar", layout=layout)


def _packed(cloud: PointCloud, order: str) -> bytes:
    """The records as the writers packed them before (a structured array's ``tobytes``)."""
    columns, _ = pc.output_columns(cloud, cloud.layout, effect="none")
    arr = np.empty(len(cloud), [(f"f{i}", np.dtype(dt).newbyteorder(order)) for i, (_, dt, _) in enumerate(columns)])
    for i, (_, _, col) in enumerate(columns):
        arr[f"f{i}"] = col
    return arr.tobytes()


@pytest.mark.parametrize("name,fmt,mode,order", [
    ("a.pcd", "pcd", "binary", "<"), ("a.ply", "ply", "binary_little_endian", "<"),
    ("a.ply", "ply", "binary_big_endian", ">"), ("a.bin", "kitti_bin", "binary", "<")])
def test_a_written_cloud_is_its_packed_records_and_is_hashed_from_memory(tmp_path, name, fmt, mode, order):
    cloud = _cloud(fmt, mode)
    with staged_writes() as stage:
        pc.write_pointcloud(tmp_path / name, cloud, effect="none")
        (tmp, _), = stage.files
        kept = stage.written.get(tmp)
        assert kept is not None and kept.readonly          # no second read for the manifest
        assert stage.sha256_of(tmp) == sha256_file(tmp)
    stage.commit()
    data = (tmp_path / name).read_bytes()
    assert data.endswith(_packed(cloud, order))
    back = pc.read_pointcloud(tmp_path / name)
    assert np.array_equal(back.positions_m, cloud.positions_m.astype(np.float32).astype(np.float64))
    assert np.array_equal(back.fields["intensity"], cloud.fields["intensity"])


@pytest.mark.parametrize("name,fmt,mode", [("a.pcd", "pcd", "binary"), ("a.ply", "ply", "binary_little_endian"),
                                           ("a.bin", "kitti_bin", "binary")])
def test_a_cloud_without_points_is_written_as_its_header_alone(tmp_path, name, fmt, mode):
    """(A chain may remove every point of a list.)"""
    with staged_writes() as stage:
        pc.write_pointcloud(tmp_path / name, _cloud(fmt, mode, n=0), effect="none")
        (tmp, _), = stage.files
        assert stage.sha256_of(tmp) == sha256_file(tmp)
    stage.commit()
    data = (tmp_path / name).read_bytes()
    assert data == b"" if fmt == "kitti_bin" else data.endswith(b"binary\n" if fmt == "pcd" else b"end_header\n")


def test_writable_bytes_are_not_kept_for_their_hash(tmp_path):
    """A buffer its owner may still change is hashed from the file, not from memory."""
    with staged_writes() as stage:
        write_bytes_atomic(tmp_path / "a.bin", bytearray(b"abc"))
        write_bytes_atomic(tmp_path / "b.bin", memoryview(bytearray(b"abc")))
        assert all(stage.sha256_of(tmp) is None for tmp, _ in stage.files)
    stage.commit()


@pytest.mark.parametrize("name,fmt,mode", [("a.pcd", "pcd", "binary"), ("a.pcd", "pcd", "binary_compressed"),
                                           ("a.ply", "ply", "binary_big_endian"), ("a.bin", "kitti_bin", "binary")])
def test_a_cloud_read_from_bytes_at_hand_is_the_cloud_read_from_its_file(tmp_path, name, fmt, mode):
    path = tmp_path / name
    pc.write_pointcloud(path, _cloud(fmt, mode), effect="none")
    a, b = pc.read_pointcloud(path), pc.read_pointcloud(path, data=path.read_bytes())
    assert np.array_equal(a.positions_m, b.positions_m) and a.layout == b.layout
    assert a.fields.keys() == b.fields.keys()
    for k in a.fields:
        assert np.array_equal(a.fields[k], b.fields[k]) and a.fields[k].dtype == b.fields[k].dtype
        assert b.fields[k].flags.c_contiguous


def test_the_runner_reads_a_cloud_once_for_its_sha256_and_its_reader(tmp_path, monkeypatch):
    path = tmp_path / "a.bin"
    path.write_bytes(np.random.default_rng(2).normal(size=(3000, 4)).astype("<f4").tobytes())
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert runner.sha256_input(path, whole=True) == (digest, path.read_bytes())
    assert runner.sha256_input(path) == (digest, None)                       # streamed: an image, a depth map
    monkeypatch.setattr(runner, "READ_ONCE_MAX_BYTES", 1000)
    assert runner.sha256_input(path, whole=True) == (digest, None)           # too large to hold: streamed


def test_a_bin_range_check_looks_at_the_coordinates_only(tmp_path):
    """A large value in another column (a timestamp in µs) passes; coordinates beyond any LiDAR's range do not."""
    rng = np.random.default_rng(3)
    table = np.column_stack([rng.normal(0, 30, (500, 3)), rng.random(500)]).astype("<f4")
    table[7, 3] = 1.7e15
    (tmp_path / "a.bin").write_bytes(table.tobytes())
    assert pc.read_pointcloud(tmp_path / "a.bin").fields["intensity"][7] == np.float32(1.7e15)
    table[9, 1] = -3.0e5
    (tmp_path / "b.bin").write_bytes(table.tobytes())
    with pytest.raises(InputError, match="coordinates reach 3e[+]05 m"):
        pc.read_pointcloud(tmp_path / "b.bin")
