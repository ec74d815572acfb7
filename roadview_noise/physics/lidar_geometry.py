"""LiDAR spherical coordinates (both conventions of models.md §0.3) and the range image (§3.0).

Angles in radians, ranges in metres, arrays (N,) or (N, 3). A model must convert back with the convention it used
forward: mixing them swaps x and y (mirrors the cloud about the plane x = y; models.md calls it a 90° turn).

- ROADVIEW (D3.4 Matlab weather models): azimuth ``φ = atan2(y, x)`` (counter-clockwise from x),
  elevation ``θ = asin(z / r)``; inverse ``x = r cosθ cosφ, y = r cosθ sinφ, z = r sinθ``.
- Velodyne manual / D3.5 Eq. (4) and (6): azimuth ``α = atan2(x, y)`` (clockwise from y),
  elevation ``ω = atan2(z, sqrt(x² + y²))``; inverse ``x = r cosω sinα, y = r cosω cosα, z = r sinω``.

The origin (r = 0) maps to zero angles in both conventions and back to the origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..types import LidarProfile


def _xyz(positions_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = np.asarray(positions_m, dtype=np.float64)
    return p[:, 0], p[:, 1], p[:, 2]


def xyz_to_roadview(positions_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(r, φ, θ)`` in the ROADVIEW Matlab convention: φ = atan2(y, x), θ = asin(z/r)."""
    x, y, z = _xyz(positions_m)
    r = np.sqrt(x * x + y * y + z * z)
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = np.arcsin(np.clip(np.where(r > 0, z / r, 0.0), -1.0, 1.0))
    return r, np.arctan2(y, x), theta


def roadview_to_xyz(r: np.ndarray, phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(N, 3) positions from ROADVIEW ``(r, φ, θ)``."""
    c = r * np.cos(theta)
    return np.stack([c * np.cos(phi), c * np.sin(phi), r * np.sin(theta)], axis=1)


def xyz_to_velodyne(positions_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(r, α, ω)`` by D3.5 Eq. (6): α = atan2(x, y), ω = atan2(z, sqrt(x² + y²))."""
    x, y, z = _xyz(positions_m)
    rho = np.hypot(x, y)
    return np.sqrt(rho * rho + z * z), np.arctan2(x, y), np.arctan2(z, rho)


def velodyne_to_xyz(r: np.ndarray, alpha: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """(N, 3) positions by D3.5 Eq. (4): x = r cosω sinα, y = r cosω cosα, z = r sinω."""
    c = r * np.cos(omega)
    return np.stack([c * np.sin(alpha), c * np.cos(alpha), r * np.sin(omega)], axis=1)


def has_return(positions_m: np.ndarray) -> np.ndarray:
    """(N,) bool: the point is a return — finite and not at the origin (full grids mark no-return cells with 0)."""
    x, y, z = _xyz(positions_m)
    return np.isfinite(x + y + z) & ((x != 0) | (y != 0) | (z != 0))


# --- range image (models.md §3.0) ------------------------------------------------------------------------------


def ring_rows(profile: LidarProfile) -> np.ndarray:
    """Row of each ring in the range image: rings sorted by elevation, highest beam in row 0."""
    order = np.argsort(-np.asarray(profile.beam_elevation_deg), kind="stable")
    rows = np.empty(len(order), dtype=np.int64)
    rows[order] = np.arange(len(order))
    return rows


@dataclass(frozen=True, eq=False)
class RangeImage:
    """Points of a cloud on a ``rows × columns`` grid (rows = rings by elevation, columns = firing azimuth).

    ``row``/``col``: pixel of every input point (also for points that lost a collision); ``index``: the input point
    shown in each pixel (the nearest when several fall in one), −1 where empty; ``range_m``: its range, 0 where
    empty."""

    row: np.ndarray
    col: np.ndarray
    index: np.ndarray
    range_m: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.index.shape

    def shown(self) -> np.ndarray:
        """(N,) bool: the point is the one its pixel shows."""
        mask = np.zeros(len(self.row), dtype=bool)
        mask[self.index[self.index >= 0]] = True
        return mask


def range_image(positions_m: np.ndarray, ring: np.ndarray, profile: LidarProfile, *, columns: int | None = None,
                column0_azimuth_deg: float = 180.0, clockwise: bool = True) -> RangeImage:
    """Project points with known rings onto the sensor's firing grid (models.md §3.0).

    A point's firing (encoder) azimuth is its azimuth ``φ = atan2(y, x)`` plus its beam's azimuth offset
    (``profile.beam_azimuth_offset_deg``; Ouster and Velodyne tables share this sign); column ``c`` is centred on
    ``column0_azimuth_deg ∓ c·360°/columns`` (− when ``clockwise``). The defaults reproduce the Ouster
    measurement-ID layout (column 0 looks backwards, columns turn clockwise seen from above) — on a real OS1-128
    scan every point lands in its own cell. Points with zero position (no return) or a non-finite one are left
    out (row/col −1). Rows are rings sorted by elevation (:func:`ring_rows`). Collisions keep the nearest return.
    """
    x, y, z = _xyz(positions_m)
    ring = np.asarray(ring, dtype=np.int64)
    columns = int(columns or profile.columns)
    r = np.sqrt(x * x + y * y + z * z)
    valid = has_return(positions_m)
    step = 2 * np.pi / columns
    firing = np.arctan2(y, x) + np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring]
    turns = (np.deg2rad(column0_azimuth_deg) - firing) if clockwise else (firing - np.deg2rad(column0_azimuth_deg))
    col = np.where(valid, np.rint(np.nan_to_num(turns) / step).astype(np.int64) % columns, -1)
    row = np.where(valid, ring_rows(profile)[ring], -1)

    n_rows = profile.channels
    pixel = row * columns + col
    order = np.flatnonzero(valid)
    # one stable sort by pixel, then range in µm (ties within 1 µm: the earlier point); ~free for grid-ordered input
    range_um = np.minimum(np.rint(r[order] * 1e6), 2 ** 32 - 1).astype(np.int64)
    order = order[np.argsort((pixel[order] << 32) | range_um, kind="stable")]
    first = np.ones(len(order), dtype=bool)
    first[1:] = pixel[order[1:]] != pixel[order[:-1]]
    winners = order[first]
    index = np.full(n_rows * columns, -1, dtype=np.int64)
    index[pixel[winners]] = winners
    rng_img = np.zeros(n_rows * columns)
    rng_img[pixel[winners]] = r[winners]
    return RangeImage(row, col, index.reshape(n_rows, columns), rng_img.reshape(n_rows, columns))
