"""Procedural blob masks on any grid (models.md §2.4, reused by LiDAR/radar obstruction) and lens-dirt image
formation (Gu et al. 2009)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roadview_noise.physics.blob_mask import blob_mask
from roadview_noise.physics.cfa import SiteLayout
from roadview_noise.physics.soiling import soil
from roadview_noise.types import cfa_index_map


def test_deterministic_and_in_unit_range():
    a = blob_mask((366, 484), np.random.default_rng(5), size_px=(23, 68), count=12)
    b = blob_mask((366, 484), np.random.default_rng(5), size_px=(23, 68), count=12)
    np.testing.assert_array_equal(a.mask, b.mask)
    assert a.mask.dtype == np.float32 and a.mask.min() >= 0 and a.mask.max() <= 1 and a.count == 12
    assert 0 < a.covered_fraction() < 0.5


@settings(max_examples=25, deadline=None)
@given(size=st.floats(4, 60), seed=st.integers(0, 2 ** 32))
def test_a_blob_stays_within_its_diameter(size, seed):
    """Without softening, every covered cell lies within S/2 (+1 px of rasterisation) of the blob centre."""
    h = w = 201
    m = blob_mask((h, w), np.random.default_rng(seed), size_px=(size, size), count=1, softness=0.0).mask
    rows, cols = np.nonzero(m > 0)
    assert rows.size > 0
    centre_r, centre_c = (rows.min() + rows.max()) / 2, (cols.min() + cols.max()) / 2
    assert rows.max() - rows.min() <= size + 2 and cols.max() - cols.min() <= size + 2
    assert np.hypot(rows - centre_r, cols - centre_c).max() <= size / 2 * np.sqrt(2) + 2


def test_seed_probability_gives_binomial_counts():
    """D3.5 obstruction: p = 6e-5 per cell of a 128×2048 range image → 15.7 blobs per frame on average."""
    counts = [blob_mask((128, 2048), np.random.default_rng(s), size_px=(2, 6), seed_probability=6e-5,
                        column_scale=2.0, wrap_columns=True).count for s in range(300)]
    assert np.mean(counts) == pytest.approx(128 * 2048 * 6e-5, rel=0.06)
    assert np.var(counts) == pytest.approx(128 * 2048 * 6e-5, rel=0.25)


def test_wrapping_columns_keeps_the_blob_whole():
    h, w = 64, 256
    seeds = range(400)
    clipped = wrapped = 0.0
    for s in seeds:   # blobs near the seam: wrapped ones keep their full area, clipped ones lose part of it
        clipped += blob_mask((h, w), np.random.default_rng(s), size_px=(30, 30), count=1).mask.sum()
        wrapped += blob_mask((h, w), np.random.default_rng(s), size_px=(30, 30), count=1, wrap_columns=True).mask.sum()
    assert wrapped > clipped
    tiny = blob_mask((8, 6), np.random.default_rng(0), size_px=(20, 20), count=2, wrap_columns=True)
    assert tiny.mask.shape == (8, 6) and tiny.mask.max() <= 1


def test_vertical_bias_moves_blobs_down():
    rows = np.arange(400)[:, None]
    def centre_row(bias):
        m = sum(blob_mask((400, 300), np.random.default_rng(s), size_px=(10, 10), count=20,
                          vertical_bias=bias).mask for s in range(10))
        return (m * rows).sum() / m.sum()
    assert centre_row(1.0) > centre_row(0.0) + 40          # density 2y/H: mean 2/3 H against 1/2 H


def test_parameters_checked():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="exactly one"):
        blob_mask((10, 10), rng, size_px=(2, 3))
    with pytest.raises(ValueError, match="exactly one"):
        blob_mask((10, 10), rng, size_px=(2, 3), count=1, seed_probability=0.1)
    with pytest.raises(ValueError, match="S_min"):
        blob_mask((10, 10), rng, size_px=(5, 3), count=1)


def test_soil_formation_rgb_and_mosaic():
    rng = np.random.default_rng(1)
    img = rng.random((40, 50, 3)).astype(np.float32)
    cov = np.zeros((40, 50), np.float32)
    cov[10:20, 10:30] = 1.0
    cov[25:30] = 0.5
    stray = np.array([0.30, 0.25, 0.20]) * img.reshape(-1, 3).mean(axis=0)      # ρ_mud ⊙ Ī
    out = soil(SiteLayout(np.arange(3).reshape(1, 1, 3)), img, cov, 1.0, stray)
    np.testing.assert_array_equal(out[cov == 0], img[cov == 0])                  # bit-identical
    np.testing.assert_array_equal(out[cov == 1], np.broadcast_to(stray.astype(np.float32), (200, 3)))
    np.testing.assert_allclose(out[cov == 0.5], 0.5 * img[cov == 0.5] + 0.5 * stray.astype(np.float32),
                               rtol=1e-6)
    ch = cfa_index_map("RGGB", 40, 50)
    site = np.take_along_axis(img, ch[..., None].astype(np.int64), axis=2)[..., 0]
    mo = soil(SiteLayout(ch), site, cov, 1.0, stray)
    np.testing.assert_array_equal(mo[cov == 0], site[cov == 0])
    np.testing.assert_array_equal(mo[cov == 1], stray.astype(np.float32)[ch[cov == 1]])
