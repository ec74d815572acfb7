"""The weather's sky radiance (physics.photometry.airlight_radiance): level = the frame's sky luminance, colour = the
illuminant's (Narasimhan & Nayar 2002: fog scatters all visible wavelengths alike), on synthetic scenes whose
illuminant and reflectances are known. RGB frames are white-balanced (neutral); raw mosaics estimate the
illuminant."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.physics.cfa import SiteLayout
from roadview_noise.physics.photometry import (LUMINANCE_WEIGHTS, airlight_radiance, illuminant_chromaticity,
                                               raindrop_radiance, sky_luminance)
from roadview_noise.types import cfa_index_map

H, W = 240, 320
RGB = SiteLayout(np.arange(3).reshape(1, 1, 3))
# linear sRGB reflectances: asphalt, concrete, white line, foliage, brick, blue paint, yellow paint, dark soil
GREYS = [(0.06, 0.06, 0.06), (0.25, 0.25, 0.25), (0.75, 0.75, 0.75)]
COLOURS = [(0.07, 0.14, 0.03), (0.33, 0.11, 0.06), (0.04, 0.09, 0.33), (0.55, 0.45, 0.04), (0.09, 0.06, 0.04)]
BLUE_SKY = (0.30, 0.48, 0.95)
NEUTRAL = (1.0, 1.0, 1.0)
WARM = (1.0, 0.78, 0.50)           # ~3000 K rendered by a camera balanced for daylight
DEEP_SKY_ROWS = 60


def scene(illuminant=NEUTRAL, sky=BLUE_SKY, seed=0, grey_share=0.4, sky_rows=DEEP_SKY_ROWS):
    """Blocks of 16×16 px: reflectance × illuminant with ±10 % shading and ±2 % per-channel texture; the upper
    ``sky_rows`` rows are sky (depth inf) of colour ``sky``; surfaces at 5–80 m."""
    rng = np.random.default_rng(seed)
    bh, bw = H // 16, W // 16
    grey = rng.random((bh, bw)) < grey_share
    pick = np.where(grey, rng.integers(0, len(GREYS), (bh, bw)), len(GREYS) + rng.integers(0, len(COLOURS), (bh, bw)))
    palette = np.array(GREYS + COLOURS)
    refl = np.repeat(np.repeat(palette[pick], 16, axis=0), 16, axis=1)
    img = refl * np.asarray(illuminant) * rng.uniform(0.9, 1.1, (H, W, 1)) * rng.uniform(0.98, 1.02, (H, W, 3))
    depth = rng.uniform(5.0, 80.0, (H, W))
    img[:sky_rows] = sky
    depth[:sky_rows] = np.inf
    return img.astype(np.float32), depth.astype(np.float32)


def chroma(v):
    v = np.asarray(v, float)
    return v / (LUMINANCE_WEIGHTS @ v)


def mosaic(img):
    ch = cfa_index_map("RGGB", H, W)
    return SiteLayout(ch), np.take_along_axis(img, ch[..., None].astype(np.int64), axis=2)[..., 0]


@pytest.mark.parametrize("illuminant", [NEUTRAL, WARM, (0.85, 1.0, 1.1)])
def test_airlight_has_the_illuminants_colour_and_the_skys_luminance(illuminant):
    """A blue clear sky over surfaces lit by a known illuminant. Raw mosaic (unbalanced camera channels): the
    airlight's chromaticity is the illuminant's within 2 % per channel, not the sky's. RGB (white-balanced by the
    camera): neutral. Both: the sky's luminance (exact)."""
    img, depth = scene(illuminant)
    sky_y = LUMINANCE_WEIGHTS @ np.asarray(BLUE_SKY, np.float32)
    raw = airlight_radiance(*mosaic(img), depth)
    np.testing.assert_allclose(chroma(raw), chroma(illuminant), rtol=0.02)
    rgb = airlight_radiance(RGB, img, depth)
    np.testing.assert_allclose(rgb, np.full(3, sky_y), rtol=1e-6)
    assert LUMINANCE_WEIGHTS @ raw == pytest.approx(sky_y, rel=1e-6)


def test_the_clear_skys_colour_does_not_colour_the_weather():
    """Two clear skies of equal luminance but different colour give the same fog airlight and raindrop radiance."""
    blue = np.array(BLUE_SKY)
    red = (LUMINANCE_WEIGHTS @ blue) * chroma((0.9, 0.5, 0.3))
    (img_b, depth), (img_r, _) = scene(sky=blue), scene(sky=red)
    for layout, (sig_b, sig_r) in ((RGB, (img_b, img_r)), (mosaic(img_b)[0], (mosaic(img_b)[1], mosaic(img_r)[1]))):
        np.testing.assert_allclose(airlight_radiance(layout, sig_r, depth), airlight_radiance(layout, sig_b, depth),
                                   rtol=1e-6)
        np.testing.assert_allclose(raindrop_radiance(layout, sig_r, depth),
                                   raindrop_radiance(layout, sig_b, depth), rtol=1e-6)


def test_without_sky_the_level_is_the_brightest_pixels_luminance():
    img, depth = scene(WARM, sky_rows=0)
    y = img @ LUMINANCE_WEIGHTS.astype(np.float32)
    level = sky_luminance(RGB, img, depth)
    assert 0.9 * y.max() < level <= y.max() + 1e-6
    np.testing.assert_allclose(chroma(airlight_radiance(*mosaic(img), depth)), chroma(WARM), rtol=0.02)


def test_raw_estimate_ignores_clipped_pixels():
    """Clipped pixels have lost their colour: a clipped warm highlight (1, 1, 0.6) does not tint the raw estimate."""
    img, depth = scene()
    img[DEEP_SKY_ROWS:DEEP_SKY_ROWS + 60] = (1.0, 1.0, 0.6)
    np.testing.assert_allclose(illuminant_chromaticity(*mosaic(img), depth), chroma(NEUTRAL), rtol=0.02)


def test_scale_invariance_carries_the_low_light_factor():
    """A frame darkened by k (low light before the weather): airlight and drop radiance scale by exactly k."""
    img, depth = scene(WARM)
    for layout, signal in ((RGB, img), mosaic(img)):
        dark = signal * np.float32(0.008)
        np.testing.assert_allclose(airlight_radiance(layout, dark, depth),
                                   0.008 * airlight_radiance(layout, signal, depth), rtol=1e-5)
        np.testing.assert_allclose(raindrop_radiance(layout, dark, depth),
                                   0.008 * raindrop_radiance(layout, signal, depth), rtol=1e-5)


def test_raw_airlight_of_a_clipped_sky_stays_at_the_white_level():
    """A sky clipped at white (signal 1 in every channel) under a warm illuminant: its luminance 1 times the warm
    chromaticity would put R above white; a site records no more than saturation, so each raw channel is capped at
    1 (the RGB airlight, neutral, is 1 already)."""
    img, depth = scene(WARM, sky=(1.0, 1.0, 1.0))
    raw = airlight_radiance(*mosaic(img), depth)
    assert raw.max() == pytest.approx(1.0) and chroma(WARM).max() > 1.0
    assert np.all(raw <= 1.0)
    np.testing.assert_allclose(airlight_radiance(RGB, img, depth), np.ones(3), rtol=1e-6)
