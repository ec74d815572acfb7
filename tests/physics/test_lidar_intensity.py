"""What a LiDAR's intensities are (physics/lidar_intensity.py, profiles/lidar.py): read from Ouster metadata, from the
data, checked against the stated unit — never guessed silently."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from roadview_noise.profiles.lidar import with_intensity_scale
from roadview_noise.errors import ModelError
from roadview_noise.physics.lidar_intensity import read_intensity, resolve_profile
from roadview_noise.profiles.lidar import default_profile, load_lidar_profile, os1_128, os1_128_reflectivity


def scene(kind: str, n=20000, seed=0):
    """Targets 2–100 m of reflectance 0.02–1: 8-bit calibrated reflectivity (100 ρ, whole counts) or OS1 signal
    photons (65535 ρ / R², whole counts)."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(2.0, 100.0, n)
    rho = rng.uniform(0.02, 1.0, n)
    u = rng.normal(size=(n, 3))
    pos = u / np.linalg.norm(u, axis=1, keepdims=True) * r[:, None]
    values = 100 * rho if kind == "reflectivity" else 65535 * rho / r ** 2
    return np.maximum(np.round(values), 1).astype(np.float32), pos


@pytest.mark.parametrize("kind, values", [("reflectivity", "8-bit counts"), ("signal", "counts")])
def test_read_intensity_tells_range_compensated_from_signal(kind, values):
    intensity, pos = scene(kind)
    reading = read_intensity(intensity, pos)
    assert reading.kind == kind and reading.values == values
    assert abs(reading.slope - (0.0 if kind == "reflectivity" else -2.0)) < 0.3


def test_read_intensity_says_when_it_cannot_tell():
    rng = np.random.default_rng(1)
    pos = rng.normal(size=(300, 3)) * 0.2 + 3.0                           # all at about 5 m: no range lever
    reading = read_intensity(rng.uniform(0, 1, 300).astype(np.float32), pos)
    assert reading.kind is None and reading.values == "[0, 1]" and np.isnan(reading.slope)


def test_a_stated_unit_is_followed():
    """A stated unit is not second-guessed (an earlier step, e.g. laser power variance, may change how the data
    look); values it cannot hold are refused (below)."""
    intensity, pos = scene("reflectivity")
    for profile in (os1_128(), os1_128_reflectivity()):
        scale = resolve_profile(profile, intensity, pos, "fog.lidar")
        assert scale.profile == profile and scale.warning is None and "stated by the profile" in scale.note


def test_nothing_stated_follows_the_data_loudly():
    refl, pos = scene("reflectivity")
    adopted = resolve_profile(default_profile(), refl, pos, "snow.lidar")
    expected = dataclasses.replace(os1_128_reflectivity(), name="os1-128", intensity_source="the data")
    assert adopted.profile == expected and "8-bit range-compensated reflectivity" in adopted.warning
    signal, pos = scene("signal")
    kept = resolve_profile(default_profile(), signal, pos, "snow.lidar")
    assert kept.profile == default_profile() and kept.warning is None and "the data agree" in kept.note
    rng = np.random.default_rng(2)
    unclear = resolve_profile(default_profile(), rng.uniform(1, 1000, 500).round().astype(np.float32),
                              rng.normal(size=(500, 3)) * 0.1 + 3.0, "rain.lidar")
    assert "do not tell" in unclear.warning and "lidar_profile" in unclear.warning
    assert unclear.profile == default_profile()                 # whole counts beyond 8 bits: photons, warned


def slope_scene(slope: float, n=20000, seed=3):
    """8-bit whole counts on targets at 2–100 m whose bright end falls as R^slope (0: range-compensated, −2:
    received signal, −1: in between, neither): I = 200 u (R / 2 m)^slope, u uniform in (0.02, 1]."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(2.0, 100.0, n)
    u = rng.normal(size=(n, 3))
    pos = u / np.linalg.norm(u, axis=1, keepdims=True) * r[:, None]
    return np.maximum(np.round(200 * rng.uniform(0.02, 1.0, n) * (r / 2.0) ** slope), 1).astype(np.float32), pos


@pytest.mark.parametrize("slope, kind, read_as", [(0.0, "reflectivity", "reflectivity"),
                                                  (-2.0, "signal", "signal"), (-1.0, None, "reflectivity")])
def test_8_bit_counts_are_reflectivity_unless_they_fall_as_signal(slope, kind, read_as):
    """8-bit whole counts, nothing stated: range-compensated (flat) and undecidable slopes are read as the sensor's
    8-bit calibrated reflectivity (most 8-bit channels are), warned; 1/R² stays the default photons (no warning).
    Before: the undecidable slope was read as photons (a Livox-like 8-bit channel then lost every return to fog)."""
    intensity, pos = slope_scene(slope)
    reading = read_intensity(intensity, pos)
    assert reading.values == "8-bit counts" and reading.kind == kind, reading
    scale = resolve_profile(default_profile(), intensity, pos, "fog.lidar")
    assert scale.profile.intensity_kind == read_as
    if read_as == "reflectivity":
        assert scale.profile == dataclasses.replace(os1_128_reflectivity(), name="os1-128",
                                                    intensity_source="the data")
        assert ("read as such" if kind else "read as 8-bit reflectivity, as most 8-bit channels are,") in scale.warning
        assert ("cannot tell signal from reflectivity" in scale.warning) == (kind is None)
    else:
        assert scale.warning is None and scale.profile == default_profile()


@pytest.mark.parametrize("low, high", [(0.0, 2.0), (0.0, 255.0), (0.005, 27.0)])
def test_fractional_floats_beyond_0_1_are_refused_when_nothing_states_the_unit(low, high):
    """Luminar 0–2 reflectance, View-of-Delft 0–255 floats, Waymo 0.005–27: no photon counts and no full scale in the
    data. Before: read as the default photons, warned (fog 30 m moved every Luminar and Waymo return to < 2.4 m).
    The error names the values seen and the lines that state the unit; a stated unit takes them."""
    _, pos = scene("reflectivity", n=3000)
    intensity = np.random.default_rng(4).uniform(low, high, len(pos)).astype(np.float32)
    with pytest.raises(ModelError, match=r"fog\.lidar\.intensity: intensities .* have fractions") as e:
        resolve_profile(default_profile(), intensity, pos, "fog.lidar")
    text = str(e.value)
    assert f"… {float(intensity.max()):g} have" in text and f"at least {float(intensity.max()):g}" in text
    assert "'intensity_unit: unit'" in text and "'intensity_full_scale: F'" in text and "lidar_profile" in text
    stated = with_intensity_scale(default_profile(), "unit", float(np.ceil(high)))
    assert resolve_profile(stated, intensity, pos, "fog.lidar").profile == stated


@pytest.mark.parametrize("profile", [default_profile(), os1_128_reflectivity()])
def test_returns_that_all_read_0_are_refused_stated_or_not(profile):
    """hku-mars/mlcc's Livox maps store intensity 0 for every point: no return strength, so every return was lost to
    fog 30 m. Refused; no-return cells (at the origin) reading 0 next to real returns are fine."""
    _, pos = scene("reflectivity", n=500)
    with pytest.raises(ModelError, match="every return's intensity is 0"):
        resolve_profile(profile, np.zeros(len(pos), np.float32), pos, "rain.lidar")
    grid = np.vstack([pos, np.zeros((10, 3))])
    intensity = np.concatenate([np.full(len(pos), 7.0, np.float32), np.zeros(10, np.float32)])
    assert resolve_profile(profile, intensity, grid, "rain.lidar").profile.intensity_kind == "reflectivity"


def test_impossible_values_are_refused():
    intensity, pos = scene("reflectivity")
    with pytest.raises(ModelError, match="full scale"):
        resolve_profile(os1_128_reflectivity(), intensity * 10, pos, "fog.lidar")
    with pytest.raises(ModelError, match="intensity_unit 'unit'"):
        resolve_profile(os1_128(), (intensity / 255).astype(np.float32), pos, "fog.lidar")


def test_fractions_in_0_1_are_refused_however_few_when_nothing_states_the_unit():
    """A KITTI-style frame of 50 points (mmdetection3d's test a.bin: intensities 0–0.39) was read as photons and
    written back brighter (19–740 counts); with nothing stating the unit, fractions are refused at any count."""
    intensity, pos = scene("reflectivity", n=50)
    with pytest.raises(ModelError, match="intensity_unit 'unit'"):
        resolve_profile(default_profile(), (intensity / 255).astype(np.float32), pos, "fog.lidar")


def _metadata(tmp_path, udp_profile):
    path = tmp_path / f"{udp_profile or 'none'}.json"
    meta = {"beam_altitude_angles": list(os1_128().beam_elevation_deg),
            "beam_azimuth_angles": list(os1_128().beam_azimuth_offset_deg),
            "lidar_origin_to_beam_origin_mm": 15.806, "lidar_to_sensor_transform": [0] * 11 + [36.18, 0, 0, 0, 1],
            "data_format": {"columns_per_frame": 512, **({"udp_profile_lidar": udp_profile} if udp_profile else {})}}
    path.write_text(json.dumps(meta))
    return path


@pytest.mark.parametrize("udp, kind, stated", [("RNG15_RFL8_NIR8", "reflectivity", True),
                                               ("FUSA_RNG15_RFL8_NIR8_DUAL", "reflectivity", True),
                                               ("RNG19_RFL8_SIG16_NIR16", "signal", False),
                                               ("LEGACY", "signal", False), (None, "signal", False)])
def test_ouster_metadata_names_the_channel_when_it_can(tmp_path, udp, kind, stated):
    """A packet profile without a signal channel carries only the 8-bit reflectivity: the profile states it. With a
    signal channel the file may hold either: the data decide (and warn)."""
    profile = load_lidar_profile(str(_metadata(tmp_path, udp)))
    assert profile.intensity_kind == kind and bool(profile.intensity_source) == stated and profile.columns == 512
    if stated:
        assert profile.intensity_unit == "uint8" and profile.faint_reading == "lowest"
        assert dataclasses.replace(profile, name="x", columns=2048, intensity_source="") == dataclasses.replace(
            os1_128_reflectivity(), name="x", intensity_source="")


def test_what_states_the_unit():
    assert load_lidar_profile(None).intensity_source == ""
    assert load_lidar_profile("os1-128").intensity_source == "the profile"
    assert load_lidar_profile({"detection_threshold": 2.0}).intensity_source == ""
    assert load_lidar_profile({"intensity_unit": "uint8", "intensity_full_scale": 255.0}).intensity_source
    recipe = with_intensity_scale(default_profile(), "uint8", None)
    assert "recipe" in recipe.intensity_source and recipe.intensity_step is None


def test_a_profile_mapping_restates_the_scale_as_the_recipe_does():
    """``intensity_unit``/``intensity_full_scale`` in a lidar.yaml or an inline mapping store the base sensor's
    intensities in another scale: its sensor constant and threshold (signal) or white reading (reflectivity) follow,
    as with the recipe's inputs; fields given with them are taken as given. Before: replaced alone, a 0–2 channel
    over the default OS1's photon constant and threshold read every return as too faint, and fog at 30 m moved all
    4 000 returns of the test below to 1.5 m, each written 2.0 (the full scale)."""
    mapped = load_lidar_profile({"intensity_unit": "unit", "intensity_full_scale": 2.0})
    recipe = with_intensity_scale(default_profile(), "unit", 2.0)
    assert mapped == dataclasses.replace(recipe, intensity_source=mapped.intensity_source)
    assert mapped.detection_threshold == pytest.approx(default_profile().detection_threshold * 2.0 / 65535.0)
    assert load_lidar_profile({"intensity_full_scale": 2.0, "detection_threshold": 0.5}).detection_threshold == 0.5
    hdl = load_lidar_profile({"base": "hdl-32e", "intensity_unit": "unit", "intensity_full_scale": 2.0})
    assert hdl.reflectivity_white_reading == pytest.approx(100.0 * 2.0 / 255.0) and hdl.intensity_step is None
    refl = load_lidar_profile({"intensity_kind": "reflectivity", "intensity_unit": "unit", "intensity_full_scale": 2.0})
    assert (refl.sensor_constant, refl.detection_threshold) == (os1_128().sensor_constant,
                                                                os1_128().detection_threshold)


def reflectance_bin(folder, n=4000, seed=5, full_scale=2.0):
    """A Luminar-like KITTI-layout .bin: range-compensated float reflectance 0.05–2 (fractions) on returns 2–60 m
    away around the sensor, elevations within ±10°."""
    rng = np.random.default_rng(seed)
    r, az, el = rng.uniform(2, 60, n), rng.uniform(-np.pi, np.pi, n), np.radians(rng.uniform(-10, 10, n))
    table = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el),
                      rng.uniform(0.05, full_scale, n)], 1)
    path = folder / "lidar" / "seq0" / "000000.bin"
    path.parent.mkdir(parents=True)
    table.astype("<f4").tofile(path)
    return path, table


def test_unstated_fractions_fail_their_file_in_augment_and_preview_and_a_stated_unit_runs(tmp_path):
    """The refusal reaches the user with the file's name: augment's manifest entry (status failed), preview's
    ``rvnoise: FILE: …`` line (exit 2). The two lines in a lidar.yaml next to the file state the unit: fog at 30 m
    then writes no intensity above the stated full scale and keeps most returns nearer than 10 m (before, unstated:
    every return moved to < 2.4 m, intensities up to 55 in a 0–2 channel)."""
    import yaml
    from typer.testing import CliRunner

    from roadview_noise.cli.main import app
    from roadview_noise.io.pointcloud import read_pointcloud
    from roadview_noise.manifest import read_manifest

    path, table = reflectance_bin(tmp_path / "in")
    recipe = tmp_path / "fog.yaml"
    recipe.write_text(yaml.safe_dump({"chain": [{"model": "fog.lidar", "params": {"visibility_m": 30}}], "seed": 1,
                                      "inputs": {"lidar": "lidar/**/*.bin"}}))
    cli = CliRunner()
    r = cli.invoke(app, ["augment", str(tmp_path / "in"), str(tmp_path / "o1"), "--recipe", str(recipe), "--quiet"])
    assert r.exit_code == 1
    [entry] = read_manifest(tmp_path / "o1" / "manifest.jsonl")
    assert entry["status"] == "failed" and entry["error"].startswith("lidar/seq0/000000.bin: fog.lidar.intensity: ")
    assert "have fractions and nothing states their unit" in entry["error"] and "intensity_full_scale" in entry["error"]
    r = cli.invoke(app, ["preview", "--recipe", str(recipe), str(path), "-o", str(tmp_path / "p.png"),
                         "--panel-px", "160"])
    assert r.exit_code == 2 and f"rvnoise: {path}: fog.lidar.intensity: intensities" in r.output.replace("\n", "")
    (path.parent / "lidar.yaml").write_text("intensity_unit: unit\nintensity_full_scale: 2.0\n")
    r = cli.invoke(app, ["augment", str(tmp_path / "in"), str(tmp_path / "o2"), "--recipe", str(recipe), "--quiet"])
    assert r.exit_code == 0, r.output
    written = tmp_path / "o2" / "lidar" / "seq0" / "000000.bin"
    out = read_pointcloud(written)
    effect = np.fromfile(f"{written}.rv_effect", np.uint8)                  # the .bin's effect sidecar
    assert len(effect) == len(out.positions_m) and np.count_nonzero(effect == 2) > 0       # some moved to fog
    assert out.fields["intensity"].max() <= 2.0
    near_in = np.count_nonzero(np.linalg.norm(table[:, :3], axis=1) < 10)
    kept = out.positions_m[effect <= 1]                                         # KEPT, ATTENUATED
    assert np.count_nonzero(np.linalg.norm(kept, axis=1) < 10) > 0.5 * near_in


@pytest.mark.parametrize("model_id", ["fog.lidar", "rain.lidar", "snow.lidar", "ray_drop.lidar", "power.lidar",
                                      "power_electronics.lidar"])
def test_every_model_that_reads_intensities_refuses_unstated_fractions(model_id):
    """Weather, ray drop and laser power read the unit through the same decision (the chain's input:
    ``chain_intensity_scale``), so none of them reads fractions as photons (occlusion reads intensities only behind
    partial patches, through the weather's ``cloud_rays``)."""
    from roadview_noise.compound import apply_models
    from roadview_noise.registry import get_model
    from roadview_noise.types import PointCloud

    _, pos = scene("reflectivity", n=3000)
    intensity = np.random.default_rng(6).uniform(0.0, 2.0, len(pos)).astype(np.float32)
    cloud = PointCloud(pos, {"intensity": intensity}, "lidar", default_profile())
    with pytest.raises(ModelError, match=f"{model_id}.intensity: intensities .* have fractions"):
        apply_models([get_model(model_id)()], cloud, seed=1, key="k", sequence_id="s", metrics=False)
