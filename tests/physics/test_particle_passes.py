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
