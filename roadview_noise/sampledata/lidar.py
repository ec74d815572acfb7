"""Spinning-LiDAR scan of the sample drive with the profile's exact beam geometry (models.md §3.0, §3.1).

Sensor frame: x forward, y left, z up, origin at the sensor reference point (for Ouster the "sensor" frame: the beam
origins lie ``sensor_z_offset_m`` above it, ``beam_origin_offset_m`` off the rotation axis). Columns: the head turns
clockwise seen from above; column j has encoder angle ``2π j / W``; beam r of column j points at azimuth
``−(2π j / W + α_r)`` (counter-clockwise from +x) and elevation ``ω_r`` (Ouster SDK convention, which the Velodyne
table shares once its clockwise-from-forward azimuths are expressed in this frame). Its origin is
``(n cos θ_j, n sin θ_j, z_off)`` with θ_j = −2π j / W. Rays are cast from the sensor pose at the frame time (an
instantaneous, i.e. motion-compensated, scan); ``time_s`` is the nominal firing time of the column within a 0.1 s
revolution.

Intensity: the Lambertian LiDAR equation, received signal ``S = K ρ cos θ / R²`` (§3.1) with the profile's sensor
constant K (signal of a ρ = 1 target at 1 m), stored as the profile's intensity kind
(:func:`lidar_intensity.reported_intensity`: OS1 ``signal`` photons ``I = S``; VLS calibrated 8-bit reflectivity
``I = W · S R² / K = W ρ cos θ`` with the white reading W = 110 of the VLS-128), rounded for count units, clipped to
full scale. Returns whose stored intensity reads below the detection threshold (:func:`received_signal`) or beyond
max range are no-returns, so every stored point is detectable under its own profile.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..physics.lidar_intensity import received_signal, reported_intensity, sensor_constant
from ..types import IntensityUnit, LidarProfile, PointCloud
from .scene import Snapshot, surface_properties

REVOLUTION_S = 0.1


@lru_cache(maxsize=8)
def beam_rays(profile: LidarProfile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cell (rings, columns): ray origins (…, 3) and unit directions (…, 3) in the sensor frame, and the column
    firing times (columns,) in seconds."""
    w = profile.columns
    enc = 2 * np.pi * np.arange(w) / w
    az = np.radians(np.asarray(profile.beam_azimuth_offset_deg))[:, None]
    el = np.radians(np.asarray(profile.beam_elevation_deg))[:, None]
    heading = -(enc[None, :] + az)
    d = np.stack([np.cos(el) * np.cos(heading), np.cos(el) * np.sin(heading),
                  np.broadcast_to(np.sin(el), heading.shape)], axis=-1)
    n = profile.beam_origin_offset_m
    o = np.stack([n * np.cos(-enc), n * np.sin(-enc), np.full(w, profile.sensor_z_offset_m)], axis=-1)
    o = np.broadcast_to(o[None], d.shape).copy()
    for a in (o, d):
        a.setflags(write=False)
    return o, d, REVOLUTION_S * np.arange(w) / w


@dataclass(frozen=True)
class Scan:
    """A full rings × columns scan in the sensor frame; ``valid`` marks cells with a return."""

    positions_m: np.ndarray       # (C, W, 3), zero where not valid
    intensity: np.ndarray         # (C, W), profile unit, zero where not valid
    valid: np.ndarray             # (C, W) bool
    time_s: np.ndarray            # (W,)
    profile: LidarProfile


def scan(snapshot: Snapshot, profile: LidarProfile, sensor_origin_m: np.ndarray) -> Scan:
    """Ray-cast every beam of every column once (one ``cast_rays`` call)."""
    o, d, t_col = beam_rays(profile)
    shape = d.shape[:2]
    hits = snapshot.cast((sensor_origin_m + o).reshape(-1, 3), d.reshape(-1, 3))
    rng_m = hits.t_m
    ok = hits.hit & (rng_m + profile.beam_origin_offset_m <= profile.max_range_m)
    p_local = o.reshape(-1, 3) + np.where(ok, rng_m, 0.0)[:, None] * d.reshape(-1, 3)
    _, rho = surface_properties(sensor_origin_m + p_local, hits)
    cos_inc = np.abs(np.sum(hits.normal * d.reshape(-1, 3), axis=-1))
    r = np.where(ok, rng_m, 1.0)
    intensity = reported_intensity(sensor_constant(profile) * rho * cos_inc / r**2, r, profile)
    if profile.intensity_unit != IntensityUnit.UNIT:
        intensity = np.rint(intensity)
    intensity = np.minimum(intensity, profile.intensity_full_scale)
    ok &= received_signal(intensity, r, profile) >= profile.detection_threshold
    positions = np.where(ok[:, None], p_local, 0.0).reshape(*shape, 3)
    return Scan(positions, np.where(ok, intensity, 0.0).reshape(shape), ok.reshape(shape), t_col, profile)


def to_cloud(s: Scan, *, grid: bool) -> PointCloud:
    """The scan as a point cloud: returns only (row-major over ring, column), or the full grid with no-return
    cells all-zero except their ring (as ``PointCloud.drop`` leaves them)."""
    rings = np.broadcast_to(np.arange(s.valid.shape[0], dtype=np.uint16)[:, None], s.valid.shape)
    time_s = np.broadcast_to(s.time_s[None, :], s.valid.shape)
    fields = {"intensity": s.intensity.astype(np.float32), "ring": rings.copy(),
              "time_s": np.where(s.valid, time_s, 0.0)}
    if grid:
        return PointCloud(s.positions_m.reshape(-1, 3), {k: v.reshape(-1) for k, v in fields.items()}, "lidar",
                          s.profile, grid_shape=s.valid.shape)
    m = s.valid
    return PointCloud(s.positions_m[m], {k: v[m] for k, v in fields.items()}, "lidar", s.profile)
