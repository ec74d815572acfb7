"""Firing grid of a point list from each return's firing time (Argoverse 2's ``offset_ns``; models.md §0.3, §3.0).

A spinning sensor fires all its beams once per firing cycle (VLP-32C: 55.296 µs, 16 firings of two lasers 2.304 µs
apart, then a recharge: the manual's timing), one cycle per column of its grid. A list that stores each return's
firing time (``offset_ns``, nanoseconds) therefore gives each return's column exactly, where the azimuth gaps
:mod:`firing_grid` measures are blurred: Argoverse 2 sweeps are ego-motion compensated (av2 devkit ``Sweep``), which
leaves the azimuths of a real sweep's returns beyond 10 m 0.09° (median, 0.3° at the 99th percentile) off a uniform
spin — half a column.

- cycle ``k = floor((t − t₀) / T)``, ``t₀`` in the widest gap of the firing times modulo ``T`` (the recharge);
- spin rate ω: the slope of the returns' firing azimuths ``atan2(y, x) + offset`` against time (unwrapped, a least
  squares line through about 4 000 returns, evenly strided: every 12th of a real sweep's sensor): the sign says which way the head turns in the sensor's frame (Argoverse 2: clockwise for the upper
  sensor, counter-clockwise for the lower one, upside down), ``W = round(2π / (|ω| T))`` columns;
- column ``c = (−sign(ω)·k) mod W`` (:mod:`firing_grid`'s clockwise convention); per beam the azimuth of its column
  0 (the shift, in steps) is the range-weighted circular mean of ``atan2 + offset + c·step`` over its sampled returns
  (a beam without them: the mean of the others; its lasers fire within 0.7 step of each other);
- each return's firing azimuth is then put on its cell (``−(c + shift)·step``), so :func:`firing_grid.empty_rays`
  finds the empty cells and their directions as for a measured grid.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError
from ..types import LidarProfile
from .lidar_geometry import ring_index

TIME_FIELD = "offset_ns"        # a return's firing time after the sweep's stamp, ns (Argoverse 2)
MIN_RETURNS = 200               # fewer returns: no reliable spin rate
SAMPLES = 4096                  # about this many returns (evenly strided) measure the spin rate and the beams' phase
MAX_TIME_GAP_S = 0.025          # a quarter turn at 10 Hz: a longer span without returns leaves the fit's turns unknown


def timed(cloud, profile: LidarProfile) -> bool:
    """Whether the list's grid comes from its firing times: the profile states its firing cycle and the cloud has
    the time field."""
    return profile.firing_cycle_s > 0 and TIME_FIELD in cloud.fields


def firing_time_columns(cloud, profile: LidarProfile, range_m: np.ndarray):
    """The :class:`firing_grid.FiringColumns` of a list from its firing times (module doc), or the reason it has
    none. ``range_m``: each point's range (0: no return)."""
    from .firing_grid import FiringColumns

    try:
        ring = ring_index(cloud, profile)
    except InputError as e:
        return str(e)
    valid = range_m > 0
    if np.count_nonzero(valid) < MIN_RETURNS:
        return f"only {np.count_nonzero(valid)} returns: no spin rate from their firing times"
    t_ns = np.asarray(cloud.fields[TIME_FIELD]).astype(np.int64)
    cycle = _cycles(t_ns, int(round(profile.firing_cycle_s * 1e9)))
    sample = np.flatnonzero(valid)
    sample = sample[::max(1, len(sample) // SAMPLES)]
    p = np.asarray(cloud.positions_m, dtype=np.float64)[sample]
    offsets = np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg, dtype=np.float64))
    azimuth = np.arctan2(p[:, 1], p[:, 0]) + offsets[ring[sample]]
    rate = _spin_rate(t_ns[sample] * 1e-9, azimuth)
    if isinstance(rate, str):
        return rate
    columns = int(round(2 * math.pi / (abs(rate) * profile.firing_cycle_s)))
    step = 2 * math.pi / columns
    column = np.mod(-np.sign(rate) * (cycle - cycle.min()), columns).astype(np.int64)
    angle = azimuth + column[sample] * step
    weight = range_m[sample]
    sums = (np.bincount(ring[sample], weight * np.cos(angle), profile.channels)
            + 1j * np.bincount(ring[sample], weight * np.sin(angle), profile.channels))
    sums = np.where(sums != 0, sums, sums.sum())
    shift = -np.angle(sums) / step
    firing = -(column + shift[ring]) * step
    return FiringColumns(ring, firing, columns, shift, valid, timed=True)


def _cycles(t_ns: np.ndarray, cycle_ns: int) -> np.ndarray:
    """Each time's firing cycle ``floor((t − t₀) / T)`` (integer ns), ``t₀`` the middle of the widest gap of the
    times modulo ``T`` (no laser fires there: the recharge): one pass counts the times per ns of the cycle."""
    used = np.bincount(np.mod(t_ns, cycle_ns), minlength=cycle_ns) > 0
    at = np.flatnonzero(used)
    gaps = np.diff(np.concatenate([at, at[:1] + cycle_ns]))
    widest = int(np.argmax(gaps))
    t0 = int(at[widest]) + int(gaps[widest]) // 2
    return (t_ns - t0) // cycle_ns


def _spin_rate(t_s: np.ndarray, azimuth: np.ndarray) -> float | str:
    """The head's angular rate (rad/s, signed) from the sampled returns' times and firing azimuths: a least-squares
    line through the azimuths unwrapped in time order (their steps wrapped to ±π, summed); the reason there is none
    when a span of a quarter turn (at 10 Hz) has no return."""
    order = np.argsort(t_s, kind="stable")
    t = t_s[order]
    step = np.diff(azimuth[order])
    a = np.concatenate([[0.0], np.cumsum(np.mod(step + math.pi, 2 * math.pi) - math.pi)])
    gap = np.diff(t).max(initial=0.0)
    if gap > MAX_TIME_GAP_S:
        return f"no return for {1e3 * gap:.1f} ms of the sweep: the spin rate is not measured from the firing times"
    t = t - t.mean()
    return float(np.dot(t, a - a.mean()) / np.dot(t, t))
