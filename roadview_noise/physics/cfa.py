"""Colour channels and per-site arithmetic shared by RGB frames and Bayer mosaics (models.md §2.0, §2.1).

Per-channel camera physics is written once against :class:`SiteLayout`, built from the frames' per-site API
(``channel_index()``): a :class:`~roadview_noise.types.CameraFrame` has three sites per pixel (H, W, 3), a
:class:`~roadview_noise.types.RawFrame` one site per pixel (H, W) whose colour follows the 2×2 CFA cell — the
ROADVIEW way of running the weather on the mosaic with each site's own wavelength, without a demosaic round trip.
Planes (depth, transmission, particle coverage) are (H, W) pixel maps in both layouts.
"""

from __future__ import annotations

import cv2
import numpy as np

CHANNEL_WAVELENGTH_M = (600e-9, 530e-9, 460e-9)   # R, G, B centre wavelengths of the D3.4 fog model
WATER_INDEX = (1.3320 + 1.09e-8j, 1.3338 + 1.448e-9j, 1.3366 + 9.86e-10j)   # n + iκ at those wavelengths


def _values3(values) -> np.ndarray:
    v = np.broadcast_to(np.asarray(values, dtype=np.float32), (3,))
    return np.ascontiguousarray(v)


class SiteLayout:
    """Per-site arithmetic with per-channel constants, fast for both layouts.

    For RGB frames the operations run on OpenCV's interleaved 3-channel arithmetic (NumPy broadcasting of a
    length-3 trailing axis is an order of magnitude slower); for mosaics each site takes its channel's value."""

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

    def attenuation(self, distance_m: np.ndarray, sigma_per_m) -> np.ndarray:
        """Per-site Beer–Lambert transmission ``exp(−σ_c d)`` of an (H, W) distance map (inf → 0), float32.

        Distances are capped where the optical depth reaches 80 (t < 2·10⁻³⁵, which leaves no trace in float32
        arithmetic) because exp() of −inf and of sub-normal results takes a slow path."""
        s = _values3(sigma_per_m)
        if np.any(s < 0):
            raise ValueError("extinction coefficients must be ≥ 0")
        if s.max() <= 0:
            return self.expand(np.ones_like(distance_m, dtype=np.float32))
        d = np.minimum(distance_m, np.float32(80.0 / s[s > 0].min()), dtype=np.float32)
        if self.mosaic:
            d *= -np.take(s, self.channel_index)
            return np.exp(d, out=d)
        t = cv2.cvtColor(d, cv2.COLOR_GRAY2RGB)
        cv2.multiply(t, (-float(s[0]), -float(s[1]), -float(s[2]), 0.0), dst=t)
        return cv2.exp(t, dst=t)

    def expand(self, plane: np.ndarray) -> np.ndarray:
        """The (H, W) plane on every site (float32)."""
        plane = np.ascontiguousarray(plane, dtype=np.float32)
        return plane if self.mosaic else cv2.cvtColor(plane, cv2.COLOR_GRAY2RGB)

    def blend(self, signal: np.ndarray, t: np.ndarray, values) -> np.ndarray:
        """``values + t · (signal − values)`` with ``t`` per site and ``values`` per channel (Koschmieder form)."""
        v = _values3(values)
        signal = np.ascontiguousarray(signal, dtype=np.float32)
        if self.mosaic:
            vm = np.take(v, self.channel_index)
            out = signal - vm
            out *= t
            out += vm
            return out
        scalar = (float(v[0]), float(v[1]), float(v[2]), 0.0)
        out = cv2.subtract(signal, scalar)
        cv2.multiply(out, np.ascontiguousarray(t, dtype=np.float32), dst=out)
        cv2.add(out, scalar, dst=out)
        return out

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
