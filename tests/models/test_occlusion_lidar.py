"""occlusion.lidar: identity at p = 0, exactly the points of blocked cells removed (grids and lists, weather returns
too), one pattern per sensor instance, partial patches re-thresholded, rotating windows blocking rings."""

from __future__ import annotations

import numpy as np
import pytest
from lidar_scans import scan

from roadview_noise.compound import apply_models
from roadview_noise.models.lidar.occlusion import OcclusionLidar
from roadview_noise.models.lidar.rain import RainLidar
from roadview_noise.physics.lidar_geometry import has_return, ring_index, ring_rows
from roadview_noise.physics.window_obstruction import window_pattern
from roadview_noise.provenance import Effect


def run(models, cloud, key="f0", seq="s", seed=4):
    out, rec = apply_models(models, cloud, seed=seed, key=key, sequence_id=seq)
    return out, rec


def _transmission(model, cloud, state):
    """Per point of ``cloud``: its window cell's two-way transmission under the recorded pattern (cell from the ring's
    elevation row and the azimuth column, in NumPy)."""
    prof = cloud.profile
    pat = window_pattern(model._spec(prof), prof.channels, prof.columns, state["pattern_seed"])
    hit = has_return(cloud.positions_m)
    t = np.ones(len(cloud))
    row = ring_rows(prof)[ring_index(cloud, prof)[hit]]
    p = cloud.positions_m[hit]
    col = np.floor(np.mod(-np.arctan2(p[:, 1], p[:, 0]), 2 * np.pi) / (2 * np.pi) * prof.columns).astype(int)
    t[hit] = pat.transmission[row, 0] if pat.transmission.shape[1] == 1 else pat.transmission[row, col]
    return t


@pytest.mark.parametrize("grid", [False, True])
def test_zero_probability_is_the_identity(grid):
    cloud = scan(columns=512, grid=grid)
    out, rec = run([OcclusionLidar(seed_probability=0.0)], cloud)
    assert np.array_equal(out.positions_m, cloud.positions_m)
    assert np.array_equal(out.fields["intensity"], cloud.fields["intensity"])
    assert rec[0].diagnostics["points_removed"] == 0 and rec[0].diagnostics["blocked_fraction"] == 0


@pytest.mark.parametrize("grid", [False, True])
@pytest.mark.parametrize("window", ["static", "rotating"])
def test_removes_exactly_the_points_in_blocked_cells(grid, window):
    cloud = scan(columns=512, grid=grid)
    model = OcclusionLidar(seed_probability=3e-3 if window == "rotating" else 3e-4, window=window)
    out, rec = run([model], cloud)
    blocked = _transmission(model, cloud, rec[0].state) == 0
    d = rec[0].diagnostics
    assert 0 < blocked.sum() < len(cloud) and d["points_removed"] == d["points_blocked"] == int(blocked.sum())
    if grid:
        assert len(out) == len(cloud)
        assert np.array_equal(out.effect == Effect.REMOVED, blocked)
        assert np.all(out.positions_m[blocked] == 0) and np.array_equal(out.positions_m[~blocked],
                                                                        cloud.positions_m[~blocked])
    else:
        assert np.array_equal(out.origin, np.flatnonzero(~blocked))
    if window == "rotating":                       # whole rings: a ring is either all blocked or not at all
        ring = cloud.fields["ring"][has_return(cloud.positions_m)]
        per_ring = np.bincount(ring, blocked[has_return(cloud.positions_m)], 128) / np.bincount(ring, minlength=128)
        assert set(np.unique(per_ring)) == {0.0, 1.0}


def test_weather_returns_in_blocked_cells_are_removed_too():
    """Eq. 3: the window sits behind the weather, so it blocks fog and rain returns like target returns."""
    cloud = scan(columns=512, range_m=np.where(np.arange(128)[:, None] < 40, 0.0, 30.0))   # sky above
    model = OcclusionLidar(seed_probability=5e-4)
    rained, _ = run([RainLidar(rain_rate_mm_per_h=50.0)], cloud)
    out, rec = run([RainLidar(rain_rate_mm_per_h=50.0), model], cloud)
    added = rained.effect == Effect.ADDED
    assert added.sum() > 50                                      # weather returns on the sky rays
    blocked = _transmission(model, rained, rec[1].state) == 0
    assert (blocked & added).sum() > 0
    assert len(out) == len(rained) - blocked.sum()
    kept_added = (out.effect == Effect.ADDED).sum()
    assert kept_added == (added & ~blocked).sum()


def test_one_pattern_per_sensor_instance():
    cloud = scan(columns=512)
    model = OcclusionLidar(seed_probability=3e-4)
    _, a = run([model], cloud, key="frame0", seq="drive1")
    _, b = run([model], cloud, key="frame7", seq="drive1")
    _, c = run([model], cloud, key="frame0", seq="drive2")
    assert a[0].state == b[0].state and a[0].state["patches"] != c[0].state["patches"]
    assert a[0].diagnostics["points_removed"] == b[0].diagnostics["points_removed"]
    per_frame = OcclusionLidar(seed_probability=3e-4, per_frame=True)
    _, d = run([per_frame], cloud, key="frame0", seq="drive1")
    _, e = run([per_frame], cloud, key="frame7", seq="drive1")
    assert d[0].state == {} and d[0].drawn["patches"] != e[0].drawn["patches"]


def test_partial_patches_attenuate_then_rethreshold():
    rho = np.where(np.arange(512)[None, :] % 2 == 0, 0.9, 0.004)           # bright and faint rays, alternating
    cloud = scan(columns=512, range_m=20.0, reflectance=rho)
    model = OcclusionLidar(seed_probability=5e-4, opacity=0.5)               # passes 0.25 of the signal
    out, rec = run([model], cloud)
    t = _transmission(model, cloud, rec[0].state)
    behind = t < 1
    assert set(np.unique(t)) == {0.25, 1.0} and behind.sum() > 0
    d = rec[0].diagnostics
    bright = np.tile(np.arange(512) % 2 == 0, 128)
    kept = np.zeros(len(cloud), bool)
    kept[out.origin] = True
    assert kept[behind & bright].all() and not kept[behind & ~bright].any()   # faint ones fall below the threshold
    assert d["points_removed"] == (behind & ~bright).sum() and d["points_attenuated"] == (behind & bright).sum()
    pos = np.searchsorted(out.origin, np.flatnonzero(behind & bright))
    np.testing.assert_allclose(out.fields["intensity"][pos], np.round(cloud.fields["intensity"][behind & bright] / 4))
    assert np.all(out.effect[pos] == Effect.ATTENUATED)


def test_profile_window_and_blob_shape():
    from roadview_noise.profiles.lidar import vls_128

    vls = scan(vls_128(), columns=360, range_m=25.0)
    _, rec = run([OcclusionLidar(seed_probability=5e-3)], vls)
    assert rec[0].diagnostics["window"] == "rotating"
    _, rec = run([OcclusionLidar(seed_probability=2e-4, shape="blob", aspect="angular")], scan(columns=512))
    assert rec[0].state["seeds"] > 0 and rec[0].diagnostics["obstructed_fraction"] > rec[0].diagnostics[
        "blocked_fraction"]
