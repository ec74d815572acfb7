"""The camera noise factors of D3.5 Table 2 (models.md §2.4–§2.6, §2.8): soiling.camera, windscreen.camera,
motion_blur.camera, low_light.camera, on RGB frames and natively on raw Bayer mosaics, and their couplings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.errors import ModelError
from roadview_noise.model import Scope, Stage
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.registry import load_all
from roadview_noise.types import CameraFrame, Conditions, RawFrame, cfa_index_map

MODELS = load_all()
Soiling, Windscreen, MotionBlur, LowLight, Fog, Compression = (MODELS[m] for m in (
    "soiling.camera", "windscreen.camera", "motion_blur.camera", "low_light.camera", "fog.camera",
    "compression.camera"))


def frame(h=183, w=243, seed=0, sky_rows=None) -> CameraFrame:
    """Textured frame; the upper ``sky_rows`` rows are sky (range inf), the rest at 20 m. Odd sizes: the principal
    point is a pixel."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.05, 0.6, (h, w, 3)).astype(np.float32)
    depth = np.full((h, w), 20.0, np.float32)
    if sky_rows:
        img[:sky_rows] = (0.55, 0.65, 0.85)
        depth[:sky_rows] = np.inf
    return CameraFrame(img, lucid_triton_028s().resized(w, h), depth)


def mosaic(f: CameraFrame, black=64.0, white=4095.0) -> RawFrame:
    ch = cfa_index_map("RGGB", *f.shape)
    site = np.take_along_axis(f.linear_rgb, ch[..., None].astype(np.int64), axis=2)[..., 0]
    dn = np.rint(black + site * (white - black)).astype(np.float32)              # whole DN, as read from a file
    return RawFrame(dn, "RGGB", black, white, f.profile, f.depth_m)


def colour_constant_mosaic(h=64, w=90) -> RawFrame:
    f = frame(h, w)
    f = dataclasses.replace(f, linear_rgb=np.broadcast_to(np.float32([0.8, 0.4, 0.1]), (h, w, 3)).copy())
    return mosaic(f)


def run(model, data, seed=0, state=None):
    return model.apply(data, state=state or {}, drawn={}, rng=np.random.default_rng(seed))


def test_registered_with_their_stages():
    assert Soiling.stage == Stage.WINDOW and Soiling.scope == Scope.SEQUENCE
    assert Windscreen.stage == Stage.WINDSCREEN and Windscreen.uses_camera_geometry
    assert MotionBlur.stage == Stage.EXPOSURE and MotionBlur.uses_camera_geometry
    assert LowLight.stage == Stage.SCENE and not LowLight.uses_camera_geometry and not Soiling.uses_camera_geometry
    assert Windscreen().k1 == 1e-7 and MotionBlur().blur == 0.002 and MotionBlur().iterations == 7
    assert (Soiling().s_min_px, Soiling().s_max_px, Soiling().opacity) == (93.0, 271.0, 0.45)


# --- windscreen -----------------------------------------------------------------------------------------------

def test_windscreen_resamples_with_exactly_its_warp():
    f = frame()
    model = Windscreen(p1=1e-5, s3=-5e-6)          # tangential and prism terms, in D3.5 pixel units
    warp = model.warp(f, state={}, drawn={})
    out, diag = run(model, f)
    np.testing.assert_array_equal(out.linear_rgb, warp.apply(f.linear_rgb, border=0))
    assert out.shape == f.shape and diag["outside_fraction"] > 0
    cy, cx = (f.shape[0] - 1) // 2, (f.shape[1] - 1) // 2
    assert (warp.map_x[cy, cx], warp.map_y[cy, cx]) == (cx, cy)              # distortion centre fixed
    np.testing.assert_array_equal(out.linear_rgb[cy, cx], f.linear_rgb[cy, cx])
    box = np.array([[40.0, 30.0], [200.0, 150.0]])                           # annotations move with the image
    moved = warp.forward(box)
    assert np.all((moved > 0) & (moved < (f.shape[1] - 1, f.shape[0] - 1)))
    back = [warp.map_x[int(round(y)), int(round(x))] for x, y in moved], \
        [warp.map_y[int(round(y)), int(round(x))] for x, y in moved]
    assert np.abs(np.array(back).T - box).max() < 1.0                        # nearest-pixel look-up


def test_windscreen_reference_units_follow_the_image_width():
    """1e-7 px⁻² at 1936 px: a point at 968 px is pulled from 1058.7 px; on a 4× smaller image from ¼ of that."""
    for w, h in ((1936, 1464), (484, 366)):
        d = Windscreen().distortion(frame(h, w))
        xd, _ = d.distort(np.array([968.0 * w / 1936 / d.unit_px[0]]), np.array([0.0]))
        assert xd[0] * d.unit_px[0] == pytest.approx((968.0 + 1e-7 * 968.0 ** 3) * w / 1936, rel=1e-9)


def test_windscreen_normalised_equals_reference_with_f_squared():
    f = frame(1464, 1936)
    prof = lucid_triton_028s()                           # square pixels
    f = dataclasses.replace(f, profile=prof)
    ref = Windscreen(k1=1e-7).warp(f, state={}, drawn={})
    norm = Windscreen(k1=1e-7 * prof.fx_px ** 2, coefficient_units="normalised").warp(f, state={}, drawn={})
    np.testing.assert_allclose(norm.map_x, ref.map_x, atol=1e-3)
    np.testing.assert_allclose(norm.map_y, ref.map_y, atol=1e-3)


def test_windscreen_on_a_mosaic_keeps_the_cfa():
    raw = colour_constant_mosaic()
    out, _ = run(Windscreen(k1=3e-6, p2=1e-4, border="reflect"), raw)
    np.testing.assert_allclose(out.dn, raw.dn, rtol=1e-5)                   # colours never mix
    moved, _ = run(Windscreen(k1=3e-6), mosaic(frame(64, 90)))
    assert not np.allclose(moved.dn, mosaic(frame(64, 90)).dn)


@pytest.mark.parametrize("kw", [{"distortion_centre_px": [1, 2, 3]}, {"distortion_centre_px": "centre"},
                                {"coefficient_units": "mm"}, {"border": "wrap"}])
def test_windscreen_bad_parameters(kw):
    with pytest.raises(ModelError):
        Windscreen(**kw)


# --- motion blur ----------------------------------------------------------------------------------------------

def test_motion_blur_reference_keeps_centre_and_constant_image():
    f = frame()
    out, diag = run(MotionBlur(blur=0.01), f)
    cy, cx = (f.shape[0] - 1) // 2, (f.shape[1] - 1) // 2
    np.testing.assert_allclose(out.linear_rgb[cy, cx], f.linear_rgb[cy, cx], rtol=1e-6)
    assert not np.allclose(out.linear_rgb, f.linear_rgb)
    flat = dataclasses.replace(f, linear_rgb=np.full_like(f.linear_rgb, 0.3))
    np.testing.assert_allclose(run(MotionBlur(blur=0.01), flat)[0].linear_rgb, 0.3, rtol=1e-6)
    assert diag["radial_sd_at_corner_px"] == pytest.approx(0.01 * np.sqrt(7) * np.hypot(cx, cy))


@pytest.mark.parametrize("kw", [{}, {"mode": "physical", "ego_speed_m_per_s": 30.0, "yaw_rate_deg_per_s": 20.0}])
def test_motion_blur_on_a_mosaic_never_mixes_colours(kw):
    raw = colour_constant_mosaic()
    out, _ = run(MotionBlur(blur=0.02, **kw), raw)
    np.testing.assert_allclose(out.dn, raw.dn, rtol=1e-5)


def test_motion_blur_physical_uses_the_recipe_ego_velocity_and_needs_depth():
    f = frame()
    explicit, diag = run(MotionBlur(mode="physical", ego_speed_m_per_s=15.0, exposure_time_s=0.02), f)
    moving = dataclasses.replace(f, conditions=Conditions(ego_velocity_m_per_s=(15.0, 0.0, 0.0)))
    implicit, _ = run(MotionBlur(mode="physical", exposure_time_s=0.02), moving)
    np.testing.assert_array_equal(explicit.linear_rgb, implicit.linear_rgb)
    assert 0 < diag["blur_length_mean_px"] < diag["blur_length_max_px"]
    with pytest.raises(ModelError, match="depth"):
        run(MotionBlur(mode="physical", ego_speed_m_per_s=15.0), dataclasses.replace(f, depth_m=None))
    plane = run(MotionBlur(mode="physical", ego_speed_m_per_s=15.0, scene_depth_m=20.0),
                dataclasses.replace(f, depth_m=None))[0]
    assert not np.allclose(plane.linear_rgb, f.linear_rgb)


# --- soiling --------------------------------------------------------------------------------------------------

def test_soiling_same_mud_on_every_frame_of_a_sequence():
    model = Soiling()
    a, rec_a = apply_models([model], frame(seed=1), seed=3, key="f1", sequence_id="seq0")
    b, rec_b = apply_models([model], frame(seed=2), seed=3, key="f2", sequence_id="seq0")
    c, rec_c = apply_models([model], frame(seed=1), seed=3, key="f1", sequence_id="seq1")
    assert rec_a[0].state == rec_b[0].state != rec_c[0].state
    assert rec_a[0].diagnostics["covered_fraction"] == rec_b[0].diagnostics["covered_fraction"]


@pytest.mark.parametrize("as_mosaic", [False, True])
def test_soiling_leaves_uncovered_sites_untouched(as_mosaic):
    model = Soiling()
    f = frame(366, 484)
    data = mosaic(f) if as_mosaic else f
    state = model.draw_sequence(np.random.default_rng(4), data)
    coverage = model.mask(state, *data.shape).mask
    assert 0 < (coverage > 0.5).mean() < 0.5
    out, diag = run(model, data, state=state)
    before, after = (data.dn, out.dn) if as_mosaic else (data.linear_rgb, out.linear_rgb)
    clear = coverage == 0
    if as_mosaic:   # DN → signal → DN rounds in float32 (≪ 1 DN; the writer rounds to whole DN)
        np.testing.assert_allclose(after[clear], before[clear], atol=1e-3)
        np.testing.assert_array_equal(np.rint(after[clear]), before[clear])
    else:
        np.testing.assert_array_equal(after[clear], before[clear])
    assert np.all(after[coverage > 0.9] != before[coverage > 0.9])
    assert diag["covered_fraction"] == pytest.approx((coverage > 0.5).mean())


def test_soiling_darkens_monotonically_with_opacity_and_scales_with_width():
    f = frame(366, 484)
    state = Soiling().draw_sequence(np.random.default_rng(7), f)
    means = [run(Soiling(opacity=o), f, state=state)[0].linear_rgb.mean() for o in (0.0, 0.3, 0.6, 1.0)]
    assert means[0] == pytest.approx(f.linear_rgb.mean()) and np.all(np.diff(means) < 0)
    small = Soiling().mask(state, 366, 484).covered_fraction()
    large = Soiling().mask(state, 1464, 1936).covered_fraction()
    assert large == pytest.approx(small, rel=0.10)                  # sizes follow the width (D3.5 at 1936 px)


def test_soiling_bad_parameters():
    with pytest.raises(ModelError, match="s_min_px"):
        Soiling(s_min_px=300)
    with pytest.raises(ModelError, match="mud_albedo"):
        Soiling(mud_albedo=[0.2, 0.3])


# --- low light and its coupling to the weather -----------------------------------------------------------------

def test_low_light_publishes_its_factor():
    f = dataclasses.replace(frame(), conditions=Conditions(luminance_factor=0.5))
    out, diag = run(LowLight(), f)
    assert diag["luminance_factor"] == pytest.approx(1e-3 * 8)
    assert out.conditions.luminance_factor == pytest.approx(0.5 * 8e-3)
    assert out.linear_rgb.mean() == pytest.approx(8e-3 * f.linear_rgb.mean(), rel=0.02)
    identity, _ = run(LowLight(illuminance_lux=10000.0, shot_noise="off", read_noise_e=0.0,
                               dark_current_e_per_s=0.0), f)
    assert np.abs(identity.linear_rgb - f.linear_rgb).max() <= 0.5 / (4095 - 64) + 1e-6
    raw_out, _ = run(LowLight(), mosaic(f))
    assert raw_out.signal().mean() == pytest.approx(8e-3 * mosaic(f).signal().mean(), rel=0.03)


def test_cnf14_fog_airlight_is_scaled_by_the_published_factor():
    """Low light → fog: the airlight fog estimates from the darkened frame is the daylight airlight × k·g (no
    double darkening); a user airlight given for the daylight scene is scaled by the same factor."""
    f = frame(400, 600, sky_rows=150)
    low = LowLight()
    _, day = apply_models([Fog()], f, seed=1, key="k", sequence_id="s")
    _, night = apply_models([low, Fog()], f, seed=1, key="k", sequence_id="s")
    factor = night[0].diagnostics["luminance_factor"]
    np.testing.assert_allclose(night[1].diagnostics["airlight"], factor * np.array(day[0].diagnostics["airlight"]),
                               rtol=0.03)
    _, given = apply_models([low, Fog(airlight=[0.6, 0.7, 0.9])], f, seed=1, key="k", sequence_id="s")
    np.testing.assert_allclose(given[1].diagnostics["airlight"], factor * np.array([0.6, 0.7, 0.9]), rtol=1e-12)


@pytest.mark.parametrize("weather", ["rain.camera", "snow.camera"])
def test_cnf13_cnf15_particle_radiance_follows_the_darker_scene(weather):
    f = frame(400, 600, sky_rows=150)
    _, day = apply_models([MODELS[weather]()], f, seed=1, key="k", sequence_id="s")
    _, night = apply_models([LowLight(), MODELS[weather]()], f, seed=1, key="k", sequence_id="s")
    np.testing.assert_allclose(night[1].diagnostics["particle_radiance"],
                               8e-3 * np.array(day[0].diagnostics["particle_radiance"]), rtol=0.03)


def _onnx_model(path, scale=0.5, offset=-0.5):
    """y = scale·x + offset through SpaceToDepth/DepthToSpace of block 4: sizes must be multiples of 4."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "H", "W"])
    y = helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 3, "H", "W"])
    nodes = [helper.make_node("SpaceToDepth", ["image"], ["s2d"], blocksize=4),
             helper.make_node("DepthToSpace", ["s2d"], ["d2s"], blocksize=4),
             helper.make_node("Mul", ["d2s", "scale"], ["scaled"]),
             helper.make_node("Add", ["scaled", "offset"], ["out"])]
    inits = [helper.make_tensor("scale", TensorProto.FLOAT, [], [scale]),
             helper.make_tensor("offset", TensorProto.FLOAT, [], [offset])]
    model = helper.make_model(helper.make_graph(nodes, "tiny_night", [x], [y], inits),
                              opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def test_onnx_backend_full_resolution_with_padding(tmp_path):
    pytest.importorskip("onnxruntime")
    from roadview_noise.physics import srgb

    path = _onnx_model(tmp_path / "night.onnx")
    f = frame(37, 50)                                           # not a multiple of 4: padded, then cropped
    out, diag = run(LowLight(backend="onnx", onnx_model=str(path)), f)
    want = srgb.decode(srgb.encode(f.linear_rgb) * 0.5)        # sRGB halved by the network
    assert out.linear_rgb.shape == f.linear_rgb.shape
    np.testing.assert_allclose(out.linear_rgb, want, atol=2e-6)
    assert diag["luminance_factor"] == pytest.approx(want.mean() / f.linear_rgb.mean(), rel=0.05)
    assert out.conditions.luminance_factor == pytest.approx(diag["luminance_factor"])
    with pytest.raises(ModelError, match="night.onnx"):         # without padding the network cannot run
        run(LowLight(backend="onnx", onnx_model=str(path), onnx_input_multiple_px=1), f)


def test_onnx_backend_errors(tmp_path):
    with pytest.raises(ModelError, match="onnx_model"):
        LowLight(backend="onnx")
    with pytest.raises(ModelError, match="not found"):
        run(LowLight(backend="onnx", onnx_model=str(tmp_path / "missing.onnx")), frame())
    with pytest.raises(ModelError, match="physical"):
        run(LowLight(backend="onnx", onnx_model=str(tmp_path / "missing.onnx")), mosaic(frame()))


def test_compression_refuses_a_mosaic_naming_the_alternative():
    with pytest.raises(ModelError, match="RGB output instead"):
        run(Compression(), mosaic(frame()))
