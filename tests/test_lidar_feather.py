"""Argoverse 2 LiDAR sweeps (``sensors/lidar/<ns>.feather``), built synthetically with the real sweeps' layout: an
Arrow/Feather v2 table x, y, z halffloat (vehicle frame), intensity uint8, laser_number uint8, offset_ns int32, the
pandas metadata their writer left, two record batches; read and written in place with pyarrow, profile av2-vlp32c."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from roadview_noise.errors import InputError
from roadview_noise.io.pointcloud import read_pointcloud, write_pointcloud
from roadview_noise.manifest import read_manifest
from roadview_noise.profiles.lidar import AV2_SENSOR_ORIGIN_M, load_lidar_profile
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run

pa = pytest.importorskip("pyarrow")
import pyarrow.feather  # noqa: E402

VLP32C_DEG = (-25, -1, -1.667, -15.639, -11.31, 0, -0.667, -8.843, -7.254, 0.333, -0.333, -6.148, -5.333, 1.333,
              0.667, -4, -4.667, 1.667, 1, -3.667, -3.333, 3.333, 2.333, -2.667, -3, 7, 4.667, -2.333, -2, 15, 10.333,
              -1.333)                   # the VLP-32C manual's vertical angles, by laser ID


def av2_sweep(path, firings: int = 300, seed: int = 0, coordinate=np.float16) -> dict:
    """An Argoverse 2 sweep: 64 beams (av2-vlp32c's table) × ``firings`` azimuths, returns 3–80 m from the sensors'
    origin, stored in the vehicle frame (origin + point) as halffloat, the av2 devkit's columns and metadata; written
    in two record batches as the real files are (``coordinate``: the x, y, z dtype; the devkit's docs say float32).
    Returns the columns as stored."""
    rng = np.random.default_rng(seed)
    elevation = np.deg2rad(np.asarray(load_lidar_profile("av2-vlp32c").beam_elevation_deg))
    laser = np.tile(np.arange(64), firings)
    az = np.repeat(-2 * np.pi * np.arange(firings) / firings, 64)
    r = rng.uniform(3, 80, len(laser))
    p = r[:, None] * np.stack([np.cos(elevation[laser]) * np.cos(az), np.cos(elevation[laser]) * np.sin(az),
                               np.sin(elevation[laser])], 1) + AV2_SENSOR_ORIGIN_M
    cols = {"x": p[:, 0].astype(coordinate), "y": p[:, 1].astype(coordinate), "z": p[:, 2].astype(coordinate),
            "intensity": rng.integers(0, 256, len(laser)).astype(np.uint8), "laser_number": laser.astype(np.uint8),
            "offset_ns": (np.arange(len(laser)) * 5000).astype(np.int32)}
    meta = {b"pandas": json.dumps({"index_columns": [], "columns": [{"name": k} for k in cols]}).encode()}
    table = pa.table(cols).replace_schema_metadata(meta)
    pyarrow.feather.write_feather(table, str(path), chunksize=len(laser) // 2 + 1)
    return cols


def test_av2_profile_is_the_vlp32c_table_twice():
    """64 beams: the VLP-32C manual's 32 angles, each once per sensor, in Argoverse 2's laser_number order (laser 0:
    +7°, 4: +15°, 31: −25°, matched on real sweeps); the sensors' origin in the vehicle frame; no firing grid."""
    p = load_lidar_profile("av2-vlp32c")
    elevation = np.asarray(p.beam_elevation_deg)
    assert p.channels == 64 and np.array_equal(elevation[:32], elevation[32:])
    assert sorted(elevation[:32]) == pytest.approx(sorted(VLP32C_DEG))
    assert (elevation[0], elevation[4], elevation[31]) == (7.0, 15.0, -25.0)
    assert p.sensor_origin_m == (1.35, 0.0, 1.58) and p.storage_order == "merged"
    assert (p.intensity_unit, p.intensity_kind, p.max_range_m, p.wavelength_m) == ("uint8", "reflectivity", 200.0,
                                                                                   903e-9)


@pytest.mark.parametrize("coordinate", [np.float16, np.float32])
def test_feather_sweep_reads_about_the_sensors_and_writes_back_every_column(tmp_path, coordinate):
    """Read: ring from laser_number, positions about the sensors' origin, every column in its dtype. Written back:
    the same schema (order, Arrow types, pandas metadata) and, for an unchanged cloud, the same values — the vehicle
    frame's positions bit for bit, halffloat as in the real sweeps or float32 — readable by pyarrow.feather.read_table; the effect codes go to a
    sidecar, not into the table. Before (round 21): refused as "a table"."""
    src = tmp_path / "315966265259836000.feather"
    cols = av2_sweep(src, coordinate=coordinate)
    cloud = read_pointcloud(src, profile=load_lidar_profile("av2-vlp32c"))
    assert cloud.layout.fmt == "feather" and [f[1] for f in cloud.layout.fields] == list(cols)
    np.testing.assert_array_equal(cloud.fields["ring"], cols["laser_number"])
    assert cloud.fields["intensity"].dtype == np.uint8 and cloud.fields["offset_ns"].dtype == np.int32
    vehicle = np.stack([cols[a].astype(np.float64) for a in "xyz"], 1)
    np.testing.assert_allclose(cloud.positions_m, vehicle - AV2_SENSOR_ORIGIN_M, atol=1e-12)
    out = tmp_path / "out.feather"
    write_pointcloud(out, cloud.replace(effect=np.zeros(len(cloud), np.uint8)))
    back = pyarrow.feather.read_table(str(out))
    assert back.schema.equals(pyarrow.feather.read_table(str(src)).schema, check_metadata=True)
    for name, values in cols.items():
        np.testing.assert_array_equal(back.column(name).to_numpy(), values)
    assert (tmp_path / "out.feather.rv_effect").read_bytes() == bytes(len(cloud))


def test_av2_sweep_under_fog_keeps_its_table_and_moves_returns_along_the_sensors_rays(tmp_path):
    """Fog through the runner: the output table has the input's columns and types; returns kept stay bit for bit;
    a return moved to a fog droplet lies on its ray from the sensors' origin, not from the vehicle frame's (on the
    ground 2.1 m away); no empty ray gets weather (two sensors, the lower one upside down, have no single firing
    grid: the manifest says why)."""
    root = tmp_path / "in" / "log" / "sensors" / "lidar"
    root.mkdir(parents=True)
    cols = av2_sweep(root / "315966265259836000.feather")
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 3,
                           "chain": [{"model": "fog.lidar", "params": {"visibility_m": 30.0}}],
                           "inputs": {"lidar": "*/sensors/lidar/*.feather", "lidar_profile": "av2-vlp32c"}},
                          base_dir=tmp_path)
    out = tmp_path / "out"
    assert run(recipe, tmp_path / "in", out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    written = out / "log" / "sensors" / "lidar" / "315966265259836000.feather"
    table = pyarrow.feather.read_table(str(written))
    assert table.column_names == list(cols) and [f.type for f in table.schema] == [
        pa.float16(), pa.float16(), pa.float16(), pa.uint8(), pa.uint8(), pa.int32()]
    effect = np.frombuffer((written.parent / (written.name + ".rv_effect")).read_bytes(), np.uint8)
    assert len(effect) == table.num_rows == len(cols["x"])                 # fog removes none here, adds none
    got = np.stack([table.column(a).to_numpy().astype(np.float64) for a in "xyz"], 1)
    given = np.stack([cols[a].astype(np.float64) for a in "xyz"], 1)
    kept, moved = effect <= 1, effect == 2
    assert moved.sum() > 1000 and kept.sum() > 100
    np.testing.assert_array_equal(got[kept], given[kept])
    u, v = given[moved] - AV2_SENSOR_ORIGIN_M, got[moved] - AV2_SENSOR_ORIGIN_M
    cos = (u * v).sum(1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.5       # halffloat's resolution at a few metres
    entry, = read_manifest(out / "manifest.jsonl")
    diagnostics = entry["steps"][0]["diagnostics"]
    assert diagnostics["empty_rays"] == 0 and "merges several sensors" in diagnostics["empty_rays_source"]


def test_av2_sweep_without_its_profile_is_refused(tmp_path):
    """Read with another profile (the default OS1-128, a VLP-16 table) the vehicle frame's origin would be the rays':
    refused, naming the profile to give."""
    src = tmp_path / "s.feather"
    av2_sweep(src)
    with pytest.raises(InputError, match="Argoverse 2 sweep .* give lidar_profile: av2-vlp32c"):
        read_pointcloud(src, profile=load_lidar_profile("os1-128"))
    with pytest.raises(InputError, match="not a readable Feather"):
        read_pointcloud(tmp_path / "s.feather", profile=load_lidar_profile("av2-vlp32c"),
                        data=src.read_bytes()[:200])
    sink = io.BytesIO()
    pyarrow.feather.write_feather(pa.table({"x": [1.0], "y": [2.0], "z": [0.0], "tag": ["car"]}), sink)
    (tmp_path / "t.feather").write_bytes(sink.getvalue())
    with pytest.raises(InputError, match="column 'tag' is of Arrow type string"):
        read_pointcloud(tmp_path / "t.feather")
