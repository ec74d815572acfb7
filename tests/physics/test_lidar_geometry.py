"""LiDAR spherical conventions (models.md §0.3) and range-image projection (§3.0)."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.physics import lidar_geometry as lg
from roadview_noise.profiles.lidar import os1_128, uniform, vls_128


def random_points(n: int = 2000, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(-80, 80, (n, 3))


@pytest.mark.parametrize("forward, inverse", [(lg.xyz_to_roadview, lg.roadview_to_xyz),
                                              (lg.xyz_to_velodyne, lg.velodyne_to_xyz)])
def test_round_trip(forward, inverse):
    p = random_points()
    np.testing.assert_allclose(inverse(*forward(p)), p, rtol=0, atol=1e-12)


def test_axis_values():
    """Hand values: +x is φ = 0 but α = 90° (Velodyne azimuth is clockwise from +y); +z is straight up in both."""
    p = np.array([[2.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 4.0], [1.0, -1.0, np.sqrt(2.0)]])
    r, phi, theta = lg.xyz_to_roadview(p)
    r2, alpha, omega = lg.xyz_to_velodyne(p)
    np.testing.assert_allclose(r, [2, 3, 4, 2], rtol=1e-15)
    np.testing.assert_array_equal(r, r2)
    np.testing.assert_allclose(np.rad2deg(phi[[0, 1, 3]]), [0, 90, -45], atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(alpha[[0, 1, 3]]), [90, 0, 135], atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(theta), [0, 0, 90, 45], atol=1e-12)
    np.testing.assert_allclose(omega, theta, atol=1e-12)


def test_elevation_conventions_agree_and_azimuths_are_complementary():
    p = random_points()
    _, phi, theta = lg.xyz_to_roadview(p)
    _, alpha, omega = lg.xyz_to_velodyne(p)
    np.testing.assert_allclose(omega, theta, atol=1e-12)
    np.testing.assert_allclose(np.cos(alpha + phi), 0.0, atol=1e-12)      # α = 90° − φ (mod 360°)


def test_mixing_conventions_swaps_x_and_y():
    """The failure models.md §0.3 warns about: forward Velodyne, inverse ROADVIEW mirrors the cloud about x = y."""
    p = random_points()
    mixed = lg.roadview_to_xyz(*lg.xyz_to_velodyne(p))
    np.testing.assert_allclose(mixed, p[:, [1, 0, 2]], atol=1e-12)


def test_origin_maps_to_zero_and_back():
    p = np.zeros((3, 3))
    for forward, inverse in ((lg.xyz_to_roadview, lg.roadview_to_xyz), (lg.xyz_to_velodyne, lg.velodyne_to_xyz)):
        r, a, e = forward(p)
        assert np.all(r == 0) and np.all(a == 0) and np.all(e == 0)
        np.testing.assert_array_equal(inverse(r, a, e), p)


def test_has_return():
    p = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.0, 0.0, -1e-3]])
    np.testing.assert_array_equal(lg.has_return(p), [False, True, False, True])


# --- range image ----------------------------------------------------------------------------------------------------


def grid_cloud(profile, columns: int, range_m: float = 20.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One point per (ring, column) fired at the column centre of the default layout, D3.5 Eq. (4) geometry."""
    ring, col = np.meshgrid(np.arange(profile.channels), np.arange(columns), indexing="ij")
    ring, col = ring.ravel(), col.ravel()
    firing = np.pi - col * 2 * np.pi / columns                        # φ of the encoder, clockwise from 180°
    phi = firing - np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring]
    theta = np.deg2rad(np.asarray(profile.beam_elevation_deg))[ring]
    return lg.roadview_to_xyz(np.full(len(ring), range_m), phi, theta), ring, col


@pytest.mark.parametrize("profile", [os1_128(), vls_128(), uniform("u16", 16, 15.0, -15.0)], ids=lambda p: p.name)
def test_range_image_puts_every_point_in_its_cell(profile):
    columns = 360
    p, ring, col = grid_cloud(profile, columns)
    img = lg.range_image(p, ring, profile, columns=columns)
    assert img.shape == (profile.channels, columns)
    np.testing.assert_array_equal(img.col, col)
    rows = img.row
    # rows follow elevation: row 0 is the highest beam, each row holds one ring
    elev = np.asarray(profile.beam_elevation_deg)[ring]
    assert np.all(np.diff(elev[np.argsort(rows, kind="stable")]) <= 0)
    assert np.all(img.index >= 0) and img.shown().all()
    np.testing.assert_array_equal(img.index[rows, img.col], np.arange(len(p)))
    np.testing.assert_allclose(img.range_m, 20.0, rtol=1e-12)


def test_vls_rows_are_sorted_by_elevation():
    profile = vls_128()
    rows = lg.ring_rows(profile)
    elev = np.asarray(profile.beam_elevation_deg)
    assert sorted(rows) == list(range(128))
    assert elev[rows.argsort()][0] == max(elev) and elev[rows.argsort()][-1] == min(elev) == -25.0


def test_range_image_collisions_keep_nearest_and_skip_no_returns():
    profile = uniform("u4", 4, 3.0, -3.0)
    direction = np.array([1.0, 0.0, 0.0])
    p = np.array([12.0, 5.0, 0.0, 7.0, 30.0])[:, None] * direction          # same azimuth; rings as given
    ring = np.array([1, 1, 1, 1, 2])
    img = lg.range_image(p, ring, profile, columns=8)
    col = img.col[0]
    assert img.index[1, col] == 1 and img.range_m[1, col] == 5.0          # nearest of 12, 5, 7; the zero is out
    assert img.index[2, col] == 4 and img.range_m[2, col] == 30.0
    np.testing.assert_array_equal(img.shown(), [False, True, False, False, True])
    assert img.row[2] == -1 and img.col[2] == -1
    assert (img.index >= 0).sum() == 2 and np.count_nonzero(img.range_m) == 2


def test_range_image_counter_clockwise_layout():
    profile = uniform("u1", 1, 0.0, 0.0)
    phi = np.deg2rad([0.0, 90.0, -90.0, 179.0])
    p = lg.roadview_to_xyz(np.full(4, 10.0), phi, np.zeros(4))
    img = lg.range_image(p, np.zeros(4, int), profile, columns=4, column0_azimuth_deg=0.0, clockwise=False)
    np.testing.assert_array_equal(img.col, [0, 1, 3, 2])
    img = lg.range_image(p, np.zeros(4, int), profile, columns=4)   # default: column 0 at 180°, clockwise
    np.testing.assert_array_equal(img.col, [2, 1, 3, 0])


def test_range_image_reproduces_real_os1_grid(shared_data):
    """The points of a real OS1-128 scan (1024 columns) land exactly in the cells of the sensor's own range image."""
    d = shared_data / "os1-128"
    xyz = np.fromfile(d / "scan0.bin", dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    ring = np.fromfile(d / "scan0_ring.u16", dtype=np.uint16)
    grid = np.load(d / "scan0_grid.npz")
    img = lg.range_image(xyz, ring, os1_128(), columns=1024)
    filled = grid["range_mm"] > 0
    np.testing.assert_array_equal(img.index >= 0, filled)
    np.testing.assert_array_equal(img.index[filled], np.arange(len(xyz)))   # scan0.bin is the grid in row order
    # range_mm is measured from the beam origin (15.8 mm off-axis, 36.2 mm below the sensor-frame origin)
    np.testing.assert_allclose(img.range_m[filled], grid["range_mm"][filled] / 1000.0, atol=0.02)


def test_fast_atan2_matches_numpy():
    """The compiled arctangent (A&S 4.4.49) against numpy's in every octant, on the axes and at the origin."""
    rng = np.random.default_rng(0)
    xy = rng.normal(size=(200_000, 2)) * rng.uniform(1e-3, 200, (200_000, 1))
    axes = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, 1], [-1, -1], [1, -1], [-0.0, -1.0]])
    xy = np.concatenate([xy, axes * 7.5])
    got = lg._azimuths(np.ascontiguousarray(xy[:, 1]), np.ascontiguousarray(xy[:, 0]))
    want = np.arctan2(xy[:, 1], xy[:, 0])
    err = np.abs(np.angle(np.exp(1j * (got - want))))
    assert err.max() < 2.5e-8 and got[-10] == 0.0
