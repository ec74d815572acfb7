"""Scene radiances estimated from the frame itself, in the frame's own linear scale (models.md §2.1–§2.3 [PROP]).

The reference code used absolute constants (airlight 600/1500, sun 6000, flakes 255 on an 8-bit scale) that
saturate fog and streaks (models.md §7.3). Estimating from the image makes every weather radiance follow the
image, including an image darkened by an earlier low-light step (D3.5 Eq. 1 coupling).
Statistics use the sites of a 4-pixel lattice (1/16 of the frame; the lattice keeps a mosaic's CFA phase): the
mean of ~10⁵ sites per channel is exact to far below one code value, at 1/16 of the cost.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ModelError
from .cfa import SiteLayout

SAMPLE_STEP_PX = 4
BRIGHTEST_FRACTION = 0.001            # "sky" when the depth map has none: the brightest 0.1 % of sites
MIN_SKY_SAMPLES = 16                  # fewer sampled sky sites per channel than this: use the brightest sites
ENVIRONMENT_ROWS_FRACTION = 0.6       # upper 3/5 of the image ≈ the wide upward cone a raindrop refracts


def sky_radiance(layout: SiteLayout, signal: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """Per-channel (R, G, B) sky radiance: mean over sky sites (depth ``inf``), else mean of the brightest 0.1 %
    of each channel's sites."""
    sky = layout.channel_samples(signal, step=SAMPLE_STEP_PX, mask=np.isinf(depth_m))
    if all(s.size >= MIN_SKY_SAMPLES for s in sky):
        return np.array([s.mean(dtype=np.float64) for s in sky])
    out = []
    for s in layout.channel_samples(signal, step=SAMPLE_STEP_PX):
        k = max(1, math.ceil(BRIGHTEST_FRACTION * s.size))
        out.append(np.partition(s, s.size - k)[s.size - k:].mean(dtype=np.float64))
    return np.array(out)


def environment_radiance(layout: SiteLayout, signal: np.ndarray) -> np.ndarray:
    """Per-channel mean radiance of the upper 3/5 of the image (models.md §2.2 [PROP] ``E_env``)."""
    rows = max(1, round(ENVIRONMENT_ROWS_FRACTION * signal.shape[0]))
    return np.array([s.mean(dtype=np.float64) for s in
                     layout.channel_samples(signal, step=SAMPLE_STEP_PX, rows=rows)])


def absolute_radiance(value, luminance_factor: float) -> np.ndarray:
    """A user radiance in linear full-scale units (scalar or R, G, B) for the undarkened scene, scaled by the
    luminance factor an earlier low-light step set (``Conditions.luminance_factor``)."""
    v = np.broadcast_to(np.asarray(value, dtype=float), (3,))
    return v * float(luminance_factor)


def frame_depth_m(frame, model_id: str) -> np.ndarray:
    """The frame's range map as contiguous float32 (H, W); a clear :class:`ModelError` if absent or invalid."""
    depth = frame.depth_m
    if depth is None:
        raise ModelError("needs a depth map (range along each pixel ray, metres; inf = sky); give the inputs a "
                         "depth source", model=model_id, field="depth_m")
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.shape != tuple(frame.shape):
        raise ModelError(f"depth map is {depth.shape}, image is {tuple(frame.shape)}", model=model_id,
                         field="depth_m")
    if not (depth >= 0).all():
        raise ModelError("depth map has negative or NaN values (use inf for sky)", model=model_id, field="depth_m")
    return depth


RAIN_REFRACTED_FRACTION = 0.94        # share of a drop's radiance refracted from the environment (models.md §2.2)


def raindrop_radiance(layout: SiteLayout, signal: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """``S_c = 0.94 E_env,c + 0.06 E_sky,c`` (models.md §2.2 [PROP], after Garg & Nayar 2007): a drop refracts a
    wide cone of the scene in front of the camera and reflects the sky."""
    return (RAIN_REFRACTED_FRACTION * environment_radiance(layout, signal) +
            (1.0 - RAIN_REFRACTED_FRACTION) * sky_radiance(layout, signal, depth_m))
