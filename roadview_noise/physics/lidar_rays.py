"""The cloud → rays stage of the LiDAR weather pipeline: every ray a weather model acts on, with its hard-target
range and received signal, the rays that saw nothing (``empty_rays``), and the receiver that decides detections
(its threshold calibrated from the recorded returns when the datasheet's lies above them, or the datasheet's with
each recorded return counted at least at :meth:`receiver.Receiver.recorded_floor` when the profile's readings are not
radiometric at their low end, ``threshold_calibration``: :mod:`receiver`).

``empty_rays`` — which rays without a return get weather:
- ``fill`` (default): every no-return ray, for raw sensor output — a full grid's no-return cells, a point list's empty
  cells of its firing grid (:mod:`firing_grid`, measured from the list). A ray that saw nothing in clear weather
  can see fog or a snowflake.
- ``sky_only``: only no-return rays above the horizon (beam elevation > 0). For pre-processed clouds whose returns
  below the horizon were removed (ground segmentation, a z or height filter, a road mask): their empty cells below
  the horizon are removed returns, not rays that saw nothing, and must not be filled as sky. Above the horizon a
  no-return ray is sky (or beyond range) in any cloud.
- ``ignore``: only the input's returns. For clouds where emptiness means nothing (range crops, merged or
  motion-compensated clouds, accumulated maps), or to keep the point count.
A point list's rays need its rings (:func:`lidar_geometry.ring_index`): the cloud's ``ring`` field, else the ring an
earlier step stored before it moved the points (``attributes['ring']``: alignment, power), else recovered from the
elevations.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import ModelError
from ..types import LidarProfile, PointCloud
from .compiled import jit
from .firing_grid import FiringGrid, firing_grid, list_points
from .lidar_geometry import ring_index, ring_source
from .lidar_intensity import REFLECTIVITY, IntensityWarning, chain_intensity_scale, intensity_step, sensor_constant, \
    white_reading
from .reading_population import population_signal, uninformative
from .receiver import THRESHOLD_CALIBRATIONS, Receiver

EMPTY_RAYS = ("fill", "sky_only", "ignore")     # what a weather model does with rays that returned nothing


@dataclass(frozen=True, eq=False)
class Rays:
    """The rays of a cloud as a weather model sees them: one per point of the cloud, then (point lists) one per
    empty cell of the list's firing grid (``listed``).

    ``range_m``: hard-target range, the profile's max range on empty rays, 0 on rays without a direction (zero points
    of a point list; no-return rays that ``empty_rays`` leaves out). ``signal``: received signal of the target in
    units of the sensor constant K (m⁻², :func:`lidar_intensity.received_signal` / K) that its stored value stands
    for. ``receiver``: detection in units of K, calibrated from the data (:meth:`receiver.Receiver.calibrated`);
    ``datasheet_threshold``: the profile's threshold / K. ``floor``: the signal a recorded return counts as at least
    in the weather's decisions (0 unless the profile's ``threshold_calibration`` is ``datasheet``); ``unread``: the
    signal those decisions take instead of :attr:`signal` (:attr:`decision_signal`; None: the signal itself).
    ``profile``: the one the intensities are read with (:func:`lidar_intensity.resolve_profile`).
    ``notes``: what the manifest records about both."""

    range_m: np.ndarray
    signal: np.ndarray
    has_target: np.ndarray
    receiver: Receiver
    datasheet_threshold: float
    profile: LidarProfile
    listed: FiringGrid | None = None
    empty_source: str = ""
    notes: dict = dataclasses.field(default_factory=dict)
    floor: float = 0.0
    unread: np.ndarray | None = None

    @property
    def threshold(self) -> float:
        """The detection threshold in use (units of K)."""
        return self.receiver.threshold

    @property
    def decision_signal(self) -> np.ndarray:
        """The signal the weather's and ray drop's decisions take for each ray's target: :attr:`signal`, or, for a
        return whose reading carries no radiometric information, what the scan's other readings at its range say, at
        least :attr:`floor` (it was detected: :mod:`reading_population`)."""
        return self.signal if self.unread is None else self.unread

    @property
    def n_points(self) -> int:
        """Rays that are points of the input cloud (the first ``n_points`` rays)."""
        return len(self.range_m) - (0 if self.listed is None else len(self.listed.ring))

    @property
    def empty(self) -> np.ndarray:
        """Rays without a target that can still return weather (no-return cells of a grid or a list)."""
        return ~self.has_target & (self.range_m > 0)

    @property
    def faint(self) -> np.ndarray:
        """Per point of the input (the first :attr:`n_points` rays; the others have no target): whether it is a return
        whose signal lies below the profile's datasheet threshold — the sensor was more sensitive than the datasheet
        (the threshold is then calibrated from them)."""
        n = self.n_points
        return self.has_target[:n] & (self.signal[:n] < self.datasheet_threshold)

    @property
    def below_threshold(self) -> int:
        """How many :attr:`faint` returns there are (diagnostic ``below_threshold_in``)."""
        return int(np.count_nonzero(self.faint))


def cloud_rays(cloud: PointCloud, model_id: str, empty_rays: str = "fill", calibrate: bool = True,
               at: np.ndarray | None = None) -> Rays:
    """Validate a LiDAR cloud for a weather model and return its rays (signals in units of K).

    Intensities are read with :func:`lidar_intensity.chain_intensity_scale` (the chain's input decides the unit; a
    warning is printed once per process and kept in ``notes``); rays without a return get the profile's max range as
    ``empty_rays`` says (module doc), a point list's empty rays appended after its points (a list without a regular
    firing grid keeps only its points, and ``empty_source`` says why); the receiver's threshold is calibrated below
    the weakest return of the cloud as recorded (``cloud.recorded``: earlier steps' intensity noise does not make the
    sensor more sensitive), or with the profile's ``threshold_calibration: datasheet`` kept, the returns then
    counting at least the receiver's :attr:`~receiver.Receiver.recorded_floor` (``Rays.floor``); ``calibrate=False``
    keeps the datasheet receiver (ray drop) and does not read the recorded cloud. ``at`` (indices; only with
    ``empty_rays="ignore"``): the rays of those points only, the receiver still calibrated on the whole cloud (a step
    that changes a few points does not write every point's signal)."""
    profile = cloud.profile
    if cloud.sensor != "lidar" or not isinstance(profile, LidarProfile):
        raise ModelError("needs a LiDAR point cloud with a LidarProfile (intensity unit, kind, sensor constant, "
                         "threshold)", model=model_id)
    if "intensity" not in cloud.fields:
        raise ModelError("needs an intensity field (the LiDAR equation scales weather returns by it)",
                         model=model_id, field="intensity")
    if empty_rays not in EMPTY_RAYS:
        raise ModelError(f"empty_rays {empty_rays!r} is not one of {EMPTY_RAYS}", model=model_id, field="empty_rays")
    if profile.threshold_calibration not in THRESHOLD_CALIBRATIONS:
        raise ModelError(f"threshold_calibration {profile.threshold_calibration!r} is not one of "
                         f"{THRESHOLD_CALIBRATIONS}", model=model_id, field="threshold_calibration")
    if at is not None and empty_rays != "ignore":
        raise ValueError("the rays of some points only (at) have no empty rays: use empty_rays='ignore'")
    intensity = np.asarray(cloud.fields["intensity"])
    positions = np.ascontiguousarray(cloud.positions_m, dtype=np.float64)
    scale = chain_intensity_scale(cloud, model_id)
    if scale.warning:
        warnings.warn(scale.warning, IntensityWarning, stacklevel=3)
    profile = scale.profile
    k = sensor_constant(profile)
    if not (profile.detection_threshold > 0 and k > 0):
        raise ModelError(f"profile {profile.name!r} has detection_threshold {profile.detection_threshold} and sensor "
                         f"constant {k}; both must be > 0 (signal units)", model=model_id, field="detection_threshold")
    compensated = profile.intensity_kind == REFLECTIVITY
    fill = empty_rays != "ignore"
    grid = cloud.grid_shape is not None
    per_reading = 1.0 / white_reading(profile) if compensated else 1.0 / k
    listed = points = None
    if fill and not grid:                               # a list's firing grid first: its empty rays come with the
        points = list_points(cloud, profile)            # points' arrays, its pass over the points gives their ranges
        listed = firing_grid(cloud, profile, points=points)
        if not isinstance(listed, str) and empty_rays == "sky_only":
            listed = listed.subset(listed.elevation_rad()[listed.ring] > 0)
    m = 0 if listed is None or isinstance(listed, str) else len(listed.ring)
    n = len(intensity)
    if at is None:
        r, signal, has_target, weakest = _ray_signals(positions, intensity, compensated, per_reading,
                                                      profile.max_range_m if grid and fill else 0.0,
                                                      intensity_step(profile), profile.min_range_m,
                                                      _NO_RANGES if points is None else points.range_m, m,
                                                      profile.max_range_m)
    else:
        r, signal, has_target, _ = _point_signals(positions[at], intensity[at], compensated, per_reading,
                                                  intensity_step(profile), profile.min_range_m)
    recorded = cloud.recorded
    datasheet = profile.threshold_calibration == "datasheet"
    if not calibrate or datasheet:
        weakest = math.inf
    elif (recorded is not None and "intensity" in recorded.fields      # (the chain's first step: the same arrays)
          and not (recorded.positions_m is cloud.positions_m and recorded.fields["intensity"] is intensity)):
        weakest = _point_signals(np.ascontiguousarray(recorded.positions_m, dtype=np.float64),
                                 np.asarray(recorded.fields["intensity"]), compensated, per_reading,
                                 intensity_step(profile), profile.min_range_m)[3]
    elif at is not None:
        weakest = _weakest_signal(positions, intensity, compensated, per_reading, intensity_step(profile),
                                  profile.min_range_m)
    try:
        receiver = Receiver.of(profile, k).calibrated(weakest)
    except ValueError as e:
        raise ModelError(str(e), model=model_id, field="receiver") from None
    notes = {"intensity_reading": scale.note, "detection_threshold": receiver.threshold * k,
             "detection_threshold_source": receiver.source}
    floor = receiver.recorded_floor if datasheet else 0.0
    unread = None
    if datasheet:
        all_r, all_signal, all_has = (r[:n], signal[:n], has_target[:n]) if at is None else _point_signals(
            positions, intensity, compensated, per_reading, intensity_step(profile), profile.min_range_m)[:3]
        unknown = uninformative(all_signal, all_has, intensity, floor)          # (the population: the whole cloud)
        unread = population_signal(all_signal, all_r, all_has, unknown, floor)
        if at is not None:
            unread, unknown = unread[at], unknown[at]
        notes["detection_threshold_source"] = (
            f"datasheet (threshold_calibration: datasheet, the readings' low end is not radiometric); "
            f"{np.count_nonzero(unknown)} recorded returns read 0 or below {floor * k:.4g} (what a return detected at "
            f"the threshold measures on average) and count as the median reading of the scan's other returns at their "
            f"range, at least that, in the weather's and ray drop's decisions")
    if scale.warning:
        notes["intensity_warning"] = scale.warning
    if grid and empty_rays == "sky_only":
        r[~has_target & ~_above_horizon(cloud, profile)] = 0.0
    if unread is not None and m:
        unread = np.concatenate([unread, np.zeros(m)])
    if isinstance(listed, str):
        source = f"none: {listed}"
    elif listed is not None:
        source = listed.describe() + ("; above the horizon" if empty_rays == "sky_only" else "")
    else:
        source = ("none (empty_rays: ignore)" if not fill else "no-return cells of the grid" +
                  (" above the horizon" if empty_rays == "sky_only" else ""))
    return Rays(r, signal, has_target, receiver, profile.detection_threshold / k, profile,
                listed=None if isinstance(listed, str) else listed, empty_source=source, notes=notes, floor=floor,
                unread=unread)


def _above_horizon(cloud: PointCloud, profile: LidarProfile) -> np.ndarray:
    """Per cell of a full grid: whether its beam points above the horizon (ring: the cloud's field or attribute, else
    the row)."""
    elevation = np.asarray(profile.beam_elevation_deg)
    if ring_source(cloud) != "elevation":
        ring = ring_index(cloud, profile)
    else:
        rows, cols = cloud.grid_shape
        if rows != profile.channels:
            raise ModelError(f"a {rows}-row grid without a ring field does not fit the {profile.channels} beams of "
                             f"profile {profile.name!r}")
        ring = np.repeat(np.arange(rows), cols)
    return elevation[ring] > 0


_NO_RANGES = np.zeros(0)


def _point_signals(positions, intensity, compensated, scale, step, min_range_m):
    """:func:`_ray_signals` of points alone (0 range where a point is no return)."""
    return _ray_signals(positions, intensity, compensated, scale, 0.0, step, min_range_m, _NO_RANGES, 0, 0.0)


@jit(error_model="numpy")
def _ray_signals(positions, intensity, compensated, scale, empty_range_m, step, min_range_m, ranges, empty,
                 listed_range_m):  # pragma: no cover
    """Per point: range (``empty_range_m`` where the point is zero or a no-return placeholder closer than the
    profile's ``min_range_m``), received signal in units of K that the stored value stands for
    (:func:`_point_signal`; 0 without a return) and whether it is a return; and the weakest signal any return can
    have. ``ranges``: the points' ranges if known (0: no return), else empty; then ``empty`` rays without a target
    at ``listed_range_m`` (a list's empty cells)."""
    n = len(intensity)
    r = np.empty(n + empty)
    signal = np.empty(n + empty)
    has = np.empty(n + empty, np.bool_)
    weakest = math.inf
    if len(ranges) == 0:                               # one pass over the positions
        for i in range(n):
            ri = math.sqrt(positions[i, 0] ** 2 + positions[i, 1] ** 2 + positions[i, 2] ** 2)
            has[i] = ri > 0 and ri >= min_range_m
            if has[i]:
                r[i] = ri
                signal[i], low = _point_signal(ri, intensity[i], compensated, scale, step)
                if low < weakest:
                    weakest = low
            else:
                r[i] = empty_range_m
                signal[i] = 0.0
    else:                                              # the ranges known: without branches (vectorised), the
        lows = np.empty(n)                             # weakest apart
        for i in range(n):
            ri = ranges[i]
            h = ri > 0 and ri >= min_range_m
            value, low = _point_signal(ri, intensity[i], compensated, scale, step)
            has[i] = h
            r[i] = ri if h else empty_range_m
            signal[i] = value if h else 0.0
            lows[i] = low if h else math.inf
        for low in lows:
            if low < weakest:
                weakest = low
    r[n:] = listed_range_m
    signal[n:] = 0.0
    has[n:] = False
    return r, signal, has, weakest


@jit
def _weakest_signal(positions, intensity, compensated, scale, step, min_range_m):       # pragma: no cover
    """The weakest signal any return of the points can have (:func:`_ray_signals`' last value alone)."""
    weakest = math.inf
    for i in range(len(intensity)):
        ri = math.sqrt(positions[i, 0] ** 2 + positions[i, 1] ** 2 + positions[i, 2] ** 2)
        if ri > 0 and ri >= min_range_m:
            low = _point_signal(ri, intensity[i], compensated, scale, step)[1]
            if low < weakest:
                weakest = low
    return weakest


@jit(inline="always")
def _point_signal(ri, stored, compensated, scale, step):       # pragma: no cover - compiled
    """(signal, weakest signal) of a return at range ``ri`` > 0 with the stored value: ``I·scale`` or,
    range-compensated, ``I·scale / R²``; the weakest is its stored value minus half a ``step``, at least half the
    value (a reading of one step can be half a step; continuous values: the value). A stored 0 (a sensor that writes
    faint returns as 0) stands for a quarter step and can be an eighth: it was detected."""
    value = float(stored)
    low = max(value - 0.5 * step, 0.5 * value)
    if value <= 0.0 and step > 0.0:
        value = 0.25 * step
        low = 0.125 * step
    per = scale / (ri * ri) if compensated else scale
    return value * per, low * per
