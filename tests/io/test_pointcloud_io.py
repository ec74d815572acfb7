"""Point-cloud I/O: round trips of every format, mode and dtype; canonical names; the effect code; bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import pytest

from roadview_noise.errors import InputError
from roadview_noise.io.pointcloud import effect_sidecar_path, read_pointcloud, write_pointcloud
from roadview_noise.provenance import Effect
from roadview_noise.types import PointCloud

# An Ouster-like PCD with PCL padding ("_", COUNT 4), a 3-vector, float64 and signed fields.
OUSTER = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_", "(4,)|u1"), ("intensity", "<f4"), ("t", "<u4"),
          ("reflectivity", "<u2"), ("ring", "<u2"), ("normal", "(3,)<f4"), ("_", "|u1"), ("range", "<u4"),
          ("gain", "<f8"), ("offset", "|i1"), ("delta", "<i2"), ("stamp", "<u8"), ("count", "<i4")]
PCD_TYPE = {"f": "F", "u": "U", "i": "I"}


def _records(spec, n, seed=0, grid=None):
    rng = np.random.default_rng(seed)
    dtype = np.dtype([(f"f{i}", dt) for i, (_, dt) in enumerate(spec)])
    arr = np.zeros(n, dtype)
    for i, (_, dt) in enumerate(spec):
        d = np.dtype(dt)
        base = d.base
        shape = (n,) + d.shape
        if base.kind == "f":
            arr[f"f{i}"] = rng.normal(0, 30, shape).astype(base)
        else:
            info = np.iinfo(base)
            arr[f"f{i}"] = rng.integers(info.min, info.max, shape, dtype=base, endpoint=True)
    return arr


def _pcd_header(spec, n, mode, width=None, height=1):
    fields = [(np.dtype(dt).base, np.dtype(dt).shape) for _, dt in spec]
    return "\n".join([
        "# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7",
        "FIELDS " + " ".join(name for name, _ in spec),
        "SIZE " + " ".join(str(b.itemsize) for b, _ in fields),
        "TYPE " + " ".join(PCD_TYPE[b.kind] for b, _ in fields),
        "COUNT " + " ".join(str(s[0] if s else 1) for _, s in fields),
        f"WIDTH {width or n}", f"HEIGHT {height}", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", f"DATA {mode}",
        ""]).encode()


def _write_pcd(path, spec, arr, mode="binary", **kw):
    if mode == "binary":
        body = arr.tobytes()
    else:                                  # ascii, written independently of the module under test
        cols = []
        for i, (_, dt) in enumerate(spec):
            col = arr[f"f{i}"].reshape(len(arr), -1)
            fmt = "%.9g" if np.dtype(dt).base == np.float32 else "%.17g" if np.dtype(dt).base.kind == "f" else "%d"
            cols += [[fmt % v for v in col[:, j]] for j in range(col.shape[1])]
        body = ("\n".join(" ".join(row) for row in zip(*cols)) + "\n").encode()
    path.write_bytes(_pcd_header(spec, len(arr), mode, **kw) + body)


def _assert_matches_records(cloud, spec, arr):
    assert [(name, dt) for _, name, dt in cloud.layout.fields] == [(n, np.dtype(dt).base.str if not np.dtype(dt).shape
                                                                    else dt) for n, dt in spec]
    for (key, _, _), i in zip(cloud.layout.fields, range(len(spec))):
        expected = arr[f"f{i}"]
        got = cloud.positions_m[:, "xyz".index(key)] if key in "xyz" else cloud.fields[key]
        if key not in "xyz":
            assert got.dtype == expected.dtype, key
        np.testing.assert_array_equal(got, expected, err_msg=key)


def _assert_same_cloud(a, b):
    assert a.layout == b.layout and a.grid_shape == b.grid_shape and a.sensor == b.sensor
    np.testing.assert_array_equal(a.positions_m, b.positions_m)
    assert list(a.fields) == list(b.fields)
    for k in a.fields:
        assert a.fields[k].dtype == b.fields[k].dtype, k
        np.testing.assert_array_equal(a.fields[k], b.fields[k], err_msg=k)


@pytest.mark.parametrize("mode", ["binary", "ascii"])
def test_pcd_reads_every_field_in_order_with_dtype(tmp_path, mode):
    arr = _records(OUSTER, 257)
    _write_pcd(tmp_path / "o.pcd", OUSTER, arr, mode)
    cloud = read_pointcloud(tmp_path / "o.pcd")
    _assert_matches_records(cloud, OUSTER, arr)
    assert cloud.layout.fmt == "pcd" and cloud.layout.pcd_data == mode and cloud.positions_m.dtype == np.float64
    keys = [k for k, _, _ in cloud.layout.fields]
    assert keys == ["x", "y", "z", "_", "intensity", "t", "reflectivity", "ring", "normal", "_#2", "range", "gain",
                    "offset", "delta", "stamp", "count"]
    assert cloud.fields["normal"].shape == (257, 3)


@pytest.mark.parametrize("src_mode", ["ascii", "binary"])
@pytest.mark.parametrize("out_mode", ["ascii", "binary", "binary_compressed"])
def test_pcd_roundtrip_every_mode(tmp_path, src_mode, out_mode):
    arr = _records(OUSTER, 300, seed=1)
    _write_pcd(tmp_path / "in.pcd", OUSTER, arr, src_mode)
    cloud = read_pointcloud(tmp_path / "in.pcd")
    cloud = dataclasses.replace(cloud, layout=dataclasses.replace(cloud.layout, pcd_data=out_mode))
    write_pointcloud(tmp_path / "out.pcd", cloud)
    back = read_pointcloud(tmp_path / "out.pcd")
    _assert_same_cloud(back, cloud)
    write_pointcloud(tmp_path / "again.pcd", back)
    assert (tmp_path / "again.pcd").read_bytes() == (tmp_path / "out.pcd").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.pcd", "in.pcd", "out.pcd"]


def test_binary_pcd_roundtrip_is_byte_identical(tmp_path):
    arr = _records(OUSTER, 64, seed=2)
    _write_pcd(tmp_path / "in.pcd", OUSTER, arr)
    write_pointcloud(tmp_path / "out.pcd", read_pointcloud(tmp_path / "in.pcd"))
    assert (tmp_path / "out.pcd").read_bytes() == (tmp_path / "in.pcd").read_bytes()


def test_binary_compressed_interoperates_with_open3d(tmp_path):
    spec = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("t", "<u4"), ("ring", "<u2")]
    arr = _records(spec, 5000, seed=3)
    arr["f5"] = np.repeat(np.arange(50, dtype=np.uint16), 100)            # compressible column
    _write_pcd(tmp_path / "in.pcd", spec, arr)
    o3d.t.io.write_point_cloud(str(tmp_path / "o3d.pcd"), o3d.t.io.read_point_cloud(str(tmp_path / "in.pcd")),
                               write_ascii=False, compressed=True)
    assert b"DATA binary_compressed" in (tmp_path / "o3d.pcd").read_bytes()[:400]
    cloud = read_pointcloud(tmp_path / "o3d.pcd")                         # open3d writes its own field order
    assert cloud.layout.pcd_data == "binary_compressed"
    ref = read_pointcloud(tmp_path / "in.pcd")
    np.testing.assert_array_equal(cloud.positions_m, ref.positions_m)
    for k in ref.fields:
        assert cloud.fields[k].dtype == ref.fields[k].dtype
        np.testing.assert_array_equal(cloud.fields[k], ref.fields[k])

    write_pointcloud(tmp_path / "ours.pcd", cloud)                        # and open3d reads ours
    size_raw = (tmp_path / "in.pcd").stat().st_size
    assert (tmp_path / "ours.pcd").stat().st_size < size_raw              # really compressed
    back = o3d.t.io.read_point_cloud(str(tmp_path / "ours.pcd"))
    np.testing.assert_array_equal(back.point.positions.numpy(), ref.positions_m.astype(np.float32))
    for k in ("intensity", "t", "ring"):
        np.testing.assert_array_equal(back.point[k].numpy()[:, 0], ref.fields[k])


def test_organised_pcd_keeps_grid(tmp_path):
    spec = OUSTER[:3] + [("ring", "<u2")]
    arr = _records(spec, 4 * 6, seed=4)
    arr["f0"][[3, 7]] = arr["f1"][[3, 7]] = arr["f2"][[3, 7]] = 0            # no-return cells
    _write_pcd(tmp_path / "g.pcd", spec, arr, width=6, height=4)
    cloud = read_pointcloud(tmp_path / "g.pcd")
    assert cloud.grid_shape == (4, 6)
    write_pointcloud(tmp_path / "out.pcd", cloud.drop(np.arange(24) == 5))
    text = (tmp_path / "out.pcd").read_bytes()[:300]
    assert b"WIDTH 6\nHEIGHT 4" in text
    assert read_pointcloud(tmp_path / "out.pcd").grid_shape == (4, 6)


@pytest.mark.parametrize("name,sensor,columns,fmt,canonical", [
    ("k.bin", "lidar", 4, "kitti_bin", ["x", "y", "z", "intensity"]),
    ("n.pcd.bin", "lidar", 5, "nuscenes_bin", ["x", "y", "z", "intensity", "ring"]),
    ("v.bin", "radar", 7, "vod_bin", ["x", "y", "z", "rcs_dbsm", "v_r_m_per_s", "v_r_comp_m_per_s", "time_s"]),
])
def test_bin_formats_roundtrip(tmp_path, name, sensor, columns, fmt, canonical):
    table = np.random.default_rng(5).normal(0, 20, (111, columns)).astype(np.float32)
    if fmt == "vod_bin":                   # v_r_compensated − v_r = v_ego·r̂ (radar_formats.check_vod_columns)
        table[:, 5] = table[:, 4] + 4.0 * table[:, 0] / np.linalg.norm(table[:, :3], axis=1)
    table.tofile(tmp_path / name)
    cloud = read_pointcloud(tmp_path / name, sensor=sensor)
    assert cloud.layout.fmt == fmt and [k for k, _, _ in cloud.layout.fields] == canonical
    assert all(dt == "<f4" for _, _, dt in cloud.layout.fields) and cloud.sensor == sensor
    np.testing.assert_array_equal(cloud.positions_m, table[:, :3])
    for j, key in enumerate(canonical[3:], start=3):
        np.testing.assert_array_equal(cloud.fields[key], table[:, j])
    write_pointcloud(tmp_path / ("out_" + name), cloud)
    assert (tmp_path / ("out_" + name)).read_bytes() == (tmp_path / name).read_bytes()


def _ply(path, mode, props, table):
    header = ["ply", f"format {mode} 1.0", "comment CARLA-style", f"element vertex {len(table)}"]
    header += [f"property {t} {n}" for n, t in props] + ["end_header", ""]
    if mode == "ascii":
        body = "\n".join(" ".join("%.9g" % v for v in row) for row in table).encode() + b"\n"
    else:
        order = "<" if mode == "binary_little_endian" else ">"
        body = table.astype(order + "f4").tobytes()
    path.write_bytes("\n".join(header).encode() + body)


@pytest.mark.parametrize("mode", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_carla_ply_roundtrip(tmp_path, mode):
    table = np.random.default_rng(6).normal(0, 20, (50, 4)).astype(np.float32)
    _ply(tmp_path / "c.ply", mode, [("x", "float32"), ("y", "float32"), ("z", "float32"), ("I", "float32")], table)
    cloud = read_pointcloud(tmp_path / "c.ply")
    assert cloud.layout.fmt == "ply" and cloud.layout.pcd_data == mode
    assert [(k, n) for k, n, _ in cloud.layout.fields] == [("x", "x"), ("y", "y"), ("z", "z"), ("intensity", "I")]
    np.testing.assert_array_equal(cloud.fields["intensity"], table[:, 3])
    write_pointcloud(tmp_path / "out.ply", cloud)
    _assert_same_cloud(read_pointcloud(tmp_path / "out.ply"), cloud)
    assert b"property float I\n" in (tmp_path / "out.ply").read_bytes()[:200]


def test_ply_read_by_open3d(tmp_path):
    table = np.random.default_rng(7).normal(0, 20, (30, 4)).astype(np.float32)
    _ply(tmp_path / "c.ply", "binary_little_endian", [("x", "float"), ("y", "float"), ("z", "float"),
                                                      ("I", "float")], table)
    write_pointcloud(tmp_path / "out.ply", read_pointcloud(tmp_path / "c.ply"))
    o = o3d.io.read_point_cloud(str(tmp_path / "out.ply"))
    np.testing.assert_allclose(np.asarray(o.points), table[:, :3], rtol=1e-6)


def test_rehearse_radar_pcd_maps_to_canonical(tmp_path):
    spec = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("velocity", "<f4"), ("snr", "<f4"), ("power", "<f4"),
            ("rcs", "<f4")]
    arr = _records(spec, 20, seed=8)
    _write_pcd(tmp_path / "r.pcd", spec, arr)
    cloud = read_pointcloud(tmp_path / "r.pcd", sensor="radar")
    assert list(cloud.fields) == ["v_r_m_per_s", "snr_db", "power_db", "rcs_dbsm"]
    np.testing.assert_array_equal(cloud.fields["snr_db"], arr["f4"])
    write_pointcloud(tmp_path / "out.pcd", cloud)
    assert (tmp_path / "out.pcd").read_bytes() == (tmp_path / "r.pcd").read_bytes()


def test_field_map_overrides_defaults(tmp_path):
    spec = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("signal", "<u2"), ("reflectivity", "<u1"), ("chan", "<u1")]
    arr = _records(spec, 10, seed=9)
    _write_pcd(tmp_path / "m.pcd", spec, arr)
    default = read_pointcloud(tmp_path / "m.pcd")
    assert list(default.fields) == ["intensity", "reflectivity", "chan"]          # signal wins by priority
    mapped = read_pointcloud(tmp_path / "m.pcd", field_map={"reflectivity": "intensity", "chan": "ring"})
    assert list(mapped.fields) == ["signal", "intensity", "ring"]
    np.testing.assert_array_equal(mapped.fields["intensity"], arr["f4"])
    write_pointcloud(tmp_path / "out.pcd", mapped)
    assert (tmp_path / "out.pcd").read_bytes() == (tmp_path / "m.pcd").read_bytes()

    with pytest.raises(InputError, match="'nope'") as err:
        read_pointcloud(tmp_path / "m.pcd", field_map={"nope": "ring"})
    assert "m.pcd" in str(err.value)
    spec[3] = ("intensity", "<u2")
    _write_pcd(tmp_path / "clash.pcd", spec, arr)
    with pytest.raises(InputError, match="clashes"):
        read_pointcloud(tmp_path / "clash.pcd", field_map={"reflectivity": "intensity"})


def _added_points(cloud, k=3):
    return cloud.concat(np.full((k, 3), 5.0), {"intensity": np.full(k, 0.25)})     # effect ADDED on the last k


def test_effect_appended_to_pcd_and_ply_as_its_own_field(tmp_path):
    spec = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2"), ("label", "<u4")]
    records = _records(spec, 12, seed=10)
    records["f5"] = np.arange(12, dtype=np.uint32) | (7 << 16)                   # a user's class | instance << 16
    _write_pcd(tmp_path / "l.pcd", spec, records)
    cloud = _added_points(read_pointcloud(tmp_path / "l.pcd"))
    assert cloud.effect.tolist() == [Effect.KEPT] * 12 + [Effect.ADDED] * 3
    assert write_pointcloud(tmp_path / "out.pcd", cloud) == [tmp_path / "out.pcd"]
    back = read_pointcloud(tmp_path / "out.pcd")
    assert back.layout.fields[-1] == ("rv_effect", "rv_effect", "|u1") and back.fields["rv_effect"].dtype == np.uint8
    np.testing.assert_array_equal(back.fields["rv_effect"], cloud.effect)
    assert back.fields["label"].dtype == np.uint32                               # the user's label untouched
    np.testing.assert_array_equal(back.fields["label"][:12], records["f5"])
    np.testing.assert_array_equal(back.fields["ring"][-3:], 0)                    # zero-filled by concat
    write_pointcloud(tmp_path / "none.pcd", cloud, effect="none")
    assert "rv_effect" not in read_pointcloud(tmp_path / "none.pcd").fields
    # an input that already has rv_effect (an earlier run's output) keeps it; the new code gets its own name
    again = _added_points(back, k=1)
    write_pointcloud(tmp_path / "again.pcd", again)
    fields = read_pointcloud(tmp_path / "again.pcd").fields
    np.testing.assert_array_equal(fields["rv_effect"][:15], cloud.effect)
    assert fields["rv_effect_2"].tolist() == [Effect.KEPT] * 15 + [Effect.ADDED]

    table = np.random.default_rng(11).normal(0, 20, (12, 4)).astype(np.float32)
    _ply(tmp_path / "c.ply", "binary_little_endian", [("x", "float"), ("y", "float"), ("z", "float"),
                                                      ("I", "float")], table)
    cloud = _added_points(read_pointcloud(tmp_path / "c.ply"))
    write_pointcloud(tmp_path / "out.ply", cloud)
    np.testing.assert_array_equal(read_pointcloud(tmp_path / "out.ply").fields["rv_effect"], cloud.effect)


def test_effect_of_bin_goes_to_a_sidecar_named_after_the_whole_file(tmp_path):
    """``x.bin`` and ``x.pcd.bin`` in one folder get distinct sidecars, neither a SemanticKITTI ``.label``."""
    for name, width in (("000001.bin", 4), ("000001.pcd.bin", 5)):
        np.random.default_rng(12).normal(0, 20, (9, width)).astype("<f4").tofile(tmp_path / name)
        cloud = _added_points(read_pointcloud(tmp_path / name))
        written = write_pointcloud(tmp_path / "out" / name, cloud)
        assert written == [tmp_path / "out" / name, tmp_path / "out" / (name + ".rv_effect")]
        assert effect_sidecar_path(tmp_path / "out" / name) == written[1]
        np.testing.assert_array_equal(np.fromfile(written[1], np.uint8), cloud.effect)
        back = read_pointcloud(tmp_path / "out" / name)
        assert len(back) == 12 and "rv_effect" not in back.fields
        np.testing.assert_array_equal(back.positions_m[-3:], 5.0)
        assert write_pointcloud(tmp_path / "none" / name, cloud, effect="none") == [tmp_path / "none" / name]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "000001.bin", "000001.bin.rv_effect", "000001.pcd.bin", "000001.pcd.bin.rv_effect"]
    assert sorted(p.name for p in (tmp_path / "none").iterdir()) == ["000001.bin", "000001.pcd.bin"]


def test_integer_fields_rounded_and_clipped_at_writing(tmp_path):
    spec = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("signal", "<u2"), ("offset", "|i1")]
    _write_pcd(tmp_path / "i.pcd", spec, _records(spec, 4, seed=13))
    cloud = read_pointcloud(tmp_path / "i.pcd")
    cloud = cloud.with_fields(intensity=np.array([70000.0, -3.0, 2.6, 7.5]),
                              offset=np.array([300, -300, 5, -5], np.int64))
    write_pointcloud(tmp_path / "out.pcd", cloud)
    back = read_pointcloud(tmp_path / "out.pcd")
    assert back.fields["intensity"].tolist() == [65535, 0, 3, 8] and back.fields["intensity"].dtype == np.uint16
    assert back.fields["offset"].tolist() == [127, -128, 5, -5]
    with pytest.raises(ValueError, match="NaN"):
        write_pointcloud(tmp_path / "nan.pcd", cloud.with_fields(intensity=np.array([np.nan, 1, 2, 3])))


def test_writer_refuses_layout_mismatch(tmp_path):
    spec = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")]
    _write_pcd(tmp_path / "w.pcd", spec, _records(spec, 4, seed=14))
    cloud = read_pointcloud(tmp_path / "w.pcd")
    with pytest.raises(ValueError, match=r"missing from cloud: \['intensity'\]"):
        write_pointcloud(tmp_path / "a.pcd", dataclasses.replace(cloud, fields={}))
    with pytest.raises(ValueError, match=r"not in layout: \['snr_db'\]"):
        write_pointcloud(tmp_path / "b.pcd", cloud.with_fields(snr_db=np.zeros(4)))
    with pytest.raises(ValueError, match="suffix"):
        write_pointcloud(tmp_path / "c.ply", cloud)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.pcd"]


def test_cloud_without_layout_gets_a_default(tmp_path):
    cloud = PointCloud(np.arange(12, dtype=np.float64).reshape(4, 3),
                       {"intensity": np.arange(4, dtype=np.uint16), "label": np.ones(4, np.uint16)}, "lidar",
                       effect=np.ones(4, np.uint8))
    write_pointcloud(tmp_path / "d.pcd", cloud)
    back = read_pointcloud(tmp_path / "d.pcd")
    assert [(k, dt) for k, _, dt in back.layout.fields] == [("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                                            ("intensity", "<u2"), ("label", "<u2"),
                                                            ("rv_effect", "|u1")]
    write_pointcloud(tmp_path / "d.bin", dataclasses.replace(cloud, fields={"intensity": cloud.fields["intensity"]}))
    assert (tmp_path / "d.bin").stat().st_size == 4 * 16 and (tmp_path / "d.bin.rv_effect").stat().st_size == 4


# --- bad input: every error names the file ------------------------------------------------------------------------


def _expect(path, match, **kw):
    with pytest.raises(InputError, match=match) as err:
        read_pointcloud(path, **kw)
    assert path.name in str(err.value)


def test_truncated_pcd(tmp_path):
    spec = OUSTER[:3] + [("intensity", "<f4")]
    arr = _records(spec, 100, seed=15)
    _write_pcd(tmp_path / "t.pcd", spec, arr)
    (tmp_path / "t.pcd").write_bytes((tmp_path / "t.pcd").read_bytes()[:-5])
    _expect(tmp_path / "t.pcd", r"truncated PCD: header says 100 points × 16 bytes")

    _write_pcd(tmp_path / "a.pcd", spec, arr, "ascii")
    (tmp_path / "a.pcd").write_bytes((tmp_path / "a.pcd").read_bytes()[:-40])
    _expect(tmp_path / "a.pcd", "truncated ascii")

    _write_pcd(tmp_path / "c.pcd", spec, arr)
    cloud = read_pointcloud(tmp_path / "c.pcd")
    write_pointcloud(tmp_path / "z.pcd", dataclasses.replace(
        cloud, layout=dataclasses.replace(cloud.layout, pcd_data="binary_compressed")))
    (tmp_path / "z.pcd").write_bytes((tmp_path / "z.pcd").read_bytes()[:-10])
    _expect(tmp_path / "z.pcd", "truncated PCD")


def test_corrupt_compressed_pcd(tmp_path):
    spec = OUSTER[:3]
    arr = _records(spec, 50, seed=16)
    _write_pcd(tmp_path / "c.pcd", spec, arr)
    cloud = read_pointcloud(tmp_path / "c.pcd")
    write_pointcloud(tmp_path / "z.pcd", dataclasses.replace(
        cloud, layout=dataclasses.replace(cloud.layout, pcd_data="binary_compressed")))
    data = bytearray((tmp_path / "z.pcd").read_bytes())
    header_end = data.index(b"binary_compressed\n") + len(b"binary_compressed\n")
    data[header_end + 8] = 0xFF                                   # back-reference before the start of the output
    (tmp_path / "z.pcd").write_bytes(bytes(data))
    _expect(tmp_path / "z.pcd", "LZF")


def test_compressed_pcd_with_nul_padding_reads_as_without(tmp_path):
    """PCL 1.x left some KiB of NULs after binary_compressed data (its test clouds car6.pcd, milk_color.pcd, the
    grabber frames): the data state their size, so the padding is no point; anything else after them is refused."""
    spec = OUSTER[:3] + [("intensity", "<f4")]
    _write_pcd(tmp_path / "c.pcd", spec, _records(spec, 40, seed=17))
    cloud = read_pointcloud(tmp_path / "c.pcd")
    write_pointcloud(tmp_path / "z.pcd", dataclasses.replace(
        cloud, layout=dataclasses.replace(cloud.layout, pcd_data="binary_compressed")))
    data = (tmp_path / "z.pcd").read_bytes()
    (tmp_path / "pad.pcd").write_bytes(data + b"\0" * 3913)
    padded = read_pointcloud(tmp_path / "pad.pcd")
    np.testing.assert_array_equal(padded.positions_m, cloud.positions_m)
    np.testing.assert_array_equal(padded.fields["intensity"], cloud.fields["intensity"])
    (tmp_path / "junk.pcd").write_bytes(data + b"\0" * 100 + b"\x01")
    _expect(tmp_path / "junk.pcd", "the point count does not match the data")


def test_bad_bin_size_nan_empty_and_suffix(tmp_path):
    np.zeros(4 * 7 + 3, np.uint8).tofile(tmp_path / "odd.bin")
    _expect(tmp_path / "odd.bin", "not a multiple of the 16-byte point")
    np.zeros(5 * 7 + 1, np.float32).tofile(tmp_path / "vod.bin")
    _expect(tmp_path / "vod.bin", "size 144 bytes fits neither View-of-Delft.s radar .bin", sensor="radar")

    table = np.ones((5, 4), np.float32)
    table[1, 0], table[3, 2] = np.nan, np.inf
    table.tofile(tmp_path / "nan.bin")
    _expect(tmp_path / "nan.bin", "2 of 5 points have NaN or infinite coordinates")

    (tmp_path / "empty.bin").write_bytes(b"")
    _expect(tmp_path / "empty.bin", r"the file is empty \(0 bytes\)")
    (tmp_path / "empty.pcd").write_bytes(_pcd_header(OUSTER[:3], 0, "binary"))
    _expect(tmp_path / "empty.pcd", r"empty \(0 points\)")

    (tmp_path / "cloud.xyz").write_text("1 2 3\n")
    _expect(tmp_path / "cloud.xyz", "unknown point-cloud suffix")
    (tmp_path / "junk.pcd").write_bytes(b"\x00\xff" * 20)
    _expect(tmp_path / "junk.pcd", "not a PCD")
    (tmp_path / "junk.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement face 3\nproperty list uchar int v\nend_header\n")
    _expect(tmp_path / "junk.ply", "list property")
    _expect(tmp_path / "missing.pcd", "cannot read")
