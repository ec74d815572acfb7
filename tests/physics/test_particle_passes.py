"""The per-pixel passes of a camera rain/snow frame (physics/particles.py: count_buckets, blend_through_particles,
veil_transmission's bins, render_coverage's clip) give exactly what the separate steps give: the same counts for
every uniform, the same float32 image as transmit_through_particles then photometry.composite."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roadview_noise.physics import particles as P
from roadview_noise.physics.cfa import SiteLayout
from roadview_noise.physics.photometry import composite
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.registry import get_model
from roadview_noise.types import CameraFrame, Conditions, RawFrame

SNOW = get_model("snow.camera")()
PROFILE = dataclasses.replace(lucid_triton_028s(), width_px=242, height_px=183, cx_px=121.0, cy_px=91.5,
                              fx_px=lucid_triton_028s().fx_px / 8, fy_px=lucid_triton_028s().fy_px / 8)


def _field(rate_mm_per_h=3.03):
    model = get_model("snow.camera")(snowfall_rate_mm_per_h=rate_mm_per_h)
    tables = P.particle_tables(PROFILE, 0.005, model.size_classes(), model.fall_speed, Conditions(), 0.5, 30.0,
                               0.02, 1.0)
    return tables


def _counts(cuts, u):
    return (cuts[:, None, :] <= u[None, :, None]).sum(axis=2)           # (bins, uniforms): N of the draw


@pytest.mark.parametrize("cuts", [_field().unresolved.cuts, _field(50.0).unresolved.cuts,
                                  np.sort(np.random.default_rng(3).integers(0, 1 << 16, (4, 200)), axis=1)],
                         ids=["snow", "heavy snow", "200 cuts"])
def test_count_buckets_give_every_uniforms_count(cuts):
    """Per bin and 16-bit uniform: where no cut falls inside the uniform's bucket the bucket is the count; else
    (and where the count passes 127) counting on from the bucket reaches it."""
    cuts = np.concatenate([cuts, np.full((cuts.shape[0], 1), 1 << 16)], axis=1).astype(np.int32)
    buckets = P.count_buckets(cuts).reshape(cuts.shape[0], -1)
    u = np.arange(1 << 16)
    bucket = buckets[:, u >> P.BUCKET_SHIFT]
    n = _counts(cuts, u)
    exact = bucket < 128
    np.testing.assert_array_equal(bucket[exact], n[exact])
    assert np.all((bucket[~exact] & 127) <= n[~exact])
    assert exact.mean() > 0.9 if cuts.shape[1] < 64 else not exact.all()


def _scene(mosaic):
    h, w = PROFILE.height_px, PROFILE.width_px
    rng = np.random.default_rng(0)
    k = P.ray_factor(w, h, PROFILE.fx_px, PROFILE.fy_px, PROFILE.cx_px, PROFILE.cy_px)
    depth = (rng.uniform(0.3, 40.0, (h, w)) * k).astype(np.float32)
    depth[: h // 3] = np.inf
    if mosaic:
        return RawFrame(rng.uniform(64, 4095, (h, w)).astype(np.float32), "GRBG", 64.0, 4095.0, PROFILE, depth)
    return CameraFrame(rng.random((h, w, 3), np.float32), PROFILE, depth)


@pytest.mark.parametrize("mosaic", [False, True], ids=["rgb", "raw"])
@pytest.mark.parametrize("unresolved", [True, False], ids=["field", "no field"])
def test_blend_through_particles_is_transmit_then_composite(mosaic, unresolved):
    frame = _scene(mosaic)
    tables = _field()
    field = tables.unresolved if unresolved else None
    layout, signal, depth = SiteLayout.of(frame), frame.signal(), frame.depth_m
    values = np.array([0.61, 0.55, 0.48])
    coverage = np.random.default_rng(1).uniform(0.0, 1.2, depth.shape).astype(np.float32)
    sigma = SNOW.size_classes().extinction_per_m()

    t = P.veil_transmission(PROFILE, depth, tables.veil, sigma, 30.0)
    cov_a = coverage.copy()
    mean_a = P.transmit_through_particles(t, cov_a, PROFILE, depth, field, 30.0, np.random.default_rng(7))
    expected = composite(layout, signal, t, values)

    bins = np.empty(depth.shape, np.uint8)
    t_b = P.veil_transmission(PROFILE, depth, tables.veil, sigma, 30.0, bins)
    cov_b = coverage.copy()
    out, mean_b = P.blend_through_particles(layout, signal, values, t_b, cov_b, PROFILE, depth, field, 30.0,
                                            np.random.default_rng(7), bins)
    assert out.shape == signal.shape and out.dtype == np.float32
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(cov_b, cov_a)
    assert mean_b == mean_a
    assert cov_a.max() <= 1.0 and (unresolved or np.array_equal(cov_a, np.minimum(coverage, 1.0)))


def _kernel_inputs(rng, draw, scene_bins, bands, blend):
    """Random operands of ``P._transmit_kernel`` (37×53 pixels): bins given or from the depth, ``bands`` motion bands
    (0: none), ``blend`` "none" (t·(1 − M) into t), "rgb" or "mosaic"."""
    h, w, n_bins = 37, 53, P.VEIL_LUT_SIZE * max(bands, 1)
    k = rng.uniform(1.0, 1.6, (h, w)).astype(np.float32)
    depth = (rng.uniform(0.3, 40.0, (h, w)) * k).astype(np.float32)
    depth[:5] = np.inf
    cuts = np.sort(rng.integers(0, 1 << 16, (n_bins, 9)), axis=1)
    cuts = np.concatenate([cuts, np.full((n_bins, 1), 1 << 16)], axis=1).astype(np.int32)
    field = (cuts, P.count_buckets(cuts), rng.uniform(0, 0.01, n_bins).astype(np.float32),
             rng.integers(0, 1 << 16, h * w).astype(np.uint16),
             rng.integers(0, bands, (h, w)).astype(np.uint8) if bands else np.zeros((0, 0), np.uint8))
    if not draw:
        field = (np.zeros((0, 0), np.int32), np.zeros(0, np.uint8), np.zeros(0, np.float32), np.zeros(0, np.uint16),
                 np.zeros((0, 0), np.uint8))
    width = {"none": 0, "rgb": 3 * w, "mosaic": w}[blend]
    signal = rng.uniform(0, 1, (h if width else 0, width)).astype(np.float32)
    values = {"none": np.zeros((1, 1)), "rgb": np.tile([0.6, 0.5, 0.4], (1, w)),
              "mosaic": rng.uniform(0, 1, (2, w))}[blend].astype(np.float32)
    scene = rng.integers(0, 256, (h, w)).astype(np.uint8) if scene_bins else np.empty((0, 0), np.uint8)
    return [rng.uniform(0, 1, (h, w)).astype(np.float32), rng.uniform(0, 1.2, (h, w)).astype(np.float32), depth, k,
            scene, rng.uniform(1, 30, h).astype(np.float32), np.float32(255 / 30.0), *field, draw, values, signal,
            np.empty_like(signal)]


@pytest.mark.parametrize("blend", ["none", "rgb", "mosaic"])
@pytest.mark.parametrize("draw, scene_bins, bands", [(True, True, 0), (True, False, 0), (True, True, 3),
                                                     (True, False, 2), (False, True, 0), (False, False, 0)],
                         ids=["bins", "depth", "bins, bands", "depth, bands", "no field", "no field, depth"])
def test_transmit_kernel_is_the_per_pixel_formula(draw, scene_bins, bands, blend):
    """Every mode of the fused pass against the formula in NumPy float32: bin b (nearest of the scene's and the
    ground's, + band · VEIL_LUT_SIZE), N = #cuts[b] ≤ u, M = min(coverage + N · mark[b] · k, 1), then t·(1 − M)
    into t or S + t·(1 − M)·(I − S) into the output; Σ M returned."""
    a = _kernel_inputs(np.random.default_rng(5), draw, scene_bins, bands, blend)
    t, cov, depth, k, scene, ground, per_m, cuts, _, mark, bits, band, _, values, signal, _ = \
        [x.copy() if isinstance(x, np.ndarray) else x for x in a]
    h, w = depth.shape
    added = np.zeros((h, w), np.float32)
    if draw:
        half = np.float32(0.5)
        near = np.minimum(scene, (ground * per_m + half).astype(np.uint8)[:, None]) if scene_bins else \
            (np.minimum(depth / k, ground[:, None]) * per_m + half).astype(np.uint8)
        b = near.astype(np.int64) + (band.astype(np.int64) * P.VEIL_LUT_SIZE if bands else 0)
        n = (cuts[b] <= bits.reshape(h, w)[..., None]).sum(axis=-1)
        added = n.astype(np.float32) * mark[b]
    m = np.minimum(cov + added * k, np.float32(1))
    tm = t * (np.float32(1) - m)
    total = P._transmit_kernel(*a)
    np.testing.assert_array_equal(a[1], m)
    if blend == "none":
        np.testing.assert_array_equal(a[0], tm)
    else:
        s = values[np.arange(h) % values.shape[0]] if blend == "mosaic" else values
        per_value = np.repeat(tm, 3, axis=1) if blend == "rgb" else tm
        np.testing.assert_array_equal(a[-1], s + per_value * (signal - s))
    assert total == pytest.approx(float(m.astype(np.float64).sum()), rel=1e-12)
