"""fog.lidar, rain.lidar, snow.lidar (models.md §3.1–§3.4): oracles, one intensity scale (photons, 8-bit and [0, 1]
reflectivity give the same decisions), labels, identity, determinism, monotonicity, full range images with no-return
cells, and the real OS1-128 scan."""

from __future__ import annotations

import dataclasses
import json
import math
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from roadview_noise.compound import CNFS, apply_models
from roadview_noise.errors import ModelError
from roadview_noise.model import Stage
from roadview_noise.models.lidar.alignment import AlignmentLidar
from roadview_noise.models.lidar.fog import FogLidar
from roadview_noise.models.lidar.rain import RainLidar
from roadview_noise.models.lidar.snow import SnowLidar
from roadview_noise.physics import lidar_particles, lidar_weather
from roadview_noise.physics.lidar_medium import soft_target_signal, soft_target_table
from roadview_noise.physics.receiver import Receiver
from roadview_noise.physics.lidar_intensity import reported_intensity, sensor_constant
from roadview_noise.profiles.lidar import kitti_hdl64, os1_128, os1_128_reflectivity
from roadview_noise.registry import load_all
from roadview_noise.provenance import Effect
from roadview_noise.types import PointCloud

PHOTONS = dataclasses.replace(os1_128(), detection_threshold=2.42)      # the D3.4 fog threshold (models.md §3.0)
WEATHER = {"fog.lidar": (FogLidar, "visibility_m"), "rain.lidar": (RainLidar, "rain_rate_mm_per_h"),
           "snow.lidar": (SnowLidar, "snowfall_rate_mm_per_h")}
HEAVY = {"fog.lidar": FogLidar(visibility_m=30.0), "rain.lidar": RainLidar(rain_rate_mm_per_h=50.0),
         "snow.lidar": SnowLidar(snowfall_rate_mm_per_h=5.0)}


def cloud_at(ranges, intensity, profile=PHOTONS, seed=0, grid=False) -> PointCloud:
    """Points at the given ranges along random directions (each point its own ray); ``grid``: as a 1 × N range
    image, so that output point i is input point i."""
    rng = np.random.default_rng(seed)
    r = np.asarray(ranges, dtype=float)
    az, el = rng.uniform(-np.pi, np.pi, len(r)), rng.uniform(-0.3, 0.3, len(r))
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    return PointCloud(pos, {"intensity": np.broadcast_to(np.asarray(intensity, np.float64), r.shape).copy()},
                      "lidar", profile, grid_shape=(1, len(r)) if grid else None)


def street(n=4000, seed=1, profile=PHOTONS) -> PointCloud:
    """Targets 1–100 m: half with Lambertian photon intensities ``K ρ / r²`` (K = full scale), half with
    range-independent intensities 5–300 (like a range-compensated channel, which Hahner's fog scales up with R²)."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(1.0, 100.0, n)
    lambertian = 65535 * rng.uniform(0.02, 0.9, n) / r ** 2
    intensity = np.clip(np.where(np.arange(n) % 2 == 0, lambertian, rng.uniform(5, 300, n)), 3.5, 65535)
    return cloud_at(r, intensity, profile, seed)


def quiet(profile):
    """The profile with a receiver whose noise is negligible (a billion photons at the threshold, threshold 10⁹
    noise SDs): detection becomes the noise-free threshold, for tests of geometry and bookkeeping."""
    return dataclasses.replace(profile, receiver="apd", photons_at_threshold=1e12, threshold_over_noise=1e9,
                               excess_noise_factor=1.0)


def run(model, cloud, seed=3):
    out, rec = apply_models([model], cloud, seed=seed, key="k", sequence_id="s")
    return out, rec[0].diagnostics


def target_kept(out) -> np.ndarray:
    """Points still at their input position (a grid's removed cells are all-zero)."""
    return np.isin(out.effect, (Effect.KEPT, Effect.ATTENUATED)) & np.any(out.positions_m != 0, 1)


# --- registration -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model_id", sorted(WEATHER))
def test_registered_medium_lidar_models(model_id):
    cls = load_all()[model_id]
    assert cls is WEATHER[model_id][0]
    assert cls.stage == Stage.MEDIUM and cls.sensor == "lidar" and cls.summary
    assert "§3." in cls.__doc__ and "Hahner" in cls.__doc__ + sys.modules[cls.__module__].__doc__
    names = {s.name for s in cls.param_specs()}
    assert WEATHER[model_id][1] in names and "return_mode" in names


def test_d35_defaults():
    assert FogLidar().visibility_m == 30.0
    assert RainLidar().rain_rate_mm_per_h == 20.0
    assert SnowLidar().snowfall_rate_mm_per_h == 2.5
    with pytest.raises(ModelError):
        RainLidar(min_drop_diameter_mm=7.0)


@pytest.mark.parametrize("cnf", ["CNF19", "CNF20", "CNF21", "CNF22", "CNF23", "CNF24"])
def test_cnf_chains_name_these_models(cnf):
    chain = CNFS[cnf].chains["lidar"]
    assert chain[1] in WEATHER and chain[0] in ("alignment.lidar", "power.lidar")


# --- fog oracles ----------------------------------------------------------------------------------------------------

C = 299_792_458.0


def fog_peak_direct(alpha: float, beta: float, tau_h: float, k: float, r1: float, r2: float) -> tuple[float, float]:
    """Peak of K π β ∫_0^{2τ} sin²(πt/2τ) ξ(r_t) e^{−2α r_t}/r_t² (c dt/2) over the apparent range R of an empty ray
    (r_t = R + cτ/2 − ct/2 with Hahner's shift; ξ from r1 to r2), by the trapezoid rule in t — independent of the
    model's table."""
    t = np.linspace(0, 2 * tau_h, 2001)
    best = (0.0, 0.0)
    for big_r in np.arange(0.3, r2 + C * tau_h, 0.002):
        r = big_r + C * tau_h / 2 - C * t / 2
        xi = np.clip((r - r1) / (r2 - r1), 0, 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(r > r1, xi * np.exp(-2 * alpha * r) / r ** 2, 0.0)
        s = k * math.pi * beta * np.trapezoid(np.sin(np.pi * t / (2 * tau_h)) ** 2 * f, t) * C / 2
        if s > best[0]:
            best = (s, big_r)
    return best


def test_fog_surviving_range_of_hard_targets():
    """I = 100 photons, threshold 2.42 photons, V = 30 m: targets survive (in place) up to ln(I/I_thr)/(2α) = 18.6 m,
    beyond that they are removed (models.md §3.2): the extinction alone (no backscatter, β = 0), so no fog return
    competes; a recorded target keeps its recorded value × e^{−2αR}, no noise is added to it."""
    ranges = np.arange(2.0, 60.0, 0.1)
    prof = dataclasses.replace(PHOTONS, overlap_start_m=0.9, overlap_full_m=1.0)
    out, diag = run(FogLidar(visibility_m=30.0, backscatter_times_visibility_per_sr=0.0),
                    cloud_at(ranges, 100.0, prof, grid=True))
    alpha = math.log(20) / 30
    r_max = math.log(100 / 2.42) / (2 * alpha)
    assert r_max == pytest.approx(18.6, abs=0.05)
    assert diag["alpha_per_m"] == pytest.approx(0.09986, rel=1e-3)
    kept = target_kept(out)
    assert np.all(kept[ranges < r_max - 1e-6]) and not np.any(kept[ranges > r_max + 1e-6])
    surviving = out.ranges_m[kept]
    assert surviving.max() == pytest.approx(ranges[ranges < r_max].max())
    # stored as the sensor stores photons: whole counts
    np.testing.assert_array_equal(out.fields["intensity"][kept], np.round(100 * np.exp(-2 * alpha * ranges[kept])))
    assert diag["moved"] == diag["added"] == 0
    assert diag["removed"] + diag["attenuated"] == len(ranges)


def test_fog_sensor_constant_replaces_targets_beyond_the_crossover():
    """Default fog (sensor constant K = 65535 photons·m², τ_H = 10 ns, OS1 overlap 0.5 → 5 m), V = 30 m: every ray
    returns the fog's peak S_fog ≈ 32 photons at ≈ 1.4 m, measured in the SPAD's photon noise (σ ≈ √(S_fog + B)), so a
    10⁴-photon target stays in place (attenuated) while S e^{−2αR} clearly exceeds the measured fog, i.e. up to
    R* = ln(S/S_fog)/(2α) ≈ 29 m, and is replaced by the fog beyond; nothing is removed. The fog returns spread
    around the noise-free peak in intensity (mean within 3 %) and range (jitter of the peak, mean within 5 cm)."""
    prof = dataclasses.replace(PHOTONS, detection_threshold=3.28)
    ranges = np.arange(4.5, 60.0, 0.05)
    out, diag = run(FogLidar(visibility_m=30.0), cloud_at(ranges, 1e4, prof, grid=True))
    alpha, beta = math.log(20) / 30, 0.046 / 30
    s_fog, fog_range = fog_peak_direct(alpha, beta, 10e-9, 65535.0, prof.overlap_start_m, prof.overlap_full_m)
    assert 25 < s_fog < 40 and 1.0 < fog_range < 2.0
    sigma = math.sqrt(s_fog + 1.0)                         # photon noise with one background photon (os1-128)
    near, far = (math.log(1e4 / (s_fog + k * sigma)) / (2 * alpha) for k in (5, -4))
    assert 25 < near < far < 36
    kept = target_kept(out)
    assert np.all(kept[ranges < near]) and not np.any(kept[ranges > far])
    moved = out.effect == Effect.MOVED
    assert np.all(moved == ~kept) and diag["removed"] == 0
    assert np.mean(out.ranges_m[moved]) == pytest.approx(fog_range, abs=0.05)
    assert 0.05 < np.std(out.ranges_m[moved]) < 0.5
    assert np.mean(out.fields["intensity"][moved]) == pytest.approx(s_fog, rel=0.03)
    assert np.std(out.fields["intensity"][moved]) == pytest.approx(sigma, rel=0.25)


def test_fog_return_in_a_range_compensated_file_is_range_compensated():
    """The same fog in a reflectivity file reads ``W · S_fog r² / K`` at its apparent range r: with a 16-bit
    reflectivity (W = 10⁴) about 10; in Ouster's 8-bit reflectivity (W = 100) 0.1, which the OS1 stores as its lowest
    reading 1 (``faint_reading: lowest``); a sensor that writes 0 writes 0, one that drops such returns drops them."""
    alpha, beta = math.log(20) / 30, 0.046 / 30
    ranges = np.arange(25.0, 60.0, 0.1)
    wide = dataclasses.replace(os1_128_reflectivity(), intensity_unit="photons", intensity_full_scale=65535.0,
                               reflectivity_white_reading=1e4)
    k = sensor_constant(wide)
    s_fog, fog_range = fog_peak_direct(alpha, beta, 10e-9, k, wide.overlap_start_m, wide.overlap_full_m)
    out, _ = run(FogLidar(visibility_m=30.0), cloud_at(ranges, 5000.0, wide, grid=True))
    assert np.all(out.effect == Effect.MOVED)
    assert np.mean(out.fields["intensity"]) == pytest.approx(1e4 * s_fog * fog_range ** 2 / k, rel=0.1)
    for faint, reading in (("lowest", 1.0), ("zero", 0.0), ("no_return", None)):
        prof = dataclasses.replace(os1_128_reflectivity(), faint_reading=faint)
        out, diag = run(FogLidar(visibility_m=30.0), cloud_at(ranges, 50.0, prof, grid=True))
        if reading is None:
            assert diag["removed"] == len(ranges) and diag["moved"] == 0
        else:
            assert diag["moved"] == len(ranges) and np.all(out.fields["intensity"] == reading)


@pytest.mark.parametrize("r2", [1.0, 2.0, 5.0])
def test_fog_overlap_comes_from_the_profile(r2):
    """ξ is the profile's: the empty-ray fog peak (strength and apparent range) follows ``overlap_full_m`` as the
    direct integral with that overlap says, and a slower overlap gives a weaker fog."""
    prof = dataclasses.replace(PHOTONS, overlap_start_m=0.9, overlap_full_m=r2, detection_threshold=1e-3,
                               photons_at_threshold=1e6)              # a receiver with negligible noise
    out, diag = run(FogLidar(visibility_m=30.0), cloud_at(np.full(20, 200.0), 1.0, prof, grid=True))
    alpha, beta = math.log(20) / 30, 0.046 / 30
    s_fog, fog_range = fog_peak_direct(alpha, beta, 10e-9, 65535.0, 0.9, r2)
    assert np.all(out.effect == Effect.MOVED)
    np.testing.assert_allclose(out.ranges_m, fog_range, atol=0.02)
    np.testing.assert_allclose(out.fields["intensity"], np.round(s_fog), atol=1.0)      # whole photons
    hahner, _ = fog_peak_direct(alpha, beta, 10e-9, 65535.0, 0.9, 1.0)
    assert (s_fog < 0.9 * hahner) == (r2 > 1.0)


def test_fog_moved_points_stay_on_their_ray():
    cloud = street()
    out, diag = run(FogLidar(visibility_m=20.0), cloud)
    moved = out.effect == Effect.MOVED
    assert moved.sum() == diag["moved"] > 0
    # every moved point is parallel to one input point, and closer than it
    u_in = cloud.positions_m / cloud.ranges_m[:, None]
    u_out = out.positions_m[moved] / out.ranges_m[moved][:, None]
    cos = u_out @ u_in.T
    src = np.argmax(cos, axis=1)
    assert np.all(cos[np.arange(len(src)), src] > 1 - 1e-12)
    assert np.all(out.ranges_m[moved] < cloud.ranges_m[src])


# --- one intensity scale: photons, 8-bit and [0, 1] reflectivity give the same decisions ----------------------------

#: the PHOTONS sensor (K = 65535 photons·m², threshold 2.42 photons) storing range-compensated reflectivity, in 8-bit
#: (Ouster style: white reads W = 100; with an arbitrary signal unit: K = 1000) and in [0, 1] (K = 1, white reads 1):
#: same threshold relative to K
REFL_UINT8 = dataclasses.replace(PHOTONS, name="refl-8bit", intensity_unit="uint8", intensity_full_scale=255.0,
                                 intensity_kind="reflectivity", sensor_constant=1000.0,
                                 reflectivity_white_reading=100.0, detection_threshold=2.42 * 1000.0 / 65535)
REFL_UNIT = dataclasses.replace(PHOTONS, name="refl-unit", intensity_unit="unit", intensity_full_scale=1.0,
                                intensity_kind="reflectivity", sensor_constant=1.0, detection_threshold=2.42 / 65535)


def lambertian_scene(n=3000, seed=4) -> tuple[np.ndarray, np.ndarray]:
    """Targets 1–100 m of reflectance 0.02–1 (normal incidence), all detectable in clear air."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(1.0, 100.0, 3 * n)
    rho = rng.uniform(0.02, 1.0, 3 * n)
    ok = rho / r ** 2 >= 1.5 * 2.42 / 65535
    return r[ok][:n], rho[ok][:n]


def scene_cloud(r, rho, profile, seed=4) -> PointCloud:
    """The scene as the profile stores it: received signal ``K ρ / r²`` through the profile's intensity kind."""
    intensity = reported_intensity(sensor_constant(profile) * rho / r ** 2, r, profile)
    return cloud_at(r, np.minimum(intensity, profile.intensity_full_scale), profile, seed)


@pytest.mark.parametrize("model_id", sorted(WEATHER))
def test_same_decisions_for_photons_8bit_and_unit_reflectivity(model_id):
    r, rho = lambertian_scene()
    clouds = [scene_cloud(r, rho, p) for p in (PHOTONS, REFL_UINT8, REFL_UNIT)]
    assert clouds[1].fields["intensity"].max() > 1.5 and clouds[2].fields["intensity"].max() <= 1.0
    outs = [run(HEAVY[model_id], c, seed=9)[0] for c in clouds]
    assert len(outs[0]) == len(outs[1]) == len(outs[2])
    in_place = [target_kept(o) for o in outs]
    moved = [o.effect == Effect.MOVED for o in outs]
    for k in (1, 2):
        np.testing.assert_array_equal(in_place[k], in_place[0])
        np.testing.assert_array_equal(moved[k], moved[0])
        np.testing.assert_allclose(outs[k].positions_m, outs[0].positions_m, rtol=1e-9, atol=1e-9)
    # intensities: the same received signal, stored by each profile at the output range (photons and 8-bit readings
    # rounded to whole counts, [0, 1] continuous): equal within the rounding of both
    s_over_k = outs[0].fields["intensity"] / 65535
    r_out = outs[0].ranges_m
    fine = outs[0].fields["intensity"] < 65535
    photon_step = 0.5 / 65535 * r_out ** 2                   # half a photon, in units of each reflectivity reading
    np.testing.assert_array_less(np.abs(outs[1].fields["intensity"] - 100 * s_over_k * r_out ** 2)[fine],
                                 (0.5 + 100 * photon_step + 1e-9)[fine])
    np.testing.assert_array_less(np.abs(outs[2].fields["intensity"] - s_over_k * r_out ** 2)[fine],
                                 (photon_step + 1e-9)[fine])
    assert 0 < np.mean(in_place[0]) < 1 and moved[0].any()      # the scene is neither untouched nor wiped out


def test_a_unit_scale_cloud_is_not_turned_into_fog():
    """The classic peer failure: a [0, 1] cloud read with photon thresholds. Refused with a clear message, and with
    the right profile the same scene keeps the same points as in photons."""
    r, rho = lambertian_scene(1000, seed=5)
    unit = scene_cloud(r, rho, REFL_UNIT, seed=5)
    with pytest.raises(ModelError, match="intensity_unit 'unit'"):
        run(FogLidar(), dataclasses.replace(unit, profile=PHOTONS))
    too_big = dataclasses.replace(street(200), profile=kitti_hdl64())
    with pytest.raises(ModelError, match="full scale"):
        run(RainLidar(), too_big)
    out, diag = run(FogLidar(visibility_m=100.0), unit)
    ref, ref_diag = run(FogLidar(visibility_m=100.0), scene_cloud(r, rho, PHOTONS, seed=5))
    assert 0 < diag["moved"] == ref_diag["moved"] < len(unit) and diag["removed"] == ref_diag["removed"]
    np.testing.assert_array_equal(target_kept(out), target_kept(ref))


# --- labels at the file's resolution --------------------------------------------------------------------------------


@pytest.mark.parametrize("profile, value, dtype", [(PHOTONS, 100.0, np.float32), (REFL_UNIT, 0.5, np.float32),
                                                   (PHOTONS, 100.0, np.uint16)], ids=["photons", "unit", "uint16"])
def test_changes_below_the_file_resolution_are_kept(profile, value, dtype):
    """Light fog (V = 3 km, α = 1.0e-3 m⁻¹): a target whose stored intensity changes by less than half a step of the
    file's resolution (0.5 photon; 1/510 of a [0, 1] scale) keeps the label KEPT, a larger change is ATTENUATED:
    the boundary is R = −ln(1 − step/2 / I) / (2α). Photon counts are stored in whole counts even in a float file
    (the sensor cannot write 99.8 photons), continuous [0, 1] values unrounded."""
    ranges = np.linspace(1.0, 10.0, 901)
    cloud = cloud_at(ranges, value, profile, grid=True)
    if profile.intensity_kind == "reflectivity":              # a constant reflectivity reading
        cloud = cloud.with_fields(intensity=np.full(len(ranges), value, dtype))
    else:
        cloud = cloud.with_fields(intensity=cloud.fields["intensity"].astype(dtype))
    out, diag = run(FogLidar(visibility_m=3000.0), cloud)
    alpha = math.log(20) / 3000
    step = 1.0 if profile.intensity_unit == "photons" else 1 / 255
    boundary = -math.log(1 - step / 2 / value) / (2 * alpha)
    label = out.effect
    assert diag["moved"] == diag["removed"] == 0
    near = np.abs(ranges - boundary) < 0.02
    assert np.all(label[(ranges < boundary) & ~near] == Effect.KEPT)
    assert np.all(label[(ranges > boundary) & ~near] == Effect.ATTENUATED)
    assert diag["kept"] == np.count_nonzero(label == Effect.KEPT)
    if profile.intensity_unit == "unit":                      # continuous: the sub-step attenuation is written
        kept = label == Effect.KEPT
        np.testing.assert_allclose(out.fields["intensity"][kept], value * np.exp(-2 * alpha * ranges[kept]),
                                   rtol=1e-6)
    else:
        assert np.all(out.fields["intensity"][label == Effect.KEPT] == value)


# --- identity, determinism, labels, diagnostics --------------------------------------------------------------------


@pytest.mark.parametrize("model", [FogLidar(visibility_m=math.inf), RainLidar(rain_rate_mm_per_h=0.0),
                                   SnowLidar(snowfall_rate_mm_per_h=0.0)], ids=lambda m: m.id)
def test_zero_strength_is_identity(model):
    cloud = street(500)
    out, diag = run(model, cloud)
    np.testing.assert_array_equal(out.positions_m, cloud.positions_m)
    np.testing.assert_array_equal(out.fields["intensity"], cloud.fields["intensity"])
    assert out.effect.dtype == np.uint8 and np.all(out.effect == Effect.KEPT)
    assert diag["kept"] == len(cloud) and diag["alpha_per_m"] == 0.0


@pytest.mark.parametrize("model_id", sorted(WEATHER))
def test_same_rng_same_output_and_json_diagnostics(model_id):
    cloud = street(2000, seed=6)
    a, da = run(HEAVY[model_id], cloud, seed=1)
    b, db = run(HEAVY[model_id], cloud, seed=1)
    np.testing.assert_array_equal(a.positions_m, b.positions_m)
    for k in a.fields:
        np.testing.assert_array_equal(a.fields[k], b.fields[k])
    assert da == db
    json.dumps(da)
    notes = ("_source", "intensity_reading", "intensity_warning")            # explanatory strings
    numbers = {k: v for k, v in da.items() if not k.endswith(notes)}
    assert all(isinstance(v, (int, float)) for v in numbers.values())
    assert isinstance(da["empty_rays_source"], str)
    assert {"kept", "attenuated", "moved", "removed", "added", "alpha_per_m"} <= set(da)
    assert da["kept"] + da["attenuated"] + da["moved"] + da["removed"] == len(cloud)
    assert len(a) == len(cloud) - da["removed"]
    if model_id != "fog.lidar":                             # particles: another seed gives another frame
        c, _ = run(HEAVY[model_id], cloud, seed=2)
        assert not np.array_equal(a.effect, c.effect)


def test_existing_fields_are_carried_and_never_overwritten():
    """A user's ``label`` is a field like any other for the models: they carry it (dtype and values); the effect
    code goes to the provenance. A later step's effect combines with the earlier one (composed by the chain)."""
    cloud = street(1000, seed=7)
    ring = np.arange(len(cloud), dtype=np.uint16) % 128
    label = (np.arange(len(cloud), dtype=np.uint32) % 7) | (3 << 16)
    cloud = cloud.with_fields(ring=ring, label=label, intensity=cloud.fields["intensity"].astype(np.float32))
    out, diag = run(RainLidar(rain_rate_mm_per_h=50.0), cloud)
    assert out.fields["intensity"].dtype == np.float32 and out.fields["ring"].dtype == np.uint16
    assert out.fields["label"].dtype == np.uint32
    assert all(len(v) == len(out) for v in out.fields.values())
    assert np.all(out.fields["intensity"] <= PHOTONS.intensity_full_scale)
    src = out.origin >= 0
    np.testing.assert_array_equal(out.fields["label"][src], label[out.origin[src]])
    np.testing.assert_array_equal(out.fields["ring"][src], ring[out.origin[src]])
    assert set(np.unique(out.effect)) <= {Effect.KEPT, Effect.ATTENUATED, Effect.MOVED, Effect.ADDED}
    out0, _ = run(RainLidar(rain_rate_mm_per_h=0.0), cloud)
    assert np.all(out0.effect == Effect.KEPT) and out0.origin is None
    np.testing.assert_array_equal(out0.fields["label"], label)
    quantised = cloud.with_fields(intensity=np.rint(cloud.fields["intensity"]).astype(np.uint16))
    out, diag = run(FogLidar(visibility_m=2000.0), quantised)
    assert out.fields["intensity"].dtype == np.uint16 and diag["kept"] > 0
    # two steps: the second one's KEPT never hides the first one's effect
    both, recs = apply_models([RainLidar(rain_rate_mm_per_h=50.0), FogLidar(visibility_m=2000.0)], quantised, seed=3,
                              key="k", sequence_id="s")
    first, _ = run(RainLidar(rain_rate_mm_per_h=50.0), quantised)           # the chain's step 0, same rng
    where = np.full(len(quantised), -1)
    where[first.origin[first.origin >= 0]] = np.flatnonzero(first.origin >= 0)
    src = both.origin >= 0
    e1 = first.effect[where[both.origin[src]]]
    assert np.all(both.effect[src] >= e1) and np.any(e1 == Effect.ATTENUATED)
    assert np.count_nonzero(both.effect == Effect.MOVED) >= recs[1].diagnostics["moved"]


# --- monotonicity ----------------------------------------------------------------------------------------------


@settings(max_examples=12, deadline=None, derandomize=True)
@given(v1=st.floats(5.0, 500.0), shrink=st.floats(0.2, 0.95))
def test_denser_fog_never_keeps_more_targets(v1, shrink):
    """Fog is deterministic: the set of targets kept in place can only shrink as the visibility drops."""
    cloud = street(1500, seed=8)
    kept_light = _kept_points(cloud, run(FogLidar(visibility_m=v1), cloud)[0])
    kept_dense = _kept_points(cloud, run(FogLidar(visibility_m=v1 * shrink), cloud)[0])
    assert kept_dense <= kept_light


def _kept_points(cloud, out) -> set:
    """Indices of input points still in place (positions are unchanged for KEPT/ATTENUATED points)."""
    keep = target_kept(out)
    lookup = {tuple(p): i for i, p in enumerate(cloud.positions_m)}
    return {lookup[tuple(p)] for p in out.positions_m[keep]}


@settings(max_examples=8, deadline=None, derandomize=True)
@given(model_id=st.sampled_from(["rain.lidar", "snow.lidar"]), log_rate=st.floats(-2.0, 4.5),
       factor=st.floats(2.0, 4.0), seed=st.integers(0, 2 ** 16))
def test_denser_precipitation_never_keeps_more_targets(model_id, log_rate, factor, seed):
    """Rain and snow draw particles: at least a doubling of the rate keeps no more targets in place (same seed), up to
    the Monte-Carlo noise of a few points (the particles and the receiver's noise are drawn anew at each rate)."""
    cls, name = WEATHER[model_id]
    cloud = street(2500, seed=seed % 7)
    r1 = math.exp(log_rate) if model_id == "rain.lidar" else math.exp(log_rate) / 10
    k1 = run(cls(**{name: r1}), cloud, seed=seed)[1]
    k2 = run(cls(**{name: r1 * factor}), cloud, seed=seed)[1]
    assert k2["kept"] + k2["attenuated"] <= k1["kept"] + k1["attenuated"] + 3
    assert k2["alpha_per_m"] > k1["alpha_per_m"]


# --- full range image: returns on no-return rays ------------------------------------------------------------------


def small_grid(rows=32, cols=256, base=PHOTONS, first=0) -> PointCloud:
    """A full grid (photons) of 32 OS1-128 beams (from beam ``first``): a bright wall (2000 photons) at 15 m over half
    the azimuths, sky elsewhere."""
    beams = slice(first, first + rows)
    prof = dataclasses.replace(base, beam_elevation_deg=base.beam_elevation_deg[beams],
                               beam_azimuth_offset_deg=base.beam_azimuth_offset_deg[beams], columns=cols)
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))[:, None]
    az = np.pi - 2 * np.pi * np.arange(cols)[None, :] / cols - np.deg2rad(
        np.asarray(prof.beam_azimuth_offset_deg))[:, None]
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1).reshape(-1, 3)
    hit = (np.arange(rows * cols) % cols) < cols // 2
    pos = np.where(hit[:, None], d * 15.0, 0.0)
    intensity = np.where(hit, 2000.0, 0.0).astype(np.float32)
    ring = np.repeat(np.arange(rows, dtype=np.uint16), cols)
    return PointCloud(pos, {"intensity": intensity, "ring": ring}, "lidar", prof, grid_shape=(rows, cols)), d, hit


@pytest.mark.parametrize("model", [FogLidar(visibility_m=15.0), SnowLidar(snowfall_rate_mm_per_h=5.0)],
                         ids=lambda m: m.id)
def test_weather_returns_on_empty_rays_of_a_full_grid(model):
    grid, directions, hit = small_grid()
    out, diag = run(model, grid)
    assert len(out) == len(grid) and out.grid_shape == grid.grid_shape
    added = out.effect == Effect.ADDED
    assert diag["added"] == added.sum() > 0 and not np.any(added & hit)
    # added points lie on the ray of their cell (beam elevation of the row, azimuth of the column)
    u = out.positions_m[added] / out.ranges_m[added][:, None]
    np.testing.assert_allclose(np.sum(u * directions[added], axis=1), 1.0, atol=1e-6)
    assert np.median(out.ranges_m[added]) < 10.0 and np.all(out.ranges_m[added] <= grid.profile.max_range_m)
    np.testing.assert_array_equal(out.fields["ring"], grid.fields["ring"])
    removed = ~np.any(out.positions_m != 0, axis=1) & hit
    assert np.all(out.fields["intensity"][removed] == 0)
    assert diag["removed"] == removed.sum()


def small_list(first=0) -> tuple[PointCloud, PointCloud, np.ndarray]:
    """:func:`small_grid` with its lowest beam on the ground (8 m) all around, as a full grid and as a point list of
    its returns with ``ring`` and ``time`` (firing time of the column) fields; and each cell's direction."""
    grid, d, hit = small_grid(first=first)
    rows, cols = grid.grid_shape
    lowest = int(np.argmin(grid.profile.beam_elevation_deg))
    ground = np.arange(rows * cols) // cols == lowest
    pos = np.where(hit[:, None], grid.positions_m, np.where(ground[:, None], d * 8.0, 0.0))
    time = ((np.arange(rows * cols) % cols) * 1e-4).astype(np.float32)
    fields = {"intensity": np.where(hit | ground, 2000.0, 0.0).astype(np.float32), "ring": grid.fields["ring"],
              "time": time}
    full = dataclasses.replace(grid, positions_m=pos, fields=fields)
    returns = hit | ground
    listed = PointCloud(pos[returns], {k: v[returns] for k, v in fields.items()}, "lidar", grid.profile)
    return full, listed, d


def test_point_list_gets_the_weather_of_its_full_grid():
    """The list of a grid's returns gets the same returns on the same empty rays (noise-free receiver: with noise
    the list and the grid number their rays differently and draw differently)."""
    full, listed, _ = small_list()
    full, listed = (dataclasses.replace(c, profile=quiet(c.profile)) for c in (full, listed))
    model = FogLidar(visibility_m=15.0)
    out_grid, d_grid = run(model, full)
    out_list, d_list = run(model, listed)
    assert d_list["empty_rays"] == d_grid["empty_rays"] == len(full) - len(listed) > 0
    for k in ("kept", "attenuated", "moved", "removed", "added"):
        assert d_list[k] == d_grid[k], k
    added_grid = out_grid.effect == Effect.ADDED
    order = np.lexsort((out_grid.fields["time"][added_grid], out_grid.fields["ring"][added_grid]))
    tail = slice(len(out_list) - d_list["added"], None)
    order_list = np.lexsort((out_list.fields["time"][tail], out_list.fields["ring"][tail]))
    for k in ("ring", "time", "intensity"):
        np.testing.assert_array_equal(out_list.fields[k][tail][order_list], out_grid.fields[k][added_grid][order], k)
    np.testing.assert_array_equal(out_list.effect[tail], Effect.ADDED)
    assert np.all(out_list.origin[tail] == -1) and out_grid.origin is None
    np.testing.assert_allclose(out_list.positions_m[tail][order_list], out_grid.positions_m[added_grid][order],
                               atol=1e-5)                         # the quiet receiver's jitter: micrometres


def test_snow_on_the_empty_rays_of_a_point_list():
    """Flake returns on a list's empty rays are appended as ADDED points on their cell's ray, with the cell's ring
    and its column's firing time; ``empty_rays='ignore'`` adds none."""
    full, listed, d = small_list()
    out, diag = run(SnowLidar(snowfall_rate_mm_per_h=5.0), listed)
    n_in = len(listed) - diag["removed"]
    added = out.effect == Effect.ADDED
    assert diag["added"] == added.sum() > 0 and np.all(added[n_in:]) and not added[:n_in].any()
    cols = full.grid_shape[1]
    cell = out.fields["ring"][added].astype(int) * cols + np.rint(out.fields["time"][added] / 1e-4).astype(int)
    u = out.positions_m[added] / out.ranges_m[added][:, None]
    np.testing.assert_allclose(np.sum(u * d[cell], axis=1), 1.0, atol=1e-9)
    assert not np.any(np.isin(cell, np.flatnonzero(np.any(full.positions_m != 0, axis=1))))
    out_ignore, d_ignore = run(SnowLidar(snowfall_rate_mm_per_h=5.0, empty_rays="ignore"), listed)
    assert d_ignore["added"] == 0 and d_ignore["empty_rays"] == 0 and "ignore" in d_ignore["empty_rays_source"]


def test_lists_off_a_firing_grid_get_weather_only_on_their_returns():
    out, diag = run(FogLidar(visibility_m=15.0), street(5000))
    assert diag["added"] == diag["empty_rays"] == diag["firing_grid_columns"] == 0
    assert diag["empty_rays_source"].startswith("none: azimuths are not on a regular firing grid")


def test_fog_on_empty_rays_uses_the_saturated_table():
    """Dense fog: every sky ray sees the fog at the saturated table's peak; without receiver noise one range and
    one intensity (homogeneous fog), with the SPAD's noise a spread around them (no deterministic shell)."""
    grid, _, hit = small_grid()
    alpha, beta = math.log(20) / 10, 0.046 / 10
    g, at = soft_target_table(alpha, 10e-9, grid.profile.overlap_start_m, grid.profile.overlap_full_m).saturated
    s_fog = soft_target_signal(g, beta) * 65535
    for noisy in (False, True):
        cloud = grid if noisy else dataclasses.replace(grid, profile=quiet(grid.profile))
        out, diag = run(FogLidar(visibility_m=10.0), cloud)
        added = out.effect == Effect.ADDED
        assert added.sum() == (~hit).sum()
        r, i = out.ranges_m[added], out.fields["intensity"][added]
        if noisy:
            assert 0.05 < np.std(r) < 0.5 and np.std(i) > 0.5 * math.sqrt(s_fog)
            assert np.mean(r) == pytest.approx(at, abs=0.03) and np.mean(i) == pytest.approx(s_fog, rel=0.02)
        else:
            np.testing.assert_allclose(r, at, atol=1e-6)
            assert np.all(i == np.round(s_fog))


@pytest.mark.parametrize("overlap", ["os1", "hahner"])
def test_os1_overlap_sky_rays_see_dense_fog_but_not_light_fog(overlap):
    """The OS1-128 profile (SPAD, threshold 3.28 photons, overlap full at 5 m): the empty (sky) rays return the fog at
    V = 30 m (32 photons) and at V = 1 km (1.3 photons) only as often as the photon statistics detect 1.3 photons
    (a few %); with Hahner's overlap (full at 1 m) the same sensor would see the 1 km fog (5.2 photons) on most sky
    rays. The fraction of sky rays with a fog return is the receiver's detection probability (binomial 4 SD)."""
    base = os1_128() if overlap == "os1" else dataclasses.replace(os1_128(), overlap_start_m=0.9, overlap_full_m=1.0)
    grid, _, hit = small_grid(base=base)
    sky = np.count_nonzero(~hit)
    for visibility in (30.0, 1000.0):
        out, diag = run(FogLidar(visibility_m=visibility), grid)
        alpha, beta = math.log(20) / visibility, 0.046 / visibility
        s_fog, _ = fog_peak_direct(alpha, beta, 10e-9, 65535.0, base.overlap_start_m, base.overlap_full_m)
        p = float(Receiver.of(base).detection_probability(s_fog)) - float(Receiver.of(base).detection_probability(0))
        assert abs(diag["added"] - p * sky) <= 4 * math.sqrt(sky * p * (1 - p)) + 1, (visibility, p)
        if visibility == 30.0:
            assert diag["added"] == sky
            assert np.mean(out.fields["intensity"][out.effect == Effect.ADDED]) == pytest.approx(
                s_fog, rel=0.03)
        else:
            assert (p < 0.1) == (overlap == "os1") and (p > 0.5) == (overlap == "hahner")


# --- the real OS1-128 scan -------------------------------------------------------------------------------------------


# the scan's 4th column is the OS1's calibrated 8-bit reflectivity (1024 columns per revolution)
REFLECTIVITY = dataclasses.replace(os1_128_reflectivity(), columns=1024)


def real_scan(shared_data) -> PointCloud:
    a = np.fromfile(shared_data / "os1-128" / "scan0.bin", dtype=np.float32).reshape(-1, 4)
    return PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3].copy()}, "lidar", REFLECTIVITY)


@pytest.mark.parametrize("model_id, values", [
    ("fog.lidar", [math.inf, 200.0, 50.0, 30.0, 10.0]),
    ("rain.lidar", [0.0, 5.0, 20.0, 50.0, 150.0]),
    ("snow.lidar", [0.0, 0.5, 2.5, 10.0, 30.0])])
def test_real_scan_loses_more_points_as_the_weather_thickens(shared_data, model_id, values):
    """Points lost from their target (removed or moved to a weather return) and points removed grow with the
    weather; the intensity left in place falls."""
    cloud = real_scan(shared_data)
    cls, name = WEATHER[model_id]
    lost, transmission, removed = [], [], []
    for v in values:
        out, d = run(cls(**{name: v}), cloud)
        assert d["points_in"] == len(cloud) and len(out) == len(cloud) - d["removed"] + d["added"]
        if v not in (0.0, math.inf):                   # the list's empty rays: its real 128 × 1024 no-return cells
            assert (d["empty_rays"], d["firing_grid_columns"]) == (128 * 1024 - len(cloud), 1024)
        lost.append((d["removed"] + d["moved"]) / len(cloud))
        removed.append((d["removed"] - d["removed_below_threshold_in"]) / (len(cloud) - d["below_threshold_in"]))
        kept = target_kept(out)
        transmission.append(float(np.sum(out.fields["intensity"][kept])) / float(np.sum(cloud.fields["intensity"])))
    assert lost[0] == 0 and all(b >= a for a, b in zip(lost, lost[1:])) and lost[-1] > lost[1], lost
    assert removed[0] == 0 and all(b >= a for a, b in zip(removed, removed[1:])), removed
    # the scan's calibrated sensitivity (its weakest returns, 10× below the datasheet threshold) sees weather on
    # nearly every ray: a target that fades below the threshold is replaced by a weather return, not removed
    assert all(b < a for a, b in zip(transmission, transmission[1:])), transmission


def real_grid(shared_data) -> tuple[PointCloud, np.ndarray]:
    g = np.load(shared_data / "os1-128" / "scan0_grid.npz")
    xyz = g["xyz_m"].reshape(-1, 3).astype(np.float64)
    valid = g["range_mm"].reshape(-1) > 0
    return PointCloud(np.where(valid[:, None], xyz, 0.0),
                      {"intensity": g["reflectivity"].reshape(-1).astype(np.float32)}, "lidar", REFLECTIVITY,
                      grid_shape=(128, 1024)), valid


def test_real_list_gets_the_weather_of_its_full_grid_on_the_empty_rays(shared_data):
    """The point list of the real scan, with a profile that even states the wrong column count (2048), gets fog on
    exactly the no-return cells of the real range image: same number, same directions (within 0.02°, against a
    0.35° column step: the grid fits one column phase, the list one per beam), same fog returns."""
    from scipy.spatial import cKDTree

    grid, _ = real_grid(shared_data)
    grid = dataclasses.replace(grid, profile=quiet(grid.profile))         # noise-free: the rays are numbered apart
    listed = dataclasses.replace(real_scan(shared_data), profile=quiet(os1_128_reflectivity()))
    assert listed.profile.columns == 2048
    model = FogLidar(visibility_m=30.0)
    out_grid, d_grid = run(model, grid)
    out_list, d_list = run(model, listed)
    assert d_list["empty_rays"] == d_grid["empty_rays"] == 128 * 1024 - len(listed)
    assert d_list["firing_grid_columns"] == 1024 and "2048" in d_list["empty_rays_source"]
    for k in ("kept", "attenuated", "moved", "removed", "added"):
        assert d_list[k] == d_grid[k], k
    a = out_grid.positions_m[out_grid.effect == Effect.ADDED]
    b = out_list.positions_m[out_list.effect == Effect.ADDED]
    assert len(b) == d_list["added"] > 20_000 and np.all(out_list.effect[-len(b):] == Effect.ADDED)
    unit = lambda p: p / np.linalg.norm(p, axis=1, keepdims=True)       # noqa: E731
    dist, j = cKDTree(unit(a)).query(unit(b))
    assert np.all(np.rad2deg(dist) < 0.02) and len(np.unique(j)) == len(b)
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), np.linalg.norm(a[j], axis=1), atol=1e-5)   # jitter ≤ µm
    np.testing.assert_allclose(out_list.fields["intensity"][-len(b):], out_grid.fields["intensity"][
        np.flatnonzero(out_grid.effect == Effect.ADDED)[j]])


def test_real_grid_empty_rays_get_returns_along_their_beams(shared_data):
    cloud, valid = real_grid(shared_data)
    xyz = cloud.positions_m
    # the fitted column azimuths reproduce the directions of the real returns, up to the angle subtended by the
    # neglected beam-origin offsets (36 mm up, 16 mm out)
    from roadview_noise.physics.lidar_output import empty_ray_directions

    far = np.flatnonzero(valid & (np.linalg.norm(xyz, axis=1) > 3.0))[::10]
    r = np.linalg.norm(xyz[far], axis=1)
    angle = np.arccos(np.clip(np.sum(xyz[far] / r[:, None] * empty_ray_directions(cloud, valid, far), axis=1), -1, 1))
    offset = math.hypot(REFLECTIVITY.sensor_z_offset_m, REFLECTIVITY.beam_origin_offset_m)
    assert np.all(angle <= np.arctan(offset / r) + np.deg2rad(0.02))
    out, diag = run(SnowLidar(snowfall_rate_mm_per_h=10.0), cloud)
    added = out.effect == Effect.ADDED
    assert diag["added"] > 0 and not np.any(added & valid) and len(out) == len(cloud)
    elev = np.degrees(np.arcsin(out.positions_m[added, 2] / out.ranges_m[added]))
    rows = np.flatnonzero(added) // 1024
    np.testing.assert_allclose(elev, np.asarray(REFLECTIVITY.beam_elevation_deg)[rows], atol=1e-9)


@pytest.mark.parametrize("model_id", ["rain.lidar", "snow.lidar", "fog.lidar"])
def test_first_return_mode_reports_weather_in_front_more_often(model_id):
    cloud = street(3000, seed=10)
    cls = type(HEAVY[model_id])
    params = {**HEAVY[model_id].params()}
    strongest = run(cls(**{**params, "return_mode": "strongest"}), cloud, seed=4)[1]
    first = run(cls(**{**params, "return_mode": "first"}), cloud, seed=4)[1]
    assert first["moved"] >= strongest["moved"] and first["moved"] > 0


@pytest.mark.parametrize("model_id", ["rain.lidar", "snow.lidar"])
def test_brightest_first_draw_matches_the_exhaustive_draw(model_id):
    """The strongest return drawn from each ray's brightest particle down (:mod:`lidar_strongest`, the default)
    against drawing every particle above the base level (``exhaustive``), on a small scan (24 k rays at 2–60 m, a
    Lambertian 2–90 % target on three in four, the rest empty; photons), four frames each:
    - weather returns (moved + added): each count is a sum of independent per-ray outcomes, whose variance is at
      most its mean, so the two totals differ by less than 4 √(N_fast + N_exhaustive) unless the laws differ;
    - their ranges and received intensities: two-sample Kolmogorov–Smirnov, p > 0.001;
    - targets left in place: the same count within 1 % and mean intensity within 1 % (the fast path adds the mean
      backscatter of the undrawn particles in front of a target, the exhaustive draw their fluctuating sum);
    - the fast path draws far fewer particles."""
    n = 24000
    rng = np.random.default_rng(0)
    ranges = rng.uniform(2.0, 60.0, n)
    cloud = cloud_at(ranges, 65535 * rng.uniform(0.02, 0.9, n) / ranges ** 2, grid=True)
    cloud = dataclasses.replace(cloud, positions_m=np.where(np.arange(n)[:, None] % 4 == 0, 0.0, cloud.positions_m))
    model = HEAVY[model_id]
    results = []
    for exhaustive in (False, True):
        ranges_w, signal_w, kept, kept_intensity, drawn = [], [], 0, [], 0
        for seed in range(4):
            out, d = lidar_weather.precipitation(cloud, model.id, model.medium(), "strongest",
                                                 np.random.default_rng(seed), model.draw_fraction_of_threshold,
                                                 exhaustive=exhaustive)
            weather = np.isin(out.effect, (Effect.MOVED, Effect.ADDED))
            ranges_w.append(out.ranges_m[weather])
            signal_w.append(out.fields["intensity"][weather])
            in_place = np.isin(out.effect, (Effect.KEPT, Effect.ATTENUATED)) & np.any(out.positions_m != 0, 1)
            kept += int(in_place.sum())
            kept_intensity.append(out.fields["intensity"][in_place] / cloud.fields["intensity"][in_place])
            drawn += d["particles_drawn"]
        results.append((np.concatenate(ranges_w), np.concatenate(signal_w), kept, np.concatenate(kept_intensity),
                        drawn))
    (r_fast, s_fast, kept_fast, i_fast, drawn_fast), (r_all, s_all, kept_all, i_all, drawn_all) = results
    assert len(r_all) > 2000
    assert abs(len(r_fast) - len(r_all)) < 4 * math.sqrt(len(r_fast) + len(r_all))
    assert stats.ks_2samp(r_fast, r_all).pvalue > 1e-3
    assert stats.ks_2samp(s_fast, s_all).pvalue > 1e-3
    assert kept_fast == pytest.approx(kept_all, rel=0.01)
    assert i_fast.mean() == pytest.approx(i_all.mean(), rel=0.01)
    assert drawn_fast < 0.5 * drawn_all


@pytest.mark.parametrize("model_id", ["rain.lidar", "snow.lidar"])
def test_draw_fraction_trades_particles_for_a_small_bias(model_id):
    """A quarter of the default ``draw_fraction_of_threshold`` (rain 1/16, snow ½) draws fainter particles (the
    floor of every ray's draw) but changes the weather returns (moved + added, six frames of 60 k rays) by less than
    6 % (rain) or 5 % (snow; their undrawn backscatter is the model's approximation, models/lidar/rain.py)."""
    n = 60000
    cloud = cloud_at(np.full(n, 60.0), 30.0, grid=True)
    cloud = dataclasses.replace(cloud, positions_m=np.where(np.arange(n)[:, None] % 4 == 0, 0.0,
                                                            cloud.positions_m))       # a quarter of empty rays
    model = HEAVY[model_id]
    draws = []
    for fraction in (model.draw_fraction_of_threshold, model.draw_fraction_of_threshold / 4):
        diags = [run(dataclasses.replace(model, draw_fraction_of_threshold=fraction), cloud, seed=s)[1]
                 for s in range(6)]
        draws.append((np.mean([d["particles_drawn"] for d in diags]), np.mean([d["moved"] + d["added"] for d in diags])))
    (drawn, returns), (drawn_fine, returns_fine) = draws
    assert drawn_fine >= drawn
    assert returns == pytest.approx(returns_fine, rel=0.06 if model_id == "rain.lidar" else 0.05)
    with pytest.raises(ModelError):
        dataclasses.replace(model, draw_fraction_of_threshold=0.0)


# --- rings through the chain (CNF19–21) ------------------------------------------------------------------------------


def ringless_scan(columns: int = 1024) -> PointCloud:
    """A ring-less point list of a full OS1-128 revolution (photons, the datasheet threshold): ground at −1.8 m, a
    building front at y = 9 m over a third of the azimuths, sky above — as a KITTI-style .bin holds it. Beams start
    at the OS1's beam origins (15.8 mm off the axis, 36 mm up), as ring recovery expects."""
    prof = dataclasses.replace(os1_128(), columns=columns)
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))[:, None]
    az = (np.pi - 2 * np.pi * np.arange(columns)[None, :] / columns
          - np.deg2rad(np.asarray(prof.beam_azimuth_offset_deg))[:, None])
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1).reshape(-1, 3)
    flat = np.hypot(d[:, 0], d[:, 1])
    o = np.stack([prof.beam_origin_offset_m * d[:, 0] / flat, prof.beam_origin_offset_m * d[:, 1] / flat,
                  np.full(len(d), prof.sensor_z_offset_m)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ground = np.where(d[:, 2] < 0, (-1.8 - o[:, 2]) / d[:, 2], np.inf)
        wall = np.where((d[:, 1] > 0) & (np.abs(d[:, 0]) < 0.5 * d[:, 1]), (9.0 - o[:, 1]) / d[:, 1], np.inf)
    t = np.minimum(ground, wall)
    cos_inc = np.where(wall < ground, np.abs(d[:, 1]), np.abs(d[:, 2]))
    signal = sensor_constant(prof) * np.where(wall < ground, 0.4, 0.12) * cos_inc / np.where(np.isfinite(t), t, 1) ** 2
    hit = (t <= prof.max_range_m) & (np.round(signal) >= prof.detection_threshold)
    return PointCloud(o[hit] + d[hit] * t[hit, None], {"intensity": np.round(signal[hit]).astype(np.float32)}, "lidar",
                      prof)


@pytest.mark.parametrize("model_id", ["fog.lidar", "rain.lidar", "snow.lidar"])
def test_misaligned_beams_keep_their_empty_rays(model_id):
    """CNF19–21 on a ring-less point list: alignment.lidar tilts the beams by N(0, 0.127°) (more than half the
    OS1-128's beam spacing for many), but the rings it used travel with the points and its beam table is the tilted
    one, so the weather finds the same firing grid and adds weather on the empty rays within 5 % of the weather alone
    (D3.5 rates). The added returns lie on their tilted beams. Without what alignment carries (attribute and beam
    table stripped) the rings recovered from the tilted elevations break the firing grid."""
    cloud = ringless_scan()
    weather = {"fog.lidar": FogLidar(), "rain.lidar": RainLidar(), "snow.lidar": SnowLidar()}[model_id]
    _, alone = run(weather, cloud)
    out, rec = apply_models([AlignmentLidar(), weather], cloud, seed=3, key="k", sequence_id="s")
    chained = rec[1].diagnostics
    assert alone["added"] > 1000 and "firing grid" in alone["empty_rays_source"]
    assert chained["empty_rays"] == alone["empty_rays"]
    assert chained["added"] == pytest.approx(alone["added"], rel=0.05)
    added = out.effect == Effect.ADDED
    elevation = np.rad2deg(np.arcsin(out.positions_m[added, 2] / out.ranges_m[added]))
    tilted = np.asarray(out.profile.beam_elevation_deg)[out.attributes["ring"][added]]
    np.testing.assert_allclose(elevation, tilted, atol=1e-9)
    aligned, _ = apply_models([AlignmentLidar()], cloud, seed=3, key="k", sequence_id="s")
    stripped = dataclasses.replace(aligned, attributes={}, profile=cloud.profile, origin=None, effect=None)
    assert run(weather, stripped)[1]["added"] < 0.5 * alone["added"]


# --- pre-processed clouds: empty_rays sky_only ----------------------------------------------------------------------


@pytest.mark.parametrize("as_list", [False, True], ids=["grid", "list"])
def test_sky_only_fills_the_empty_rays_above_the_horizon_only(as_list):
    """A scan whose ground was removed (beams +5.0° … −5.9°, a wall over half the azimuths, no ground: what a
    ground filter leaves): ``fill`` treats the removed ground cells as rays that saw nothing and puts fog on them;
    ``sky_only`` fills only the empty rays above the horizon — the same ones ``fill`` fills there."""
    grid, _, hit = small_grid(first=48, base=quiet(PHOTONS))
    cloud = grid
    if as_list:
        cloud = PointCloud(grid.positions_m[hit], {k: v[hit] for k, v in grid.fields.items()}, "lidar", grid.profile)
    elevation = np.asarray(grid.profile.beam_elevation_deg)
    out_fill, d_fill = run(FogLidar(visibility_m=15.0), cloud)
    out_sky, d_sky = run(FogLidar(visibility_m=15.0, empty_rays="sky_only"), cloud)
    below_cells = int(np.count_nonzero(elevation <= 0)) * grid.grid_shape[1] // 2
    if as_list:                  # a list's empty rays are those in view: near the wall's azimuths (firing_grid.py)
        assert d_fill["empty_rays"] > d_sky["empty_rays"] > 0
    else:
        assert d_fill["empty_rays"] - d_sky["empty_rays"] == below_cells > 0
    assert "horizon" in d_sky["empty_rays_source"]

    def added_elevations(out):
        added = out.effect == Effect.ADDED
        return np.degrees(np.arcsin(out.positions_m[added, 2] / np.linalg.norm(out.positions_m[added], axis=1)))

    assert np.any(added_elevations(out_fill) < 0) and np.all(added_elevations(out_sky) > 0)
    assert d_sky["added"] == np.count_nonzero(added_elevations(out_fill) > 0) > 0
    assert run(FogLidar(visibility_m=15.0, empty_rays="ignore"), cloud)[1]["added"] == 0


def test_datasheet_threshold_fog_fades_smoothly_with_visibility():
    """The OS1-128 (datasheet threshold 3.28 photons, clear returns all above it): the sky rays' fog fades between
    MOR 120 and 700 m; in 1 % steps the weather returns never jump by more than 3 % of the rays (they used to fall
    from every sky ray to none between 380 and 385 m)."""
    grid, _, hit = small_grid(base=os1_128())
    visibilities = 120.0 * 1.01 ** np.arange(178)
    counts = np.array([run(FogLidar(visibility_m=float(v)), grid)[1]["added"] for v in visibilities])
    assert np.max(np.abs(np.diff(counts))) <= 0.03 * len(grid)
    assert counts[0] > 0.8 * np.count_nonzero(~hit) and counts[-1] < 0.2 * np.count_nonzero(~hit)
    assert np.all(np.diff(counts) <= 0.01 * len(grid))             # common random numbers: nearly monotone
