"""ray_drop.lidar: identity at strength 0, never adds points, drops more at longer range and lower reflectance
(properties), beyond max range always, dropped rays stay rays for the weather, both back-ends."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lidar_scans import scan

from roadview_noise.compound import apply_models
from roadview_noise.errors import ModelError
from roadview_noise.io.ray_drop_model import read_model, write_model
from roadview_noise.models.lidar.ray_drop import RayDropLidar
from roadview_noise.models.lidar.rain import RainLidar
from roadview_noise.physics.lidar_intensity import sensor_constant
from roadview_noise.physics.lidar_rays import cloud_rays
from roadview_noise.physics.ray_drop import AdditiveLogistic
from roadview_noise.physics.scan_cells import scan_cells
from roadview_noise.profiles.lidar import carla_64
from roadview_noise.provenance import Effect


def run(models, cloud, key="f0", seed=2):
    return apply_models(models, cloud, seed=seed, key=key, sequence_id="s")


def mean_drop_probability(model, cloud) -> float:
    return run([model], cloud)[1][0].diagnostics["mean_drop_probability"]


@pytest.mark.parametrize("grid", [False, True])
def test_strength_zero_is_the_identity(grid):
    cloud = scan(columns=256, range_m=80.0, reflectance=0.05, grid=grid)
    out, rec = run([RayDropLidar(strength=0.0)], cloud)
    assert np.array_equal(out.positions_m, cloud.positions_m) and rec[0].diagnostics["dropped"] == 0
    assert np.array_equal(out.fields["intensity"], cloud.fields["intensity"])


coefficients = st.fixed_dictionaries({
    "log_gain": st.floats(-3, 3), "range_exponent": st.floats(-3, 1.9), "incidence_exponent": st.floats(0, 3),
    "log_signal_sd": st.floats(0.05, 3), "floor_drop_probability": st.floats(0, 0.3)})


@settings(max_examples=25, deadline=None)
@given(coefficients, st.floats(2, 100), st.floats(1.05, 3), st.floats(0.02, 1.0), st.integers(0, 2 ** 31))
def test_drops_more_at_longer_range_and_lower_reflectance_and_never_adds(coef, r, factor, rho, seed):
    """On a sensor with continuous intensities (CARLA: the reading is ρ), so that no rounding of the stored value
    blurs a small step in range."""
    model = RayDropLidar(**coef)
    near, far = (scan(carla_64(), columns=64, range_m=d, reflectance=rho) for d in (r, r * factor))
    dark = scan(carla_64(), columns=64, range_m=r, reflectance=rho / factor)
    p_near, p_far, p_dark = (mean_drop_probability(model, c) for c in (near, far, dark))
    assert p_far >= p_near - 1e-12 and p_dark >= p_near - 1e-12
    out, rec = apply_models([model], near, seed=seed, key="k", sequence_id="s")
    assert len(out) <= len(near) and np.all(out.origin >= 0)                     # never adds points
    assert len(out) == len(near) - rec[0].diagnostics["dropped"]


def test_strictly_more_drops_far_and_dark_with_the_defaults():
    p = {(r, rho): mean_drop_probability(RayDropLidar(), scan(columns=128, range_m=r, reflectance=rho))
         for r in (10.0, 40.0) for rho in (0.05, 0.5)}
    assert p[(40.0, 0.05)] > p[(10.0, 0.05)] > p[(10.0, 0.5)] and p[(40.0, 0.05)] > p[(40.0, 0.5)]


def test_beyond_max_range_always_drops():
    far = scan(columns=64, range_m=130.0, reflectance=1.0)                        # OS1-128: 120 m
    out, rec = run([RayDropLidar(floor_drop_probability=0.0, log_gain=10.0)], far)
    assert len(out) == 0 and rec[0].diagnostics["beyond_max_range"] == len(far)


def test_grid_cells_become_no_return_cells():
    cloud = scan(columns=256, range_m=60.0, reflectance=0.03, grid=True)
    out, rec = run([RayDropLidar()], cloud)
    removed = out.effect == Effect.REMOVED
    assert len(out) == len(cloud) and removed.sum() == rec[0].diagnostics["dropped"] > 0
    assert np.all(out.positions_m[removed] == 0) and np.all(out.fields["ring"] == cloud.fields["ring"])
    assert cloud_rays(out, "w", "fill").empty.sum() == removed.sum()           # the weather sees them as empty rays


def test_dropped_rays_of_a_list_are_empty_rays_for_the_weather():
    """CNF28–30 (Eq. 1): a list loses the dropped points; the weather's firing grid finds exactly their cells empty
    and can return weather from them."""
    r = np.where(np.arange(128)[:, None] < 30, 0.0, 45.0) * np.ones((1, 512))     # sky rows above
    cloud = scan(columns=512, range_m=r, reflectance=0.04)
    out, rec = run([RayDropLidar()], cloud)
    dropped = np.setdiff1d(np.arange(len(cloud)), out.origin)
    assert len(dropped) == rec[0].diagnostics["dropped"] > 100
    before, after = scan_cells(cloud, cloud.profile), scan_cells(out, out.profile)
    newly_empty = np.setdiff1d(after.empty, before.empty)
    assert np.array_equal(np.sort(newly_empty), np.sort(before.cell[dropped]))
    assert len(cloud_rays(out, "w", "fill").listed.ring) == len(after.empty)
    rained, rec = run([RayDropLidar(), RainLidar(rain_rate_mm_per_h=50.0)], cloud)
    weather = rained.effect == Effect.ADDED
    assert weather.sum() > 0 and rec[1].diagnostics["added"] == weather.sum()


def test_list_without_firing_grid_falls_back_to_own_values():
    cloud = scan(columns=256, range_m=30.0)
    rng = np.random.default_rng(0)
    jumbled = dataclasses.replace(cloud, positions_m=cloud.positions_m * rng.uniform(0.5, 2, (len(cloud), 1))
                                  + rng.normal(0, 0.3, cloud.positions_m.shape))
    _, rec = run([RayDropLidar()], jumbled)
    assert "own signal and range" in rec[0].diagnostics["features"]


def test_learned_back_end_json_and_onnx_agree(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    model = AdditiveLogistic(("log_signal", "log_range", "cos_incidence"),
                             (np.array([0.0, 1.0, 3.0]), np.array([1.0, 4.0]), np.array([0.1, 0.5, 1.0])),
                             (np.array([0.0, -1.5, -4.0]), np.array([0.0, 1.0]), np.array([0.0, -0.5, -1.0])), -0.5)
    js, ox = write_model(tmp_path / "m.json", model, {"test": True}), write_model(tmp_path / "m.onnx", model, {})
    f = np.random.default_rng(1).uniform([-2, 0, 0, -0.4], [5, 5, 1, 0.4], (2000, 4))
    np.testing.assert_allclose(read_model(js).drop_probability(f), model.drop_probability(f), rtol=1e-12)
    np.testing.assert_allclose(read_model(ox).drop_probability(f), model.drop_probability(f), atol=2e-6)
    cloud = scan(columns=256, range_m=50.0, reflectance=0.05)
    (out_j, rec_j), (out_o, rec_o) = (run([RayDropLidar(backend="learned", model_file=str(p))], cloud)
                                      for p in (js, ox))
    assert rec_j[0].diagnostics["dropped"] > 0 and rec_j[0].diagnostics["model_file_sha256"]
    assert abs(len(out_j) - len(out_o)) <= 2                       # float32 ONNX: a boundary draw may differ


def test_learned_back_end_needs_a_model_file(tmp_path):
    with pytest.raises(ModelError, match="model_file"):
        RayDropLidar(backend="learned")
    bad = tmp_path / "bad.json"
    bad.write_text('{"schema": "something else"}')
    with pytest.raises(Exception, match="bad.json"):
        run([RayDropLidar(backend="learned", model_file=str(bad))], scan(columns=64))


def test_ray_drop_keeps_the_datasheet_receiver_and_a_first_step_reads_its_input_once():
    cloud = scan(range_m=np.random.default_rng(5).uniform(30, 150, (128, 512)), reflectance=1.0)   # counts 3 … 73
    datasheet = cloud_rays(cloud, "w", "ignore", calibrate=False).receiver
    calibrated = cloud_rays(cloud, "w", "ignore").receiver
    assert calibrated.threshold < datasheet.threshold       # faint returns: the weather's receiver is more sensitive
    assert datasheet.threshold == cloud.profile.detection_threshold / sensor_constant(cloud.profile)
    # the chain's input as `recorded`: the same receiver whether it shares the step input's arrays or is a copy
    copy = dataclasses.replace(cloud, positions_m=cloud.positions_m.copy(),
                               fields={k: v.copy() for k, v in cloud.fields.items()})
    fainter = dataclasses.replace(copy, fields={**copy.fields, "intensity": copy.fields["intensity"] // 2})
    shared = cloud_rays(dataclasses.replace(cloud, recorded=cloud), "w", "ignore").receiver
    assert shared == cloud_rays(dataclasses.replace(cloud, recorded=copy), "w", "ignore").receiver == calibrated
    assert cloud_rays(dataclasses.replace(cloud, recorded=fainter), "w", "ignore").receiver.threshold < \
        calibrated.threshold
