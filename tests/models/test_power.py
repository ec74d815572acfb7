"""power.lidar / power_electronics.lidar (models.md §3.7): per-beam gain and bias, proportional intensity noise."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.errors import ModelError
from roadview_noise.model import Scope, Stage
from roadview_noise.models.lidar.power import PowerElectronicsLidar, PowerLidar
from roadview_noise.physics.lidar_geometry import velodyne_to_xyz
from roadview_noise.profiles.lidar import carla_64, os1_128, vls_128
from roadview_noise.registry import get_model, load_all
from roadview_noise.seeding import derive_rng
from roadview_noise.types import PointCloud
from tests.lidar_scans import scan

PLATES_PCT = np.array([10.0, 20.0, 40.0, 80.0])
MEAN_RESPONSE = np.array([16.37, 28.07, 51.47, 98.27])          # models.md §3.7 / §8 oracle, 8-bit counts
NOISELESS = dict(gain_sd=0.0, bias_sd_counts=0.0, noise_sd_factor=0.0)


def cloud_of(profile, intensity, columns: int = 8, with_ring: bool = True) -> PointCloud:
    """``columns`` returns per beam (range 5–60 m, nominal elevation); intensity a scalar or one per column."""
    ring, col = (a.ravel() for a in np.meshgrid(np.arange(profile.channels), np.arange(columns), indexing="ij"))
    r = 5.0 + 55.0 * (col + 0.5) / columns
    alpha = np.deg2rad(col * 360.0 / columns + np.asarray(profile.beam_azimuth_offset_deg)[ring])
    omega = np.deg2rad(np.asarray(profile.beam_elevation_deg))[ring]
    fields = {"intensity": np.broadcast_to(np.asarray(intensity, dtype=np.float32), (profile.channels, columns)).ravel()}
    if with_ring:
        fields["ring"] = ring.astype(np.uint16)
    return PointCloud(velodyne_to_xyz(r, alpha, omega), fields, "lidar", profile)


def apply(model, cloud, seed: int = 0, state=None):
    if state is None:
        state = model.draw_sequence(np.random.default_rng(seed + 100), cloud)
    return model.apply(cloud, state=state, drawn={}, rng=np.random.default_rng(seed))


def plate_cloud(profile, columns: int = 4, **kw) -> PointCloud:
    """The four D3.5 plates on every beam: x % converted to the profile's unit by full-scale matching."""
    x = np.tile(PLATES_PCT, columns // 4)
    return cloud_of(profile, x * profile.intensity_full_scale / 255.0, columns=columns, **kw)


def test_registered():
    models = load_all()
    assert models["power.lidar"] is PowerLidar and models["power_electronics.lidar"] is PowerElectronicsLidar
    assert PowerLidar.stage == Stage.EMITTER and PowerLidar.scope == Scope.SEQUENCE
    assert PowerElectronicsLidar.stage == Stage.ELECTRONICS
    m = PowerLidar()
    assert (m.gain_mean, m.gain_sd, m.bias_mean_counts, m.bias_sd_counts, m.noise_sd_factor, m.mode) == \
        (1.17, 0.084, 4.67, 2.64, 0.14, "fgi")


def test_mean_parameters_give_the_oracle_response():
    """models.md §3.7: with mean gain and bias and no noise, 10/20/40/80 % → 16.37/28.07/51.47/98.27 counts."""
    profile = carla_64()                                                       # unit intensity: not rounded
    out, diag = apply(PowerLidar(**NOISELESS), plate_cloud(profile))
    counts = out.fields["intensity"].astype(np.float64) * 255.0
    np.testing.assert_allclose(counts.reshape(-1, 4), np.broadcast_to(MEAN_RESPONSE, (64, 4)), atol=1e-4)
    assert diag["mean_gain"] == pytest.approx(1.17)


def test_uint8_sensor_rounds_to_counts():
    out, _ = apply(PowerLidar(**NOISELESS), plate_cloud(vls_128()))
    np.testing.assert_array_equal(out.fields["intensity"].reshape(-1, 4)[0], np.round(MEAN_RESPONSE))
    assert out.fields["intensity"].dtype == np.float32


def test_photon_counts_use_the_full_scale():
    profile = os1_128()
    out, _ = apply(PowerLidar(**NOISELESS), plate_cloud(profile))
    np.testing.assert_allclose(out.fields["intensity"].reshape(-1, 4)[0] * 255.0 / 65535.0, MEAN_RESPONSE,
                               rtol=1e-6)


@pytest.mark.parametrize("profile", [carla_64(), vls_128(), os1_128()], ids=lambda p: p.name)
def test_ideal_sensor_is_identity(profile):
    """Gain 1, bias 0, no noise: the unit conversion goes there and back exactly."""
    rng = np.random.default_rng(1)
    values = rng.uniform(0, profile.intensity_full_scale, profile.channels * 8)
    if profile.name == "vls-128":
        values = np.round(values)
    cloud = cloud_of(profile, 0.0).with_fields(intensity=values)
    out, _ = apply(PowerLidar(gain_mean=1.0, bias_mean_counts=0.0, **NOISELESS), cloud)
    np.testing.assert_allclose(out.fields["intensity"], values, rtol=1e-12)


def test_sensor_instances_follow_the_d35_distribution():
    """200 instances × 128 beams = 25 600 draws. Bounds are 5 standard errors: the mean has SE σ/sqrt(n)
    (gain: 0.084/160 = 5.3e-4, so ±0.0026 — inside the ±0.01 of the acceptance criterion), the sample SD
    σ/sqrt(2(n−1))."""
    model = PowerLidar()
    cloud = cloud_of(vls_128(), 50.0, columns=1)
    draws = [model.draw_sequence(derive_rng(7, "sequence", f"drive_{i:03d}", model.id), cloud) for i in range(200)]
    for key, mean, sd in (("gain", 1.17, 0.084), ("bias_counts", 4.67, 2.64)):
        x = np.concatenate([d[key] for d in draws])
        n = len(x)
        assert n == 25600
        assert abs(x.mean() - mean) < 5 * sd / np.sqrt(n)
        assert abs(x.std(ddof=1) - sd) < 5 * sd / np.sqrt(2 * (n - 1))
    assert json.loads(json.dumps(draws[0])) == draws[0]


@pytest.mark.parametrize("noise_sd_factor, expected_sd", [(0.0, [2.77, 3.13, 4.27, 7.22]),
                                                          (0.14, [3.60, 5.02, 8.38, 15.54])])
def test_spread_over_sensors_matches_the_oracle(noise_sd_factor, expected_sd):
    """models.md §3.7: beam-to-beam SD sqrt((0.084x)² + 2.64²), with the 0.14·y noise the total SD. 100 instances ×
    128 beams; at least 12 800 independent beam draws per plate, so 5 SE of the SD is 5/sqrt(25 600) = 3.1 %."""
    model = PowerLidar(noise_sd_factor=noise_sd_factor)
    cloud = plate_cloud(carla_64(), columns=8)
    y = []
    for i in range(100):
        state = model.draw_sequence(derive_rng(3, "sequence", i, model.id), cloud)
        out, _ = model.apply(cloud, state=state, drawn={}, rng=derive_rng(3, "frame", i, model.id))
        y.append(out.fields["intensity"].astype(np.float64).reshape(-1, 4) * 255.0)
    y = np.concatenate(y)
    np.testing.assert_allclose(y.std(axis=0, ddof=1), expected_sd, rtol=5 / np.sqrt(2 * 12800))
    np.testing.assert_allclose(y.mean(axis=0), MEAN_RESPONSE, atol=5 * 15.54 / np.sqrt(12800))


def test_one_sequence_shares_the_gains_and_another_does_not():
    profile = vls_128()
    frame1, frame2 = cloud_of(profile, 40.0), cloud_of(profile, 60.0)
    model = PowerLidar(noise_sd_factor=0.0)
    out1, (rec1,) = apply_models([model], frame1, seed=9, key="a/1.bin", sequence_id="a")
    out2, (rec2,) = apply_models([model], frame2, seed=9, key="a/2.bin", sequence_id="a")
    _, (rec3,) = apply_models([model], frame1, seed=9, key="b/1.bin", sequence_id="b")
    assert rec1.state == rec2.state and rec1.state["gain"] != rec3.state["gain"]
    ring = frame1.fields["ring"].astype(int)
    gain, bias = np.asarray(rec1.state["gain"])[ring], np.asarray(rec1.state["bias_counts"])[ring]
    for x, out in ((40.0, out1), (60.0, out2)):
        np.testing.assert_array_equal(out.fields["intensity"], np.clip(np.round(gain * x + bias), 0, 255))


def test_additive_mode():
    """D3.5 §5.2.2 reading: y = x + N(0, 5²); no per-beam state. Unit profile so nothing is rounded."""
    model = PowerLidar(mode="additive")
    cloud = cloud_of(carla_64(), 100.0 / 255.0, columns=400)
    assert model.draw_sequence(np.random.default_rng(0), cloud) == {}
    out, diag = apply(model, cloud, state={})
    noise = out.fields["intensity"].astype(np.float64) * 255.0 - 100.0
    n = len(noise)
    assert abs(noise.std(ddof=1) - 5.0) < 5 * 5.0 / np.sqrt(2 * (n - 1))
    assert abs(noise.mean()) < 5 * 5.0 / np.sqrt(n)
    assert "mean_gain" not in diag


def test_split_electronics_equals_the_whole_model_on_mean_parameters():
    profile = carla_64()
    cloud = plate_cloud(profile)
    split = [PowerLidar(split_electronics=True, **NOISELESS),
             PowerElectronicsLidar(bias_sd_counts=0.0, noise_sd_factor=0.0)]
    out, (gain_step, bias_step) = apply_models(split, cloud, seed=1, key="k", sequence_id="s")
    assert set(gain_step.state) == {"gain"} and set(bias_step.state) == {"bias_counts"}
    whole, _ = apply(PowerLidar(**NOISELESS), cloud)
    np.testing.assert_allclose(out.fields["intensity"], whole.fields["intensity"], rtol=1e-6)


def test_split_gain_is_the_same_draw_as_the_whole_model():
    cloud = plate_cloud(vls_128())
    whole = PowerLidar().draw_sequence(derive_rng(1, "sequence", "s", "power.lidar"), cloud)
    gain_only = PowerLidar(split_electronics=True).draw_sequence(derive_rng(1, "sequence", "s", "power.lidar"), cloud)
    assert gain_only["gain"] == whole["gain"]


def test_no_returns_keep_zero_and_clipping():
    profile = vls_128()
    cloud = cloud_of(profile, 250.0)
    pos = cloud.positions_m.copy()
    pos[::3] = 0.0
    intensity = cloud.fields["intensity"].copy()
    intensity[::3] = 0.0
    grid = dataclasses.replace(cloud, positions_m=pos, grid_shape=(128, 8)).with_fields(intensity=intensity)
    out, diag = apply(PowerLidar(), grid)
    assert np.all(out.fields["intensity"][::3] == 0.0)
    assert out.fields["intensity"].max() == 255.0                     # 1.17·250 saturates the 8-bit sensor
    assert diag["clipped_fraction"] > 0.5 and diag["points"] == int(np.any(pos != 0, axis=1).sum())
    low_cloud = cloud_of(profile, 2.0)                                # (a uint8 cloud all ≤ 1 is refused)
    low, diag_low = apply(PowerLidar(bias_mean_counts=-20.0, **NOISELESS), low_cloud)
    assert np.all(low.fields["intensity"] == 0.0) and diag_low["clipped_fraction"] == 1.0


def test_ring_recovered_when_absent():
    profile = vls_128()
    a, _ = apply(PowerLidar(), cloud_of(profile, 30.0))
    b, _ = apply(PowerLidar(), cloud_of(profile, 30.0, with_ring=False))
    np.testing.assert_array_equal(a.fields["intensity"], b.fields["intensity"])


def test_same_rng_same_output_and_input_untouched():
    cloud = plate_cloud(vls_128())
    before = cloud.fields["intensity"].copy()
    a, _ = apply(PowerLidar(), cloud, seed=3)
    b, _ = apply(PowerLidar(), cloud, seed=3)
    c, _ = apply(PowerLidar(), cloud, seed=4)
    np.testing.assert_array_equal(a.fields["intensity"], b.fields["intensity"])
    assert not np.array_equal(a.fields["intensity"], c.fields["intensity"])
    np.testing.assert_array_equal(cloud.fields["intensity"], before)
    np.testing.assert_array_equal(a.positions_m, cloud.positions_m)


def test_diagnostics():
    cloud = plate_cloud(carla_64())
    out, diag = apply(PowerLidar(**NOISELESS), cloud)
    assert diag["mean_intensity_in"] == pytest.approx(np.mean(PLATES_PCT) / 255.0, rel=1e-6)
    assert diag["mean_intensity_out"] == pytest.approx(np.mean(MEAN_RESPONSE) / 255.0, rel=1e-4)
    assert all(type(v) in (int, float) for v in diag.values())


def test_refusals():
    cloud = plate_cloud(vls_128())
    with pytest.raises(ModelError, match="intensity"):
        apply(PowerLidar(), dataclasses.replace(cloud, fields={"ring": cloud.fields["ring"]}))
    with pytest.raises(ModelError, match="profile"):
        apply(PowerLidar(), dataclasses.replace(cloud, profile=None), state={"gain": [1.0], "bias_counts": [0.0]})
    with pytest.raises(ModelError, match="beams"):
        apply(PowerLidar(), cloud, state={"gain": [1.0] * 64, "bias_counts": [0.0] * 64})
    with pytest.raises(ModelError, match="split_electronics"):
        PowerLidar(mode="additive", split_electronics=True)
    with pytest.raises(ModelError):
        PowerLidar(noise_sd_factor=-0.1)


@pytest.mark.parametrize("weather", [("snow.lidar", {"snowfall_rate_mm_per_h": 2.5}),
                                     ("fog.lidar", {"visibility_m": 100.0})])
def test_power_noise_before_the_weather_leaves_the_receiver_as_recorded(weather):
    """CNF22–24 order: power variance (emitter, with D3.5's bias and 0.14·I noise) then the weather. The weather's
    receiver is calibrated on the cloud as recorded, not on the noised one: the noise leaves some returns far below
    the sensor's threshold, which calibrated from them would make the sensor sensitive to every faint flake or
    droplet (snow 2.5 mm/h: 27× lower threshold, a return on every empty ray)."""
    rng = np.random.default_rng(5)
    cloud = scan(os1_128(), columns=256, range_m=rng.uniform(3.0, 60.0, (128, 256)), reflectance=0.3, grid=True)
    model_id, params = weather
    weather_model = get_model(model_id)(**params)
    _, alone = apply_models([weather_model], cloud, seed=1, key="k", sequence_id="s", metrics=False)
    _, chained = apply_models([PowerLidar(), weather_model], cloud, seed=1, key="k", sequence_id="s", metrics=False)
    assert chained[1].diagnostics["detection_threshold"] == alone[0].diagnostics["detection_threshold"]
    assert chained[1].diagnostics["detection_threshold_source"] == alone[0].diagnostics["detection_threshold_source"]
