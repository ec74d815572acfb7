"""Cost of the manifest metrics (issue 18 target: ≤ 10 % of `augment` time).

1. `augment` with `output.metrics` on and off, 1 worker in this process, on a 6-frame drive at the committed
   sample-data preset (camera 484×366, LiDAR 128×256 columns) and on 2 frames at full resolution (camera 1936×1464,
   OS1-128 2048 columns): CPU seconds of the process per output file (read → chain → write), the least of 5
   alternating runs. CPU time rather than wall time, so other work on a shared machine barely moves the figures.
2. One `metrics.compare` per step plus one per output, alone (CPU ms), on a full-resolution frame and a 128×2048 grid.

    .venv/bin/python bench/bench_metrics.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import yaml

from roadview_noise.compound import apply_models
from roadview_noise.dataset import load
from roadview_noise.metrics import compare
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import build_models, plan, run
from roadview_noise.sampledata.generate import generate

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ["cnf10", "cnf16", "cnf20", "cnf22", "cnf25-radar"]
REPEATS = 5


def recipe_with_metrics(name: str, on: bool, tmp: Path) -> Path:
    body = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
    body.setdefault("output", {})["metrics"] = on
    path = tmp / f"{name}-{on}.yaml"
    path.write_text(yaml.safe_dump(body))
    return path


def cpu_ms_per_file(recipe: Path, data: Path, out: Path) -> float:
    t0 = time.process_time()
    summary = run(load_recipe(recipe), data, out, workers=1, progress=False, overwrite=True, echo=lambda m: None)
    return (time.process_time() - t0) / summary.done * 1e3


def augment_overhead(data: Path, label: str, tmp: Path) -> None:
    print(f"\naugment, {label}: CPU ms per file, metrics off → on (least of {REPEATS} runs)")
    for name in RECIPES:
        paths = {on: recipe_with_metrics(name, on, tmp) for on in (False, True)}
        cpu_ms_per_file(paths[True], data, tmp / "warm")                    # kernels compiled and cached
        times = {False: [], True: []}
        for _ in range(REPEATS):
            for on in (False, True):
                times[on].append(cpu_ms_per_file(paths[on], data, tmp / f"{name}-{on}"))
        off, on = min(times[False]), min(times[True])
        print(f"  {name:<12} {off:8.1f} → {on:8.1f}  ({(on / off - 1) * 100:+5.1f} %)")


def compare_cost(data: Path) -> None:
    print("\nmetrics alone (n steps + 1 output comparisons, fresh data objects), CPU ms per file (least of 5)")
    for name in ("cnf16", "cnf20"):
        recipe = load_recipe(ROOT / "recipes" / f"{name}.yaml")
        task = next(t for t in plan(data, recipe) if "grid" in t.sample.relpath or t.sample.modality == "camera")
        models = build_models(recipe, task)
        samples = []
        for _ in range(5):
            original = load(task.sample, data, recipe)
            steps = [original]
            for k in range(1, len(models) + 1):
                steps.append(apply_models(models[:k], original, seed=recipe.seed, key=task.out_relpath,
                                          sequence_id=task.sample.sequence_id, metrics=False)[0])
            t0 = time.process_time()
            for before, after in zip(steps, steps[1:]):
                compare(before, after)
            compare(steps[0], steps[-1])
            samples.append((time.process_time() - t0) * 1e3)
        print(f"  {name:<12} {task.sample.relpath:<40} {min(samples[1:]):6.2f}")


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        small, full = tmp / "small", tmp / "full"
        generate(small, frames=6, seed=0, camera_size=(484, 366), lidar_columns=256)
        generate(full, frames=2, seed=0)
        augment_overhead(small, "6 frames, camera 484×366, LiDAR 128×256", tmp)
        augment_overhead(full, "2 frames, camera 1936×1464, LiDAR 128×2048", tmp)
        compare_cost(full)


if __name__ == "__main__":
    main()
