"""A radar file's work in one worker, in process (issue 19): ``runner.process_encoded`` — what a run's worker does
per task: read, hash, checks, the chain with its metrics, the staged write, the manifest entry and its line — on N
copies of the sample radar files, thread CPU µs per file (mean over a pass, after a warm-up pass; the staged
temporaries are removed between files, outside the timing), optionally against a second checkout of the code
(``--base DIR``: e.g. ``git archive main | tar -x -C DIR``), the versions alternating run by run, each in a fresh
process with its code on ``PYTHONPATH`` and its folder as the working directory. Printed per recipe: the median
and range over the rounds of each run's best pass.

    .venv/bin/python bench/bench_radar_per_file.py [--files 300] [--passes 3] [--rounds 3] [--base /tmp/main-code]
                                                   [--recipes weather-fog-radar,weather-rain-radar,...]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
from pathlib import Path

from bench_radar_chain import run_script

ROOT = Path(__file__).resolve().parents[1]
RECIPES = "weather-fog-radar,weather-rain-radar,weather-snow-radar,cnf25-radar"

ONE_RUN = r"""
import json, os, time, yaml
from pathlib import Path
from roadview_noise.recipe import parse_recipe
from roadview_noise import runner
tree, out, recipes = Path({tree!r}), Path({out!r}), Path("recipes")
result = {{}}
for name in {names!r}:
    body = yaml.safe_load((recipes / (name + ".yaml")).read_text())
    body["inputs"] = {{"radar": "radar/**/*.pcd"}}
    recipe = parse_recipe(body, source=name, base_dir=recipes)
    ctx = runner.RunContext(tree, out, recipe, capture_output=True, fsync_outputs=False)
    tasks = runner.plan(tree, recipe)
    passes = []
    for _ in range({passes} + 1):
        cpu = 0.0
        for t in tasks:
            c0 = time.thread_time()
            e = runner.process_encoded(t, ctx)
            cpu += time.thread_time() - c0
            assert e["status"] == "ok", e
            for tmp, _ in e["staged"]:
                os.unlink(out / tmp)
        passes.append(cpu / len(tasks) * 1e6)
    result[name] = min(passes[1:])
print(json.dumps(result))
"""


def build_tree(root: Path, files: int) -> Path:
    src = ROOT / "sample_data" / "radar" / "seq0"
    dst = root / "in" / "radar" / "seq0"
    dst.mkdir(parents=True)
    shutil.copy(src / "radar.yaml", dst)
    pcds = sorted(src.glob("*.pcd"))
    for i in range(files):
        shutil.copy(pcds[i % len(pcds)], dst / f"{i:06d}.pcd")
    return (root / "in").resolve()


def one_run(code: Path, tree: Path, out: Path, names: list[str], passes: int) -> dict[str, float]:
    out.mkdir(parents=True, exist_ok=True)
    return run_script(code, ONE_RUN.format(tree=str(tree), out=str(out.resolve()), names=names, passes=passes))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--files", type=int, default=300)
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--recipes", default=RECIPES)
    ap.add_argument("--base", type=Path, help="a second checkout's root (run as 'base')")
    args = ap.parse_args()
    names = args.recipes.split(",")
    codes = {"this": ROOT, **({"base": args.base.resolve()} if args.base else {})}
    results: dict[tuple[str, str], list[float]] = {}
    with tempfile.TemporaryDirectory() as scratch:
        tree = build_tree(Path(scratch), args.files)
        for _ in range(args.rounds):
            for label, code in codes.items():
                for name, us in one_run(code, tree, Path(scratch) / f"out-{label}", names, args.passes).items():
                    results.setdefault((label, name), []).append(us)
    print(f"thread CPU µs per radar file in process ({args.files} files, best of {args.passes} passes; median "
          f"(range) over {args.rounds} rounds)")
    print("| recipe | " + " | ".join(codes) + " |\n|---|" + "---|" * len(codes))
    for name in names:
        cells = [f"{statistics.median(v):.0f} ({min(v):.0f}–{max(v):.0f})"
                 for v in (results[label, name] for label in codes)]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
