"""Do two versions of the code write the same metrics and outputs? (issue 18: speed work on the metrics must not
change a single value.)

Runs ``rvnoise augment`` with this worktree's code and with a baseline worktree's (``--baseline``, e.g. ../main;
each in a subprocess with its own tree first on ``PYTHONPATH``) on the LiDAR and radar recipes (or any shipped
recipes, camera ones too: ``--recipes``), on ``sample_data``, for LiDAR recipes on the real OS1-128 scan
(``../shared/data/os1-128/scan0.bin`` with its own beam table, when present) and with ``--generated`` on the
full-resolution generated tree of ``bench/bench_metrics.py`` (128×2048 grid and list, 1936×1464 camera), and
compares per output: the manifest's ``metrics``, every step's ``metrics`` (parsed JSON: equal floats are equal
bits) and the output files' sha256. Prints one line per recipe and input tree, exits 1 on any difference.
``--changed ssim``: metrics allowed to change (a change of method); the others must stay identical, and the largest
absolute change of each allowed one (over outputs and steps) is printed.

    .venv/bin/python bench/check_metrics_identical.py --baseline ../main [--recipes cnf25,cnf22] [--generated]
                                                      [--changed ssim]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from roadview_noise.recipe import load_recipe

ROOT = Path(__file__).resolve().parents[1]
SHARED_OS1 = ROOT.parent / "shared" / "data" / "os1-128"
RECIPES = (["weather-rain-lidar", "weather-fog-lidar", "weather-snow-lidar"]
           + [f"cnf{n}" for n in range(19, 31)]
           + ["weather-rain-radar", "weather-fog-radar", "weather-snow-radar", "cnf25-radar", "cnf26-radar",
              "cnf27-radar"])
#: one run in a fresh interpreter: the recipe, input tree, output folder, workers and LiDAR profile ('' = the recipe's)
RUN = """import sys
from pathlib import Path
from roadview_noise.overrides import with_input_overrides
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import run
recipe, tree, out, workers, lidar_profile = sys.argv[1:]
recipe = with_input_overrides(load_recipe(Path(recipe)), lidar_profile=lidar_profile or None)
run(recipe, Path(tree), Path(out), workers=int(workers), progress=False, echo=lambda m: None, warn=lambda m: None)
"""


def augment(code: Path, recipe: str, tree: Path, out: Path, workers: int, lidar_profile: str) -> dict[str, dict]:
    """The manifest entries (by output path) of one ``runner.run`` with the code of the tree ``code`` (a worktree
    or an export of a commit: ``git archive``)."""
    env = {**os.environ, "PYTHONPATH": str(code)}
    cmd = [sys.executable, "-c", RUN, str(ROOT / "recipes" / f"{recipe}.yaml"), str(tree), str(out), str(workers),
           lidar_profile]
    subprocess.run(cmd, env=env, cwd=code, check=True)     # cwd: the tree is first on sys.path
    entries = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    shutil.rmtree(out)
    return {e["output"]: e for e in entries if "output" in e}


def essentials(entry: dict, changed: tuple[str, ...] = ()) -> dict:
    """What must not change: the metrics of the output and of every step (but ``changed``), the files' hashes, the
    status."""
    def kept(metrics):
        return metrics if metrics is None else {k: v for k, v in metrics.items() if k not in changed}

    return {"status": entry.get("status"), "error": entry.get("error"), "metrics": kept(entry.get("metrics")),
            "steps": [kept(s.get("metrics")) for s in entry.get("steps", [])],
            "files": [f.get("sha256") for f in entry.get("files", [])]}


def largest_changes(a: dict, b: dict, changed: tuple[str, ...]) -> dict[str, float]:
    """The largest absolute change of each metric of ``changed`` between two entries (output and steps)."""
    pairs = [(a.get("metrics") or {}, b.get("metrics") or {})]
    pairs += [(x.get("metrics") or {}, y.get("metrics") or {}) for x, y in zip(a.get("steps", []), b.get("steps", []))]
    return {k: max((abs(x[k] - y[k]) for x, y in pairs if isinstance(x.get(k), float) and isinstance(y.get(k), float)),
                   default=0.0) for k in changed}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, required=True,
                    help="the other code: a worktree (../main) or an export (git archive COMMIT | tar -x -C DIR)")
    ap.add_argument("--recipes", help=f"comma-separated subset of {', '.join(RECIPES)}")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--generated", action="store_true", help="also the full-resolution generated sample tree")
    ap.add_argument("--changed", default="", help="comma-separated metrics allowed to change (their largest change "
                                                  "is printed)")
    args = ap.parse_args()
    changed = tuple(filter(None, args.changed.split(",")))
    recipes = args.recipes.split(",") if args.recipes else RECIPES
    different = 0
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        trees = {"sample_data": (ROOT / "sample_data", "")}
        if (SHARED_OS1 / "scan0.bin").is_file():
            real = tmp / "real"
            (real / "lidar" / "os1-128-real").mkdir(parents=True)
            shutil.copy(SHARED_OS1 / "scan0.bin", real / "lidar" / "os1-128-real" / "000000.bin")
            trees["real OS1-128"] = (real, str(SHARED_OS1 / "beam_intrinsics.json"))
        if args.generated:
            from roadview_noise.sampledata.generate import generate

            generate(tmp / "generated", frames=1, seed=0)
            trees["generated"] = (tmp / "generated", "")
        for recipe in recipes:
            for label, (tree, lidar_profile) in trees.items():
                if label == "real OS1-128" and load_recipe(ROOT / "recipes" / f"{recipe}.yaml").sensor != "lidar":
                    continue
                runs = [augment(code, recipe, tree, tmp / "out", args.workers, lidar_profile)
                        for code in (args.baseline.resolve(), ROOT)]
                bad = sorted(k for k in set(runs[0]) | set(runs[1])
                             if k not in runs[0] or k not in runs[1]
                             or essentials(runs[0][k], changed) != essentials(runs[1][k], changed))
                different += len(bad)
                steps = sum(len(e.get("steps", [])) for e in runs[1].values())
                largest = {m: max((largest_changes(runs[0][k], runs[1][k], changed)[m] for k in runs[1] if k in runs[0]),
                                  default=0.0) for m in changed}
                print(f"  {recipe:<20} {label:<12} {len(runs[1]):3d} outputs, {steps:3d} steps: "
                      + (f"DIFFERENT {bad[:3]}" if bad else "identical")
                      + "".join(f"; {m} changed by ≤ {v:.1e}" for m, v in largest.items()), flush=True)
    return 1 if different else 0


if __name__ == "__main__":
    sys.exit(main())
