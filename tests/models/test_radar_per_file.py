"""Per-file shortcuts of the radar weather models (issue 19): each must give what the general path gives."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.models.radar.detection import _median_of_finite, with_loss
from roadview_noise.models.radar.weather import _attenuate_and_drop, _detection_summary
from roadview_noise.physics.radar_cfar import PROBABILITY_TIERS, CaCfar, FixedThreshold, tier_ratios
from roadview_noise.physics.numpy_sums import numpy_sum
from roadview_noise.physics.radar_frame import point_ranges_m
from roadview_noise.physics.radar_clutter import (ResolutionGrid, clutter_cells, clutter_tables, frame_cells,
                                                  generate_clutter, rain_drops, snow_flakes)
from roadview_noise.provenance import ATTENUATED, Effect, mark
from roadview_noise.profiles.radar import load_radar_profile
from roadview_noise.recipe import parse_recipe
from roadview_noise.registry import get_model
from roadview_noise.runner import build_models, plan
from roadview_noise.seeding import derive_rng

ROOT = Path(__file__).resolve().parents[2]
WAVELENGTH_M = 299_792_458.0 / 77e9


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, st.integers(1, 80), elements=st.floats(-1e6, 1e6, allow_nan=False)),
       st.sampled_from([np.nan, np.inf, -np.inf]))
def test_radar_constant_median_is_numpys_median_bit_for_bit(values, bad):
    # the finite values' median: equal order statistics are the same bits, but for the sign of a zero (partition and
    # sort may pick −0 or +0)
    with_bad = np.insert(values, len(values) // 2, bad)
    rcs = np.zeros(len(with_bad), dtype=np.float32)
    got = _median_of_finite(with_bad, rcs, np.zeros(len(with_bad)))
    assert np.float64(got).tobytes() == np.float64(np.median(values)).tobytes() or got == 0.0 == np.median(values)
    assert np.isnan(_median_of_finite(np.full(3, bad), rcs[:3], np.zeros(3)))


@pytest.mark.parametrize("detector", [CaCfar(1e-4, 16), CaCfar(5e-2, 4), FixedThreshold()])
@pytest.mark.parametrize("margin_db", [40.0, 68.0, 76.0, 95.0])
def test_tier_bounds_equal_a_search_of_every_range_bin(detector, margin_db):
    """Range bins whose lowest tier bound is above every pair are not searched: the bounds equal a search of
    them all, far and near, in rain and snow."""
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1, 1.0, 20.0)
    for h in (rain_drops(20.0), snow_flakes(2.5)):
        cells = clutter_cells(h, grid, WAVELENGTH_M, (0.3, -1.0, 0.0), 12.0 + margin_db, 12.0, 9.7, detector)
        g, ratio = cells.pair_rcs_per_m3, cells.range_ratio_per_rcs
        every = np.searchsorted(-g, -(tier_ratios(detector)[None, :] / ratio[:, None]).ravel(), side="left")
        assert cells.tier_bounds.dtype == every.dtype
        np.testing.assert_array_equal(cells.tier_bounds, every.reshape(len(ratio), PROBABILITY_TIERS))


def _numpy_cell_ratios(cells, positions, v_r):
    """ratio_at and the frame's range ratios and expected count as NumPy expressions (before round 17)."""
    t, grid = cells.tables, cells.grid
    a, b = cells.threshold_db - cells.radar_constant_db, 2e-3 * cells.gamma_db_per_km
    def sigma_t(r):
        return np.exp(math.log(10) / 10 * (a + b * r)) * (r * r) * (r * r)
    ratio = t.edges.shell_volume_per_sr_m3 / sigma_t(t.edges.range_centre_m)
    w, table, saturated = t.count_table
    expected = float(np.interp(np.log(ratio), w, table, left=0.0, right=saturated).sum())
    az_e, el_e = t.edges.azimuth_rad, t.edges.elevation_rad
    az = np.arctan2(positions[:, 1], positions[:, 0])
    el = np.arctan2(positions[:, 2], np.hypot(positions[:, 0], positions[:, 1]))
    i_az = np.clip(((az - az_e[0]) * ((len(az_e) - 1) / (az_e[-1] - az_e[0]))).astype(np.int64), 0, len(az_e) - 2)
    i_el = np.clip(((el - el_e[0]) * ((len(el_e) - 1) / (el_e[-1] - el_e[0]))).astype(np.int64), 0, len(el_e) - 2)
    m = np.floor(v_r / grid.doppler_resolution_m_per_s + 0.5).astype(np.int64) - (t.doppler_bin_min - 1)
    g = t.rcs_table[i_az * (len(el_e) - 1) + i_el, np.clip(m, 0, t.rcs_table.shape[1] - 1)]
    r = np.linalg.norm(positions, axis=1)
    dr = grid.range_resolution_m
    y = np.divide(g * (r * r * dr + dr ** 3 / 12), sigma_t(r), out=np.zeros(len(r)), where=r > 0)
    return ratio, expected, y


@pytest.mark.parametrize("detector", [CaCfar(1e-4, 16), FixedThreshold()])
@pytest.mark.parametrize("margin_db", [40.0, 76.0, 95.0])
def test_compiled_frame_cells_equal_numpys_expressions_bit_for_bit(detector, margin_db):
    """The compiled passes around NumPy's exp, log and arctan2 give the NumPy expressions' values: range ratios,
    cells per tier, expected count (NumPy's interp and pairwise sum) and each point's cell ratio, at points in and
    out of the field of view, at the origin and with Doppler outside the spectrum."""
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1, 1.0, 20.0)
    rng = np.random.default_rng(3)
    positions = rng.normal(0.0, 8.0, (300, 3)) * [1.0, 1.0, 0.3]
    positions[0] = 0.0
    positions[1] = [-5.0, 0.1, 0.0]
    v_r = rng.normal(-3.0, 4.0, 300)
    v_r[2] = 500.0
    for h in (rain_drops(20.0), snow_flakes(2.5)):
        tables = clutter_tables(h, grid, WAVELENGTH_M, (0.3, -8.0, 0.0), detector)
        cells, y = frame_cells(tables, 12.0 + margin_db, 12.0, 9.7, positions, v_r, np.linalg.norm(positions, axis=1))
        ratio, expected, y_numpy = _numpy_cell_ratios(cells, positions, v_r)
        assert ratio.tobytes() == cells.range_ratio_per_rcs.tobytes() and expected == cells.expected_count
        assert y.tobytes() == y_numpy.tobytes() == cells.ratio_at(positions, v_r).tobytes()
        totals = cells.tier_bounds.sum(axis=0)
        np.testing.assert_array_equal(cells.tier_cells, np.diff(totals, prepend=0))


def test_numpy_sum_is_numpys_sum_bit_for_bit():
    rng = np.random.default_rng(0)
    for n in (0, 1, 7, 8, 9, 95, 128, 129, 300, 1000, 4099):
        a = rng.exponential(1.0, n) * 10.0 ** rng.uniform(-6, 6, n) * rng.choice([-1.0, 1.0], n)
        assert np.float64(numpy_sum(a)).tobytes() == a.sum().tobytes()


def test_point_ranges_are_the_clouds_norms_bit_for_bit():
    src = ROOT / "sample_data" / "radar" / "seq0"
    cloud = read_pointcloud(sorted(src.glob("*.pcd"))[0], sensor="radar",
                            profile=load_radar_profile(src / "radar.yaml"))
    rng = np.random.default_rng(1)
    for positions in (cloud.positions_m, rng.normal(0, 50, (999, 3)) * 10.0 ** rng.uniform(-3, 3, (999, 1))):
        c = cloud.replace(positions_m=positions, fields={}) if positions is not cloud.positions_m else cloud
        assert point_ranges_m(c).tobytes() == c.ranges_m.tobytes()


def test_detection_summary_and_attenuate_and_drop_equal_the_numpy_steps():
    """The compiled masks and diagnostics of a radar weather step, and its one-copy attenuate-and-drop, equal the
    NumPy expressions and ``mark(with_loss(…)).drop(…)``, also for a cloud that has provenance already."""
    src = ROOT / "sample_data" / "radar" / "seq0"
    profile = load_radar_profile(src / "radar.yaml")
    cloud = read_pointcloud(sorted(src.glob("*.pcd"))[0], sensor="radar", profile=profile)
    rng = np.random.default_rng(1)
    n = len(cloud)
    r = np.linalg.norm(cloud.positions_m, axis=1)
    values, loss = rng.normal(15.0, 5.0, n), 2.0 * 9.7 * r / 1000.0
    loss[:3] = 0.0
    for rise in (np.zeros(n), rng.exponential(2.0, n)):
        removed, attenuated = np.empty(n, dtype=bool), np.empty(n, dtype=bool)
        got = _detection_summary(values, loss, 12.0, rise, r, removed, attenuated)
        margin = values - loss - 12.0
        keep = margin >= rise
        assert (~keep == removed).all() and ((loss > 0) == attenuated).all()
        assert got == (int(keep.sum()), loss.sum(), r.max(), r[keep].max(), int(((margin >= 0) & ~keep).sum()),
                       rise.max(), rise.sum())
        for c in (cloud, cloud.replace(effect=np.full(n, ATTENUATED), origin=np.arange(n)[::-1].copy())):
            fused = _attenuate_and_drop(c, loss, attenuated, removed)
            steps = mark(with_loss(c, loss), attenuated, Effect.ATTENUATED).drop(removed)
            for name in ("positions_m", "origin", "effect"):
                assert getattr(fused, name).tobytes() == getattr(steps, name).tobytes()
                assert getattr(fused, name).dtype == getattr(steps, name).dtype
            assert list(fused.fields) == list(steps.fields)
            assert all(fused.fields[k].tobytes() == steps.fields[k].tobytes() for k in steps.fields)


def test_a_frame_without_tier_picks_draws_no_points_and_points_otherwise():
    grid = ResolutionGrid(120, 30, 1, 2, 0.2, 0.1, 1.0, 20.0)
    quiet = clutter_cells(rain_drops(20.0), grid, WAVELENGTH_M, (0.0, -10.0, 0.0), 80.0, 12.0, 9.7, CaCfar(1e-4, 16))
    assert quiet.expected_count < 1
    counts = [len(generate_clutter(np.random.default_rng(s), quiet).v_r_m_per_s) for s in range(200)]
    assert 0 in counts
    empty = next(generate_clutter(np.random.default_rng(s), quiet) for s, n in enumerate(counts) if n == 0)
    assert empty.positions_m.shape == (0, 3) and empty.positions_m.dtype == np.float64
    busy = clutter_cells(rain_drops(20.0), grid, WAVELENGTH_M, (0.0, -10.0, 0.0), 95.0, 12.0, 9.7, FixedThreshold())
    pts = generate_clutter(np.random.default_rng(0), busy)
    assert len(pts.v_r_m_per_s) > 10 and pts.positions_m.shape == (len(pts.v_r_m_per_s), 3)


def test_a_static_occlusion_pattern_is_the_sequence_generators_draw_and_a_fresh_copy():
    src = ROOT / "sample_data" / "radar" / "seq0"
    model = get_model("occlusion.radar")(seed_probability=0.05)
    cloud = read_pointcloud(src / "000000.pcd", sensor="radar", profile=load_radar_profile(src / "radar.yaml"))
    n_az, n_el = (len(e) - 1 for e in model._edges(cloud))
    first = model.draw_sequence(derive_rng(3, "sequence", "s0", model.id), cloud)
    direct_n, direct_cells = model._draw_pattern(derive_rng(3, "sequence", "s0", model.id), n_az, n_el)
    assert first["seeds"] == direct_n and first["blocked_cells"] == list(direct_cells) and direct_n > 0
    first["blocked_cells"].clear()
    again = model.draw_sequence(derive_rng(3, "sequence", "s0", model.id), cloud)
    assert again["blocked_cells"] == list(direct_cells)
    other = model.draw_sequence(derive_rng(3, "sequence", "s1", model.id), cloud)
    assert other["blocked_cells"] != again["blocked_cells"]


def test_steps_without_draws_are_built_once_and_drawn_steps_per_file(tmp_path):
    src = ROOT / "sample_data" / "radar" / "seq0"
    tree = tmp_path / "in" / "radar" / "seq0"
    tree.mkdir(parents=True)
    for p in src.iterdir():
        (tree / p.name).write_bytes(p.read_bytes())
    recipe = parse_recipe({
        "schema": "rvnoise.recipe/1", "seed": 1, "inputs": {"radar": ["radar/**/*.pcd"]},
        "chain": [{"model": "rain.radar", "params": {"rain_rate_mm_per_h": {"uniform": [5, 30]}}},
                  {"model": "occlusion.radar"}]}, base_dir=tmp_path)
    tasks = plan(tmp_path / "in", recipe)
    a, b = build_models(recipe, tasks[0]), build_models(recipe, tasks[1])
    assert a[1] is b[1]
    assert a[0].rain_rate_mm_per_h != b[0].rain_rate_mm_per_h
    assert build_models(recipe, tasks[0]) == a


@pytest.mark.parametrize("chain, derived", [(["fog.radar"], []), (["occlusion.radar"], []),
                                            (["rain.radar", "occlusion.radar"], [(0, "rain.radar")])])
def test_steps_that_draw_nothing_per_frame_get_no_frame_generator(chain, derived, monkeypatch):
    """fog.radar and a static occlusion.radar draw nothing per frame: the chain derives no frame generator for them
    (≈ 20 µs per step and file) and their output is the one they give with a generator."""
    import roadview_noise.compound as compound

    src = ROOT / "sample_data" / "radar" / "seq0"
    cloud = read_pointcloud(src / "000001.pcd", sensor="radar", profile=load_radar_profile(src / "radar.yaml"))
    models = [get_model(m)(**({"seed_probability": 0.05} if m == "occlusion.radar" else {})) for m in chain]
    keys = []
    real = compound.derive_rng
    monkeypatch.setattr(compound, "derive_rng", lambda seed, *k: keys.append(k) or real(seed, *k))
    out, records = compound.apply_models(models, cloud, seed=5, key="f", sequence_id="s")
    assert [k[1:] for k in keys if k[0] == "f"] == derived
    data = cloud
    for i, m in enumerate(models):
        state = m.draw_sequence(real(5, "sequence", "s", m.id), data) if m.scope.value == "sequence" else {}
        data, _ = m.apply(data, state=state, drawn={}, rng=real(5, "f", i, m.id))
    assert np.array_equal(out.positions_m, data.positions_m)
    assert all(np.array_equal(out.fields[k], data.fields[k]) for k in data.fields)
    assert records[-1].diagnostics["points_removed"] > 0 or chain == ["fog.radar"]
