"""4D radar models: weather attenuation/detection/clutter, obstruction, alignment, power (models.md §4)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from roadview_noise.compound import apply_models
from roadview_noise.errors import InputError, ModelError
from roadview_noise.model import Scope, Stage
from roadview_noise.physics.radar_link import noise_floor_dbm, two_way_loss_db
from roadview_noise.profiles.radar import BUILTIN, load_radar_profile
from roadview_noise.recipe import load_recipe
from roadview_noise.registry import get_model
from roadview_noise.provenance import Effect
from roadview_noise.types import Conditions, PointCloud, RadarProfile

ROOT = Path(__file__).resolve().parents[2]
C_DB, T_DB = 88.0, 12.0          # radar constant and threshold of the synthetic sensor


def radar_cloud(n: int = 3000, seed: int = 0, fields=("rcs_dbsm", "v_r_m_per_s", "v_r_comp_m_per_s", "snr_db",
                                                        "power_db"), profile: RadarProfile | None = None,
                conditions: Conditions = Conditions()) -> PointCloud:
    """Detections of a radar with SNR = C + RCS − 40 log10 r, kept where SNR ≥ T (the clear-weather cloud)."""
    rng = np.random.default_rng(seed)
    m = 4 * n
    r = 2 + 198 * rng.random(m) ** 1.5
    az, el = np.deg2rad(rng.uniform(-58, 58, m)), np.deg2rad(rng.uniform(-14, 14, m))
    rcs = rng.normal(5, 10, m)
    snr = C_DB + rcs - 40 * np.log10(r)
    ok = np.flatnonzero(snr >= T_DB)[:n]
    r, az, el, rcs, snr = r[ok], az[ok], el[ok], rcs[ok], snr[ok]
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    all_fields = {"rcs_dbsm": rcs, "v_r_m_per_s": rng.normal(0, 3, len(r)),
                  "v_r_comp_m_per_s": rng.normal(0, 1, len(r)), "snr_db": snr, "power_db": snr - 90.0}
    return PointCloud(pos, {k: all_fields[k].astype(np.float32) for k in fields}, "radar",
                      profile or load_radar_profile(None), conditions=conditions)


def run(model, cloud, seed=1, key="frame-0", sequence="seq"):
    out, rec = apply_models([model], cloud, seed=seed, key=key, sequence_id=sequence)
    return out, rec[0]


def real(cloud):
    return cloud.effect != Effect.ADDED


# --- registration -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("model_id, stage, scope", [
    ("rain.radar", Stage.MEDIUM, Scope.FRAME), ("fog.radar", Stage.MEDIUM, Scope.FRAME),
    ("snow.radar", Stage.MEDIUM, Scope.FRAME), ("occlusion.radar", Stage.WINDOW, Scope.SEQUENCE),
    ("alignment.radar", Stage.EMITTER, Scope.SEQUENCE), ("power.radar", Stage.ELECTRONICS, Scope.FRAME)])
def test_registered(model_id, stage, scope):
    cls = get_model(model_id)
    assert cls.sensor == "radar" and cls.stage == stage and cls.scope == scope and cls.summary


def test_d35_defaults():
    assert get_model("rain.radar")().rain_rate_mm_per_h == 20.0
    assert get_model("fog.radar")().visibility_m == 30.0
    assert get_model("snow.radar")().snowfall_rate_mm_per_h == 2.5
    assert get_model("occlusion.radar")().seed_probability == 2e-3


# --- weather ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("model_id, params, gamma", [
    ("rain.radar", {}, 9.7176), ("rain.radar", {"rain_law": "sander"}, 8.4546), ("fog.radar", {}, 1.1794),
    ("snow.radar", {}, 2.05125), ("fog.radar", {"temperature_c": 20.0}, 2.713 * 0.37474)])
def test_two_way_loss_applied_to_every_power_field(model_id, params, gamma):
    cloud = radar_cloud()
    params = {**params, "clutter": False} if model_id != "fog.radar" else params
    out, rec = run(get_model(model_id)(**params), cloud)
    assert rec.diagnostics["specific_attenuation_db_per_km"] == pytest.approx(gamma, rel=1e-3)
    snr = cloud.fields["snr_db"]
    kept = np.flatnonzero(snr - two_way_loss_db(gamma, cloud.ranges_m) >= snr.min())
    assert len(out) == len(kept)                 # removed exactly the points pushed below the clear minimum
    loss = two_way_loss_db(gamma, cloud.ranges_m[kept])
    for name in ("snr_db", "power_db", "rcs_dbsm"):
        np.testing.assert_allclose(out.fields[name], cloud.fields[name][kept] - loss, atol=2e-3)
    np.testing.assert_array_equal(out.positions_m, cloud.positions_m[kept])
    assert out.effect.dtype == np.uint8 and np.all(out.effect == Effect.ATTENUATED)
    assert rec.diagnostics["points_removed"] == len(cloud) - len(kept)


def test_rcs_left_alone_when_the_radar_compensates_weather():
    profile = dataclasses.replace(load_radar_profile(None), rcs_compensates_weather=True)
    cloud = radar_cloud(profile=profile)
    out, _ = run(get_model("rain.radar")(clutter=False), cloud)
    loss = two_way_loss_db(9.7176, cloud.ranges_m)
    kept = cloud.fields["snr_db"] - loss >= cloud.fields["snr_db"].min()
    assert 0 < len(out) == kept.sum() < len(cloud)
    np.testing.assert_array_equal(out.fields["rcs_dbsm"], cloud.fields["rcs_dbsm"][kept])
    np.testing.assert_allclose(out.fields["snr_db"], cloud.fields["snr_db"][kept] - loss[kept], atol=2e-3)


def test_profile_threshold_and_power_only_clouds():
    profile = dataclasses.replace(load_radar_profile(None), snr_threshold_db=20.0)
    cloud = radar_cloud(profile=profile)
    out, rec = run(get_model("fog.radar")(), cloud)
    assert rec.diagnostics["threshold_source"] == "profile" and rec.diagnostics["threshold_db"] == 20.0
    assert out.fields["snr_db"].min() >= 20.0
    # power only, in dBm: SNR threshold + receiver noise floor
    dbm = dataclasses.replace(profile, power_unit="dBm")
    power_cloud = radar_cloud(fields=("rcs_dbsm", "v_r_m_per_s", "power_db"), profile=dbm)
    _, rec = run(get_model("fog.radar")(), power_cloud)
    assert rec.diagnostics["detection_statistic"] == "power_db" and rec.diagnostics["threshold_source"] == "profile"
    assert rec.diagnostics["threshold_db"] == pytest.approx(20.0 + noise_floor_dbm(20e6, 12.0))
    # relative power (the default unit): the noise floor is unknown, so the frame's weakest power
    _, rec = run(get_model("fog.radar")(), radar_cloud(fields=("rcs_dbsm", "v_r_m_per_s", "power_db"),
                                                        profile=profile))
    assert rec.diagnostics["threshold_source"] == "frame quantile 0"
    assert rec.diagnostics["threshold_db"] == pytest.approx(T_DB - 90.0, abs=0.5)
    # without a profile threshold: the frame's weakest power
    _, rec = run(get_model("fog.radar")(), radar_cloud(fields=("rcs_dbsm", "power_db")))
    assert rec.diagnostics["threshold_source"] == "frame quantile 0"
    assert rec.diagnostics["threshold_db"] == pytest.approx(T_DB - 90.0, abs=0.5)


def test_rcs_only_cloud_view_of_delft_style():
    cloud = radar_cloud(fields=("rcs_dbsm", "v_r_m_per_s", "v_r_comp_m_per_s"), profile=load_radar_profile("vod"))
    out, rec = run(get_model("rain.radar")(detector="fixed"), cloud)
    d = rec.diagnostics
    assert d["detection_statistic"] == "rcs_dbsm-40log10(r)" and d["radar_constant_db"] == pytest.approx(0.0, abs=1e-4)
    assert d["threshold_db"] == pytest.approx(T_DB - C_DB, abs=0.5)
    assert d["clutter_points"] > 0 and set(out.fields) == {"rcs_dbsm", "v_r_m_per_s", "v_r_comp_m_per_s"}
    added = ~real(out)
    stat = out.fields["rcs_dbsm"][added] - 40 * np.log10(out.ranges_m[added])
    assert np.all(stat >= d["threshold_db"] - 1e-3)


def test_cloud_without_detection_fields_is_refused():
    with pytest.raises(ModelError, match="snr_db, power_db or rcs_dbsm"):
        run(get_model("fog.radar")(), radar_cloud(fields=("v_r_m_per_s",)))


def test_zero_rate_is_identity():
    cloud = radar_cloud()
    for model in (get_model("rain.radar")(rain_rate_mm_per_h=0.0), get_model("snow.radar")(snowfall_rate_mm_per_h=0)):
        out, rec = run(model, cloud)
        np.testing.assert_array_equal(out.positions_m, cloud.positions_m)
        for k, v in cloud.fields.items():
            np.testing.assert_array_equal(out.fields[k], v)
        assert np.all(out.effect == Effect.KEPT) and rec.diagnostics["clutter_points"] == 0


@pytest.mark.parametrize("params", [{"detector": "fixed"}, {"detector": "cfar", "cfar_pfa": 1e-2}])
def test_rain_adds_labelled_clutter_near_the_sensor(params):
    ego = (10.0, 0.0, 0.0)
    cloud = radar_cloud(conditions=Conditions(ego_velocity_m_per_s=ego, wind_velocity_m_per_s=(0.0, 4.0, 0.0)))
    out, rec = run(get_model("rain.radar")(**params), cloud)
    assert rec.diagnostics["detector"] == params["detector"]
    added = ~real(out)
    assert added.sum() == rec.diagnostics["clutter_points"] > 0
    assert np.all(out.effect[added] == Effect.ADDED)
    r = out.ranges_m[added]
    assert r.min() >= 1.0 and r.max() <= 20.0
    assert np.all(out.fields["snr_db"][added] >= rec.diagnostics["threshold_db"])
    np.testing.assert_allclose(out.fields["power_db"][added], out.fields["snr_db"][added] - 90.0, atol=1e-3)
    # radar constant consistent: SNR = C + RCS − 40 log r on the added points too
    np.testing.assert_allclose(out.fields["snr_db"][added] - out.fields["rcs_dbsm"][added]
                               + 40 * np.log10(r), C_DB, atol=1e-2)
    # Doppler of falling drops: over ground (compensated) they move down and with the wind, never toward the ego
    p = out.positions_m[added]
    v_ground = out.fields["v_r_comp_m_per_s"][added] - p @ np.array([0.0, 4.0, 0.0]) / r
    assert np.all(v_ground * np.sign(p[:, 2]) <= 0.6)
    np.testing.assert_allclose(out.fields["v_r_comp_m_per_s"][added],
                               out.fields["v_r_m_per_s"][added] + p @ np.array(ego) / r, atol=1e-4)
    assert abs(rec.diagnostics["clutter_points"] - rec.diagnostics["clutter_expected_points"]) < \
        5 * math.sqrt(rec.diagnostics["clutter_expected_points"]) + 5


def test_fog_adds_no_clutter_and_snow_less_than_rain():
    cloud = radar_cloud()
    out, rec = run(get_model("fog.radar")(), cloud)
    assert np.all(real(out)) and "clutter_points" not in rec.diagnostics
    _, snow = run(get_model("snow.radar")(detector="fixed"), cloud)
    _, rain = run(get_model("rain.radar")(detector="fixed"), cloud)
    assert 0 < snow.diagnostics["clutter_expected_points"] < rain.diagnostics["clutter_expected_points"]
    _, snow = run(get_model("snow.radar")(), cloud)      # cfar: P_fa per clutter-dominated cell, a few points
    assert 0 < snow.diagnostics["clutter_expected_points"] < 1e-4 * 1800 * 95 * 100


@pytest.mark.parametrize("params", [{"detector": "fixed"}, {"detector": "cfar", "cfar_pfa": 1e-2}])
def test_same_rng_same_output_and_input_untouched(params):
    cloud = radar_cloud()
    before = {k: v.copy() for k, v in cloud.fields.items()}
    model = get_model("rain.radar")(**params)
    a, _ = run(model, cloud)
    b, _ = run(model, cloud)
    np.testing.assert_array_equal(a.positions_m, b.positions_m)
    for k in a.fields:
        np.testing.assert_array_equal(a.fields[k], b.fields[k])
    for k, v in before.items():
        np.testing.assert_array_equal(cloud.fields[k], v)
    c, _ = run(model, cloud, key="frame-1")
    assert len(c) != len(a) or not np.array_equal(c.positions_m, a.positions_m)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), rates=st.lists(st.floats(0.0, 150.0), min_size=2, max_size=4))
def test_heavier_rain_never_adds_real_detections(seed, rates):
    cloud = radar_cloud(n=600, seed=seed % 7)
    kept, max_range = [], []
    for rate in sorted(rates):
        for law in ("itu", "sander"):
            out, _ = run(get_model("rain.radar")(rain_rate_mm_per_h=rate, rain_law=law), cloud, seed=seed)
            kept.append((law, rate, int(real(out).sum()), float(out.ranges_m[real(out)].max(initial=0.0))))
    for law in ("itu", "sander"):
        rows = [k for k in kept if k[0] == law]
        assert all(a[2] >= b[2] and a[3] >= b[3] for a, b in zip(rows, rows[1:]))


def test_max_detection_range_shrinks_with_rate():
    cloud = radar_cloud(n=4000)
    ranges = [run(get_model("rain.radar")(rain_rate_mm_per_h=r, clutter=False), cloud)[1].diagnostics["max_range_m"]
              for r in (0.0, 10.0, 50.0, 150.0, 400.0)]
    assert ranges[0] == pytest.approx(cloud.ranges_m.max())
    assert all(a >= b for a, b in zip(ranges, ranges[1:])) and ranges[-1] < ranges[0]


def test_cfar_is_the_default_and_keeps_clutter_few():
    """Default CA-CFAR (P_fa 1e-4, 16 cells): clutter far below the fixed threshold's and below P_fa × cells, at
    C − t = 76 dB (the synthetic sensor) and 83 dB; the fixed-threshold count explodes."""
    model = get_model("rain.radar")()
    assert (model.detector, model.cfar_pfa, model.cfar_reference_cells) == ("cfar", 1e-4, 16)
    counts = {}
    for margin in (76.0, 83.0):
        profile = dataclasses.replace(load_radar_profile(None), snr_threshold_db=C_DB - margin)
        cloud = radar_cloud(n=1500, profile=profile)
        for detector in ("cfar", "fixed"):
            _, rec = run(get_model("rain.radar")(detector=detector), cloud)
            d = rec.diagnostics
            assert d["radar_constant_db"] - d["threshold_db"] == pytest.approx(margin, abs=0.1)
            counts[margin, detector] = d["clutter_expected_points"]
        assert d["detector"] == "fixed" and "cfar_points_lost" not in d
    assert counts[83.0, "fixed"] > 5 * counts[76.0, "fixed"] > 10_000
    assert counts[76.0, "cfar"] < 20 and counts[83.0, "cfar"] < 1e-4 * 1800 * 95 * 100
    assert counts[83.0, "cfar"] < 1e-3 * counts[83.0, "fixed"]


def _weak_near_target_scene(v_r_near: float) -> PointCloud:
    """The synthetic clear cloud plus a weak target at 2 m on boresight (SNR 3 dB above the 12 dB profile threshold)
    with radial velocity ``v_r_near``; stationary radar."""
    profile = dataclasses.replace(load_radar_profile(None), snr_threshold_db=T_DB)
    cloud = radar_cloud(profile=profile)
    cloud = cloud.select(cloud.ranges_m > 10.0)
    near = {"rcs_dbsm": T_DB + 3.0 - C_DB + 40 * math.log10(2.0), "v_r_m_per_s": v_r_near, "v_r_comp_m_per_s": 0.0,
            "snr_db": T_DB + 3.0, "power_db": T_DB + 3.0 - 90.0}
    scene = cloud.concat(np.array([[2.0, 0.005, 0.005]]), {k: np.array([v]) for k, v in near.items()})
    return dataclasses.replace(scene, origin=None, effect=None)          # an input: no provenance yet


def test_cfar_loses_a_weak_near_target_in_heavy_rain():
    """At 2 m in 50 mm/h the boresight cell's clutter-to-noise ratio is ≈ 10 dB: the CFAR threshold rises by
    10 log10(1 + CNR) > 3 dB and the weak target is lost; the fixed threshold keeps it. A target whose Doppler lies
    outside the rain spectrum of its cell, and targets beyond 10 m, are unaffected."""
    cloud = _weak_near_target_scene(0.0)
    near = np.flatnonzero(cloud.ranges_m < 3.0)
    assert len(near) == 1
    fixed, f_rec = run(get_model("rain.radar")(rain_rate_mm_per_h=50.0, detector="fixed", clutter_max_range_m=1.5),
                       cloud)
    cfar, c_rec = run(get_model("rain.radar")(rain_rate_mm_per_h=50.0, clutter_max_range_m=1.5), cloud)
    real_fixed, real_cfar = fixed.select(real(fixed)), cfar.select(real(cfar))
    assert np.any(real_fixed.ranges_m < 3.0) and not np.any(real_cfar.ranges_m < 3.0)
    assert c_rec.diagnostics["cfar_points_lost"] >= 1 and c_rec.diagnostics["cfar_max_threshold_rise_db"] > 3.0
    # far targets: identical detections (the clutter-to-noise ratio falls as r⁻², the rise is < 0.5 dB past 10 m)
    far_f, far_c = real_fixed.select(real_fixed.ranges_m > 10.0), real_cfar.select(real_cfar.ranges_m > 10.0)
    np.testing.assert_array_equal(far_f.positions_m, far_c.positions_m)
    assert c_rec.diagnostics["cfar_points_lost"] == c_rec.diagnostics["points_removed"] - \
        f_rec.diagnostics["points_removed"]
    # Doppler separates a target from the clutter of its cell (boresight rain: |v| ≤ 9.65 sin 1° ≈ 0.17 m/s)
    moving = _weak_near_target_scene(5.0)
    out, _ = run(get_model("rain.radar")(rain_rate_mm_per_h=50.0, clutter_max_range_m=1.5), moving)
    assert np.any(out.select(real(out)).ranges_m < 3.0)
    # no radial-velocity field: the static-world Doppler −v_ego·r̂ (0 for a stationary radar) → lost
    no_v = _weak_near_target_scene(0.0)
    no_v = PointCloud(no_v.positions_m, {k: v for k, v in no_v.fields.items() if k != "v_r_m_per_s"}, "radar",
                      no_v.profile)
    out, _ = run(get_model("rain.radar")(rain_rate_mm_per_h=50.0, clutter_max_range_m=1.5), no_v)
    assert not np.any(out.select(real(out)).ranges_m < 3.0)


def test_cfar_threshold_rise_matches_the_cell_clutter():
    """Rise of the near target = 10 log10(1 + α μ/σ_t) with μ, σ_t of its resolution cell (physics oracle in
    tests/physics/test_radar_clutter.py); recomputed here from the diagnostics' radar constant and threshold."""
    from roadview_noise.physics.radar_cfar import CaCfar
    from roadview_noise.physics.radar_clutter import ResolutionGrid, clutter_cells, radar_wavelength_m, rain_drops

    cloud = _weak_near_target_scene(0.0)
    _, rec = run(get_model("rain.radar")(rain_rate_mm_per_h=50.0), cloud)
    d = rec.diagnostics
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1035, 1.0, 20.0)
    cells = clutter_cells(rain_drops(50.0), grid, radar_wavelength_m(77e9), (0.0, 0.0, 0.0), d["radar_constant_db"],
                          d["threshold_db"], d["specific_attenuation_db_per_km"], CaCfar(1e-4, 16))
    y = cells.ratio_at(np.array([[2.0, 0.005, 0.005]]), np.array([0.0]))[0]
    assert d["cfar_max_threshold_rise_db"] == pytest.approx(10 * math.log10(1 + 12.452470560622764 * y), rel=1e-6)
    assert 3.0 < d["cfar_max_threshold_rise_db"] < 20.0


def test_doppler_bins_follow_the_profile():
    fine = radar_cloud(n=800)
    coarse = dataclasses.replace(fine, profile=dataclasses.replace(fine.profile, velocity_resolution_m_per_s=1.0))
    _, a = run(get_model("rain.radar")(detector="fixed"), fine)
    _, b = run(get_model("rain.radar")(detector="fixed"), coarse)
    assert b.diagnostics["clutter_expected_points"] > 1.2 * a.diagnostics["clutter_expected_points"]
    assert "doppler_resolution_m_per_s" not in get_model("rain.radar")().params()


def test_recipe_ego_velocity_reaches_the_model_and_hits_the_doppler_cache():
    """``inputs.ego_velocity_m_per_s`` sets every frame's conditions; a constant ego velocity computes the per-cell
    Doppler tables once."""
    from roadview_noise.dataset import discover, load
    from roadview_noise.physics.radar_clutter import cell_doppler_probabilities
    from roadview_noise.recipe import parse_recipe

    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "chain": [{"model": "rain.radar"}], "seed": 1,
                           "inputs": {"radar": "radar/**/*.pcd", "ego_velocity_m_per_s": [13, 0, 0]}})
    root = ROOT / "sample_data"
    samples = discover(root, recipe)
    assert len(samples) == 3
    model = get_model("rain.radar")()
    misses = []
    for sample in samples:
        cloud = load(sample, root, recipe)
        assert cloud.conditions.ego_velocity_m_per_s == (13.0, 0.0, 0.0)
        run(model, cloud, key=sample.relpath)
        misses.append(cell_doppler_probabilities.cache_info().misses)
    assert misses[0] == misses[-1]


# --- obstruction ------------------------------------------------------------------------------------------------

def test_occlusion_expected_seeds():
    model = get_model("occlusion.radar")()
    cloud = radar_cloud(n=200)
    seeds = [model.draw_sequence(np.random.default_rng(s), cloud)["seeds"] for s in range(2000)]
    expected = 2e-3 * 1800
    assert np.mean(seeds) == pytest.approx(expected, abs=4 * math.sqrt(expected / 2000))


def test_occlusion_removes_exactly_the_blocked_cells_and_is_static():
    from roadview_noise.physics.radar_clutter import angular_cell_index, angular_edges_rad

    cloud = radar_cloud(n=20000)
    model = get_model("occlusion.radar")(seed_probability=0.02)
    out, rec = run(model, cloud)
    blocked = set(rec.state["blocked_cells"])
    cells = angular_cell_index(cloud.positions_m, angular_edges_rad(120, 1), angular_edges_rad(30, 2))
    gone = np.isin(cells, list(blocked))
    assert len(out) == len(cloud) - gone.sum() and rec.diagnostics["points_removed"] == gone.sum() > 0
    np.testing.assert_array_equal(out.positions_m, cloud.positions_m[~gone])
    assert rec.state["seeds"] <= len(blocked) <= 9 * rec.state["seeds"]
    _, rec2 = run(model, radar_cloud(n=500, seed=3), key="frame-7")
    assert rec2.state == rec.state                                       # one pattern per sensor instance
    _, rec3 = run(model, cloud, sequence="other-seq")
    assert rec3.state != rec.state
    moving = get_model("occlusion.radar")(seed_probability=0.02, static=False)
    _, f1 = run(moving, cloud, key="a")
    _, f2 = run(moving, cloud, key="b")
    assert f1.drawn["blocked_cells"] != f2.drawn["blocked_cells"] and f1.state == {}


def test_occlusion_zero_probability_and_attenuate_mode():
    cloud = radar_cloud()
    out, _ = run(get_model("occlusion.radar")(seed_probability=0.0), cloud)
    np.testing.assert_array_equal(out.positions_m, cloud.positions_m)
    weather, _ = run(get_model("rain.radar")(), cloud)
    model = get_model("occlusion.radar")(seed_probability=0.05, mode="attenuate", two_way_loss_db=6.0)
    out, rec = run(model, weather)
    assert rec.diagnostics["points_removed"] < rec.diagnostics["points_blocked"]
    assert np.all(out.fields["snr_db"] >= rec.diagnostics["threshold_db"])
    assert np.sum(out.effect == Effect.ADDED) <= np.sum(weather.effect == Effect.ADDED)
    full, _ = run(get_model("occlusion.radar")(seed_probability=1.0, mode="attenuate", two_way_loss_db=0.0), cloud)
    np.testing.assert_array_equal(full.positions_m, cloud.positions_m)
    with pytest.raises(ModelError):
        get_model("occlusion.radar")(patch_min_cells=3, patch_max_cells=2)


# --- alignment and power ----------------------------------------------------------------------------------------

def test_alignment_default_is_identity_and_rotation_keeps_rays():
    cloud = radar_cloud(conditions=Conditions(ego_velocity_m_per_s=(15.0, 0.0, 0.0)))
    out, _ = run(get_model("alignment.radar")(), cloud)
    np.testing.assert_allclose(out.positions_m, cloud.positions_m, atol=1e-12)
    model = get_model("alignment.radar")(yaw_sd_deg=2.0, pitch_sd_deg=1.0, roll_sd_deg=0.5)
    out, rec = run(model, cloud)
    np.testing.assert_allclose(out.ranges_m, cloud.ranges_m, rtol=1e-12)
    np.testing.assert_array_equal(out.fields["v_r_m_per_s"], cloud.fields["v_r_m_per_s"])
    yaw = math.radians(rec.state["yaw_deg"])
    boresight = np.flatnonzero(np.abs(cloud.positions_m[:, 1:]).max(axis=1) < 0.02 * cloud.ranges_m)
    if len(boresight):  # a point near boresight turns by yaw (pitch/roll small)
        p, q = cloud.positions_m[boresight[0]], out.positions_m[boresight[0]]
        assert math.atan2(q[1], q[0]) - math.atan2(p[1], p[0]) == pytest.approx(yaw, abs=0.04)
    r_hat_new, r_hat_old = out.positions_m / out.ranges_m[:, None], cloud.positions_m / cloud.ranges_m[:, None]
    np.testing.assert_allclose(out.fields["v_r_comp_m_per_s"] - cloud.fields["v_r_comp_m_per_s"],
                               15.0 * (r_hat_new[:, 0] - r_hat_old[:, 0]), atol=1e-4)
    _, other = run(model, cloud, key="frame-9")
    assert other.state == rec.state


def test_power_noise():
    cloud = radar_cloud(n=5000)
    out, _ = run(get_model("power.radar")(), cloud)
    assert out is cloud
    out, rec = run(get_model("power.radar")(power_sd_db=2.0), cloud)
    delta = out.fields["snr_db"] - cloud.fields["snr_db"]
    np.testing.assert_allclose(out.fields["power_db"] - cloud.fields["power_db"], delta, atol=1e-4)
    np.testing.assert_allclose(out.fields["rcs_dbsm"] - cloud.fields["rcs_dbsm"], delta, atol=1e-4)
    assert np.std(delta) == pytest.approx(2.0, rel=0.05) and abs(np.mean(delta)) < 0.1
    assert len(out) == len(cloud)


# --- profiles and recipes ---------------------------------------------------------------------------------------

def test_radar_profiles(tmp_path):
    assert set(BUILTIN) == {"generic-77ghz", "rehearse", "vod", "ars408", "astyx-6455", "oculii-eagle", "ars548",
                            "arbe-phoenix"}
    assert load_radar_profile(None).name == "generic-77ghz" and load_radar_profile("vod").max_range_m == 100.0
    f = tmp_path / "r.yaml"
    f.write_text(yaml.safe_dump({"base": "rehearse", "snr_threshold_db": 11, "rcs_compensates_weather": True}))
    p = load_radar_profile(str(f))
    assert (p.name, p.snr_threshold_db, p.rcs_compensates_weather, p.max_range_m) == ("rehearse", 11.0, True, 300.0)
    assert load_radar_profile({"base": "vod", "azimuth_resolution_deg": 2}).azimuth_resolution_deg == 2.0
    with pytest.raises(InputError, match="unknown radar profile keys"):
        load_radar_profile({"fov_az": 3})
    with pytest.raises(InputError, match="no radar profile"):
        load_radar_profile("ars-999")
    with pytest.raises(InputError, match="> 0"):
        load_radar_profile({"range_resolution_m": 0})
    p = load_radar_profile({"base": "rehearse", "power_unit": "dBm", "velocity_resolution_m_per_s": 0.2})
    assert (p.power_unit, p.velocity_resolution_m_per_s) == ("dBm", 0.2)
    assert load_radar_profile(None).power_unit == "relative"
    with pytest.raises(InputError, match="power_unit"):
        load_radar_profile({"power_unit": "W"})


@pytest.mark.parametrize("name, models", [
    ("cnf25-radar", ("rain.radar", "occlusion.radar")), ("cnf26-radar", ("fog.radar", "occlusion.radar")),
    ("cnf27-radar", ("snow.radar", "occlusion.radar")), ("weather-rain-radar", ("rain.radar",)),
    ("weather-fog-radar", ("fog.radar",)), ("weather-snow-radar", ("snow.radar",))])
def test_recipes_load(name, models):
    recipe = load_recipe(ROOT / "recipes" / f"{name}.yaml")
    assert recipe.model_ids == models and recipe.sensor == "radar"


def test_clutter_skipped_without_rcs_or_points():
    _, rec = run(get_model("rain.radar")(), radar_cloud(fields=("snr_db", "v_r_m_per_s")))
    assert rec.diagnostics["clutter_points"] == 0 and "rcs_dbsm" in rec.diagnostics["clutter_skipped"]
    empty = radar_cloud().select(np.zeros(3000, dtype=bool)[: len(radar_cloud())])
    out, rec = run(get_model("rain.radar")(), empty)
    assert len(out) == 0 and rec.diagnostics["clutter_points"] == 0 and rec.diagnostics["points_in"] == 0


def test_log_r4_is_nan_at_the_origin_and_40_log10_r_elsewhere():
    from roadview_noise.models.radar.detection import _log_r4

    r = np.array([0.0, 1.0, 10.0, 2.5])
    out = _log_r4(r)
    assert np.isnan(out[0]) and np.array_equal(out[1:], 40 * np.log10(r[1:]))
    assert np.array_equal(_log_r4(r[1:]), out[1:]) and len(_log_r4(np.zeros(0))) == 0
