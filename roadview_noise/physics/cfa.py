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

    def lattice(self, x: np.ndarray, step: int = 4) -> list[tuple[int | None, np.ndarray]]:
        """Views of ``x``'s sites on a ``step``-pixel lattice (even, so a mosaic keeps its CFA phase), one per colour
        phase: ``(channel, x[i::step, j::step])`` for each 2×2 CFA cell (i, j) of a mosaic, ``(None,
        x[::step, ::step])`` for RGB (channels on the last axis). An (H, W) plane (depth, mask) gives the views of
        the same pixels, in the same order."""
        if step < 2 or step % 2:
            raise ValueError("the sampling step must be even")
        if self.mosaic:
            return [(c, x[i::step, j::step]) for (i, j), c in self.cells]
        return [(None, x[::step, ::step])]

    @staticmethod
    def lattice_channels(views: list[tuple[int | None, np.ndarray]], masks: list[np.ndarray] | None = None
                         ) -> list[np.ndarray]:
        """Values of each channel (R, G, B) in :meth:`lattice` views, where the matching views of an (H, W) mask
        are true (all values without ``masks``)."""
        out: list[list[np.ndarray]] = [[], [], []]
        for k, (c, xs) in enumerate(views):
            for ch in range(3) if c is None else (c,):
                v = xs if c is not None else xs[..., ch]
                out[ch].append(v[masks[k]] if masks is not None else v.ravel())
        return [parts[0] if len(parts) == 1 else np.concatenate(parts) for parts in out]

    def channel_samples(self, x: np.ndarray, *, step: int = 4, mask: np.ndarray | None = None,
                        rows: int | None = None) -> list[np.ndarray]:
        """Values of each channel's sites on a ``step``-pixel lattice (:meth:`lattice`), in the first ``rows`` rows,
        optionally only where the (H, W) ``mask`` is true."""
        masks = None if mask is None else [m for _, m in self.lattice(mask[:rows], step)]
        return self.lattice_channels(self.lattice(x[:rows], step), masks)
