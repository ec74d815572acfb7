"""Cost of the manifest metrics per file in the workers (issue 18 target: the metrics add ≤ 10 % to `augment` time).

**Which figure is "augment time"** (round 13, docs/metrics-cost.md): what a user's run pays is its workers' CPU
time per file, summed over the files (a worker does not wait for storage: per file, wall = thread CPU + the wait for
a core, measured from ``/proc/…/schedstat``; the rest was 0 within the method's resolution), plus the main
process's (unchanged by the metrics: 1.4 ms per file). ``--whole-run`` measures that sum (its CPU column, paired
within a round): the acceptance figure. Its wall columns are not: on a shared machine they add a wait for a core
that differed between the paired runs of a round by −60…+150 ms per file (the metrics cost 4–13). The per-file
mode below is its steady state (no first file), on the same kind of data: photo-like camera frames (σ = 2 codes of
noise, as ``bench/run.py``: the smooth rendered frames PNG-decode ≈ 11 ms faster, so their increase in % was 1–3
points too high) and distinct files cycled through (the same file repeated finds its data in the caches).

Each case runs ``FRAMES`` full-resolution input files of a folder, in turn, through ``runner.process`` — what a
worker does per file: read, hash, the chain, the metrics, encode, write (staged temporaries, removed after each
run) — in this process, set up like a worker (one thread per numeric library, the workers' allocator setting),
with ``output.metrics`` off and on alternately (the order flipping every run), ``--repeat`` times each after one
untimed run of each. Figures per case: the median per-file thread CPU time and wall time, off → on, and the
increase in %; and the growth of the ``metrics`` phase of the ``--profile`` split (the manifest's per-file
``profile``, wall time; on minus off, as it also holds the chain's own bookkeeping), in ms and as a share of the
per-file time with metrics on. The increase also holds what the metrics cost the steps after them (their reads of
whole frames push the next model's tables out of the caches), and the work they add to the 8-bit sRGB decode and
encode passes that take a frame's luminance on the way (``roadview_noise.luminance``; that work is counted in the
``convert``/``encode`` phases, not in ``metrics``).
CPU time is the steadier figure on a shared machine.

``--compare-only``: the metrics work alone — per case, the CPU time of the ``metrics.compare`` calls a chain makes
(each step's input against its output, with the step's own output as ``apply_models`` hands it in, then the chain's
input against its output) on the chain's frames or clouds, and interleaved with it the same calls without the
steps' outputs (``positional``: clouds linked by matching positions, as before the steps' provenance was used),
made once beforehand and handed in as new objects each time (nothing cached, no noted geometry: the chain runs
with metrics off, so the models count none), median and quartiles of ``--repeat``
× 3 runs. Steadier than the on/off difference on a shared machine; run it in two worktrees to compare versions.
The calls read every frame's luminance themselves (no sRGB pass to share, as outside a run). With ``--baseline DIR``
(``--compare-only --baseline DIR``): the same calls with DIR's ``metrics.py`` (loaded as for ``--baseline`` below) and
with this tree's, alternating, each after reading 64 MB so that the clouds come from memory as in a run, thread CPU
time, median and quartiles of ``--repeat`` × 3 each: a paired A/B of the metrics' own work, much steadier than the
per-file or whole-run increase on a shared machine (the models noting no geometry: for a CNF chain as in a run).

``--fusion``: per case, the per-file CPU time with metrics off, on, and on with the sRGB passes left plain (each
frame's luminance read by the metrics themselves, ``luminance.collect`` kept off), interleaved in this process,
medians of ``--repeat``: what taking the luminance in the decode/encode passes saves, steadier than two worktrees'
runs on a loaded machine.

``--baseline DIR``: per case, the per-file CPU time with metrics off, on with the metrics of another version of the
code and on with this tree's, interleaved in this process (the order rotates every run), medians and quartiles of
``--repeat``: a paired A/B of two versions on a shared machine. DIR is a worktree or an export of a commit (``git
archive COMMIT | tar -x -C DIR``); its ``roadview_noise/metrics.py``, ``luminance.py`` and
``physics/lidar_output.py`` (the LiDAR weather models' output cloud, which counts return geometry for the metrics)
are loaded beside this tree's (its metrics bound to its luminance, their other relative imports resolving to this
tree's modules, so use it for versions that differ in those three files; the alignment's ``return_ranges.write_rows``
is swapped too, for a plain scatter where DIR has none, and the laser power's and the alignment's ``has_return``, for
one that notes no geometry where DIR's takes no profile) and its step records are turned into manifest dicts as its
``compound.py`` does (``StepRecord.as_entry`` or ``dataclasses.asdict``).
While DIR's metrics run the models count no return geometry for them (``physics.return_ranges.collect`` kept off,
unless DIR's metrics read it), so the other version does not pay for work only this tree's metrics use.
The first runs of each check that both versions write the same metrics (but those named by ``--changed``, e.g.
``ssim`` for a change of method).

``--whole-run``: whole ``augment`` runs instead (``runner.run``, 1 worker, in this process, the full-resolution trees
of ``bench/run.py``: ``--frames × 3`` files per sensor, LiDAR as the OS1-128 128×2048 *point list*), metrics off and
on alternately (the order flips every round), ``--repeat`` rounds after one untimed round. Figures per recipe: the
wall time, the sum of the workers' per-file times (manifest ``seconds``) and the run's CPU time (the per-file
thread CPU, ``profile.cpu``, summed, plus the main process's), off → on as medians and the median [range] of the
increase paired within a round; the growth of the ``metrics`` phase per file, and the manifest's bytes per line.
A run's first file (a fresh worker: ≈ 230 ms CPU for a camera file, ≈ 430 ms for a LiDAR one) is in the sums, with
what the metrics add to it (≈ +35–50 ms once); the last CPU column leaves it out (files 2–n: what each further file
of a long run costs; the first file's CPU moved by up to ≈ 100 ms between the paired runs of a round). With
``--baseline DIR``: paired whole runs of DIR's code and this tree's, each run in a fresh interpreter with its tree
first on ``PYTHONPATH`` (so its workers run that code), metrics off and on, the order rotating every round; the sums
of the per-file wall seconds and the run's CPU seconds (all files, and files 2–n). Each increase is also given with a
95 % bootstrap interval of its median (the rounds' paired increases resampled: the figure's resolution at the load of
the session; the median and [range] are computed as before, so older figures stay comparable).

``--whole-run --phases``: the files of the ``--whole-run`` tree through ``runner.process`` in this process, each with
metrics off and on back to back (the order alternating), ``--repeat`` passes after a warm one: per file the thread CPU
time off → on, the median paired increase with its 95 % bootstrap interval, and the same per phase in ms — read,
hash, decode, the models' steps (thread CPU around ``compound.apply_step``: what the metrics add inside a model, e.g.
the weather placement's block counts), the chain less the models (the steps' ``compare`` calls), the ``metrics``
spans, encode, write, the rest — from the profiled spans (patched here to sum thread CPU too), and the thread's minor
page faults per file. Pairs a few hundred ms apart resolve ≈ 0.1 ms a file where whole runs swing by ± 10 points
(round 24, docs/metrics-cost.md); a run's first file and main process are not in it.

``--whole-run --valgrind``: the same whole runs (the ``--whole-run`` trees, 1 worker, ``--profile``), metrics off and
on, each in a fresh interpreter under callgrind: counts that the machine's load does not move (runs of the same code
agree within 0.08 %; across invocations the instructions within 0.01 %, the simulated last-level misses move with the
address layout: ≈ ± 0.4 point on an increase in cycles), where the CPU seconds of whole runs swing by ± 15 points on this shared VM. Callgrind rather than
cachegrind: the interpreters' start-up (imports: ≈ 3 G instructions in the main process, ≈ 4 G in the fork server with
its warm-up, the same with metrics off and on) runs uninstrumented (``--instr-atstart=no``, ≈ 5× faster), and client
requests (a 3-line C library built with ``gcc`` against ``valgrind/callgrind.h``, loaded with ctypes) switch the
instrumentation on in the main process around ``run`` and in the worker from its first file, and dump the worker's
counts after each file: the first file and files 2–n from one run. Figures per recipe, off → on and the increase: Ir,
D1 misses, last-level misses (simulated Zen 4 L1s and a 32 MiB L3) and an estimated cycle count, Ir + 10 (I1mr + D1mr +
D1mw) + 100 (ILmr + DLmr + DLmw); for the whole run, what it pays once (the main process, the first file, the worker's
exit) and files 2–n per file. Numba compiles its kernels for an AVX2 target here (``NUMBA_CPU_NAME=haswell``: valgrind
runs no AVX-512) and a warm run of each configuration without valgrind caches them first; the bench fails if a
measured run writes a kernel or a physics table (their files' mtimes, the runs' own table cache). ``--repeat 2``
checks the determinism. A 3-file run takes ≈ 2–3 min. ``--keep DIR``: the first off and on runs' callgrind files
are kept (``DIR/RECIPE/off|on``) and split — where the added counts go, in the worker's files 2–n per file: per
segment (the worker also dumps at the boundaries of its profiled spans, of the metrics' ``compare`` calls, of their
compiled cloud passes, of the LiDAR models' calls that count return geometry for them and of the manifest line's
encoding: ``VG_SEGMENTS``) and per function (exclusive counts; numba's kernels have no symbol for valgrind, hence
the segments), and per function in the main process. The segment dumps' Python wrappers are counted too (≈ 0.1 M
instructions a LiDAR file, ≈ 0.25 M of a ≈ 5 M radar file, more with metrics on): take the acceptance figures from
runs without ``--keep``. ``--split [module.attr,…]``: the worker also dumps its counts as it enters and leaves each
function named (default: the camera metrics' passes, the sRGB passes they ride on and the file's phases), and the
bench prints files 2–n per function, off → on (Ir, D1 and LL misses, cycles, and cycles with a D1 miss at 40).

Inputs: ``FRAMES`` frames of the sample drive generated at full resolution (camera 1936×1464 PNG made photo-like,
with its depth EXR, the same frame as a raw DNG, the OS1-128 128×2048 grid PCD, the same scan as a point list —
what ``--whole-run`` and ``bench/run.py`` run on —, radar PCD), and the real OS1-128 scan
``../shared/data/os1-128/scan0.bin`` (107 647 points, its own beam table) when present. Recipes: camera weather
(fog, rain, snow), CNF05 (fog →
windscreen), CNF10–12 (weather → JPEG), CNF13 (low light → rain); LiDAR weather (fog, rain, snow), CNF20, CNF22,
CNF23;
radar rain and CNF25.

    .venv/bin/python bench/bench_metrics.py [--repeat N] [--recipes cnf20,cnf22]
    .venv/bin/python bench/bench_metrics.py --compare-only [--repeat N] [--recipes cnf11,cnf05]
    .venv/bin/python bench/bench_metrics.py --compare-only --baseline DIR [--repeat N] [--recipes cnf22,cnf20]
    .venv/bin/python bench/bench_metrics.py --fusion [--repeat N] [--recipes cnf11,cnf05]
    .venv/bin/python bench/bench_metrics.py --baseline DIR [--repeat N] [--recipes cnf20,cnf22]
    .venv/bin/python bench/bench_metrics.py --whole-run [--repeat N] [--frames N] [--recipes cnf20,cnf22]
    .venv/bin/python bench/bench_metrics.py --whole-run --baseline DIR [--repeat N] [--frames N] [--recipes cnf22]
    .venv/bin/python bench/bench_metrics.py --whole-run --phases [--repeat N] [--frames N] [--recipes cnf22]
    .venv/bin/python bench/bench_metrics.py --whole-run --valgrind [--repeat N] [--frames N] [--recipes cnf10,cnf22]
        [--split [MODULE.ATTR,…]] [--keep DIR] [--last-level SIZE,ASSOC,LINE]
"""

from __future__ import annotations

from roadview_noise.executor import worker_setup

worker_setup()      # before numpy/cv2/numba load: one thread each, as in a worker

import argparse  # noqa: E402
import contextlib  # noqa: E402
import dataclasses  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

import roadview_noise  # noqa: E402
from roadview_noise import compound, luminance  # noqa: E402
from roadview_noise import metrics as this_metrics  # noqa: E402
from roadview_noise.compound import apply_models  # noqa: E402
from roadview_noise.manifest import MANIFEST_NAME  # noqa: E402
from roadview_noise.metrics import compare  # noqa: E402
from roadview_noise.models.lidar import alignment as alignment_model, power as power_model  # noqa: E402
from roadview_noise.physics import compiled, lidar_weather, return_ranges  # noqa: E402
from roadview_noise.physics.lidar_geometry import has_return  # noqa: E402
from roadview_noise.recipe import load_recipe, parse_recipe  # noqa: E402
from roadview_noise.runner import RunContext, build_models, load, plan, process, run  # noqa: E402
from roadview_noise.sampledata.generate import generate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED_OS1 = ROOT.parent / "shared" / "data" / "os1-128"
#: recipe → the inputs it is timed on (folders of the generated tree; "real" = the real OS1-128 scan)
CASES = {
    "weather-fog": ("camera/", "raw/"),
    "weather-rain": ("camera/",),
    "weather-snow": ("camera/",),
    "cnf05": ("camera/", "raw/"),
    "cnf10": ("camera/",),
    "cnf11": ("camera/",),
    "cnf12": ("camera/",),
    "cnf13": ("camera/",),
    "weather-fog-lidar": ("lidar/os1-128-grid/", "lidar/os1-128/", "real"),
    "weather-rain-lidar": ("lidar/os1-128-grid/", "lidar/os1-128/", "real"),
    "weather-snow-lidar": ("lidar/os1-128-grid/", "lidar/os1-128/", "real"),
    "cnf20": ("lidar/os1-128-grid/", "lidar/os1-128/", "real"),
    "cnf22": ("lidar/os1-128-grid/", "lidar/os1-128/", "real"),
    "cnf23": ("lidar/os1-128-grid/", "lidar/os1-128/", "real"),
    "weather-rain-radar": ("radar/",),
    "cnf25-radar": ("radar/",),
}
REAL_SCAN = "lidar/os1-128-real/seq/000000.bin"
FRAMES = 3          # per-file modes: distinct frames of the sample drive, cycled through
#: whole runs: recipe → the sensor tree of bench/run.py it runs on
WHOLE_RUN = {"weather-rain-lidar": "lidar", "weather-fog-lidar": "lidar", "weather-snow-lidar": "lidar",
             "cnf20": "lidar", "cnf22": "lidar", "cnf23": "lidar", "cnf10": "camera", "cnf11": "camera",
             "cnf12": "camera", "cnf05": "camera", "cnf25-radar": "radar"}
#: whole runs that ``--recipes`` may name besides the default set: every other radar recipe
WHOLE_RUN_TREE = {**WHOLE_RUN, **dict.fromkeys(("weather-fog-radar", "weather-rain-radar", "weather-snow-radar",
                                                "cnf26-radar", "cnf27-radar"), "radar")}


def recipe_file(name: str, metrics: bool, real: bool, tmp: Path) -> Path:
    """The shipped recipe with ``output.metrics`` set (and, for the real scan, the unit's own beam table)."""
    body = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
    body.setdefault("output", {})["metrics"] = metrics
    if real:
        body["inputs"]["lidar_profile"] = str(SHARED_OS1 / "beam_intrinsics.json")
    path = tmp / f"{name}-{'real' if real else 'gen'}-{metrics}.yaml"
    path.write_text(yaml.safe_dump(body))
    return path


def _case_tasks(in_root: Path, recipe, folder: str) -> list:
    """The tasks of a case: the files of ``folder`` (all of the tree for the real scan), cycled through by the
    per-file modes so that, as in a run, each file's data comes from memory, not from the previous run's caches."""
    return [t for t in plan(in_root, recipe) if folder == "real" or t.sample.relpath.startswith(folder)]


def run_once(task, ctx: RunContext) -> tuple[float, float, float]:
    """(thread CPU s, wall s, metrics phase s) of one ``process`` call; its staged output files are removed."""
    t0 = time.thread_time()
    entry = process(task, ctx)
    cpu = time.thread_time() - t0
    if "error" in entry:
        raise RuntimeError(f"{task.sample.relpath}: {entry['error']}")
    for tmp, _ in entry.get("staged", ()):
        (ctx.out_root / tmp).unlink(missing_ok=True)
    return cpu, entry["seconds"], entry["profile"]["metrics"]


def bench_case(name: str, folder: str, roots: dict[str, Path], tmp: Path, repeat: int) -> str | None:
    real = folder == "real"
    in_root = roots["real" if real else "gen"]
    ctxs = {}
    for on in (False, True):
        out = tmp / "out" / f"{name}-{folder.strip('/').replace('/', '-')}-{on}"
        out.mkdir(parents=True, exist_ok=True)
        ctxs[on] = RunContext(in_root, out, load_recipe(recipe_file(name, on, real, tmp)), profile=True)
    tasks = _case_tasks(in_root, ctxs[True].recipe, folder)
    if not tasks:
        return None
    task = tasks[0]
    samples = {False: [], True: []}
    for on in (False, True):
        run_once(task, ctxs[on])                                        # warm-up: kernels, caches, tables
    for r in range(repeat):
        for on in ((False, True) if r % 2 else (True, False)):
            samples[on].append(run_once(tasks[r % len(tasks)], ctxs[on]))
    med = {on: [statistics.median(s[i] for s in samples[on]) * 1e3 for i in range(3)] for on in (False, True)}
    (cpu0, wall0, metrics0), (cpu1, wall1, metrics1) = med[False], med[True]
    label = "real OS1-128 scan0.bin" if real else f"{folder} ({len(tasks)} files)"
    return (f"  {name:<12} {label:<38} {cpu0:7.1f} → {cpu1:7.1f} ({(cpu1 / cpu0 - 1) * 100:+5.1f} %)   "
            f"{wall0:7.1f} → {wall1:7.1f} ({(wall1 / wall0 - 1) * 100:+5.1f} %)   {metrics1 - metrics0:6.1f} "
            f"({(metrics1 - metrics0) / wall1 * 100:4.1f} %)")


def baseline_case(name: str, folder: str, roots: dict[str, Path], tmp: Path, repeat: int,
                  baseline: Path) -> str | None:
    """Per-file CPU ms with metrics off, on with ``baseline``'s metrics and on with this tree's (``--baseline``)."""
    real = folder == "real"
    in_root = roots["real" if real else "gen"]
    ctxs = {on: RunContext(in_root, tmp / "out", load_recipe(recipe_file(name, on, real, tmp)), profile=False)
            for on in (False, True)}
    (tmp / "out").mkdir(exist_ok=True)
    tasks = _case_tasks(in_root, ctxs[True].recipe, folder)
    if not tasks:
        return None
    versions = {"base": _baseline_version(baseline),
                "this": (this_metrics, compound.StepRecord.as_entry, luminance, lidar_weather.assemble,
                         return_ranges.write_rows, has_return)}
    collect = return_ranges.collect

    def once(kind: str, task=tasks[0]) -> tuple[float, dict]:
        if kind != "off":
            module, compound.StepRecord.as_entry, lum, lidar_weather.assemble, return_ranges.write_rows, \
                power_model.has_return = versions[kind]
            alignment_model.has_return = power_model.has_return
            sys.modules["roadview_noise.metrics"] = roadview_noise.metrics = module
            sys.modules["roadview_noise.luminance"] = roadview_noise.luminance = lum
        if kind == "base" and not hasattr(module, "return_ranges"):     # models note no geometry for it
            return_ranges.collect = lambda on: collect(False)
        try:
            t0 = time.thread_time()
            entry = process(task, ctxs[kind != "off"])
            cpu = time.thread_time() - t0
        finally:
            sys.modules["roadview_noise.metrics"] = roadview_noise.metrics = this_metrics
            sys.modules["roadview_noise.luminance"] = roadview_noise.luminance = luminance
            compound.StepRecord.as_entry, lidar_weather.assemble = versions["this"][1], versions["this"][3]
            return_ranges.write_rows = versions["this"][4]
            power_model.has_return = alignment_model.has_return = has_return
            return_ranges.collect = collect
        if "error" in entry:
            raise RuntimeError(f"{task.sample.relpath}: {entry['error']}")
        for staged, _ in entry.get("staged", ()):
            (ctxs[True].out_root / staged).unlink(missing_ok=True)
        return cpu * 1e3, entry

    def metrics_of(entry: dict) -> tuple:
        return _comparable([entry["metrics"]] + [step["metrics"] for step in entry["steps"]])

    first = {kind: once(kind)[1] for kind in ("off", "base", "this")}          # warm-up; the values must agree
    if metrics_of(first["base"]) != metrics_of(first["this"]):
        raise RuntimeError(f"{name} {folder}: the two versions' metrics differ")
    kinds = ("off", "base", "this")
    samples: dict[str, list[float]] = {k: [] for k in kinds}
    for r in range(repeat):
        for kind in kinds[r % 3:] + kinds[:r % 3]:
            samples[kind].append(once(kind, tasks[r % len(tasks)])[0])
    med = {k: statistics.median(v) for k, v in samples.items()}
    q = {k: statistics.quantiles(v, n=4) if len(v) > 1 else v * 3 for k, v in samples.items()}
    label = "real OS1-128 scan0.bin" if real else f"{folder} ({len(tasks)} files)"
    spread = ", ".join(f"{k} {q[k][0]:.2f}–{q[k][2]:.2f}" for k in kinds)
    return (f"  {name:<18} {label:<38} off {med['off']:6.2f}   base {med['base']:6.2f} "
            f"({(med['base'] / med['off'] - 1) * 100:+5.1f} %)   this {med['this']:6.2f} "
            f"({(med['this'] / med['off'] - 1) * 100:+5.1f} %)   [quartiles: {spread}]")


CHANGED: tuple[str, ...] = ()     # --changed: metrics the two versions of --baseline may compute differently


def _comparable(results: list) -> list:
    """Metrics dicts without the :data:`CHANGED` ones (what two versions must agree on)."""
    return [{k: v for k, v in r.items() if k not in CHANGED} if isinstance(r, dict) else r for r in results]


def _baseline_version(tree: Path) -> tuple:
    """(metrics module, ``StepRecord.as_entry``, luminance module, LiDAR ``assemble``, ``return_ranges.write_rows``,
    the laser power's and the alignment's ``has_return``) of another version of the code (``--baseline``): its
    ``luminance.py``, its ``metrics.py`` bound to it, its ``physics/lidar_output.py`` (the weather models' output cloud,
    which counts return geometry for the metrics), for the alignment's writes this tree's ``write_rows`` if it has one,
    else a plain scatter (no geometry noted), and this tree's ``has_return`` if its own takes the cloud (to note the
    input's geometry), else one that notes none."""
    luminance_base = _load_beside(tree, "luminance")
    try:
        sys.modules["roadview_noise.luminance"] = roadview_noise.luminance = luminance_base
        module = _load_beside(tree, "metrics")
    finally:
        sys.modules["roadview_noise.luminance"] = roadview_noise.luminance = luminance
    has_entry = "def as_entry(" in (tree / "roadview_noise" / "compound.py").read_text()
    has_rows = "def write_rows(" in (tree / "roadview_noise" / "physics" / "return_ranges.py").read_text()
    geometry_code = (tree / "roadview_noise" / "physics" / "lidar_geometry.py").read_text()
    notes_input = "def has_return(positions_m: np.ndarray, cloud" in geometry_code
    return (module, (compound.StepRecord.as_entry if has_entry else dataclasses.asdict), luminance_base,
            _load_beside(tree, "physics.lidar_output").assemble, return_ranges.write_rows if has_rows else _scatter,
            has_return if notes_input else _returns_only)


def _returns_only(positions: np.ndarray, cloud=None) -> np.ndarray:
    """``has_return`` of a version whose laser power and alignment note no geometry of their input."""
    return has_return(positions)


def _scatter(positions: np.ndarray, mask: np.ndarray, rows: np.ndarray, profile) -> None:
    """``return_ranges.write_rows`` of a version without it: the alignment's plain ``positions[mask] = rows``."""
    positions[mask] = rows


def _load_beside(tree: Path, name: str):
    """``tree``'s ``roadview_noise/<name>.py`` (``name`` dotted) as a module of its own (its relative imports: this
    tree's modules)."""
    spec = importlib.util.spec_from_file_location(f"roadview_noise.{name}_baseline",
                                                  tree / "roadview_noise" / f"{name.replace('.', '/')}.py")
    module = importlib.util.module_from_spec(spec)
    module.__package__ = f"roadview_noise.{name}".rpartition(".")[0]
    jit = compiled.jit
    compiled.jit = _uncached_jit                            # numba's cache would mix the module's two names
    try:
        spec.loader.exec_module(module)
    finally:
        compiled.jit = jit
    return module


def _uncached_jit(fn=None, **options):
    """``physics.compiled.jit`` without numba's on-disk cache (for the baseline's metrics module)."""
    def wrap(f):
        return numba.njit(nogil=True, **options)(f)

    return wrap(fn) if fn is not None else wrap


def fusion_case(name: str, folder: str, roots: dict[str, Path], tmp: Path, repeat: int) -> str | None:
    """Per-file CPU ms with metrics off, on, and on without the sRGB passes' luminance (``--fusion``)."""
    in_root = roots["gen"]
    ctxs = {on: RunContext(in_root, tmp / "out", load_recipe(recipe_file(name, on, False, tmp)), profile=True)
            for on in (False, True)}
    (tmp / "out").mkdir(exist_ok=True)
    tasks = [t for t in plan(in_root, ctxs[True].recipe) if t.sample.relpath.startswith(folder)]
    if folder == "real" or not tasks:
        return None
    collect = luminance.collect
    samples: dict[str, list[float]] = {"off": [], "fused": [], "plain": []}

    def once(kind: str) -> float:
        luminance.collect = collect if kind != "plain" else (lambda on: collect(False))
        try:
            return run_once(tasks[0], ctxs[kind != "off"])[0]
        finally:
            luminance.collect = collect

    for r in range(repeat + 1):
        for kind in samples:
            cpu = once(kind)
            if r:
                samples[kind].append(cpu)
    off, fused, plain = (statistics.median(samples[k]) * 1e3 for k in samples)
    return (f"  {name:<12} {tasks[0].sample.relpath:<38} off {off:7.1f}   on {fused:7.1f} "
            f"({(fused / off - 1) * 100:+5.1f} %)   on, plain sRGB passes {plain:7.1f} "
            f"({(plain / off - 1) * 100:+5.1f} %)")


def _chain_of(name: str, folder: str, roots: dict[str, Path], tmp: Path) -> tuple | None:
    """(each step's result, starting with the input; each step's own output, None first; label) of one file's chain
    run with metrics off, or None when the case has no input."""
    real = folder == "real"
    in_root = roots["real" if real else "gen"]
    recipe = load_recipe(recipe_file(name, True, real, tmp))
    tasks = [t for t in plan(in_root, recipe) if real or t.sample.relpath.startswith(folder)]
    if not tasks:
        return None
    task = tasks[0]
    data = load(task.sample, in_root, recipe)
    chain, steps = [data], [None]                   # each step's result and its own output (step provenance)

    follow = compound.follow

    def recording(before, out, *args, **kwargs):
        steps.append(out)
        chain.append(follow(before, out, *args, **kwargs))
        return chain[-1]

    compound.follow = recording
    try:
        apply_models(build_models(recipe, task), data, seed=recipe.seed, key=task.out_relpath,
                     sequence_id=task.sample.sequence_id, metrics=False)
    finally:
        compound.follow = follow
    return chain, steps, "real OS1-128 scan0.bin" if real else task.sample.relpath


def _chain_compares(chain: list, steps: list, by_step: bool = True, compare_fn=compare) -> list[dict]:
    """The ``compare`` calls a run makes for this chain, on new objects (no cached summaries, no geometry kept for
    their arrays): each step's input against its output (with the step's own output when ``by_step``, as
    ``apply_models`` hands it in), then, for a chain of several steps, its input against its output."""
    items = [dataclasses.replace(d) for d in chain]
    return_ranges.collect(False)
    got = [compare_fn(before, after, step if by_step else None)
           for before, after, step in zip(items, items[1:], steps[1:])]
    return got + ([compare_fn(items[0], items[-1])] if len(items) > 2 else [])


def compare_case(name: str, folder: str, roots: dict[str, Path], tmp: Path, repeat: int) -> str | None:
    """CPU ms of the ``compare`` calls of one file's chain (``--compare-only``)."""
    got = _chain_of(name, folder, roots, tmp)
    if got is None:
        return None
    chain, steps, label = got

    def once(by_step: bool) -> float:
        t0 = time.process_time()
        _chain_compares(chain, steps, by_step)
        return (time.process_time() - t0) * 1e3

    times: dict[bool, list[float]] = {True: [], False: []}
    for r in range(3 * repeat + 1):
        for by_step in (True, False):
            t = once(by_step)
            if r:
                times[by_step].append(t)
    (q1, med, q3), (_, positional, _) = (statistics.quantiles(times[k], n=4) if len(times[k]) > 1 else times[k] * 3
                                         for k in (True, False))
    return f"  {name:<18} {label:<38} {med:7.2f} ms  [{q1:.2f}–{q3:.2f}]   positional {positional:7.2f} ms"


def compare_paired_case(name: str, folder: str, roots: dict[str, Path], tmp: Path, repeat: int,
                        baseline: Path) -> str | None:
    """``--compare-only --baseline DIR``: the chain's ``compare`` calls with DIR's metrics and with this tree's,
    alternating, each after reading 64 MB (the frame's data out of the caches, as in a run); thread CPU ms."""
    got = _chain_of(name, folder, roots, tmp)
    if got is None:
        return None
    chain, steps, label = got
    modules = {"base": _baseline_version(baseline)[0], "this": this_metrics}
    if _comparable(_chain_compares(chain, steps, compare_fn=modules["base"].compare)) != \
            _comparable(_chain_compares(chain, steps)):
        raise RuntimeError(f"{name} {folder}: the two versions' metrics differ")
    flush = np.ones(8 << 20)
    times: dict[str, list[float]] = {k: [] for k in modules}
    for r in range(3 * repeat + 1):
        for kind in (("base", "this") if r % 2 else ("this", "base")):
            flush.sum()
            t0 = time.thread_time()
            _chain_compares(chain, steps, compare_fn=modules[kind].compare)
            if r:
                times[kind].append((time.thread_time() - t0) * 1e3)
    q = {k: statistics.quantiles(v, n=4) for k, v in times.items()}
    return f"  {name:<18} {label:<38} " + "   ".join(f"{k} {q[k][1]:6.2f} ms [{q[k][0]:.2f}–{q[k][2]:.2f}]"
                                                     for k in modules)


def whole_run_once(name: str, sensor: str, tree: Path, out: Path, metrics: bool, cpu: bool = False) -> tuple:
    """(wall s, sum of the per-file seconds, metrics phase s per file, manifest bytes per line[, with ``cpu``: the
    run's CPU seconds — the worker's per-file thread CPU summed, plus this (the main) process's CPU —, and the
    CPU seconds of its files but the first]) of one run."""
    from run import INPUTS      # bench/run.py: the trees' input globs (bench/ is first on sys.path)

    body = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
    body["inputs"] = dict(INPUTS[sensor])
    body.setdefault("output", {})["metrics"] = metrics
    recipe = parse_recipe(body, source=name, base_dir=ROOT / "recipes")
    shutil.rmtree(out, ignore_errors=True)
    t0, cpu0 = time.perf_counter(), time.process_time()
    run(recipe, tree, out, workers=1, progress=False, echo=lambda m: None, warn=lambda m: None, profile=True)
    wall, main_cpu = time.perf_counter() - t0, time.process_time() - cpu0
    lines = (out / MANIFEST_NAME).read_bytes().splitlines()
    entries = [e for e in map(json.loads, lines) if "seconds" in e]
    shutil.rmtree(out)
    files_cpu = sum(e["profile"]["cpu"] for e in entries)
    return (wall, sum(e["seconds"] for e in entries), statistics.mean(e["profile"]["metrics"] for e in entries),
            sum(map(len, lines)) // len(lines)) + ((files_cpu + main_cpu, files_cpu - entries[0]["profile"]["cpu"])
                                                   if cpu else ())


def whole_runs(names: list[str], repeat: int, frames: int) -> None:
    heading = (f"whole augment runs, 1 worker, {frames * 3} files, metrics off → on, {repeat} rounds (one untimed): "
               f"medians, and the median [range] of the increase paired within a round, with the 95 % bootstrap "
               f"interval of that median; the CPU s (the worker's per-file CPU summed, plus the main process's) is "
               f"the acceptance figure: the wall sums add the wait for a core")
    with _whole_run_trees(names, frames, heading) as (tmp, trees):
        print(f"  {'recipe':<20} {'wall s':^52}   {'sum of per-file s':^52}   {'CPU s (files + main process)':^52}   "
              f"{'CPU s, files 2–n':^52}   metrics ms/file   bytes/line")
        for name in names:
            sensor = WHOLE_RUN_TREE[name]
            samples = {False: [], True: []}
            for r in range(repeat + 1):
                for on in ((False, True) if r % 2 else (True, False)):
                    got = whole_run_once(name, sensor, trees[sensor], tmp / "out", on, cpu=True)
                    if r:
                        samples[on].append(got)
            cols = [_increase_text(*([s[i] for s in samples[k]] for k in (False, True))) for i in (0, 1, 4, 5)]
            (m0, b0), (m1, b1) = ([statistics.median(s[i] for s in samples[k]) for i in (2, 3)] for k in (False, True))
            print(f"  {name:<20} " + "   ".join(cols) + f"   {(m1 - m0) * 1e3:6.1f}       {b0:5.0f} → {b1:5.0f}",
                  flush=True)


@contextlib.contextmanager
def _whole_run_trees(names: list[str], frames: int, heading: str):
    """A temporary folder with the ``--whole-run`` input trees of the sensors of ``names`` (bench/run.py's:
    ``frames`` × 3 files each), ``heading`` printed first: (the folder, the trees by sensor)."""
    from run import build_trees

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(heading)
        yield tmp, build_trees(tmp / "trees", frames, {s: 3 * frames for s in sorted({WHOLE_RUN_TREE[n]
                                                                                       for n in names})})


def bootstrap_median(values: list[float], rounds: int = 2000) -> tuple[float, float]:
    """A 95 % percentile-bootstrap interval of the median of ``values`` (paired increases: resampled with
    replacement ``rounds`` times, a fixed seed, so a printed figure repeats): how far the median could move with
    other rounds of the same load, which the [range] of the rounds does not say."""
    rng = np.random.default_rng(0)
    medians = np.sort(np.median(rng.choice(np.asarray(values, float), (rounds, len(values))), axis=1))
    return float(medians[int(0.025 * rounds)]), float(medians[int(0.975 * rounds) - 1])


def _increase_text(off: list[float], on: list[float]) -> str:
    """Medians off → on and the median [range] of the paired increase (%), with its bootstrap interval."""
    ratios = sorted((b / a - 1) * 100 for a, b in zip(off, on))
    lo, hi = bootstrap_median(ratios)
    return (f"{statistics.median(off):6.3f} → {statistics.median(on):6.3f} ({statistics.median(ratios):+5.1f} % "
            f"[{ratios[0]:+.1f} … {ratios[-1]:+.1f}] 95 % {lo:+.1f} … {hi:+.1f})")


#: --whole-run --phases: the file's phases, from the profiled spans' thread CPU (s) and the models' apply_step
PHASES = ("read", "hash", "decode", "models", "chain − models", "metrics spans", "encode", "write", "rest")


def _phase_cpu(spans: dict[str, float], models_s: float, cpu_s: float) -> dict[str, float]:
    """A file's thread CPU (s) per phase (:data:`PHASES`) from its spans' ``cpu:`` entries: the chain less the models'
    steps is what the metrics' step comparisons (and the chain's bookkeeping) take; ``rest`` is the file's CPU less
    the others (sidecars, the manifest entry, the runner)."""
    get = lambda k: spans.get("cpu:" + k, 0.0)       # noqa: E731
    split = {"read": get("read"), "hash": get("hash"), "decode": get("load") - get("load.convert"),
             "models": models_s, "chain − models": get("chain") - models_s, "metrics spans": get("metrics"),
             "encode": get("save") - get("save.convert") - get("save.write"),
             "write": get("save.write") + get("sync")}
    split["rest"] = cpu_s - sum(split.values())
    return split


def whole_run_phases(names: list[str], repeat: int, frames: int) -> None:
    """``--whole-run --phases``: every file of the ``--whole-run`` tree through ``runner.process`` in this process
    (set up as a worker), metrics off and on back to back (the order alternating file by file and pass by pass),
    ``--repeat`` passes after a warm one: per file the thread CPU of each phase (the profiled spans, patched here to
    sum the thread's CPU time as well as the wall time; the models' steps timed around ``compound.apply_step``) and
    the thread's minor page faults. Paired file by file, a few hundred ms apart: steadier than whole runs under a
    changing load, and it says which phase the metrics make slower. A run's first file and its main process are not
    in it (``--whole-run`` has them)."""
    import resource
    from contextlib import contextmanager

    from run import INPUTS
    from roadview_noise import profiling, runner

    span, split, step = profiling._span, runner._profile_split, compound.apply_step
    spans_of, models_s = {}, [0.0]

    @contextmanager
    def cpu_span(name, totals):
        c0 = time.thread_time()
        with span(name, totals):
            yield
        totals["cpu:" + name] = totals.get("cpu:" + name, 0.0) + time.thread_time() - c0

    def keeping(spans, entry, cpu_s):
        spans_of["last"] = dict(spans)
        return split(spans, entry, cpu_s)

    def timed_step(*args, **kwargs):
        c0 = time.thread_time()
        try:
            return step(*args, **kwargs)
        finally:
            models_s[0] += time.thread_time() - c0

    profiling._span, runner._profile_split, compound.apply_step = cpu_span, keeping, timed_step
    heading = (f"per file of the --whole-run tree ({frames * 3} files a sensor), in this process, metrics off and on "
               f"back to back, {repeat} passes: thread CPU ms per file, median off → on, the median paired increase "
               f"and its 95 % bootstrap interval; per phase the same in ms (thread CPU of the profiled spans)")
    with _whole_run_trees(names, frames, heading) as (tmp, trees):
        for name in names:
            sensor = WHOLE_RUN_TREE[name]
            ctxs = {}
            for on in (False, True):
                body = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
                body["inputs"] = dict(INPUTS[sensor])
                body.setdefault("output", {})["metrics"] = on
                (tmp / f"out-{on}").mkdir(exist_ok=True)
                ctxs[on] = RunContext(trees[sensor], tmp / f"out-{on}", parse_recipe(body, source=name,
                                                                                      base_dir=ROOT / "recipes"),
                                      profile=True)
            tasks = plan(trees[sensor], ctxs[True].recipe)

            def once(task, on):
                models_s[0] = 0.0
                faults = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
                entry = process(task, ctxs[on])
                faults = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - faults
                if "error" in entry:
                    raise RuntimeError(f"{task.sample.relpath}: {entry['error']}")
                for staged, _ in entry.get("staged", ()):
                    (ctxs[on].out_root / staged).unlink(missing_ok=True)
                cpu = entry["profile"]["cpu"]
                return {"CPU": cpu, **_phase_cpu(spans_of["last"], models_s[0], cpu), "minor faults": faults / 1e3}

            samples = {False: [], True: []}
            for r in range(repeat + 1):
                for k, task in enumerate(tasks):
                    for on in ((False, True) if (r + k) % 2 else (True, False)):
                        got = once(task, on)
                        if r:
                            samples[on].append(got)
            off, on = samples[False], samples[True]
            cpu_off, cpu_on = [x["CPU"] for x in off], [x["CPU"] for x in on]
            ratios = [(b / a - 1) * 100 for a, b in zip(cpu_off, cpu_on)]
            lo, hi = bootstrap_median(ratios)
            print(f"  {name:<20} {len(off)} pairs: CPU {statistics.median(cpu_off) * 1e3:6.2f} → "
                  f"{statistics.median(cpu_on) * 1e3:6.2f} ms ({statistics.median(ratios):+5.2f} % 95 % {lo:+.2f} … "
                  f"{hi:+.2f}; sums {(sum(cpu_on) / sum(cpu_off) - 1) * 100:+5.2f} %)", flush=True)
            for key in (*PHASES, "minor faults"):
                a, b = [x[key] * 1e3 for x in off], [x[key] * 1e3 for x in on]
                diff = [y - x for x, y in zip(a, b)]
                lo, hi = bootstrap_median(diff)
                print(f"    {key:<16} {statistics.median(a):8.3f} → {statistics.median(b):8.3f}   paired "
                      f"{statistics.median(diff):+7.3f} (95 % {lo:+.3f} … {hi:+.3f})", flush=True)
    profiling._span, runner._profile_split, compound.apply_step = span, split, step


#: one whole run in a fresh interpreter (--whole-run --baseline): this bench, the code of the tree on PYTHONPATH
ONE_RUN = """import json, sys
sys.path.insert(0, sys.argv[1] + "/bench")
from bench_metrics import whole_run_once
from pathlib import Path
print(json.dumps(whole_run_once(sys.argv[2], sys.argv[3], Path(sys.argv[4]), Path(sys.argv[5]), sys.argv[6] == "on",
                                cpu=True)))
"""


def whole_runs_paired(names: list[str], repeat: int, frames: int, baseline: Path) -> None:
    """``--whole-run --baseline DIR``: per round, whole runs with metrics off and on with DIR's code and with this
    tree's, each in a fresh interpreter (its workers fork from a fork server importing that tree), the order of the
    four rotating every round; medians of the sums of the per-file wall and CPU seconds and of each round's
    increase (on against the same round's off: steadier under a changing load)."""
    trees_code = {"base": baseline, "this": ROOT}
    heading = (f"whole augment runs, 1 worker, {frames * 3} files, fresh interpreter each, {repeat} rounds (one "
               f"untimed): medians of the sums of the per-file wall s and CPU s, off → on, and of the increase "
               f"paired within a round [its range] with the 95 % bootstrap interval of that median")
    with _whole_run_trees(names, frames, heading) as (tmp, trees):
        for name in names:
            kinds = [(code, on) for code in ("base", "this") for on in ("off", "on")]
            samples: dict[tuple, list] = {k: [] for k in kinds}
            for r in range(repeat + 1):
                for code, on in kinds[r % 4:] + kinds[:r % 4]:
                    env = {**os.environ, "PYTHONPATH": str(trees_code[code])}
                    got = subprocess.run([sys.executable, "-c", ONE_RUN, str(ROOT), name, WHOLE_RUN_TREE[name],
                                          str(trees[WHOLE_RUN_TREE[name]]), str(tmp / "out"), on], env=env, check=True,
                                         capture_output=True, text=True).stdout.splitlines()[-1]
                    if r:
                        samples[(code, on)].append(json.loads(got))
            for code in ("base", "this"):
                cols = []
                for i, label in ((1, "wall"), (4, "CPU"), (5, "CPU files 2–n")):     # paired within a round
                    cols.append(f"{label} " + _increase_text(*([s[i] for s in samples[(code, k)]]
                                                               for k in ("off", "on"))))
                print(f"  {name:<12} {code:<5} " + "   ".join(cols), flush=True)


#: --whole-run --valgrind: the client requests a run makes under callgrind (instrumentation on, counts dumped), built
#: with the system's valgrind/callgrind.h
VG_LIB = """#include <valgrind/callgrind.h>
void vg_start(void) { CALLGRIND_START_INSTRUMENTATION; }
void vg_dump(const char *label) { CALLGRIND_DUMP_STATS_AT(label); }
"""
#: imported by the run's fork server (PRELOAD): a worker switches the instrumentation on as its first file starts,
#: dumps the counts after each file ("file") and as it leaves ("exit")
VG_HOOK = """import ctypes, os
from roadview_noise import executor, runner

lib = ctypes.CDLL(os.environ["RVNOISE_VG_LIB"])
process, leave, started = runner.process_encoded, executor.leave_at_once, []


def process_encoded(task, ctx):
    lib.vg_start()
    started.append(True)
    try:
        return process(task, ctx)
    finally:
        lib.vg_dump(b"file")


def leave_at_once(code=0):
    if started:
        lib.vg_dump(b"exit")
    leave(code)


runner.process_encoded, executor.leave_at_once = process_encoded, leave_at_once
if os.environ.get("RVNOISE_VG_SPLIT"):
    import vg_split
    runner.process_encoded = vg_split.wrapping(lib, os.environ["RVNOISE_VG_SPLIT"].split(","), process_encoded)
"""
#: --split: the worker also dumps its counts as it enters and leaves each function named (module.attr), labelled
#: "seg NAME" by the innermost one running (or "rest"); every module attribute that is the function is replaced
#: (from the first file on, when the run's modules are imported)
VG_SPLIT = """import importlib, sys


def wrapping(lib, names, process):
    stack, done = [], []

    def wrap(name, fn):
        def call(*args, **kwargs):
            lib.vg_dump(("seg " + (stack[-1] if stack else "rest")).encode())
            stack.append(name)
            try:
                return fn(*args, **kwargs)
            finally:
                lib.vg_dump(("seg " + name).encode())
                stack.pop()
        return call

    def first(task, ctx):
        if not done:
            done.append(True)
            for name in names:
                module, attr = name.rsplit(".", 1)
                fn = getattr(importlib.import_module(module), attr)
                for m in [m for k, m in list(sys.modules.items()) if k.startswith("roadview_noise")]:
                    for k, v in list(vars(m).items()):
                        if v is fn:
                            setattr(m, k, wrap(name.removeprefix("roadview_noise."), fn))
        return process(task, ctx)
    return first
"""
#: the functions --split dumps around by default: the camera metrics' passes, the sRGB passes they ride on, the
#: file's phases
VG_SPLIT_DEFAULT = ",".join(f"roadview_noise.{n}" for n in (
    "runner.load", "runner.apply_models", "runner.save", "runner._staged_files", "manifest.encoded",
    "physics.srgb.code_to_linear", "physics.srgb.linear_to_code", "luminance._decode8_blocks",
    "luminance._encode8_blocks", "luminance._codes_luminance_area", "luminance._luminance_area", "metrics.compare",
    "metrics._grey_codes", "metrics._grey_statistics", "metrics._depth_bin_index", "metrics._ssim_local_means",
    "metrics._ssim_map", "metrics.psnr_db"))
#: also imported by the fork server with ``--keep``: the counts dumped at every boundary of the worker's profiled
#: spans (``profiling``), of the metrics' ``compare`` calls inside the chain and of the manifest line's encoding, each
#: labelled ``seg:`` and the spans open before the boundary (``seg:`` alone: outside every span)
VG_SEGMENTS = """import ctypes, importlib, os
from contextlib import contextmanager
from roadview_noise import metrics, profiling, runner

lib, stack = ctypes.CDLL(os.environ["RVNOISE_VG_LIB"]), []


def _boundary():
    lib.vg_dump(("seg:" + "/".join(stack)).encode())


@contextmanager
def segment(name):
    _boundary()
    stack.append(name)
    try:
        yield
    finally:
        _boundary()
        stack.pop()


def _wrap(fn, name):
    def wrapped(*args, **kwargs):
        with segment(name):
            return fn(*args, **kwargs)
    return wrapped


span = profiling._span


def counted_span(name, totals):
    return _chained(span(name, totals), segment(name))


@contextmanager
def _chained(a, b):
    with a, b:
        yield


profiling._span = counted_span
metrics.Deferred.compare = _wrap(metrics.Deferred.compare, "compare")
runner.encoded = _wrap(runner.encoded, "manifest-line")
# the cloud metrics' compiled passes and the models' calls that count return geometry for them, as segments of
# their own (module globals their callers look up at each call)
metrics._PASSES.update({k: _wrap(f, f.__name__) for k, f in metrics._PASSES.items()})
for module, names in (("metrics", ("_mean_change", "_summarise_points")),
                      ("physics.return_ranges", ("count",)),
                      ("models.lidar.power", ("has_return",)), ("models.lidar.alignment", ("has_return",))):
    mod = importlib.import_module("roadview_noise." + module)
    for name in names:
        setattr(mod, name, _wrap(getattr(mod, name), name))
"""
#: one whole run in a fresh interpreter (arguments: the recipe as JSON, the tree, the output folder, the recipes'
#: folder); under callgrind (RVNOISE_VG_LIB set) the main process is counted from ``run``'s call to its return
VG_RUN = """import ctypes, json, os, sys
from pathlib import Path
from roadview_noise import executor
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run

body, tree, out = json.loads(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
recipe = parse_recipe(body, source="bench", base_dir=Path(sys.argv[4]))
lib = ctypes.CDLL(os.environ["RVNOISE_VG_LIB"]) if "RVNOISE_VG_LIB" in os.environ else None
if lib:
    executor.PRELOAD.extend(["vg_hook"] + (["vg_segments"] if os.environ.get("RVNOISE_VG_SEGMENTS") else []))
    lib.vg_start()
run(recipe, tree, out, workers=1, progress=False, echo=lambda m: None, warn=lambda m: None, profile=True)
if lib:
    lib.vg_dump(b"main")
"""
#: the simulated caches (Zen 4: 32 KiB 8-way L1s, a CCD's 32 MiB 16-way L3 as the last level; callgrind would take
#: this VM's reported 320 MB L3 otherwise), and the code numba compiles under valgrind and for the warm runs: AVX2,
#: as valgrind emulates no AVX-512 (its kernels cached for this target, so no compile lands in a measured run)
VG_CACHES = ["--I1=32768,8,64", "--D1=32768,8,64", "--LL=33554432,16,64"]
VG_TARGET = {"NUMBA_CPU_NAME": "haswell", "NUMBA_CPU_FEATURES": ""}
VG_EVENTS = ("Ir", "I1mr", "ILmr", "Dr", "D1mr", "DLmr", "Dw", "D1mw", "DLmw")


def est_cycles(c: dict) -> float:
    """Cachegrind's classic cycle estimate: Ir + 10 × L1 misses + 100 × last-level misses (instructions and data)."""
    return c["Ir"] + 10 * (c["I1mr"] + c["D1mr"] + c["D1mw"]) + 100 * (c["ILmr"] + c["DLmr"] + c["DLmw"])


def _compiled_files(tables: Path) -> dict[str, float]:
    """The mtime of every numba cache file of this tree and every physics table in ``tables`` (the runs' own table
    cache): a measured run must write none (a compile or a table build would land in its counts)."""
    files = list((ROOT / "roadview_noise").rglob("*.nb[ic]")) + list(tables.rglob("*"))
    return {str(f): f.stat().st_mtime for f in files if f.is_file()}


def valgrind_run(body: dict, tree: Path, tmp: Path, native: bool = False, split: str = "",
                 keep: Path | None = None) -> dict[str, list[dict]]:
    """One whole run under callgrind: the counts of ``main`` (the main process within ``run``), ``file`` (the
    worker, per file: the file and the worker's loop before it) and ``exit`` (the worker after its last file);
    ``native``: the same run without valgrind (the warm run: kernels and tables on disk), {}. ``split``: the
    functions to count apart (:data:`VG_SPLIT`), per file in ``split`` ({function: counts}); ``keep``: the worker
    also dumps at its spans' boundaries (``VG_SEGMENTS``; their counts are added to the file's) and callgrind's
    files are copied to that folder."""
    from run import TABLE_CACHE_ENV

    out, cg = tmp / "out", tmp / "cg"
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(cg, ignore_errors=True)
    cg.mkdir(parents=True)
    env = {**os.environ, **VG_TARGET, "PYTHONPATH": f"{ROOT}:{tmp}", TABLE_CACHE_ENV: str(tmp / "tables")}
    vg = []
    if not native:
        env["RVNOISE_VG_LIB"] = str(tmp / "libvg.so")
        if split:
            env["RVNOISE_VG_SPLIT"] = split
        vg = ["valgrind", "--tool=callgrind", "--instr-atstart=no", "--cache-sim=yes", *VG_CACHES,
              "--trace-children=yes", f"--callgrind-out-file={cg}/cg.%p"]
    if keep is not None:
        env["RVNOISE_VG_SEGMENTS"] = "1"
    proc = subprocess.run(vg + [sys.executable, "-c", VG_RUN, json.dumps(body), str(tree), str(out),
                                str(ROOT / "recipes")], capture_output=True, text=True, env=env)
    shutil.rmtree(out, ignore_errors=True)
    if proc.returncode:
        raise RuntimeError(f"run failed: {proc.stderr[-3000:]}")
    if keep is not None:
        shutil.rmtree(keep, ignore_errors=True)
        shutil.copytree(cg, keep)
    return _vg_parts(cg)


def _vg_parts(cg: Path) -> dict[str, list[dict]]:
    """The counts of a run's callgrind dumps by label (:func:`valgrind_run`); with ``--split``, a file's "seg NAME"
    dumps (and its "file" dump as "rest") also per file in ``split``, and its "file" counts their sum."""
    parts: dict[str, list] = {}
    pending: dict[int, dict] = {}               # counts of a pid's segments since its last main/file/exit dump
    named: dict[int, dict] = {}                 # --split: a pid's "seg NAME" counts since its last file dump
    zero = dict.fromkeys(VG_EVENTS, 0)
    for f in _dumps(cg):
        text = f.read_text(errors="replace")
        label = re.search(r"^desc: Trigger: (?:Client Request: )?(.*)$", text, re.M).group(1)
        if label not in ("main", "file", "exit") and not label.startswith(("seg:", "seg ")):
            continue
        events = re.search(r"^events: (.*)$", text, re.M).group(1).split()
        counts = dict.fromkeys(events, 0)                   # a summary leaves out trailing zeros
        counts.update(zip(events, map(int, re.search(r"^summary: (.*)$", text, re.M).group(1).split())))
        pid = int(f.name.split(".")[1])
        if label.startswith(("seg:", "seg ")):
            pending[pid] = _sum([pending.get(pid, zero), counts])
            if label.startswith("seg "):
                by = named.setdefault(pid, {})
                by[label[4:]] = _sum([by.get(label[4:], zero), counts])
            continue
        by = named.pop(pid, None)
        if by is not None and label == "file":
            by["rest"] = _sum([by.get("rest", zero), counts])
            parts.setdefault("split", []).append(by)
        parts.setdefault(label, []).append(_sum([counts, pending.pop(pid, zero)]))
    return parts


def _dumps(cg: Path) -> list[Path]:
    """Callgrind's files of a run in order: by process, then by dump (``cg.PID.N``; ``cg.PID``: its exit)."""
    return sorted(cg.iterdir(), key=lambda f: tuple(int(x) for x in f.name.split(".")[1:]) + (1 << 30,) * (
        f.name.count(".") == 1))


def cg_functions(path: Path) -> dict[str, list[int]]:
    """A callgrind file's exclusive counts per function (``object:function``, ``VG_EVENTS`` order); code without a
    symbol (numba's kernels, loaded by llvmlite) summed per object as ``object:(no symbol)``."""
    names: dict[str, dict[str, str]] = {"ob": {}, "fn": {}}
    totals: dict[str, list[int]] = {}
    order, ob, fn, skip, current = None, "", "", False, None
    with open(path, errors="replace") as fh:
        for line in fh:
            head = line[:1]
            if head.isdigit() or head in "+-*":
                if skip:
                    skip = False
                    continue
                values = line.split()[1:]
                for i, v in enumerate(values):
                    current[order[i]] += int(v)
                continue
            key, _, value = line.rstrip("\n").partition("=")
            kind = {"ob": "ob", "cob": "ob", "fn": "fn", "cfn": "fn"}.get(key)
            if kind:
                ref, _, name = value.partition(" ") if value.startswith("(") else ("", "", value)
                if name:
                    names[kind][ref] = name
                name = names[kind].get(ref, name) if ref else name
                if key == "ob":
                    ob = name
                elif key == "fn":
                    fn = name
                    label = f"{Path(ob).name}:{'(no symbol)' if fn.startswith('0x') else fn}"
                    current = totals.setdefault(label, [0] * len(VG_EVENTS))
            elif key == "calls":
                skip = True
            elif line.startswith("events:"):
                order = [VG_EVENTS.index(e) for e in line.split()[1:]]
    return totals


def _file_groups(cg: Path) -> tuple[list[list[Path]], list[Path]]:
    """A kept run's dumps: the worker's per file (its segments, then the file's own dump) and the main process's."""
    files, main, pending = [], [], []
    for f in _dumps(cg):
        label = re.search(r"^desc: Trigger: (?:Client Request: )?(.*)$", f.read_text(errors="replace"), re.M).group(1)
        if label.startswith("seg:"):
            pending.append(f)
        elif label == "file":
            files.append(pending + [f])
            pending = []
        elif label == "main":
            main.append(f)
    return files, main


def _split_rows(off: dict[str, list], on: dict[str, list], top: int) -> list[str]:
    """The entries of two count tables (name → ``VG_EVENTS``), largest difference in estimated cycles first."""
    def figures(c):
        d = dict(zip(VG_EVENTS, c))
        return d["Ir"], d["D1mr"] + d["D1mw"], d["DLmr"] + d["DLmw"], est_cycles(d)
    zero = [0] * len(VG_EVENTS)
    rows = []
    for name in set(off) | set(on):
        a, b = figures(off.get(name, zero)), figures(on.get(name, zero))
        rows.append((b[3] - a[3], name, a, b))
    rows.sort(key=lambda r: -abs(r[0]))
    return [f"      {d / 1e6:+8.3f} M cycles  Ir {(b[0] - a[0]) / 1e6:+8.3f} M  D1 {(b[1] - a[1]) / 1e3:+8.1f} k  "
            f"LL {(b[2] - a[2]) / 1e3:+7.1f} k   ({a[3] / 1e6:7.2f} → {b[3] / 1e6:7.2f} M)  {name}"
            for d, name, a, b in rows[:top]]


def vg_split(name: str, kept: Path, top: int = 25) -> str:
    """``--keep``: where switching the metrics on adds counts, from the kept off and on runs: per segment (the
    worker's profiled spans, ``VG_SEGMENTS``) and per function, in the worker's files 2–n (per file) and in the main
    process (within ``run``)."""
    groups = {on: _file_groups(kept / on) for on in ("off", "on")}

    def per_file(tables: list[dict], n: int) -> dict:
        total: dict[str, list] = {}
        for t in tables:
            for k, c in t.items():
                acc = total.setdefault(k, [0] * len(VG_EVENTS))
                for i, v in enumerate(c):
                    acc[i] += v
        return {k: [v / n for v in c] for k, c in total.items()}

    def segments(files: list[list[Path]]) -> dict:
        tables = []
        for group in files[1:]:
            table = {}
            for f in group:
                text = f.read_text(errors="replace")
                label = re.search(r"^desc: Trigger: (?:Client Request: )?(.*)$", text, re.M).group(1)
                events = re.search(r"^events: (.*)$", text, re.M).group(1).split()
                counts = dict(zip(events, map(int, re.search(r"^summary: (.*)$", text, re.M).group(1).split())))
                seg = label[4:] if label.startswith("seg:") else ""
                acc = table.setdefault(seg or "(outside the spans)", [0] * len(VG_EVENTS))
                for i, e in enumerate(VG_EVENTS):
                    acc[i] += counts.get(e, 0)
            tables.append(table)
        return per_file(tables, len(files) - 1)

    lines = [f"  {name}: where the metrics add counts (off → on), worker files 2–n per file, by span:"]
    lines += _split_rows(*(segments(groups[on][0]) for on in ("off", "on")), top)
    lines.append(f"  {name}: by function (exclusive), worker files 2–n per file:")
    lines += _split_rows(*(per_file([cg_functions(f) for g in groups[on][0][1:] for f in g],
                                    len(groups[on][0]) - 1) for on in ("off", "on")), top)
    lines.append(f"  {name}: by function (exclusive), main process within run():")
    lines += _split_rows(*(per_file([cg_functions(f) for f in groups[on][1]], 1) for on in ("off", "on")), top // 2)
    return "\n".join(lines)


def _sum(counts: list[dict]) -> dict:
    return {e: sum(c[e] for c in counts) for e in VG_EVENTS}


def whole_runs_valgrind(names: list[str], frames: int, repeat: int, split: str = "", keep: Path | None = None) -> None:
    """``--whole-run --valgrind``: per recipe, whole runs under callgrind (1 worker), metrics off and on, each after
    a warm run without valgrind; ``repeat`` runs of each (more than one: their largest relative difference).
    ``split``: the functions counted apart (``--split``); ``keep``: the first off and on runs' callgrind files kept in
    ``keep/RECIPE/off|on`` and split (:func:`vg_split`)."""
    from run import INPUTS, build_trees

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "vg.c").write_text(VG_LIB)
        subprocess.run(["gcc", "-shared", "-fPIC", "-O1", "-o", str(tmp / "libvg.so"), str(tmp / "vg.c")], check=True)
        (tmp / "vg_hook.py").write_text(VG_HOOK)
        (tmp / "vg_split.py").write_text(VG_SPLIT)
        (tmp / "vg_segments.py").write_text(VG_SEGMENTS)
        n = 3 * frames
        trees = build_trees(tmp / "trees", frames, {s: n for s in sorted({WHOLE_RUN_TREE[x] for x in names})})
        print(f"whole augment runs under callgrind, 1 worker, {n} files, metrics off → on: counts in millions "
              f"(the main process within run(), the worker from its first file; start-up imports and the fork "
              f"server's warm-up not counted); D1 = D1mr + D1mw, LL = DLmr + DLmw; cycles ≈ Ir + 10 (I1mr + D1mr + "
              f"D1mw) + 100 (ILmr + DLmr + DLmw); whole run = main + every file + the worker's exit; first = main + "
              f"the first file + exit (what a run pays once); files 2–n: per file", flush=True)
        for name in names:
            sensor = WHOLE_RUN_TREE[name]
            bodies = {on: yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text()) for on in (False, True)}
            for on, body in bodies.items():
                body["inputs"] = dict(INPUTS[sensor])
                body.setdefault("output", {})["metrics"] = on
            before = None
            for _ in range(4):      # warm runs until they write nothing (a process stores a few tables at most)
                if before == (before := _compiled_files(tmp / "tables")):
                    break
                for body in bodies.values():
                    valgrind_run(body, trees[sensor], tmp, native=True)
            runs: dict[bool, list] = {False: [], True: []}

            def measured(on: bool, first: bool) -> dict:
                kept = keep / name / ("on" if on else "off") if keep is not None and first else None
                return valgrind_run(bodies[on], trees[sensor], tmp, split=split, keep=kept)
            for i in range(repeat):
                for on in (False, True):
                    runs[on].append(measured(on, not runs[on]))
                # a table whose key holds floats that NumPy computes otherwise under valgrind (no AVX-512): it is
                # built in the first run that needs it; that pair was a warm run, measure it again
                if before != (before := _compiled_files(tmp / "tables")):
                    print(f"  {name}: a kernel or table was written during a measured run: runs again", flush=True)
                    runs = {on: runs[on][:-1] + [measured(on, len(runs[on]) == 1)] for on in runs}
                    if before != _compiled_files(tmp / "tables"):
                        raise RuntimeError(f"{name}: the measured runs write kernels or tables")
            print(_vg_rows(name, runs, n), flush=True)
            if split:
                print(_vg_split_rows(runs), flush=True)
            print("    " + json.dumps({"recipe": name, "runs": {str(k): v for k, v in runs.items()}}), flush=True)
            if keep is not None:
                print(vg_split(name, keep / name), flush=True)


def _vg_figures(parts: dict, n: int) -> dict[str, dict]:
    """A run's counts: the whole run, what it pays once, files 2–n per file, and a 24-file run made of these."""
    if len(parts.get("file", ())) != n or len(parts.get("main", ())) != 1:
        raise RuntimeError(f"expected {n} file dumps and the main process's: {[(k, len(v)) for k, v in parts.items()]}")
    once = _sum(parts["main"] + parts["file"][:1] + parts.get("exit", []))
    rest = {e: v / (n - 1) for e, v in _sum(parts["file"][1:]).items()}
    return {"whole": _sum(parts["main"] + parts["file"] + parts.get("exit", [])), "first": once, "rest": rest,
            "24": {e: once[e] + 23 * rest[e] for e in VG_EVENTS}}


def _vg_split_rows(runs: dict) -> str:
    """``--split``: per function counted apart, files 2–n per file (the first run's), off → on: Ir, D1 misses, LL
    misses, estimated cycles and the same with a D1 miss at 40 cycles; by the growth of the cycles."""
    if any("split" not in runs[on][0] for on in runs):
        return "    files 2–n by function: no function of --split ran"
    figs = {}
    for on in runs:
        files = runs[on][0]["split"][1:]
        figs[on] = {k: {e: sum(f.get(k, {}).get(e, 0) for f in files) / len(files) for e in VG_EVENTS}
                    for k in {k for f in files for k in f}}
    zero = dict.fromkeys(VG_EVENTS, 0)
    rows = []
    for k in sorted(set(figs[False]) | set(figs[True]), key=lambda k: est_cycles(figs[False].get(k, zero))
                    - est_cycles(figs[True].get(k, zero))):
        off, on = figs[False].get(k, zero), figs[True].get(k, zero)
        cells = [f"{what} {get(off) / 1e6:7.2f} → {get(on) / 1e6:7.2f}" for get, what in (
            (lambda c: c["Ir"], "Ir"), (lambda c: c["D1mr"] + c["D1mw"], "D1"),
            (lambda c: c["DLmr"] + c["DLmw"], "LL"), (est_cycles, "cycles"),
            (lambda c: est_cycles(c) + 30 * (c["D1mr"] + c["D1mw"]), "cycles@40"))]
        rows.append(f"    {k:<32} " + "   ".join(cells))
    return "\n".join(["    files 2–n, per file, by function (M):"] + rows)


def _vg_rows(name: str, runs: dict, n: int) -> str:
    """A recipe's rows: whole run, what it pays once, files 2–n per file, a 24-file run made of these (the main
    process's per-file share left out); the first run's figures, and with several the largest relative difference
    of Ir and cycles between runs of the same code."""
    figs = {on: [_vg_figures(r, n) for r in runs[on]] for on in runs}
    rows = []
    for kind, label in (("whole", f"whole run ({n} files)"), ("first", "main + first file + exit"),
                        ("rest", "files 2–n, per file"), ("24", "24 files: once + 23 × 2–n")):
        cells = []
        for get, what in ((lambda c: c["Ir"], "Ir"), (lambda c: c["D1mr"] + c["D1mw"], "D1"),
                          (lambda c: c["DLmr"] + c["DLmw"], "LL"), (est_cycles, "cycles")):
            off, on = (get(figs[k][0][kind]) for k in (False, True))
            cells.append(f"{what} {off / 1e6:8.2f} → {on / 1e6:8.2f} ({(on / off - 1) * 100:+5.2f} %)")
        spread = max(abs(f(r[kind]) / f(figs[k][0][kind]) - 1) for k in figs for r in figs[k]
                     for f in (lambda c: c["Ir"], est_cycles))
        rows.append(f"  {name:<18} {label:<24} " + "   ".join(cells)
                    + (f"   runs differ ≤ {spread * 100:.3f} %" if len(figs[False]) > 1 else ""))
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, help="runs per case with metrics off and on (default 7; --valgrind: 1)")
    ap.add_argument("--recipes", help=f"comma-separated subset of {', '.join(CASES)}")
    ap.add_argument("--whole-run", action="store_true", help="whole augment runs instead of single files")
    ap.add_argument("--compare-only", action="store_true", help="CPU time of the chain's metrics calls alone")
    ap.add_argument("--fusion", action="store_true", help="metrics off / on / on without the sRGB passes' luminance")
    ap.add_argument("--baseline", type=Path,
                    help="per file: metrics off / on with DIR's metrics.py / on with this tree's; with "
                         "--whole-run: whole runs off/on with DIR's code and with this tree's, paired")
    ap.add_argument("--changed", default="", help="--baseline: comma-separated metrics the two versions may compute "
                                                  "differently (a change of method, e.g. ssim)")
    ap.add_argument("--valgrind", action="store_true",
                    help="with --whole-run: instruction and cache-miss counts of whole runs under callgrind "
                         "(--repeat: runs of each; 2 checks their determinism)")
    ap.add_argument("--split", nargs="?", const="camera", help="--valgrind: count these functions apart "
                    "(comma-separated module.attr; without a value: the camera metrics' passes)")
    ap.add_argument("--keep", type=Path, help="with --whole-run --valgrind: keep the off and on runs' callgrind "
                                              "files in KEEP/RECIPE/ and print where the metrics add counts (per "
                                              "profiled span and per function)")
    ap.add_argument("--last-level", help="--valgrind: the simulated last-level cache as SIZE,ASSOC,LINE (default "
                                         "33554432,16,64; 1048576,8,64: a Zen 4 L2, whose misses then count as LL)")
    ap.add_argument("--phases", action="store_true",
                    help="with --whole-run: each file of the tree off and on back to back in this process, thread "
                         "CPU per phase, paired per file (--repeat passes)")
    ap.add_argument("--frames", type=int, default=4, help="--whole-run: frames rendered (× 3 copies; default 4)")
    args = ap.parse_args()
    args.repeat = args.repeat or (1 if args.valgrind else 7)
    global CHANGED
    CHANGED = tuple(filter(None, args.changed.split(",")))
    if args.last_level:
        VG_CACHES[-1] = f"--LL={args.last_level}"
    if args.whole_run and args.valgrind:
        whole_runs_valgrind(args.recipes.split(",") if args.recipes else list(WHOLE_RUN), args.frames, args.repeat,
                            VG_SPLIT_DEFAULT if args.split == "camera" else args.split or "",
                            args.keep.resolve() if args.keep else None)
        return
    if args.whole_run and args.phases:
        whole_run_phases(args.recipes.split(",") if args.recipes else list(WHOLE_RUN), args.repeat, args.frames)
        return
    if args.whole_run and args.baseline:
        whole_runs_paired(args.recipes.split(",") if args.recipes else list(WHOLE_RUN), args.repeat, args.frames,
                          args.baseline.resolve())
        return
    if args.whole_run:
        whole_runs(args.recipes.split(",") if args.recipes else list(WHOLE_RUN), args.repeat, args.frames)
        return
    names = args.recipes.split(",") if args.recipes else list(CASES)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        roots = {"gen": tmp / "full", "real": tmp / "real"}
        from run import photo_like      # bench/run.py (bench/ is first on sys.path)

        generate(roots["gen"], frames=FRAMES, seed=0)
        rng = np.random.default_rng(0)
        for png in sorted((roots["gen"] / "camera").rglob("*.png")):
            photo_like(png, png, rng)
        if (SHARED_OS1 / "scan0.bin").is_file():
            (roots["real"] / REAL_SCAN).parent.mkdir(parents=True)
            shutil.copy(SHARED_OS1 / "scan0.bin", roots["real"] / REAL_SCAN)
        else:
            print("(real OS1-128 scan absent: ../shared/data/os1-128/scan0.bin)")
        if args.baseline and args.compare_only:
            print(f"metrics.compare calls of one file's chain, thread CPU ms, median [quartiles] of {3 * args.repeat}, "
                  f"{args.baseline}'s metrics and this tree's alternating, caches flushed before each:")
        elif args.baseline:
            print(f"per file in the worker, CPU ms, medians of {args.repeat} interleaved runs: metrics off, on with "
                  f"{args.baseline}'s metrics, on with this tree's:")
        elif args.fusion:
            print(f"per file in the worker, CPU ms, medians of {args.repeat} interleaved runs:")
        elif args.compare_only:
            print(f"metrics.compare calls of one file's chain, CPU ms, median [quartiles] of {3 * args.repeat}:")
        else:
            print(f"per file in the worker, metrics off → on, median of {args.repeat} runs each:")
            print(f"  {'recipe':<12} {'input':<38} {'CPU ms':^29}   {'wall ms':^29}   metrics phase ms (share)")
        for name in names:
            for folder in CASES[name]:
                if folder == "real" and not (roots["real"] / REAL_SCAN).is_file():
                    continue
                if args.baseline and args.compare_only:
                    line = compare_paired_case(name, folder, roots, tmp, args.repeat, args.baseline.resolve())
                elif args.baseline:
                    line = baseline_case(name, folder, roots, tmp, args.repeat, args.baseline.resolve())
                else:
                    case = fusion_case if args.fusion else compare_case if args.compare_only else bench_case
                    line = case(name, folder, roots, tmp, args.repeat)
                if line:
                    print(line, flush=True)


if __name__ == "__main__":
    main()
