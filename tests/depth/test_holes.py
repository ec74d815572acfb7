"""Depth holes: pull-push fill (properties on any size and hole pattern), the sky policy against an independent
labelling, the error policy, and what holes do to fog, rain and snow: no flat patches, and fog still whitens a
mid-grey image when a dark region has no depth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage

from roadview_noise.depth.holes import connected_to_top, pull_push, resolve_holes
from roadview_noise.errors import InputError
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.registry import load_all
from roadview_noise.types import CameraFrame

MODELS = load_all()
H, W = 183, 242
PROFILE = lucid_triton_028s().resized(W, H)


@st.composite
def maps_with_holes(draw):
    h, w = draw(st.integers(1, 40)), draw(st.integers(1, 40))
    values = draw(arrays(np.float32, (h, w), elements=st.floats(0.0625, 16.0, width=32)))
    known = draw(arrays(np.bool_, (h, w)))
    known.flat[draw(st.integers(0, h * w - 1))] = True            # at least one valid pixel
    return values, known


@settings(max_examples=150, deadline=None)
@given(maps_with_holes())
def test_pull_push_properties(case):
    """Any size, any hole pattern: known pixels unchanged, holes finite and inside the range of the known values
    (every estimate is a convex combination of known values)."""
    values, known = case
    out = pull_push(values, known)
    np.testing.assert_array_equal(out[known], values[known])
    assert np.isfinite(out).all()
    lo, hi = values[known].min(), values[known].max()
    assert (out >= lo * (1 - 1e-5)).all() and (out <= hi * (1 + 1e-5)).all()


def test_pull_push_is_exact_on_a_linear_ramp_interior():
    """A plane in inverse depth (a flat surface) with a hole in its interior is filled close to the plane."""
    v, u = np.mgrid[0:64, 0:64].astype(np.float32)
    ramp = 0.01 + 0.001 * u + 0.0005 * v
    known = np.ones_like(ramp, dtype=bool)
    known[24:40, 20:44] = False
    out = pull_push(ramp, known)
    assert np.abs(out - ramp)[~known].max() < 0.1 * np.ptp(ramp)


@settings(max_examples=60, deadline=None)
@given(arrays(np.bool_, st.tuples(st.integers(1, 30), st.integers(1, 30))))
def test_sky_holes_are_the_components_touching_the_top(mask):
    labels, _ = ndimage.label(mask, structure=np.ones((3, 3)))   # independent 8-connected labelling
    top = set(labels[0][labels[0] > 0])
    np.testing.assert_array_equal(connected_to_top(mask), np.isin(labels, list(top)) & mask)


def test_policies_and_notes():
    depth = np.full((20, 30), 10.0, np.float32)
    depth[:5] = np.inf
    depth[0:8, 10:14] = np.nan            # touches the top: sky under `sky`
    depth[12:15, 3:6] = np.nan            # inside: always filled
    out, valid, notes = resolve_holes(depth, "fill")
    assert np.isfinite(out[12:15, 3:6]).all() and notes == {"holes": 41, "hole_fraction": round(41 / 600, 6),
                                                             "policy": "fill", "filled": 41, "sky": 0}
    assert not valid[12:15, 3:6].any() and valid.sum() == 600 - 41
    np.testing.assert_allclose(out[13, 4], 10.0, rtol=1e-5)          # surrounded by 10 m
    out, valid, notes = resolve_holes(depth, "sky")
    assert np.isinf(out[0:8, 10:14]).all() and notes["sky"] == 32 and notes["filled"] == 9
    assert valid[0:8, 10:14].all()                                    # declared sky counts as sky
    with pytest.raises(InputError, match=r"41 holes \(6.8 %.*depth_holes: fill") as err:
        resolve_holes(depth, "error", source="d.exr")
    assert "d.exr" in str(err.value)
    with pytest.raises(InputError, match="no pixel has a valid depth"):
        resolve_holes(np.full((3, 3), np.nan, np.float32), "fill")
    same, valid, notes = resolve_holes(np.full((3, 3), 5.0, np.float32), "error")
    assert valid is None and notes == {"holes": 0}


# --- holes under the weather models --------------------------------------------------------------------------------


def _scene(seed=0):
    """Uniform random texture; ground below the horizon, a wall at 25 m across the middle, sky above it."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = (u - PROFILE.cx_px) / PROFILE.fx_px, (v - PROFILE.cy_px) / PROFILE.fy_px
    with np.errstate(divide="ignore"):
        z = np.where(y > 0, np.minimum(1.0 / y, 25.0), np.where(y * 25 > -8, 25.0, np.inf))
    img = rng.uniform(0.05, 0.5, (H, W, 3)).astype(np.float32)
    img[~np.isfinite(z)] = (0.6, 0.7, 0.9)
    return img, (z * np.sqrt(1 + x * x + y * y)).astype(np.float32)


def _holes(seed=1, fraction=0.07):
    """Blobs inside the image (not touching the top), about ``fraction`` of the pixels."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((H, W), np.uint8)
    while mask.mean() < fraction:
        cv2.circle(mask, (int(rng.integers(20, W - 20)), int(rng.integers(60, H - 15))), int(rng.integers(4, 10)),
                   1, -1)
    return mask.astype(bool)


def _local_variance(img):
    lum = img.mean(axis=2).astype(np.float64)
    return cv2.blur(lum * lum, (5, 5)) - cv2.blur(lum, (5, 5)) ** 2


def _texture_ratio(out, holes):
    """Mean local variance inside the holes / in a 9-px ring around them."""
    ring = cv2.dilate(holes.astype(np.uint8), np.ones((19, 19), np.uint8)).astype(bool) & ~holes
    inner = cv2.erode(holes.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)   # away from the hole edge
    var = _local_variance(out)
    return var[inner].mean() / var[ring].mean()


@pytest.mark.parametrize("model_id,params", [("fog.camera", {"visibility_m": 30}),
                                             ("rain.camera", {"rain_rate_mm_per_h": 50}),
                                             ("snow.camera", {"snowfall_rate_mm_per_h": 3.03})])
def test_filled_holes_keep_the_texture_under_weather(model_id, params):
    """NaN holes with `fill`: the filled region's local variance is within a factor 2 of its surroundings'. Holes
    made sky (the hint of the old error message, NaN → inf) give flat patches: a factor < 1/10."""
    img, depth = _scene()
    holes = _holes()
    noisy = depth.copy()
    noisy[holes] = np.nan
    filled, valid, notes = resolve_holes(noisy, "fill")
    model = MODELS[model_id](**params)
    rng = np.random.default_rng(0)
    out, _ = model.apply(CameraFrame(img, PROFILE, filled, depth_valid=valid), state={}, drawn={}, rng=rng)
    ratio = _texture_ratio(out.linear_rgb, holes)
    assert 0.5 < ratio < 2.0, ratio
    as_sky = np.where(holes, np.float32(np.inf), depth)
    flat, _ = model.apply(CameraFrame(img, PROFILE, as_sky), state={}, drawn={}, rng=np.random.default_rng(0))
    assert _texture_ratio(flat.linear_rgb, holes) < 0.1


def test_fog_whitens_mid_grey_despite_a_dark_hole():
    """No sky in view, a dark region without depth: the airlight comes from the brightest pixels with a valid depth,
    so fog raises the mean brightness. Taking the hole as sky (NaN → inf) makes a dark fog that lowers it."""
    rng = np.random.default_rng(2)
    img = np.clip(rng.normal(0.18, 0.02, (H, W, 3)), 0, 1).astype(np.float32)     # mid grey (sRGB ≈ 0.46)
    img[:20] = 0.75                                                               # a bright facade, finite depth
    depth = np.full((H, W), 40.0, np.float32)
    hole = np.zeros((H, W), bool)
    hole[:, :60] = True                                                           # dark, no depth
    img[hole] = 0.01
    noisy = np.where(hole, np.float32(np.nan), depth)
    filled, valid, _ = resolve_holes(noisy, "fill")
    fog = MODELS["fog.camera"](visibility_m=30)
    out, diag = fog.apply(CameraFrame(img, PROFILE, filled, depth_valid=valid), state={}, drawn={},
                          rng=np.random.default_rng(0))
    assert out.linear_rgb.mean() > img.mean() + 0.1
    assert min(diag["airlight"]) > 0.7
    dark, diag = fog.apply(CameraFrame(img, PROFILE, np.where(hole, np.float32(np.inf), depth)), state={}, drawn={},
                           rng=np.random.default_rng(0))
    assert dark.linear_rgb.mean() < img.mean() and max(diag["airlight"]) < 0.05
