"""Radar models on real dataset layouts: nuScenes ARS 408-21 PCDs (2-D, Cartesian velocities, status codes),
View-of-Delft raw + compensated radial velocities, ti_mmwave clouds (physics/radar_frame.py, io/radar_formats.py).
Inputs are built in tmp_path from the documented layouts (nuScenes devkit ``RadarPointCloud`` header)."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.errors import ModelError
from roadview_noise.io.pointcloud import read_pointcloud, write_pointcloud
from roadview_noise.physics.radar_frame import (ego_velocity_from_data, ego_velocity_m_per_s,
                                                radial_velocity_m_per_s)
from roadview_noise.profiles.radar import load_radar_profile
from roadview_noise.provenance import Effect
from roadview_noise.registry import get_model
from roadview_noise.types import Conditions, PointCloud

NUS_FIELDS = ("x y z dyn_prop id rcs vx vy vx_comp vy_comp is_quality_valid ambig_state x_rms y_rms invalid_state "
              "pdh0 vx_rms vy_rms").split()
NUS_SIZE = "4 4 4 1 2 4 4 4 4 4 1 1 1 1 1 1 1 1"
NUS_TYPE = "F F F I I F F F F F I I I I I I I I"
EGO = np.array([12.0, 0.5, 0.0])


def nuscenes_pcd(path, n: int = 110, seed: int = 0, ego=EGO) -> np.ndarray:
    """A nuScenes RADAR_FRONT-layout binary PCD: z = 0, radial raw/compensated velocity vectors for a sensor moving
    at ``ego``, 30 % of the targets moving; returns the record array written."""
    rng = np.random.default_rng(seed)
    dt = np.dtype([(f, "<f4" if t == "F" else f"<i{s}") for f, s, t in zip(NUS_FIELDS, NUS_SIZE.split(),
                                                                         NUS_TYPE.split())])
    az, r = rng.uniform(-0.7, 0.7, n), rng.uniform(3, 200, n)
    u = np.stack([np.cos(az), np.sin(az)], axis=1)
    moving = rng.random(n) < 0.3
    v_comp = np.where(moving, rng.normal(0, 6, n), 0.0)
    v_raw = v_comp - u @ ego[:2]
    a = np.zeros(n, dt)
    a["x"], a["y"] = r * u[:, 0], r * u[:, 1]
    a["dyn_prop"], a["id"], a["rcs"] = np.where(moving, 0, 1), np.arange(n), rng.uniform(-5, 35, n)
    a["vx"], a["vy"] = (v_raw[:, None] * u).T
    a["vx_comp"], a["vy_comp"] = (v_comp[:, None] * u).T
    a["is_quality_valid"], a["ambig_state"], a["invalid_state"], a["pdh0"] = 1, 3, 0, 1
    a["x_rms"], a["y_rms"], a["vx_rms"], a["vy_rms"] = 19, 19, 17, 3
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS " + " ".join(NUS_FIELDS) +
              f"\nSIZE {NUS_SIZE}\nTYPE {NUS_TYPE}\nCOUNT " + " ".join(["1"] * 18) +
              f"\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")
    path.write_bytes(header.encode("ascii") + a.tobytes())
    return a


def run(model, cloud, seed=1):
    out, rec = apply_models([model], cloud, seed=seed, key="f0", sequence_id="seq")
    return out, rec[0]


def test_nuscenes_pcd_round_trips_byte_for_byte(tmp_path):
    nuscenes_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd", sensor="radar")
    assert [k for k, _, _ in cloud.layout.fields][:6] == ["x", "y", "z", "dyn_prop", "id", "rcs_dbsm"]
    assert cloud.fields["dyn_prop"].dtype == np.int8 and cloud.fields["id"].dtype == np.int16
    write_pointcloud(tmp_path / "out.pcd", cloud, effect="none")
    assert (tmp_path / "out.pcd").read_bytes() == (tmp_path / "in.pcd").read_bytes()


def test_radial_velocity_and_ego_velocity_from_cartesian_fields(tmp_path):
    a = nuscenes_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd", sensor="radar")
    r = np.hypot(a["x"], a["y"]).astype(float)
    expected = (a["vx"] * a["x"] + a["vy"] * a["y"]) / r
    np.testing.assert_allclose(radial_velocity_m_per_s(cloud), expected, atol=1e-5)
    v, rms = ego_velocity_from_data(cloud, planar=True)
    np.testing.assert_allclose(v, EGO, atol=1e-4)
    assert rms < 1e-4
    # the recipe's velocity wins; fields that fit no sensor velocity give zero, said so
    given = PointCloud(cloud.positions_m, cloud.fields, "radar", conditions=Conditions(ego_velocity_m_per_s=(3, 0, 0)))
    assert ego_velocity_m_per_s(given, True)[1] == "recipe"
    noisy = cloud.with_fields(vx_comp=np.random.default_rng(0).normal(0, 5, len(cloud)).astype(np.float32))
    v, source = ego_velocity_m_per_s(noisy, True)
    assert not v.any() and "fits no sensor velocity" in source


@pytest.mark.parametrize("profile", [None, "ars408"])
def test_rain_clutter_on_a_2d_radar_is_planar_radial_and_kept_by_the_devkit_filters(tmp_path, profile):
    nuscenes_pcd(tmp_path / "in.pcd", n=200)
    cloud = read_pointcloud(tmp_path / "in.pcd", sensor="radar", profile=load_radar_profile(profile))
    model = get_model("rain.radar")(rain_rate_mm_per_h=50.0, clutter_max_range_m=30.0, cfar_pfa=1e-2)
    out, rec = run(model, cloud)
    added = out.effect == Effect.ADDED
    assert added.sum() >= 3, rec.diagnostics
    assert rec.diagnostics["ego_velocity_source"].startswith("data") and not rec.diagnostics["elevation_measured"]
    p, f = out.positions_m[added], {k: v[added] for k, v in out.fields.items()}
    assert not p[:, 2].any()                                    # a 2-D radar reports z = 0
    # nuScenes devkit default filters: invalid_state in [0], dyn_prop in range(7), ambig_state in [3]
    assert (f["invalid_state"] == 0).all() and (f["dyn_prop"] < 7).all() and (f["ambig_state"] == 3).all()
    assert len(np.unique(out.fields["id"])) == len(out)
    r = np.linalg.norm(p, axis=1)
    u = p[:, :2] / r[:, None]
    v_raw = f["vx"] * u[:, 0] + f["vy"] * u[:, 1]
    v_comp = f["vx_comp"] * u[:, 0] + f["vy_comp"] * u[:, 1]
    np.testing.assert_allclose(f["vx"] * u[:, 1] - f["vy"] * u[:, 0], 0, atol=1e-4)   # radial vectors
    np.testing.assert_allclose(v_comp - v_raw, u @ EGO[:2], atol=1e-3)
    # rain seen from a car at 12 m/s: the drops ahead approach at about the ego speed (fall speed is vertical)
    assert np.all(v_raw < -0.5 * np.linalg.norm(EGO) * u[:, 0] + 1.0)


def test_cfar_threshold_rise_uses_the_doppler_of_cartesian_velocities(tmp_path):
    nuscenes_pcd(tmp_path / "in.pcd", n=200)
    cloud = read_pointcloud(tmp_path / "in.pcd", sensor="radar")
    model = get_model("rain.radar")(rain_rate_mm_per_h=50.0, clutter=True)
    _, rec = run(model, cloud)
    v_r = radial_velocity_m_per_s(cloud).astype(np.float32)
    scalar = cloud.with_fields(v_r_m_per_s=v_r, v_r_comp_m_per_s=radial_velocity_m_per_s(cloud, True))
    _, rec_scalar = run(model, scalar)
    for key in ("cfar_mean_threshold_rise_db", "cfar_max_threshold_rise_db", "points_removed"):
        assert rec.diagnostics[key] == pytest.approx(rec_scalar.diagnostics[key], rel=1e-6, abs=1e-9), key


def test_alignment_turns_cartesian_velocities_and_keeps_a_2d_radar_in_its_plane(tmp_path):
    nuscenes_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd", sensor="radar")
    model = get_model("alignment.radar")(yaw_sd_deg=3.0, pitch_sd_deg=3.0, roll_sd_deg=3.0)
    out, rec = run(model, cloud, seed=4)
    assert rec.diagnostics["rotation_deg"] > 0.5
    assert not out.positions_m[:, 2].any()
    np.testing.assert_allclose(out.ranges_m, cloud.ranges_m, rtol=1e-9)
    p = out.positions_m
    r = np.linalg.norm(p, axis=1)
    tangential = (out.fields["vx"] * p[:, 1] - out.fields["vy"] * p[:, 0]) / r
    np.testing.assert_allclose(tangential, 0, atol=1e-3)         # still along the reported ray
    np.testing.assert_allclose(radial_velocity_m_per_s(out), radial_velocity_m_per_s(cloud), atol=1e-3)
    # compensation with the assumed mounting: v_r,comp' − v_r' = v_ego · r̂'
    np.testing.assert_allclose(radial_velocity_m_per_s(out, True) - radial_velocity_m_per_s(out),
                               p[:, :2] @ EGO[:2] / r, atol=1e-3)


def test_ars408_profile_from_its_datasheet():
    p = load_radar_profile("ars408")
    assert (p.max_range_m, p.range_resolution_m, p.fov_azimuth_deg) == (250.0, 0.39, 120.0)
    assert p.velocity_resolution_m_per_s == pytest.approx(0.1194, abs=1e-4)
    assert p.elevation_measured is False and p.elevation_resolution_deg == p.fov_elevation_deg
    assert load_radar_profile({"base": "ars408", "elevation_measured": True}).elevation_measured is True
    with pytest.raises(Exception, match="true or false"):
        load_radar_profile({"elevation_measured": "no"})


def test_3d_radar_with_an_explicit_profile_is_not_flattened():
    rng = np.random.default_rng(0)
    r, az, el = rng.uniform(2, 200, 300), rng.uniform(-1, 1, 300), rng.uniform(-0.2, 0.2, 300)
    pos = r[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    cloud = PointCloud(pos, {"rcs_dbsm": rng.uniform(-10, 20, 300).astype(np.float32)}, "radar",
                       load_radar_profile(None), conditions=Conditions(ego_velocity_m_per_s=(10, 0, 0)))
    out, rec = run(get_model("rain.radar")(rain_rate_mm_per_h=50.0, cfar_pfa=1e-2), cloud)
    assert rec.diagnostics["elevation_measured"] and rec.diagnostics["ego_velocity_source"] == "recipe"
    assert out.positions_m[out.effect == Effect.ADDED, 2].any()


def test_a_cloud_without_detection_fields_says_how_to_map_one():
    cloud = PointCloud(np.ones((5, 3)), {"intensity": np.ones(5, np.float32)}, "radar", load_radar_profile(None))
    with pytest.raises(ModelError, match=r"field_map.*\{intensity: snr_db\}"):
        run(get_model("fog.radar")(), cloud)


@pytest.mark.parametrize("fields, label", [({"snr_db"}, "SNR colour"), ({"rcs_dbsm"}, "RCS colour"),
                                           ({"power_db", "rcs_dbsm"}, "power colour"), ({"v_r_m_per_s"}, "no SNR/RCS")])
def test_radar_preview_legend_names_the_field_it_colours_by(monkeypatch, fields, label):
    from roadview_noise import preview
    from roadview_noise.metrics import compare

    rng = np.random.default_rng(0)
    cloud = PointCloud(rng.uniform(2, 40, (50, 3)), {f: rng.uniform(-5, 30, 50) for f in fields}, "radar")
    seen = []
    real_legend = preview._legend
    monkeypatch.setattr(preview, "_legend", lambda w, items, e: seen.extend(items) or real_legend(w, items, e))
    preview.render_cloud(preview.ChainRun("t", [("input", cloud), ("x", cloud)], [], compare(cloud, cloud)), 160)
    assert seen[0][0] == label


def test_nuscenes_output_keeps_the_18_fields_the_devkit_asserts_and_puts_effects_in_a_sidecar(tmp_path):
    from roadview_noise.io.pointcloud import effect_sidecar_path

    nuscenes_pcd(tmp_path / "in.pcd", n=200)
    cloud = read_pointcloud(tmp_path / "in.pcd", sensor="radar")
    out, _ = run(get_model("rain.radar")(rain_rate_mm_per_h=50.0, cfar_pfa=1e-2), cloud)
    written = write_pointcloud(tmp_path / "out.pcd", out)
    lines = (tmp_path / "out.pcd").read_bytes().split(b"\n")[:11]
    # nuscenes-devkit RadarPointCloud.from_file: fixed header lines, 18 dims, invalid_state 4th from the end
    assert lines[2].split()[1:] == [f.encode() for f in NUS_FIELDS] and lines[10] == b"DATA binary"
    assert written == [tmp_path / "out.pcd", effect_sidecar_path(tmp_path / "out.pcd")]
    codes = np.fromfile(written[1], np.uint8)
    np.testing.assert_array_equal(codes, out.effect)
    back = read_pointcloud(tmp_path / "out.pcd", sensor="radar")
    assert len(back) == len(out) and set(back.fields) == set(cloud.fields)


def test_view_of_delft_raw_and_compensated_doppler_give_the_3d_ego_velocity(tmp_path):
    rng = np.random.default_rng(3)
    n, ego = 80, np.array([8.0, -0.4, 0.2])
    az, el, r = rng.uniform(-0.8, 0.8, n), rng.uniform(-0.2, 0.2, n), rng.uniform(2, 50, n)
    u = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    v_comp = np.where(rng.random(n) < 0.3, rng.normal(0, 5, n), 0.0)
    table = np.column_stack([r[:, None] * u, rng.uniform(-10, 20, n), v_comp - u @ ego, v_comp, np.zeros(n)])
    table.astype("<f4").tofile(tmp_path / "00001.bin")
    cloud = read_pointcloud(tmp_path / "00001.bin", sensor="radar")
    v, source = ego_velocity_m_per_s(cloud, planar=False)
    np.testing.assert_allclose(v, ego, atol=1e-3)
    assert source.startswith("data")


@pytest.mark.parametrize("layout", ["vod", "nuscenes"])
def test_a_dataset_layout_without_a_stated_profile_is_pointed_out(tmp_path, layout):
    """A View-of-Delft .bin or a nuScenes RADAR_* PCD augmented without a radar profile: read with the default
    generic-77ghz (200 m, 1° × 2°), and the run's warning names the dataset's built-in profile (before: silent;
    on 3 real VoD frames the generic profile's rain clutter differed from vod's, 170 vs 155 points). A stated
    profile, on the command line or as radar.yaml next to the files, silences it."""
    import json

    import yaml
    from typer.testing import CliRunner

    from roadview_noise.cli.main import app

    folder = tmp_path / "in" / "radar"
    folder.mkdir(parents=True)
    if layout == "vod":
        rng = np.random.default_rng(4)
        table = np.column_stack([rng.uniform(2, 40, (60, 3)), rng.normal(-30, 5, (60, 4))])
        table[:, 5] = table[:, 4] + 6.0 * table[:, 0] / np.linalg.norm(table[:, :3], axis=1)   # v_ego 6 m/s
        table.astype("<f4").tofile(folder / "00001.bin")
        name, glob = "vod", "radar/*.bin"
    else:
        nuscenes_pcd(folder / "00001.pcd")
        name, glob = "ars408", "radar/*.pcd"
    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump({"schema": "rvnoise.recipe/1", "seed": 1, "inputs": {"radar": glob},
                                      "chain": [{"model": "fog.radar", "params": {"visibility_m": 30}}]}))

    def warnings_of(out, *extra):
        r = CliRunner().invoke(app, ["augment", str(tmp_path / "in"), str(tmp_path / out), "--recipe", str(recipe),
                                     "--quiet", *extra])
        assert r.exit_code == 0, r.output
        entry = json.loads((tmp_path / out / "manifest.jsonl").read_text())
        return " ".join(entry.get("warnings", []))

    assert f"give radar_profile {name}" in warnings_of("o1")
    assert "RadarProfileWarning" not in warnings_of("o2", "--radar-profile", name)
    (folder / "radar.yaml").write_text(f"base: {name}\n")
    assert "RadarProfileWarning" not in warnings_of("o3")
