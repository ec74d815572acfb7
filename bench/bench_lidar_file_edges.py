"""A LiDAR file's per-file CPU in the worker (issue 19), paired: ``runner.process`` — what a worker runs per file —
on the bench's rendered 128×2048 scans (OS1-128 point lists, or their KITTI ``.bin`` copies), in one process per
run, optionally against a second checkout (``--base DIR``: e.g. ``git archive main | tar -x -C DIR``), the versions
alternating run by run.

Each run is a fresh process with its code first on ``sys.path`` and as its working folder (so the versions never
mix): it processes the files ``--passes`` times (the first pass warms the process: tables, kernels, the
allocator's heap) and records the worker thread's CPU time of each later file and its ``--profile`` split (read,
hash, decode, metrics, encode, write, other: wall ms, so they include any wait for a core on a loaded machine;
``cpu`` does not). Outputs are staged and deleted, never renamed. Printed: medians and ranges over the rounds of
the per-run medians. Thread CPU is what a loaded machine measures best; 2 w / 1 w needs an idle one
(``bench/run.py --quick --repeat 2 --sensors lidar --only-table``).

    .venv/bin/python bench/bench_lidar_file_edges.py [--rounds 3] [--passes 3] [--kitti] [--base /tmp/main-code]
                                                     [--recipes weather-rain-lidar,cnf20]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ["weather-fog-lidar", "weather-rain-lidar", "weather-snow-lidar", "cnf20"]
SPLIT = ("read", "hash", "decode", "metrics", "encode", "write", "other")

ONE_RUN = r"""
import json, os, shutil, statistics, sys, time
from pathlib import Path
sys.path.insert(0, os.getcwd())
import yaml
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import RunContext, plan, process
tree, out, name, glob, passes = Path({tree!r}), Path({out!r}), {recipe!r}, {glob!r}, {passes}
body = yaml.safe_load(Path({recipes!r}, name + ".yaml").read_text())
body["inputs"] = {{"lidar": glob}}
recipe = parse_recipe(body, source=name, base_dir=Path({recipes!r}))
out.mkdir(parents=True)
ctx = RunContext(tree.resolve(), out.resolve(), recipe, profile=True, fsync_outputs=False)
tasks = plan(ctx.in_root, recipe)
cpu, split = [], {{}}
for p in range(passes):
    for t in tasks:
        c0 = time.thread_time()
        e = process(t, ctx)
        c = time.thread_time() - c0
        if e["status"] != "ok":
            raise SystemExit(e.get("error"))
        if p:
            cpu.append(c)
            for k, v in e["profile"].items():
                if isinstance(v, float):
                    split.setdefault(k, []).append(v)
        for tmp, _ in e["staged"]:
            os.unlink(out / tmp)
shutil.rmtree(out)
print(json.dumps({{"cpu": statistics.median(cpu), **{{k: statistics.median(v) for k, v in split.items()}}}}))
"""


def build_tree(root: Path, kitti: bool) -> tuple[Path, str]:
    """The bench's rendered drive (bench/run.py: 4 frames at the profiles' full column count), its OS1-128 list or
    KITTI ``.bin`` folder; returns the tree and its input glob."""
    from roadview_noise.sampledata.generate import generate

    generate(root / "render", frames=4, seed=0)
    name = "os1-128-kitti" if kitti else "os1-128"
    dst = root / "in" / "lidar" / "seq0"
    shutil.copytree(root / "render" / "lidar" / name / "seq0", dst)
    shutil.rmtree(root / "render")
    return root / "in", "lidar/**/*.bin" if kitti else "lidar/**/*.pcd"


def one_run(code: Path, tree: Path, glob: str, scratch: Path, recipe: str, passes: int) -> dict:
    script = ONE_RUN.format(tree=str(tree), out=str(scratch / "out"), recipe=recipe, glob=glob, passes=passes,
                            recipes=str(ROOT / "recipes"))
    env = {**os.environ, "PYTHONPATH": str(code)}
    done = subprocess.run([sys.executable, "-c", script], env=env, cwd=code, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(done.stderr[-2000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--passes", type=int, default=3, help="passes over the 4 files per run (the first warms)")
    ap.add_argument("--kitti", action="store_true", help="the KITTI .bin copies of the scans")
    ap.add_argument("--recipes", default=",".join(RECIPES))
    ap.add_argument("--base", type=Path, help="a second checkout's root (its roadview_noise/ is run as 'base')")
    args = ap.parse_args()
    codes = {"this": ROOT} | ({"base": args.base.resolve()} if args.base else {})
    results: dict[tuple[str, str], list[dict]] = {}
    with tempfile.TemporaryDirectory(prefix="rvnoise-lidar-edges-") as tmp:
        scratch = Path(tmp)
        tree, glob = build_tree(scratch, args.kitti)
        for r in range(args.rounds):
            for recipe in args.recipes.split(","):
                order = list(codes.items()) if r % 2 == 0 else list(codes.items())[::-1]
                for label, code in order:
                    results.setdefault((recipe, label), []).append(
                        one_run(code, tree, glob, scratch, recipe, args.passes))
    print(f"ms per file ({'KITTI .bin' if args.kitti else 'OS1-128 PCD'} 128×2048 scans, {args.rounds} rounds, "
          f"load {os.getloadavg()[0]:.1f} at the end; median (range) of the runs' medians; split: wall ms):")
    print("| recipe | code | thread CPU | " + " | ".join(SPLIT) + " |\n|---|---|---|" + "---|" * len(SPLIT))
    for (recipe, label), runs in results.items():
        cells = []
        for k in ("cpu", *SPLIT):
            v = [1e3 * x[k] for x in runs]
            cells.append(f"{statistics.median(v):.1f} ({min(v):.1f}–{max(v):.1f})" if k == "cpu" else
                         f"{statistics.median(v):.1f}")
        print(f"| {recipe} | {label} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
