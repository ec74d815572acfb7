"""What a run's worker looks up or encodes once instead of per file (issue 19, round 16): each shortcut must give
what the per-file path gives, and a new run must look again."""

from __future__ import annotations

import io
import json
import math
import shutil
from pathlib import Path

import numpy as np
import yaml

from roadview_noise.compound import apply_models
from roadview_noise.dataset import load
from roadview_noise.manifest import _default, dumps, entry_line
from roadview_noise.models.radar import weather
from roadview_noise.recipe import load_recipe, parse_recipe
from roadview_noise.runner import RunContext, _read_to_end, build_models, plan, process

ROOT = Path(__file__).resolve().parents[1]


def _json(obj) -> str:
    return json.dumps(obj, default=_default, ensure_ascii=False, allow_nan=True)


def test_a_one_step_chains_shared_metrics_give_the_line_json_dumps_gives():
    metrics = {"points_in": 68, "max_range_m_in": 71.9692416199808, "points_per_10m_in": [2, 4, 15],
               "mean_snr_change_db": -0.7636919180552165, "odd": math.nan}
    step = {"model": "rain.radar", "params": {"rain_rate_mm_per_h": 20.0, "detector": "cfar"}, "state": {},
            "drawn": {}, "diagnostics": {"détecteur": "cfar", "v": [0.0, np.float32(1.5)]}, "seconds": 0.0086,
            "metrics": metrics}
    entry = {"output": "a.pcd", "depth": None, "variant": {}, "chain": ["rain.radar"], "metrics": metrics,
             "steps": [step], "files": [{"path": "a.pcd", "sha256": "x"}], "staged": [["t", "a.pcd"]],
             "status": "ok", "seconds": 0.021}
    want = _json({k: v for k, v in entry.items() if k != "staged"})
    assert entry_line(entry) == want
    assert entry_line({**entry, "metrics": dict(metrics)}) == want          # not shared: encoded twice, same text
    for obj in ("é\u2028", 1, 2.5, math.inf, None, [], {}, {"a": [1, {"b": np.int64(3)}]}):
        assert dumps(obj) == _json(obj)
    # the line is encoded with a mark in the metrics' two places: a value or key holding the mark's text (a file
    # named so, a diagnostic) still gives json.dumps' line
    mark = "\x00rvnoise-metrics\x00"
    for odd in ({"output": f'a"{mark}.pcd'}, {"output": mark}, {"metrics": metrics, "note": {"metrics": mark}},
                {"steps": [{**step, "diagnostics": {"metrics": mark}}]}, {"files": [{"path": f'{mark}", "x'}]}):
        e = {**entry, **odd}
        assert entry_line(e) == _json({k: v for k, v in e.items() if k != "staged"})


class _Pieces(io.RawIOBase):
    """A file that answers each read with at most ``piece`` bytes (a short read), growing by ``extra``."""

    def __init__(self, data: bytes, piece: int):
        self.data, self.piece, self.pos = data, piece, 0

    def read(self, n: int = -1) -> bytes:
        out = self.data[self.pos:self.pos + min(n, self.piece)]
        self.pos += len(out)
        return out


def test_an_input_read_once_is_read_to_its_end_after_a_short_read_or_when_it_grew():
    data = bytes(range(256)) * 40
    assert _read_to_end(_Pieces(data, 1 << 20), len(data)) == data
    assert _read_to_end(_Pieces(data, 1000), len(data)) == data               # short reads
    assert _read_to_end(_Pieces(data, 1 << 20), len(data) - 100) == data      # grew after its fstat
    assert _read_to_end(_Pieces(b"", 10), 0) == b""


def _radar_tree(root: Path) -> Path:
    seq = root / "in" / "radar" / "seq0"
    seq.mkdir(parents=True)
    shutil.copy(sorted((ROOT / "sample_data" / "radar" / "seq0").glob("*.pcd"))[0], seq / "000000.pcd")
    return (root / "in").resolve()


def test_a_new_run_looks_for_the_profile_sidecar_again(tmp_path):
    """The profile of a folder is looked up once per run, not once per process: a radar.yaml added after a run is
    the next run's profile."""
    tree = _radar_tree(tmp_path)
    recipe = load_recipe(ROOT / "recipes" / "weather-fog-radar.yaml")
    task = plan(tree, recipe)[0]
    first = process(task, RunContext(tree, tmp_path.resolve(), recipe))
    side = yaml.safe_load((ROOT / "sample_data" / "radar" / "seq0" / "radar.yaml").read_text())
    side["max_range_m"] = float(side.get("max_range_m", 200.0)) / 2
    (tree / "radar" / "seq0" / "radar.yaml").write_text(yaml.safe_dump(side))
    second = process(task, RunContext(tree, tmp_path.resolve(), recipe))
    key = "profile_max_range_in_weather_m"
    assert first["status"] == second["status"] == "ok"
    assert second["steps"][0]["diagnostics"][key] < first["steps"][0]["diagnostics"][key]


def test_the_radar_weathers_per_profile_set_up_gives_the_per_frame_outputs():
    """γ, the particles, the grid and the detector made once per model and profile give the outputs and records
    of the same models made afresh for each frame (rain, snow with the fixed detector, fog; drawn rain rates)."""
    tree = (ROOT / "sample_data").resolve()
    for name, change in (("weather-rain-radar", {}), ("weather-snow-radar", {"detector": "fixed"}),
                         ("weather-fog-radar", {}), ("weather-rain-radar", {"rain_rate_mm_per_h":
                                                                            {"uniform": [5.0, 40.0]}})):
        body = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
        body["chain"][0].setdefault("params", {}).update(change)
        recipe = parse_recipe(body, source=name, base_dir=ROOT / "recipes")
        for task in plan(tree, recipe):
            data = load(task.sample, tree, recipe)
            runs = []
            for fresh in (False, True):
                if fresh:
                    weather._per_profile.clear()
                out, records = apply_models(build_models(recipe, task), data, seed=recipe.seed, key=task.out_relpath,
                                            sequence_id=task.sample.sequence_id)
                runs.append((out.positions_m.tobytes(), sorted(out.fields), dumps([r.as_entry() | {"seconds": 0}
                                                                                    for r in records])))
            assert runs[0] == runs[1], (name, change, task.out_relpath)
    assert 0 < len(weather._per_profile) <= weather.MAX_PER_PROFILE
