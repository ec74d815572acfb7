"""Window obstruction patterns: the Boolean-model blocked fraction, shapes, the 360° seam, rotating windows."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.physics.window_obstruction import PatchSpec, column_scale, window_pattern, window_transmission
from roadview_noise.profiles.lidar import os1_128


def _spec(window="static", shape="square", p=6e-5, size=(4, 16), scale=1.0, opacity=1.0):
    return PatchSpec(window, shape, p, size, scale, opacity, 0.05)


@pytest.mark.parametrize("window", ["static", "rotating"])
def test_blocked_fraction_follows_the_boolean_model(window):
    """models.md §3.8: blocked fraction ≈ 1 − exp(−p·E[s²]) = 0.68 % for s uniform on 4…16 (E[s²] = 114), within 10 %
    over many draws (mean of 400 sensor instances; its standard error is ≈ 2 % for static windows)."""
    p, sizes = 6e-5, np.arange(4, 17)
    expected = 1 - np.exp(-p * np.mean(sizes ** 2.0))
    assert expected == pytest.approx(0.0068, abs=5e-5)
    n = 400 if window == "static" else 6000       # a rotating window has ~1 blocked ring per instance: more draws
    got = np.mean([window_pattern(_spec(window), 128, 2048, seed).blocked_fraction for seed in range(n)])
    assert got == pytest.approx(expected, rel=0.10)
    seeds = np.mean([window_pattern(_spec(), 128, 2048, seed).seeds for seed in range(200)])
    assert seeds == pytest.approx(6e-5 * 128 * 2048, rel=0.1)      # 15.7 expected seeds per frame


def test_zero_probability_blocks_nothing_and_patterns_are_reproducible():
    assert window_pattern(_spec(p=0.0), 128, 2048, 1).obstructed_fraction == 0
    a, b = window_pattern(_spec(p=1e-3), 128, 512, 7), window_pattern(_spec(p=1e-3), 128, 512, 7)
    assert a is b and not a.transmission.flags.writeable              # cached, read-only
    c = window_pattern(_spec(p=1e-3), 128, 512, 8)
    assert not np.array_equal(a.transmission, c.transmission)


def test_square_patches_wrap_over_the_seam_and_follow_the_aspect():
    for seed in range(200):
        pat = window_pattern(_spec(p=2e-4, size=(6, 6), scale=2.0), 64, 256, seed)
        blocked = pat.transmission == 0
        for r, c, rows, cols in pat.patches:
            assert (rows, cols) == (6, 12)
            assert blocked[r, (c + 6) % 256] and blocked[r, (c - 5) % 256]   # 12 columns around the seed, wrapped
        if any(c < 5 or c > 250 for _, c, _, _ in pat.patches):
            assert blocked[:, 0].any() and blocked[:, -1].any()
            return
    pytest.fail("no patch near the seam in 200 draws")


def test_rotating_window_blocks_whole_rings_and_opacity_attenuates():
    pat = window_pattern(_spec("rotating", p=5e-3), 128, 2048, 3)
    assert pat.transmission.shape == (128, 1) and pat.blocked_fraction > 0
    soft = window_pattern(_spec(p=1e-3, opacity=0.5), 128, 512, 3)
    assert set(np.unique(soft.transmission)) == {0.25, 1.0}          # (1 − 0.5)² two ways


def test_blobs_have_soft_edges():
    pat = window_pattern(_spec(shape="blob", p=2e-4, scale=2.0), 128, 2048, 5)
    t = pat.transmission
    assert pat.seeds > 0 and pat.patches == []
    assert np.any((t > 0) & (t < 1)) and np.any(t < 0.01)


def test_window_cells_of_points_and_aspect():
    prof = os1_128()
    assert column_scale(prof, "cells") == 1.0
    assert column_scale(prof, "angular") == pytest.approx((42.77 / 127) / (360 / 2048), rel=1e-4)   # 1.92
    ring = np.array([0, 127, 64])
    az = np.deg2rad(np.array([-0.01, 90.0, 179.99]))                # clockwise columns from azimuth 0
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))[ring]
    pos = 10 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    cell_number = -1.0 - np.arange(128 * 2048).reshape(128, 2048)               # a table that names its cells
    at, t = window_transmission(np.vstack([pos, np.zeros((1, 3))]), np.append(ring, 5), prof, cell_number)
    assert at.tolist() == [0, 1, 2] and (-1 - t).tolist() == [0, 127 * 2048 + 1536, 64 * 2048 + 1024]  # no return
    at, t = window_transmission(pos, ring, prof, cell_number[:, :1])
    assert at.tolist() == [0, 1, 2] and (-1 - t).tolist() == [0, 127 * 2048, 64 * 2048]
    clear = np.ones((128, 2048))
    clear[3, 5] = 0.0
    at, t = window_transmission(pos, ring, prof, clear)
    assert len(at) == 0 and len(t) == 0
    clear[127, 1536] = 0.25                                         # only the dimmed points, ascending
    assert [a.tolist() for a in window_transmission(pos[::-1], ring[::-1], prof, clear)] == [[1], [0.25]]
