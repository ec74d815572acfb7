"""Instructions per radar file (issue 19), in the worker and in the main process: callgrind counts, which the load
of a shared machine does not move (wall and CPU times on the 2-core VM swing by ± 50 % between runs of one code).

- **worker**: a worker's loop in one warm process — each task's pickle loaded, ``runner.process_encoded``, its
  answer pickled, as ``executor._worker_main`` does — over N copies of the sample radar files, after two passes
  that callgrind does not instrument (``--instr-atstart=no``, then a client request), the garbage collector frozen:
  instructions per file of the third pass (the staged temporaries are removed after it).
- **main**: a whole ``runner.run`` with ``--workers`` workers, the main process counted from its call of ``run`` to
  its return (its fsync threads included), the workers native (``--trace-children=no``: the fork server is a
  spawned interpreter); per file as the difference of an N-file and an N/5-file run (``limit``), so what a run
  pays once cancels. The main process under callgrind is ≈ 50× slower than its workers, so it finds every
  worker's answers batched: the count is that of a main process that is never ahead of its workers.

Numba compiles for an AVX2 target (``NUMBA_CPU_NAME=haswell``: valgrind runs no AVX-512) and a native run of each
harness fills its caches and the physics table cache first. ``--base DIR`` (e.g. ``git archive main | tar -x -C
DIR``) runs DIR's code the same way, alternating with this tree's. The recipe name ``copy`` counts the plain copy's
task of ``bench/run.py`` (``bench/plain_copy.copy_one``: read, decode, encode, write; its fsync is kernel time) in
the same loop, against which the radar line of issue 19 is stated.

    .venv/bin/python bench/bench_radar_instructions.py [--files 300] [--workers 2] [--base DIR] [--split [F,…]]
                                                       [--recipes weather-fog-radar,weather-rain-radar,...]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_metrics import VG_LIB, VG_TARGET    # bench/ is the script's folder, first on sys.path
from bench_small_files import build_tree

ROOT = Path(__file__).resolve().parents[1]
RECIPES = "weather-fog-radar,weather-rain-radar,weather-snow-radar,cnf25-radar"
COMMON = r"""
import ctypes, gc, os, pickle, sys, yaml
from pathlib import Path
from roadview_noise.recipe import parse_recipe
from roadview_noise import runner
name, tree, out, recipes, n = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]), int(sys.argv[5])
copy = name == "copy"
name = "weather-fog-radar" if copy else name
lib = ctypes.CDLL(os.environ["RVNOISE_VG_LIB"]) if os.environ.get("RVNOISE_VG_ON") else None
body = yaml.safe_load((recipes / (name + ".yaml")).read_text())
body["inputs"] = {"radar": "radar/**/*.pcd"}
recipe = parse_recipe(body, source=name, base_dir=recipes)
"""
WORKER = COMMON + r"""
ctx = runner.RunContext(tree, out, recipe, capture_output=True, fsync_outputs=False)
tasks = runner.plan(tree, recipe)[:n]
staged = []
if copy:                        # the plain copy's task (bench/plain_copy.py: read, decode, encode, write + fsync)
    from plain_copy import copy_one
    payloads = [pickle.dumps((i, ("radar", str(tree / t.sample.relpath), str(out / f"{i:06d}.pcd"), False, None)),
                             pickle.HIGHEST_PROTOCOL) for i, t in enumerate(tasks)]
else:
    payloads = [pickle.dumps((i, t), pickle.HIGHEST_PROTOCOL) for i, t in enumerate(tasks)]


def one_pass():
    for p in payloads:
        tid, task = pickle.loads(p)
        if copy:
            pickle.dumps([(tid, copy_one(task))], pickle.HIGHEST_PROTOCOL)
            continue
        result = runner.process_encoded(task, ctx)
        pickle.dumps([(tid, result)], pickle.HIGHEST_PROTOCOL)
        staged.extend(result["staged"])


split = [x for x in os.environ.get("RVNOISE_VG_SPLIT", "").split(",") if x]
if split and lib:               # count each named function apart: a dump as it is entered and left (innermost wins)
    import importlib
    stack = []

    def wrap(label, fn):
        def call(*args, **kwargs):
            lib.vg_dump(("seg " + (stack[-1] if stack else "rest")).encode())
            stack.append(label)
            try:
                return fn(*args, **kwargs)
            finally:
                lib.vg_dump(("seg " + label).encode())
                stack.pop()
        return call

    for full in split:
        module, attr = full.rsplit(".", 1)
        try:
            owners = [importlib.import_module(module)]
        except ModuleNotFoundError:                 # a class's method: module.Class.method
            module, cls = module.rsplit(".", 1)
            owners = [getattr(importlib.import_module(module), cls)]
        fn = getattr(owners[0], attr)
        if not isinstance(owners[0], type):         # a function: wherever a module holds it
            owners = [m for k, m in list(sys.modules.items()) if k.startswith("roadview_noise")]
        for m in owners:
            for k, v in list(vars(m).items()):
                if v is fn:
                    setattr(m, k, wrap(full.removeprefix("roadview_noise."), fn))
for counted in (False, False, True):
    if counted:
        gc.freeze()
        if lib:
            lib.vg_start()
    one_pass()
    if counted and lib:
        lib.vg_dump(b"seg rest" if split else b"files")
    for tmp, _ in staged:
        os.unlink(out / tmp)
    staged.clear()
"""
MAIN = COMMON + r"""
workers = int(sys.argv[6])
if lib:
    lib.vg_start()
s = runner.run(recipe, tree, out, workers=workers, limit=n, progress=False, echo=lambda m: None,
               warn=lambda m: None)
if lib:
    lib.vg_dump(b"main")
assert s.done == n and not s.failed, s
"""


def counted(code: Path, script: str, args: list, tmp: Path, valgrind: bool, split: str = "") -> dict[str, int]:
    """Instructions of the run's dumps by label ({} without valgrind: the native warm run); ``split``: the functions
    the worker harness counts apart (``seg NAME``; ``seg rest``: outside them)."""
    cg = tmp / "cg"
    shutil.rmtree(cg, ignore_errors=True)
    cg.mkdir()
    env = {**os.environ, **VG_TARGET, "PYTHONPATH": f"{code}:{ROOT / 'bench'}",
           "RVNOISE_TABLE_CACHE": str(tmp / "tables"), "RVNOISE_VG_LIB": str(tmp / "libvg.so")}
    vg = []
    if valgrind:
        env["RVNOISE_VG_ON"] = "1"
        env["RVNOISE_VG_SPLIT"] = split
        vg = ["valgrind", "--tool=callgrind", "--instr-atstart=no", "--trace-children=no",
              f"--callgrind-out-file={cg}/cg.%p"]
    done = subprocess.run(vg + [sys.executable, "-c", script, *map(str, args)], env=env, cwd=code,
                          capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(done.stderr[-3000:])
    totals: dict[str, int] = {}
    for f in cg.iterdir():
        text = f.read_text(errors="replace")
        label = re.search(r"^desc: Trigger: (?:Client Request: )?(.*)$", text, re.M).group(1)
        if label in ("files", "main") or label.startswith("seg "):
            totals[label] = totals.get(label, 0) + int(re.search(r"^summary: (\d+)", text, re.M).group(1))
    return totals


#: --split: the worker's phases counted apart by default
SPLIT_DEFAULT = ",".join(f"roadview_noise.{n}" for n in (
    "runner.input_path", "runner.sha256_input", "runner._check_sizes", "runner.load", "runner.drop_invalid_points",
    "annotations.read", "compound.apply_models", "seeding.derive_rng", "compound.follow", "metrics.Deferred.compare",
    "annotations.carry", "runner.save", "runner._staged_files", "runner.encoded", "runner.captured_output"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--files", type=int, default=300)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--recipes", default=RECIPES)
    ap.add_argument("--base", type=Path, help="a second checkout's root (run as 'base')")
    ap.add_argument("--split", nargs="?", const=SPLIT_DEFAULT,
                    help="the worker only: its instructions per file by function (module.attr,…; default: phases)")
    args = ap.parse_args()
    codes = {"this": ROOT, **({"base": args.base.resolve()} if args.base else {})}
    n, small = args.files, max(1, args.files // 5)
    with tempfile.TemporaryDirectory(prefix="rvnoise-vg-") as tmp:
        tmp = Path(tmp)
        (tmp / "vg.c").write_text(VG_LIB)
        subprocess.run(["gcc", "-shared", "-fPIC", "-O1", "-o", str(tmp / "libvg.so"), str(tmp / "vg.c")], check=True)
        tree = build_tree(tmp, n).resolve()
        if args.split:
            print(f"worker instructions per radar file by function (callgrind, exclusive of the other functions "
                  f"named; k; {n} files, third pass; the wrappers' own dumps included)")
        else:
            print(f"instructions per radar file (callgrind; M): worker loop in process ({n} files, third pass), "
                  f"main process of run() with {args.workers} workers ({n} − {small} files)")
            print("| recipe | " + " | ".join(f"{c} worker | {c} main" for c in codes) + " |\n|---|"
                  + "---|---|" * len(codes))
        for name in args.recipes.split(","):
            cells, parts = [], {}
            for label, code in codes.items():
                out = tmp / f"out-{label}"

                def worker(valgrind: bool) -> dict[str, int]:
                    shutil.rmtree(out, ignore_errors=True)
                    out.mkdir()
                    return counted(code, WORKER, [name, tree, out, ROOT / "recipes", n], tmp, valgrind,
                                   args.split or "")

                def main_run(files: int, valgrind: bool) -> int:
                    shutil.rmtree(out, ignore_errors=True)
                    return counted(code, MAIN, [name, tree, out, ROOT / "recipes", files, args.workers], tmp,
                                   valgrind).get("main", 0)

                worker(False)
                if args.split:
                    parts[label] = {k.removeprefix("seg "): v / n for k, v in worker(True).items()}
                    continue
                w = worker(True)["files"] / n
                m = math.nan
                if name != "copy":
                    main_run(small, False)
                    m = (main_run(n, True) - main_run(small, True)) / (n - small)
                cells += [f"{w / 1e6:.3f}", f"{m / 1e6:.3f}"]
                print("    " + json.dumps({"recipe": name, "code": label, "worker": w, "main": m}), flush=True)
            if args.split:
                keys = sorted({k for p in parts.values() for k in p}, key=lambda k: -parts["this"].get(k, 0))
                print(f"{name}: | function | " + " | ".join(codes) + " |")
                for k in keys + ["total"]:
                    print(f"| {k} | " + " | ".join(
                        f"{(sum(parts[c].values()) if k == 'total' else parts[c].get(k, 0)) / 1e3:.0f}"
                        for c in codes) + " |", flush=True)
                continue
            print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
