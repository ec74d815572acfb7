"""Hints, never silent guesses, about a depth map that does not look like metres along the ray of a forward camera.

A depth file in the wrong unit or sense is read without error and makes fog far too strong or too weak: millimetres
(NYU's and most RGB-D PNGs, read as metres: every pixel km away), a normalised or relative depth (all within about
1 m), or the inverse depth / disparity a monocular network outputs (large where the scene is near). Checked on every
8th row and column (≈ 0.5 ms at 1920×1080): the median valid range above ``MAX_MEDIAN_M`` or its 99th percentile at
most ``MIN_P99_M`` (a normalised depth read as planar reaches 1.3 m at the corners), or the bottom rows (the road a
few metres ahead) ``INVERSE_RATIO`` times farther than the rows about the horizon. The manifest's
``inputs.depth.doubt`` records the reason and a run-level warning counts the files; the depth is used as it is.
"""

from __future__ import annotations

import numpy as np

STRIDE = 8
MIN_SAMPLES = 100
MAX_MEDIAN_M = 1000.0         # no road scene has its median pixel a kilometre away: millimetres or centimetres
MIN_P99_M = 2.0               # nor 99 % of its pixels within 2 m: normalised, relative or inverse depth
INVERSE_RATIO = 2.0           # bottom rows (ground ahead) twice as far as the middle rows: inverse depth, disparity
BOTTOM_ROWS, MIDDLE_ROWS = (0.8, 1.0), (0.35, 0.55)        # fractions of the image height


def depth_doubt(range_m: np.ndarray) -> dict | None:
    """Why ``range_m`` (H, W; NaN holes, inf sky) does not look like metres along the ray, or None."""
    sample = range_m[::STRIDE, ::STRIDE]
    finite = sample[np.isfinite(sample)]
    if finite.size < MIN_SAMPLES:
        return None
    median, p99 = (float(v) for v in np.percentile(finite, [50, 99]))
    if median > MAX_MEDIAN_M:
        return {"reason": "unit", "median_m": round(median, 3),
                "text": f"median {median:.4g} m: millimetres or centimetres read as metres?"}
    if p99 <= MIN_P99_M:
        return {"reason": "unit", "median_m": round(median, 3),
                "text": f"99 % of the pixels within {p99:.3g} m: a normalised or relative depth, or inverse depth?"}
    bottom, middle = (_band_median(sample, band) for band in (BOTTOM_ROWS, MIDDLE_ROWS))
    if bottom is not None and middle and bottom > INVERSE_RATIO * middle:
        return {"reason": "inverse", "median_m": round(median, 3),
                "text": f"the bottom rows are {bottom / middle:.3g}× as far as the middle rows: inverse depth or "
                        "disparity?"}
    return None


def _band_median(sample: np.ndarray, band: tuple[float, float]) -> float | None:
    rows = sample[int(band[0] * sample.shape[0]):int(np.ceil(band[1] * sample.shape[0]))]
    finite = rows[np.isfinite(rows)]
    return float(np.median(finite)) if finite.size >= MIN_SAMPLES // 4 else None
