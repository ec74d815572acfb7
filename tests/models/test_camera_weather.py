"""Camera weather models fog.camera, rain.camera, snow.camera and the Eq. 2 modifier wind.camera
(models.md §2.1–§2.3, §2.9), on linear RGB frames and on raw Bayer mosaics."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roadview_noise.compound import apply_models, order_chain
from roadview_noise.errors import ModelError, RecipeError
from roadview_noise.model import Stage
from roadview_noise.physics.fog_optics import fog_extinction_per_m
from roadview_noise.physics.photometry import LUMINANCE_WEIGHTS
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.registry import load_all
from roadview_noise.types import CameraFrame, Conditions, RawFrame, cfa_index_map

MODELS = load_all()
Fog, Rain, Snow, Wind = (MODELS[m] for m in ("fog.camera", "rain.camera", "snow.camera", "wind.camera"))
H, W = 183, 242
PROFILE = lucid_triton_028s().resized(W, H)


def scene(seed: int = 0, sky: bool = True) -> CameraFrame:
    """Sky on top (range inf), a ground plane at the camera height, a wall at 6 m on the left."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = (u - PROFILE.cx_px) / PROFILE.fx_px, (v - PROFILE.cy_px) / PROFILE.fy_px
    with np.errstate(divide="ignore"):
        z = np.where(y > 0, 1.0 / y, np.inf if sky else 500.0)
    wall = (x * 6.0 < -0.5) & (y * 6.0 > -2.0)
    z = np.where(wall, 6.0, z)
    img = rng.uniform(0.05, 0.5, (H, W, 3))
    img[~np.isfinite(z)] = (0.6, 0.7, 0.9)
    depth = (z * np.sqrt(1 + x * x + y * y)).astype(np.float32)
    return CameraFrame(img.astype(np.float32), PROFILE, depth)


def mosaic(frame: CameraFrame, black: float = 64.0, white: float = 4095.0) -> RawFrame:
    ch = cfa_index_map("RGGB", H, W)
    site = np.take_along_axis(frame.linear_rgb, ch[..., None].astype(np.int64), axis=2)[..., 0]
    return RawFrame((black + site * (white - black)).astype(np.float32), "RGGB", black, white, frame.profile,
                    frame.depth_m)


def run(model, data, seed=0):
    return model.apply(data, state={}, drawn={}, rng=np.random.default_rng(seed))


# --- registry -----------------------------------------------------------------------------------------------------

def test_registered_with_their_stages():
    for cls in (Fog, Rain, Snow):
        assert cls.stage == Stage.MEDIUM and cls.sensor == "camera" and cls.needs_depth
    assert Wind.stage == Stage.MODIFIER and Wind.sensor == "camera"
    assert Rain().rain_rate_mm_per_h == 50.0 and Snow().snowfall_rate_mm_per_h == 3.03
    assert Fog().visibility_m == 30.0 and Wind().wind_speed_m_per_s == 3.0


# --- fog ------------------------------------------------------------------------------------------------------------

def test_fog_black_target_at_visibility_keeps_five_percent():
    """Koschmieder/MOR: a black target at d = V against airlight 1 shows 1 − t; t = 0.05 ± 0.005 per channel."""
    frame = CameraFrame(np.zeros((H, W, 3), np.float32), PROFILE, np.full((H, W), 30.0, np.float32))
    out, diag = run(Fog(visibility_m=30.0, airlight=1.0), frame)
    t = 1.0 - out.linear_rgb.reshape(-1, 3).mean(axis=0, dtype=np.float64)
    assert np.all(np.abs(t - 0.05) <= 0.005)
    np.testing.assert_allclose(diag["mean_transmission"], t, rtol=1e-5)


def test_fog_reference_table_reproduces_the_d35_pixel():
    """models.md §2.1 oracle: black object at 10 m, V = 30 m, G channel, A = 255 (reference σ) → 165.14."""
    frame = CameraFrame(np.zeros((H, W, 3), np.float32), PROFILE, np.full((H, W), 10.0, np.float32))
    out, diag = run(Fog(airlight=1.0, fog_table="reference"), frame)
    assert float(out.linear_rgb[5, 5, 1]) * 255 == pytest.approx(165.14, abs=0.01)
    np.testing.assert_allclose(diag["extinction_per_m"], (0.1061, 0.1043, 0.1024))


def test_fog_sky_becomes_the_estimated_airlight():
    """Airlight: the sky's luminance in the illuminant's colour — neutral in white-balanced RGB — not the clear
    sky's blue (physics.photometry.airlight_radiance; tests/physics/test_airlight.py)."""
    frame = scene()
    out, diag = run(Fog(), frame)
    sky = np.isinf(frame.depth_m)
    sky_y = LUMINANCE_WEIGHTS @ np.float32([0.6, 0.7, 0.9])
    np.testing.assert_allclose(diag["airlight"], np.full(3, sky_y), rtol=1e-6)
    np.testing.assert_allclose(out.linear_rgb[sky], np.broadcast_to(diag["airlight"], (sky.sum(), 3)), rtol=1e-6)
    np.testing.assert_allclose(diag["extinction_per_m"], fog_extinction_per_m(30.0))


def test_fog_without_sky_uses_the_brightest_sites():
    frame = scene(sky=False)
    _, diag = run(Fog(), frame)
    y = frame.linear_rgb @ LUMINANCE_WEIGHTS.astype(np.float32)
    assert 0.9 * y.max() < LUMINANCE_WEIGHTS @ diag["airlight"] <= y.max() + 1e-6


def test_fog_user_airlight_follows_the_luminance_factor():
    frame = dataclasses.replace(scene(), conditions=Conditions(luminance_factor=0.25))
    out, diag = run(Fog(airlight=[0.8, 0.8, 0.4]), frame)
    np.testing.assert_allclose(diag["airlight"], (0.2, 0.2, 0.1))


def test_fog_raw_sites_equal_rgb_channels():
    frame = scene(3)
    raw = mosaic(frame)
    fog = Fog(visibility_m=20.0, airlight=(0.7, 0.75, 0.8))
    rgb_out, rgb_diag = run(fog, frame)
    raw_out, raw_diag = run(fog, raw)
    ch = cfa_index_map("RGGB", H, W)[..., None].astype(np.int64)
    expected = np.take_along_axis(rgb_out.linear_rgb, ch, axis=2)[..., 0]
    np.testing.assert_allclose(raw_out.signal(), expected, atol=2e-6)
    np.testing.assert_allclose(raw_diag["mean_transmission"], rgb_diag["mean_transmission"], rtol=0.02)


@settings(max_examples=15, deadline=None)
@given(st.floats(3.0, 300.0), st.floats(1.01, 5.0), st.sampled_from(["corrected", "reference"]))
def test_denser_fog_never_raises_contrast(visibility_m, factor, table):
    frame = scene(1)
    light, diag = run(Fog(visibility_m=visibility_m * factor, fog_table=table), frame)
    dense, _ = run(Fog(visibility_m=visibility_m, fog_table=table), frame)
    a = np.asarray(diag["airlight"], np.float32)
    assert np.all(np.abs(dense.linear_rgb - a) <= np.abs(light.linear_rgb - a) + 1e-6)


@settings(max_examples=10, deadline=None)
@given(st.floats(5.0, 200.0))
def test_raw_and_rgb_give_consistent_mean_transmission(visibility_m):
    """Depth is made constant per 2×2 Bayer cell so both paths sample the same depths per channel."""
    frame = scene(2)
    block = np.repeat(np.repeat(frame.depth_m[::2, ::2], 2, axis=0), 2, axis=1)[:H, :W]
    frame = dataclasses.replace(frame, depth_m=block)
    _, d_rgb = run(Fog(visibility_m=visibility_m), frame)
    _, d_raw = run(Fog(visibility_m=visibility_m), mosaic(frame))
    np.testing.assert_allclose(d_raw["mean_transmission"], d_rgb["mean_transmission"], rtol=0.02, atol=1e-4)
    assert d_rgb["mean_transmission"][0] <= d_rgb["mean_transmission"][2]          # red extinguished most


# --- rain and snow ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("model", [Rain(), Snow(), Rain(rain_rate_mm_per_h=5.0), Snow(snow_dsd="brandes")])
def test_particles_deterministic_and_a_convex_blend(model):
    frame = scene()
    out1, diag = run(model, frame, seed=7)
    out2, _ = run(model, frame, seed=7)
    out3, _ = run(model, frame, seed=8)
    np.testing.assert_array_equal(out1.linear_rgb, out2.linear_rgb)
    assert not np.array_equal(out1.linear_rgb, out3.linear_rgb)
    s = np.asarray(diag["particle_radiance"], np.float32)
    lo, hi = np.minimum(frame.linear_rgb, s), np.maximum(frame.linear_rgb, s)
    assert np.all((out1.linear_rgb >= lo - 1e-6) & (out1.linear_rgb <= hi + 1e-6))
    assert diag["particles_visible"] <= diag["particles_drawn"]
    assert diag["particles_drawn"] == pytest.approx(diag["particles_expected"],
                                                    abs=5 * math.sqrt(diag["particles_expected"]) + 1)
    assert 0 < diag["mean_streak_opacity"] < 0.5


@settings(max_examples=10, deadline=None)
@given(st.floats(0.5, 150.0), st.floats(1.05, 3.0))
def test_rain_count_and_veil_grow_with_rate(rate, factor):
    frame = scene()
    _, low = run(Rain(rain_rate_mm_per_h=rate), frame)
    _, high = run(Rain(rain_rate_mm_per_h=rate * factor), frame)
    assert high["particles_expected"] > low["particles_expected"]
    assert high["veil_extinction_per_m"] > low["veil_extinction_per_m"]


@pytest.mark.parametrize("model", [Rain(), Snow()])
def test_weather_scales_with_the_scene_under_low_light(model):
    """Streak and veil radiances come from the frame, so a darkened scene gets darker weather: the result is
    linear in the scene radiance (Eq. 1 coupling, models.md §1, §7.3)."""
    frame = scene()
    dark = dataclasses.replace(frame, linear_rgb=frame.linear_rgb * np.float32(0.05))
    bright_out, _ = run(model, frame, seed=3)
    dark_out, _ = run(model, dark, seed=3)
    np.testing.assert_allclose(dark_out.linear_rgb, 0.05 * bright_out.linear_rgb, rtol=1e-4, atol=1e-7)


def test_unresolved_snowflakes_drawn_per_pixel_keep_the_count_and_the_mean_image():
    """The default draws flakes whose streak spans < 1 px per pixel (their compound-Poisson opacity); drawing every
    visible flake one by one (``min_explicit_extent_px: 0``) gives the same expected count and the same mean
    opacity and image, with more particles drawn one by one."""
    frame = scene()
    results = {}
    for extent in (0.0, 1.0):
        runs = [run(Snow(min_explicit_extent_px=extent), frame, seed) for seed in range(3)]
        results[extent] = (np.mean([o.linear_rgb.mean(axis=(0, 1)) for o, _ in runs], axis=0),
                           np.mean([d["mean_streak_opacity"] for _, d in runs]), runs[0][1])
    (img0, m0, d0), (img1, m1, d1) = results[0.0], results[1.0]
    assert d0["particles_unresolved_expected"] == 0 < d1["particles_unresolved_expected"]
    assert d1["particles_drawn"] < d0["particles_drawn"]
    assert d1["particles_expected"] + d1["particles_unresolved_expected"] == pytest.approx(d0["particles_expected"],
                                                                                         rel=1e-9)
    assert m1 == pytest.approx(m0, rel=0.02)
    np.testing.assert_allclose(img1, img0, rtol=2e-3)


def test_snow_flake_radiance_is_reflectance_times_sky():
    """White flakes lit like the fog: ρ_s × the airlight fog estimates (sky luminance, illuminant colour)."""
    _, diag = run(Snow(flake_reflectance=0.9), scene())
    _, fog = run(Fog(), scene())
    np.testing.assert_allclose(diag["particle_radiance"], 0.9 * np.array(fog["airlight"]), rtol=1e-6)


def test_rain_raw_and_rgb_share_the_particles():
    frame = scene(4)
    rgb_out, d_rgb = run(Rain(), frame, seed=2)
    raw_out, d_raw = run(Rain(), mosaic(frame), seed=2)
    assert d_raw["particles_drawn"] == d_rgb["particles_drawn"]
    assert d_raw["mean_streak_opacity"] == d_rgb["mean_streak_opacity"]
    ch = cfa_index_map("RGGB", H, W)[..., None].astype(np.int64)
    expected = np.take_along_axis(rgb_out.linear_rgb, ch, axis=2)[..., 0]
    assert np.abs(raw_out.signal() - expected).max() < 0.02        # radiance estimates differ by sampling only


def test_streaks_only_in_front_of_the_scene():
    """A wall at 0.4 m (nearer than every explicit particle) sees only the veil of the particles nearer than it
    (optical depth to within the 12 cm depth bins of the veil table: |Δτ| ≤ σ·0.06 m)."""
    frame = scene()
    near = dataclasses.replace(frame, depth_m=np.full((H, W), 0.4, np.float32))
    out, diag = run(Rain(), near)
    assert diag["particles_visible"] == 0
    sigma = diag["veil_extinction_per_m"]
    t = np.exp(-sigma * 0.4)
    s = np.asarray(diag["particle_radiance"], np.float32)
    np.testing.assert_allclose(out.linear_rgb, s + t * (frame.linear_rgb - s), rtol=0, atol=sigma * 0.07)


def test_exposure_override_and_validation():
    _, d = run(Rain(exposure_time_s=0.002), scene())
    assert d["exposure_time_s"] == 0.002
    assert run(Rain(), scene())[1]["exposure_time_s"] == PROFILE.exposure_time_s
    with pytest.raises(ModelError) as e:
        Rain(exposure_time_s=-1.0)
    assert e.value.field == "exposure_time_s"
    with pytest.raises(ModelError) as e:
        Snow(min_distance_m=40.0)
    assert e.value.field == "max_particle_distance_m"
    with pytest.raises(ModelError) as e:
        Snow(snow_dsd="brandes", snowfall_rate_mm_per_h=1.0)
    assert e.value.field == "snowfall_rate_mm_per_h"
    with pytest.raises(ModelError) as e:
        Fog(airlight=[0.5, 0.5])
    assert e.value.field == "airlight"


@pytest.mark.parametrize("model", [Fog(), Rain(), Snow()])
def test_depth_is_required(model):
    frame = dataclasses.replace(scene(), depth_m=None)
    with pytest.raises(ModelError) as e:
        run(model, frame)
    assert e.value.field == "depth_m" and e.value.model == model.id
    with pytest.raises(ModelError):
        run(model, dataclasses.replace(scene(), depth_m=np.full((H, W), np.nan, np.float32)))



@pytest.mark.parametrize("model", [Fog(visibility_m=30.0), Rain(rain_rate_mm_per_h=100.0), Snow()], ids=lambda m: m.id)
@pytest.mark.parametrize("h,w", [(1, 1), (1, 2), (2, 1), (1, 7)])
def test_tiny_photos_keep_their_size(model, h, w):
    """A 1×1 photo came out of fog 4×1 (OpenCV read the 1×1 depth map as a Scalar in ``cv2.min``)."""
    frame = CameraFrame(np.full((h, w, 3), 0.3, np.float32), lucid_triton_028s().resized(w, h),
                        np.full((h, w), 40.0, np.float32))
    for seed in range(3):
        out, _ = run(model, frame, seed)
        assert out.linear_rgb.shape == (h, w, 3) and np.isfinite(out.linear_rgb).all()

# --- wind -----------------------------------------------------------------------------------------------------------

def test_wind_sets_the_conditions_and_leaves_pixels():
    frame = scene()
    out, diag = run(Wind(), frame)
    np.testing.assert_allclose(out.conditions.wind_velocity_m_per_s, (0.0, 3.0, 0.0), atol=1e-12)
    assert diag["wind_velocity_m_per_s"] == list(out.conditions.wind_velocity_m_per_s)
    assert out.linear_rgb is frame.linear_rgb and frame.conditions.wind_velocity_m_per_s == (0.0, 0.0, 0.0)
    forward, _ = run(Wind(wind_direction_deg=0.0, wind_speed_m_per_s=2.0, lateral_response=0.5), frame)
    np.testing.assert_allclose(forward.conditions.wind_velocity_m_per_s, (1.0, 0.0, 0.0), atol=1e-12)


@pytest.mark.parametrize("weather", [Rain(), Snow()])
def test_zero_wind_reproduces_the_no_wind_result_exactly(weather):
    frame = scene()
    calm, _ = run(Wind(wind_speed_m_per_s=0.0), frame)
    np.testing.assert_array_equal(run(weather, calm, seed=4)[0].linear_rgb, run(weather, frame, seed=4)[0].linear_rgb)
    windy, _ = run(Wind(), frame)
    assert not np.array_equal(run(weather, windy, seed=4)[0].linear_rgb, run(weather, frame, seed=4)[0].linear_rgb)


def test_fog_is_unchanged_by_wind():
    frame = scene()
    windy, _ = run(Wind(wind_speed_m_per_s=10.0), frame)
    np.testing.assert_array_equal(run(Fog(), windy)[0].linear_rgb, run(Fog(), frame)[0].linear_rgb)


def test_cnf16_chain():
    assert order_chain(["wind.camera", "rain.camera"]) == ("wind.camera", "rain.camera")
    with pytest.raises(RecipeError):
        order_chain(["wind.camera"])
    out, records = apply_models([Wind(), Rain()], scene(), seed=1, key="k", sequence_id="s")
    assert records[1].diagnostics["particles_drawn"] > 0
    assert out.conditions.wind_velocity_m_per_s[1] == pytest.approx(3.0)


# --- compositing kernels (physics.photometry) against NumPy -------------------------------------------------------

@pytest.mark.parametrize("pattern, shape", [(None, (183, 242)), (None, (5, 7)), ("RGGB", (183, 242)),
                                            ("GBRG", (7, 5)), ("BGGR", (1, 3))])
def test_site_compositing_matches_numpy(pattern, shape):
    """``composite``: S + t·(I − S) per site with t per pixel or per site (in place); ``site_transmission``:
    exp(−σ_c d) per site, inf → 0. RGB frames and mosaics of odd sizes."""
    from roadview_noise.physics.cfa import SiteLayout
    from roadview_noise.physics.photometry import composite, site_transmission

    rng = np.random.default_rng(len(shape) + shape[0])
    h, w = shape
    ch = np.arange(3).reshape(1, 1, 3) if pattern is None else cfa_index_map(pattern, h, w)
    layout = SiteLayout(ch)
    signal = rng.random((h, w, 3) if pattern is None else (h, w), dtype=np.float32)
    values = np.array([0.3, 0.5, 0.9])
    per_site_values = values[ch] if pattern else values
    t_pixel = rng.random((h, w), dtype=np.float32)
    expected = per_site_values + (t_pixel[..., None] if pattern is None else t_pixel) * (signal - per_site_values)
    np.testing.assert_allclose(composite(layout, signal, t_pixel, values), expected, rtol=1e-6, atol=1e-7)
    t_site = rng.random(signal.shape, dtype=np.float32)
    out = composite(layout, signal, t_site, values, out=t_site.copy())
    np.testing.assert_allclose(out, per_site_values + t_site * (signal - per_site_values), rtol=1e-6, atol=1e-7)

    depth = (rng.random((h, w)) * 100).astype(np.float32)
    depth[0, 0] = np.inf
    sigma = np.array([0.03, 0.02, 0.01])
    per_site_sigma = sigma[ch] if pattern else sigma
    with np.errstate(invalid="ignore"):
        expected_t = np.exp(-per_site_sigma * (depth[..., None] if pattern is None else depth))
    t = site_transmission(layout, depth, sigma)
    np.testing.assert_allclose(t, expected_t, rtol=1e-5, atol=1e-30)
    assert np.all(t[0, 0] < 1e-30)
    np.testing.assert_array_equal(site_transmission(layout, depth, 0.0), np.ones_like(t))
