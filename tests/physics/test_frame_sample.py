"""The radiance estimates' shared lattice sample (physics.photometry.FrameSample, physics.cfa.SiteLayout.lattice):
the sites it reads are those of the ``SAMPLE_STEP_PX`` lattice of every CFA phase, whatever the frame's size, and the
estimates built on it equal a direct full-frame computation (masks over the whole (H, W) frame, then sub-sampled)."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.physics.cfa import SiteLayout
from roadview_noise.physics.photometry import (ENVIRONMENT_ROWS_FRACTION, LUMINANCE_WEIGHTS, SAMPLE_STEP_PX,
                                               FrameSample, airlight_radiance, environment_radiance,
                                               raindrop_radiance, sky_luminance)
from roadview_noise.types import cfa_index_map

RGB = SiteLayout(np.arange(3).reshape(1, 1, 3))
STEP = SAMPLE_STEP_PX


def frame(h, w, seed=0, holes=True):
    """Random RGB radiance and a depth map with a sky band, NaN holes (not valid) and surfaces at 2–90 m."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.0, 1.0, (h, w, 3)).astype(np.float32)
    depth = rng.uniform(2.0, 90.0, (h, w)).astype(np.float32)
    depth[: h // 3] = np.inf
    depth[rng.random((h, w)) < 0.05] = np.inf                      # sky seen between surfaces
    if holes:
        depth[rng.random((h, w)) < 0.1] = np.nan
    return img, depth


def lattice_sites(layout, shape, rows=None):
    """(H, W) bool: the sites a step-``STEP`` lattice of each CFA phase reads, from the index arithmetic alone."""
    r, c = np.indices(shape)
    phase = 2 if layout.mosaic else 1
    on = (r % STEP < phase) & (c % STEP < phase)
    return on & (r < (shape[0] if rows is None else rows))


def channel_of(layout, img):
    """Per channel, an (H, W) plane of the signal and the (H, W) bool map of the sites of that channel."""
    if layout.mosaic:
        return [(img, layout.channel_index == c) for c in range(3)]
    return [(img[..., c], np.ones(img.shape[:2], bool)) for c in range(3)]


@pytest.mark.parametrize("shape", [(37, 53), (64, 96), (41, 40)])
@pytest.mark.parametrize("mosaic", [False, True])
def test_lattice_sample_reads_the_lattice_sites_of_each_channel(shape, mosaic):
    """Values per channel (as multisets) where a mask is true, also in the first rows only, equal a full-frame
    selection of the lattice sites; FrameSample.values(test) is that selection with the mask test(depth)."""
    img, depth = frame(*shape)
    layout = SiteLayout(cfa_index_map("RGGB", *shape)) if mosaic else RGB
    signal = np.take_along_axis(img, layout.channel_index[..., None].astype(np.int64), 2)[..., 0] if mosaic else img
    finite = np.isfinite(depth)
    rows = shape[0] // 2 + 1
    got_all = layout.channel_samples(signal, step=STEP, mask=finite)
    got_top = layout.channel_samples(signal, step=STEP, mask=finite, rows=rows)
    got_sample = FrameSample(layout, signal, depth).values(np.isfinite)
    for c, (plane, of_channel) in enumerate(channel_of(layout, signal)):
        want_all = np.sort(plane[lattice_sites(layout, shape) & of_channel & finite])
        want_top = np.sort(plane[lattice_sites(layout, shape, rows) & of_channel & finite])
        np.testing.assert_array_equal(np.sort(got_all[c]), want_all)
        np.testing.assert_array_equal(np.sort(got_sample[c]), want_all)
        np.testing.assert_array_equal(np.sort(got_top[c]), want_top)


@pytest.mark.parametrize("mosaic", [False, True])
def test_estimates_equal_a_full_frame_computation(mosaic):
    """Sky luminance = Y of the per-channel mean over the lattice's sky sites; the environment radiance = per channel
    mean over the upper 3/5's lattice sites of finite depth, sky sites counting as the given sky radiance, NaN (not
    valid) sites left out — computed here from full-frame masks in float64."""
    shape = (90, 132)
    img, depth = frame(*shape, seed=3)
    layout = SiteLayout(cfa_index_map("RGGB", *shape)) if mosaic else RGB
    signal = np.take_along_axis(img, layout.channel_index[..., None].astype(np.int64), 2)[..., 0] if mosaic else img
    sky = np.array([0.7, 0.8, 0.9])
    rows = max(1, round(ENVIRONMENT_ROWS_FRACTION * shape[0]))
    sky_mean, env = np.empty(3), np.empty(3)
    for c, (plane, of_channel) in enumerate(channel_of(layout, signal)):
        on = lattice_sites(layout, shape) & of_channel
        sky_mean[c] = plane[on & np.isinf(depth)].astype(np.float64).mean()
        top = lattice_sites(layout, shape, rows) & of_channel
        seen = plane[top & np.isfinite(depth)].astype(np.float64)
        n_sky = np.count_nonzero(top & np.isinf(depth))
        env[c] = (seen.sum() + n_sky * sky[c]) / (seen.size + n_sky)
    assert sky_luminance(layout, signal, depth) == pytest.approx(LUMINANCE_WEIGHTS @ sky_mean, rel=1e-12)
    np.testing.assert_allclose(environment_radiance(layout, signal, depth, sky), env, rtol=1e-12)


def test_without_sky_the_brightest_valid_lattice_pixels_set_the_level():
    """No sky in view, NaN holes in the depth: the level is the mean Y of the brightest 0.1 % (at least one) of the
    lattice pixels with a valid depth — a brighter pixel in a hole does not count."""
    img, depth = frame(80, 120, seed=5)
    depth[np.isinf(depth)] = 50.0
    depth[::STEP, ::STEP][3, 4] = np.nan
    img[::STEP, ::STEP][3, 4] = 1.0                               # the brightest lattice pixel, in a hole
    y = img[::STEP, ::STEP] @ LUMINANCE_WEIGHTS
    valid_y = y[~np.isnan(depth[::STEP, ::STEP])]
    assert y.max() > valid_y.max()
    assert sky_luminance(RGB, img, depth) == pytest.approx(valid_y.max(), rel=1e-12)


@pytest.mark.parametrize("mosaic", [False, True])
def test_a_validity_mask_acts_as_nan_depth(mosaic):
    """``depth_valid`` False (filled holes: their depth is a finite or ``inf`` fill) gives the estimates of the same
    depth with NaN there — also where the fill says sky — and differs from trusting the fill."""
    shape = (96, 128)
    img, depth = frame(*shape, seed=9, holes=False)
    rng = np.random.default_rng(1)
    valid = rng.random(shape) > 0.3
    valid[: shape[0] // 3, : shape[1] // 2] = False                 # a filled hole in the sky: fill says inf
    img[~valid] *= 0.5                                               # the fill's colour differs
    layout = SiteLayout(cfa_index_map("RGGB", *shape)) if mosaic else RGB
    signal = np.take_along_axis(img, layout.channel_index[..., None].astype(np.int64), 2)[..., 0] if mosaic else img
    nan_depth = np.where(valid, depth, np.float32(np.nan))
    for radiance in (airlight_radiance, raindrop_radiance):
        with_mask = radiance(layout, signal, depth, valid)
        np.testing.assert_array_equal(with_mask, radiance(layout, signal, nan_depth))
        assert not np.array_equal(with_mask, radiance(layout, signal, depth))
