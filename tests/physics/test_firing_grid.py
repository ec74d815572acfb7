"""Firing grid of a point list (physics/firing_grid.py): the empty rays of a spinning LiDAR's list are exactly the
cells of its beams × columns grid without a return, with the column count measured from the data."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from roadview_noise.physics.firing_grid import _sorted_turn, beam_gaps, firing_grid, measured_step_rad
from roadview_noise.profiles.lidar import os1_128, vls_128
from roadview_noise.types import PointCloud


def scan(profile, columns: int, fill: float = 0.7, seed: int = 0, shift_steps=None, jitter_steps: float = 0.0,
         phase_rad: float = 0.3):
    """A list from a ``channels × columns`` firing grid with a fraction ``fill`` of cells returning: column c of beam
    b fires at encoder azimuth ``phase − (c + shift_b)·step`` (+ jitter), the point lies at that azimuth minus the
    beam's offset, 2–80 m away. Returns (cloud, occupied cells, direction of every cell)."""
    rng = np.random.default_rng(seed)
    channels, step = profile.channels, 2 * np.pi / columns
    shift = np.zeros(channels) if shift_steps is None else shift_steps
    c = np.arange(columns)[None, :]
    firing = phase_rad - (c + shift[:, None]) * step
    az = firing - np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[:, None]
    el = np.broadcast_to(np.deg2rad(np.asarray(profile.beam_elevation_deg))[:, None], az.shape)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    occupied = rng.random((channels, columns)) < fill
    ring, col = np.nonzero(occupied)
    az_pt = az[ring, col] + rng.normal(0, jitter_steps * step, len(ring))
    r = rng.uniform(2, 80, len(ring))
    pos = np.stack([np.cos(el[ring, col]) * np.cos(az_pt), np.cos(el[ring, col]) * np.sin(az_pt),
                    np.sin(el[ring, col])], 1) * r[:, None]
    order = rng.permutation(len(ring))                  # any point order
    fields = {"intensity": np.full(len(ring), 50.0), "ring": ring[order].astype(np.uint16),
              "time": (col[order] * 1e-5).astype(np.float32)}
    bare = dataclasses.replace(profile, sensor_z_offset_m=0.0, beam_origin_offset_m=0.0)
    return PointCloud(pos[order], fields, "lidar", bare), occupied, d


def matched_cells(grid, d, tol_rad: float = 1e-6) -> set:
    """(ring, column) of the true cell each empty ray points along (its nearest direction in its ring, within
    ``tol_rad``)."""
    u = grid.directions(np.arange(len(grid.ring)))
    cells = set()
    for ring in np.unique(grid.ring):
        sel = grid.ring == ring
        cos = u[sel] @ d[ring].T
        best = np.argmax(cos, axis=1)
        assert np.all(cos[np.arange(len(best)), best] > np.cos(tol_rad))
        cells.update((int(ring), int(c)) for c in best)
    return cells


@pytest.mark.parametrize("profile, columns", [(os1_128(), 1024), (vls_128(), 900)], ids=["os1-128", "vls-128"])
def test_every_empty_cell_and_nothing_else(profile, columns):
    cloud, occupied, d = scan(profile, columns)
    grid = firing_grid(cloud, cloud.profile)
    assert not isinstance(grid, str), grid
    assert grid.columns == columns != profile.columns
    assert len(grid.ring) == np.count_nonzero(~occupied)
    assert matched_cells(grid, d) == set(zip(*np.nonzero(~occupied)))


def test_per_beam_shifts_and_jitter_keep_each_return_in_its_cell():
    """Velodyne beams fire up to a column apart within a firing sequence: with per-beam shifts of ±0.45 steps and
    5 % of a step of azimuth jitter every return still lands in its own cell."""
    profile = vls_128()
    shift = np.random.default_rng(4).uniform(-0.45, 0.45, profile.channels)
    cloud, occupied, d = scan(profile, 1800, shift_steps=shift, jitter_steps=0.05, seed=2)
    grid = firing_grid(cloud, cloud.profile)
    assert grid.columns == 1800 and len(grid.ring) == np.count_nonzero(~occupied)
    assert matched_cells(grid, d, tol_rad=0.05 * 2 * np.pi / 1800) == set(zip(*np.nonzero(~occupied)))
    # the shifts are measured up to one common offset (the column labels are arbitrary), each from ~80 returns
    # with 0.05-step jitter: SD 0.0056 step
    diff = np.angle(np.exp(2j * np.pi * (grid.shift - shift))) / (2 * np.pi)
    np.testing.assert_allclose(diff - diff.mean(), 0.0, atol=0.03)


def test_added_returns_copy_fields_of_their_firing_column():
    """``like`` names a return of the empty cell's own firing column (its time stamp says which)."""
    cloud, occupied, d = scan(os1_128(), 512, seed=3)
    grid = firing_grid(cloud, cloud.profile)
    u = grid.directions(np.arange(len(grid.ring)))
    true_col = np.array([np.argmax(d[b] @ v) for b, v in zip(grid.ring, u)])
    np.testing.assert_array_equal(np.rint(cloud.fields["time"][grid.like] / 1e-5).astype(int), true_col)


def test_cropped_view_dead_beam_and_dual_returns_are_not_filled():
    cloud, occupied, d = scan(os1_128(), 1024, seed=5)
    az = np.arctan2(cloud.positions_m[:, 1], cloud.positions_m[:, 0])
    front = np.abs(az) < np.pi / 4
    keep = front & (cloud.fields["ring"] != 7)
    cropped = cloud.select(keep)
    grid = firing_grid(cropped, cropped.profile)
    u = grid.directions(np.arange(len(grid.ring)))
    assert len(grid.ring) > 0 and 7 not in grid.ring        # ring 7 lies between beams with returns: dead
    step = 2 * np.pi / 1024
    assert np.all(np.abs(np.arctan2(u[:, 1], u[:, 0])) < np.pi / 4 + 5 * step)
    # inside the view every empty cell is found (one column of margin at its edges)
    cells = matched_cells(grid, d)
    az_cell = np.arctan2(d[..., 1], d[..., 0])
    inner = ~occupied & (np.abs(az_cell) < np.pi / 4 - step)
    inner[7] = False
    assert set(zip(*np.nonzero(inner))) <= cells
    # a second (farther) echo on every ray changes nothing
    dual = PointCloud(np.concatenate([cloud.positions_m, cloud.positions_m * 1.5]),
                      {k: np.concatenate([v, v]) for k, v in cloud.fields.items()}, "lidar", cloud.profile)
    again = firing_grid(dual, dual.profile)
    assert len(again.ring) == np.count_nonzero(~occupied)


def test_sky_above_a_sparse_ground_beam_stays_in_view():
    """Open sky: only the lowest beam returns (70 % of its cells); every other cell, up to the top beam, is an empty
    ray, and each borrows the fields of the nearest column that returned."""
    cloud, occupied, d = scan(os1_128(), 512, seed=8)
    bottom = int(np.argmin(cloud.profile.beam_elevation_deg))
    sparse = cloud.select(cloud.fields["ring"] == bottom)
    grid = firing_grid(sparse, sparse.profile)
    assert grid.columns == 512 and len(grid.ring) == 128 * 512 - len(sparse)
    assert matched_cells(grid, d) == set(zip(*np.nonzero(~occupied | (np.arange(128) != bottom)[:, None])))
    own_col = np.rint(sparse.fields["time"] / 1e-5).astype(int)
    filled = np.flatnonzero(occupied[bottom])
    u = grid.directions(np.arange(len(grid.ring)))
    true_col = np.array([np.argmax(d[b] @ v) for b, v in zip(grid.ring, u)])
    def circular(a, b):
        return np.minimum(np.abs(a - b), 512 - np.abs(a - b))

    nearest = np.min(circular(filled[None, :], true_col[:, None]), axis=1)
    np.testing.assert_array_equal(circular(own_col[grid.like], true_col), nearest)


def test_zero_points_are_not_returns():
    cloud, occupied, _ = scan(os1_128(), 1024, seed=6)
    zeros = PointCloud(np.concatenate([cloud.positions_m, np.zeros((50, 3))]),
                       {k: np.concatenate([v, v[:50]]) for k, v in cloud.fields.items()}, "lidar", cloud.profile)
    assert len(firing_grid(zeros, zeros.profile).ring) == np.count_nonzero(~occupied)


def test_lists_without_a_firing_grid_say_why():
    rng = np.random.default_rng(0)
    profile = os1_128()
    random = PointCloud(rng.normal(size=(20000, 3)) * 20, {"intensity": np.ones(20000)}, "lidar", profile)
    assert "regular firing grid" in firing_grid(random, profile)
    few = PointCloud(rng.normal(size=(50, 3)) * 20, {"intensity": np.ones(50)}, "lidar", profile)
    assert "only" in firing_grid(few, profile)
    bad_ring = PointCloud(rng.normal(size=(50, 3)), {"intensity": np.ones(50), "ring": np.full(50, 200)}, "lidar",
                          profile)
    assert "ring values" in firing_grid(bad_ring, profile)
    assert firing_grid(PointCloud(np.zeros((10, 3)), {"intensity": np.zeros(10)}, "lidar", profile),
                       profile) == "no returns"


def test_real_os1_list_measures_its_grid_and_beam_azimuths(shared_data):
    """The real 1024-column OS1-128 list (ring recovered, no ring field): exactly its range image's no-return cells
    per beam; the measured column phases reproduce the azimuths of its far returns to 0.001° (SD), half the error of the
    nominal grid with the unit's azimuth table alone."""
    from roadview_noise.physics.lidar_geometry import recover_ring

    a = np.fromfile(shared_data / "os1-128" / "scan0.bin", dtype=np.float32).reshape(-1, 4)
    g = np.load(shared_data / "os1-128" / "scan0_grid.npz")
    profile = os1_128()
    cloud = PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3]}, "lidar", profile)
    grid = firing_grid(cloud, profile)
    assert grid.columns == 1024
    np.testing.assert_array_equal(np.bincount(grid.ring, minlength=128), (g["range_mm"] == 0).sum(axis=1))
    ring = recover_ring(cloud.positions_m, profile).astype(int)
    r = np.linalg.norm(cloud.positions_m, axis=1)
    far = r > 20
    off = np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring[far]]
    az = np.arctan2(cloud.positions_m[far, 1], cloud.positions_m[far, 0])
    step = 2 * np.pi / 1024
    col = np.floor(-(az + off) / step - grid.shift[ring[far]] + 0.5)

    def azimuth_error_sd(shift):
        return np.rad2deg(np.std(np.angle(np.exp(1j * (az - (-(col + shift) * step - off))))))

    measured, nominal = azimuth_error_sd(grid.shift[ring[far]]), azimuth_error_sd(0.0)
    assert measured < 0.001 and measured < 0.6 * nominal, (measured, nominal)


def test_beam_gaps_are_the_sorted_gaps_of_each_sampled_beam():
    """The compiled gather of the step's gaps against NumPy: sampled beams' returns sorted by (beam, azimuth mod 2π),
    neighbour differences within a beam, echoes (≤ 1e-7 rad) left out; other beams and non-returns ignored."""
    rng = np.random.default_rng(4)
    n = 5000
    ring = rng.integers(0, 16, n)
    firing = rng.uniform(-7.0, 7.0, n)
    firing[1::50] = firing[::50][:len(firing[1::50])]          # second echoes of a ray
    ring[1::50] = ring[::50][:len(ring[1::50])]
    valid = rng.random(n) > 0.2
    sampled = np.zeros(16, bool)
    sampled[[2, 5, 11]] = True
    sel = np.flatnonzero(sampled[ring] & valid)
    f = np.mod(firing[sel], 2 * np.pi)
    order = np.lexsort((f, ring[sel]))
    f, r = f[order], ring[sel][order]
    expected = np.diff(f)[r[1:] == r[:-1]]
    gaps, returns = beam_gaps(firing, ring, valid, sampled, np.bincount(ring, minlength=16))
    assert returns == len(sel)
    np.testing.assert_array_equal(gaps, expected[expected > 1e-7])
    assert len(gaps) < len(expected)                            # the echoes were there and left out


def test_a_turn_in_firing_order_is_read_sorted():
    """``_sorted_turn`` is ``np.sort``: turns listed ascending or descending from any start (ties included), and
    anything else."""
    rng = np.random.default_rng(5)
    for t in range(400):
        n = int(rng.integers(0, 12))
        values = np.sort(rng.integers(0, 4, n).astype(float) if t % 2 else rng.random(n))
        start = int(rng.integers(0, n + 1))
        turn = np.concatenate([values[start:], values[:start]])
        for f in (turn, turn[::-1].copy(), rng.random(n)):
            np.testing.assert_array_equal(_sorted_turn(f), np.sort(f))


def numpy_step(gap):
    """:func:`measured_step_rad`'s fit in NumPy: the seed (of the 10th, 25th and 50th percentiles, the one with the
    most gaps within 15 % of it, the first with half the gaps), then step = Σg / Σk over the gaps within 0.25 of a
    whole number k ≥ 1 of steps of up to 2, 4, 8, 8 steps; (the step, the fraction of gaps within 0.15 of k ≥ 1 whole
    steps alone or, both at least 0.15 step, with a neighbour)."""
    best, best_count = math.nan, -1
    for q in (len(gap) // 10, len(gap) // 4, len(gap) // 2):
        if 2 * best_count > len(gap):
            break
        c = float(np.partition(gap, q)[q])
        count = np.count_nonzero(np.abs(gap / c - 1) < 0.15)
        if not (best_count >= 0 and abs(c / best - 1) < 0.15) and count > best_count:
            best, best_count = c, count
    step = best
    for most in (2, 4, 8, 8):
        last = step
        whole = np.rint(gap / last)
        fit = (whole >= 1) & (gap < (most + 0.5) * last) & (np.abs(gap / last - whole) < 0.25)
        step = float(gap[fit].sum() / whole[fit].sum())

    def is_whole(g):
        return (np.rint(g / last) >= 1) & (np.abs(g / step - np.rint(g / last)) < 0.15)

    long = gap >= 0.15 * step
    pair = np.zeros(len(gap), bool)
    pair[1:] |= is_whole(gap[1:] + gap[:-1]) & long[1:] & long[:-1]
    pair[:-1] |= is_whole(gap[:-1] + gap[1:]) & long[:-1] & long[1:]
    near = gap < (8 + 0.5) * last
    return step, float(np.mean((is_whole(gap) | pair)[near]))


def test_measured_step_is_the_numpy_refit():
    """The compiled fit against NumPy's (:func:`numpy_step`): the same step to rounding, the same column count,
    regular fraction and verdict — on gaps of whole steps with jitter, and with off-phase returns (a fraction of a
    step and its complement to whole steps, as a Velodyne decoder's last block of a packet leaves them)."""
    rng = np.random.default_rng(6)
    for t in range(300):
        columns = int(rng.choice([512, 1024, 1800, 2048]))
        step0 = 2 * np.pi / columns
        k = rng.geometric(rng.uniform(0.05, 0.95), int(rng.integers(200, 4000))).astype(float)
        if t % 3 == 0:                                          # a tenth of the returns off phase by δ steps
            off = np.flatnonzero(rng.random(len(k) - 1) < 0.1)
            delta = rng.uniform(0.2, 0.8)
            k[off] -= delta
            k[off + 1] += delta
        gap = np.abs(k * step0 + rng.normal(0, rng.choice([0.0, 0.02, 0.1, 0.3]) * step0, len(k))) + 1e-9
        step, regular = numpy_step(gap)
        got, reason = measured_step_rad(gap, len(gap))
        assert bool(reason) == (regular < 0.8)
        assert (f"({100 * regular:.0f} % of the gaps" in reason) if reason else (
            abs(got - step) < 1e-12 * step and round(2 * np.pi / got) == round(2 * np.pi / step))


def test_list_rings_are_each_points_nearest_beam_in_any_order():
    """:func:`list_points` checks a point against the last recovered beam's interval of z/ρ, then the next beam's in
    the list's order, before searching: its rings equal :func:`lidar_geometry.recover_ring`'s per-point search
    whether a list holds each beam's points together, goes column by column (either way) or has any order, for
    points on a midpoint between beams, behind the beam origin, at the origin or not finite."""
    from roadview_noise.physics.firing_grid import list_points
    from roadview_noise.physics.lidar_geometry import recover_ring, ring_search_table

    profile = os1_128()
    cloud, _, _ = scan(profile, 256, seed=3)
    rng = np.random.default_rng(4)
    pos = cloud.positions_m * (1 + 0.02 * rng.standard_normal((len(cloud), 1)))
    beam_by_beam = np.argsort(cloud.fields["ring"], kind="stable")
    column_by_column = np.lexsort((cloud.fields["ring"], cloud.fields["time"]))
    tan_mid = ring_search_table(tuple(profile.beam_elevation_deg))[0]
    rho_offset = profile.beam_origin_offset_m
    elevation = np.sort(np.deg2rad(profile.beam_elevation_deg))

    def at(tan):                                        # a point whose z/ρ from the beam origin is ``tan`` (to the bit)
        x, z0 = 10 + rho_offset, profile.sensor_z_offset_m
        rho = math.sqrt(x * x) - rho_offset
        z = tan * rho + z0
        for _ in range(8):
            if (z - z0) / rho != tan:
                z = np.nextafter(z, np.inf if (z - z0) / rho < tan else -np.inf)
        return [x, 0, z]

    beam = [at(t) for t in np.tan(elevation)]
    edge = [[0, 0, 0], [0, 0, 1], [0, 0, -1], [1e-3, 0, 1], [np.nan, 1, 1], [np.inf, 0, 1],
            beam[40], at(tan_mid[40]), beam[40], beam[41], at(tan_mid[40]),   # on a midpoint (the higher beam) after
            beam[38], beam[39], at(tan_mid[40]),                               # either beam, and where the list's
            [rho_offset, 0, profile.sensor_z_offset_m]]                        # order predicts the lower one
    for positions in (np.concatenate([pos[beam_by_beam], edge, pos[:50]]), np.concatenate([edge, pos])[::-1],
                      np.concatenate([pos[column_by_column], edge]), pos[column_by_column][::-1]):
        listed = PointCloud(positions, {"intensity": np.ones(len(positions))}, "lidar", profile)
        points = list_points(listed, profile)
        np.testing.assert_array_equal(points.ring, recover_ring(positions, profile))
        np.testing.assert_array_equal(points.counts, np.bincount(points.ring, minlength=profile.channels))


def test_list_points_firing_azimuths_and_ranges_are_numpys():
    """:func:`list_points`' one pass in blocks of 1 024 points (views of the block: no negative-index wraparound)
    gives NumPy's firing azimuths (:func:`lidar_geometry.firing_azimuth_rad` with its rings) and ranges (``|p|``, 0 for
    zero points and returns nearer than ``min_range_m``), carried rings or recovered, on a list of 3 blocks and a tail
    with several returns per ray (the same direction at three ranges), zero points and near points."""
    from roadview_noise.physics.firing_grid import list_points
    from roadview_noise.physics.lidar_geometry import firing_azimuth_rad, recover_ring

    profile = dataclasses.replace(os1_128(), min_range_m=0.5)
    cloud, _, _ = scan(profile, 64, fill=0.6, seed=11)
    p = cloud.positions_m[:1000]
    pos = np.concatenate([p, p * 0.5, p * 0.25, np.zeros((40, 3)), p[:30] * 1e-3, cloud.positions_m[1000:1500]])
    carried = np.concatenate([cloud.fields["ring"][:1000]] * 3 + [np.zeros(40, np.uint16),
                             cloud.fields["ring"][:30], cloud.fields["ring"][1000:1500]])
    assert len(pos) > 3 * 1024
    norm = np.linalg.norm(pos, axis=1)
    ranges = np.where((norm > 0) & (norm >= profile.min_range_m), norm, 0.0)
    for fields in ({"intensity": np.ones(len(pos))}, {"intensity": np.ones(len(pos)), "ring": carried}):
        listed = PointCloud(pos, fields, "lidar", cloud.profile)
        points = list_points(listed, listed.profile)
        ring = carried if "ring" in fields else recover_ring(pos, listed.profile)
        np.testing.assert_array_equal(points.ring, ring)
        np.testing.assert_array_equal(points.firing_rad, firing_azimuth_rad(pos, ring, listed.profile))
        np.testing.assert_array_equal(points.range_m, ranges)
        np.testing.assert_array_equal(points.counts, np.bincount(ring, minlength=profile.channels))


@pytest.mark.parametrize("seed, fill", [(0, 0.7), (1, 0.3), (2, 0.95)])
def test_empty_cells_take_their_nearest_filled_column_and_count_the_returning_beams(seed, fill):
    """The firing grid's empty cells give, in their own pass, each cell's ``like`` (a return of the nearest column
    that has one: NumPy's ``_nearest_filled(like)[column]``) and how many lie on beams that returned (NumPy's
    ``count_nonzero(returned[ring])``, which the sparse-list warning compares), on lists with dead beams, a cropped
    view, columns without any return, beams above every return (sky: filled, not returning) and several returns
    per ray."""
    from roadview_noise.physics import firing_grid as fg

    profile = os1_128()
    cloud, occupied, _ = scan(profile, 512, fill=fill, seed=seed)
    keep = ~np.isin(cloud.fields["ring"], (0, 1, 50, 51))      # the top beams (sky above the others) and dead ones
    col = np.rint(-(np.arctan2(cloud.positions_m[:, 1], cloud.positions_m[:, 0]) - 0.3) / (2 * np.pi / 512)) % 512
    keep &= ~((col > 100) & (col < 140))                                       # a crop: 40 columns without returns
    twice = np.flatnonzero(keep)[::7]                                          # several returns per ray
    idx = np.concatenate([np.flatnonzero(keep), twice])
    pos = cloud.positions_m[idx] * np.where(np.arange(len(idx)) < keep.sum(), 1.0, 0.6)[:, None]
    listed = PointCloud(pos, {k: v[idx] for k, v in cloud.fields.items()}, "lidar", cloud.profile)
    measured = fg.firing_columns(listed, listed.profile)
    assert not isinstance(measured, str), measured
    grid = fg.empty_rays(measured, listed.profile)
    offsets = np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg, dtype=np.float64))
    step = 2 * np.pi / measured.columns
    occupied, like, seen = fg._cells(measured.firing_rad, measured.valid, measured.ring, offsets, measured.shift, step,
                                     measured.columns, profile.channels)
    returned = occupied.any(axis=1)
    assert not returned.all() and len(grid.ring) > 0
    np.testing.assert_array_equal(grid.like, fg._nearest_filled(like)[grid.column])
    m = fg.VIEW_MARGIN_STEPS
    in_view = np.convolve(np.concatenate([seen[-m:], seen, seen[:m]]), np.ones(2 * m + 1), "valid") > 0
    words = occupied.reshape(-1).view(np.uint64)
    ring, column, like_cells, on_returned = fg._empty_cells(occupied, words, fg._firing_beams(returned, profile),
                                                            in_view, measured.shift, offsets, step, returned,
                                                            fg._nearest_filled(like))
    np.testing.assert_array_equal(ring, grid.ring)
    np.testing.assert_array_equal(column, grid.column)
    assert on_returned == np.count_nonzero(returned[ring]) < len(ring)
