"""The return geometry a LiDAR model notes while it reads its input or writes its output (``physics.return_ranges``:
the weather models' placement, the alignment's turned points, the laser power's and the alignment's return mask of
their input) equals the metrics' own pass over the same arrays, value for value, and changes nothing the model
writes; a step whose input's geometry is already known (a CNF's second step) counts only its output's (issue 18)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from roadview_noise import metrics
from roadview_noise.compound import apply_models
from roadview_noise.physics import return_ranges
from roadview_noise.physics.lidar_geometry import has_return
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import build_models, load, plan

ROOT = Path(__file__).resolve().parents[1]
TREES = ("lidar/os1-128-grid/", "lidar/os1-128/", "lidar/vls-128/", "lidar/os1-128-kitti/")


def own_pass(positions: np.ndarray, n_bins: int) -> tuple:
    """The metrics' pass over an array whose geometry nobody noted."""
    none = np.zeros(0, np.bool_)
    return metrics._cloud_pass(positions, none, metrics._NO_CODES, metrics._NO_VALUES, metrics.RANGE_BIN_M, n_bins,
                               metrics.NO_LINK, positions[:0], none, metrics._NO_VALUES)[0]


def run_chain(recipe, task, data, metrics_on: bool):
    return apply_models(build_models(recipe, task), data, seed=recipe.seed, key=task.out_relpath,
                        sequence_id=task.sample.sequence_id, metrics=metrics_on)


@pytest.mark.parametrize("n_bins", [3, 32, 300])
def test_counted_geometry_is_the_metrics_own_pass(n_bins):
    """The weather models' vectorised count (``return_ranges.count``: bins as bytes or, past 255 bins, 16-bit words;
    the largest x² + y² + z² as its bits) on the edge cases of a return: the origin, NaN, ±inf, an overflowing and
    an underflowing r², −0.0, and far points in the last bin."""
    rng = np.random.default_rng(7)
    positions = rng.normal(0.0, 1.5 * n_bins, (4099, 3))
    positions[::5] = 0.0
    positions[1], positions[2, 1], positions[3, 2] = np.nan, np.inf, -np.inf
    positions[4], positions[6], positions[7] = [1e200, 0.0, 0.0], [1e-170, 0.0, 0.0], [-0.0, 0.0, 2.5]
    positions[8], positions[9] = [0.0, 1e5, 0.0], [0.0, 0.0, 10.0 * (n_bins - 2)]
    got = return_ranges.count(positions, n_bins)
    want = own_pass(positions, n_bins)
    assert (got[0], got[1].tolist(), got[2]) == (want[0], want[1].tolist(), want[2])
    assert np.array_equal(got[3], want[3])
    empty = return_ranges.count(positions[:0], n_bins)
    assert (empty[0], len(empty[1]), empty[2]) == (0, 0, 0.0)


#: recipe → the arrays its models note: the chain input (a first weather step's, the laser power's or the alignment's
#: return mask), a first weather step's output, the alignment's output, a later rain step's output (not a later fog
#: step's, nor the laser power's, which hands the positions on)
NOTED = {"weather-fog-lidar": 2, "weather-rain-lidar": 2, "weather-snow-lidar": 2, "cnf20": 3, "cnf22": 2, "cnf23": 2}


@pytest.mark.parametrize("name", sorted(NOTED))
@pytest.mark.parametrize("tree", TREES)
def test_noted_geometry_is_the_metrics_own(monkeypatch, name, tree):
    recipe = load_recipe(ROOT / "recipes" / f"{name}.yaml")
    task = next((t for t in plan(ROOT / "sample_data", recipe) if t.sample.relpath.startswith(tree)), None)
    if task is None:
        pytest.skip(f"no {tree} input")
    data = load(task.sample, ROOT / "sample_data", recipe)
    by_model, note = [], return_ranges.note

    def noting(positions, n_bins, geometry):
        if sys._getframe(1).f_globals["__name__"] != metrics.__name__:
            by_model.append((positions, n_bins, geometry))
        note(positions, n_bins, geometry)

    monkeypatch.setattr(return_ranges, "note", noting)
    out, records = run_chain(recipe, task, data, True)
    first_step = name.startswith("weather-")                       # a CNF's weather step gets a known input
    assert any(p is out.positions_m for p, _, _ in by_model)
    assert any(p is data.positions_m for p, _, _ in by_model)
    assert len({id(p) for p, _, _ in by_model}) == NOTED[name]
    for positions, n_bins, (returns, hist, max_range_m, valid) in by_model:
        r, h, m, v = own_pass(positions, n_bins)
        assert (returns, hist.tolist(), max_range_m) == (r, h.tolist(), m)
        assert np.array_equal(valid, v)
    assert records[-1].metrics["points_out"] == own_pass(out.positions_m, return_ranges.bin_count(out.profile))[0]
    off, _ = run_chain(recipe, task, data, False)                   # the model writes the same cloud
    assert np.array_equal(off.positions_m, out.positions_m)
    assert all(np.array_equal(off.fields[k], out.fields[k]) for k in out.fields)
    assert np.array_equal(off.effect, out.effect) and np.array_equal(off.origin, out.origin)


def test_geometry_is_noted_only_while_a_chain_records_metrics():
    return_ranges.collect(False)
    assert not return_ranges.wanted()
    positions = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, 25.0, 0.0]])
    geometry = own_pass(positions, 4)
    assert geometry[0] == 2 and geometry[1].tolist() == [1, 0, 1] and geometry[2] == 25.0
    return_ranges.note(positions, 4, geometry)
    assert return_ranges.noted(positions, 4) is geometry
    assert return_ranges.noted(positions, 5) is None and return_ranges.noted(positions.copy(), 4) is None
    return_ranges.collect(False)                                    # a chain without metrics forgets them
    assert return_ranges.noted(positions, 4) is None


def test_return_mask_counted_for_the_metrics_is_has_return():
    """The laser power's and the alignment's return mask with the geometry and the intensity sum counted (a compiled
    pass) is NumPy's, and what it notes is the metrics' own pass, on the edge cases: the origin, NaN, ±inf, a sum that
    overflows, coordinates whose squares underflow or overflow, a NaN intensity."""
    positions = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [np.nan, 1.0, 1.0], [np.inf, 0.0, 0.0],
                          [1e308, 1e308, 0.0], [1e-200, 0.0, 0.0], [-0.0, 0.0, 0.0], [0.0, -2.0, 1e300],
                          [1.0, -np.inf, np.inf], [0.0, 0.0, 295.0], [0.5, 7.0, -1.0]])
    intensity = np.array([1.5, 2, 3, 4, 5, 6, 7, 8, 9, 10.25, np.nan], np.float32)
    recipe = load_recipe(ROOT / "recipes" / "cnf23.yaml")
    cloud = load(plan(ROOT / "sample_data", recipe)[0].sample, ROOT / "sample_data", recipe)
    cloud = cloud.replace(positions_m=positions, fields={"intensity": intensity}, attributes={})
    n_bins = return_ranges.bin_count(cloud.profile)
    return_ranges.collect(True)
    try:
        hit = has_return(positions, cloud)
        noted, sums = return_ranges.noted(positions, n_bins), return_ranges.noted_sum(positions, intensity)
        assert return_ranges.noted_sum(positions, intensity.copy()) is None
    finally:
        return_ranges.collect(False)
    with np.errstate(over="ignore", invalid="ignore"):
        assert np.array_equal(hit, has_return(positions))
    assert hit.tolist() == [True, False, False, False, False, True, False, True, False, True, True]
    none = np.zeros(0, np.bool_)
    own = metrics._cloud_pass(positions, none, metrics._NO_CODES, intensity, metrics.RANGE_BIN_M, n_bins,
                              metrics.NO_LINK, positions[:0], none, metrics._NO_VALUES)
    r, h, m, v = own[0]
    returns, hist, max_range_m, valid = noted
    assert (returns, hist.tolist(), max_range_m) == (r, h.tolist(), m) and np.array_equal(valid, v)
    assert sums == (own[2], own[3]) == (11.75, 2)
