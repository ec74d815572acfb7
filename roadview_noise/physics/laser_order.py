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
- a return's firing index counts firings: the laser's first return at ``rint(θ/step)``, each next one
  ``max(1, rint(gap/step))`` firings after the previous (a gap of k firings lies within k ± 0.54 steps: counted
  exactly). Its grid column, in :mod:`firing_grid`'s clockwise convention, is ``−index mod W``.

Confidence — else the reason, and the weather acts on the returns only: one run per laser of the profile, or at least
half as many that fit the beam table as consecutive lasers in exactly one place (:func:`_first_laser`: a crop such
as KITTI's camera-view ``velodyne_reduced`` loses lasers without returns in view; shuffled or re-sorted points break
into many runs or few); the runs' mean elevations falling (at least 90 % of neighbouring runs); at least 93 % of a laser's neighbouring returns consecutive firings (real scans 98 %, a random
10 % thinning 88 %: its gaps would be filled as empty rays); W within 0.4 … 2.5× the profile's ``columns``.
Three compiled passes over the returns (runs and gap histogram, consecutive gaps, columns): ≈ 3 ms for 120 k points.
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
    total_rad, consecutive = _consecutive(theta, ring, CONSECUTIVE_GAP * median_rad)
    if consecutive < MIN_CONSECUTIVE * counted[-1]:
        return (f"only {100 * consecutive / counted[-1]:.0f} % of neighbouring returns are consecutive firings (a "
                f"thinned or downsampled scan)")
    columns = int(round(2.0 * math.pi * consecutive / total_rad))
    low, high = (round(f * profile.columns) for f in COLUMN_RANGE)
    if not low <= columns <= high:
        return f"{columns} firings per turn, not within {low}…{high} for profile {profile.name!r}"
    column = _firing_columns(theta, ring, 2.0 * math.pi / columns, columns)
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
    """(sum, count) of the gaps within a run that are consecutive firings: above 0, below ``limit_rad``."""
    total = 0.0
    count = 0
    for i in range(1, len(theta)):
        g = theta[i] - theta[i - 1]
        if ring[i] == ring[i - 1] and 0.0 < g < limit_rad:
            total += g
            count += 1
    return total, count


@jit
def _firing_columns(theta, ring, step, columns):       # pragma: no cover - compiled
    """Each return's column ``−index mod W``: a laser's first return fired at ``rint(θ/step)``, each next
    ``max(1, rint(gap/step))`` firings after the one before."""
    out = np.empty(len(theta), np.int64)
    index = 0
    for i in range(len(theta)):
        if i == 0 or ring[i] != ring[i - 1]:
            index = int(math.floor(theta[i] / step + 0.5))
        else:
            index += max(1, int(math.floor((theta[i] - theta[i - 1]) / step + 0.5)))
        out[i] = (-index) % columns
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
