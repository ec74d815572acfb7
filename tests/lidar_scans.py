"""Synthetic spinning-LiDAR scans for tests: every ray of a firing grid hits a surface at a given range and
reflectance (a sphere around the sensor unless ranges vary), as a full grid or as a point list with rings."""

from __future__ import annotations

import dataclasses

import numpy as np

from roadview_noise.physics.lidar_intensity import COUNT_UNITS, reported_intensity, sensor_constant, stored_intensity
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.types import LidarProfile, PointCloud


def scan(profile: LidarProfile | None = None, *, columns: int = 512, range_m=10.0, reflectance=0.2,
         grid: bool = False) -> PointCloud:
    """A ``channels × columns`` scan: ray (ring b, column c) points at azimuth ``−(2π c/W + α_b)`` and elevation ω_b;
    ``range_m`` and ``reflectance`` are scalars or (channels, columns) arrays (range 0: no return); intensity is the
    profile's stored reading of ``S = K ρ / R²`` (normal incidence on a sphere; counts as uint16). Grid: every cell, no-returns zero; list:
    the returns only, ring field set."""
    profile = dataclasses.replace(profile or os1_128(), columns=columns)
    ch = profile.channels
    ring = np.repeat(np.arange(ch), columns)
    col = np.tile(np.arange(columns), ch)
    az = -(2 * np.pi * col / columns + np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring])
    el = np.deg2rad(np.asarray(profile.beam_elevation_deg))[ring]
    r = np.broadcast_to(np.asarray(range_m, dtype=np.float64), (ch, columns)).reshape(-1)
    rho = np.broadcast_to(np.asarray(reflectance, dtype=np.float64), (ch, columns)).reshape(-1)
    direction = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    pos = r[:, None] * direction
    with np.errstate(divide="ignore", invalid="ignore"):
        signal = np.where(r > 0, sensor_constant(profile) * rho / (r * r), 0.0)
    reading = stored_intensity(reported_intensity(signal, r, profile), profile)
    intensity = (np.minimum(reading, profile.intensity_full_scale).astype(np.uint16)
                 if profile.intensity_unit in COUNT_UNITS else reading.astype(np.float32))
    keep = np.ones(len(r), dtype=bool) if grid else r > 0
    return PointCloud(pos[keep], {"intensity": intensity[keep], "ring": ring[keep].astype(np.uint16)}, "lidar",
                      profile, grid_shape=(ch, columns) if grid else None)
