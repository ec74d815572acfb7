"""The one benchmark table of README "Performance", measured in one run on one machine (issue 19).

Renders the sample drive at full resolution (camera 1936×1464 with range EXR, OS1-128 128×2048 list, 4D radar) into a
temporary folder and builds one tree per sensor: camera frames are made photo-like (σ = 2 codes of noise, each copy
its own noise: the rendered frames are smooth and PNG-code 10× faster than photographs), LiDAR and radar frames are
copied. Then, per sensor, with 1 and 2 processes:

- **copy**: the plain loop a user would write with the same codecs — read, decode, encode, write (+ fsync, as rvnoise
  writes) each file — run by the executor ``augment`` uses, one task per file, with 1 as with 2 worker processes
  (``bench/plain_copy.py``: worker start and hand-over alike on both sides); for the camera also **floor**: the
  copy plus decoding the depth sidecar the recipes read, i.e. the I/O every camera weather recipe must do. The
  camera copy and floor use OpenCV's PNG codec; a second copy uses rvnoise's (``io/png.py``, ≈ 2× faster, the same
  pixels, its files 0–5 % smaller on these frames), and the camera recipes are stated against both;
- **augment**: ``runner.run`` of each weather recipe and one CNF (in-process, so the wall time includes the fork
  server, the workers' start and the manifest), ``--profile`` on: per-model ms in the workers at the D3.5 rates and
  each worker's peak RSS come from the manifest; what bounds 2 workers / 1 worker: the **worker CPU ms/file** with
  1 and 2 workers (thread CPU time, ``profile.cpu``: the cores' shared caches and memory bandwidth, not the wait
  for a core that a loaded machine adds), each worker's **first file + CPU ms** (its per-process tables and
  first-use costs: every worker pays it, side by side, so on few files it weighs like a fixed cost) and the run's
  time **beyond the files** (wall − in-worker seconds / workers: worker start, run record, lock, manifest, close);
- **start-up**: ``rvnoise augment --limit 1`` in a fresh process, minus the file's own time, and in all (the augment
  rows exclude it: the fork server is started for each recipe before its timed runs); and the worker start-up of
  that run (run.json ``worker_start_seconds``: from starting the workers to the first one ready for tasks);
- **small files**: fog.radar on 10× the radar tree's files, 1 and 2 workers: what each file costs beyond its own time
  (task hand-over, the main process's manifest line and rename), the main process's CPU and the workers' busy share;
- ``compression.camera`` against OpenCV's JPEG codec alone and albumentations' ``ImageCompression`` on one frame
  (as 8-bit codes, and as the float32 frame a float-valued step hands on, which albumentations converts), and
  albumentations' nearest weather transforms (``RandomFog``, ``RandomRain``, ``RandomSnow``) on the same frames, when
  albumentations is installed (``.venv/bin/pip install --no-deps albumentations==2.0.8 albucore==0.0.24
  stringzilla simsimd``: its wheel's opencv-python-headless would shadow opencv-contrib);
- **memory**: the main process's peak RSS for 100 and 10 000 tiny radar files (``--quick`` skips it).

Physics tables (``roadview_noise/table_cache.py``): each recipe's one-file warm-up run leaves them on disk, so the
timed runs read them as a repeated run does; ``--cold-tables`` gives the bench a folder of its own and empties it
before each timed run, so every worker builds them as on a first run after an install or an edit.

**Steady state** (``--steady N``, default 48; 0: off): every copy and recipe also runs on N files per sensor (radar:
10 N, its files take ≈ 2 ms), and two columns give the **marginal** figures of the files after the first 12:
(N − 12) / (wall(N) − wall(12)) files/s with 1 and 2 workers and their ratio. What a run pays once (the workers'
start, each worker's first-file costs, the run record, the lock: ≈ 20–60 ms) is in both walls and cancels, so this
is the 2 w / 1 w a run of 10⁵ frames sees; the 12-file column keeps the fixed cost in (a radar run of 12 files
takes ≈ 60 ms in all). It is a difference of two walls: noisy on a loaded machine ("—" when not positive).

Figures are medians (``--repeat R``: R runs of each copy and recipe, 1 and 2 workers alternating); ratios are
measured in the same run. A shared machine makes absolute figures noisy. ``--sensors lidar,radar``, ``--recipes``,
``--only-table`` and ``--small-files`` measure a part of the table; ``--copies 12`` gives 48 files per sensor.

    .venv/bin/python bench/run.py [--frames N] [--copies C] [--quick] [--repeat R] [--sensors S] [--only-table]
                                  [--cold-tables] [--steady N]
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
import time
from pathlib import Path

import cv2
import numpy as np
import yaml
from bench_foundation import median_ms      # bench/ is the script's folder, first on sys.path
from plain_copy import plain_copy

ROOT = Path(__file__).resolve().parents[1]
RECIPES = {
    "camera": ["weather-fog", "weather-rain", "weather-snow", "cnf10", "cnf11", "cnf12"],
    "lidar": ["weather-fog-lidar", "weather-rain-lidar", "weather-snow-lidar", "cnf20"],
    "radar": ["weather-fog-radar", "weather-rain-radar", "weather-snow-radar", "cnf25-radar"],
}
INPUTS = {"camera": {"camera": "camera/**/*.png", "depth": "{stem}_depth.exr"},
          "lidar": {"lidar": "lidar/**/*.pcd"}, "radar": {"radar": "radar/**/*.pcd"}}
PHOTO_NOISE_CODES = 2.0
TABLE_CACHE_ENV = "RVNOISE_TABLE_CACHE"     # roadview_noise.table_cache.ENV (not imported before the fork server)
COLD_TABLES = False                         # --cold-tables
STEADY_FACTOR = {"radar": 10}               # --steady N: N files per sensor, 10 N radar files (≈ 2 ms each)


# --- data ------------------------------------------------------------------------------------------------------------


def build_trees(root: Path, frames: int, files: dict[str, int]) -> dict[str, Path]:
    """One input tree per sensor of ``files`` under ``root`` with its number of files, copies of ``frames`` rendered
    frames (see module docstring)."""
    from roadview_noise.sampledata.generate import generate

    src = root / "render"
    generate(src, frames=frames, seed=0)
    trees = {s: root / s for s in files}
    rng = np.random.default_rng(0)
    if "camera" in trees:
        cam = trees["camera"] / "camera" / "seq0"
        cam.mkdir(parents=True)
        shutil.copy(src / "camera" / "seq0" / "camera.yaml", cam)
        for k in range(files["camera"]):
            i = k % frames
            photo_like(src / "camera" / "seq0" / f"{i:06d}.png", cam / f"{k:06d}.png", rng)
            shutil.copy(src / "camera" / "seq0" / f"{i:06d}_depth.exr", cam / f"{k:06d}_depth.exr")
    for sensor, folder in (("lidar", src / "lidar" / "os1-128" / "seq0"), ("radar", src / "radar" / "seq0")):
        if sensor not in trees:
            continue
        dst = trees[sensor] / sensor / "seq0"
        dst.mkdir(parents=True)
        for side in folder.glob("*.yaml"):
            shutil.copy(side, dst)
        for k in range(files[sensor]):
            shutil.copy(folder / f"{k % frames:06d}.pcd", dst / f"{k:06d}.pcd")
    shutil.rmtree(src)
    return trees


def photo_like(src: Path, dst: Path, rng: np.random.Generator) -> None:
    """The rendered 8-bit frame ``src`` with σ = ``PHOTO_NOISE_CODES`` of noise, written to ``dst`` (PNG): a frame
    that PNG-codes like a photograph (the smooth rendered frames code ≈ 10× faster)."""
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED).astype(np.float32)
    noisy = np.clip(np.rint(img + rng.normal(0, PHOTO_NOISE_CODES, img.shape)), 0, 255).astype(np.uint8)
    cv2.imwrite(str(dst), noisy)


def recipe_for(name: str, sensor: str):
    from roadview_noise.recipe import parse_recipe

    body = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
    body["inputs"] = dict(INPUTS[sensor])
    return parse_recipe(body, source=name, base_dir=ROOT / "recipes")


# --- augment ---------------------------------------------------------------------------------------------------------


def augment(name: str, sensor: str, tree: Path, out: Path, workers: int, files: int | None = None) -> dict:
    from roadview_noise.manifest import read_manifest
    from roadview_noise.runner import run

    recipe = recipe_for(name, sensor)
    warm = out.with_name(out.name + "-warm")        # the fork server's start is start-up, measured by startup()
    run(recipe, tree, warm, workers=1, limit=1, progress=False, echo=lambda m: None)
    shutil.rmtree(warm)
    if COLD_TABLES:                                 # this run builds its tables as a first run would
        shutil.rmtree(Path(os.environ[TABLE_CACHE_ENV]), ignore_errors=True)
    cpu0, t0 = _cpu_s(), time.perf_counter()
    s = run(recipe, tree, out, workers=workers, progress=False, echo=lambda m: None, profile=True, limit=files)
    wall, cpu = time.perf_counter() - t0, _cpu_s() - cpu0
    entries = [e for e in read_manifest(out / "manifest.jsonl") if e["status"] == "ok"]
    models: dict[str, list[float]] = {}
    for e in entries[1:] or entries:                # the first file of a run pays first-use costs
        for m, sec in e["profile"]["models"].items():
            models.setdefault(m, []).append(sec)
    return {"wall": wall, "done": s.done, "failed": s.failed, "main_cpu_ms": 1e3 * cpu / max(s.done, 1),
            "busy": sum(e["seconds"] for e in entries) / (wall * workers),
            "models_ms": {m: 1e3 * statistics.median(v) for m, v in models.items()},
            "file_ms": 1e3 * statistics.median(e["seconds"] for e in entries),
            "file_mean_ms": 1e3 * statistics.mean(e["seconds"] for e in entries),
            "cpu_ms": 1e3 * statistics.median(e["profile"]["cpu"] for e in entries[workers:] or entries),
            "first_extra_ms": 1e3 * (entries[0]["profile"]["cpu"] - statistics.median(e["profile"]["cpu"]
                                                                                   for e in entries[1:]))
            if len(entries) > 1 else 0.0,
            "beyond_ms": 1e3 * (wall - sum(e["seconds"] for e in entries) / workers),
            "split_ms": {k: 1e3 * statistics.median(e["profile"][k] for e in entries)
                         for k in entries[0]["profile"] if k not in ("models", "total", "cpu", "peak_rss_mb")},
            "peak_rss_mb": max(e["profile"].get("peak_rss_mb", 0) for e in entries)}


def _cpu_s() -> float:
    """CPU seconds of this (the main) process so far."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def small_files(tree: Path, root: Path, copies: int, n: int) -> dict:
    """fog.radar on ``copies`` × the radar tree's first ``n`` files with 1 and 2 workers: files/s, the wall time per
    file beyond the in-worker time, the main process's CPU per file and the workers' busy share (in-worker time /
    wall)."""
    many = root / "radar-many"
    dst = many / "radar" / "seq0"
    dst.mkdir(parents=True)
    src = tree / "radar" / "seq0"
    for side in src.glob("*.yaml"):
        shutil.copy(side, dst)
    files = sorted(src.glob("*.pcd"))[:n]
    for k in range(len(files) * copies):
        shutil.copy(files[k % len(files)], dst / f"{k:06d}.pcd")
    r = {w: augment("weather-fog-radar", "radar", many, root / f"many-{w}", w) for w in (1, 2)}
    shutil.rmtree(many)
    for w in (1, 2):
        shutil.rmtree(root / f"many-{w}")
    return r


def startup(name: str, sensor: str, tree: Path, out: Path) -> tuple[float, float, float]:
    """Seconds of a one-file CLI run: beyond the file's own time (process start, imports, workers, manifest), in
    all, and the worker start-up (run.json ``worker_start_seconds``: from starting the workers to the first one
    ready for tasks)."""
    from roadview_noise.manifest import read_manifest

    recipe = out.parent / f"{name}-startup.yaml"
    body = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
    body["inputs"] = dict(INPUTS[sensor])
    recipe.write_text(yaml.safe_dump(body))
    t0 = time.perf_counter()
    subprocess.run([str(Path(sys.executable).with_name("rvnoise")), "augment", "--recipe", str(recipe), str(tree),
                    str(out), "--limit", "1", "--workers", "1", "--quiet"], check=True, capture_output=True)
    wall = time.perf_counter() - t0
    worker = json.loads((out / "run.json").read_text())["worker_start_seconds"]
    return wall - read_manifest(out / "manifest.jsonl")[0]["seconds"], wall, worker


# --- single frames ---------------------------------------------------------------------------------------------------


def single_frame(tree: Path, repeat: int) -> dict[str, float]:
    """compression.camera vs the codec alone and albumentations on one frame; albumentations' weather transforms."""
    from roadview_noise.allocator import keep_freed_memory
    from roadview_noise.io.image import read_image
    from roadview_noise.models.camera.compression import CompressionCamera
    from roadview_noise.physics import srgb
    from roadview_noise.types import CameraFrame
    from roadview_noise.profiles.camera import carla_pinhole

    keep_freed_memory()
    path = sorted(tree.rglob("*.png"))[0]
    linear, _, _ = read_image(path)
    changed = linear * np.float32(0.9)                   # a frame a weather step changed (no kept codes)
    frame = CameraFrame(changed, carla_pinhole(linear.shape[1], linear.shape[0]))
    model = CompressionCamera(quality=15)
    rgb8 = srgb.linear_to_code(changed)
    first = CameraFrame(linear, frame.profile)           # the frame as decoded: it keeps its codes
    res = {"compression.camera (Q15, after a weather step)":
           median_ms(lambda: model.apply(frame, state={}, drawn={}, rng=None), repeat),
           "compression.camera (Q15, first step: the frame as decoded)":
           median_ms(lambda: model.apply(first, state={}, drawn={}, rng=None), repeat),
           "OpenCV JPEG encode + decode alone (Q15)":
           median_ms(lambda: cv2.imdecode(cv2.imencode(".jpg", rgb8, [cv2.IMWRITE_JPEG_QUALITY, 15])[1],
                                           cv2.IMREAD_COLOR), repeat),
           "sRGB linear → 8-bit codes (tables)": median_ms(lambda: srgb.linear_to_code(changed), repeat),
           "sRGB 8-bit codes → linear (tables)": median_ms(lambda: srgb.code_to_linear(rgb8), repeat)}
    try:
        import albumentations as A
    except ImportError:
        return res
    jpeg = A.ImageCompression(quality_range=(15, 15), p=1)
    codes01 = rgb8.astype(np.float32) / np.float32(255)   # a float-valued step's frame: converted to uint8 and back
    for label, t, image in [("ImageCompression (Q15)", jpeg, rgb8), ("RandomFog", A.RandomFog(p=1), rgb8),
                            ("RandomRain", A.RandomRain(p=1), rgb8), ("RandomSnow", A.RandomSnow(p=1), rgb8),
                            ("ImageCompression (Q15)", jpeg, codes01)]:
        frame = ", float32 frame" if image is codes01 else ""
        res[f"albumentations {label} {A.__version__}{frame}"] = median_ms(lambda: t(image=image), repeat)
    return res


# --- memory of the main process --------------------------------------------------------------------------------------

MEMORY_CHILD = r"""
import sys, json
from pathlib import Path
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import run
s = run(load_recipe(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), workers=2, progress=False,
        echo=lambda m: None, yes=True)
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(json.dumps({"done": s.done, "failed": s.failed, "peak_kb": hwm}))
"""


def memory(root: Path) -> dict[int, dict]:
    frames = sorted((ROOT / "sample_data" / "radar" / "seq0").glob("*.pcd"))
    res = {}
    for n in (100, 10_000):
        tree = root / f"mem{n}"
        for i in range(n):
            folder = tree / "radar" / f"seq{i // 100:03d}"
            folder.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(frames[i % len(frames)], folder / f"{i:06d}.pcd")
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-c", MEMORY_CHILD, str(ROOT / "recipes" / "weather-fog-radar.yaml"),
                              str(tree), str(root / f"memout{n}")], check=True, capture_output=True, text=True)
        res[n] = {**json.loads(out.stdout.strip().splitlines()[-1]), "seconds": time.perf_counter() - t0}
        shutil.rmtree(tree)
        shutil.rmtree(root / f"memout{n}")
    return res


# --- the table -------------------------------------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=4, help="rendered frames (each copied to make 12 per sensor)")
    ap.add_argument("--copies", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="skip the 10 000-file memory run")
    ap.add_argument("--sensors", default=",".join(RECIPES), help="comma-separated sensors to measure (default: all)")
    ap.add_argument("--recipes", help="comma-separated recipes of those sensors to run (default: all of them)")
    ap.add_argument("--only-table", action="store_true",
                    help="only the copy/augment table (no per-model, start-up, small-file or single-frame rows)")
    ap.add_argument("--small-files", action="store_true", help="only the small-files table (radar)")
    ap.add_argument("--cold-tables", action="store_true",
                    help="every timed run starts with an empty table cache, as a first run after an install or an "
                         "edit (default: the tables on disk, as a repeated run finds them)")
    ap.add_argument("--steady", type=int, default=48,
                    help="also run every copy and recipe on this many files per sensor and report the marginal "
                         "2 w / 1 w of the files after the first --frames × --copies (0: off)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="runs of each copy and recipe per worker count, 1 and 2 workers alternating (medians)")
    args = ap.parse_args()
    sensors = [x for x in args.sensors.split(",") if x]
    unknown = set(sensors) - set(RECIPES)
    if unknown:
        ap.error(f"unknown sensor(s) {sorted(unknown)}; choose from {list(RECIPES)}")
    if args.small_files:
        sensors = ["radar"]
    recipes = {s: [r for r in RECIPES[s] if not args.recipes or r in args.recipes.split(",")] for s in sensors}
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="rvnoise-bench-") as tmp:
        root = Path(tmp)
        if args.cold_tables:                # before the first fork server: the workers read the server's env
            global COLD_TABLES
            COLD_TABLES = True
            os.environ[TABLE_CACHE_ENV] = str(root / "tables")
        n = args.frames * args.copies
        steady = {} if args.small_files else {s: args.steady * STEADY_FACTOR.get(s, 1) for s in sensors}
        trees = build_trees(root, args.frames, {s: max(n, steady.get(s, 0)) for s in sensors})
        more = ", ".join(f"{s} {k}" for s, k in steady.items() if k > n)
        print(f"# rvnoise bench/run.py — {n} files per sensor{f' (marginal columns: {more})' if more else ''}, "
              f"{os.cpu_count()} cores, load average {load:.1f} "
              f"at the start (medians; ratios from this run); physics tables "
              f"{'built by every run (--cold-tables)' if COLD_TABLES else 'read from the table cache'}\n")
        if not args.small_files:
            per_model, splits = table(root, trees, recipes, n, args.repeat, steady)
        if not (args.small_files or args.only_table):
            details(per_model, splits)
            startup_table(root, trees)
        if "radar" in trees and not args.only_table:
            small_files_table(trees["radar"], root, n)
        if "camera" in trees and not args.only_table:
            print("\n| one 1936×1464 frame, one core | ms |\n|---|---|")
            for label, ms in single_frame(trees["camera"], 9).items():
                print(f"| {label} | {ms:.1f} |")
        if not (args.quick or args.only_table or args.small_files):
            mem = memory(root)
            print("\n| main process, fog.radar on tiny files, 2 workers | files | peak RSS MB | s |\n|---|---|---|---|")
            for k, v in mem.items():
                print(f"| {k} files | {v['done']} | {v['peak_kb'] / 1024:.1f} | {v['seconds']:.1f} |")
            print(f"\n10 000 / 100 files peak RSS: {mem[10_000]['peak_kb'] / mem[100]['peak_kb']:.3f}")
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")


def table(root: Path, trees: dict[str, Path], recipes: dict[str, list[str]], n: int,
          repeat: int = 1, steady: dict[str, int] | None = None) -> tuple[dict, dict]:
    """The copy/augment rows of each sensor (files/s: the median of ``repeat`` runs on the first ``n`` files);
    where ``steady[sensor]`` > ``n``, also runs on that many files and the **marginal** figures of the files after
    the first ``n`` (:func:`_marginal`); returns the per-model ms and each recipe's split (1 worker)."""
    steady = {s: k for s, k in (steady or {}).items() if k > n}
    extra = [f"2 w / 1 w, files {n + 1}…N (marginal; N)", "marginal files/s (1 w / 2 w)"] if steady else []
    head = ["sensor", "recipe", "1 worker files/s", "2 workers files/s", f"2 w / 1 w ({n} files)", *extra,
            "vs copy (1 w / 2 w)", "vs floor (1 w / 2 w)", "in-worker ms/file", "peak RSS/worker MB",
            "worker CPU ms/file (1 w / 2 w)", "first file + CPU ms (1 w)", "beyond the files ms (1 w / 2 w)"]
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    per_model: dict[str, list[float]] = {}
    splits = {}
    same_codec: dict[str, tuple[float, float]] = {}

    def fps_of(walls: dict) -> dict[int, float]:
        return {p: n / walls[n, p] for p in (1, 2)}

    def row(sensor: str, label: str, walls: dict, cells: list[str]) -> None:
        fps = fps_of(walls)
        steady_cells = [""] * len(extra)
        if sensor in steady:
            m = _marginal(walls, n, steady[sensor])
            steady_cells = [f"{m[2] / m[1]:.2f} ({steady[sensor]})" if m[1] and m[2] else
                            f"— ({steady[sensor]}: noise above the difference)",
                            " / ".join(f"{m[p]:.1f}" if m[p] else "—" for p in (1, 2))]
        print(f"| {sensor} | {label} | {fps[1]:.2f} | {fps[2]:.2f} | {fps[2] / fps[1]:.2f} | "
              + " | ".join(steady_cells + cells) + " |", flush=True)

    for sensor, names in recipes.items():
        tree = trees[sensor]
        sizes = (n, steady[sensor]) if sensor in steady else (n,)

        def copies(kind: str, **kw) -> dict:
            return _walls(repeat, sizes, lambda p, k: plain_copy(sensor, tree, root / f"{kind}-{sensor}-{p}-{k}", p,
                                                                 files=k, **kw))

        copy = copies("copy")
        floor = copy if sensor != "camera" else copies("floor", with_depth=True)
        row(sensor, "*decode + encode copy*" if sensor == "camera" else "*read + write copy*", copy, [""] * 7)
        if sensor == "camera":
            row("camera", "*floor: copy + depth decode*", floor, [""] * 7)
            own = copies("own", codec="rvnoise")
            row("camera", "*copy with rvnoise's PNG codec (augment's)*", own,
                [f"{fps_of(own)[1] / fps_of(copy)[1]:.2f} / {fps_of(own)[2] / fps_of(copy)[2]:.2f}"] + [""] * 6)
        for name in names:
            runs: dict[int, list[dict]] = {1: [], 2: []}

            def one(w: int, k: int) -> float:
                out = root / f"{name}-{w}"
                shutil.rmtree(out, ignore_errors=True)
                got = augment(name, sensor, tree, out, w, files=k)
                if k == n:
                    runs[w].append(got)
                return got["wall"] * k / got["done"]

            walls = _walls(repeat, sizes, one)
            fps, cfps, ffps = fps_of(walls), fps_of(copy), fps_of(floor)
            r = {w: runs[w][0] for w in (1, 2)}
            row(sensor, name, walls, [
                f"{fps[1] / cfps[1]:.2f} / {fps[2] / cfps[2]:.2f}", f"{fps[1] / ffps[1]:.2f} / {fps[2] / ffps[2]:.2f}",
                f"{r[1]['file_ms']:.0f}", f"{max(r[1]['peak_rss_mb'], r[2]['peak_rss_mb']):.0f}",
                f"{r[1]['cpu_ms']:.1f} / {r[2]['cpu_ms']:.1f}", f"{r[1]['first_extra_ms']:.0f}",
                f"{r[1]['beyond_ms']:.0f} / {r[2]['beyond_ms']:.0f}"])
            if sensor == "camera":
                ofps = fps_of(own)
                same_codec[name] = (fps[1] / ofps[1], fps[2] / ofps[2])
            for m, ms in r[1]["models_ms"].items():
                per_model.setdefault(m, []).append(ms)
            splits[name] = r[1]["split_ms"]
            for w in (1, 2):
                shutil.rmtree(root / f"{name}-{w}")
        for leftover in root.glob(f"*-{sensor}-*-*"):
            shutil.rmtree(leftover)
    if same_codec:
        print("\n| camera recipe | vs the copy with rvnoise's PNG codec (1 w / 2 w) |\n|---|---|")
        for name, (one_w, two_w) in same_codec.items():
            print(f"| {name} | {one_w:.2f} / {two_w:.2f} |")
    return per_model, splits


def _walls(repeat: int, sizes: tuple[int, ...], measure) -> dict[tuple[int, int], float]:
    """The median of ``repeat`` wall times ``measure(processes, files)`` per (files, processes) for each size of
    ``sizes`` and 1 and 2 processes, measured alternately (1 w, 2 w, 1 w, …)."""
    got: dict[tuple[int, int], list[float]] = {(k, p): [] for k in sizes for p in (1, 2)}
    for _ in range(repeat):
        for k in sizes:
            for p in (1, 2):
                got[k, p].append(measure(p, k))
    return {key: statistics.median(v) for key, v in got.items()}


def _marginal(walls: dict[tuple[int, int], float], n: int, big: int) -> dict[int, float | None]:
    """Files/s of files n+1…big per process count: (big − n) / (wall(big) − wall(n)); None when the difference is
    not positive (a loaded machine's noise). What a run costs once (the workers' start, each worker's first-file
    costs, the run record, the lock) is in both walls and cancels: this is the rate a run of 10⁵ frames sees, where
    the 12-file figure weighs ≈ 30 ms of fixed cost against the files."""
    return {p: (big - n) / (walls[big, p] - walls[n, p]) if walls[big, p] > walls[n, p] else None for p in (1, 2)}


def details(per_model: dict, splits: dict) -> None:
    """Per-model ms and each recipe's split of a file's time."""
    print("\n| model (D3.5 rates, in the workers) | ms/frame |\n|---|---|")
    for m, v in sorted(per_model.items()):
        print(f"| {m} | {statistics.median(v):.1f} |")
    if not splits:
        return
    print("\n| recipe | " + " | ".join(next(iter(splits.values()))) + " |")
    print("|---|" + "---|" * len(next(iter(splits.values()))))
    for name, sp in splits.items():
        print(f"| {name} | " + " | ".join(f"{v:.1f}" for v in sp.values()) + " |")


def startup_table(root: Path, trees: dict[str, Path]) -> None:
    print("\n| start-up of a one-file run (CLI process) | beyond the file's own time s | in all s | worker "
          "start-up s |\n|---|---|---|---|")
    for sensor, name in (("camera", "weather-fog"), ("lidar", "weather-fog-lidar"), ("radar", "weather-fog-radar")):
        if sensor in trees:
            beyond, wall, worker = startup(name, sensor, trees[sensor], root / f"start-{name}")
            print(f"| {name} | {beyond:.2f} | {wall:.2f} | {worker:.2f} |")


def small_files_table(tree: Path, root: Path, n: int) -> None:
    many = small_files(tree, root, 10, n)
    print(f"\n| small files: weather-fog-radar on {many[1]['done']} radar files | 1 worker | 2 workers |\n"
          "|---|---|---|")
    print(f"| files/s | {many[1]['done'] / many[1]['wall']:.0f} | {many[2]['done'] / many[2]['wall']:.0f} |")
    print(f"| 2 w / 1 w | | {many[1]['wall'] / many[2]['wall']:.2f} |")
    for key, label in (("file_mean_ms", "in-worker ms/file"), ("main_cpu_ms", "main process CPU ms/file")):
        print(f"| {label} | {many[1][key]:.2f} | {many[2][key]:.2f} |")
    print("| wall ms/file beyond the in-worker time (× workers) | "
          + " | ".join(f"{1e3 * many[w]['wall'] * w / many[w]['done'] - many[w]['file_mean_ms']:.2f}" for w in (1, 2))
          + " |")
    print(f"| workers busy (in-worker time / wall) | {100 * many[1]['busy']:.0f} % | {100 * many[2]['busy']:.0f} % |")


if __name__ == "__main__":
    main()
