"""Astyx HiRes2019 radar text tables (io/text_table.py, io/radar_formats.py, profile ``astyx-6455``). Inputs are
built in tmp_path from the layout of the public files (a blank line, ``X Y Z V_r Mag``, ``%.18g`` values; V_r in
0.0812 m/s float32 steps, positive approaching; Mag in 0.5 dB steps from 45)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from typer.testing import CliRunner

from roadview_noise.cli.main import app
from roadview_noise.compound import apply_models
from roadview_noise.errors import EmptyCloudError, InputError
from roadview_noise.io.pointcloud import effect_sidecar_path, read_pointcloud, write_pointcloud
from roadview_noise.preview import guess_sensor
from roadview_noise.profiles.radar import load_radar_profile
from roadview_noise.provenance import Effect
from roadview_noise.registry import get_model

DOPPLER_STEP = float(np.float32(0.0812))


def astyx_rows(n: int = 400, seed: int = 0) -> np.ndarray:
    """(n, 5) X Y Z V_r Mag of a frame: 3-D detections 3–100 m ahead, ±50° azimuth, ±8° elevation."""
    rng = np.random.default_rng(seed)
    r, az, el = rng.uniform(3, 100, n), np.radians(rng.uniform(-50, 50, n)), np.radians(rng.uniform(-8, 8, n))
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    v_r = rng.integers(-64, 65, n) * DOPPLER_STEP
    mag = 45 + 0.5 * rng.integers(0, 60, n)
    mag[0] = 45.0                                           # the sensor's floor is in every frame
    return np.column_stack([xyz, v_r, mag])


def astyx_file(path, rows=None, newline="\n", fmt="%.18g") -> bytes:
    rows = astyx_rows() if rows is None else rows
    lines = ["", "X Y Z V_r Mag"] + [" ".join(fmt % v for v in row) for row in rows]
    data = (newline.join(lines) + newline).encode("ascii")
    path.write_bytes(data)
    return data


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_astyx_txt_round_trips_byte_for_byte_and_maps_its_columns(tmp_path, newline):
    rows = astyx_rows()
    data = astyx_file(tmp_path / "000001.txt", rows, newline)
    cloud = read_pointcloud(tmp_path / "000001.txt", sensor="radar")
    assert cloud.layout.fmt == "txt" and [k for k, _, _ in cloud.layout.fields] == [
        "x", "y", "z", "v_r_m_per_s", "power_db"]
    np.testing.assert_array_equal(cloud.positions_m, rows[:, :3])
    np.testing.assert_array_equal(cloud.fields["v_r_m_per_s"], -rows[:, 3])     # stored positive approaching
    np.testing.assert_array_equal(cloud.fields["power_db"], rows[:, 4])
    write_pointcloud(tmp_path / "out.txt", cloud, effect="none")
    assert (tmp_path / "out.txt").read_bytes() == data
    out, _ = apply_models([get_model("power.radar")()], cloud, seed=1, key="k", sequence_id="s")   # identity
    write_pointcloud(tmp_path / "chain.txt", out)
    assert (tmp_path / "chain.txt").read_bytes() == data


def test_changed_and_new_rows_are_printed_as_the_file_prints_and_the_others_keep_their_text(tmp_path):
    rows = astyx_rows(50)
    data = astyx_file(tmp_path / "in.txt", rows, fmt="%.9g")
    cloud = read_pointcloud(tmp_path / "in.txt", sensor="radar")
    assert cloud.layout.text.number_format == "%.9g"
    power = cloud.fields["power_db"].copy()
    power[3] -= 1.25
    changed = cloud.with_fields(power_db=power).select(np.r_[0:10, 11:50])          # row 10 lost, row 3 weaker
    new = changed.concat(np.array([[20.0, 1.0, 0.5]]), {"v_r_m_per_s": np.array([2.0]),
                                                       "power_db": np.array([46.5])})
    write_pointcloud(tmp_path / "out.txt", new, effect="none")
    lines_in = data.decode().split("\n")[2:-1]
    lines_out = (tmp_path / "out.txt").read_text().split("\n")
    assert lines_out[:2] == ["", "X Y Z V_r Mag"] and lines_out[-1] == ""
    body = lines_out[2:-1]
    assert len(body) == 50
    assert body[:3] == lines_in[:3] and body[4:10] == lines_in[4:10] and body[10:49] == lines_in[11:50]
    assert body[3] == " ".join("%.9g" % v for v in (*rows[3, :4], rows[3, 4] - 1.25))
    assert body[49] == "20 1 0.5 -2 46.5"                  # V_r back to the file's sign


def test_a_recipe_field_map_wins_over_the_astyx_names(tmp_path):
    rows = astyx_rows(20)
    astyx_file(tmp_path / "a.txt", rows)
    cloud = read_pointcloud(tmp_path / "a.txt", sensor="radar", field_map={"Mag": "snr_db"})
    assert "snr_db" in cloud.fields and "power_db" not in cloud.fields
    np.testing.assert_array_equal(cloud.fields["v_r_m_per_s"], -rows[:, 3])
    raw = read_pointcloud(tmp_path / "a.txt", sensor="radar", field_map={"V_r": "doppler_as_stored"})
    np.testing.assert_array_equal(raw.fields["doppler_as_stored"], rows[:, 3])   # mapped elsewhere: not negated
    assert "v_r_m_per_s" not in raw.fields


def test_other_text_tables_need_their_columns_named(tmp_path):
    (tmp_path / "h.txt").write_text("# X Y Z V_r Mag\n1 2 3 0.5 45\n")              # numpy.savetxt's header
    assert read_pointcloud(tmp_path / "h.txt", sensor="radar").layout.text.names == ("X", "Y", "Z", "V_r", "Mag")
    (tmp_path / "t.txt").write_text("x y z snr\n1 2 3 10\n4 5 6 12\n")
    cloud = read_pointcloud(tmp_path / "t.txt", sensor="radar")
    assert sorted(cloud.fields) == ["snr_db"] and cloud.layout.text.negated == (False,) * 4
    write_pointcloud(tmp_path / "o.txt", cloud, effect="none")
    assert (tmp_path / "o.txt").read_text() == "x y z snr\n1 2 3 10\n4 5 6 12\n"
    (tmp_path / "u.txt").write_text("X Y Z Vel\n1 2 3 10\n")
    with pytest.raises(InputError, match="no scalar 'x' field"):
        read_pointcloud(tmp_path / "u.txt", sensor="radar")
    assert "Vel" in read_pointcloud(tmp_path / "u.txt", sensor="radar", field_map={"X": "x", "Y": "y", "Z": "z"}).fields


@pytest.mark.parametrize("text, message", [
    ("\n1 2 3 0 45\n", "no header line naming the columns"),
    ("X Y Z V_r Mag\n1 2 3 0 45\n1 2 3 0\n", "line 3 has 4 values, the header names 5"),
    ("X Y Z V_r Mag\n1 2 3 0 45\n\n1 2 3 0 45\n", "line 3 is blank"),
    ("X Y Z V_r Mag\n1 2 3 0 4o\n", "line 2, column 5: '4o' is not a number"),
    ("X Y Z X Mag\n1 2 3 0 45\n", "names a column twice"),
    ("\n\n", "only blank lines"),
])
def test_bad_text_tables_fail_naming_the_line(tmp_path, text, message):
    (tmp_path / "bad.txt").write_text(text)
    with pytest.raises(InputError, match=message) as info:
        read_pointcloud(tmp_path / "bad.txt", sensor="radar")
    assert "bad.txt" in str(info.value)


def test_a_header_without_rows_is_an_empty_frame_and_lidar_txt_is_refused(tmp_path):
    (tmp_path / "e.txt").write_text("\nX Y Z V_r Mag\n")
    with pytest.raises(EmptyCloudError):
        read_pointcloud(tmp_path / "e.txt", sensor="radar")
    astyx_file(tmp_path / "l.txt")
    with pytest.raises(InputError, match=r"\.txt: radar only"):
        read_pointcloud(tmp_path / "l.txt", sensor="lidar")
    assert guess_sensor(tmp_path / "l.txt") == "radar"                     # rvnoise preview


def test_astyx_6455_profile_from_the_paper_and_the_files():
    p = load_radar_profile("astyx-6455")
    assert (p.fov_azimuth_deg, p.fov_elevation_deg, p.max_range_m) == (110.0, 10.0, 100.0)
    assert p.velocity_resolution_m_per_s == 0.0812 and p.range_resolution_m == 0.075
    assert p.elevation_measured is True and p.power_unit == "relative"


@pytest.mark.parametrize("model, params", [("fog.radar", {"visibility_m": 30}),
                                           ("rain.radar", {"rain_rate_mm_per_h": 50})])
def test_weather_on_an_astyx_frame_loses_far_weak_points_and_adds_no_clutter(tmp_path, model, params):
    rows = astyx_rows(2000, seed=3)
    astyx_file(tmp_path / "f.txt", rows)
    cloud = read_pointcloud(tmp_path / "f.txt", sensor="radar", profile=load_radar_profile("astyx-6455"))
    out, rec = apply_models([get_model(model)(**params)], cloud, seed=2, key="f", sequence_id="s")
    d = rec[0].diagnostics
    assert d["detection_statistic"] == "power_db" and d["threshold_db"] == 45.0
    lost = np.setdiff1d(np.arange(len(cloud)), out.origin)
    assert 0 < len(lost) < len(cloud) // 2 and d["points_removed"] == len(lost)
    assert (out.origin >= 0).all() and d.get("clutter_points", 0) == 0      # no RCS: no clutter
    if model == "rain.radar":
        assert "rcs_dbsm" in d["clutter_skipped"]
    loss_db = 2 * d["specific_attenuation_db_per_km"] * np.linalg.norm(rows[:, :3], axis=1) / 1000
    kept = rows[:, 4] - loss_db >= 45.0                                   # models.md §4.1: D − L ≥ t survives
    np.testing.assert_array_equal(out.origin, np.flatnonzero(kept))
    np.testing.assert_allclose(out.fields["power_db"], (rows[:, 4] - loss_db)[kept], atol=1e-9)
    np.testing.assert_array_equal(out.fields["v_r_m_per_s"], cloud.fields["v_r_m_per_s"][out.origin])
    write_pointcloud(tmp_path / "o.txt", out)
    back = read_pointcloud(tmp_path / "o.txt", sensor="radar")
    np.testing.assert_array_equal(back.fields["power_db"], out.fields["power_db"])
    effect = np.fromfile(effect_sidecar_path(tmp_path / "o.txt"), np.uint8)
    assert len(effect) == len(out) and set(effect) <= {Effect.KEPT, Effect.ATTENUATED}


def test_cli_augments_an_astyx_tree(tmp_path):
    (tmp_path / "in" / "radar_6455").mkdir(parents=True)
    data = astyx_file(tmp_path / "in" / "radar_6455" / "000000.txt")
    (tmp_path / "r.yaml").write_text("schema: rvnoise.recipe/1\nchain: [{model: power.radar}]\nseed: 1\n"
                                     "inputs: {radar: 'radar_6455/*.txt', radar_profile: astyx-6455}\n")
    result = CliRunner().invoke(app, ["augment", "--recipe", str(tmp_path / "r.yaml"), str(tmp_path / "in"),
                                      str(tmp_path / "out"), "--yes"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "out" / "radar_6455" / "000000.txt").read_bytes() == data
    entries = [json.loads(line) for line in (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()]
    assert any(e.get("status") == "ok" for e in entries)


@pytest.mark.parametrize("ending", ["", "\n\n\n", "\n  \n"])
def test_text_after_the_last_row_is_kept(tmp_path, ending):
    text = "X Y Z V_r Mag\n1 2 3 0.5 45\n4 5 6 0 46" + ending
    (tmp_path / "e.txt").write_text(text)
    cloud = read_pointcloud(tmp_path / "e.txt", sensor="radar")
    write_pointcloud(tmp_path / "o.txt", cloud.select(np.array([1, 0])), effect="none")     # rows reordered
    assert (tmp_path / "o.txt").read_text() == "X Y Z V_r Mag\n4 5 6 0 46\n1 2 3 0.5 45" + ending


def test_a_cloud_built_in_memory_is_written_as_a_table_with_its_field_names(tmp_path):
    astyx_file(tmp_path / "a.txt", astyx_rows(5))
    built = read_pointcloud(tmp_path / "a.txt", sensor="radar")
    built = type(built)(built.positions_m, dict(built.fields), "radar")               # no layout
    write_pointcloud(tmp_path / "m.txt", built, effect="none")
    lines = (tmp_path / "m.txt").read_text().splitlines()
    assert lines[0] == "x y z v_r_m_per_s power_db" and len(lines) == 6
    back = read_pointcloud(tmp_path / "m.txt", sensor="radar")
    np.testing.assert_array_equal(back.positions_m, built.positions_m)
    np.testing.assert_array_equal(back.fields["power_db"], built.fields["power_db"])
