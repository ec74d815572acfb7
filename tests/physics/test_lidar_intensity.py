"""What a LiDAR's intensities are (physics/lidar_intensity.py, profiles/lidar.py): read from Ouster metadata, from the
data, checked against the stated unit — never guessed silently."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from roadview_noise.dataset import with_intensity_scale
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
    unclear = resolve_profile(default_profile(), rng.uniform(1, 200, 500).astype(np.float32),
                              rng.normal(size=(500, 3)) * 0.1 + 3.0, "rain.lidar")
    assert "do not tell" in unclear.warning and "lidar_profile" in unclear.warning


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
