"""Spatial resampling of a Bayer mosaic per CFA sub-lattice, without a demosaic round trip (models.md §2.0).

The four 2×2 phases ``(i, j)`` of a mosaic (rows i::2, columns j::2) each hold one colour. A geometric operation
given in mosaic pixel coordinates moves each site by sampling the sub-lattice of its own phase: mosaic position
``(x, y)`` is sub-lattice position ``((x − j)/2, (y − i)/2)``. So a colour is only ever interpolated from sites of
the same colour, and the output keeps the input's CFA pattern.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from .bilinear_table import TabledWarp

PHASES = ((0, 0), (0, 1), (1, 0), (1, 1))


def phases(height: int, width: int) -> Iterator[tuple[int, int]]:
    """The 2×2 phases (row, column offset) present in an image of this size."""
    return ((i, j) for i, j in PHASES if i < height and j < width)


def to_sublattice(x: np.ndarray, y: np.ndarray, phase: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Mosaic coordinates → coordinates on the sub-lattice of ``phase`` (float32)."""
    i, j = phase
    return ((np.asarray(x, np.float32) - np.float32(j)) * np.float32(0.5),
            (np.asarray(y, np.float32) - np.float32(i)) * np.float32(0.5))


def sublattice_warps(map_x: np.ndarray, map_y: np.ndarray) -> list[tuple[tuple[int, int], TabledWarp]]:
    """A pull map in mosaic coordinates as one pull map per 2×2 phase in that phase's sub-lattice coordinates
    (tabled: keep them cached when the map serves many frames)."""
    return [((i, j), TabledWarp(*to_sublattice(map_x[i::2, j::2], map_y[i::2, j::2], (i, j))))
            for i, j in phases(*map_x.shape)]


def remap_mosaic(plane: np.ndarray, warps: list, *, border: int, fill: float = 0.0) -> np.ndarray:
    """Resample an (H, W) mosaic per sub-lattice (bilinear) through :func:`sublattice_warps` of a pull map."""
    out = np.empty(plane.shape, np.float32)
    plane = np.asarray(plane, np.float32)
    for (i, j), warp in warps:
        out[i::2, j::2] = warp.apply(np.ascontiguousarray(plane[i::2, j::2]), border=border, fill=fill)
    return out
