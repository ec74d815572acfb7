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
        real sensor detects: :func:`scan_rays` reads the rays with ``calibrate=False``)."""
        return self.rays.receiver

    def features(self, at: np.ndarray, positions_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`ray_features` of the image cells ``at``."""
        return ray_features(self.cells, self.log_signal, self.rays.range_m[:len(positions_m)], positions_m,
                            row_elevation_rad(self.rays.profile), at)


def scan_rays(cloud: PointCloud, model_id: str, empty: bool = True) -> ScanRays:
    """Validate a LiDAR cloud and read its rays and cells (:class:`ScanRays`; ``empty=False``: without the empty
    cells, which only fitting needs)."""
    rays = cloud_rays(cloud, model_id, "ignore", calibrate=False)
    cells = scan_cells(cloud, rays.profile, rays.range_m[:len(cloud)], empty)
    log_signal = np.divide(rays.decision_signal, rays.datasheet_threshold)     # unread readings: their population
    with np.errstate(divide="ignore"):
        np.log(log_signal, out=log_signal)
    if isinstance(cells, str):
        return ScanRays(rays, None, cells, log_signal)
    return ScanRays(rays, cells, "", log_signal)


def ray_features(cells: ScanCells, log_signal: np.ndarray, range_m: np.ndarray, positions_m: np.ndarray,
                 elevation_by_row: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(len(at), 4) features (:data:`FEATURES`) of the image cells ``at`` (flat indices) from the points' values
    (per point; only returns shown in their cell count), and each cell's number of returning neighbours (0–8)."""
    features, median_range, support = _neighbour_features(
        cells.padded_index_image(), np.ascontiguousarray(log_signal, dtype=np.float64),
        np.ascontiguousarray(range_m, dtype=np.float64), np.ascontiguousarray(positions_m, dtype=np.float64),
        np.asarray(elevation_by_row, dtype=np.float64), np.ascontiguousarray(at, dtype=np.int64), cells.columns)
    np.log(median_range, out=features[:, 1])            # numpy's SIMD log, not one libm call per ray
    return features, support


@jit(inline="always")
def _insert(buf, k, v):       # pragma: no cover - compiled
    """Insert v into the sorted ``buf[:k]``."""
    j = k
    while j > 0 and buf[j - 1] > v:
        buf[j] = buf[j - 1]
        j -= 1
    buf[j] = v


@jit(inline="always")
def _median8(a0, a1, a2, a3, a4, a5, a6, a7):       # pragma: no cover - compiled
    """Median of 8 values: Batcher's odd–even merge sort (19 compare-exchanges) on scalars, only as far as the 4th
    and 5th values need it."""
    a0, a1 = min(a0, a1), max(a0, a1)
    a2, a3 = min(a2, a3), max(a2, a3)
    a4, a5 = min(a4, a5), max(a4, a5)
    a6, a7 = min(a6, a7), max(a6, a7)
    a0, a2 = min(a0, a2), max(a0, a2)
    a1, a3 = min(a1, a3), max(a1, a3)
    a4, a6 = min(a4, a6), max(a4, a6)
    a5, a7 = min(a5, a7), max(a5, a7)
    a1, a2 = min(a1, a2), max(a1, a2)
    a5, a6 = min(a5, a6), max(a5, a6)
    a0, a4 = min(a0, a4), max(a0, a4)
    a1, a5 = min(a1, a5), max(a1, a5)
    a2, a6 = min(a2, a6), max(a2, a6)
    a3, a7 = min(a3, a7), max(a3, a7)
    a2, a4 = min(a2, a4), max(a2, a4)
    a3, a5 = min(a3, a5), max(a3, a5)
    a3, a4 = min(a3, a4), max(a3, a4)
    return 0.5 * (a3 + a4)


@jit(inline="always")
def _gather8(dst, k, values, q0, q1, q2, q3, q4, q5, q6, q7):       # pragma: no cover - compiled
    """``dst[:, k]`` = ``values`` at the 8 indices (one column of a block of rings)."""
    dst[0, k], dst[1, k], dst[2, k], dst[3, k] = values[q0], values[q1], values[q2], values[q3]
    dst[4, k], dst[5, k], dst[6, k], dst[7, k] = values[q4], values[q5], values[q6], values[q7]


@jit(inline="always")
def _median8_at(v, k):       # pragma: no cover - compiled
    """:func:`_median8` of ``v[:, k]``."""
    return _median8(v[0, k], v[1, k], v[2, k], v[3, k], v[4, k], v[5, k], v[6, k], v[7, k])


@jit(inline="always")
def _ring_cos(pos, q0, q1, q2, q3, q4, q5, q6, q7):       # pragma: no cover - compiled
    """|n̂·d̂| of a full ring of 8 neighbours (points ``q0 … q7`` in order around the cell, see
    :func:`_neighbour_features`): n = ``Σ_{i even} v_{i+1} × (v_{i+2} − v_i)``, d = Σ v_i; 1 when degenerate."""
    x0, y0, z0 = pos[q0, 0], pos[q0, 1], pos[q0, 2]
    x1, y1, z1 = pos[q1, 0], pos[q1, 1], pos[q1, 2]
    x2, y2, z2 = pos[q2, 0], pos[q2, 1], pos[q2, 2]
    x3, y3, z3 = pos[q3, 0], pos[q3, 1], pos[q3, 2]
    x4, y4, z4 = pos[q4, 0], pos[q4, 1], pos[q4, 2]
    x5, y5, z5 = pos[q5, 0], pos[q5, 1], pos[q5, 2]
    x6, y6, z6 = pos[q6, 0], pos[q6, 1], pos[q6, 2]
    x7, y7, z7 = pos[q7, 0], pos[q7, 1], pos[q7, 2]
    nx = ny = nz = 0.0
    for xa, ya, za, xm, ym, zm, xb, yb, zb in ((x0, y0, z0, x1, y1, z1, x2, y2, z2),
                                               (x2, y2, z2, x3, y3, z3, x4, y4, z4),
                                               (x4, y4, z4, x5, y5, z5, x6, y6, z6),
                                               (x6, y6, z6, x7, y7, z7, x0, y0, z0)):
        ex, ey, ez = xb - xa, yb - ya, zb - za
        nx += ym * ez - zm * ey
        ny += zm * ex - xm * ez
        nz += xm * ey - ym * ex
    dx = ((((((x0 + x1) + x2) + x3) + x4) + x5) + x6) + x7
    dy = ((((((y0 + y1) + y2) + y3) + y4) + y5) + y6) + y7
    dz = ((((((z0 + z1) + z2) + z3) + z4) + z5) + z6) + z7
    return _cos_between(nx, ny, nz, dx, dy, dz)


@jit
def _full_medians(ring_s, ring_r, full, k_full, out, median_range):       # pragma: no cover - compiled
    """The medians of a block of full rings (:func:`_neighbour_features`), vectorised, then put in place."""
    res_s, res_r = np.empty(k_full), np.empty(k_full)
    for k in range(k_full):
        res_s[k] = _median8_at(ring_s, k)
        res_r[k] = _median8_at(ring_r, k)
    for k in range(k_full):
        out[full[k], 0], median_range[full[k]] = res_s[k], res_r[k]


@jit(inline="always")
def _cos_between(nx, ny, nz, dx, dy, dz):       # pragma: no cover - compiled
    """|n̂·d̂|, 1 when either vector (nearly) vanishes."""
    norm = math.sqrt((nx * nx + ny * ny + nz * nz) * (dx * dx + dy * dy + dz * dz))
    return abs(nx * dx + ny * dy + nz * dz) / norm if norm > 1e-12 else 1.0


@jit(inline="always")
def _median(buf, k):       # pragma: no cover - compiled
    """Median of ``buf[:k]`` (insertion sort; fewer than 8 values)."""
    for j in range(1, k):
        _insert(buf, j, buf[j])
    return buf[k // 2] if k % 2 else 0.5 * (buf[k // 2 - 1] + buf[k // 2])


@jit
def _neighbour_features(padded, log_signal, range_m, pos, elevation, at, columns):       # pragma: no cover - compiled
    """:func:`ray_features` over the cells ``at`` of the image ``padded`` (the point each cell shows, −1: none;
    :meth:`ScanCells.padded_index_image`): medians of the returning neighbours' log signal and range (the cell's own
    values without any; the range returned apart, for the caller's vectorised log), and |n̂·d̂| with n the area vector
    of the polygon of the returning neighbours in order around the cell and d the sum of their positions (1 with fewer
    than 3 of them, or collinear ones). The area vector is Newell's ``Σ v_i × v_{i+1}``; for the full ring of 8 the
    same sum as ``Σ_{i even} v_{i+1} × (v_{i+2} − v_i)`` (4 cross products). The full rings' medians (most cells)
    are taken per block of cells in one vectorised loop (:func:`_full_medians`)."""
    w = columns + 2
    # the 8 neighbours in order around the cell, as offsets in the padded image
    ring = np.array([-w - 1, -w, -w + 1, 1, w + 1, w, w - 1, -1])
    out = np.empty((len(at), 4))
    median_range = np.empty(len(at))
    support = np.empty(len(at), np.int8)                # (0–8: one byte, a pass over the rays less to memory)
    buf_s = np.empty(8)
    buf_r = np.empty(8)
    px = np.empty(9)
    py = np.empty(9)
    pz = np.empty(9)
    block = 1024                    # full rings' values gathered per block, their medians in one vectorised loop
    full = np.empty(block, np.int64)
    ring_s, ring_r = np.empty((8, block)), np.empty((8, block))
    r, row_start = 0, 0
    k_full = 0
    for i in range(len(at)):
        if not row_start <= at[i] < row_start + columns:     # (cells mostly come row by row: no division)
            r = at[i] // columns
            row_start = r * columns
        base = at[i] + 2 * r + w + 1
        out[i, 3] = elevation[r]
        q0, q1, q2, q3 = padded[base + ring[0]], padded[base + ring[1]], padded[base + ring[2]], padded[base + ring[3]]
        q4, q5, q6, q7 = padded[base + ring[4]], padded[base + ring[5]], padded[base + ring[6]], padded[base + ring[7]]
        if min(min(min(q0, q1), min(q2, q3)), min(min(q4, q5), min(q6, q7))) >= 0:      # the full ring (most cells)
            support[i] = 8
            full[k_full] = i
            _gather8(ring_s, k_full, log_signal, q0, q1, q2, q3, q4, q5, q6, q7)
            _gather8(ring_r, k_full, range_m, q0, q1, q2, q3, q4, q5, q6, q7)
            k_full += 1
            if k_full == block:
                _full_medians(ring_s, ring_r, full, k_full, out, median_range)
                k_full = 0
            out[i, 2] = _ring_cos(pos, q0, q1, q2, q3, q4, q5, q6, q7)
            continue
        k = 0
        for j in range(8):
            p = padded[base + ring[j]]
            if p >= 0:
                buf_s[k] = log_signal[p]
                buf_r[k] = range_m[p]
                px[k] = pos[p, 0]
                py[k] = pos[p, 1]
                pz[k] = pos[p, 2]
                k += 1
        support[i] = k
        if k > 0:
            out[i, 0] = _median(buf_s, k)
            median_range[i] = _median(buf_r, k)
        else:
            own = padded[base]
            out[i, 0] = log_signal[own] if own >= 0 else np.nan
            median_range[i] = range_m[own] if own >= 0 else np.nan
        cos = 1.0
        if k >= 3:
            px[k], py[k], pz[k] = px[0], py[0], pz[0]          # close the polygon
            nx = ny = nz = 0.0
            for j in range(k):
                nx += py[j] * pz[j + 1] - pz[j] * py[j + 1]
                ny += pz[j] * px[j + 1] - px[j] * pz[j + 1]
                nz += px[j] * py[j + 1] - py[j] * px[j + 1]
            dx = dy = dz = 0.0
            for j in range(k):
                dx += px[j]
                dy += py[j]
                dz += pz[j]
            cos = _cos_between(nx, ny, nz, dx, dy, dz)
        out[i, 2] = cos
    _full_medians(ring_s, ring_r, full, k_full, out, median_range)
    return out, median_range, support


# ---------------------------------------------------------------------------------------------------------------
# Models


def always_dropped(range_m: np.ndarray, cos_incidence: np.ndarray, max_range_m: float,
                   max_incidence_deg: float) -> np.ndarray:
    """The hard rules: beyond the maximum range (the ray's own range), or incidence above ``max_incidence_deg`` (none
    at 90°)."""
    beyond = np.asarray(range_m) > max_range_m
    if max_incidence_deg >= 90.0:
        return beyond
    return beyond | (np.asarray(cos_incidence) < math.cos(math.radians(max_incidence_deg)))


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

    def drop_probability(self, features: np.ndarray, receiver: Receiver) -> np.ndarray:
        """``1 − (1 − p_0)·p_detect(ln S_eff / T)`` of every ray (one compiled pass, linear interpolation in the
        :func:`detection_table`)."""
        x, p = detection_table(receiver, float(self.log_signal_sd))
        features = np.asarray(features, dtype=np.float64)
        log_cos = np.maximum(features[:, 2], MIN_COS)
        np.log(log_cos, out=log_cos)                    # numpy's SIMD log, not one libm call per ray
        return _physical_drop(np.ascontiguousarray(features), log_cos, self.log_gain - self.range_exponent
                              * math.log(REFERENCE_RANGE_M), self.range_exponent, self.incidence_exponent,
                              self.elevation_linear_per_rad, self.elevation_quadratic_per_rad2,
                              self.floor_drop_probability, x[0], 1.0 / TABLE_STEP, p)


@jit
def _physical_drop(f, log_cos, offset, a_range, a_cos, e1, e2, floor, x0, inv_h, table):  # pragma: no cover - compiled
    """:meth:`PhysicalRayDrop.drop_probability`: ``x = ln S/T + offset + a_R ln R + a_θ ln cos θ + e1 ω + e2 ω²``
    (``log_cos``: ln cos θ per ray, floored)."""
    out = np.empty(len(f))
    last = len(table) - 1
    for i in range(len(f)):
        e = f[i, 3]
        x = (f[i, 0] + offset + a_range * f[i, 1] + a_cos * log_cos[i] + e * (e1 + e2 * e))
        u = (x - x0) * inv_h
        if not u > 0.0:                                  # (NaN: no estimate, as for no signal)
            detect = table[0]
        elif u >= last:
            detect = table[last]
        else:
            j = int(u)
            t = u - j
            detect = table[j] * (1.0 - t) + table[j + 1] * t
        out[i] = 1.0 - (1.0 - floor) * detect
    return out


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
        """``1 / (1 + e^{−logit})``: the logit in one compiled pass (the same piecewise-linear interpolation as
        :meth:`logit`), the logistic function vectorised."""
        columns = np.array([FEATURES.index(n) for n in self.features], dtype=np.int64)
        starts = np.cumsum([0] + [len(k) for k in self.knots]).astype(np.int64)
        slopes = np.concatenate([np.append(np.diff(v) / np.diff(k), 0.0) for k, v in zip(self.knots, self.values)])
        z = _additive_logit(np.ascontiguousarray(features, dtype=np.float64), columns, starts,
                            np.concatenate(self.knots), np.concatenate(self.values), slopes, float(self.intercept))
        np.exp(np.negative(z, out=z), out=z)            # numpy's SIMD exp, not one libm call per ray
        z += 1.0
        return np.reciprocal(z, out=z)


@jit
def _additive_logit(f, columns, starts, knots, values, slopes, intercept):       # pragma: no cover - compiled
    """The logit of :meth:`AdditiveLogistic.drop_probability`. Each feature's piecewise-linear function (flat beyond
    its outer knots) as a sum of ramps, ``g(x) = v_0 + Σ_q s_q · clip(x − k_q, 0, k_{q+1} − k_q)`` (a missing value:
    v_0), which compiles to SIMD without branches; rays in blocks that stay in the L1 cache."""
    n = len(f)
    z = np.empty(n)
    block = 1024
    x = np.empty(block)
    acc = np.empty(block)
    for b0 in range(0, n, block):
        m = min(n, b0 + block) - b0
        acc[:m] = intercept
        for j in range(len(columns)):
            col, lo0, hi0 = columns[j], starts[j], starts[j + 1] - 1
            v0 = values[lo0]
            for i in range(m):
                xi = f[b0 + i, col]
                x[i] = xi if xi == xi else -np.inf
                acc[i] += v0
            for q in range(lo0, hi0):
                k, width, slope = knots[q], knots[q + 1] - knots[q], slopes[q]
                for i in range(m):
                    acc[i] += slope * min(max(x[i] - k, 0.0), width)
        z[b0:b0 + m] = acc[:m]
    return z
