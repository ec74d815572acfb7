"""RadarScenes ``radar_data.h5``: refused with a conversion hint; one scan's rows become a 2-D radar cloud in its
sensor's frame (io/radar_formats.radarscenes_scan). Rows are built from the devkit's field names
(github.com/oleschum/radar_scenes: sequence.py, viewer.py) with h5py's dtypes for them."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from roadview_noise.cli.main import app
from roadview_noise.errors import InputError
from roadview_noise.io.pointcloud import read_pointcloud, write_pointcloud
from roadview_noise.io.radar_formats import radarscenes_scan
from roadview_noise.manifest import read_manifest
from roadview_noise.provenance import Effect

RS_DTYPE = np.dtype([("timestamp", "<u8"), ("sensor_id", "u1"), ("range_sc", "<f4"), ("azimuth_sc", "<f4"),
                     ("rcs", "<f4"), ("vr", "<f4"), ("vr_compensated", "<f4"), ("x_cc", "<f4"), ("y_cc", "<f4"),
                     ("x_seq", "<f4"), ("y_seq", "<f4"), ("uuid", "S32"), ("track_id", "S32"), ("label_id", "u1")])
STATIC = 11                                    # radar_scenes.labels.Label.STATIC


def scan_rows(n: int = 150, seed: int = 0, timestamp: int = 156859092752, sensor: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = np.zeros(n, RS_DTYPE)
    a["timestamp"], a["sensor_id"] = timestamp, sensor
    a["range_sc"], a["azimuth_sc"] = rng.uniform(1, 100, n), rng.uniform(-1.2, 1.2, n)
    a["rcs"], a["vr"] = rng.uniform(-20, 20, n), rng.normal(-8, 2, n)
    a["vr_compensated"] = a["vr"] + 8 * np.cos(a["azimuth_sc"])
    a["uuid"] = [f"{i:032x}".encode() for i in range(n)]
    a["label_id"] = np.where(rng.random(n) < 0.8, STATIC, 0)
    a["track_id"] = np.where(a["label_id"] == STATIC, b"", b"t7")
    return a


def test_radar_data_h5_is_refused_with_the_conversion_hint(tmp_path):
    (tmp_path / "radar_data.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    with pytest.raises(InputError, match="whole sequence.*radarscenes_scan"):
        read_pointcloud(tmp_path / "radar_data.h5", sensor="radar")


def test_a_scan_becomes_a_2d_cloud_in_its_sensor_frame_that_round_trips_as_pcd(tmp_path):
    rows = scan_rows()
    cloud = radarscenes_scan(rows, first_row=1000)
    r, az = rows["range_sc"].astype(float), rows["azimuth_sc"].astype(float)
    np.testing.assert_allclose(cloud.positions_m[:, 0], r * np.cos(az))
    np.testing.assert_allclose(np.hypot(*cloud.positions_m[:, :2].T), r, rtol=1e-12)
    assert not cloud.positions_m[:, 2].any()
    np.testing.assert_array_equal(cloud.fields["row"], 1000 + np.arange(len(rows)))
    assert cloud.fields["label_id"].dtype == np.uint8 and cloud.fields["timestamp"].dtype == np.uint64
    write_pointcloud(tmp_path / "s.pcd", cloud, effect="none")
    back = read_pointcloud(tmp_path / "s.pcd", sensor="radar")
    np.testing.assert_array_equal(back.fields["rcs_dbsm"], rows["rcs"])
    np.testing.assert_array_equal(back.fields["v_r_comp_m_per_s"], rows["vr_compensated"])
    np.testing.assert_array_equal(back.fields["timestamp"], rows["timestamp"])
    with pytest.raises(InputError, match="more than one scan"):
        radarscenes_scan(np.concatenate([rows, scan_rows(3, timestamp=156859092800)]))
    with pytest.raises(InputError, match="no fields"):
        radarscenes_scan(np.zeros(3, [("x", "<f4")]))


def rain_on_a_converted_scan(tmp_path, annotations: str = ""):
    """``augment`` with rain 50 mm/h on a 400-detection scan written as README's conversion writes it; the output
    cloud. ``annotations``: the recipe's ``inputs.annotations`` (YAML flow mapping), if any."""
    (tmp_path / "in" / "radar").mkdir(parents=True)
    write_pointcloud(tmp_path / "in" / "radar" / "156859092752.pcd", radarscenes_scan(scan_rows(400, seed=4)),
                     effect="none")
    (tmp_path / "r.yaml").write_text(
        "schema: rvnoise.recipe/1\nchain: [{model: rain.radar, params: {rain_rate_mm_per_h: 50}}]\nseed: 3\n"
        "inputs:\n  radar: 'radar/*.pcd'\n" + (f"  annotations: {annotations}\n" if annotations else ""))
    result = CliRunner().invoke(app, ["augment", "--recipe", str(tmp_path / "r.yaml"), str(tmp_path / "in"),
                                      str(tmp_path / "out"), "--yes", "--quiet"])
    assert result.exit_code == 0, result.output
    return read_pointcloud(tmp_path / "out" / "radar" / "156859092752.pcd", sensor="radar")


def test_rain_on_a_converted_scan_adds_static_clutter_in_the_sensor_plane(tmp_path):
    out = rain_on_a_converted_scan(tmp_path, "{weather_class: {clutter: 11}}")
    added = out.fields["rv_effect"] == Effect.ADDED
    (entry,) = [e for e in read_manifest(tmp_path / "out" / "manifest.jsonl") if e.get("status") == "ok"]
    diagnostics = entry["steps"][0]["diagnostics"]
    assert added.sum() == diagnostics["clutter_points"] > 0 and diagnostics["points_removed"] > 0
    assert not out.positions_m[:, 2].any()                                   # 2-D: clutter in the sensor plane
    assert (out.fields["label_id"][added] == STATIC).all() and not out.fields["row"][added].any()
    kept = ~added
    assert len(np.unique(out.fields["row"][kept])) == kept.sum()            # input detections keep their row


def test_label_id_is_a_class_field_without_being_declared(tmp_path):
    """RadarScenes' ``label_id`` is a class annotation by its name: clutter added by rain gets the default weather
    class (20, out of RadarScenes' 0–11, so a training script sees it); before, it got 0 — CAR — in silence unless
    the recipe declared ``field_roles``."""
    out = rain_on_a_converted_scan(tmp_path)
    added = out.fields["rv_effect"] == Effect.ADDED
    assert added.any() and (out.fields["label_id"][added] == 20).all()
    assert set(np.unique(out.fields["label_id"][~added])) <= {0, STATIC}
