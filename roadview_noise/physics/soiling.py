"""Image formation through dirt on the lens (models.md §2.4 [PROP], after Gu, Ramamoorthi, Belhumeur & Nayar 2009).

The dirt layer lies far out of focus, so it acts per pixel as an attenuation plus scattered light:
``I'(p) = I(p)·(1 − ι M(p)) + ι M(p)·S_c`` with M the (defocused) coverage, ι the opacity and ``S_c = ρ_c Ī_c``
the light the mud scatters towards the sensor (mud albedo ρ times the mean image radiance Ī, per colour).
Written as ``I·(1 − a) + a·S`` so that uncovered sites (a = 0) are bit-identical and opaque mud (a = 1) gives S
exactly. Per site: RGB frames (H, W, 3) or Bayer mosaics (H, W) with each site's colour.
"""

from __future__ import annotations

import numpy as np

from .cfa import SiteLayout
from .compiled import jit


@jit
def _soil_rgb(signal, coverage, opacity, stray, out):                      # pragma: no cover - compiled
    s0, s1, s2 = stray[0], stray[1], stray[2]
    for y in range(signal.shape[0]):
        src, dst, cov = signal[y], out[y], coverage[y]
        for x in range(signal.shape[1]):
            a = opacity * cov[x]
            b = 1 - a
            dst[x, 0] = src[x, 0] * b + a * s0
            dst[x, 1] = src[x, 1] * b + a * s1
            dst[x, 2] = src[x, 2] * b + a * s2


@jit
def _soil_mosaic(signal, coverage, opacity, stray_rows, out):               # pragma: no cover - compiled
    """``stray_rows``: the stray light of each site of the first two rows; later rows repeat them."""
    for y in range(signal.shape[0]):
        s = stray_rows[y % stray_rows.shape[0]]
        for x in range(signal.shape[1]):
            a = opacity * coverage[y, x]
            out[y, x] = signal[y, x] * (1 - a) + a * s[x]


def soil(layout: SiteLayout, signal: np.ndarray, coverage: np.ndarray, opacity: float, stray) -> np.ndarray:
    """The soiled signal (float32, the signal's shape) for an (H, W) coverage in [0, 1], opacity ι and stray light
    S per colour (R, G, B) in the signal's units."""
    stray = np.ascontiguousarray(np.broadcast_to(np.asarray(stray, np.float32), (3,)))
    signal = np.asarray(signal, np.float32)
    coverage = np.asarray(coverage, np.float32)
    out = np.empty_like(signal, order="C")
    if layout.mosaic:
        _soil_mosaic(signal, coverage, np.float32(opacity), np.take(stray, layout.channel_index[:2]), out)
    else:
        _soil_rgb(signal, coverage, np.float32(opacity), stray, out)
    return out
