"""Issue 19: the Dask backend writes what the local workers write, ``--profile`` says where the time goes, and the
main process keeps nothing per file (streaming walk, plan, ledger and manifest)."""

from __future__ import annotations

import json
import pathlib
import shutil
import tracemalloc
from pathlib import Path

import pytest
from test_cli import CAMERA, _augment, _recipe, _tree_hashes, runner, tree  # noqa: F401

from roadview_noise.manifest import read_manifest

ROOT = Path(__file__).resolve().parents[1]
SAME = ("output", "input", "status", "error", "files", "output_sha256", "worker_deaths")


def _record(out: Path) -> list[tuple]:
    return [tuple(e.get(k) for k in SAME) for e in read_manifest(out / "manifest.jsonl")]


def test_dask_local_cluster_writes_what_two_local_workers_write(tmp_path, tree):
    pytest.importorskip("distributed")
    (tree / "cam" / "seqA" / "000009.png").write_bytes(b"\x89PNG\r\n\x1a\n cut short")   # one file fails
    recipe = _recipe(tmp_path, CAMERA)
    local = _augment(tree, tmp_path / "local", "--recipe", recipe, "--workers", 2)
    dask = _augment(tree, tmp_path / "dask", "--recipe", recipe, "--workers", 2, "--backend", "dask")
    assert local.exit_code == dask.exit_code == 1, local.output + dask.output        # the bad file, recorded
    assert _tree_hashes(tmp_path / "dask") == _tree_hashes(tmp_path / "local")
    assert len(_tree_hashes(tmp_path / "local")) == 6
    assert _record(tmp_path / "dask") == _record(tmp_path / "local")                 # plan order, same failure
    run = json.loads((tmp_path / "dask" / "run.json").read_text())
    assert run["backend"] == "dask" and run["state"] == "complete" and run["counts"]["failed"] == 1
    assert not any(p.name.startswith(".") for p in (tmp_path / "dask").rglob("*") if p.name != ".rvnoise.lock")


def test_a_worker_with_other_cpu_math_extensions_is_refused():
    """NumPy's SIMD kernels and glibc's FMA variants of exp/atan2 depend on the CPU: a worker on another CPU family
    could round differently, so the client refuses it as it refuses other library versions."""
    from roadview_noise import dask_backend
    from roadview_noise.errors import RecipeError
    from roadview_noise.manifest import library_versions

    here = library_versions()
    assert here["cpu_math"]                                  # recorded in run.json and compared with each worker

    class Client:
        def wait_for_workers(self, n, timeout): pass
        def nthreads(self): return {"tcp://a:1": 1, "tcp://b:1": 1}
        def run(self, fn): return {"tcp://a:1": fn(), "tcp://b:1": {**fn(), "cpu_math": "baseline"}}

    executor = object.__new__(dask_backend.DaskExecutor)
    executor.client = Client()
    with pytest.raises(RecipeError, match=r"tcp://b:1 .*CPU math.*cpu_math"):
        executor._check_workers()


def test_backend_options_are_checked(tmp_path, tree):
    recipe = _recipe(tmp_path, CAMERA)
    r = _augment(tree, tmp_path / "o", "--recipe", recipe, "--scheduler", "tcp://127.0.0.1:1")
    assert r.exit_code == 2 and "--backend dask" in r.output
    r = _augment(tree, tmp_path / "o", "--recipe", recipe, "--backend", "spark")
    assert r.exit_code == 2 and "unknown backend" in r.output
    assert not (tmp_path / "o").exists()


def test_profile_says_where_each_files_time_goes(tmp_path, tree):
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA), "--workers", 1, "--profile")
    assert r.exit_code == 0, r.output
    for e in read_manifest(tmp_path / "o" / "manifest.jsonl"):
        p = e["profile"]
        assert set(p) == {"read", "hash", "decode", "convert", "models", "metrics", "encode", "write", "other",
                          "total", "cpu", "peak_rss_mb"}
        assert 20 < p["peak_rss_mb"] < 4000
        assert 0 < p["cpu"] <= p["total"] + 1e-3
        assert set(p["models"]) == {"compression.camera"}
        parts = [v for k, v in p.items() if k not in ("models", "total", "cpu", "peak_rss_mb")] + \
            list(p["models"].values())
        assert all(v >= 0 for v in parts) and p["decode"] > 0 and p["encode"] > 0 and p["hash"] > 0
        assert sum(parts) == pytest.approx(p["total"], rel=0.02, abs=2e-4)
    plain = _augment(tree, tmp_path / "p", "--recipe", _recipe(tmp_path, CAMERA), "--workers", 1)
    assert plain.exit_code == 0 and "profile" not in read_manifest(tmp_path / "p" / "manifest.jsonl")[0]


def _radar_tree(root: Path, n: int) -> Path:
    """``n`` copies of the sample radar frames, 100 per folder (a folder's listing is all the walk holds)."""
    frames = sorted((ROOT / "sample_data" / "radar" / "seq0").glob("*.pcd"))
    for i in range(n):
        folder = root / f"seq{i // 100:03d}"
        folder.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(frames[i % len(frames)], folder / f"{i:06d}.pcd")
    return root


def _intern_table_bytes(snapshot: tracemalloc.Snapshot) -> int:
    """Bytes of the blocks ≥ 256 kB that pathlib allocated and still holds: the interpreter's table of interned strings
    (pathlib interns each path part) growing past a size, once, wherever it stood — not data the run keeps."""
    return sum(t.size for t in snapshot.traces if t.size >= 256_000
               and any(frame.filename == pathlib.__file__ for frame in t.traceback))


def test_the_main_process_keeps_nothing_per_file(tmp_path):
    # Python memory of the main process (walk, plan, ledger, manifest, summary) over a run of 150 and one of 900
    # files: what grows per file would show as ≥ 1 kB × 750 (an entry is 1.5–3 kB); the bound leaves room for noise.
    # The 900 new file names can push the interpreter's intern table past a resize (1.9–3.7 MB, by where earlier
    # imports left it): that block is not counted
    from roadview_noise.recipe import load_recipe
    from roadview_noise.runner import run

    recipe = load_recipe(ROOT / "recipes" / "weather-fog-radar.yaml")
    small, large = _radar_tree(tmp_path / "s" / "radar", 150).parent, _radar_tree(tmp_path / "l" / "radar", 900).parent
    run(recipe, small, tmp_path / "warm", workers=2, progress=False, echo=lambda m: None, limit=20)
    peaks = []
    for name, tree_ in (("small", small), ("large", large)):
        tracemalloc.start()
        summary = run(recipe, tree_, tmp_path / name, workers=2, progress=False, echo=lambda m: None)
        peaks.append(tracemalloc.get_traced_memory()[1] - _intern_table_bytes(tracemalloc.take_snapshot()))
        tracemalloc.stop()
        assert summary.failed == 0
    assert summary.done == 900 and len(read_manifest(tmp_path / "large" / "manifest.jsonl")) == 900
    assert peaks[1] - peaks[0] < 400_000, peaks
