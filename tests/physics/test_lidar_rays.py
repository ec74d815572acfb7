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
