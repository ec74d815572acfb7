"""Per-file overhead on tiny files (issue 19), paired: ``augment`` of one recipe on N copies of the sample radar
files against the plain read + write copy of the same files (``bench/plain_copy.py``, the executor ``augment``
uses), with 1 and 2 workers, optionally against a second checkout of the code (``--base DIR``: e.g.
``git archive main | tar -x -C DIR``), the versions alternating run by run.

Each run is a fresh process with the code on ``PYTHONPATH`` (so the versions never mix): it warms the fork server
with a one-file run, then times ``runner.run`` on the N files (wall, the main process's CPU, the workers' in-worker
seconds from the manifest), then the plain copy with the same number of workers. Printed: medians and ranges over
the rounds of files/s, the ratio to the copy of the same round, ms per file in a worker, the main process's CPU ms
per file, and the wall ms per file beyond the in-worker time (× workers).

    .venv/bin/python bench/bench_small_files.py [--files 600] [--rounds 5] [--recipe weather-fog-radar]
                                                [--base /tmp/main-code] [--scratch DIR]
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

ONE_RUN = r"""
import json, resource, shutil, sys, time
from pathlib import Path
import yaml
sys.path.insert(0, {bench!r})
from plain_copy import plain_copy
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
tree, out, workers, name = Path({tree!r}), Path({out!r}), {workers}, {recipe!r}
body = yaml.safe_load(Path({recipes!r}, name + ".yaml").read_text())
body["inputs"] = {{"radar": "radar/**/*.pcd"}}
recipe = parse_recipe(body, source=name, base_dir=Path({recipes!r}))
run(recipe, tree, out.with_name("warm"), workers=1, limit=1, progress=False, echo=lambda m: None)
cpu = lambda: sum(resource.getrusage(resource.RUSAGE_SELF)[:2])
c0, t0 = cpu(), time.perf_counter()
s = run(recipe, tree, out, workers=workers, progress=False, echo=lambda m: None)
wall, main_cpu = time.perf_counter() - t0, cpu() - c0
inside = sum(e["seconds"] for e in read_manifest(out / "manifest.jsonl"))
copy = plain_copy("radar", tree / "radar" / "seq0", out.with_name("copy"), workers)
print(json.dumps({{"files": s.done, "failed": s.failed, "wall": wall, "main_cpu": main_cpu, "inside": inside,
                  "copy": copy}}))
"""


def build_tree(root: Path, files: int) -> Path:
    src = ROOT / "sample_data" / "radar" / "seq0"
    dst = root / "in" / "radar" / "seq0"
    dst.mkdir(parents=True)
    for side in src.glob("*.yaml"):
        shutil.copy(side, dst)
    pcds = sorted(src.glob("*.pcd"))
    for k in range(files):
        shutil.copy(pcds[k % len(pcds)], dst / f"{k:06d}.pcd")
    return root / "in"


def one_run(code: Path, tree: Path, scratch: Path, workers: int, recipe: str) -> dict:
    out = scratch / "run" / "out"
    shutil.rmtree(out.parent, ignore_errors=True)
    out.parent.mkdir(parents=True)
    script = ONE_RUN.format(bench=str(ROOT / "bench"), tree=str(tree), out=str(out), workers=workers,
                            recipe=recipe, recipes=str(ROOT / "recipes"))
    env = {**os.environ, "PYTHONPATH": str(code)}
    done = subprocess.run([sys.executable, "-c", script], env=env, cwd=scratch, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(done.stderr[-2000:])
    r = json.loads(done.stdout.strip().splitlines()[-1])
    if r["failed"]:
        raise RuntimeError(f"{r['failed']} files failed with the code of {code}")
    n = r["files"]
    return {"files/s": n / r["wall"], "vs copy": r["copy"] / r["wall"],
            "copy files/s": n / r["copy"], "in-worker ms/file": 1e3 * r["inside"] / n,
            "main CPU ms/file": 1e3 * r["main_cpu"] / n,
            "beyond ms/file": 1e3 * (r["wall"] - r["inside"] / workers) / n}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--files", type=int, default=600)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--recipe", default="weather-fog-radar")
    ap.add_argument("--base", type=Path, help="a second checkout's root (its roadview_noise/ is run as 'base')")
    ap.add_argument("--scratch", type=Path, help="the folder for the trees (default: the system's temporary folder; "
                    "a tmpfs takes the storage out: fsync costs nothing there)")
    args = ap.parse_args()
    codes = {"this": ROOT} | ({"base": args.base.resolve()} if args.base else {})
    with tempfile.TemporaryDirectory(prefix="rvnoise-small-", dir=args.scratch) as tmp:
        scratch = Path(tmp)
        tree = build_tree(scratch, args.files)
        results: dict[tuple[str, int], list[dict]] = {}
        for r in range(args.rounds):
            for workers in (1, 2):
                order = list(codes.items()) if r % 2 == 0 else list(codes.items())[::-1]
                for label, code in order:
                    results.setdefault((label, workers), []).append(one_run(code, tree, scratch, workers,
                                                                            args.recipe))
    print(f"{args.recipe} on {args.files} sample radar files, {args.rounds} rounds (median, range):")
    keys = list(next(iter(results.values()))[0])
    print("| code | workers | " + " | ".join(keys) + " |\n|---|---|" + "---|" * len(keys))
    for (label, workers), runs in results.items():
        cells = []
        for k in keys:
            v = [x[k] for x in runs]
            cells.append(f"{statistics.median(v):.3g} ({min(v):.3g}–{max(v):.3g})")
        print(f"| {label} | {workers} | " + " | ".join(cells) + " |")
    for label in codes:
        ratio = [b["files/s"] / a["files/s"] for a, b in zip(results[(label, 1)], results[(label, 2)])]
        print(f"{label}: 2 w / 1 w {statistics.median(ratio):.2f} ({min(ratio):.2f}–{max(ratio):.2f})")


if __name__ == "__main__":
    main()
