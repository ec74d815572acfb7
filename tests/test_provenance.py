"""Point provenance: select/drop/concat keep origin, effect and attributes aligned; the chain composes per-step
provenance (origin into the chain input, effects by severity, the step that made each new point); a model that
changes the point count without saying where points come from is refused."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.errors import ModelError
from roadview_noise.model import Model, Stage
from roadview_noise.models.lidar.fog import FogLidar
from roadview_noise.models.lidar.rain import RainLidar
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.provenance import MADE_BY_STEP, NEW, Effect, combine, follow_points, gather, is_new, mark
from roadview_noise.types import PointCloud

E = Effect


def _cloud(n=10, grid=None, **kw):
    pos = np.column_stack([np.arange(1, n + 1, dtype=float), np.zeros(n), np.zeros(n)])
    return PointCloud(pos, {"v": np.arange(n, dtype=np.int32) * 10}, "lidar", grid_shape=grid, **kw)


def test_select_drop_concat_keep_provenance_aligned():
    c = _cloud(attributes={"cell": np.arange(10) + 100})
    s = c.select(np.array([True, False] * 5))
    assert s.origin.tolist() == [0, 2, 4, 6, 8] and s.effect is None and s.attributes["cell"].tolist() == [
        100, 102, 104, 106, 108]
    s2 = s.select(np.array([4, 0]))
    assert s2.origin.tolist() == [8, 0] and s2.fields["v"].tolist() == [80, 0]
    a = s2.concat(np.ones((2, 3)), {"v": np.array([7, 7])}, {"cell": np.array([5, 6])})
    assert a.origin.tolist() == [8, 0, NEW, NEW] and a.effect.tolist() == [E.KEPT, E.KEPT, E.ADDED, E.ADDED]
    assert a.attributes["cell"].tolist() == [108, 100, 5, 6]
    d = a.drop(np.array([False, True, False, False]))                      # a list: removal is absence
    assert d.origin.tolist() == [8, NEW, NEW] and d.effect.tolist() == [E.KEPT, E.ADDED, E.ADDED]
    g = _cloud(4, grid=(2, 2), attributes={"cell": np.arange(4)}).drop(np.array([False, True, False, False]))
    assert g.origin is None and g.effect.tolist() == [E.KEPT, E.REMOVED, E.KEPT, E.KEPT]
    assert g.fields["v"].tolist() == [0, 0, 20, 30] and g.attributes["cell"].tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="attribute 'cell' has 3 values for 4 points"):
        dataclasses.replace(g, attributes={"cell": np.arange(3)})


def test_effects_combine_by_severity_and_new_points_override():
    before = np.array([E.KEPT, E.ATTENUATED, E.MOVED, E.ADDED, E.REMOVED, E.REMOVED, E.ATTENUATED], np.uint8)
    step = np.array([E.ATTENUATED, E.KEPT, E.ATTENUATED, E.KEPT, E.KEPT, E.ADDED, E.MOVED], np.uint8)
    assert combine(before, step).tolist() == [E.ATTENUATED, E.ATTENUATED, E.MOVED, E.ADDED, E.REMOVED, E.ADDED,
                                              E.MOVED]
    assert is_new(np.arange(5, dtype=np.uint8)).tolist() == [False, False, True, True, False]
    assert gather(np.array([5, 6, 7]), np.array([2, NEW, 0]), fill=-9).tolist() == [7, -9, 5]


def test_follow_composes_two_steps():
    """Step 1 keeps points 1, 3, 5 (attenuating 3) and adds one; step 2 keeps its points 3, 0, 2 (moving its 0 to a
    particle) and adds one: the composed origin indexes the chain input."""
    c = _cloud(6)
    s1 = dataclasses.replace(c.select(np.array([1, 3, 5])).concat(np.ones((1, 3)), {}), attributes={})
    s1 = dataclasses.replace(s1, effect=np.array([E.KEPT, E.ATTENUATED, E.KEPT, E.ADDED], np.uint8))
    first = follow_points(c, s1, 0)
    assert first.origin.tolist() == [1, 3, 5, NEW] and first.attributes[MADE_BY_STEP].strides == (0,)
    step_in = dataclasses.replace(first, origin=None, effect=None, attributes={})
    s2 = step_in.select(np.array([3, 0, 2])).concat(np.ones((1, 3)), {})
    s2 = dataclasses.replace(s2, effect=np.array([E.KEPT, E.MOVED, E.KEPT, E.ADDED], np.uint8))
    both = follow_points(first, s2, 1)
    assert both.origin.tolist() == [NEW, 1, 5, NEW]
    assert both.effect.tolist() == [E.ADDED, E.MOVED, E.KEPT, E.ADDED]
    assert both.attributes[MADE_BY_STEP].tolist()[:2] == [0, 1] and both.attributes[MADE_BY_STEP][3] == 1


@dataclass(frozen=True)
class _Decimate(Model):
    """Test model that keeps every other point, optionally without saying so."""

    id: ClassVar[str] = "decimate_test.lidar"
    stage: ClassVar[Stage] = Stage.RAY_DROP
    sensor: ClassVar[str] = "lidar"
    honest: ClassVar[bool] = True

    def apply(self, data, *, state, drawn, rng):
        if self.honest:
            return data.select(np.arange(0, len(data), 2)), {}
        return dataclasses.replace(data, positions_m=data.positions_m[::2],
                                   fields={k: v[::2] for k, v in data.fields.items()}), {}


def test_the_chain_refuses_a_model_that_loses_track_of_its_points():
    c = _cloud(10)
    out, _ = apply_models([_Decimate()], c, seed=0, key="k", sequence_id="s")
    assert out.origin.tolist() == [0, 2, 4, 6, 8]
    liar = type("_Liar", (_Decimate,), {"honest": False})
    with pytest.raises(ModelError, match="returned 5 points for 10"):
        apply_models([liar()], c, seed=0, key="k", sequence_id="s")


def test_provenance_through_two_weather_models_and_the_step_that_made_each_point():
    """Rain then fog on a street scan (the order forced): origin indexes the chain input, effects never get milder,
    each new point knows whether rain or fog made it, and attributes follow their ray."""
    prof = os1_128()
    rng = np.random.default_rng(4)
    n = 3000
    ring = rng.integers(0, 128, n)
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))[ring]
    r = rng.uniform(3, 60, n)
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    cloud = PointCloud(pos, {"intensity": (3e4 / r ** 2).astype(np.float32), "ring": ring.astype(np.uint16)},
                       "lidar", prof, attributes={"ray_id": np.arange(n) + 1000})
    out, recs = apply_models([RainLidar(rain_rate_mm_per_h=150.0), FogLidar(visibility_m=40.0)], cloud, seed=2,
                             key="k", sequence_id="s")
    src = out.origin >= 0
    assert src.sum() > 0.5 * n and out.origin.max() < n
    np.testing.assert_array_equal(out.fields["ring"][src], cloud.fields["ring"][out.origin[src]])
    np.testing.assert_array_equal(out.attributes["ray_id"][src], cloud.attributes["ray_id"][out.origin[src]])
    made = out.attributes[MADE_BY_STEP]
    new = is_new(out.effect)
    assert set(np.unique(made[new])) == {0, 1}
    assert np.count_nonzero(made[new] == 1) >= recs[1].diagnostics["moved"]
    assert np.all(out.positions_m[src & ~new] == cloud.positions_m[out.origin[src & ~new]])


def test_replace_is_dataclasses_replace_and_checks_lengths():
    c = _cloud(4, effect=np.array([0, 1, 3, 4], np.uint8), attributes={"a": np.arange(4)})
    pos, v = c.positions_m * 2, np.zeros(4, np.int32)
    new = c.replace(positions_m=pos, fields={"v": v})
    assert type(new) is PointCloud and new.positions_m is pos and new.fields["v"] is v and list(new.fields) == ["v"]
    assert all(getattr(new, f.name) is getattr(c, f.name) for f in dataclasses.fields(PointCloud)
               if f.name not in ("positions_m", "fields"))
    assert c.positions_m is not pos and c.fields["v"][1] == 10                      # the original unchanged
    with pytest.raises(ValueError, match="field 'v' has 3 values for 4 points"):
        c.replace(fields={"v": np.zeros(3)})
    with pytest.raises(TypeError, match="no field 'colour'"):
        c.replace(colour=1)


def test_mark_on_a_cloud_without_codes_is_combine_with_kept():
    mask = np.array([True, False, True, False, True])
    for e in E:
        fresh = mark(_cloud(5), mask, e).effect
        coded = mark(_cloud(5, effect=np.zeros(5, np.uint8)), mask, e).effect
        assert fresh.dtype == np.uint8 and np.array_equal(fresh, coded)
        assert np.array_equal(fresh, np.where(mask, combine(np.zeros(5, np.uint8), np.full(5, np.uint8(e))), 0))
