"""The strongest-return sampler (physics/lidar_strongest.py) against main's before round 13
(tests/physics/reference_strongest.py, with main's float64 tables, exactly evaluated backgrounds and three uniforms
per receiver decision): the package draws each ray's head a ray ahead (its random draws in another order), reads
its Λ, range-quantile and cover tables as float32, a cluster peak's background from the uncut windows (within 3e-4
of the level's largest background) and splits one uniform into the receiver's three
(:func:`lidar_detection.three_uniforms`); the law of the returns must not change.

Rain at 20 and 100 mm/h, snow at 0.5, 2.5 and 10 mm/h, on a 1 × 8000 OS1-128 range image (targets of 2–90 %
reflectance at 2–60 m on three rays in four, sky on the rest), 16 frames per sampler (seeds 0–15, the same for
both; the samplers' draws differ):
- per outcome (no return / target / weather return) and ray group (sky; targets below and above 20 m, faint and
  bright), a χ² test of homogeneity of the two tables of counts, p > 0.001;
- ranges and signals of the weather returns, signals of the targets kept: two-sample Kolmogorov–Smirnov, p > 0.001;
- the particles drawn: the same mean within 4 Poisson SDs;
- the number of weather returns and of targets kept within 4 binomial SDs, the mean range and signal of the
  weather returns and the mean signal of the targets kept within 4 standard errors (a bias of a mean that the
  rank tests above miss).
Its power: rain at 22 against 20 mm/h fails it (χ² p = 1.4e-4, particles 6.1 SDs apart); snow at 2.6 against
2.5 mm/h gives p = 0.005–0.05.
The first return does not use this sampler (it draws every particle, :func:`lidar_particles.sample_particles`)."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.models.lidar.rain import RainLidar
from roadview_noise.models.lidar.snow import SnowLidar
from roadview_noise.physics import lidar_echo, lidar_particles, lidar_strongest
from roadview_noise.physics.lidar_medium import pulse_length_m
from roadview_noise.physics.lidar_particles import Beam
from tests.physics import reference_strongest
from tests.physics.test_lidar_strongest import _scan_rays, assert_same_law, ray_groups, tally

FRAMES = 16


def _table_arguments(rays, model):
    """(medium, beam, base level, pulse length) of the strongest return's tables."""
    medium, beam = model.medium(), Beam.of(rays.profile)
    length = float(pulse_length_m(rays.profile.pulse_half_power_width_s))
    level, _ = lidar_particles.draw_level(medium, beam, rays.threshold, model.draw_fraction_of_threshold, length)
    return medium, beam, float(level), length


def _frames(rays, model, group):
    """:func:`tally` of FRAMES frames of the package's sampler (seeds 0 … FRAMES − 1)."""
    medium, beam, level, _ = _table_arguments(rays, model)
    return tally([lidar_strongest.strongest_returns(np.random.default_rng(seed), rays, medium, beam, level)
                  for seed in range(FRAMES)], group)


@pytest.mark.parametrize("model", [RainLidar(rain_rate_mm_per_h=20.0), RainLidar(rain_rate_mm_per_h=100.0),
                                   SnowLidar(snowfall_rate_mm_per_h=0.5), SnowLidar(snowfall_rate_mm_per_h=2.5),
                                   SnowLidar(snowfall_rate_mm_per_h=10.0)],
                         ids=["rain20", "rain100", "snow0.5", "snow2.5", "snow10"])
def test_sampler_has_the_law_of_mains(model, monkeypatch):
    """Module doc: the package's sampler and main's give the same law of outcomes, ranges and intensities."""
    rays = _scan_rays(8000)
    group = ray_groups(rays, model.medium())
    package = _frames(rays, model, group)
    monkeypatch.setattr(lidar_strongest, "TABLE_DTYPE", np.float64)         # main's tables
    tables = lidar_strongest.brightest_tables.uncached(*_table_arguments(rays, model))
    monkeypatch.setattr(lidar_strongest, "brightest_tables", lambda *args: tables)
    monkeypatch.setattr(lidar_strongest, "_strongest", reference_strongest._strongest)
    main = _frames(rays, model, group)
    assert_same_law(package, main)
    assert_same_means(package, main, len(rays.range_m) * FRAMES)


def assert_same_means(a, b, rays: int, sds: float = 4.0) -> None:
    """Two :func:`tally` s of ``rays`` rays in all: the weather returns and the targets kept as many within
    ``sds`` binomial SDs, the weather returns' mean range and signal and the kept targets' mean signal within
    ``sds`` standard errors of their difference."""
    for outcome in (lidar_echo.WEATHER, lidar_echo.TARGET):
        n_a, n_b = a[0][outcome].sum(), b[0][outcome].sum()
        p = (n_a + n_b) / (2 * rays)
        assert abs(n_a - n_b) < sds * np.sqrt(2 * rays * p * (1 - p)), outcome
    for x, y in zip(a[1:4], b[1:4]):
        assert abs(x.mean() - y.mean()) < sds * np.sqrt(x.var() / len(x) + y.var() / len(y))
