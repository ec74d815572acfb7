"""Per-point fields that restate a point's position, kept true to the position written.

- Ouster's ``range`` (uint32, millimetres; ouster-ros' and ouster-sdk's clouds) and the ``distance`` (float, metres)
  of nebula/Autoware's ``PointXYZIRCAEDT`` (Hesai, Velodyne, Robosense drivers) are the distance the sensor measured.
  A point the chain moved along its ray to a weather particle (:class:`~roadview_noise.provenance.Effect` MOVED) or
  added on an empty ray (ADDED) gets ``|p|`` (``rint(|p| · 1000)`` for ``range``): the distance from the cloud's
  origin, which differs from the sensor's own by its beam-origin offset (−12 … +14 mm on a real OS1-128 scan);
  before, such a point kept the range of the object behind the particle (median 12.8 m off under fog 30 m) or of the
  point its other fields were copied from. A ``range`` stored in another type (a float ``range`` a conversion tool
  wrote) gets the unit its recorded points follow, millimetres or metres (:func:`_range_unit`; neither: untouched).
- ``azimuth`` and ``elevation`` (nebula's radians, or any other unit, sign and zero): an ADDED point takes the
  direction of its position in the convention the cloud's own points follow (fitted on them: ``value = k·(s·angle +
  c)``, k rad/deg/centideg, s ±1; azimuth wrapped as the recorded values are); before, it kept the angles of the
  point its other fields were copied from (up to 32° off on a real VLP-16 scan). A MOVED point stays on its ray.
  Angles that follow no such convention (fewer than 99 % of the recorded points within 0.01 rad) are not touched.
- ouster-ros' ``reflectivity`` next to its signal ``intensity`` (:func:`lidar_intensity.ouster_signal_layout`) is
  the sensor's calibrated reflectivity of the return: a MOVED or ADDED point (a weather return) gets the reading
  its own return gives, ``W·S·R²/K`` of its written signal S at its range R in the 8-bit reflectivity channel of the
  cloud's profile (:func:`lidar_intensity.reflectivity_variant`: W = 100, rounded, a faint return reads 1); before,
  a fog return kept the reflectivity of the object behind it (or of the point its fields were copied from).

- TJ4DRadSet's ``Range``, ``Alpha``, ``Beta`` and ars548_ros' ``r`` (io/radar_formats.RESTATING): recomputed for
  every point whose stored value no longer restates its position (added, moved, or turned by alignment.radar).

Every other point keeps the value it was recorded with. Fields of other names or types are not touched.
"""

from __future__ import annotations

import numpy as np

from ..types import PointCloud
from .radar_formats import restated_column

RANGE_UNITS = {"range": ("u4", 1000.0), "distance": ("f", 1.0)}   # field → (stored type, stored value per metre)
ANGLE_FIELDS = ("azimuth", "elevation")
ANGLE_UNITS = (1.0, 180.0 / np.pi, 18000.0 / np.pi)   # stored value per radian: rad, deg, centideg (Hesai packets)
ANGLE_TOLERANCE_RAD = 0.01                     # a convention holds when 99 % of the recorded points are this close
ANGLE_SAMPLE = 4096                            # recorded points the convention is fitted on (evenly strided)


def with_derived(values: np.ndarray, file_name: str, dt: str, cloud: PointCloud) -> np.ndarray:
    """``values`` of the stored field ``file_name`` with the points the chain moved or added brought up to date."""
    restated = restated_column(values, file_name, cloud)        # radar layouts' own (io/radar_formats.py)
    if restated is not None:
        return restated
    if file_name == "reflectivity":
        return _weather_reflectivity(values, cloud)
    kind = np.dtype(dt).kind
    stored = f"u{np.dtype(dt).itemsize}" if kind == "u" else kind
    fitted = file_name in RANGE_UNITS and RANGE_UNITS[file_name][0] != stored and kind in "fiu"
    if cloud.effect is None or not (RANGE_UNITS.get(file_name, ("",))[0] == stored or fitted
                                    or (file_name in ANGLE_FIELDS and kind in "fiu")):
        return values
    from ..provenance import Effect

    moved_or_added = (cloud.effect == Effect.MOVED) | (cloud.effect == Effect.ADDED)
    new = cloud.effect == Effect.ADDED if file_name in ANGLE_FIELDS else moved_or_added
    if not new.any():
        return values
    out = np.array(values, dtype=np.float64)
    p = cloud.positions_m[new]
    if file_name in RANGE_UNITS:
        per_m = _range_unit(out, cloud.positions_m, moved_or_added) if fitted else RANGE_UNITS[file_name][1]
        if per_m is None:
            return values
        r = np.linalg.norm(p, axis=1) * per_m
        out[new] = np.rint(r) if kind in "iu" else r
        return out
    recorded = np.flatnonzero(~moved_or_added & np.isfinite(out) & np.any(cloud.positions_m != 0, axis=1))
    recorded = recorded[::max(1, len(recorded) // ANGLE_SAMPLE)]
    angle = _azimuth if file_name == "azimuth" else _elevation
    convention = _convention(out[recorded], angle(cloud.positions_m[recorded]), file_name == "azimuth")
    if convention is not None:
        out[new] = convention(angle(p))
    return out


def _weather_reflectivity(values: np.ndarray, cloud: PointCloud) -> np.ndarray:
    """ouster-ros' ``reflectivity`` of the points the chain moved or added: the 8-bit calibrated reading of their
    own return (module docstring); every other cloud's field as it is."""
    from ..physics import lidar_intensity as li
    from ..provenance import Effect

    if cloud.effect is None or cloud.profile is None or not li.ouster_signal_layout(cloud.fields):
        return values
    new = (cloud.effect == Effect.MOVED) | (cloud.effect == Effect.ADDED)
    if not new.any():
        return values
    r = np.linalg.norm(cloud.positions_m[new], axis=1)
    signal = li.received_signal(np.asarray(cloud.fields["intensity"])[new], r, cloud.profile)
    channel = li.reflectivity_variant(cloud.profile)
    out = np.array(values, dtype=np.float64)
    out[new] = li.stored_intensity(li.reported_intensity(signal, r, channel), channel)
    return out


def _range_unit(values: np.ndarray, positions: np.ndarray, new: np.ndarray) -> float | None:
    """The stored value per metre of a range field stored in another type than its driver's (a ``range`` saved as
    float by a conversion tool): millimetres or metres, whichever the recorded points (not ``new``) beyond 2 m agree
    with within 2 % (median), None if neither; with fewer than 8 such points (dense fog moved them all), millimetres
    if a value exceeds 1 000 (no LiDAR reports a kilometre), else metres."""
    r = np.linalg.norm(positions, axis=1)
    far = (r > 2.0) & ~new & np.isfinite(values)
    if np.count_nonzero(far) < 8:
        finite = values[np.isfinite(values)]
        return 1000.0 if len(finite) and finite.max() > 1000.0 else 1.0
    ratio = float(np.median(values[far] / r[far]))
    return next((k for k in (1000.0, 1.0) if abs(ratio / k - 1.0) < 0.02), None)


def _azimuth(p: np.ndarray) -> np.ndarray:
    return np.arctan2(p[:, 1], p[:, 0])


def _elevation(p: np.ndarray) -> np.ndarray:
    return np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))


def _convention(values: np.ndarray, angle_rad: np.ndarray, circular: bool):
    """The map angle (rad) → stored value the recorded points follow (None: none of the candidates fits)."""
    if len(values) < 8:
        return None
    low = 0.0 if values.min() >= 0 else -np.pi                     # wrapped to [0, 2π) or [−π, π)
    for k in ANGLE_UNITS:
        for s in (1.0, -1.0):
            d = values / k - s * angle_rad
            c = float(np.angle(np.exp(1j * d).mean())) if circular else float(np.median(d))
            e = np.angle(np.exp(1j * (d - c))) if circular else d - c
            if np.percentile(np.abs(e), 99) <= ANGLE_TOLERANCE_RAD:
                if circular:
                    return lambda a, k=k, s=s, c=c: k * (np.mod(s * a + c - low, 2 * np.pi) + low)
                return lambda a, k=k, s=s, c=c: k * (s * a + c)
    return None
