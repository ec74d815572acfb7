"""Colour channels and per-site arithmetic shared by RGB frames and Bayer mosaics (models.md §2.0, §2.1).

Per-channel camera physics is written once against :class:`SiteLayout`, built from the frames' per-site API
(``channel_index()``): a :class:`~roadview_noise.types.CameraFrame` has three sites per pixel (H, W, 3), a
:class:`~roadview_noise.types.RawFrame` one site per pixel (H, W) whose colour follows the 2×2 CFA cell — the
ROADVIEW way of running the weather on the mosaic with each site's own wavelength, without a demosaic round trip.
Planes (depth, transmission, particle coverage) are (H, W) pixel maps in both layouts.
"""

from __future__ import annotations

import numpy as np

CHANNEL_WAVELENGTH_M = (600e-9, 530e-9, 460e-9)   # R, G, B centre wavelengths of the D3.4 fog model
WATER_INDEX = (1.3320 + 1.09e-8j, 1.3338 + 1.448e-9j, 1.3366 + 9.86e-10j)   # n + iκ at those wavelengths


class SiteLayout:
    """Which colour each site has, for both layouts (per-site compositing kernels: physics.photometry)."""

    def __init__(self, channel_index: np.ndarray):
        """``channel_index``: (1, 1, 3) for RGB, or the (H, W) map of a 2×2-periodic CFA."""
        ch = np.asarray(channel_index)
        self.mosaic = ch.ndim == 2
        self.channel_index = ch
        if self.mosaic:
            h, w = ch.shape
            self.cells = tuple(((i, j), int(ch[i, j])) for i in range(min(2, h)) for j in range(min(2, w)))

    @classmethod
    def of(cls, frame) -> "SiteLayout":
        return cls(frame.channel_index())

    def channel_samples(self, x: np.ndarray, *, step: int = 4, mask: np.ndarray | None = None,
                        rows: int | None = None) -> list[np.ndarray]:
        """Values of each channel's sites on a ``step``-pixel lattice (even, so a mosaic keeps its CFA phase),
        in the first ``rows`` rows, optionally only where the (H, W) ``mask`` is true."""
        if step < 2 or step % 2:
            raise ValueError("the sampling step must be even")
        out: list[list[np.ndarray]] = [[], [], []]
        if self.mosaic:
            for (i, j), c in self.cells:
                xs = x[i:rows:step, j::step]
                out[c].append(xs[mask[i:rows:step, j::step]] if mask is not None else xs.ravel())
        else:
            xs = x[:rows:step, ::step]
            ms = mask[:rows:step, ::step] if mask is not None else None
            for c in range(3):
                out[c].append(xs[..., c][ms] if ms is not None else xs[..., c].ravel())
        return [np.concatenate(parts) for parts in out]
