"""Depth files in the wrong unit or sense (millimetres, normalised, inverse depth) are read without error and made
fog far too strong or too weak in silence: they are now named in a run-level warning (``depth.doubts``)."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.camera_inputs import InputWarnings
from roadview_noise.depth.doubts import depth_doubt


def _road(h=375, w=1242, f=707.0, height_m=1.65, holes=0.0):
    """Range along the ray of a forward camera over a flat road (sky above the horizon), a wall at 30 m on the
    left; ``holes``: that fraction of the pixels NaN (sparse LiDAR depth)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2) / f, (v - h / 2) / f
    with np.errstate(divide="ignore"):
        z = np.where(y > 0, height_m / y, np.inf)
    z = np.where((u < w / 4) & (y > -0.05), np.minimum(z, 30.0), z)
    r = (z * np.sqrt(1 + x * x + y * y)).astype(np.float32)
    r[np.random.default_rng(0).random(r.shape) < holes] = np.nan
    return r


@pytest.mark.parametrize("holes", [0.0, 0.95])
def test_metres_pass(holes):
    assert depth_doubt(_road(holes=holes)) is None
    assert depth_doubt(np.full((480, 640), 3.0, np.float32)) is None             # indoor: a wall at 3 m


@pytest.mark.parametrize("convert,reason,words", [
    (lambda r: r * 1000, "unit", "millimetres"),                                  # NYU / RGB-D millimetres
    (lambda r: r / np.nanmax(np.where(np.isfinite(r), r, np.nan)), "unit", "normalised"),
    (lambda r: 1 / r, "unit", "inverse depth"),                                    # inverse depth in 1/m
    (lambda r: 1000 / r, "inverse", "inverse depth or disparity"),               # a monocular net's relative disparity
])
def test_wrong_units_and_senses_are_named(convert, reason, words):
    with np.errstate(divide="ignore"):
        depth = convert(_road(holes=0.5))
    doubt = depth_doubt(np.where(depth > 0, depth, np.nan))                       # the readers' holes: ≤ 0 → NaN
    assert doubt is not None and doubt["reason"] == reason and words in doubt["text"]


def test_one_warning_line_per_run_names_a_file():
    w = InputWarnings()
    for i in range(3):
        w.add({"input": f"cam/{i:06d}.png", "inputs": {"warnings": ["depth_doubtful"], "depth": {
            "doubt": {"reason": "unit", "median_m": 19320.0, "text": "median 1.932e+04 m: millimetres?"}}}})
    (line,) = w.lines()
    assert line.startswith("depth of 3 file(s) does not look like metres") and "cam/000000.png: median" in line
