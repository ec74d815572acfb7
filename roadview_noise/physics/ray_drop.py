"""Ray drop: the probability that a real sensor misses the return of a ray an ideal (simulated) scan has
(models.md §3.9; D3.5 CNF28–30, Eq. 1, before the weather).

Features of a ray (:data:`FEATURES`), all from its 8 neighbours in the destaggered range image
(:mod:`scan_cells`), the ray itself left out:
- ``log_signal``: ln(S/T), the median over the neighbours of the received signal S of their returns
  (:func:`lidar_intensity.received_signal`, LiDAR equation ``S = K ρ cos θ / R²``) over the datasheet threshold T;
- ``log_range``: ln(R / 1 m), the median of their ranges;
- ``cos_incidence``: |n̂·d̂| of the surface normal n — the area vector of the polygon of the returning neighbours taken
  in order around the ray (Newell's method) — and the viewing direction d (their mean position); 1 (no penalty) with
  fewer than 3 of them or collinear ones; a depth edge among them reads as grazing incidence (the footprint straddles
  two surfaces: mixed pixel);
- ``elevation_rad``: the beam's elevation.
Why neighbours: a model must be fitted on real scans, where a dropped ray has no range or intensity of its own; its
neighbours stand for the surface it looked at. Fitting and application compute the features with this one function,
so a model fitted on real scans sees the same quantities when it is applied to an ideal scan (a ray without a
returning neighbour falls back to its own values).

Models of p_drop:
- :class:`PhysicalRayDrop` — the detection probability of the shared receiver (:class:`receiver.Receiver`) for an
  effective signal ``S_eff = S · g · (R / 10 m)^a_R · cos^a_θ θ · exp(e1 ω + e2 ω²)`` that varies from ray to ray
  by a log-normal factor of log-SD σ (partial beam cover, surface texture, the neighbours' estimate):
  ``p_detect = E_z[P_rx(S_eff e^{σ z})]``, z ~ N(0, 1), ``p_drop = 1 − (1 − p_0)·p_detect`` with a
  floor p_0 (specular and refractive surfaces, models.md §3.9). For σ much wider than the receiver's own noise this
  is §3.9's ``Φ((ln S_eff − ln T)/σ)``; for σ → 0 it is the receiver's own detection probability.
- :class:`AdditiveLogistic` — ``logit p_drop = b + Σ_f g_f(x_f)`` with piecewise-linear shape functions
  g_f (knots, values; constant beyond the outer knots), fitted on a user's real scans (``rvnoise fit ray-drop``).
Hard rules on top of both: a ray beyond the sensor's maximum range (its own range) always drops, and so does one
whose incidence exceeds ``max_incidence_deg``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import ndtr

from ..types import PointCloud
from .compiled import jit
from .lidar_intensity import sensor_constant
from .lidar_rays import Rays, cloud_rays
from .receiver import Receiver
from .scan_cells import ScanCells, row_elevation_rad, scan_cells

FEATURES = ("log_signal", "log_range", "cos_incidence", "elevation_rad")
REFERENCE_RANGE_M = 10.0
MIN_COS = 1e-3                    # cos θ floor in the logarithm (grazing incidence)
TABLE_HALF_WIDTH = 14.0           # ln(S/T) span of the detection table either side of the threshold
TABLE_STEP = 0.01                 # its grid step in ln(S/T)


# ---------------------------------------------------------------------------------------------------------------
# Features


@dataclass(frozen=True, eq=False)
class ScanRays:
    """What ray drop reads from a cloud: its rays (:func:`lidar_rays.cloud_rays`: ranges, signals in units of K, the
    profile the intensities are read with), its range-image cells (None for a list without a firing grid, ``reason``
    says why) and ln(S/T) of every return."""

    rays: Rays
    cells: ScanCells | None
    reason: str
    log_signal: np.ndarray

    def receiver(self) -> Receiver:
        """The datasheet receiver in units of K (never calibrated from the data: an ideal scan may hold returns no
        real sensor detects)."""
        return Receiver.of(self.rays.profile, sensor_constant(self.rays.profile))

    def features(self, at: np.ndarray, positions_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`ray_features` of the image cells ``at``."""
        return ray_features(self.cells, self.log_signal, self.rays.range_m[:len(positions_m)], positions_m,
                            row_elevation_rad(self.rays.profile), at)


def scan_rays(cloud: PointCloud, model_id: str) -> ScanRays:
    """Validate a LiDAR cloud and read its rays and cells (:class:`ScanRays`)."""
    rays = cloud_rays(cloud, model_id, "ignore")
    cells = scan_cells(cloud, rays.profile)
    with np.errstate(divide="ignore"):
        log_signal = np.log(rays.signal / rays.datasheet_threshold)
    if isinstance(cells, str):
        return ScanRays(rays, None, cells, log_signal)
    return ScanRays(rays, cells, "", log_signal)


def ray_features(cells: ScanCells, log_signal: np.ndarray, range_m: np.ndarray, positions_m: np.ndarray,
                 elevation_by_row: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(len(at), 4) features (:data:`FEATURES`) of the image cells ``at`` (flat indices) from the points' values
    (per point; only returns shown in their cell count), and each cell's number of returning neighbours (0–8)."""
    present = cells.image(np.ones(len(cells.cell), dtype=bool), False)
    with np.errstate(divide="ignore"):
        log_range = np.log(np.asarray(range_m, dtype=np.float64))
    return _neighbour_features(present, cells.image(np.asarray(log_signal, dtype=np.float64)),
                               cells.image(log_range), cells.image(np.asarray(positions_m, dtype=np.float64)),
                               np.asarray(elevation_by_row, dtype=np.float64),
                               np.ascontiguousarray(at, dtype=np.int64))


@jit(inline="always")
def _insert(buf, k, v):       # pragma: no cover - compiled
    """Insert v into the sorted ``buf[:k]``."""
    j = k
    while j > 0 and buf[j - 1] > v:
        buf[j] = buf[j - 1]
        j -= 1
    buf[j] = v


@jit(inline="always")
def _median(buf, k):       # pragma: no cover - compiled
    return buf[k // 2] if k % 2 else 0.5 * (buf[k // 2 - 1] + buf[k // 2])


#: the 8 neighbours in order around the cell (row, column offsets)
_RING_DR = np.array([-1, -1, -1, 0, 1, 1, 1, 0])
_RING_DC = np.array([-1, 0, 1, 1, 1, 0, -1, -1])


@jit(inline="always")
def _cos_incidence(present, pos, r, c, rows, columns, ring_dr, ring_dc):       # pragma: no cover - compiled
    """|n̂·d̂| with n the area vector of the polygon of the returning neighbours in order around the cell (Newell's
    method: Σ v_i × v_{i+1}) and d the sum of their positions; 1 when fewer than 3 return or they are collinear."""
    nx = ny = nz = 0.0
    dx = dy = dz = 0.0
    first = -1
    prev = -1
    k = 0
    for j in range(8):
        rr = r + ring_dr[j]
        cc = c + ring_dc[j]
        if rr < 0 or rr >= rows:
            continue
        if cc < 0:
            cc += columns
        elif cc >= columns:
            cc -= columns
        if not present[rr, cc]:
            continue
        idx = rr * columns + cc
        if prev >= 0:
            pr, pc = prev // columns, prev % columns
            nx += pos[pr, pc, 1] * pos[rr, cc, 2] - pos[pr, pc, 2] * pos[rr, cc, 1]
            ny += pos[pr, pc, 2] * pos[rr, cc, 0] - pos[pr, pc, 0] * pos[rr, cc, 2]
            nz += pos[pr, pc, 0] * pos[rr, cc, 1] - pos[pr, pc, 1] * pos[rr, cc, 0]
        else:
            first = idx
        prev = idx
        dx += pos[rr, cc, 0]
        dy += pos[rr, cc, 1]
        dz += pos[rr, cc, 2]
        k += 1
    if k < 3:
        return 1.0
    pr, pc = prev // columns, prev % columns
    fr, fc = first // columns, first % columns
    nx += pos[pr, pc, 1] * pos[fr, fc, 2] - pos[pr, pc, 2] * pos[fr, fc, 1]
    ny += pos[pr, pc, 2] * pos[fr, fc, 0] - pos[pr, pc, 0] * pos[fr, fc, 2]
    nz += pos[pr, pc, 0] * pos[fr, fc, 1] - pos[pr, pc, 1] * pos[fr, fc, 0]
    norm = math.sqrt((nx * nx + ny * ny + nz * nz) * (dx * dx + dy * dy + dz * dz))
    return abs(nx * dx + ny * dy + nz * dz) / norm if norm > 1e-12 else 1.0


@jit
def _neighbour_features(present, log_signal, log_range, pos, elevation, at):       # pragma: no cover - compiled
    """:func:`ray_features` over the cells ``at``: medians of the returning neighbours (own values without any)."""
    rows, columns = present.shape
    out = np.empty((len(at), 4))
    support = np.empty(len(at), np.int64)
    buf_s = np.empty(8)
    buf_r = np.empty(8)
    for i in range(len(at)):
        r = at[i] // columns
        c = at[i] - r * columns
        k = 0
        for rr in range(max(r - 1, 0), min(r + 2, rows)):
            for dc in range(-1, 2):
                if rr == r and dc == 0:
                    continue
                cc = c + dc
                if cc < 0:
                    cc += columns
                elif cc >= columns:
                    cc -= columns
                if present[rr, cc]:
                    _insert(buf_s, k, log_signal[rr, cc])
                    _insert(buf_r, k, log_range[rr, cc])
                    k += 1
        support[i] = k
        if k > 0:
            out[i, 0] = _median(buf_s, k)
            out[i, 1] = _median(buf_r, k)
        elif present[r, c]:
            out[i, 0] = log_signal[r, c]
            out[i, 1] = log_range[r, c]
        else:
            out[i, 0] = np.nan
            out[i, 1] = np.nan
        out[i, 2] = _cos_incidence(present, pos, r, c, rows, columns, _RING_DR, _RING_DC)
        out[i, 3] = elevation[r]
    return out, support


# ---------------------------------------------------------------------------------------------------------------
# Models


def always_dropped(range_m: np.ndarray, cos_incidence: np.ndarray, max_range_m: float,
                   max_incidence_deg: float) -> np.ndarray:
    """The hard rules: beyond the maximum range (the ray's own range), or incidence above ``max_incidence_deg``."""
    return (np.asarray(range_m) > max_range_m) | (np.asarray(cos_incidence) < math.cos(math.radians(max_incidence_deg)))


@lru_cache(maxsize=32)
def detection_table(receiver: Receiver, log_sd: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, p): the receiver's detection probability of a signal ``T·e^x`` spread by a log-normal factor of log-SD σ,
    ``p(x) = ∫ P_rx(T e^{x + σ z}) φ(z) dz``, on a grid of step :data:`TABLE_STEP` over x ∈ ±14 (clamped beyond): the
    receiver curve on that grid convolved with the normal law's mass per grid cell (exact for a curve constant within
    a cell, so a sharp receiver is no harder than a soft one)."""
    h = TABLE_STEP
    half = int(math.ceil(TABLE_HALF_WIDTH / h))
    k = int(math.ceil(8 * log_sd / h)) if log_sd > 0 else 0
    x = np.arange(-half - k, half + k + 1) * h
    p = np.asarray(receiver.detection_probability(receiver.threshold * np.exp(x)), dtype=np.float64)
    if k:
        edges = (np.arange(-k, k + 2) - 0.5) * h / log_sd
        p = np.convolve(p, np.diff(ndtr(edges)), mode="valid")
        x = x[k:-k]
    return x, p


@dataclass(frozen=True)
class PhysicalRayDrop:
    """The §3.9 detection model on the shared receiver (module doc); coefficients as the model's parameters."""

    log_gain: float
    range_exponent: float
    incidence_exponent: float
    elevation_linear_per_rad: float
    elevation_quadratic_per_rad2: float
    log_signal_sd: float
    floor_drop_probability: float

    def log_effective_signal(self, features: np.ndarray) -> np.ndarray:
        """ln(S_eff / T) of every ray."""
        f = np.asarray(features, dtype=np.float64)
        e = f[:, 3]
        return (f[:, 0] + self.log_gain + self.range_exponent * (f[:, 1] - math.log(REFERENCE_RANGE_M))
                + self.incidence_exponent * np.log(np.maximum(f[:, 2], MIN_COS))
                + e * (self.elevation_linear_per_rad + self.elevation_quadratic_per_rad2 * e))

    def drop_probability(self, features: np.ndarray, receiver: Receiver) -> np.ndarray:
        x, p = detection_table(receiver, float(self.log_signal_sd))
        detect = np.interp(self.log_effective_signal(features), x, p)
        return 1.0 - (1.0 - self.floor_drop_probability) * detect


@dataclass(frozen=True, eq=False)
class AdditiveLogistic:
    """``logit p_drop = intercept + Σ_f interp(x_f, knots_f, values_f)`` (module doc)."""

    features: tuple[str, ...]
    knots: tuple[np.ndarray, ...]
    values: tuple[np.ndarray, ...]
    intercept: float

    def logit(self, features: np.ndarray) -> np.ndarray:
        f = np.asarray(features, dtype=np.float64)
        out = np.full(len(f), float(self.intercept))
        for j, name in enumerate(self.features):
            out += np.interp(f[:, FEATURES.index(name)], self.knots[j], self.values[j])
        return out

    def drop_probability(self, features: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.logit(features)))
