"""The range-image cell of every point of a LiDAR scan: rows are beams by elevation, columns azimuth steps of the
scan's own firing grid, destaggered (models.md §3.0) — so that the 8 neighbours of a cell are the rays around it.

- A full grid (``PointCloud.grid_shape``): a point's ring is its ``ring`` field, else its grid row; its firing column
  is its grid column.
- A point list: ring (:func:`lidar_geometry.ring_index`) and the firing column on the grid measured from the list
  (:mod:`firing_grid`: column step and per-beam shift), ``rint(−firing/step − shift) mod W`` as the firing grid
  counts its empty cells. A list without a regular firing grid has no cells (the reason is returned instead).
- Rows: rings sorted by elevation (:func:`lidar_geometry.ring_rows`); columns: the firing column plus a per-beam
  integer shift measured from the returns, the most common ``rint(∓azimuth/step) − column`` of the beam — so the
  image is destaggered whatever the beam azimuth offsets (Ouster: ±4° = ±12 columns at 1024) or the column origin,
  and a grid already stored destaggered (shift 0) or turning counter-clockwise is read as it is.
Collisions (two returns of a list in one cell: dual returns) keep the nearest in the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..types import LidarProfile, PointCloud
from .compiled import jit
from .firing_grid import _wrap, describe_grid, empty_rays, firing_columns
from .lidar_geometry import has_return, ring_index, ring_rows

SHIFT_SAMPLE = 16384           # returns looked at (evenly strided) to measure each beam's destagger shift


@dataclass(frozen=True, eq=False)
class ScanCells:
    """``cell``: (N,) flat index ``row·columns + column`` of every point in the destaggered range image, −1 for points
    without one (no return); ``shown``: (N,) the point is the one its cell shows (nearest of a collision);
    ``empty``: flat indices of the rays fired without a return (a grid's no-return cells, a list's empty cells of
    its firing grid); ``source``: how the grid was found (for the manifest)."""

    rows: int
    columns: int
    cell: np.ndarray
    shown: np.ndarray
    empty: np.ndarray
    source: str

    @property
    def shape(self) -> tuple[int, int]:
        return self.rows, self.columns

    def padded_index_image(self) -> np.ndarray:
        """((rows + 2)·(columns + 2),) int64: the point each cell shows, −1 where none, with a border — a row of −1
        above and below, the first and last columns copied across the 360° seam — so that every neighbour of a cell
        sits at a fixed offset: cell ``q`` of row r at ``q + 2r + columns + 3``."""
        return _padded_index_image(self.cell, self.shown, self.rows, self.columns)

    def image(self, values: np.ndarray, fill=0.0) -> np.ndarray:
        """(rows, columns) image of per-point ``values`` (or (N, k) → (rows, columns, k)) at the shown points,
        ``fill`` elsewhere."""
        values = np.asarray(values)
        out = np.full((self.rows * self.columns,) + values.shape[1:], fill, dtype=values.dtype)
        out[self.cell[self.shown]] = values[self.shown]
        return out.reshape((self.rows, self.columns) + values.shape[1:])


def scan_cells(cloud: PointCloud, profile: LidarProfile, range_m: np.ndarray | None = None,
               empty: bool = True) -> ScanCells | str:
    """The cells of a grid or a point list (module doc), or why a point list has none. ``range_m``: the points'
    ranges if known (0: no return); ``empty=False``: leave the empty cells out (``empty`` holds none; a list's
    firing grid is then not searched for them)."""
    positions = np.ascontiguousarray(cloud.positions_m, dtype=np.float64)
    valid = has_return(positions) if range_m is None else np.asarray(range_m) > 0
    if cloud.grid_shape is not None:
        n_rows, columns = cloud.grid_shape
        if "ring" in cloud.fields:
            ring = ring_index(cloud, profile)
        elif n_rows == profile.channels:
            ring = np.repeat(np.arange(n_rows), columns)
        else:
            return (f"a {n_rows}-row grid without a ring field does not fit the {profile.channels} beams of profile "
                    f"{profile.name!r}")
        firing = None                                   # a grid point's column is its index mod the columns
        source = f"{n_rows}x{columns} grid"
        empty_at = np.flatnonzero(~valid) if empty else np.zeros(0, np.int64)
        empty_ring, empty_column = ring[empty_at], empty_at % columns
    else:
        measured = firing_columns(cloud, profile, range_m)
        if isinstance(measured, str):
            return f"no firing grid: {measured}"
        ring, columns, firing = measured.ring, measured.columns, measured.firing_rad
        source = describe_grid(profile, columns, measured.gaps_columns)
        if empty:
            grid = empty_rays(measured, profile)
            empty_ring, empty_column = grid.ring, grid.column
        else:
            empty_ring = empty_column = np.zeros(0, np.int64)
    ring = np.asarray(ring, dtype=np.int64)
    if firing is None:
        column_at = None
    else:
        def column_at(at):
            return _firing_columns(firing[at], ring[at], valid[at], measured.shift, columns)
    shift = _destagger_shift(positions, valid, ring, column_at, columns, profile.channels)
    rows = ring_rows(profile)
    if firing is None:
        cell = _flat_cells(ring, np.zeros(0, np.int64), valid, rows, shift, columns)
    else:
        cell = _list_cells(firing, ring, valid, measured.shift, rows, shift, columns)
    empty = _flat_cells(np.asarray(empty_ring, dtype=np.int64), np.asarray(empty_column, dtype=np.int64),
                        np.ones(len(empty_ring), dtype=bool), rows, shift, columns)
    return ScanCells(profile.channels, columns, cell, _nearest_in_cell(cell, positions, profile.channels * columns),
                     empty, source)


@jit
def _firing_columns(firing, ring, valid, shift, columns):       # pragma: no cover - compiled
    """Firing column of each return, ``rint(−firing/step − shift[ring]) mod W`` as :mod:`firing_grid` counts its
    cells (0 for non-returns)."""
    out = np.zeros(len(ring), np.int64)
    per_rad = columns / (2.0 * math.pi)
    for i in range(len(ring)):
        if valid[i]:
            out[i] = _firing_column(firing[i], shift[ring[i]], per_rad, columns)
    return out


@jit(inline="always")
def _firing_column(firing, shift, per_rad, columns):       # pragma: no cover - compiled
    return _wrap(int(math.floor(-firing * per_rad - shift + 0.5)), columns)


@jit
def _list_cells(firing, ring, valid, firing_shift, rows, shift, columns):       # pragma: no cover - compiled
    """:func:`_flat_cells` of a list's returns at their :func:`_firing_columns`, in one pass."""
    out = np.empty(len(ring), np.int64)
    per_rad = columns / (2.0 * math.pi)
    for i in range(len(ring)):
        b = ring[i]
        if valid[i]:
            out[i] = rows[b] * columns + _wrap(_firing_column(firing[i], firing_shift[b], per_rad, columns) + shift[b],
                                               columns)
        else:
            out[i] = -1
    return out


@jit
def _flat_cells(ring, column, valid, rows, shift, columns):       # pragma: no cover - compiled
    """``rows[ring]·W + (column + shift[ring]) mod W`` of the valid points, −1 for the others; without ``column``
    (empty: a grid) a point's column is its index mod W."""
    out = np.empty(len(ring), np.int64)
    gridded = len(column) == 0
    own = 0                                             # i mod W, counted (no integer division per point)
    for i in range(len(ring)):
        if valid[i]:
            out[i] = rows[ring[i]] * columns + _wrap((own if gridded else column[i]) + shift[ring[i]], columns)
        else:
            out[i] = -1
        own += 1
        if own == columns:
            own = 0
    return out


def _destagger_shift(positions: np.ndarray, valid: np.ndarray, ring: np.ndarray, column_at, columns: int,
                     channels: int) -> np.ndarray:
    """Per beam, the column shift that puts its returns at their azimuth column: the most common
    ``rint(−azimuth/step) − column`` (or ``+azimuth`` when the columns turn counter-clockwise) among sampled returns
    (``column_at(indices)``: their columns; None: a grid's, the index mod the columns)."""
    stride = max(1, len(ring) // SHIFT_SAMPLE)
    idx = np.arange(0, len(ring), stride)[valid[::stride]]
    if len(idx) == 0:
        return np.zeros(channels, dtype=np.int64)
    azimuth_steps = np.arctan2(positions[idx, 1], positions[idx, 0]) * (columns / (2 * math.pi))
    sampled_column = idx % columns if column_at is None else column_at(idx)
    best, best_share = np.zeros(channels, dtype=np.int64), -1.0
    for sign in (-1.0, 1.0):
        offset = np.mod(np.rint(sign * azimuth_steps).astype(np.int64) - sampled_column, columns)
        mode, hits = _most_common(ring[idx], offset, channels, columns)
        share = hits / len(idx)
        if share > best_share:
            best, best_share = mode, share
            if sign < 0 and share > 0.5:
                break                                   # clockwise (Ouster, Velodyne) is the common case
    return best.astype(np.int64)


@jit
def _most_common(ring, offset, channels, columns):       # pragma: no cover - compiled
    """Per beam the most common ``offset`` (0 … columns − 1; the smallest of a tie, 0 without any) and how many
    samples the beams' most common offsets hold together (an int32 count table, one pass over it)."""
    counts = np.zeros((channels, columns), np.int32)
    for i in range(len(ring)):
        counts[ring[i], offset[i]] += 1
    mode = np.zeros(channels, np.int64)
    hits = 0
    for b in range(channels):
        best = 0
        for c in range(1, columns):
            if counts[b, c] > counts[b, best]:
                best = c
        mode[b] = best
        hits += counts[b, best]
    return mode, hits


def _nearest_in_cell(cell: np.ndarray, positions: np.ndarray, n_cells: int) -> np.ndarray:
    """(N,) bool: the point is the nearest return of its cell (every return when no cell holds two)."""
    shown, collided = _first_in_cell(cell, n_cells)
    if not collided:
        return shown
    placed = np.flatnonzero(cell >= 0)
    r = np.linalg.norm(positions[placed], axis=1)
    order = placed[np.lexsort((r, cell[placed]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell[order[1:]] != cell[order[:-1]]
    shown[:] = False
    shown[order[first]] = True
    return shown


@jit
def _first_in_cell(cell, n_cells):       # pragma: no cover - compiled
    """(points with a cell, whether any cell holds two)."""
    seen = np.zeros(n_cells, np.bool_)
    shown = np.zeros(len(cell), np.bool_)
    collided = False
    for i in range(len(cell)):
        q = cell[i]
        if q >= 0:
            shown[i] = True
            if seen[q]:
                collided = True
            seen[q] = True
    return shown, collided


@jit
def _padded_index_image(cell, shown, rows, columns):       # pragma: no cover - compiled
    w = columns + 2
    out = np.full((rows + 2) * w, -1, np.int64)
    per_column = 1.0 / columns
    for i in range(len(cell)):
        if shown[i]:
            q = cell[i]
            r = int(q * per_column)                     # the row, without an integer division per point
            if r * columns > q:
                r -= 1
            elif (r + 1) * columns <= q:
                r += 1
            out[q + 2 * r + w + 1] = i
    for r in range(rows):
        base = (r + 1) * w
        out[base] = out[base + columns]
        out[base + columns + 1] = out[base + 1]
    return out


def row_elevation_rad(profile: LidarProfile) -> np.ndarray:
    """Elevation (rad) of each image row (rings sorted by elevation, highest first)."""
    out = np.empty(profile.channels)
    out[ring_rows(profile)] = np.deg2rad(np.asarray(profile.beam_elevation_deg, dtype=np.float64))
    return out
