"""cloud_rays on some points only (``at``): the same rays and receiver as on the whole cloud."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roadview_noise.physics.lidar_intensity import REFLECTIVITY, SIGNAL
from roadview_noise.physics.lidar_rays import cloud_rays
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.types import PointCloud


@pytest.mark.parametrize("kind", [SIGNAL, REFLECTIVITY])
def test_rays_at_some_points_match_the_whole_cloud(kind):
    rng = np.random.default_rng(3)
    n = 5000
    pos = rng.normal(0, 20, (n, 3))
    pos[rng.random(n) < 0.05] = 0.0                                    # no return
    intensity = np.round(rng.uniform(0, 300, n)).astype(np.float32)
    intensity[rng.random(n) < 0.01] = 0.0                              # stored zeros: faint returns
    intensity[np.argmax(np.linalg.norm(pos, axis=1))] = 1.0            # the weakest return sets the threshold
    cloud = PointCloud(pos, {"intensity": intensity}, "lidar", dataclasses.replace(os1_128(), intensity_kind=kind))
    whole = cloud_rays(cloud, "m", "ignore")
    at = np.sort(rng.choice(n, 700, replace=False))
    some = cloud_rays(cloud, "m", "ignore", at=at)
    for name in ("range_m", "signal", "has_target"):
        assert np.array_equal(getattr(some, name), getattr(whole, name)[at]), name
    assert some.threshold == whole.threshold and some.notes == whole.notes
    # the threshold comes from every point, not from the subset
    assert cloud_rays(cloud, "m", "ignore", at=at[:5]).threshold == whole.threshold
    recorded = dataclasses.replace(cloud, fields={"intensity": intensity * 0.5})
    later = dataclasses.replace(cloud, recorded=recorded)
    assert cloud_rays(later, "m", "ignore", at=at).threshold == cloud_rays(later, "m", "ignore").threshold
    with pytest.raises(ValueError):
        cloud_rays(cloud, "m", "fill", at=at)


@pytest.mark.parametrize("kind", [SIGNAL, REFLECTIVITY])
def test_a_lists_rays_from_its_firing_grid_pass_match_its_points_alone(kind):
    """With ``empty_rays: fill`` a list's ranges come from its firing grid's pass over the points: its points' rays
    and receiver are those of ``ignore`` (ranges from the positions), zero points and returns closer than the
    profile's minimum range included."""
    rng = np.random.default_rng(5)
    profile = dataclasses.replace(os1_128(), intensity_kind=kind, sensor_z_offset_m=0.0, beam_origin_offset_m=0.0,
                                  min_range_m=1.0)
    columns = 256
    ring, col = np.nonzero(rng.random((profile.channels, columns)) < 0.7)
    el = np.deg2rad(np.asarray(profile.beam_elevation_deg))[ring]
    az = 0.3 - 2 * np.pi * col / columns - np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring]
    r = rng.uniform(2, 80, len(ring))
    r[rng.random(len(r)) < 0.02] = 0.5 * profile.min_range_m                   # too close: no return
    pos = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1) * r[:, None]
    pos[rng.random(len(r)) < 0.03] = 0.0                                        # zero points
    intensity = np.round(rng.uniform(0, 200, len(r))).astype(np.float32)
    cloud = PointCloud(pos, {"intensity": intensity}, "lidar", profile)
    filled, alone = cloud_rays(cloud, "m", "fill"), cloud_rays(cloud, "m", "ignore")
    n = len(cloud)
    assert filled.listed is not None and filled.listed.columns == columns and len(filled.range_m) > n
    for name in ("range_m", "signal", "has_target"):
        assert np.array_equal(getattr(filled, name)[:n], getattr(alone, name)), name
    assert filled.threshold == alone.threshold and filled.notes == alone.notes
