"""Ray-drop physics: the log-normal detection table against Monte Carlo and the §3.9 oracle, neighbour features
against geometry (incidence on a ground plane), leave-one-out, the additive model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from lidar_scans import scan

from roadview_noise.physics.lidar_intensity import sensor_constant
from roadview_noise.physics.ray_drop import AdditiveLogistic, PhysicalRayDrop, detection_table, scan_rays
from roadview_noise.physics.receiver import Receiver
from roadview_noise.profiles.lidar import os1_128, vls_128


def test_table_without_spread_is_the_receiver():
    rx = Receiver.of(os1_128())
    x, p = detection_table(rx, 0.0)
    np.testing.assert_allclose(p, rx.detection_probability(rx.threshold * np.exp(x)), rtol=1e-12)


@pytest.mark.parametrize("profile", [os1_128(), vls_128()], ids=["spad", "apd"])
def test_table_is_the_receiver_averaged_over_a_log_normal_signal(profile):
    """Independent check of the convolution: Monte Carlo over 400 000 log-normal draws."""
    rx = Receiver.of(profile)
    x, p = detection_table(rx, 1.1)
    z = np.random.default_rng(0).standard_normal(400_000)
    for xi in (-2.0, -0.5, 0.0, 0.7, 2.5):
        mc = np.mean(rx.detection_probability(rx.threshold * np.exp(xi + 1.1 * z)))
        assert np.interp(xi, x, p) == pytest.approx(mc, abs=4e-3)


def test_signal_at_threshold_detects_half_the_time():
    """models.md §3.9 oracle: with Φ((ln S − ln T)/σ) (a receiver far sharper than the spread), S = T gives 0.5."""
    sharp = dataclasses.replace(vls_128(), photons_at_threshold=1e9, threshold_over_noise=1e4)
    x, p = detection_table(Receiver.of(sharp), 0.8)
    assert np.interp(0.0, x, p) == pytest.approx(0.5, abs=1e-3)
    assert np.interp(0.8, x, p) == pytest.approx(0.8413, abs=2e-3)      # Φ(1)


def test_incidence_of_a_ground_plane_and_own_values_left_out():
    """Beams below the horizon see the ground 1.9 m down at incidence cos θ = |sin ω|; the features of a ray come from
    its neighbours only, so changing its own return changes nothing."""
    prof = os1_128()
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))
    r = np.where(el < np.deg2rad(-3), 1.9 / np.sin(-np.minimum(el, -1e-3)), 0.0)[:, None] * np.ones((1, 512))
    cloud = scan(range_m=r, reflectance=0.3, grid=True)
    sr = scan_rays(cloud, "test")
    hit = np.flatnonzero(r.reshape(-1) > 0)
    inner = hit[(hit // 512 > np.argmax(r[:, 0] > 0) + 1) & (hit // 512 < 126)]
    f, support = sr.features(sr.cells.cell[inner], cloud.positions_m)
    assert np.all(support == 8)
    np.testing.assert_allclose(f[:, 2], np.abs(np.sin(el[inner // 512])), rtol=0.02)
    np.testing.assert_allclose(f[:, 3], el[inner // 512], atol=1e-12)
    k = sensor_constant(prof)
    own = np.log(k * 0.3 / r.reshape(-1)[inner] ** 2 / prof.detection_threshold)
    assert np.median(np.abs(f[:, 0] - own)) < 0.05                        # the neighbours stand for the ray
    brighter = dataclasses.replace(cloud, fields={**cloud.fields, "intensity": cloud.fields["intensity"] * 1.0})
    brighter.fields["intensity"][inner[500]] *= 50
    f2, _ = scan_rays(brighter, "test").features(sr.cells.cell[inner[500:501]], cloud.positions_m)
    np.testing.assert_array_equal(f2, f[500:501])


def test_physical_model_is_monotone_and_additive_model_evaluates_its_knots():
    rx = Receiver.of(os1_128(), sensor_constant(os1_128()))
    m = PhysicalRayDrop(1.5, -0.16, 0.37, 0.0, 0.0, 1.1, 0.0067)
    f = np.array([[s, np.log(10.0), c, 0.0] for s in (-1.0, 0.0, 1.0, 3.0) for c in (0.1, 1.0)])
    p = m.drop_probability(f, rx).reshape(4, 2)
    assert np.all(np.diff(p, axis=0) < 0) and np.all(p[:, 0] > p[:, 1])   # more signal, less grazing: fewer drops
    assert p.min() >= 0.0067 - 1e-12
    a = AdditiveLogistic(("log_signal",), (np.array([0.0, 2.0]),), (np.array([0.0, -4.0]),), 1.0)
    logit = a.logit(np.array([[-5.0, 0, 1, 0], [1.0, 0, 1, 0], [9.0, 0, 1, 0]]))
    np.testing.assert_allclose(logit, [1.0, -1.0, -3.0])                   # flat beyond the outer knots


def test_additive_drop_probability_is_the_logistic_of_its_logit():
    rng = np.random.default_rng(4)
    a = AdditiveLogistic(("log_signal", "cos_incidence", "log_range"),
                         (np.sort(rng.normal(size=8)), np.array([0.1, 0.5, 1.0]), np.array([0.0, 2.0, 3.0, 5.0])),
                         (rng.normal(size=8), np.array([2.0, 0.0, -1.0]), np.array([-3.0, 0.0, 1.0, 4.0])), -2.5)
    f = rng.normal(1.0, 2.0, (5000, 4))
    f[rng.random((5000, 4)) < 0.01] = np.nan                    # no estimate: the lowest knot's value
    f[::7, 0] = a.knots[0][rng.integers(0, 8, len(f[::7]))]      # exactly on the knots
    expected = 1.0 / (1.0 + np.exp(-a.logit(np.nan_to_num(f, nan=-np.inf))))
    np.testing.assert_allclose(a.drop_probability(f), expected, rtol=1e-12, atol=0)


def test_neighbour_median_of_any_count():
    from roadview_noise.physics.ray_drop import _median

    rng = np.random.default_rng(0)
    for k in range(1, 9):
        for _ in range(300):
            b = rng.normal(size=8)
            b[rng.random(8) < 0.3] = b[0]                                  # ties
            assert _median(b.copy(), k) == pytest.approx(np.median(b[:k]), abs=1e-15)


def test_neighbour_medians_and_support_against_numpy():
    """:func:`_neighbour_features` on an image with holes (full rings and partial ones, several blocks of full
    rings and a partial last one): each cell's medians of its returning neighbours' values (wrapped over the seam,
    none above the top or below the bottom row) equal ``np.median``, its support their count."""
    from roadview_noise.physics.ray_drop import _neighbour_features

    rng = np.random.default_rng(5)
    rows, columns = 9, 700
    filled = rng.random((rows, columns)) > 0.08
    image = np.full((rows, columns), -1, dtype=np.int64)
    image[filled] = np.arange(filled.sum())
    padded = np.full((rows + 2, columns + 2), -1, dtype=np.int64)
    padded[1:-1, 1:-1] = image
    padded[1:-1, 0], padded[1:-1, -1] = image[:, -1], image[:, 0]
    n = int(filled.sum())
    log_signal, range_m, pos = rng.normal(size=n), rng.uniform(1, 50, n), rng.normal(size=(n, 3))
    at = np.flatnonzero(filled.ravel())
    out, median_range, support = _neighbour_features(padded.ravel(), log_signal, range_m, pos, np.zeros(rows), at,
                                                     columns)
    for i, q in enumerate(at):
        r, c = divmod(int(q), columns)
        around = [image[rr, cc % columns] for rr in (r - 1, r, r + 1) for cc in (c - 1, c, c + 1)
                  if (rr, cc) != (r, c) and 0 <= rr < rows]
        p = [a for a in around if a >= 0]
        assert support[i] == len(p)
        if p:
            assert out[i, 0] == np.median(log_signal[p]) and median_range[i] == np.median(range_m[p])
    assert np.count_nonzero(support == 8) > 2048
