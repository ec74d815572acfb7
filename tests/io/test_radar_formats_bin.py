"""Radar ``.bin`` layouts other than View-of-Delft's (io/radar_formats.py): TJ4DRadSet's N×8 float32 ``x y z V_r
Range Power Alpha Beta`` and columns a recipe names (``inputs.radar_bin_fields``: Dual-Radar's N×5). Inputs are
built in tmp_path from the layout of the public TJ4DRadSet sample frames (Range = |p|, Alpha = −atan2(y, x) and
Beta = −atan2(z, x) in degrees, V_r positive receding, Power the SNR in dB, 2 302–3 191 detections a frame)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from roadview_noise.cli.main import app
from roadview_noise.compound import apply_models
from roadview_noise.errors import InputError
from roadview_noise.io.pointcloud import effect_sidecar_path, read_pointcloud, write_pointcloud
from roadview_noise.io.radar_formats import dataset_profile
from roadview_noise.profiles.radar import load_radar_profile
from roadview_noise.recipe import InputsSpec
from roadview_noise.registry import get_model

VOD_NAMES = ["x", "y", "z", "rcs_dbsm", "v_r_m_per_s", "v_r_comp_m_per_s", "time_s"]


def tj4d_rows(n: int = 700, seed: int = 0, ego_m_per_s: float = 17.0) -> np.ndarray:
    """(n, 8) float32 x y z V_r Range Power Alpha Beta of a frame: 3–370 m ahead, ±60° azimuth, ±20° elevation,
    a stationary world seen from a car driving ahead (V_r = −v cos θ)."""
    rng = np.random.default_rng(seed)
    r, az, el = rng.uniform(3, 370, n), np.radians(rng.uniform(-60, 60, n)), np.radians(rng.uniform(-20, 20, n))
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1).astype("<f4")
    p = xyz.astype(np.float64)
    rng_m = np.linalg.norm(p, axis=1)
    columns = [xyz[:, 0], xyz[:, 1], xyz[:, 2], -ego_m_per_s * p[:, 0] / rng_m, rng_m, rng.uniform(0.3, 30, n),
               -np.degrees(np.arctan2(p[:, 1], p[:, 0])), -np.degrees(np.arctan2(p[:, 2], p[:, 0]))]
    return np.column_stack(columns).astype("<f4")


def test_a_tj4d_frame_is_read_in_its_own_layout_and_written_back_byte_for_byte(tmp_path):
    rows = tj4d_rows(700)                  # 700 × 32 bytes is also 800 View-of-Delft points: told by the data
    (tmp_path / "070070.bin").write_bytes(rows.tobytes())
    cloud = read_pointcloud(tmp_path / "070070.bin", sensor="radar")
    assert cloud.layout.fmt == "tj4d_bin" and len(cloud) == 700
    assert [k for k, _, _ in cloud.layout.fields] == ["x", "y", "z", "v_r_m_per_s", "Range", "snr_db", "Alpha",
                                                      "Beta"]
    assert [n for _, n, _ in cloud.layout.fields] == ["x", "y", "z", "V_r", "Range", "Power", "Alpha", "Beta"]
    np.testing.assert_array_equal(cloud.fields["snr_db"], rows[:, 5])
    assert dataset_profile(cloud) == ("TJ4DRadSet (Oculii Eagle)", "oculii-eagle")
    write_pointcloud(tmp_path / "o.bin", cloud, effect="none")
    assert (tmp_path / "o.bin").read_bytes() == rows.tobytes()


def test_a_view_of_delft_frame_whose_size_also_fits_8_columns_stays_view_of_delft(tmp_path):
    rng = np.random.default_rng(1)
    vod = rng.normal(0, 10, (64, 7))                          # 64 × 28 bytes = 56 rows of 32 bytes
    vod[:, 5] = vod[:, 4] + 3.0 * vod[:, 0] / np.linalg.norm(vod[:, :3], axis=1)      # v_r_comp − v_r = v_ego·r̂
    (tmp_path / "00001.bin").write_bytes(vod.astype("<f4").tobytes())
    cloud = read_pointcloud(tmp_path / "00001.bin", sensor="radar")
    assert cloud.layout.fmt == "vod_bin" and len(cloud) == 64
    assert [k for k, _, _ in cloud.layout.fields] == VOD_NAMES


def test_a_radar_bin_in_neither_layout_is_refused_naming_both_and_the_recipe_key(tmp_path):
    (tmp_path / "000000.bin").write_bytes(tj4d_rows(9).tobytes())
    (tmp_path / "000001.bin").write_bytes(np.zeros((3, 5), "<f4").tobytes())     # Dual-Radar: 60 bytes
    with pytest.raises(InputError, match="radar_bin_fields") as info:
        read_pointcloud(tmp_path / "000001.bin", sensor="radar")
    assert "000001.bin" in str(info.value) and "View-of-Delft" in str(info.value) and "TJ4DRadSet" in str(info.value)
    rows = tj4d_rows(9)
    rows[4, 4] += 1.0                      # a Range that does not restate |p|: not TJ4DRadSet, 288 bytes ≠ 28 k
    (tmp_path / "000002.bin").write_bytes(rows.tobytes())
    with pytest.raises(InputError, match="fits neither"):
        read_pointcloud(tmp_path / "000002.bin", sensor="radar")


def test_a_dual_radar_frame_of_7k_points_is_not_taken_for_view_of_delft(tmp_path):
    rng = np.random.default_rng(8)
    r, az = rng.uniform(3, 60, 70), rng.uniform(-1, 1, 70)        # 70 × 20 bytes = 50 VoD points of 28 bytes
    rows = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(-2, 2, 70), rng.uniform(0, 40, 70),
                            -10 * np.cos(az)]).astype("<f4")
    (tmp_path / "000000.bin").write_bytes(rows.tobytes())
    with pytest.raises(InputError, match=r"fits no sensor velocity \(RMS .* m/s.*radar_bin_fields"):
        read_pointcloud(tmp_path / "000000.bin", sensor="radar")


def test_radar_bin_fields_read_a_dual_radar_frame_and_write_it_back(tmp_path):
    rng = np.random.default_rng(2)
    rows = np.column_stack([rng.uniform(3, 80, (40, 3)), rng.normal(0, 5, 40), rng.normal(0, 5, 40)]).astype("<f4")
    (tmp_path / "000000.bin").write_bytes(rows.tobytes())
    cloud = read_pointcloud(tmp_path / "000000.bin", sensor="radar", bin_fields=["x", "y", "z", "rcs", "v_r"])
    assert cloud.layout.fmt == "radar_bin" and set(cloud.fields) == {"rcs_dbsm", "v_r_m_per_s"}
    write_pointcloud(tmp_path / "o.bin", cloud, effect="none")
    assert (tmp_path / "o.bin").read_bytes() == rows.tobytes()
    with pytest.raises(InputError, match="not a multiple of the 24-byte point"):
        read_pointcloud(tmp_path / "000000.bin", sensor="radar", bin_fields=["x", "y", "z", "rcs", "v_r", "t"])
    with pytest.raises(InputError, match="inputs.radar_bin_fields"):
        read_pointcloud(tmp_path / "000000.bin", sensor="radar", bin_fields=["rcs", "x", "y", "z", "v_r"])


def test_turned_points_get_range_alpha_beta_of_their_new_position_and_the_rest_keep_their_bytes(tmp_path):
    rows = tj4d_rows(300, seed=4)
    (tmp_path / "f.bin").write_bytes(rows.tobytes())
    cloud = read_pointcloud(tmp_path / "f.bin", sensor="radar", profile=load_radar_profile("oculii-eagle"))
    turned, _ = apply_models([get_model("alignment.radar")(yaw_sd_deg=2, pitch_sd_deg=1)], cloud, seed=3,
                             key="f", sequence_id="s")
    write_pointcloud(tmp_path / "o.bin", turned, effect="none")
    out = np.fromfile(tmp_path / "o.bin", "<f4").reshape(-1, 8).astype(np.float64)
    p = out[:, :3]
    np.testing.assert_allclose(out[:, 4], np.linalg.norm(p, axis=1), atol=5e-4)         # TJ4D_TOLERANCE
    np.testing.assert_allclose(out[:, 6], -np.degrees(np.arctan2(p[:, 1], p[:, 0])), atol=1e-3)
    np.testing.assert_allclose(out[:, 7], -np.degrees(np.arctan2(p[:, 2], p[:, 0])), atol=1e-3)
    assert np.abs(out[:, 6] - rows[:, 6]).max() > 0.1                  # (the turn moved the azimuths)
    np.testing.assert_array_equal(out[:, 4], rows[:, 4])               # a turn keeps |p|: stored Range kept
    np.testing.assert_array_equal(out[:, [3, 5]], rows[:, [3, 5]])


@pytest.mark.parametrize("rates", [(5, 20, 50)])
def test_rain_on_a_tj4d_frame_loses_more_points_as_it_rains_harder_and_adds_no_clutter(tmp_path, rates):
    rows = tj4d_rows(3000, seed=5)
    (tmp_path / "f.bin").write_bytes(rows.tobytes())
    cloud = read_pointcloud(tmp_path / "f.bin", sensor="radar", profile=load_radar_profile("oculii-eagle"))
    lost = []
    for rate in rates:
        out, rec = apply_models([get_model("rain.radar")(rain_rate_mm_per_h=rate)], cloud, seed=2, key="f",
                                sequence_id="s")
        d = rec[0].diagnostics
        assert d["detection_statistic"] == "snr_db" and d.get("clutter_points", 0) == 0
        assert "rcs_dbsm" in d["clutter_skipped"]
        lost.append(len(cloud) - len(out))
        write_pointcloud(tmp_path / "o.bin", out)
        back = np.fromfile(tmp_path / "o.bin", "<f4").reshape(-1, 8)
        kept = rows[out.origin]
        np.testing.assert_array_equal(back[:, [0, 1, 2, 3, 4, 6, 7]], kept[:, [0, 1, 2, 3, 4, 6, 7]])
        assert (back[:, 5] <= kept[:, 5]).all() and (back[:, 5] < kept[:, 5]).any()     # SNR lowered by the loss
        assert len(np.fromfile(effect_sidecar_path(tmp_path / "o.bin"), np.uint8)) == len(out)
    assert 0 < lost[0] < lost[1] < lost[2] < len(cloud)


def test_oculii_eagle_profile_from_the_manual_and_the_files():
    p = load_radar_profile("oculii-eagle")
    assert (p.fov_azimuth_deg, p.fov_elevation_deg, p.max_range_m, p.elevation_measured) == (120.0, 40.0, 375.0,
                                                                                             True)


def test_radar_bin_fields_stay_out_of_a_recipe_that_does_not_set_them():
    assert "radar_bin_fields" not in InputsSpec().model_dump()
    assert InputsSpec(radar_bin_fields=["x", "y", "z", "rcs", "v_r"]).model_dump()["radar_bin_fields"] == (
        "x", "y", "z", "rcs", "v_r")


def test_cli_augments_a_dual_radar_tree_with_radar_bin_fields_and_a_tj4d_tree_without(tmp_path):
    rng = np.random.default_rng(6)
    dual = np.column_stack([rng.uniform(3, 60, (50, 3)), rng.normal(0, 5, 50), rng.normal(0, 3, 50)]).astype("<f4")
    (tmp_path / "in" / "ars548").mkdir(parents=True)
    (tmp_path / "in" / "ars548" / "000000.bin").write_bytes(dual.tobytes())
    (tmp_path / "in" / "velodyne").mkdir()
    (tmp_path / "in" / "velodyne" / "070070.bin").write_bytes(tj4d_rows(70).tobytes())
    recipe = ("schema: rvnoise.recipe/1\nchain: [{model: fog.radar}]\nseed: 1\ninputs: {radar: '%s/*.bin'%s}\n")
    runs = {"ars548": ", radar_bin_fields: [x, y, z, rcs, v_r]", "velodyne": ", radar_profile: oculii-eagle"}
    for folder, extra in runs.items():
        (tmp_path / f"{folder}.yaml").write_text(recipe % (folder, extra))
        result = CliRunner().invoke(app, ["augment", "--recipe", str(tmp_path / f"{folder}.yaml"),
                                          str(tmp_path / "in"), str(tmp_path / f"out_{folder}"), "--yes"])
        assert result.exit_code == 0, result.output
        manifest = (tmp_path / f"out_{folder}" / "manifest.jsonl").read_text()
        entries = [json.loads(line) for line in manifest.splitlines()]
        assert [e.get("status", "ok") for e in entries if "input" in e] == ["ok"], entries


@pytest.mark.parametrize("layout,n,row_bytes", [("tj4d", 224, 32), ("dual", 224, 20), ("vod", 224, 28)])
def test_max_points_counts_the_points_of_each_radar_bin_layout(tmp_path, layout, n, row_bytes):
    """``--max-points`` counted every radar ``.bin`` at View-of-Delft's 28 bytes a point: a TJ4DRadSet frame of 224
    points read as 256 (refused at 224), a Dual-Radar one (20 B) as 160 (passed at 159). Each layout's own row."""
    rng = np.random.default_rng(8)
    v_r = rng.normal(0, 3, n)                                     # VoD: a standing sensor, compensated = measured
    rows = {"tj4d": tj4d_rows(n), "vod": np.column_stack([rng.uniform(3, 60, (n, 3)), rng.normal(0, 5, n), v_r, v_r,
                                                          np.zeros(n)]),
            "dual": np.column_stack([rng.uniform(3, 60, (n, 3)), rng.normal(0, 5, n), rng.normal(0, 3, n)])}[layout]
    data = rows.astype("<f4").tobytes()
    assert len(data) == n * row_bytes
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "000000.bin").write_bytes(data)
    fields = ", radar_bin_fields: [x, y, z, rcs, v_r]" if layout == "dual" else ""
    (tmp_path / "r.yaml").write_text("schema: rvnoise.recipe/1\nchain: [{model: fog.radar}]\nseed: 1\n"
                                     f"inputs: {{radar: '*.bin'{fields}}}\n")
    for limit, failed in ((n, 0), (n - 1, 1)):
        out = tmp_path / f"out{limit}"
        CliRunner().invoke(app, ["augment", "--recipe", str(tmp_path / "r.yaml"), str(tmp_path / "in"), str(out),
                                 "--max-points", str(limit), "--yes"])
        entries = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
        errors = [e.get("error", "") for e in entries if e.get("status") == "failed"]
        assert len(errors) == failed and all(f"declares {n:,} points" in e for e in errors), errors


# --- ars548_ros PointCloudDetection (x y z v r RCS azimuth elevation; PointCloud2Modifier packs them unpadded) ------

ARS548_FIELDS = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("v", 12, 7), ("r", 16, 7), ("RCS", 20, 1),
                 ("azimuth", 21, 7), ("elevation", 25, 7)]            # datatype 7 FLOAT32, 1 INT8; point_step 29


def ars548_cloud2(n: int = 400, seed: int = 7):
    from rosbags.typesys import Stores, get_typestore

    from roadview_noise.io import ros_messages as rm

    types = get_typestore(Stores.ROS2_HUMBLE).types
    rng = np.random.default_rng(seed)
    r = rng.uniform(1.5, 60, n).astype("<f4")
    az, el = rng.uniform(-1.0, 1.0, n).astype("<f4"), rng.uniform(-0.2, 0.2, n).astype("<f4")
    record = np.dtype({"names": [f[0] for f in ARS548_FIELDS], "offsets": [f[1] for f in ARS548_FIELDS],
                       "formats": ["<" + rm.POINTFIELD_TYPES[f[2]] for f in ARS548_FIELDS], "itemsize": 29})
    points = np.zeros(n, record)
    points["x"], points["y"], points["z"] = r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)
    points["v"] = -12.0 * np.cos(az) * np.cos(el)                   # a stationary world, car at 12 m/s
    points["r"], points["RCS"], points["azimuth"], points["elevation"] = r, rng.integers(-10, 30, n), az, el
    pf = types["sensor_msgs/msg/PointField"]
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="r")
    return types["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=n, fields=[pf(name=a, offset=b, datatype=c, count=1) for a, b, c in
                                                  ARS548_FIELDS],
        is_bigendian=False, point_step=29, row_step=29 * n, data=points.view(np.uint8), is_dense=True)


def test_an_ars548_ros_detection_cloud_reads_v_as_range_rate_and_added_clutter_gets_its_own_r():
    from roadview_noise.io import ros_messages as rm
    from roadview_noise.provenance import Effect

    msg = ars548_cloud2()
    cloud = rm.cloud_to_pointcloud(msg, sensor="radar", profile=load_radar_profile("ars548"), field_map=None,
                                   source="t")
    assert [k for k, _, _ in cloud.layout.fields] == ["x", "y", "z", "v_r_m_per_s", "r", "rcs_dbsm", "azimuth",
                                                      "elevation"]
    assert dataset_profile(cloud) == ("ars548_ros (Continental ARS 548 RDI)", "ars548")
    assert bytes(rm.pointcloud_to_cloud2(msg, cloud, effect="none", source="t").data) == bytes(msg.data)
    out, rec = apply_models([get_model("rain.radar")(rain_rate_mm_per_h=50)], cloud, seed=1, key="f",
                            sequence_id="s")
    added = out.effect == Effect.ADDED
    assert rec[0].diagnostics["clutter_points"] == int(added.sum()) > 0
    back = rm.cloud_columns(rm.pointcloud_to_cloud2(msg, out, effect="none", source="t"), source="t")
    values = {name: col for name, _, col in back}
    p = out.positions_m[added]
    np.testing.assert_allclose(values["r"][added], np.linalg.norm(p, axis=1), rtol=1e-6)        # before: 0
    np.testing.assert_allclose(values["azimuth"][added], np.arctan2(p[:, 1], p[:, 0]), atol=1e-5)
    kept = ~added
    np.testing.assert_array_equal(values["r"][kept], cloud.fields["r"][out.origin[kept]])
    assert (values["RCS"].dtype == np.int8) and values["v"].dtype == np.float32


def test_an_oculii_eagle_pointcloud2_layout_is_pointed_to_its_profile(tmp_path):
    """NTU4DRadLM's Eagle clouds (EaglePointXYZIVRAB: x y z snr_db doppler range alpha beta, float32), as a PCD."""
    rows = tj4d_rows(20)[:, [0, 1, 2, 5, 3, 4, 6, 7]]
    names = "x y z snr_db doppler range alpha beta"
    header = (f"VERSION 0.7\nFIELDS {names}\nSIZE {' '.join(['4'] * 8)}\nTYPE {' '.join(['F'] * 8)}\n"
              f"COUNT {' '.join(['1'] * 8)}\nWIDTH 20\nHEIGHT 1\nPOINTS 20\nDATA binary\n")
    (tmp_path / "e.pcd").write_bytes(header.encode() + rows.tobytes())
    cloud = read_pointcloud(tmp_path / "e.pcd", sensor="radar")
    assert dataset_profile(cloud) == ("Oculii Eagle PointCloud2", "oculii-eagle")
    assert {"snr_db", "v_r_m_per_s", "range"} <= set(cloud.fields)


def test_a_tj4d_frame_read_as_lidar_is_refused_and_preview_guesses_radar(tmp_path):
    from roadview_noise.preview import guess_sensor

    path = tmp_path / "TJ4DRadSet_4DRadar" / "training" / "velodyne" / "070070.bin"
    path.parent.mkdir(parents=True)
    path.write_bytes(tj4d_rows(50).tobytes())             # 32-byte points: 100 KITTI points of 16 bytes
    with pytest.raises(InputError, match="TJ4DRadSet 4D-radar .bin .* read as a LiDAR scan"):
        read_pointcloud(path)
    assert guess_sensor(path) == "radar"
    kitti = tmp_path / "kitti" / "training" / "velodyne" / "000000.bin"
    kitti.parent.mkdir(parents=True)
    kitti.write_bytes(np.random.default_rng(9).uniform(-40, 40, (100, 4)).astype("<f4").tobytes())
    assert guess_sensor(kitti) == "lidar" and len(read_pointcloud(kitti)) == 100
