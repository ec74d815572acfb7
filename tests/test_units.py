"""units.ray_factor: the compiled pass gives NumPy's float64 expression rounded once, bit for bit."""

import numpy as np
import pytest

from roadview_noise.units import planar_depth_to_range, ray_factor


def _numpy_ray_factor(width, height, fx, fy, cx, cy):
    u = (np.arange(width) - cx) / fx
    v = (np.arange(height) - cy) / fy
    return np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2).astype(np.float32)


@pytest.mark.parametrize("seed", range(6))
def test_ray_factor_is_numpys_expression_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    args = (int(rng.integers(1, 400)), int(rng.integers(1, 300)), *rng.uniform(20, 3000, 2),
            *rng.uniform(-200, 500, 2))
    k = ray_factor(*args)
    assert k.dtype == np.float32 and not k.flags.writeable
    np.testing.assert_array_equal(k.view(np.uint32), _numpy_ray_factor(*args).view(np.uint32))


def test_range_is_depth_times_the_ray_length():
    """A pixel at (u, v) with planar depth z lies at range z·sqrt(1 + x² + y²), x, y its normalised coordinates."""
    z = np.full((3, 4), 10.0, np.float32)
    r = planar_depth_to_range(z, fx=2.0, fy=4.0, cx=0.0, cy=0.0)
    assert r[0, 0] == pytest.approx(10.0)
    assert r[2, 3] == pytest.approx(10.0 * np.sqrt(1 + (3 / 2) ** 2 + (2 / 4) ** 2), rel=1e-6)
