"""A run's workers encode each entry's manifest line (issue 19: the main process writes it as it is): the manifest is
the one the main process would have encoded, and an entry the main process must fail still records everything."""

from __future__ import annotations

import io
import json
import math
import shutil
from pathlib import Path

from roadview_noise.manifest import LINE, LINE_ONLY, dumps, encoded, entry_line, full_entry, read_manifest
from roadview_noise.outputs import Ledger
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import run

ROOT = Path(__file__).resolve().parents[1]


def _entry(name: str, path: str) -> dict:
    return {"output": f"{name}.pcd", "input": f"{name}.pcd", "status": "ok", "chain": ["fog.radar"],
            "steps": [{"model": "fog.radar", "params": {"visibility_m": 30.0}, "drawn": {"x": math.nan},
                       "seconds": 0.001}],
            "metrics": {"points_kept": 0.97}, "warnings": ["w (×2)"], "seconds": 0.002,
            "files": [{"path": path, "sha256": name}], "output_sha256": name, "staged": [[f".{name}.tmp", path]]}


def test_an_encoded_entry_carries_the_line_the_main_process_would_write():
    entry = _entry("a", "a.pcd")
    slim = encoded(entry)
    assert slim[LINE] == entry_line(entry) == dumps({k: v for k, v in entry.items() if k != "staged"})
    assert not set(LINE_ONLY) & set(slim)                      # what only the line needs does not travel twice
    assert slim["staged"] == entry["staged"] and slim["warnings"] == entry["warnings"]
    back = full_entry(slim)
    assert json.dumps(back, sort_keys=True) == json.dumps(entry, sort_keys=True)   # NaN drawn values included
    assert full_entry(entry) is entry


def test_the_ledger_writes_an_encoded_line_as_it_is_and_fails_it_in_full(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    for name in ("a", "b", "c"):
        (out / f".{name}.tmp").write_text(name)
    log = io.StringIO()
    ledger = Ledger(out, log, lambda e: None)
    a, b, c = _entry("a", "x.label"), _entry("b", "x.label"), _entry("c", "c.pcd")
    plain_line = entry_line(a)
    released = ledger.put(0, encoded(a)) + ledger.put(1, encoded(b)) + ledger.put(2, encoded(c))
    assert [e["status"] for e in released] == ["ok", "failed", "ok"]
    lines = log.getvalue().splitlines()
    assert lines[0] == plain_line and lines[2] == entry_line(c)
    failed = json.loads(lines[1])
    assert "'x.label' is also written for 'a.pcd'" in failed["error"]
    assert failed["steps"] == json.loads(entry_line(b))["steps"] and failed["metrics"] == b["metrics"]
    assert "files" not in failed and "output_sha256" not in failed and LINE not in failed
    assert (out / "x.label").read_text() == "a" and (out / "c.pcd").read_text() == "c"
    assert not (out / ".b.tmp").exists()


def _untimed(value):
    """An entry without its times (``seconds``, at any depth): what differs between two runs."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if k != "seconds"}
    if isinstance(value, list):
        return [_untimed(v) for v in value]
    return value


def test_a_runs_manifest_holds_every_key_of_the_workers_entries(tmp_path):
    tree = tmp_path / "in"
    shutil.copytree(ROOT / "sample_data" / "radar", tree / "radar")
    recipe = load_recipe(ROOT / "recipes" / "weather-fog-radar.yaml")
    lines = {}
    for w in (1, 2):
        run(recipe, tree, tmp_path / f"out{w}", workers=w, progress=False, echo=lambda m: None)
        lines[w] = [_untimed(e) for e in read_manifest(tmp_path / f"out{w}" / "manifest.jsonl")]
    assert lines[1] == lines[2] and len(lines[1]) == 3
    for e in lines[2]:
        assert e["status"] == "ok" and set(LINE_ONLY) - {"profile", "library_messages"} <= set(e)
        assert LINE not in e and "staged" not in e
