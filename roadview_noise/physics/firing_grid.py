"""Firing grid of a LiDAR point list: where a spinning sensor fired without a return (models.md §0.3, §3.0).

A point list keeps only the rays that returned, but a weather model must also act on the others (fog and
particles return on rays that saw nothing in clear weather; models.md §1, "ray drop before weather"). A spinning
sensor fires every beam of the profile's table at every column of a revolution, so the empty rays are the cells of
that ``beams × columns`` grid that hold no point:

- ring: the ``ring`` field, else the ring an earlier step stored before moving the points (``attributes``), else
  the beam of nearest elevation (:func:`lidar_geometry.ring_index`);
- a sweep merging several sensors in one frame (Argoverse 2's two VLP-32C: profile ``storage_order: merged``) has
  no single grid: each sensor's rows go through the chain on their own in its frame (:mod:`sensor_rig`, with the
  log's calibration), else weather on its returns only;
- a list that stores each return's firing time (Argoverse 2's ``offset_ns``) under a profile that states its firing
  cycle (``firing_cycle_s``) has its columns from those times (:mod:`firing_time`), not from its azimuth gaps;
- a ring-less list stored laser by laser (KITTI: profile ``storage_order: laser``) has its rings and firing columns
  recovered from that order on the chain's input (:mod:`laser_order`; its encoder's 0.09° azimuth steps are no
  whole number of firing steps) and carried as attributes; the rest below holds for it with no per-beam shift;
- columns: *measured* from the data — the firing-azimuth step between neighbouring returns of one beam — because
  the column count is a recording mode (Ouster 512/1024/2048, Velodyne: rotation rate), not a property of the
  sensor; the profile's ``columns`` is only compared with it, and wins (warned) over twice its count when its step
  fits the data too (:func:`undecided_columns`). A list whose azimuths are not on a regular step (a
  merged, resampled or motion-compensated cloud, random test points) has no firing grid, and the reason is kept;
- each beam's columns may be shifted by a fraction of a step (Velodyne firing sequence): the shift is measured per
  beam (circular mean weighted by range, against the parallax of near returns), so a return never lands in its
  neighbour's cell;
- a list that stores its no-return rays as points (nuScenes: within the profile's ``min_range_m``): each such
  point is an empty ray, in the cell its storage order gives (:func:`_placeholder_rays`): a weather return on that
  ray takes the placeholder's row, so the output has one return per ray;
- which cells are empty rays: those whose own azimuth (beam offsets included) lies within 4 steps of a return of
  any beam — a cropped field of view or lost packets are not filled, while a sparse ground beam keeps the open sky
  above it in view — on the beams that returned something and on every beam above the highest of them (they saw
  only sky). A beam without returns below or between beams with returns is dead, blocked or removed (or the
  profile has more beams than the data) and gets no weather.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..types import LidarProfile
from .compiled import jit
from .lidar_geometry import atan2, beam_means, elevation_rad, far_returns, has_return, ring_index, \
    ring_search_table, ring_source, sorted_beam, tangent_position
from .firing_time import TIME_FIELD, firing_time_columns, timed
from .laser_order import FIRING_COLUMN, LASER_ORDER, laser_order

TWO_PI = 2.0 * math.pi
STEP_SAMPLE_BEAMS = 4           # the most populated beams measure the column step from their neighbour gaps
PHASE_SAMPLE_STRIDE = 16        # every 16th return measures the per-beam column shift
MIN_GAPS = 200                  # fewer neighbour gaps: no reliable step
MIN_REGULAR_FRACTION = 0.8      # gaps within ±15 % of a whole number of steps, for a regular grid
MAX_GAP_STEPS = 8               # gaps up to this many steps measure the step (longer ones: open sky)
WHOLE_STEPS = 0.15              # a gap within this of a whole number of steps is on the grid
FIT_STEPS = 0.25                # gaps within this of a whole number of steps refit the step
UNDECIDED_WHOLE_FRACTION = 0.7  # whole-step gaps on the profile's grid for it to win over twice its columns
VIEW_MARGIN_STEPS = 4           # an azimuth is in view within this many steps of a return (any beam)
MIN_FILLED_FRACTION = 0.2       # fewer returns per cell in view of the returning beams: fewer beams (warned)
FIRING_ORDER = 0.9              # a ring's successive returns 1 … 8 columns apart, one way: stored in firing order
MERGED_SENSORS = "merged"       # LidarProfile.storage_order of a sweep merging several sensors (Argoverse 2): no grid
MERGED_REASON = ("the sweep merges several sensors in one frame (profile storage_order: merged; Argoverse 2's two "
                 "VLP-32C, the lower one upside down): no single firing grid, and no calibration/"
                 "egovehicle_SE3_sensor.feather of its log beside it for each sensor's own (positions about the "
                 "profile's sensor_origin_m)")
FULL_SWEEP = 0.98               # points stored per ring, of the columns, for a list that stores every firing


@dataclass(frozen=True, eq=False)
class FiringGrid:
    """Empty rays of a point list on its ``channels × columns`` firing grid (M cells).

    ``ring``, ``column``: the empty cells; ``like``: for each, a return fired in the same column (same firing time),
    whose other per-point fields (time stamps) an added return copies; ``columns``: measured column count;
    ``shift``: per beam, the measured offset of its columns (in steps); ``firing_rad``: every point's firing azimuth
    (:func:`lidar_geometry.firing_azimuth_rad`, by the rings the grid was measured with)."""

    ring: np.ndarray
    column: np.ndarray
    like: np.ndarray
    columns: int
    shift: np.ndarray
    profile: LidarProfile
    firing_rad: np.ndarray
    out_of_view: int = 0        # azimuth bins (of ``columns``) farther than the view margin from every return
    gaps_columns: int | None = None     # the count the gaps gave when the profile's won (:func:`undecided_columns`)
    measured_elevation_rad: np.ndarray | None = None    # per beam, from the list (:func:`measured_elevations`)
    host: np.ndarray | None = None      # per empty cell, the no-return point stored on it (−1: none; None: no such)
    timed: bool = False                 # the grid comes from the returns' firing times (:mod:`firing_time`)

    def elevation_rad(self) -> np.ndarray:
        """Each beam's elevation: the profile's, or the list's own when its ring field counts other beams."""
        if self.measured_elevation_rad is not None:
            return self.measured_elevation_rad
        return np.deg2rad(np.asarray(self.profile.beam_elevation_deg, dtype=np.float64))

    def directions(self, cells: np.ndarray, range_m: np.ndarray | None = None) -> np.ndarray:
        """(len(cells), 3) unit vectors of the empty cells ``cells`` (indices into ``ring``/``column``), times
        ``range_m`` (per cell) if given: elevation of the beam, azimuth ``−c·step − (shift·step + offset)`` of the
        column turned back by the beam's shift and azimuth offset (angle sum of a per-column and a per-beam table).
        The mm-scale beam-origin offsets are neglected."""
        step = TWO_PI / self.columns
        col_angle = -np.arange(self.columns) * step
        beam_angle = -self.shift * step - np.deg2rad(np.asarray(self.profile.beam_azimuth_offset_deg))
        elevation = self.elevation_rad()
        scale = np.ones(len(cells)) if range_m is None else np.asarray(range_m, dtype=np.float64)
        return _directions(np.asarray(cells, dtype=np.int64), self.ring, self.column, scale, np.cos(col_angle),
                           np.sin(col_angle), np.cos(beam_angle), np.sin(beam_angle), np.cos(elevation),
                           np.sin(elevation))

    def subset(self, keep: np.ndarray) -> FiringGrid:
        """The empty cells where ``keep`` (a boolean mask over them) holds."""
        return dataclasses.replace(self, ring=self.ring[keep], column=self.column[keep], like=self.like[keep],
                                   host=None if self.host is None else self.host[keep])

    def describe(self) -> str:
        crop = (f"; {self.out_of_view} of {self.columns} columns out of view (a crop, an azimuth window or lost "
                f"packets): not filled" if self.out_of_view else "")
        if self.timed:
            return (f"{self.profile.channels}x{self.columns} firing grid from the returns' firing times "
                    f"({TIME_FIELD}){crop}")
        return describe_grid(self.profile, self.columns, self.gaps_columns) + crop


def describe_grid(profile: LidarProfile, columns: int, gaps_columns: int | None = None) -> str:
    """What a firing grid of ``columns`` measured from a list is, for the manifest; ``gaps_columns``: the count
    the list's gaps gave when the profile's ``columns`` won over it (:func:`undecided_columns`)."""
    if profile.storage_order == LASER_ORDER:
        return f"{profile.channels}x{columns} firing grid from the list's laser-by-laser storage order"
    if gaps_columns is not None:
        return (f"{profile.channels}x{columns} firing grid of profile {profile.name!r}: the list's gaps fit its step "
                f"and {gaps_columns} columns alike")
    note = "" if columns == profile.columns else f"; profile {profile.name!r} says {profile.columns}"
    return f"{profile.channels}x{columns} firing grid measured from the list{note}"


@jit
def _directions(cells, ring, column, scale, ca, sa, cb, sb, ce, se):       # pragma: no cover - compiled
    """Rows ``scale · (cos e cos(a + b), cos e sin(a + b), sin e)`` of the cells (a: column angle, b: beam angle)."""
    out = np.empty((len(cells), 3))
    for i in range(len(cells)):
        cell = np.uintp(cells[i])                      # (unsigned: no negative-index wraparound compiled)
        b, c = np.uintp(ring[cell]), np.uintp(column[cell])
        h = scale[i] * ce[b]
        out[i, 0] = h * (ca[c] * cb[b] - sa[c] * sb[b])
        out[i, 1] = h * (sa[c] * cb[b] + ca[c] * sb[b])
        out[i, 2] = scale[i] * se[b]
    return out


def measured_step_rad(gap: np.ndarray, returns: int) -> tuple[float, str]:
    """Column step (rad) of a scan from the firing-azimuth gaps between neighbouring returns of one beam (``gap``:
    :func:`beam_gaps` of the ``returns`` of its most populated beams); (nan, reason) when the gaps are too few or not
    whole multiples of one step.

    The most common gap seeds the step (:func:`_most_common_gap`): on a grid with fill fraction p, a gap of k steps
    occurs with probability ∝ (1 − p)^(k−1), so one step is always the most common gap. The step is then refitted on
    the gaps of up to 2, 4, then 8 steps that lie within 0.25 step of a whole number k ≥ 1 (step = Σg / Σk: along a
    run of neighbouring returns their azimuth jitter cancels; Σgk / Σk² left the step 0.03 % off at 5 % jitter, half a
    column at 1 800); the grid is regular when 80 % of those gaps lie within 0.15 step of a whole number — alone, or
    with a neighbouring gap (:func:`_whole_or_pair`: a Velodyne decoder puts the returns of a packet's last block a
    fraction of a step off their beam's phase, 1 in 6 in dual-return mode)."""
    if returns < MIN_GAPS:
        return math.nan, f"only {returns} returns in the sampled beams"
    if len(gap) < MIN_GAPS:
        return math.nan, f"only {len(gap)} azimuth gaps between returns of one beam"
    step, regular = _refit_step(gap)
    if regular < MIN_REGULAR_FRACTION:
        return math.nan, f"azimuths are not on a regular firing grid ({100 * regular:.0f} % of the gaps are whole steps)"
    return step, ""


@jit(error_model="numpy")
def _refit_step(gap):       # pragma: no cover - compiled
    """:func:`measured_step_rad`'s seed (:func:`_most_common_gap`) and refits on the gaps within ``FIT_STEPS`` of a
    whole number (≥ 1) of steps: (the step, the fraction of the last refit's gaps that are whole steps, alone or with
    a neighbour, :func:`_whole_or_pair`). A refit without gaps gives NaN, as NumPy's did (the NumPy error model: no
    ZeroDivisionError from compiled code)."""
    step = _most_common_gap(gap)
    last = step
    for most_steps in (2, 4, MAX_GAP_STEPS, MAX_GAP_STEPS):
        last, gs, ks = step, 0.0, 0.0
        bound, per_step = (most_steps + 0.5) * last, 1.0 / last
        for g in gap:
            if g < bound:
                k = np.rint(g * per_step)
                if k >= 1 and abs(g * per_step - k) < FIT_STEPS:
                    gs += g
                    ks += k
        step = gs / ks
    near = regular = 0.0
    per_step, per_last, short = 1.0 / step, 1.0 / last, WHOLE_STEPS * step
    for j in range(len(gap)):
        if gap[j] < bound:
            near += 1.0
            regular += _whole_or_pair(gap, j, per_step, per_last, short)
    return step, regular / near


@jit(inline="always")
def _whole(g, per_step, per_last):       # pragma: no cover - compiled
    """Whether the gap ``g`` lies within ``WHOLE_STEPS`` steps (``1 / per_step``) of the whole number (≥ 1) of steps
    ``1 / per_last`` it rounds to."""
    k = np.rint(g * per_last)
    return k >= 1 and abs(g * per_step - k) < WHOLE_STEPS


@jit(inline="always")
def _whole_or_pair(gap, j, per_step, per_last, short):       # pragma: no cover - compiled
    """1.0 if gap ``j`` is whole (:func:`_whole`) or, not shorter than ``WHOLE_STEPS`` and with the gap before or
    after it (not shorter either), adds up to a whole number of steps (one return off its beam's phase between two
    on it: a Velodyne decoder's last block of a packet, its azimuth not interpolated), else 0.0. Two returns of one
    beam closer than that (``short``) are not on one grid (another beam's return, a resampled point)."""
    g = gap[j]
    if _whole(g, per_step, per_last):
        return 1.0
    if g < short:
        return 0.0
    if j > 0 and gap[j - 1] >= short and _whole(gap[j - 1] + g, per_step, per_last):
        return 1.0
    if j + 1 < len(gap) and gap[j + 1] >= short and _whole(g + gap[j + 1], per_step, per_last):
        return 1.0
    return 0.0


@jit
def _most_common_gap(gap):       # pragma: no cover - compiled
    """The seed of the step: of the gaps' 10th, 25th and 50th percentiles, the one with the most gaps within
    ``WHOLE_STEPS`` of it (the earlier on a tie or within that of it; a percentile with half the gaps near it is
    taken). One step is the most common gap, but off-phase returns (a Velodyne decoder's) can make a tenth of the
    gaps a fraction of a step."""
    n = len(gap)
    best, best_count = math.nan, -1
    for q in (n // 10, n // 4, n // 2):
        if 2 * best_count > n:
            break
        c = np.partition(gap, q)[q]
        if best_count >= 0 and abs(c / best - 1.0) < WHOLE_STEPS:
            continue
        count, low, high = 0, (1.0 - WHOLE_STEPS) * c, (1.0 + WHOLE_STEPS) * c
        for g in gap:
            count += (g > low) & (g < high)
        if count > best_count:
            best, best_count = c, count
    return best


@jit
def _cells(firing, valid, ring, offsets, shift, step, columns, channels):       # pragma: no cover - compiled
    """One pass over the returns with their firing azimuths (:func:`lidar_geometry.firing_azimuth_rad`): column
    ``rint(−firing/step − shift[ring]) mod W`` (clockwise turn), the occupancy of every (ring, column) cell, per
    column one return fired there (−1: none), and which azimuth bins of one step hold a return (azimuth
    ``firing − offset``)."""
    occupied = np.zeros((channels, columns), np.bool_)
    like = np.full(columns, -1, np.int64)
    seen = np.zeros(columns, np.bool_)
    inv_step = 1.0 / step
    for i in range(len(ring)):
        if not valid[i]:
            continue
        b = np.uintp(ring[i])                          # (unsigned indices: no negative-index wraparound compiled)
        c = np.uintp(_wrap(int(math.floor(-firing[i] * inv_step - shift[b] + 0.5)), columns))
        occupied[b, c] = True
        if like[c] < 0:
            like[c] = i
        seen[np.uintp(_wrap(int(math.floor((firing[i] - offsets[b]) * inv_step)), columns))] = True
    return occupied, like, seen


@jit(inline="always")
def _wrap(k, n):       # pragma: no cover - compiled
    """``k mod n`` for k within a few turns of [0, n) (no integer division)."""
    while k < 0:
        k += n
    while k >= n:
        k -= n
    return k


@jit
def _empty_cells(occupied, words, fires, in_view, shift, offsets, step, returned, nearest):       # pragma: no cover
    """(ring, column, like) of the cells without a return on firing beams whose own azimuth
    ``−(c + shift)·step − offset`` lies in a one-step azimuth bin in view, and how many of them lie on the beams that
    ``returned``. ``words``: ``occupied`` read 8 cells at a time (empty unless a row is whole words): 8 occupied cells
    are skipped at once. ``like``: per cell ``nearest`` of its column (:func:`_nearest_filled`)."""
    channels, columns = occupied.shape
    ring = np.empty(channels * columns, np.int64)
    col = np.empty(channels * columns, np.int64)
    like = np.empty(channels * columns, np.int64)
    per_row = len(words) // channels
    full = np.uint64(0x0101010101010101)
    m = on_returned = 0
    for b in range(channels):
        if not fires[b]:
            continue
        c = 0
        first = m
        beam_shift, beam_offset = shift[b], offsets[b] / step      # (per beam: the same values per cell)
        while c < columns:
            if c & 7 == 0 and c < 8 * per_row and words[np.uintp(b * per_row + (c >> 3))] == full:
                c += 8
                continue
            if not occupied[b, np.uintp(c)]:
                k = _wrap(int(math.floor(-(c + beam_shift) - beam_offset)), columns)
                if in_view[np.uintp(k)]:
                    at = np.uintp(m)                   # (unsigned: no negative-index wraparound compiled)
                    ring[at], col[at], like[at] = b, c, nearest[np.uintp(c)]
                    m += 1
            c += 1
        if returned[b]:
            on_returned += m - first
    return ring[:m], col[:m], like[:m], on_returned


@jit
def beam_gaps(firing, ring, valid, sampled, counts):       # pragma: no cover - compiled
    """(the gaps between neighbouring firing azimuths, wrapped to [0, 2π), of the returns of each beam where
    ``sampled``, beam by beam — those of one ray's several echoes, ≤ 1e-7 rad, left out —, the number of those
    returns): one pass gathers them beam by beam (``counts``: at least each sampled beam's returns, the points per
    ring), each beam's sorted on its own."""
    channels = len(sampled)
    start = np.zeros(channels + 1, np.int64)
    for b in range(channels):
        start[b + 1] = start[b] + (counts[b] if sampled[b] else 0)
    f = np.empty(start[channels])
    at = start[:channels].copy()
    for i in range(len(ring)):
        b = np.uintp(ring[i])                          # (unsigned: no negative-index wraparound compiled)
        if valid[i] and sampled[b]:
            f[np.uintp(at[b])] = np.mod(firing[i], TWO_PI)
            at[b] += 1
    gap = np.empty(len(f))
    m = returns = 0
    for b in range(channels):
        beam = _sorted_turn(f[start[b]:at[b]])
        returns += len(beam)
        for j in range(1, len(beam)):
            g = beam[j] - beam[j - 1]
            if g > 1e-7:                               # several echoes of one ray are not a gap
                gap[m] = g
                m += 1
    return gap[:m], returns


@jit
def _sorted_turn(f):       # pragma: no cover - compiled
    """``np.sort(f)``, without sorting when ``f`` is a turn in firing order — ascending or descending with one wrap,
    as a beam's returns are listed — by reading it from the wrap on (the sorted array of the same values either
    way)."""
    n = len(f)
    up = down = 0
    at_up = at_down = 0
    for i in range(1, n):
        if f[i] > f[i - 1]:
            up += 1
            at_up = i
        elif f[i] < f[i - 1]:
            down += 1
            at_down = i
    if down == 0:                                       # ascending already (or fewer than two)
        return f.copy()
    if up == 0:
        return f[::-1].copy()
    out = np.empty(n)
    if up == 1 and f[0] <= f[n - 1]:                    # descending, one wrap: each part reversed, the later on top
        for i in range(at_up):
            out[i] = f[at_up - 1 - i]
        for i in range(n - at_up):
            out[at_up + i] = f[n - 1 - i]
        return out
    if down == 1 and f[n - 1] <= f[0]:                  # ascending, one wrap: from the wrap on
        out[:n - at_down] = f[at_down:]
        out[n - at_down:] = f[:at_down]
        return out
    return np.sort(f)


@jit
def _beam_phase(firing, ring, range_m, valid, stride, per_rad, channels):       # pragma: no cover - compiled
    """Per beam, the sums of ``R cos(per_rad · firing)`` and ``R sin(…)`` over every ``stride``-th point that is a
    return: the phase of its columns, weighted by range ``R`` (near returns carry the mm-scale beam-origin
    parallax)."""
    cos_sum = np.zeros(channels)
    sin_sum = np.zeros(channels)
    for i in range(0, len(ring), stride):
        if valid[i]:
            angle = firing[i] * per_rad
            cos_sum[ring[i]] += range_m[i] * math.cos(angle)
            sin_sum[ring[i]] += range_m[i] * math.sin(angle)
    return cos_sum, sin_sum


@dataclass(frozen=True, eq=False)
class FiringColumns:
    """The firing grid measured from a point list, before its empty cells are looked for: every point's ``ring`` and
    firing azimuth ``firing_rad``, the measured column count ``columns`` and per-beam ``shift`` (in steps), which
    points are returns (``valid``), and ``gaps_columns``: the count the gaps gave when the profile's won."""

    ring: np.ndarray
    firing_rad: np.ndarray
    columns: int
    shift: np.ndarray
    valid: np.ndarray
    gaps_columns: int | None = None
    timed: bool = False


class FiringGridWarning(UserWarning):
    """The firing grid's column count is the profile's, not the one measured from the list; or the list fills too
    few of its cells for the profile's beams."""


def undecided_columns(gap: np.ndarray, columns: int, profile: LidarProfile) -> int:
    """The profile's column count instead of the ``columns`` measured from the gaps ``gap`` when they are twice the
    profile's (±3 %) and 70 % of the gaps are whole steps of the profile's grid too: the data do not tell a sensor's
    grid from one of half its step (which would fill twice the empty rays), so the profile wins, warned. A grid
    really recorded at twice the profile's columns (Ouster 2048 against 1024) has gaps of an odd number of its steps
    — half of the profile's — on over half its gaps (a fraction 1/(2 − fill))."""
    if abs(columns - 2 * profile.columns) > 0.06 * profile.columns or _whole_fraction(
            gap, TWO_PI / profile.columns) < UNDECIDED_WHOLE_FRACTION:
        return columns
    warnings.warn(f"the firing grid measured from the list has {columns} columns, twice the {profile.columns} of "
                  f"profile {profile.name!r}, whose step fits the data too: the profile's are used (give the "
                  f"sensor's column count in the profile if it is {columns})", FiringGridWarning, stacklevel=4)
    return profile.columns


@jit
def _whole_fraction(gap, step):       # pragma: no cover - compiled
    """The fraction of the gaps up to ``MAX_GAP_STEPS`` steps of ``step`` that are whole steps (:func:`_whole`)."""
    near = whole = 0
    for g in gap:
        if g < (MAX_GAP_STEPS + 0.5) * step:
            near += 1
            whole += _whole(g, 1.0 / step, 1.0 / step)
    return whole / max(near, 1)


def firing_grid(cloud, profile: LidarProfile, range_m: np.ndarray | None = None,
                points: ListPoints | None = None) -> FiringGrid | str:
    """The empty rays of a point-list scan (see the module doc), or the reason it has no firing grid. ``range_m``:
    the points' ranges if known, 0 where a point is no return; ``points``: the list read already
    (:func:`list_points`)."""
    measured = firing_columns(cloud, profile, range_m, points)
    if isinstance(measured, str):
        return measured
    grid = empty_rays(measured, profile, hosts=ring_source(cloud) != "elevation")
    if ring_source(cloud) == "field" and int(measured.ring.max()) + 1 != profile.channels and not measured.timed:
        grid = dataclasses.replace(grid, measured_elevation_rad=measured_elevations(cloud, measured, profile))
    return grid


def measured_elevations(cloud, measured: FiringColumns, profile: LidarProfile) -> np.ndarray:
    """Per beam of ``profile``, the mean elevation of the list's returns beyond 2 m on that ring (rings without: the
    nearest rings'). For a list whose ring field counts other beams than the profile's (a VLP-16's 16 rings read with
    the default OS1-128): its empty rays lie on its own beams, not on the profile's first ones (real VLP-16 list under
    fog: 26.7° off, median)."""
    p = np.asarray(cloud.positions_m, dtype=np.float64)
    far = far_returns(p, measured.valid)
    if len(far) == 0:
        return np.deg2rad(np.asarray(profile.beam_elevation_deg, dtype=np.float64))
    return beam_means(measured.ring[far], elevation_rad(p[far]), profile.channels)


def empty_rays(measured: FiringColumns, profile: LidarProfile, hosts: bool = False) -> FiringGrid:
    """The empty rays of the firing grid ``measured`` (:func:`firing_columns`) of a list (module doc); ``hosts``
    (rings carried, not recovered from positions): the no-return points stored as rays (:func:`_placeholder_rays`)."""
    ring, firing, columns, shift, valid = (measured.ring, measured.firing_rad, measured.columns, measured.shift,
                                           measured.valid)
    offsets = np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg, dtype=np.float64))
    step = TWO_PI / columns
    occupied, like, seen = _cells(firing, valid, ring, offsets, shift, step, columns, profile.channels)
    m = VIEW_MARGIN_STEPS
    in_view = np.convolve(np.concatenate([seen[-m:], seen, seen[:m]]), np.ones(2 * m + 1), "valid") > 0
    words = occupied.reshape(-1).view(np.uint64) if columns % 8 == 0 else np.zeros(0, np.uint64)
    returned = occupied.any(axis=1)
    nearest = _nearest_filled(like)
    er, ec, el, on_returned = _empty_cells(occupied, words, _firing_beams(returned, profile), in_view, shift, offsets,
                                           step, returned, nearest)
    _warn_sparse(on_returned, int(np.count_nonzero(returned)) * int(np.count_nonzero(in_view)),
                 columns, profile)
    host = None
    if hosts and not valid.all():
        er, ec, el, host = _placeholder_rays(measured, er, ec, el, nearest, profile.channels)
    return FiringGrid(er, ec, el, columns, shift, profile, firing,
                      int(np.count_nonzero(~in_view)), measured.gaps_columns, host=host, timed=measured.timed)


def _placeholder_rays(measured: FiringColumns, er: np.ndarray, ec: np.ndarray, el: np.ndarray,
                      nearest: np.ndarray, channels: int) -> tuple[np.ndarray, ...]:
    """The empty rays (ring, column, like, host) of a list that stores its no-return rays as points (nuScenes: within
    ``min_range_m``), from the empty cells ``er``, ``ec``, ``el`` and each column's return ``nearest``: every such
    point is an empty ray of its own (``host``: the point; its weather return takes its row) in the column as far
    between its ring's neighbouring returns' columns as it is in storage (rounded), or one column per firing on from
    the nearest of them at a ring's ends; the columns of returns come from their azimuths, which jitter by a column
    between beams (14 % of a nuScenes firing's neighbouring returns), so a cell holding no point is no ray where the
    list stores every firing (each ring with returns ≥ ``FULL_SWEEP`` of the columns): its empty rays are its
    no-return points; in a list storing fewer firings the empty cells no such point lies on stay empty rays too
    (``host`` −1, appended). Unchanged (``host`` −1) unless the list's rings are stored in firing order: 90 % of
    the steps between a ring's successive returns go 1 … 8 columns one way (a shuffled or re-sorted list: ≈ 0 %).

    Real scan (nuScenes LIDAR_TOP, 34 688 rows, 1 084 firings a ring on 1 081 columns, 8 029 placeholders): of its
    8 705 empty cells 914 hold no placeholder, 452 of them between two consecutive firings of their ring (jitter),
    most others beside returns within 5 m (parallax); 238 placeholders rounded to a cell another one or a return
    took."""
    return _stored_rays(measured.ring, measured.valid, measured.firing_rad, measured.shift,
                        measured.columns / TWO_PI, measured.columns, channels, er, ec, el, nearest)


@jit
def _stored_rays(ring, valid, firing, shift, inv_step, columns, channels, er, ec, el, nearest):  # pragma: no cover
    """:func:`_placeholder_rays`: one pass over the list in storage order gives each return's column (as
    :func:`_cells` finds it), each point's ordinal within its ring, each no-return point's previous return of its
    ring, and counts the steps between a ring's successive returns that go 1 … ``MAX_GAP_STEPS`` columns forward
    and backward; one pass back places each no-return point between its ring's previous and next return."""
    n = len(ring)
    column = np.full(n, -1, np.int64)
    seq = np.empty(n, np.int64)
    prev = np.full(n, -1, np.int64)
    count = np.zeros(channels, np.int64)
    last = np.full(channels, -1, np.int64)
    forward = backward = steps = 0
    for i in range(n):
        r = np.uintp(ring[i])
        seq[i] = count[r]
        count[r] += 1
        if not valid[i]:
            prev[i] = last[r]
            continue
        c = _wrap(int(math.floor(-firing[i] * inv_step - shift[r] + 0.5)), columns)
        column[i] = c
        if last[r] >= 0:
            gap = _wrap(c - column[last[r]], columns)
            steps += 1
            forward += 1 <= gap <= MAX_GAP_STEPS
            backward += 1 <= columns - gap <= MAX_GAP_STEPS
        last[r] = i
    if steps < MIN_GAPS or max(forward, backward) < FIRING_ORDER * steps:
        return er, ec, el, np.full(len(er), -1, np.int64)   # not stored in firing order
    sign = 1 if forward >= backward else -1
    rings = full = 0
    for r in range(channels):
        if last[r] >= 0:
            rings += 1
            full += count[r] >= FULL_SWEEP * columns
    every = full == rings                                    # every firing stored: a cell without a point is no ray
    cell = np.full(channels * columns, -1, np.int64)
    for k in range(len(er)):
        cell[er[k] * columns + ec[k]] = k
    keep = np.full(len(er), not every)
    placed = np.full(n, -1, np.int64)                        # each no-return point's column
    last[:] = -1
    for i in range(n - 1, -1, -1):                           # the next return of each point's ring
        r = np.uintp(ring[i])
        p, q = prev[i], last[r]
        if valid[i]:
            last[r] = i
            continue
        c = 0
        if p >= 0 and q >= 0:
            firings = seq[q] - seq[p]
            turn = _wrap(sign * (column[q] - column[p]), columns)     # columns, the way the sensor turns
            ahead = seq[i] - seq[p]
            c = column[p] + sign * (int(np.rint(turn * ahead / firings)) if 1 <= turn <= MAX_GAP_STEPS * firings
                                    else ahead)
        elif p >= 0:
            c = column[p] + sign * (seq[i] - seq[p])
        elif q >= 0:
            c = column[q] - sign * (seq[q] - seq[i])
        if p >= 0 or q >= 0:                                 # (a ring without returns: none)
            placed[i] = _wrap(c, columns)
            k = cell[r * columns + placed[i]]
            if k >= 0 and not every:                          # its cell is its ray, not another one
                keep[k] = False
    m = 0                                                    # (loops: np.flatnonzero cost 4x the passes above)
    for k in range(len(er)):
        m += keep[k]
    for i in range(n):
        m += placed[i] >= 0
    out_ring, out_col, out_like, host = (np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m, np.int64),
                                         np.full(m, -1, np.int64))
    j = 0
    for k in range(len(er)):
        if keep[k]:
            out_ring[j], out_col[j], out_like[j] = er[k], ec[k], el[k]
            j += 1
    for i in range(n):
        if placed[i] >= 0:
            out_ring[j], out_col[j], out_like[j], host[j] = ring[i], placed[i], nearest[placed[i]], i
            j += 1
    return out_ring, out_col, out_like, host


def _warn_sparse(empty: int, cells: int, columns: int, profile: LidarProfile) -> None:
    """A :class:`FiringGridWarning` when returns fill under :data:`MIN_FILLED_FRACTION` of the grid's cells in view
    on the beams that returned (``empty`` of ``cells``; the sky above them aside): a list of a sensor with fewer beams
    than the profile (a VLP-16's ``x y z intensity`` list read with the default OS1-128 returns on 84 of its 128
    beams, filling 10 % of them: fog added 12× its points on the beams between its own)."""
    if cells and empty > (1 - MIN_FILLED_FRACTION) * cells:
        warnings.warn(f"the list's returns fill {1 - empty / cells:.0%} of the {profile.channels}x{columns} firing "
                      f"grid of profile {profile.name!r}: its sensor has fewer beams than the profile? Weather then "
                      f"returns on rays it never fired: give its lidar_profile (e.g. an inline beam table)",
                      FiringGridWarning, stacklevel=4)


def firing_columns(cloud, profile: LidarProfile, range_m: np.ndarray | None = None,
                   points: ListPoints | None = None) -> FiringColumns | str:
    """The rings, firing azimuths, column count and per-beam shifts of a point list's firing grid (module doc), or
    the reason it has none; :func:`firing_grid` then finds the empty cells. A list stored laser by laser (KITTI)
    takes its rings and columns from the attributes :func:`laser_order.with_laser_order` gave the chain's input.
    ``points``: the list's :func:`list_points`, if read already (its ranges then stand for ``range_m``)."""
    if points is None:
        if range_m is None:
            positions = np.ascontiguousarray(cloud.positions_m, dtype=np.float64)
            range_m = np.where(has_return(positions), np.linalg.norm(positions, axis=1), 0.0)
        points = list_points(cloud, profile, range_m)
    range_m = points.range_m
    if points.reason:
        return points.reason
    if points.ring is None:
        if timed(cloud, profile):
            return firing_time_columns(cloud, profile, range_m)
        return _laser_order_columns(cloud, profile, range_m)
    ring, firing, counts = points.ring, points.firing_rad, points.counts
    valid = range_m > 0
    if not valid.any():
        return "no returns"
    sampled = np.zeros(profile.channels, dtype=bool)                 # counts hold zero points too: only to pick beams
    sampled[np.argsort(counts, kind="stable")[-STEP_SAMPLE_BEAMS:]] = True
    gap, returns = beam_gaps(firing, ring, valid, sampled, counts)
    step, reason = measured_step_rad(gap, returns)
    if reason:
        return reason
    gaps_columns = int(round(TWO_PI / step))
    columns = undecided_columns(gap, gaps_columns, profile)
    step = TWO_PI / columns                             # the grid closes on itself
    cos_sum, sin_sum = _beam_phase(firing, ring, range_m, valid, PHASE_SAMPLE_STRIDE, TWO_PI / step,
                                   profile.channels)
    phase = cos_sum - 1j * sin_sum
    phase = np.where(phase != 0, phase, phase.sum())   # beams without samples: the scan's common phase
    shift = np.angle(phase) / TWO_PI                    # per beam, in steps
    return FiringColumns(ring, firing, columns, shift, valid, None if columns == gaps_columns else gaps_columns)


@dataclass(frozen=True, eq=False)
class ListPoints:
    """A point list read once for its firing grid (:func:`list_points`): each point's range ``range_m`` (0: no
    return) and its ``ring``, firing azimuth ``firing_rad`` and the points per ring ``counts`` — None when a list
    stored laser by laser takes them from its attributes, or one with firing times from those
    (:mod:`firing_time`), or with the ``reason`` it has no firing grid."""

    range_m: np.ndarray
    ring: np.ndarray | None = None
    firing_rad: np.ndarray | None = None
    counts: np.ndarray | None = None
    reason: str = ""


def list_points(cloud, profile: LidarProfile, range_m: np.ndarray | None = None) -> ListPoints:
    """One pass over a point list's points (module doc): rings (carried, else recovered), firing azimuths, points per
    ring and, unless ``range_m`` is given, each point's range ``|p|`` (0 where it is zero, not finite or closer than
    the profile's ``min_range_m``: the rays' ranges of :mod:`lidar_rays`)."""
    positions = np.ascontiguousarray(cloud.positions_m, dtype=np.float64)
    laser = profile.storage_order == LASER_ORDER and (FIRING_COLUMN in cloud.attributes
                                                      or ring_source(cloud) == "elevation") or timed(cloud, profile)
    reason = MERGED_REASON if profile.storage_order == MERGED_SENSORS else ""
    try:
        carried = (np.zeros(0, np.int64) if laser or reason or ring_source(cloud) == "elevation"
                   else ring_index(cloud, profile))
    except InputError as e:
        reason, carried = str(e), np.zeros(0, np.int64)
    rings = not (laser or reason)
    if not rings and range_m is not None:
        return ListPoints(range_m, reason=reason)
    offsets = np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg, dtype=np.float64))
    tan_mid, order = ring_search_table(tuple(profile.beam_elevation_deg))
    ring, firing, counts, ranges = _rings_and_azimuths(
        positions, carried, float(profile.sensor_z_offset_m), float(profile.beam_origin_offset_m), tan_mid, order,
        offsets, profile.channels, rings, range_m is None, float(profile.min_range_m))
    if range_m is None:
        range_m = ranges
    return ListPoints(range_m, ring, firing, counts) if rings else ListPoints(range_m, reason=reason)


def _laser_order_columns(cloud, profile: LidarProfile, range_m: np.ndarray) -> FiringColumns | str:
    """The firing grid of a list stored laser by laser: rings and columns carried as attributes, each point's firing
    azimuth its column's (``−column·step``, no per-beam shift); without them, why the chain's input
    (``cloud.recorded``) did not look stored that way (:func:`laser_order.laser_order`, only for the reason: rings
    are never recovered after a step moved points)."""
    if FIRING_COLUMN not in cloud.attributes:
        found = laser_order((cloud if cloud.recorded is None else cloud.recorded).positions_m, profile)
        return found if isinstance(found, str) else "rings and columns were not recovered from the chain's input"
    try:
        ring = ring_index(cloud, profile)
    except InputError as e:
        return str(e)
    step = TWO_PI / profile.columns
    firing = np.asarray(cloud.attributes[FIRING_COLUMN], dtype=np.float64) * -step
    return FiringColumns(ring, firing, profile.columns, np.zeros(profile.channels), range_m > 0)


@jit
def _rings_and_azimuths(positions, carried, z_offset, rho_offset, tan_mid, order, offsets, channels, rings, ranges,
                        min_range_m):       # pragma: no cover - compiled
    """One pass over the points, in blocks: if ``rings``, ring (``carried``, or when it is empty the beam of nearest
    elevation, :func:`lidar_geometry.beam_of`), firing azimuth ``atan2(y, x) + offset[ring]``
    (:func:`lidar_geometry.firing_azimuth_rad`) and the points per ring; if ``ranges``, the range ``|p|`` (0 where
    it is not > 0 and ≥ ``min_range_m``)."""
    n = len(positions)
    recover = len(carried) == 0
    ring = np.empty(n if rings and recover else 0, np.int64) if recover else carried   # (a carried ring: no copy)
    firing = np.empty(n if rings else 0)
    range_m = np.empty(n if ranges else 0)
    counts = np.zeros(channels, np.int64)
    block = 1024                                        # points whose coordinates stay in the L1 cache
    x, y, z, t = np.empty(block), np.empty(block), np.empty(block), np.empty(block)
    low, high, beam = math.inf, -math.inf, 0           # the last recovered beam and its interval of z/ρ
    s, change, top = 0, 0, len(tan_mid)                 # its sorted position, the change that led to it
    for b0 in range(0, n, block):
        m = min(n, b0 + block) - b0
        xyz = positions[b0:b0 + m]                      # (the block's views: loop indices from 0, contiguous
        for i in range(m):                              # stores, no negative-index wraparound compiled)
            x[i], y[i], z[i] = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        if ranges:
            rb = range_m[b0:b0 + m]
            for i in range(m):                          # (the expression of lidar_rays' ranges: the same bits)
                ri = math.sqrt(x[i] ** 2 + y[i] ** 2 + z[i] ** 2)
                rb[i] = ri if (ri > 0) & (ri >= min_range_m) else 0.0
        if not rings:
            continue
        fb = firing[b0:b0 + m]
        for i in range(m):                              # one vectorised loop over contiguous coordinates
            fb[i] = atan2(y[i], x[i])
        gb = ring[b0:b0 + m]
        if recover:
            for i in range(m):                          # z/ρ from the beam origin, vectorised (NaN: sorted_beam's)
                rho = math.sqrt(x[i] * x[i] + y[i] * y[i]) - rho_offset
                t[i] = (z[i] - z_offset) / rho if rho > 0 else math.nan
            for i in range(m):                          # the last beam's interval first, then the next beam's in
                if not (low <= t[i] < high):            # the list's order (the last change repeated), else a search
                    q = min(max(s + change, 0), top)
                    if not (q == 0 or tan_mid[q - 1] <= t[i]) or not (q == top or t[i] < tan_mid[q]):
                        q = (tangent_position(t[i], tan_mid) if t[i] == t[i]
                             else sorted_beam(x[i], y[i], z[i], z_offset, rho_offset, tan_mid))
                    change, s = q - s, q
                    low = tan_mid[s - 1] if s > 0 else -math.inf
                    high = tan_mid[s] if s < top else math.inf
                    beam = order[s]
                gb[i] = beam
        for i in range(m):
            b = np.uintp(gb[i])                         # (unsigned: no negative-index wraparound compiled)
            fb[i] += offsets[b]
            counts[b] += 1
    return ring, firing, counts, range_m


def _firing_beams(has_returns: np.ndarray, profile: LidarProfile) -> np.ndarray:
    """Beams whose empty cells are rays: those with returns and those above the highest of them (sky)."""
    elevation = np.asarray(profile.beam_elevation_deg)
    return has_returns | (elevation > elevation[has_returns].max())


def _nearest_filled(like: np.ndarray) -> np.ndarray:
    """``like`` with each column without a return (−1) taking the entry of the nearest column that has one
    (circular)."""
    filled = np.flatnonzero(like >= 0)
    n = len(like)
    if len(filled) == n:
        return like
    ring_pos = np.concatenate([filled - n, filled, filled + n])
    j = np.clip(np.searchsorted(ring_pos, np.arange(n)), 1, len(ring_pos) - 1)
    nearer_left = np.arange(n) - ring_pos[j - 1] <= ring_pos[j] - np.arange(n)
    return like[np.mod(np.where(nearer_left, ring_pos[j - 1], ring_pos[j]), n)]
