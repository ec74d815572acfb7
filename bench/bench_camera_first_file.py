"""What a camera worker's first file costs beyond the later ones, paired with another checkout (issue 19 round 11):
with 12 files on 2 workers each worker pays it once, side by side, so it weighs like a fixed cost of the run.

A child process per side imports what the fork server imports (``executor.PRELOAD``, the recipe's worker modules,
the warm-up), then forks fresh workers one after the other, as the fork server does; each runs the first ``--files``
files of ``bench/run.py``'s camera tree (rendered 1936×1464 frames made photo-like, range EXR) through
``runner.process`` with ``--profile`` and reports per file its thread CPU ms, minor page faults and the profile split
(the profile's wall ms: noisy on a loaded machine). The first file's extra page faults are also given in ms at
this machine's cost of a fresh-page fault (:func:`fault_us`: a first touch of anonymous memory, ≈ 3 µs on the
2-core VM): the share of the first file's extra that is its heap growing to the frame's high-water mark.
Sides alternate (this checkout's code, then ``--against``'s, its package first on ``PYTHONPATH`` and as the working
directory); figures are medians over workers and rounds, with their range. The physics tables are read from the
table cache as a repeated run finds them (each side's first worker of the first round fills it). The outputs'
decoded pixels must be the same on both sides (checked; their PNG bytes may differ: the encoder's settings).

    .venv/bin/python bench/bench_camera_first_file.py --against /tmp/main [--rounds 3] [--workers 3]
                                                     [--recipes weather-snow,cnf12] [--files 3]
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PHASES = ("read", "hash", "decode", "convert", "metrics", "encode", "write", "other")


def child(recipe_name: str, tree: Path, out_root: Path, workers: int, files: int) -> list[list[dict]]:
    """In the side's process: import like the fork server, then per worker fork, run ``files`` files, report."""
    from run import recipe_for     # bench/run.py

    from roadview_noise.executor import PRELOAD
    from roadview_noise.runner import RunContext, plan, process, worker_modules

    recipe = recipe_for(recipe_name, "camera")
    for module in PRELOAD + worker_modules(recipe) + ["roadview_noise.warmup"]:
        importlib.import_module(module)
    tasks = plan(tree, recipe)[:files]
    result = []
    for w in range(workers):
        out = out_root / f"w{w}"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        read_fd, write_fd = os.pipe()
        pid = os.fork()
        if pid == 0:                                   # a fresh worker
            os.close(read_fd)
            ctx = RunContext(tree.resolve(), out.resolve(), recipe, profile=True)
            rows = []
            for task in tasks:
                faults, cpu = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.thread_time()
                entry = process(task, ctx)
                rows.append({"cpu_ms": 1e3 * (time.thread_time() - cpu), "status": entry["status"],
                             "faults": resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults,
                             "split": {k: 1e3 * entry["profile"].get(k, 0.0) for k in PHASES},
                             "models": {k: 1e3 * v for k, v in entry["profile"]["models"].items()},
                             "sha256": _pixels_sha256(out, entry)})
            os.write(write_fd, json.dumps(rows).encode())
            os._exit(0)
        os.close(write_fd)
        with os.fdopen(read_fd, "rb") as fh:
            result.append(json.loads(fh.read()))
        os.waitpid(pid, 0)
    return result


def _pixels_sha256(out: Path, entry: dict) -> str | None:
    """sha256 of the decoded pixels of an entry's output image (final, or still its staged temporary), None if it
    has none."""
    import hashlib

    import cv2

    paths = [out / p for tmp, final in entry.get("staged", ()) if final == entry.get("output") for p in (final, tmp)]
    found = [p for p in paths if p.exists()]
    pixels = cv2.imread(str(found[0]), cv2.IMREAD_UNCHANGED) if found else None
    return None if pixels is None else hashlib.sha256(pixels.tobytes()).hexdigest()


def fault_us(rounds: int = 3, size: int = 32 << 20) -> float:
    """Thread CPU µs of one minor page fault here: the median over ``rounds`` first touches of ``size`` bytes of
    fresh anonymous memory, a byte per page."""
    import mmap

    import numpy as np

    costs = []
    for _ in range(rounds):
        with mmap.mmap(-1, size) as m:
            pages = np.frombuffer(m, np.uint8)[::mmap.PAGESIZE]
            faults, cpu = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.thread_time()
            pages[:] = 1
            costs.append(1e6 * (time.thread_time() - cpu) /
                         max(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults, 1))
            del pages
    return statistics.median(costs)


def _med(values: list[float]) -> str:
    return f"{statistics.median(values):.1f} ({min(values):.1f}–{max(values):.1f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", type=Path, required=True, help="the other checkout (e.g. git archive main)")
    ap.add_argument("--recipes", default="weather-snow,cnf12")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--workers", type=int, default=3, help="fresh workers per side and round")
    ap.add_argument("--files", type=int, default=3, help="files per worker (the first, then later ones)")
    ap.add_argument("--child", nargs=4, metavar=("RECIPE", "TREE", "OUT", "RESULT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        recipe_name, tree, out, result = args.child
        Path(result).write_text(json.dumps(child(recipe_name, Path(tree), Path(out), args.workers, args.files)))
        return
    sys.path.insert(0, str(ROOT / "bench"))
    from run import build_trees

    sides = {"this": ROOT, "against": args.against.resolve()}
    with tempfile.TemporaryDirectory(prefix="rvnoise-first-file-") as tmp:
        root = Path(tmp)
        tree = build_trees(root, 4, {"camera": max(args.files, 1)})["camera"]
        per_fault_us = fault_us()
        print(f"# camera first file vs later ones, {args.workers} fresh workers × {args.rounds} rounds per side, "
              f"{args.files} files each; load average {os.getloadavg()[0]:.1f} at the start; a page fault "
              f"{per_fault_us:.1f} µs\n")
        print("| recipe | side | first file CPU ms | later files CPU ms | first − later | first − later faults (≈ ms) | "
              "first − later by phase (ms, medians) |\n|---|---|---|---|---|---|---|")
        for name in args.recipes.split(","):
            got: dict[str, list[list[dict]]] = {s: [] for s in sides}
            for r in range(args.rounds):
                for side in (sides if r % 2 == 0 else dict(reversed(list(sides.items())))):
                    path = root / f"{name}-{side}.json"
                    env = {**os.environ, "PYTHONPATH": f"{sides[side]}{os.pathsep}{sides[side] / 'bench'}"}
                    subprocess.run([sys.executable, str(Path(__file__).resolve()), "--against", str(args.against),
                                    "--workers", str(args.workers), "--files", str(args.files), "--child", name,
                                    str(tree), str(root / f"out-{side}"), str(path)],
                                   cwd=sides[side], env=env, check=True)
                    got[side] += json.loads(path.read_text())
            shas = {side: {tuple(f["sha256"] for f in w) for w in got[side]} for side in sides}
            if len(shas["this"] | shas["against"]) != 1 or any(f["status"] != "ok" for s in got.values()
                                                                for w in s for f in w):
                raise SystemExit(f"{name}: outputs differ between the sides or a file failed: {shas}")
            for side, workers in got.items():
                first = [w[0]["cpu_ms"] for w in workers]
                later = [statistics.median(f["cpu_ms"] for f in w[1:]) for w in workers if len(w) > 1]
                extra = [w[0]["cpu_ms"] - statistics.median(f["cpu_ms"] for f in w[1:]) for w in workers
                         if len(w) > 1]
                phases = {k: statistics.median(w[0]["split"][k] - statistics.median(f["split"][k] for f in w[1:])
                                               for w in workers if len(w) > 1) for k in PHASES}
                phases.update({m: statistics.median(w[0]["models"][m] - statistics.median(f["models"][m]
                                                                                          for f in w[1:])
                                                    for w in workers if len(w) > 1)
                               for m in workers[0][0]["models"]})
                faults = statistics.median([w[0]["faults"] - statistics.median(f["faults"] for f in w[1:])
                                            for w in workers if len(w) > 1] or [w[0]["faults"] for w in workers])
                split = ", ".join(f"{k} {v:+.1f}" for k, v in phases.items() if abs(v) >= 0.5)
                print(f"| {name} | {side} | {_med(first)} | {_med(later) if later else '—'} | "
                      f"{_med(extra) if extra else '—'} | {faults:.0f} (≈ {faults * per_fault_us / 1e3:.0f}) | "
                      f"{split} |", flush=True)
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
