"""Rings and firing columns of a point list stored laser by laser: KITTI's Velodyne HDL-64E ``.bin`` scans (raw,
object detection, odometry, SemanticKITTI: N×4 float32 without a ring), models.md §3.0.

The order (checked on 7 real full scans — five frames of one KITTI raw drive, one of another, SemanticKITTI 00/000000
— and on the camera-view crops of mmdet3d's KITTI samples): the returns of one laser after another, lasers from
the highest to the lowest (their mean elevations fall run by run), each laser's returns in firing order over one
revolution that starts and ends facing forward (+x, azimuth 0) and turns counter-clockwise seen from above
(θ = atan2(y, x) mod 2π grows within a laser). Hence, on the returns in storage order:

- a new laser starts where θ falls back by more than half a turn. Within a laser θ only grows in a raw scan; an
  ego-motion compensated one (KITTI odometry, SemanticKITTI: the devkits' readme) steps back by a few degrees near
  the car (at most 7° in SemanticKITTI 00/000000), far less than half a turn. Elevations would not do: the lasers'
  vertical offsets (≈ 0.2 m, upper block) put a laser's returns within 10 m degrees away from its angle, against a
  beam spacing of 1/3°;
- the firing step: the HDL-64E reports its azimuth in steps of 0.09° while a laser fires every ≈ 0.166°, so
  neighbouring returns lie 0.09° or 0.18° apart — no whole number of one step (the regular-grid measure of
  :mod:`firing_grid` finds 4 000 columns there, half of them empty). The step is the mean gap between consecutive
  firings (gaps below 1.25× the median gap); W = 2π/step columns (2 162 … 2 172 on the real scans). The rotation
  rate drifts by ±0.04° within a turn, so no fixed-step grid fits a whole turn; instead
- a return's firing index counts firings, on F(θ), the firings from azimuth 0 to θ: each of
  :data:`DRIFT_SECTORS` sectors of the turn its width over its own mean step between consecutive firings (every
  laser's: they share one rotation), scaled to W per turn (:func:`firing_count`). Within a stretch of consecutive
  firings the count is exact; a gap of more firings (a dropout, the open sky: hundreds of firings) is not — a
  0.09° reading at either end is half a step off, and counting every gap by ``rint(gap/step)`` lost or gained one
  firing across the sky and 4–12 over a real laser's turn, so that 0.11–0.16 % of a real scan's returns shared a
  cell with another at the seam. A stretch has a phase, the mean of ``F(θ)`` minus its count over its returns; the
  laser's first stretch starts at ``rint`` of its phase, each next at ``rint`` of the difference of the two phases
  after the one before (at least one firing after its last return), or, when either stretch holds fewer than
  :data:`MIN_STRETCH` returns, ``rint`` of F across the gap. Real scans: 0.00–0.04 % of returns share a cell (the
  seam), the synthetic scan's gaps are all exact. Its grid column, in :mod:`firing_grid`'s clockwise convention, is
  ``−index mod W``.

Confidence — else the reason, and the weather acts on the returns only: one run per laser of the profile, or at least
half as many that fit the beam table as consecutive lasers in exactly one place (:func:`_first_laser`: a crop such
as KITTI's camera-view ``velodyne_reduced`` loses lasers without returns in view; shuffled or re-sorted points break
into many runs or few); the runs' mean elevations falling (at least 90 % of neighbouring runs); at least 93 % of a laser's neighbouring returns consecutive firings (real scans 98 %, a random
10 % thinning 88 %: its gaps would be filled as empty rays); W within 0.4 … 2.5× the profile's ``columns``.
Three compiled passes over the returns (runs and gap histogram, consecutive gaps and their sectors, columns).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np

from ..types import LidarProfile, PointCloud
from .compiled import jit
from .lidar_geometry import RING, atan2, has_return, ring_source

LASER_ORDER = "laser"               # LidarProfile.storage_order of a list stored laser by laser (KITTI)
FIRING_COLUMN = "firing_column"     # attribute: each point's column on the firing grid (module doc)
LASER_BREAK_RAD = math.pi           # θ falling back by more than this starts the next laser
CONSECUTIVE_GAP = 1.25              # gaps below this × the median gap are consecutive firings
MIN_CONSECUTIVE = 0.93              # fraction of a laser's neighbour gaps that must be consecutive firings
MIN_FALLING = 0.9                   # fraction of neighbouring runs whose mean elevation falls
COLUMN_RANGE = (0.4, 2.5)           # measured columns over the profile's
MATCH_DEG = 0.12                    # a crop's runs match the table within this (half the smallest spacing)
GAP_BIN_RAD = 1e-5                  # histogram bin of the gaps whose median is taken (0.006 of a step)
GAP_BINS = 10_000                   # bins up to 0.1 rad; longer gaps share the last
DRIFT_SECTORS = 64                  # sectors of a turn with their own mean firing step (the rotation rate's drift)
MIN_SECTOR_GAPS = 64                # consecutive gaps a sector needs for its own step
STRETCH_GAP = 1                     # a stretch: returns at most this many firings apart (consecutive firings)
MIN_STRETCH = 3                     # returns two stretches need for their phases to place the second


class LaserOrderWarning(UserWarning):
    """A scan whose profile says it is stored laser by laser does not look like it: its weather acts on its returns
    only (printed once per process; the manifest's ``empty_rays_source`` says why per file)."""


@dataclass(frozen=True, eq=False)
class LaserOrder:
    """Per point its ``ring`` (laser, 0 = the highest) and ``column`` on the ``columns``-column firing grid (0 for
    points without a return)."""

    ring: np.ndarray
    column: np.ndarray
    columns: int


def laser_order(positions_m: np.ndarray, profile: LidarProfile) -> LaserOrder | str:
    """The rings and firing columns of a list stored laser by laser (module doc), or why it does not look like one."""
    p = np.asarray(positions_m, dtype=np.float64)
    at = np.flatnonzero(has_return(p))
    channels = profile.channels
    if len(at) < 2 * channels:
        return f"only {len(at)} returns for {channels} lasers"
    returns = p if len(at) == len(p) else p[at]
    theta, ring, runs, tan_sum, gaps = _runs(returns, channels)
    if not channels // 2 <= runs <= channels:
        return (f"{runs} laser runs in the storage order for the {channels} lasers of profile {profile.name!r} "
                f"(shuffled, sorted or merged points)")
    falling = float(np.mean(np.diff(tan_sum[:runs] / np.bincount(ring, minlength=runs)) < 0))
    if falling < MIN_FALLING:
        return f"the lasers' elevations do not fall run by run ({100 * falling:.0f} % of neighbouring runs do)"
    if runs < channels:
        first = _first_laser(returns, ring, runs, profile)
        if isinstance(first, str):
            return first
        ring = ring + first
    counted = np.cumsum(gaps)
    median_rad = (np.searchsorted(counted, 0.5 * counted[-1]) + 0.5) * GAP_BIN_RAD
    total_rad, consecutive, bin_sum, bin_count = _consecutive(theta, ring, CONSECUTIVE_GAP * median_rad)
    if consecutive < MIN_CONSECUTIVE * counted[-1]:
        return (f"only {100 * consecutive / counted[-1]:.0f} % of neighbouring returns are consecutive firings (a "
                f"thinned or downsampled scan)")
    columns = int(round(2.0 * math.pi * consecutive / total_rad))
    low, high = (round(f * profile.columns) for f in COLUMN_RANGE)
    if not low <= columns <= high:
        return f"{columns} firings per turn, not within {low}…{high} for profile {profile.name!r}"
    column = _firing_columns(theta, ring, firing_count(bin_sum, bin_count, total_rad / consecutive, columns), columns)
    if len(at) == len(p):
        return LaserOrder(ring, column, columns)
    out_ring, out_column = np.zeros(len(p), np.int64), np.zeros(len(p), np.int64)
    out_ring[at], out_column[at] = ring, column
    return LaserOrder(out_ring, out_column, columns)


def _first_laser(returns: np.ndarray, ring: np.ndarray, runs: int, profile: LidarProfile) -> int | str:
    """The laser of the first of fewer runs than lasers (a crop: KITTI's camera-view ``velodyne_reduced`` loses the
    lowest lasers, which see only the ground below the image; the highest may see only sky): the runs are consecutive
    lasers, placed where every run's median elevation, seen from its laser's origin (``beam_z_offset_m``), lies within
    MATCH_DEG of the table — the one placement that does (on mmdet3d's real crops: within 0.07°, the next placement
    7° off), else why not."""
    table = np.asarray(profile.beam_elevation_deg)
    offsets = np.asarray(profile.beam_z_offset_m or (0.0,) * profile.channels, dtype=np.float64)
    heights = np.unique(offsets)
    rho = np.hypot(returns[:, 0], returns[:, 1])
    bounds = np.flatnonzero(np.diff(ring)) + 1
    median = np.array([[np.median(e) for e in np.split(np.rad2deg(np.arctan2(returns[:, 2] - h, rho)), bounds)]
                       for h in heights])                                   # (heights, runs)
    row, run = np.searchsorted(heights, offsets), np.arange(runs)
    fits = [k for k in range(profile.channels - runs + 1)
            if np.abs(median[row[k + run], run] - table[k + run]).max() < MATCH_DEG]
    if len(fits) == 1:
        return fits[0]
    return (f"{runs} laser runs in the storage order for the {profile.channels} lasers of profile {profile.name!r}: "
            f"{'no' if not fits else len(fits)} placement{'' if len(fits) == 1 else 's'} of them as consecutive "
            f"lasers matching its beam table within {MATCH_DEG}° (a crop that lost a laser between others, merged "
            f"points)")


@jit
def _runs(p, channels):       # pragma: no cover - compiled
    """One pass over the returns in storage order: θ = atan2(y, x) mod 2π (:func:`lidar_geometry.atan2`), the run of
    each (the next where θ falls back by more than half a turn), the number of runs, per run (of the first
    ``channels``) the sum of tan(elevation), and a histogram of the gaps within a run (bins of GAP_BIN_RAD, the last
    for all longer ones; steps back in bin 0)."""
    n = len(p)
    theta = np.empty(n)
    ring = np.zeros(n, np.int64)
    tan_sum = np.zeros(channels)
    gaps = np.zeros(GAP_BINS + 1, np.int64)
    r = 0
    for i in range(n):
        x, y = p[i, 0], p[i, 1]
        t = atan2(y, x)
        theta[i] = t + 2.0 * math.pi if t < 0 else t
        if i > 0:
            g = theta[i] - theta[i - 1]
            if g < -LASER_BREAK_RAD:
                r += 1
            elif r < channels:
                gaps[min(int(g / GAP_BIN_RAD), GAP_BINS) if g > 0 else 0] += 1
        if r < channels:
            ring[i] = r
            rho = math.sqrt(x * x + y * y)
            tan_sum[r] += p[i, 2] / rho if rho > 0 else 0.0
    return theta, ring, r + 1, tan_sum, gaps


@jit
def _consecutive(theta, ring, limit_rad):       # pragma: no cover - compiled
    """(sum, count) of the gaps within a run that are consecutive firings (above 0, below ``limit_rad``), and the
    same per sector of the turn (:data:`DRIFT_SECTORS`, by the gap's start)."""
    total = 0.0
    count = 0
    bin_sum = np.zeros(DRIFT_SECTORS)
    bin_count = np.zeros(DRIFT_SECTORS, np.int64)
    per_rad = DRIFT_SECTORS / (2.0 * math.pi)
    for i in range(1, len(theta)):
        g = theta[i] - theta[i - 1]
        if ring[i] == ring[i - 1] and 0.0 < g < limit_rad:
            total += g
            count += 1
            b = min(int(theta[i - 1] * per_rad), DRIFT_SECTORS - 1)
            bin_sum[b] += g
            bin_count[b] += 1
    return total, count, bin_sum, bin_count


def firing_count(bin_sum: np.ndarray, bin_count: np.ndarray, step_rad: float, columns: int) -> np.ndarray:
    """The firings counted from azimuth 0 at the edges of the :data:`DRIFT_SECTORS` sectors of a turn: each sector's
    width over its mean step between consecutive firings (the whole turn's where a sector has fewer than
    :data:`MIN_SECTOR_GAPS`), scaled to ``columns`` over the turn."""
    step = np.where(bin_count >= MIN_SECTOR_GAPS, bin_sum / np.maximum(bin_count, 1), step_rad)
    edges = np.concatenate([[0.0], np.cumsum(2.0 * math.pi / DRIFT_SECTORS / step)])
    return edges * (columns / edges[-1])


@jit(inline="always")
def _firings_at(theta, edges):       # pragma: no cover - compiled
    """Firings from azimuth 0 to θ (:func:`firing_count`'s sector edges, linear within a sector)."""
    u = theta * (DRIFT_SECTORS / (2.0 * math.pi))
    b = min(max(int(u), 0), DRIFT_SECTORS - 1)
    return edges[b] + (u - b) * (edges[b + 1] - edges[b])


@jit
def _firing_columns(theta, ring, edges, columns):       # pragma: no cover - compiled
    """Each return's column ``−index mod W`` (module doc). F(θ): the firings counted from azimuth 0
    (:func:`firing_count`); ``k = max(1, rint(F(θ) − F(θ_previous)))`` per gap. Within a stretch (gaps of at most
    :data:`STRETCH_GAP` firings) each return k firings after the one before; a stretch's phase is the mean of F(θ)
    minus those counts over its returns; a laser's first stretch starts at ``rint`` of its phase, each next ``rint``
    of the difference of the two phases after the stretch before (at least one firing after its last return), or k
    after it when either holds fewer than :data:`MIN_STRETCH` returns."""
    n = len(theta)
    out = np.empty(n, np.int64)
    count = np.empty(n, np.int64)       # firings since the stretch's first return
    start = 0
    phase_sum = 0.0
    before_phase, before_first, before_last, before_size, gap = 0.0, 0, 0, 0, 0
    at = 0.0                            # F(θ) of the return before
    for i in range(n + 1):
        before, at = at, _firings_at(theta[i], edges) if i < n else 0.0
        new_laser = i == n or i == 0 or ring[i] != ring[i - 1]
        k = 0
        if not new_laser:
            k = max(1, int(math.floor(at - before + 0.5)))
        if new_laser or k > STRETCH_GAP:          # the stretch start … i − 1 ends: place it
            if i > 0:
                phase = phase_sum / (i - start)
                if start == 0 or ring[start] != ring[start - 1]:
                    first = int(math.floor(phase + 0.5))
                elif min(i - start, before_size) < MIN_STRETCH:
                    first = before_last + gap
                else:
                    first = max(before_last + 1, before_first + int(math.floor(phase - before_phase + 0.5)))
                for q in range(start, i):
                    out[q] = (-(first + count[q])) % columns
                before_phase, before_first, before_last, before_size = phase, first, first + count[i - 1], i - start
            start = i
            gap = k
            phase_sum = 0.0
            if i < n:
                count[i] = 0
        else:
            count[i] = count[i - 1] + k
        if i < n:
            phase_sum += at - count[i]
    return out


def with_laser_order(cloud: PointCloud) -> PointCloud:
    """The chain's input with its rings and firing columns as attributes (``ring``, :data:`FIRING_COLUMN`; they
    travel with the points, :mod:`roadview_noise.provenance`) and its profile's ``columns`` the measured count —
    when its profile says it is stored laser by laser and it carries no ring; otherwise (or when it does not look
    like it: :class:`LaserOrderWarning`) unchanged."""
    profile = cloud.profile
    if (not isinstance(profile, LidarProfile) or profile.storage_order != LASER_ORDER or cloud.grid_shape is not None
            or ring_source(cloud) != "elevation"):
        return cloud
    found = laser_order(cloud.positions_m, profile)
    if isinstance(found, str):
        warnings.warn(f"a scan read with profile {profile.name!r} is not in its laser-by-laser storage order: LiDAR "
                      f"weather acts on its returns only, no empty ray gets weather (the manifest's "
                      f"empty_rays_source says why per file)", LaserOrderWarning, stacklevel=2)
        return cloud
    attributes = {**cloud.attributes, RING: found.ring.astype(np.uint16), FIRING_COLUMN: found.column.astype(np.int32)}
    return dataclasses.replace(cloud, attributes=attributes,
                               profile=dataclasses.replace(profile, columns=found.columns))
