"""Geometric camera models as pixel maps: the one description that moves the image, its masks and its boxes alike.

A geometric model (windscreen distortion, …) returns a :class:`Warp` from ``Model.warp``; its ``apply`` resamples
the image through exactly that map, and the annotation mechanism resamples masks (nearest neighbour) and moves
box corners (:meth:`Warp.forward`) through the same map, so annotations stay aligned pixel for pixel.

Conventions (OpenCV ``remap``): pixel centres at integer coordinates; ``map_x[v, u], map_y[v, u]`` is the input
position that output pixel ``(u, v)`` samples (a *pull* map).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# label dtypes cv2.remap resamples as they are
_REMAP_DTYPES = tuple(map(np.dtype, (np.uint8, np.int8, np.uint16, np.int16, np.int32, np.float32, np.float64)))


@dataclass(frozen=True, eq=False)
class Warp:
    """Pull map ``(map_x, map_y)``, float32 (H_out, W_out), in input pixel coordinates."""

    map_x: np.ndarray
    map_y: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.map_x.shape

    def is_identity(self) -> bool:
        """Whether the map is exactly the identity (every output pixel samples its own position): nothing moves."""
        h, w = self.shape
        return bool(np.array_equal(self.map_x, np.broadcast_to(np.arange(w, dtype=self.map_x.dtype), (h, w))) and
                    np.array_equal(self.map_y, np.broadcast_to(np.arange(h, dtype=self.map_y.dtype)[:, None], (h, w))))

    def apply(self, image: np.ndarray, *, interpolation: int = cv2.INTER_LINEAR,
              border: int = cv2.BORDER_REFLECT_101, fill: float = 0.0) -> np.ndarray:
        """Resample ``image`` (H, W[, C]) through the map; OpenCV handles up to 4 channels per call."""
        if image.ndim == 3 and image.shape[2] > 4:
            return np.stack([self.apply(image[..., c], interpolation=interpolation, border=border, fill=fill)
                             for c in range(image.shape[2])], axis=-1)
        return cv2.remap(image, self.map_x, self.map_y, interpolation, borderMode=border, borderValue=fill)

    def apply_labels(self, labels: np.ndarray, ignore_index: int = 255) -> np.ndarray:
        """Nearest-neighbour resampling of a label image; output pixels whose source lies outside the input get
        ``ignore_index`` in every channel (an RGBA bitmask's too: OpenCV's scalar fills the first channel only). A
        dtype OpenCV does not resample as it is (uint32, int64 — which it returns as int32 —, bool) or more than 4
        channels: the nearest source pixel by index."""
        if labels.dtype in _REMAP_DTYPES and (labels.ndim == 2 or labels.shape[2] <= 4):
            return cv2.remap(labels, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=(ignore_index,) * 4)
        h, w = labels.shape[:2]
        xs, ys = np.rint(self.map_x).astype(np.intp), np.rint(self.map_y).astype(np.intp)
        out = labels[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]
        out[(xs < 0) | (xs >= w) | (ys < 0) | (ys >= h)] = np.asarray(ignore_index).astype(labels.dtype)
        return out

    def forward(self, points_xy: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Output positions of input points (N, 2) x, y: solves ``map(q) = p`` by fixed-point iteration
        ``q ← q + (p − map(q))`` with bilinear map sampling (converges for the mild, smooth maps of lens and
        windscreen distortion; models with a closed-form forward map may override)."""
        p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        q = p.copy()
        for _ in range(iterations):
            mx = _bilinear(self.map_x, q)
            my = _bilinear(self.map_y, q)
            q[:, 0] += p[:, 0] - mx
            q[:, 1] += p[:, 1] - my
        return q


def moving(warps) -> list:
    """The warps that move anything: all but exact identities."""
    return [wp for wp in warps if not wp.is_identity()]


def _bilinear(grid: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``grid`` sampled at (x, y) positions ``q`` with bilinear interpolation, clamped at the borders (and linearly
    extrapolated beyond them from the border gradient, so the inversion can follow points mapped off-image)."""
    h, w = grid.shape
    x = np.clip(q[:, 0], 0, w - 1)
    y = np.clip(q[:, 1], 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.intp), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.intp), max(h - 2, 0))
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = x - x0
    fy = y - y0
    g = grid.astype(np.float64, copy=False)
    top = g[y0, x0] * (1 - fx) + g[y0, x1] * fx
    bot = g[y1, x0] * (1 - fx) + g[y1, x1] * fx
    val = top * (1 - fy) + bot * fy
    # beyond the grid: continue with the border slope
    gx = np.where(x1 > x0, (g[y0, x1] - g[y0, x0]), 0.0)
    gy = np.where(y1 > y0, (g[y1, x0] - g[y0, x0]), 0.0)
    return val + gx * (q[:, 0] - x) + gy * (q[:, 1] - y)
