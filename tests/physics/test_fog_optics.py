"""Per-channel camera fog extinction (models.md §2.1, §8): corrected and reference tables, interpolation in V."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roadview_noise.physics.atmosphere import LN_MOR
from roadview_noise.physics.cfa import CHANNEL_WAVELENGTH_M, WATER_INDEX
from roadview_noise.physics.dsd import CE_FOG_LOGNORMAL, lognormal_fog
from roadview_noise.physics.fog_optics import (FOG_RADIUS_GRID_UM, REFERENCE_FOG_EXTINCTION_PER_M,
                                               ce_extinction_table, fog_extinction_per_m,
                                               mie_extinction_table)
from roadview_noise.physics.mie import efficiencies

# models.md §2.1 oracle (correct size parameter), B, G, R order as printed there
CORRECTED_BGR = {10.0: (0.2748, 0.2770, 0.2792), 20.0: (0.1381, 0.1393, 0.1405),
                 30.0: (0.0968, 0.0977, 0.0986), 50.0: (0.0651, 0.0659, 0.0666)}


def test_corrected_extinction_at_30_m_matches_models_md_section_8():
    sigma_rgb = fog_extinction_per_m(30.0, "corrected")
    np.testing.assert_allclose(sigma_rgb[::-1], [0.0968, 0.0977, 0.0986], rtol=0.01)


@pytest.mark.parametrize("visibility_m", sorted(CORRECTED_BGR))
def test_corrected_table_all_visibilities(visibility_m):
    np.testing.assert_allclose(fog_extinction_per_m(visibility_m, "corrected")[::-1], CORRECTED_BGR[visibility_m],
                               rtol=0.01)


def test_grid_is_the_d34_grid():
    """199 radii 0.1–10 µm; droplets inside it at 30 m: 2742.4 cm⁻³ of N = 2754.154 (models.md §2.1)."""
    r = np.asarray(FOG_RADIUS_GRID_UM)
    assert r.size == 199 and r[0] == pytest.approx(0.1) and r[-1] == pytest.approx(10.0)
    assert np.trapezoid(lognormal_fog(r, *CE_FOG_LOGNORMAL[30.0]), r) == pytest.approx(2742.4, rel=1e-3)


def test_reference_table_is_the_shipped_table_and_comes_from_the_halved_size_parameter():
    """The D3.5 values are reproduced by Mie with x = π r/λ (radius passed as diameter, models.md §7.2):
    an independent recomputation of the reference bug."""
    vis, sigma = ce_extinction_table("reference")
    for i, v in enumerate(vis):
        assert tuple(sigma[i]) == REFERENCE_FOG_EXTINCTION_PER_M[v]
        r = np.asarray(FOG_RADIUS_GRID_UM)
        for c, (lam, m) in enumerate(zip(CHANNEL_WAVELENGTH_M, WATER_INDEX)):
            q_ext, _ = efficiencies(m, math.pi * r * 1e-6 / lam)
            halved = np.trapezoid(math.pi * r ** 2 * q_ext * lognormal_fog(r, *CE_FOG_LOGNORMAL[v]), r) * 1e-6
            assert sigma[i, c] == pytest.approx(halved, rel=5e-3)
    np.testing.assert_allclose(fog_extinction_per_m(30.0, "reference"), (0.1061, 0.1043, 0.1024))


def test_reference_is_about_six_percent_higher():
    ratio = fog_extinction_per_m(30.0, "reference") / fog_extinction_per_m(30.0, "corrected")
    assert np.all((ratio > 1.04) & (ratio < 1.09))


def test_channel_order_red_extinguished_most():
    for v in (10.0, 25.0, 50.0):
        r, g, b = fog_extinction_per_m(v)
        assert r > g > b


def test_black_target_at_visibility_keeps_five_percent():
    """MOR definition: a black target at d = V keeps 5 % contrast; the CE distributions at 30 m give 0.05 ± 0.005."""
    t = np.exp(-fog_extinction_per_m(30.0) * 30.0)
    assert np.all(np.abs(t - 0.05) <= 0.005)
    assert np.all(np.abs(fog_extinction_per_m(30.0) * 30.0 - LN_MOR) < 0.1)


def test_interpolation_in_log_visibility_and_held_ends():
    vis, sigma = ce_extinction_table("corrected")
    sv = sigma * vis[:, None]
    # between 20 and 30 m: σ·V lies between the neighbours, at the log-midpoint it is their mean
    v_mid = math.sqrt(20.0 * 30.0)
    np.testing.assert_allclose(fog_extinction_per_m(v_mid) * v_mid, 0.5 * (sv[1] + sv[2]), rtol=1e-12)
    # outside 10–50 m, σ·V is held
    np.testing.assert_allclose(fog_extinction_per_m(5.0) * 5.0, sv[0], rtol=1e-12)
    np.testing.assert_allclose(fog_extinction_per_m(200.0) * 200.0, sv[-1], rtol=1e-12)
    # denser fog, more extinction
    vs = np.geomspace(3.0, 300.0, 40)
    assert np.all(np.diff([fog_extinction_per_m(v)[1] for v in vs]) < 0)


def test_bad_inputs():
    with pytest.raises(ValueError):
        fog_extinction_per_m(0.0)
    with pytest.raises(ValueError):
        fog_extinction_per_m(30.0, "shipped")


def test_stored_corrected_table_is_the_mie_computation():
    """The stored table equals the Mie integrals over the CE distributions (rtol 1e-12: a newer miepython may move
    the last bits; any change of the inputs moves it far more)."""
    vis, sigma = ce_extinction_table("corrected")
    mie_vis, mie_sigma = mie_extinction_table()
    np.testing.assert_array_equal(vis, mie_vis)
    np.testing.assert_allclose(sigma, mie_sigma, rtol=1e-12, atol=0)
