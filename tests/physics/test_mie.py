"""Mie efficiencies against the oracles of models.md Appendix A / §8 and against closed-form limits."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.physics.mie import efficiencies, efficiency_table, size_parameter


@pytest.mark.parametrize("m, x, q_ext", [
    (1.33, 1.0, 0.0939), (1.33, 10.0, 2.2065), (1.33, 100.0, 2.1011), (1.33, 1000.0, 2.0163),
    (1.55, 5.213, 3.105),            # Bohren–Huffman test case (published 3.10543 at x = 5.2128)
    (1.5 + 0.1j, 3.0, 3.022),        # absorbing sphere, n + iκ
    (1.328, 3632.0, 2.0063),         # 1 mm raindrop at 865 nm (models.md §8)
])
def test_extinction_oracles(m, x, q_ext):
    q, _ = efficiencies(m, x)
    assert q == pytest.approx(q_ext, rel=1e-3)


@pytest.mark.parametrize("m, x, q_back", [(1.55, 5.213, 2.924), (1.5 + 0.1j, 3.0, 0.0971)])
def test_backscatter_oracles(m, x, q_back):
    _, q = efficiencies(m, x)
    assert q == pytest.approx(q_back, rel=2e-3)


def test_backscatter_fog_droplet_at_865nm():
    """models.md §8: Q_back(x = 36.32, m = 1.328) = 0.535, i.e. a 5 µm-radius droplet at 865 nm. Q_back swings by
    ±0.05 within Δx = ±0.002 here, so the size parameter is computed, not rounded."""
    x = size_parameter(5e-6, 865e-9)
    assert float(x) == pytest.approx(36.32, abs=0.005)
    assert efficiencies(1.328, x)[1] == pytest.approx(0.535, rel=5e-3)


def test_rayleigh_limit():
    """Small non-absorbing sphere: Q_ext = Q_sca = (8/3) x⁴ |(m² − 1)/(m² + 2)|² (Bohren & Huffman 5.8)."""
    m, x = 1.33, 0.01
    rayleigh = 8 / 3 * x ** 4 * abs((m * m - 1) / (m * m + 2)) ** 2
    assert efficiencies(m, x)[0] == pytest.approx(rayleigh, rel=1e-3)


def test_large_sphere_tends_to_two():
    q, _ = efficiencies(1.33, np.array([1e3, 1e4]))
    assert np.all(np.abs(q - 2.0) < 0.02)
    assert abs(q[1] - 2.0) < abs(q[0] - 2.0)


def test_vectorised_shape_and_size_parameter():
    x = size_parameter(np.array([[0.5e-6, 1e-6], [2e-6, 5e-6]]), 530e-9)
    assert x[0, 1] == pytest.approx(2 * np.pi * 1e-6 / 530e-9)
    q_ext, q_back = efficiencies(1.3338 + 1.448e-9j, x)
    assert q_ext.shape == q_back.shape == (2, 2)
    for i in range(2):
        for j in range(2):
            assert q_ext[i, j] == pytest.approx(efficiencies(1.3338 + 1.448e-9j, x[i, j])[0], rel=1e-12)


def test_absorbing_sign_convention_is_checked():
    with pytest.raises(ValueError):
        efficiencies(1.5 - 0.1j, 3.0)        # miepython's n − iκ must not leak into the physics API
    with pytest.raises(ValueError):
        efficiencies(1.33, 0.0)


def test_table_is_cached_and_read_only():
    grid = tuple(np.linspace(1.0, 50.0, 40))
    a = efficiency_table(1.33 + 0j, grid)
    b = efficiency_table(1.33 + 0j, grid)
    assert a[0] is b[0]
    with pytest.raises(ValueError):
        a[0][0] = 1.0
