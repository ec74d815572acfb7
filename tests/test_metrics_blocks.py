"""The LiDAR metrics' block passes (issue 18, round 22: fewer bytes moved per file) equal the paths they replace, value
for value: the weather placement that counts its input's and output's geometry block by block
(``lidar_output._place_counted`` with ``return_ranges.Tally``) against ``_place`` and ``return_ranges.count`` of the
same arrays, and the metrics' STEP_LINK pass over a cloud whose returns are known (``metrics._counted_step_pass``)
against the generic pass (``metrics._pass``), on hand-built clouds of several blocks: grids and lists, moved,
removed and added points, NaN points, several returns on one ray."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise import metrics
from roadview_noise.physics import lidar_output, return_ranges
from roadview_noise.physics.lidar_echo import NO_RETURN, TARGET, WEATHER

N_BINS = 32
N = 3 * return_ranges.BLOCK + 17                 # three full blocks and a partial one


def scan(rng: np.random.Generator, n: int = N) -> np.ndarray:
    """Positions (m) of a scan with no-return zeros, NaN, inf and far points."""
    positions = rng.normal(0.0, 60.0, (n, 3))
    positions[rng.random(n) < 0.2] = 0.0
    positions[5], positions[6, 1], positions[7] = np.nan, np.inf, [1e200, 0.0, 0.0]
    positions[8], positions[9] = [0.0, 0.0, 10.0 * N_BINS + 3.0], [-0.0, 0.0, 2.5]
    return positions


def placement(rng: np.random.Generator, positions: np.ndarray, grid: bool) -> tuple:
    """``_place``'s arguments for a weather step on these points: targets kept or attenuated, weather returns
    moving targets and filling empty rays (ADDED, zeros until the caller writes them), lost targets."""
    n = len(positions)
    has = np.isfinite(positions).all(axis=1) & (np.abs(positions).sum(axis=1) > 0)
    kind = rng.choice(np.array([TARGET, WEATHER, NO_RETURN], np.uint8), n, p=[0.6, 0.2, 0.2])
    ray_range = np.where(has, 50.0, 0.0)
    return_range = rng.uniform(1.0, 49.0, n)
    reported = rng.uniform(0.0, 300.0, n)
    intensity = rng.uniform(0.0, 300.0, n).astype(np.float32)
    intensity[11] = np.nan
    size = n
    outputs = (np.empty((size, 3)), np.empty(size, np.float32), np.empty(size, np.uint8), np.empty(size, np.int64))
    return (kind, has, return_range, ray_range, reported, 255.0, False, 0.5, grid, positions, intensity, *outputs)


def old_sum(valid: np.ndarray, values: np.ndarray) -> tuple:
    return metrics._return_value_sum(valid, values)


@pytest.mark.parametrize("grid", [False, True])
@pytest.mark.parametrize("noted_input", [False, True])
def test_placement_counted_by_blocks_is_place_and_count(grid, noted_input):
    rng = np.random.default_rng(3 + grid)
    positions = scan(rng)
    args = placement(rng, positions, grid)
    plain = args[:11] + tuple(np.empty_like(a) for a in args[11:])
    removed, n_out, counts = lidar_output._place(*plain)
    return_ranges.collect(True)
    try:
        if noted_input:                            # a later step's input: its geometry known, not counted again
            return_ranges.note(positions, N_BINS, return_ranges.count(positions, N_BINS))
        tally = return_ranges.Tally(positions, args[10], len(positions), N_BINS)
        got_removed, got_n, got_counts, *counted = lidar_output._place_counted(*args, *tally.arrays)
        tally.counted(*counted)
        out = args[11]
        added = np.flatnonzero(args[13][:got_n] == 3)            # a grid's ADDED cells, written after the blocks
        out[added] = rng.uniform(-80.0, 80.0, (len(added), 3))
        tally.add_rows(out, added)
        total = min(got_n + 100, len(out))                       # a list's rows appended after the blocks
        out[got_n:total] = rng.uniform(-400.0, 400.0, (total - got_n, 3))
        out[got_n:got_n + 2] = [np.nan, 0.0, 0.0]
        tally.append(out, got_n, total)
        outputs = out[:total]
        tally.note(outputs)
        noted_out = return_ranges.noted(outputs, N_BINS)
        noted_in = return_ranges.noted(positions, N_BINS)
        summed = return_ranges.noted_sum(positions, args[10])
    finally:
        return_ranges.collect(False)
    assert got_n == n_out and got_counts == counts and np.array_equal(got_removed, removed)
    for mine, theirs in zip(args[11:], plain[11:]):              # the same rows written
        assert np.array_equal(mine[:n_out][~np.isin(np.arange(n_out), added)],
                              theirs[:n_out][~np.isin(np.arange(n_out), added)], equal_nan=True)
    want_out = return_ranges.count(outputs, N_BINS)
    assert (noted_out[0], noted_out[1].tolist(), noted_out[2]) == (want_out[0], want_out[1].tolist(), want_out[2])
    assert np.array_equal(noted_out[3], want_out[3])
    want_in = return_ranges.count(positions, N_BINS)
    assert (noted_in[0], noted_in[1].tolist(), noted_in[2]) == (want_in[0], want_in[1].tolist(), want_in[2])
    assert np.array_equal(noted_in[3], want_in[3])
    if noted_input:
        assert summed is None
    else:
        assert summed == old_sum(want_in[3], args[10]) and summed[1] < len(positions)


def test_tally_recounts_rewritten_rows():
    """Rows the blocks counted and the model rewrote (a list's stored no-return points that take a weather return)
    are counted anew."""
    rng = np.random.default_rng(11)
    positions = scan(rng)
    args = placement(rng, positions, False)
    return_ranges.collect(True)
    try:
        tally = return_ranges.Tally(positions, args[10], len(positions), N_BINS)
        _, n_out, _, *counted = lidar_output._place_counted(*args, *tally.arrays)
        tally.counted(*counted)
        out = args[11][:n_out]
        out[:50] = rng.uniform(-300.0, 300.0, (50, 3))
        tally.note(out, recount=True)
        noted = return_ranges.noted(out, N_BINS)
    finally:
        return_ranges.collect(False)
    want = return_ranges.count(out, N_BINS)
    assert (noted[0], noted[1].tolist(), noted[2]) == (want[0], want[1].tolist(), want[2])


def step_link(rng: np.random.Generator, in_order: bool, grid: bool) -> tuple:
    """A step's output linked to its input (``before``): kept, attenuated and moved points (some moved to where they
    were, some to another point's ray: several returns on a ray), removed points (lists) or zeroed cells (grids),
    ADDED points appended (lists: origin NEW) or in empty cells (grids), NaN values."""
    pb = scan(rng)
    nb = len(pb)
    valid_b = return_ranges.count(pb, N_BINS)[3]
    values_b = rng.uniform(0.0, 255.0, nb).astype(np.float32)
    values_b[::97] = np.nan
    keep = np.ones(nb, bool) if in_order or grid else rng.random(nb) < 0.8
    origin = np.flatnonzero(keep)
    positions = pb[origin].copy()
    codes = rng.choice(np.array([0, 1, 2], np.uint8), len(origin), p=[0.6, 0.2, 0.2])
    moved = np.flatnonzero(codes == 2)
    positions[moved[::3]] *= rng.uniform(0.2, 0.9, (len(moved[::3]), 1))          # along the ray
    positions[moved[1::3]] = pb[origin[moved[1::3]] - 1]                            # onto another point's ray
    if grid:                                        # removed cells zeroed, empty cells filled with ADDED returns
        cut = rng.random(nb) < 0.1
        positions[cut], codes[cut] = 0.0, 0
        fill = ~valid_b & (rng.random(nb) < 0.3)
        positions[fill], codes[fill] = rng.uniform(-50.0, 50.0, (int(fill.sum()), 3)), 3
        step_origin = np.zeros(0, np.int64)
    else:
        extra = 200
        positions = np.vstack([positions, rng.uniform(-50.0, 50.0, (extra, 3))])
        codes = np.concatenate([codes, np.full(extra, 3, np.uint8)])
        step_origin = np.concatenate([origin, np.full(extra, -1)]) if not in_order else np.zeros(0, np.int64)
        if in_order:
            positions, codes = positions[:nb], codes[:nb]
    values = rng.uniform(0.0, 255.0, len(positions)).astype(np.float32)
    values[::89] = np.nan
    return positions, codes, values, pb, valid_b, values_b, (step_origin, codes)


@pytest.mark.parametrize("in_order,grid", [(False, False), (True, False), (True, True)])
def test_step_pass_with_known_returns_is_the_generic_pass(in_order, grid):
    rng = np.random.default_rng(5 + 2 * in_order + grid)
    positions, codes, values, pb, valid_b, values_b, step = step_link(rng, in_order, grid)
    none = np.zeros(0, np.bool_)
    generic = metrics._cloud_pass(positions, none, codes, values, metrics.RANGE_BIN_M, N_BINS, metrics.STEP_LINK,
                                  pb, valid_b, values_b, step)
    valid = generic[0][3]
    got = metrics._cloud_pass(positions, valid, codes, values, metrics.RANGE_BIN_M, N_BINS, metrics.STEP_LINK,
                              pb, valid_b, values_b, step)
    assert got[1].tolist() == generic[1].tolist() and got[2:4] == generic[2:4]
    index, moved, change = got[4]
    assert np.array_equal(index, generic[4][0]) and np.array_equal(moved, generic[4][1])
    assert change == generic[4][2] or (np.isnan(change) and np.isnan(generic[4][2]))
    assert moved.any() and (~moved & (index >= 0)).any() and (index < 0).any() == (not in_order or grid)
    counts = np.bincount(codes[valid], minlength=4)              # against NumPy too
    assert got[1].tolist() == counts.tolist()
    finite = valid & np.isfinite(values)
    assert got[3] == int(finite.sum()) and got[2] == pytest.approx(float(values[finite].astype(np.float64).sum()))


@pytest.mark.parametrize("in_order,origin", [(False, True), (True, False), (True, True)])
@pytest.mark.parametrize("given", ["all", "no codes", "no values", "no step codes"])
def test_unlinked_step_pass_sums_as_the_linked_one(in_order, origin, given):
    """The STEP_LINK pass of a chain's only step (no correspondence written: ``metrics._unlinked_step_pass``) gives
    the linked pass's counts, sums and mean change bit for bit — in the branches compiled with constant flags (a
    weather step's output) and in the one that tests them (no codes, no values, no step codes)."""
    rng = np.random.default_rng(17 + 2 * in_order + origin)
    positions, codes, values, pb, valid_b, values_b, (step_origin, step_codes) = step_link(rng, in_order, False)
    if origin and in_order:                         # an origin that says point i is point i (appended: NEW)
        step_origin = np.concatenate([np.arange(len(pb)), np.full(len(positions) - len(pb), -1)])
    codes = codes if given != "no codes" else np.zeros(0, np.uint8)
    values = values if given != "no values" else np.zeros(0)
    step = (step_origin, step_codes if given != "no step codes" else np.zeros(0, np.uint8))
    valid = return_ranges.count(positions, N_BINS)[3]
    args = (positions, valid, codes, values, metrics.RANGE_BIN_M, N_BINS, pb, valid_b, values_b, step)
    linked, unlinked = metrics._counted_step_pass(*args), metrics._unlinked_step_pass(*args)
    generic = metrics._step_pass(positions, np.zeros(0, np.bool_), *args[2:])
    assert linked[1].tolist() == unlinked[1].tolist() == generic[1].tolist()
    assert linked[2:4] == unlinked[2:4] == generic[2:4]
    changes = [linked[4][2], unlinked[4][2], generic[4][2]]
    assert all(np.array_equal(c, changes[0], equal_nan=True) for c in changes)
    assert np.array_equal(linked[4][0], generic[4][0]) and np.array_equal(linked[4][1], generic[4][1])
    assert len(unlinked[4][0]) == len(unlinked[4][1]) == 0
    if given == "all":                              # the change is a sum over points: some are linked in place
        assert not np.isnan(changes[0]) and (linked[4][0] >= 0).sum() > len(pb) // 2


@pytest.mark.parametrize("steps", [1, 3])
@pytest.mark.parametrize("seed", range(4))
def test_a_chain_compared_without_its_steps_links_gives_the_same_metrics(steps, seed):
    """A chain whose step outputs' geometry was noted (as the weather models note it in a run), compared step by
    step with ``linked=False`` for a chain of one step (as ``apply_models`` does) and with it for three: the same
    metrics bit for bit as with every link written, and the same correspondence when it is asked for afterwards
    (made then from the step's provenance: ``metrics._link``)."""
    from test_metrics_provenance import STEPS, random_list
    from roadview_noise.provenance import follow_points, step_input
    import dataclasses

    rng = np.random.default_rng(100 + seed)
    clouds, outputs = [random_list(rng, int(rng.integers(300, 900)), "lidar", ring=False)], [None]
    for i, name in enumerate(rng.choice(["weather", "drop", "move", "add"], size=steps)):
        outputs.append(STEPS[name](step_input(clouds[-1]), rng))
        clouds.append(follow_points(clouds[-1], outputs[-1], i))
    results = {}
    for linked in (True, False):
        items = [dataclasses.replace(c, positions_m=c.positions_m.copy()) for c in clouds]
        n_bins = return_ranges.bin_count(items[0].profile)
        return_ranges.collect(True)
        try:
            for c in items:                         # every cloud's geometry noted, as the models note it in a run
                return_ranges.note(c.positions_m, n_bins, return_ranges.count(c.positions_m, n_bins))
            got = [metrics.compare(b, a, s, linked=linked or steps > 1)
                   for b, a, s in zip(items, items[1:], outputs[1:])]
            got.append(metrics.compare(items[0], items[-1]))
            assert ("relink" in metrics._summaries[items[1]]) == (not linked and steps == 1)   # the path taken
            results[linked] = got, metrics.correspondence(items[0], items[-1]), [
                metrics.correspondence(b, a) for b, a in zip(items, items[1:])]
        finally:
            return_ranges.collect(False)
    (want, want_chain, want_steps), (got, got_chain, got_steps) = results[True], results[False]
    assert got == want
    assert all(np.array_equal(x, y) for x, y in zip(got_chain, want_chain))
    assert all(np.array_equal(x, y) for g, w in zip(got_steps, want_steps) for x, y in zip(g, w))


def test_rows_appended_after_the_blocks_are_counted_as_count_does():
    """A list's points appended after the blocks (more than a block of them, with zeros, NaN, inf and far points)
    counted by ``Tally.append`` give the output's geometry as ``return_ranges.count``."""
    rng = np.random.default_rng(23)
    positions = scan(rng, 2 * return_ranges.BLOCK)
    out = np.vstack([np.zeros((100, 3)), scan(rng, 2 * return_ranges.BLOCK + 5)])
    return_ranges.collect(True)
    try:
        tally = return_ranges.Tally(positions, None, len(out), N_BINS)
        largest_in = lidar_output._place_counted(*placement(rng, positions, False), *tally.arrays)[3]
        tally.arrays[4][:100], tally.arrays[5][:] = False, 0     # the output: 100 rows of zeros placed, then
        tally.arrays[5][0] = 100                                 # the rest appended
        tally.counted(largest_in, 0, 0.0, 0)
        tally.append(out, 100, len(out))
        tally.note(out)
        noted = return_ranges.noted(out, N_BINS)
    finally:
        return_ranges.collect(False)
    want = return_ranges.count(out, N_BINS)
    assert (noted[0], noted[1].tolist(), noted[2]) == (want[0], want[1].tolist(), want[2])
    assert np.array_equal(noted[3], want[3]) and want[0] > return_ranges.BLOCK


def placed_step(rng: np.random.Generator, grid: bool, removals: bool, unmoved: bool) -> tuple:
    """A weather step placed block by block with its metrics' sums (``_place_counted`` with ``Tally``), as
    ``lidar_output.assemble`` places it: (the Tally, the placement's arguments, the output's rows, positions, codes,
    intensities and origin — None: point i is input point i). Lists get rows appended after the blocks on the rays of
    input points (several returns on one ray; origin NEW, ADDED) and, without ``removals``, no lost targets;
    ``unmoved``: some weather returns at their target's range (MOVED at scale 1)."""
    positions = scan(rng)
    args = list(placement(rng, positions, grid))
    kind, has = args[0], args[1]
    if not removals:
        kind[(kind == NO_RETURN) & has] = TARGET
    if unmoved:
        args[2][np.flatnonzero((kind == WEATHER) & has)[::50]] = 50.0          # return range = ray range
    if not grid:                                    # lists: a weather return is on a target's ray, not an empty one
        kind[(kind == WEATHER) & ~has] = TARGET
    tally = return_ranges.Tally(positions, args[10], len(positions) + 300, N_BINS)
    outputs = (np.empty((len(positions) + 300, 3)), np.empty(len(positions) + 300, np.float32),
               np.empty(len(positions) + 300, np.uint8), np.empty(len(positions) + 300, np.int64))
    args[11:] = outputs
    _, n_out, counts, *counted = lidar_output._place_counted(*args, *tally.arrays)
    tally.counted(*counted)
    out, intensity, effect, origin = outputs
    total = n_out if grid else n_out + 300
    if not grid:                                    # appended: along input points' rays, some NaN
        rays = rng.integers(0, len(positions), total - n_out)
        out[n_out:total] = positions[rays] * rng.uniform(0.1, 0.9, (total - n_out, 1))
        intensity[n_out:total] = rng.uniform(0.0, 255.0, total - n_out)
        intensity[n_out + 3] = np.nan
        effect[n_out:total], origin[n_out:total] = 3, -1
        tally.append(out, n_out, total, effect, intensity)
    step_origin = None if grid or not (counts[3] or total > n_out) else origin[:total]
    return tally, args, out[:total], effect[:total], intensity[:total], step_origin


@pytest.mark.parametrize("grid,removals", [(False, True), (False, False), (True, True)])
@pytest.mark.parametrize("unmoved", [False, True])
def test_the_placements_step_sums_are_the_unlinked_pass(grid, removals, unmoved):
    """What the weather placement sums for the metrics' STEP_LINK pass over its output (the output rows' code counts
    and value sum block by block, the change in place in ``_place_rows``) is what ``metrics._unlinked_step_pass``
    sums over the output, bit for bit: lists with removed, moved, kept and attenuated points and rows appended on
    the rays of input points (NaN points, NaN values), grids with zeroed cells; with a MOVED row at scale 1 (the
    pass then asks whether it moved) nothing is noted, nor for a grid whose empty cells took returns after the
    blocks."""
    rng = np.random.default_rng(31 + 2 * grid + removals + 4 * unmoved)
    return_ranges.collect(True)
    try:
        tally, args, out, codes, values, origin = placed_step(rng, grid, removals, unmoved)
        tally.note(out, False, codes, values, origin)
        step = (np.zeros(0, np.int64) if origin is None else origin, codes)
        got = return_ranges.noted_link(out, codes, values, step[0], args[10])
        others = [return_ranges.noted_link(out, codes, values.copy(), step[0], args[10]),
                  return_ranges.noted_link(out, codes, values, step[0], args[10].copy())]
        valid = return_ranges.noted(out, N_BINS)[3]
    finally:
        return_ranges.collect(False)
    assert others == [None, None]                   # other arrays: not these sums
    if unmoved:
        assert got is None
        return
    pb = args[9]
    want = metrics._unlinked_step_pass(out, valid, codes, values, metrics.RANGE_BIN_M, N_BINS, pb,
                                       return_ranges.count(pb, N_BINS)[3], args[10], step)
    assert got is not None and list(got[:4]) == want[1].tolist() and got[4:6] == want[2:4]
    assert np.array_equal(got[6] / got[7], want[4][2], equal_nan=True) and got[7] > len(pb) // 4
    assert got[2] > 0 and (origin is None) == grid
    generic = metrics._step_pass(out, np.zeros(0, np.bool_), codes, values, metrics.RANGE_BIN_M, N_BINS, pb,
                                 return_ranges.count(pb, N_BINS)[3], args[10], step)
    assert list(got[:6]) == [*generic[1].tolist(), *generic[2:4]] and got[6] / got[7] == generic[4][2]


def test_grid_cells_filled_after_the_blocks_note_no_step_sums():
    rng = np.random.default_rng(41)
    return_ranges.collect(True)
    try:
        tally, _, out, codes, values, _ = placed_step(rng, True, True, False)
        added = np.flatnonzero(codes == 3)
        out[added] = rng.uniform(-80.0, 80.0, (len(added), 3))
        tally.add_rows(out, added)
        tally.note(out, False, codes, values, None)
        assert len(added) and return_ranges.noted_link(out, codes, values, np.zeros(0, np.int64),
                                                        tally.values_in) is None
    finally:
        return_ranges.collect(False)


@pytest.mark.parametrize("chain", [["fog.lidar"], ["rain.lidar"], ["fog.lidar", "rain.lidar", "snow.lidar"]])
@pytest.mark.parametrize("tree", ["lidar/os1-128/", "lidar/os1-128-grid/"])
def test_a_chain_with_the_placements_sums_gives_the_passs_metrics(monkeypatch, chain, tree):
    """The weather models' chains of one and three steps on the sample lists and grids: the same step and output
    metrics bit for bit with the placement's sums (a one-step chain on a list takes them) as with the pass."""
    from pathlib import Path

    from roadview_noise.compound import apply_models
    from roadview_noise.recipe import parse_recipe
    from roadview_noise.runner import build_models, load, plan

    root = Path(__file__).resolve().parents[1]
    steps = {"fog.lidar": {"visibility_m": 30}, "rain.lidar": {"rain_rate_mm_per_h": 20},
             "snow.lidar": {"snowfall_rate_mm_per_h": 2.5}}
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 20261122, "inputs": {"lidar": ["lidar/**/*.pcd"]},
                           "chain": [{"model": m, "params": steps[m]} for m in chain]}, source="test",
                          base_dir=root / "recipes")
    task = next(t for t in plan(root / "sample_data", recipe) if t.sample.relpath.startswith(tree))
    taken, noted_link = [], return_ranges.noted_link

    def spying(*args):
        got = noted_link(*args)
        taken.append(got is not None)
        return got

    results = []
    for sums in (False, True):
        monkeypatch.setattr(return_ranges, "noted_link", spying if sums else lambda *args: None)
        data = load(task.sample, root / "sample_data", recipe)
        out, records = apply_models(build_models(recipe, task), data, seed=recipe.seed, key=task.out_relpath,
                                    sequence_id=task.sample.sequence_id, metrics=True)
        results.append(([r.metrics for r in records], metrics.compare(data, out)))
    assert results[0] == results[1]
    assert any(taken) == (len(chain) == 1 and tree == "lidar/os1-128/")
