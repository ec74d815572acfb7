"""Range-image cells of grids and point lists: the same destaggered image from either form, empty rays, collisions."""

from __future__ import annotations

import dataclasses

import numpy as np
from lidar_scans import scan

from roadview_noise.physics.scan_cells import row_elevation_rad, scan_cells
from roadview_noise.profiles.lidar import os1_128, vls_128


def _ranges(seed=0, columns=512, channels=128):
    rng = np.random.default_rng(seed)
    r = rng.uniform(3, 60, (channels, columns))
    r[rng.random((channels, columns)) < 0.1] = 0.0            # no-return rays
    return r


def test_grid_and_list_give_the_same_destaggered_image():
    r = _ranges()
    grid, listed = scan(range_m=r, grid=True), scan(range_m=r)
    cg, cl = scan_cells(grid, grid.profile), scan_cells(listed, listed.profile)
    img_g = cg.image(np.linalg.norm(grid.positions_m, axis=1))
    img_l = cl.image(np.linalg.norm(listed.positions_m, axis=1))
    assert cg.shape == cl.shape == (128, 512)
    # the list's column origin is arbitrary: the images agree up to one turn of the columns
    turns = [np.mean(np.roll(img_l, k, axis=1) == img_g) for k in range(512)]
    assert max(turns) == 1.0
    assert len(cg.empty) == int(np.sum(r == 0)) and len(cl.empty) == len(cg.empty)
    assert np.array_equal(np.sort(cg.empty), np.flatnonzero(img_g.reshape(-1) == 0))


def test_destaggered_columns_share_one_azimuth():
    """OS1-128 beams are ±4° apart in azimuth at one firing column; in the image a column is one azimuth."""
    grid = scan(range_m=20.0, grid=True)
    cells = scan_cells(grid, grid.profile)
    az = cells.image(np.arctan2(grid.positions_m[:, 1], grid.positions_m[:, 0]))
    step = 2 * np.pi / 512
    spread = np.angle(np.exp(1j * (az - az[64:65, :])))          # against the middle row
    assert np.abs(spread).max() < step                             # within one column (offsets are not whole steps)
    raw = grid.positions_m.reshape(128, 512, 3)
    raw_spread = np.angle(np.exp(1j * (np.arctan2(raw[..., 1], raw[..., 0]) - np.arctan2(raw[64, :, 1],
                                                                                           raw[64, :, 0]))))
    assert np.abs(raw_spread).max() > 10 * step                     # the stored grid is staggered


def test_counter_clockwise_grid_and_rows_by_elevation():
    prof = vls_128()                                               # laser ids are not in elevation order
    grid = scan(prof, columns=360, range_m=15.0, grid=True)
    flipped = dataclasses.replace(grid, positions_m=grid.positions_m * np.array([1.0, -1.0, 1.0]))
    for cloud in (grid, flipped):
        cells = scan_cells(cloud, cloud.profile)
        el = cells.image(np.arctan2(cloud.positions_m[:, 2], np.hypot(cloud.positions_m[:, 0],
                                                                         cloud.positions_m[:, 1])))
        assert np.all(np.diff(el[:, 0]) < 0)                        # rows: highest beam first
        np.testing.assert_allclose(el[:, 7], row_elevation_rad(cloud.profile), atol=1e-9)
        az = cells.image(np.arctan2(cloud.positions_m[:, 1], cloud.positions_m[:, 0]))
        assert np.abs(np.angle(np.exp(1j * (az - az[:1])))).max() < 2 * np.pi / 360


def test_collisions_keep_the_nearest_return():
    cloud = scan(columns=256, range_m=30.0)
    twin = dataclasses.replace(cloud, positions_m=cloud.positions_m[:10] * 0.5,
                               fields={k: v[:10] for k, v in cloud.fields.items()})
    both = dataclasses.replace(cloud, positions_m=np.concatenate([cloud.positions_m, twin.positions_m]),
                               fields={k: np.concatenate([cloud.fields[k], twin.fields[k]]) for k in cloud.fields})
    cells = scan_cells(both, both.profile)
    n = len(cloud)
    assert not cells.shown[:10].any() and cells.shown[n:].all() and cells.shown[10:n].all()
    assert np.array_equal(cells.cell[:10], cells.cell[n:])


def test_unstructured_list_has_no_cells():
    rng = np.random.default_rng(3)
    cloud = scan(columns=256)
    jumbled = dataclasses.replace(cloud, positions_m=cloud.positions_m * rng.uniform(0.5, 2, (len(cloud), 1))
                                  + rng.normal(0, 0.3, cloud.positions_m.shape))
    assert isinstance(scan_cells(jumbled, os1_128()), str)


def test_cells_without_the_empty_ones_are_the_same_cells():
    r = _ranges(seed=3)
    for cloud in (scan(range_m=r, grid=True), scan(range_m=r)):
        full, lean = scan_cells(cloud, cloud.profile), scan_cells(cloud, cloud.profile, empty=False)
        assert np.array_equal(full.cell, lean.cell) and np.array_equal(full.shown, lean.shown)
        assert full.source == lean.source and len(full.empty) == int(np.sum(r == 0)) and len(lean.empty) == 0
