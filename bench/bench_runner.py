"""Whole-runner throughput: read → chain → atomic write → manifest, per output file.

Renders a 12-frame drive at the committed sample-data preset into a temporary folder, runs each recipe once to warm
the on-disk kernel caches, then prints per recipe the wall time per output with 1 and 2 workers (process start-up
included) and the mean in-worker time per file (from the manifest), so the runner's overhead is visible.

    .venv/bin/python bench/bench_runner.py
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import run
from roadview_noise.sampledata.generate import generate

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ["recipes/cnf10.yaml", "recipes/cnf16.yaml", "recipes/cnf19.yaml", "recipes/cnf22.yaml",
           "recipes/cnf25-radar.yaml"]


def main() -> None:
    with tempfile.TemporaryDirectory() as data:
        generate(Path(data), frames=12, seed=0, camera_size=(484, 366), lidar_columns=256)
        bench(Path(data))


def bench(data: Path) -> None:
    print(f"input: 12-frame drive (camera 484×366, LiDAR 128×256 columns), {data}")
    print(f"{'recipe':<28} {'outputs':>7} {'1 worker ms/file':>17} {'2 workers ms/file':>18} "
          f"{'in-worker ms/file':>18}")
    for rel in RECIPES:
        path = ROOT / rel
        if not path.is_file():
            print(f"{rel:<28} (missing)")
            continue
        recipe = load_recipe(path)
        row = []
        with tempfile.TemporaryDirectory() as tmp:
            run(recipe, data, Path(tmp) / "warm", workers=1, limit=1, progress=False, echo=lambda m: None)
            for workers in (1, 2):
                out = Path(tmp) / f"w{workers}"
                t0 = time.perf_counter()
                s = run(recipe, data, out, workers=workers, progress=False, echo=lambda m: None)
                row.append((time.perf_counter() - t0) / max(s.done, 1) * 1e3)
            inner = statistics.mean(e["seconds"] for e in read_manifest(Path(tmp) / "w1" / "manifest.jsonl")) * 1e3
        print(f"{rel:<28} {s.done:>7} {row[0]:>17.1f} {row[1]:>18.1f} {inner:>18.1f}")


if __name__ == "__main__":
    main()
