"""Obstruction of a LiDAR's window: dirt, mud and water patches on the azimuth–elevation grid of the window
(models.md §3.8; D3.5 CNF25–27, Eq. 3: after the weather, so weather returns are blocked too).

The window grid is the profile's: rows = beams by elevation (:func:`lidar_geometry.ring_rows`), columns = the
profile's azimuth steps (``columns``; a point list recorded with another column count maps onto it by azimuth), so
the same dirt lies at the same place in every frame whatever the recording mode. Patches (D3.5's proof of concept,
models.md §3.8 [PROP]): every cell seeds one with probability p; a ``square`` patch of side ``s ~ U{s_min … s_max}``
rows × ``round(s·column_scale)`` columns is centred on its seed (rows clipped at the top and bottom beam, columns
wrapped over the 360° seam); a ``blob`` is the camera soiling mask's splatter (:mod:`blob_mask`, diameter s, soft
edge) on the same grid. Coverage m ∈ [0, 1] combines as ``1 − Π(1 − m_i)``; a patch of opacity o passes
``t = 1 − o·m`` one way, ``t²`` two ways (emitter and receiver both look through it).
Windows (the profile's ``window``):
- ``static`` (Ouster): the window stands still, so a patch blocks a fixed azimuth–elevation region;
- ``rotating`` (Velodyne head): the window turns with the beams; each beam leaves through one spot of it, so a patch
  over that spot blocks the beam at every azimuth — whole rings. The window is drawn as a strip of the same cells
  (wide enough for the largest patch) and each beam passes it at its centre column.
With hard squares (o = 1) a cell is blocked with the Boolean-model probability ``1 − exp(−p·E[s·s_c])`` for both
windows (0.68 % for p = 6·10⁻⁵ and s uniform on 4…16).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..types import LidarProfile
from .blob_mask import blob_mask
from .compiled import jit
from .lidar_geometry import atan2, ring_rows

SHAPES = ("square", "blob")
WINDOWS = ("static", "rotating")


@dataclass(frozen=True)
class PatchSpec:
    """What a window pattern is drawn from (hashable: patterns are cached per process)."""

    window: str
    shape: str
    seed_probability: float
    size_cells: tuple[int, int]
    column_scale: float
    opacity: float
    softness: float


@dataclass(frozen=True, eq=False)
class WindowPattern:
    """``transmission``: two-way transmission (rows, columns) of the window grid (rotating: (rows, 1), every azimuth);
    ``patches``: square patches as [row, column, rows, columns] (empty for blobs); ``seeds``: patches drawn;
    ``blocked_fraction``: share of the window's cells (rotating: beams) that pass nothing; ``obstructed_fraction``:
    share that lose anything; ``partial``: some cells pass part of the light."""

    transmission: np.ndarray
    patches: list
    seeds: int
    blocked_fraction: float
    obstructed_fraction: float
    partial: bool


def column_scale(profile: LidarProfile, aspect: str) -> float:
    """Columns per row of a round patch: 1 for ``cells`` (D3.5: squares on the range image), the mean beam spacing
    over the column step for ``angular`` (OS1-128 at 2048 columns: 1.92)."""
    if aspect == "cells":
        return 1.0
    e = np.asarray(profile.beam_elevation_deg, dtype=np.float64)
    spacing = (e.max() - e.min()) / max(1, len(e) - 1)
    return float(spacing / (360.0 / profile.columns)) if spacing > 0 else 1.0


@lru_cache(maxsize=16)
def window_pattern(spec: PatchSpec, rows: int, columns: int, pattern_seed: int) -> WindowPattern:
    """The pattern of ``spec`` on a ``rows × columns`` window grid from ``pattern_seed`` (module doc); cached, its
    array read-only."""
    rng = np.random.default_rng(pattern_seed)
    lo, hi = spec.size_cells
    width = columns if spec.window == "static" else 2 * int(math.ceil(hi * spec.column_scale)) + 1
    wrap = spec.window == "static"
    patches: list = []
    if spec.shape == "blob":
        blobs = blob_mask((rows, width), rng, size_px=(lo, hi), seed_probability=spec.seed_probability,
                          softness=spec.softness, column_scale=spec.column_scale, wrap_columns=wrap)
        coverage, seeds = blobs.mask.astype(np.float64), blobs.count
    else:
        coverage, patches = _squares(rng, rows, width, spec.seed_probability, lo, hi, spec.column_scale, wrap)
        seeds = len(patches)
    if spec.window == "rotating":
        coverage = coverage[:, width // 2:width // 2 + 1]
    transmission = (1.0 - spec.opacity * coverage) ** 2
    transmission.setflags(write=False)
    blocked, obstructed = float(np.mean(transmission == 0)), float(np.mean(transmission < 1))
    return WindowPattern(transmission, patches, seeds, blocked, obstructed,
                         bool(np.any((transmission > 0) & (transmission < 1))))


def _squares(rng: np.random.Generator, rows: int, columns: int, p: float, lo: int, hi: int, scale: float,
             wrap: bool) -> tuple[np.ndarray, list]:
    """Binary coverage of square patches seeded with probability p per cell (module doc) and their list."""
    n = int(rng.binomial(rows * columns, p))
    seeds = rng.choice(rows * columns, size=n, replace=False) if n else np.zeros(0, dtype=np.int64)
    sides = rng.integers(lo, hi + 1, n)
    coverage = np.zeros((rows, columns))
    patches = []
    for seed, side in zip(seeds, sides):
        r, c = divmod(int(seed), columns)
        width = max(1, int(round(side * scale)))
        r0, c0 = r - (int(side) - 1) // 2, c - (width - 1) // 2
        cols = np.arange(c0, c0 + width)
        cols = np.mod(cols, columns) if wrap else cols[(cols >= 0) & (cols < columns)]
        coverage[max(r0, 0):max(min(r0 + int(side), rows), 0), cols] = 1.0
        patches.append([r, c, int(side), width])
    return coverage, patches


def window_transmission(positions_m: np.ndarray, ring: np.ndarray, profile: LidarProfile,
                        transmission: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points the window dims and their two-way transmission, as (indices ascending, t): every point whose cell
    of the ``channels × columns`` table is not 1 (the others, and points without a return, pass everything). The
    cell: row of the point's ring by elevation, column of its azimuth ``φ = atan2(y, x)`` turning clockwise,
    ``floor(((−φ) mod 2π) / step)`` (one column: a rotating window, every azimuth). Sparse: a window dims few points,
    so no full-length array is written."""
    table = np.ascontiguousarray(transmission, dtype=np.float64)
    return _window_transmission(np.ascontiguousarray(positions_m, dtype=np.float64), np.asarray(ring),
                                ring_rows(profile), table.reshape(-1), table.shape[1], np.any(table != 1, axis=1))


@jit
def _window_transmission(pos, ring, rows, table, columns, row_obstructed):       # pragma: no cover - compiled
    """Per point: nothing on a row without obstruction (no azimuth needed) or without a return, else its cell's value
    when not 1. In blocks of points that stay in the L1 cache: their coordinates copied contiguous, the azimuths in
    one vectorised loop (most rows hold a patch), then the lookups."""
    n = len(ring)
    block = 1024
    x = np.empty(block)
    y = np.empty(block)
    azimuth = np.empty(block)
    at = np.empty(n, np.int64)                          # (pages never written are never touched)
    t = np.empty(n)
    k = 0
    per_rad = columns / (2.0 * math.pi)
    for b0 in range(0, n, block):
        m = min(n, b0 + block) - b0
        for i in range(m):
            x[i] = pos[b0 + i, 0]
            y[i] = pos[b0 + i, 1]
        for i in range(m):
            azimuth[i] = atan2(y[i], x[i])
        for i in range(m):
            p = b0 + i
            row = rows[ring[p]]
            if not row_obstructed[row]:
                continue
            z = pos[p, 2]
            if not (math.isfinite(x[i] + y[i] + z) and (x[i] != 0.0 or y[i] != 0.0 or z != 0.0)):
                continue
            turn = -azimuth[i]
            if turn < 0.0:
                turn += 2.0 * math.pi
            value = table[row * columns + min(int(turn * per_rad), columns - 1)]
            if value != 1.0:
                at[k] = p
                t[k] = value
                k += 1
    return at[:k].copy(), t[:k].copy()
