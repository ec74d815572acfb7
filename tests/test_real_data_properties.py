"""Properties of every registered model on real files (bench/audit_real_data.py audits all of them; here the ones
that hold, fast): zero strength is the identity, outputs stay in what the sensor can report, weather is monotone in
its strength, the same seed writes the same bytes. The real files are never committed: these tests skip without
/work/realdata or ../shared/data. The synthetic tests at the end cover the faults the audit found, for CI."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from bench.audit_real_data import (MONOTONE, VANISH, Input, changed_fraction, digest, lost_returns,
                                   luminance_contrast, range_problems, real_inputs, run, written)
from roadview_noise.compound import apply_models
from roadview_noise.profiles.lidar import with_intensity_scale
from roadview_noise.errors import ModelError
from roadview_noise.physics.lidar_intensity import intensity_step, read_intensity, resolve_profile
from roadview_noise.profiles.lidar import default_profile
from roadview_noise.registry import get_model, load_all
from roadview_noise.types import PointCloud


def real(name: str) -> Input:
    found = [i for i in real_inputs() if i.name == name]
    if not found:
        pytest.skip(f"real file {name} is absent (never committed)")
    return found[0]


LIDAR_MODELS = sorted(k for k, c in load_all().items() if c.sensor == "lidar")
CAMERA_IDENTITY = ("fog.camera", "motion_blur.camera", "rain.camera", "snow.camera", "soiling.camera",
                   "wind.camera", "windscreen.camera", "low_light.camera")
RAW_IDENTITY = ("fog.camera", "motion_blur.camera", "rain.camera", "snow.camera", "soiling.camera",
                "windscreen.camera")


@pytest.mark.parametrize("name", ["kitti-000008.bin", "nuscenes-LIDAR_TOP", "ouster-scan0.bin",
                                  "waymo-unit30-0000000.bin"])
@pytest.mark.parametrize("model_id", LIDAR_MODELS)
def test_lidar_zero_strength_is_the_identity(model_id, name):
    """Rate 0, visibility 10¹⁵ m, probability 0, σ 0: at most 0.1 % of the points change (all four: none)."""
    _, data, out = run(real(name), model_id, VANISH[model_id])
    assert changed_fraction(data, out) <= 1e-3


@pytest.mark.parametrize("name", ["kitti-000008.bin", "nuscenes-LIDAR_TOP", "waymo-unit30-0000000.bin"])
@pytest.mark.parametrize("model_id", ["rain.lidar", "snow.lidar", "fog.lidar", "ray_drop.lidar"])
def test_lidar_weather_stays_in_the_sensor_and_repeats(model_id, name, tmp_path):
    """At the default strength: finite, intensity within the profile's full scale (whole counts for 8-bit units), no
    new point beyond max_range_m, the input's .bin columns; the same seed writes the same bytes."""
    in_sensor_range_and_repeatable(real(name), model_id, tmp_path)


def in_sensor_range_and_repeatable(item: Input, model_id: str, scratch: Path) -> None:
    recipe, data, out = run(item, model_id, {})
    path = written(item, recipe, out, scratch)
    assert range_problems(item, data, out, path) == []
    first = digest(path)
    recipe, _, out = run(item, model_id, {})
    assert digest(written(item, recipe, out, scratch)) == first


def test_more_rain_loses_no_fewer_returns_on_kitti():
    """KITTI 000008, 2 seeds: lost returns at 1 / 20 / 100 mm/h rise (audit: 25, 632, 1 471)."""
    item = real("kitti-000008.bin")
    name, values = MONOTONE["rain.lidar"]
    lost = [np.mean([lost_returns(*run(item, "rain.lidar", {name: v}, seed=s)[1:]) for s in (1, 2)])
            for v in values]
    assert lost[0] < lost[1] < lost[2]


@pytest.mark.parametrize("model_id", CAMERA_IDENTITY)
def test_camera_zero_strength_is_the_identity_on_a_kitti_photo(model_id):
    _, data, out = run(real("kitti-000008.png"), model_id, VANISH[model_id])
    assert changed_fraction(data, out) <= 1e-3


@pytest.mark.parametrize("model_id", RAW_IDENTITY)
def test_raw_zero_strength_is_the_identity_on_a_real_dng(model_id, tmp_path):
    """The written DNG's DN equal the input's (a real 10-bit GBRG mosaic)."""
    from roadview_noise.io.raw import read_raw

    item = real("dng-minhtcai_camera_test")
    recipe, _, out = run(item, model_id, VANISH[model_id])
    assert changed_fraction(read_raw(item.path)[0], read_raw(written(item, recipe, out, tmp_path))[0]) <= 1e-3


def test_lower_visibility_lowers_the_contrast_of_real_photos():
    """Fog at 1 000 / 200 / 50 m on KITTI's and nuScenes' photos (ground-plane depth): RMS contrast falls."""
    for name in ("kitti-000008.png", "nuscenes-CAM_BACK_LEFT"):
        item = real(name)
        c = [luminance_contrast(run(item, "fog.camera", {"visibility_m": v})[2]) for v in (1000.0, 200.0, 50.0)]
        assert c[0] > c[1] > c[2], (name, c)


@pytest.mark.parametrize("model_id", ["fog.camera", "rain.camera", "snow.camera", "soiling.camera"])
def test_camera_weather_writes_the_input_dtype_and_repeats(model_id, tmp_path):
    in_sensor_range_and_repeatable(real("kitti-000008.png"), model_id, tmp_path)


# --- synthetic versions of the faults found (CI has no real data) -------------------------------------------


def fractional_scan(n: int = 2000, seed: int = 0, profile=None) -> PointCloud:
    """A cloud like Waymo's KITTI-format export: float intensities 0.01–1.5 (not whole counts, not within [0, 1]) on
    returns 2–60 m away, read with ``profile`` (default: the default profile, nothing stated)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) * 0.1
    pos = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(2, 60, (n, 1))
    fields = {"intensity": rng.uniform(0.01, 1.5, n).astype(np.float32)}
    return PointCloud(pos, fields, "lidar", profile or default_profile())


def test_fractional_intensities_need_a_stated_unit_which_keeps_them_continuous():
    """Nothing states the unit and the values have fractions: refused (since 2026-11-27; before, the default
    profile's photons were assumed, warned, at the file's continuous resolution). A stated float unit keeps them
    continuous; whole counts keep the photon step."""
    cloud = fractional_scan()
    assert read_intensity(cloud.fields["intensity"], cloud.positions_m).values == "floats"
    with pytest.raises(ModelError, match="have fractions and nothing states their unit"):
        resolve_profile(default_profile(), cloud.fields["intensity"], cloud.positions_m, "fog.lidar")
    stated = resolve_profile(with_intensity_scale(default_profile(), "unit", 1.5), cloud.fields["intensity"],
                             cloud.positions_m, "fog.lidar")
    assert intensity_step(stated.profile) == 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        counts = np.rint(cloud.fields["intensity"] * 1000)
        kept = resolve_profile(default_profile(), counts, cloud.positions_m, "fog.lidar")
    assert intensity_step(kept.profile) == 1.0


@pytest.mark.parametrize("model_id, params", [("fog.lidar", {"visibility_m": 1e15}),
                                              ("rain.lidar", {"rain_rate_mm_per_h": 0.0})])
def test_vanishing_weather_keeps_fractional_intensities(model_id, params):
    """Before: every intensity of a real Waymo scan (0.04–1.04) was rounded to whole photons, i.e. written as 0,
    by fog at 10⁹ m visibility: 100 % of the points changed. Now with its unit stated (unstated: refused)."""
    cloud = fractional_scan(profile=with_intensity_scale(default_profile(), "unit", 30.0))
    out, _ = apply_models([get_model(model_id)(**params)], cloud, seed=1, key="k", sequence_id="s", metrics=False)
    assert len(out.positions_m) == len(cloud.positions_m)
    np.testing.assert_allclose(out.fields["intensity"], cloud.fields["intensity"], rtol=1e-6)


@pytest.mark.parametrize("black, white", [(0.0, 65535.0), (2056.0, 15000.0)])
def test_low_light_identity_gives_a_dngs_codes_back(black, white, tmp_path):
    """Illuminance = reference, no noise: the written DNG holds the input's DN exactly. Before: a 16-bit mosaic was
    re-digitised by a second ADC (65 471 levels for 65 536 codes: 0.51 % of a real DNG's sites ±1 DN) and codes
    below black (its read noise) were raised to black (0.59 % of a real DNG, up to 98 DN)."""
    from roadview_noise.io.raw import read_raw, write_dng

    rng = np.random.default_rng(0)
    dn = np.rint(rng.uniform(black, white, (64, 96)))
    dn[:8] = np.rint(np.clip(rng.normal(black, 30.0, (8, 96)), 0, None))      # dark rows around black
    path = tmp_path / "in" / "mosaic.dng"
    path.parent.mkdir()
    write_dng(path, dn.astype(np.uint16), "RGGB", black, white)
    item = Input("synthetic", path, "raw")
    recipe, _, out = run(item, "low_light.camera", VANISH["low_light.camera"])
    (tmp_path / "out").mkdir()
    np.testing.assert_array_equal(read_raw(written(item, recipe, out, tmp_path / "out"))[0], read_raw(path)[0])


def test_waymo_read_without_its_unit_is_refused():
    """Waymo's KITTI-format scan with only its columns named (0.005–1.04): before 2026-11-27 read as photons, warned
    (fog at 30 m moved all 800 returns to 1.4 m; snow 2.5 mm/h wrote up to 5 750). Now ``augment`` fails the file,
    naming it, the values and the lines that state the unit; with them stated it runs."""
    from bench.audit_real_data import WAYMO_FIELDS

    item = real("waymo-unit30-0000000.bin")
    with pytest.raises(ModelError, match="intensities 0.00476074 … 1.03906 have fractions"):
        run(Input("waymo", item.path, "lidar", {"bin_fields": WAYMO_FIELDS}), "fog.lidar", {"visibility_m": 30.0})
    _, data, out = run(item, "fog.lidar", {"visibility_m": 30.0})
    assert 0 < lost_returns(data, out) < len(data.positions_m) / 2


def faint_scan(folder: Path, n: int = 800, seed: int = 0) -> Input:
    """A KITTI-style .bin like Waymo's scans read as photons (stated: unstated fractions are refused): targets 5–15 m
    away, intensities 0.01–0.3 (one in a hundred 1.04) — so faint that sub-mm flakes outshine them."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) * 0.1
    pos = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(5, 15, (n, 1))
    intensity = np.where(np.arange(n) % 100 == 0, 1.04, rng.uniform(0.01, 0.3, n))
    path = folder / "faint.bin"
    np.column_stack([pos, intensity]).astype(np.float32).tofile(path)
    return Input("faint", path, "lidar", {"intensity_unit": "photons"})


def test_fewer_faint_returns_lost_in_heavier_snow_is_physics(tmp_path):
    """Faint targets are outshone by small flakes, and an exponential DSD has fewer small flakes in heavier snow
    (Gunn–Marshall: N(D ≥ d) = N0/Λ e^{−Λd}, N0 ∝ S^−0.87): lost returns fall from 0.5 to 2.5 mm/h beyond seed
    noise, as the closed form does. Before: FAIL. The closed form is within 5 % of the Monte-Carlo mean."""
    from bench.audit_real_data import expected_outshone, monotone

    item = faint_scan(tmp_path)
    text = monotone(item, "snow.lidar")
    assert text.startswith("ok") and "physics" in text, text
    lost = [lost_returns(*run(item, "snow.lidar", {"snowfall_rate_mm_per_h": 0.5}, seed=s)[1:]) for s in (1, 2)]
    data = run(item, "snow.lidar", {"snowfall_rate_mm_per_h": 0.0})[1]
    assert expected_outshone(data, "snow.lidar", {"snowfall_rate_mm_per_h": 0.5}) == pytest.approx(np.mean(lost),
                                                                                                   rel=0.05)


def test_a_fall_physics_does_not_expect_still_fails(tmp_path, monkeypatch):
    """The same falling lost returns with a closed form that rises with the rate: a violation."""
    import bench.audit_real_data as audit

    monkeypatch.setattr(audit, "expected_outshone", lambda data, model_id, params: sum(params.values()))
    assert audit.monotone(faint_scan(tmp_path), "snow.lidar").startswith("FAIL")


def test_seed_noise_is_no_fall():
    from bench.audit_real_data import falls

    assert falls([100.0, 96.0, 120.0], [1.0, 1.0, 1.0]) == []          # −4 within 3 SE of the difference (4.2)
    assert falls([100.0, 95.0, 120.0], [1.0, 1.0, 1.0]) == [0]


def reflectivity_scan(n: int = 20000, seed: int = 3) -> PointCloud:
    """A cloud like nuScenes' LIDAR_TOP read without a profile: whole 8-bit range-compensated values (100 ρ) on
    returns 2–100 m away, which the data-decided unit reads as 8-bit reflectivity."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) * 0.1
    pos = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(2, 100, (n, 1))
    fields = {"intensity": np.maximum(np.round(100 * rng.uniform(0.02, 1.0, n)), 1).astype(np.float32)}
    return PointCloud(pos, fields, "lidar", default_profile())


def test_the_unit_the_data_decide_is_the_chains_input_s():
    """CNF22 (laser power variance, then rain) on nuScenes scans: power.lidar's gains give the intensities fractions,
    so rain.lidar read the same file as photons (full scale 65535), not as the 8-bit reflectivity CNF19 reads, and
    wrote intensities up to 3197–6099 into a 0–255 channel."""
    cloud = reflectivity_scan()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out, _ = apply_models([get_model("power.lidar")(), get_model("rain.lidar")(rain_rate_mm_per_h=20)], cloud,
                              seed=1, key="k", sequence_id="s", metrics=False)
    assert float(out.fields["intensity"].max()) <= 255


def test_laser_power_reads_the_unit_the_data_decide():
    """power.lidar on the same scan without a profile: the 8-bit reflectivity the weather models read is the model's
    count domain (x = I, D3.5's y = g·x + b), so the mean becomes ≈ 1.17·mean + 4.67 in whole counts ≤ 255 — not the
    default profile's photons (x = I·255/65535, which wrote ≈ 1 200 for every return)."""
    cloud = reflectivity_scan()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out, _ = apply_models([get_model("power.lidar")()], cloud, seed=1, key="k", sequence_id="s", metrics=False)
    before, after = cloud.fields["intensity"].astype(float), out.fields["intensity"].astype(float)
    assert after.max() <= 255 and np.array_equal(after, np.rint(after))
    assert abs(after.mean() - (1.17 * before.mean() + 4.67)) < 0.05 * before.mean()
