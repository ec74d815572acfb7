"""Rings and firing columns of a point list stored laser by laser: KITTI's Velodyne HDL-64E ``.bin`` scans (raw,
object detection, odometry, SemanticKITTI: N×4 float32 without a ring), models.md §3.0.

The order (checked on 7 real full scans — five frames of two KITTI raw drives, SemanticKITTI 00/000000, another raw
frame — and on the camera-view crops of mmdet3d's KITTI samples): the returns of one laser after another, lasers from
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

Confidence — else the reason, and the weather acts on the returns only: exactly one run per laser of the profile
(a crop — KITTI's camera-view ``velodyne_reduced`` — leaves lasers without returns, whose place in the order is
unknown; shuffled or re-sorted points break into many runs or few); the runs' mean elevations falling (at least 90 % of
neighbouring runs); at least 93 % of a laser's neighbouring returns consecutive firings (real scans 98 %, a random
10 % thinning 88 %: its gaps would be filled as empty rays); W within 0.4 … 2.5× the profile's ``columns``.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np

from ..types import LidarProfile, PointCloud
from .lidar_geometry import RING, has_return, ring_source

LASER_ORDER = "laser"               # LidarProfile.storage_order of a list stored laser by laser (KITTI)
FIRING_COLUMN = "firing_column"     # attribute: each point's column on the firing grid (module doc)
LASER_BREAK_RAD = math.pi           # θ falling back by more than this starts the next laser
CONSECUTIVE_GAP = 1.25              # gaps below this × the median gap are consecutive firings
MIN_CONSECUTIVE = 0.93              # fraction of a laser's neighbour gaps that must be consecutive firings
MIN_FALLING = 0.9                   # fraction of neighbouring runs whose mean elevation falls
COLUMN_RANGE = (0.4, 2.5)           # measured columns over the profile's


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
    valid = has_return(p)
    at = np.flatnonzero(valid)
    channels = profile.channels
    if len(at) < 2 * channels:
        return f"only {len(at)} returns for {channels} lasers"
    x, y, z = (p[:, k] if len(at) == len(p) else p[at, k] for k in range(3))
    theta = np.mod(np.arctan2(y, x), 2.0 * math.pi)
    turn = np.diff(theta)
    breaks = np.flatnonzero(turn < -LASER_BREAK_RAD) + 1
    if len(breaks) + 1 != channels:
        return (f"{len(breaks) + 1} laser runs in the storage order for the {channels} lasers of profile "
                f"{profile.name!r} (a crop without some lasers, shuffled, sorted or merged points)")
    starts = np.concatenate([[0], breaks])
    ring = np.repeat(np.arange(channels), np.diff(np.concatenate([starts, [len(at)]])))
    elevation = np.bincount(ring, np.arctan2(z, np.hypot(x, y)), channels)       # sum per run
    falling = float(np.mean(np.diff(elevation / np.bincount(ring, minlength=channels)) < 0))
    if falling < MIN_FALLING:
        return f"the lasers' elevations do not fall run by run ({100 * falling:.0f} % of neighbouring runs do)"
    same = ring[1:] == ring[:-1]
    gap = turn[same]
    consecutive = (gap > 0) & (gap < CONSECUTIVE_GAP * np.median(gap))
    if consecutive.mean() < MIN_CONSECUTIVE:
        return (f"only {100 * consecutive.mean():.0f} % of neighbouring returns are consecutive firings (a thinned "
                f"or downsampled scan)")
    columns = int(round(2.0 * math.pi / gap[consecutive].mean()))
    low, high = (round(f * profile.columns) for f in COLUMN_RANGE)
    if not low <= columns <= high:
        return f"{columns} firings per turn, not within {low}…{high} for profile {profile.name!r}"
    step = 2.0 * math.pi / columns
    fired = np.zeros(len(at), np.int64)                # firings since the previous return of the laser
    fired[1:][same] = np.maximum(1, np.rint(gap / step)).astype(np.int64)
    count = np.cumsum(fired)
    index = count - count[starts][ring] + np.rint(theta[starts] / step).astype(np.int64)[ring]
    column = np.mod(-index, columns)
    if len(at) == len(p):
        return LaserOrder(ring, column, columns)
    out_ring, out_column = np.zeros(len(p), np.int64), np.zeros(len(p), np.int64)
    out_ring[at], out_column[at] = ring, column
    return LaserOrder(out_ring, out_column, columns)


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
