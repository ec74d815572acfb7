"""Cost of point provenance (issue 13) for the LiDAR weather models on the real OS1-128 scan.

Times ``apply_models([model], scan)`` (the model plus the chain's provenance composition) for fog.lidar, rain.lidar
and snow.lidar at the D3.5 rates on ../shared/data/os1-128/scan0.bin (107 647 points + 23 425 empty rays; profile
os1-128-reflectivity), and the annotation gather that carries a uint32 label array to the output
(:func:`annotations.carry_values`).

Before/after: ``--baseline DIR`` imports the package of another checkout (e.g. ``git archive main | tar -x -C
/tmp/base``) under another name into the same process and times its frames and this checkout's frames in
alternation (ABBA order), so the load of a shared machine hits both alike; it prints both medians (wall clock and
the thread's CPU time, which leaves out the time other processes hold the core) and the median of the paired
differences. Run: ``taskset -c 0 .venv/bin/python bench/bench_provenance.py --baseline /tmp/base
[--frames 61]``.
"""

from __future__ import annotations

import importlib
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve()
SCAN = HERE.parents[2] / "shared" / "data" / "os1-128" / "scan0.bin"
MODELS = ("fog.lidar", "rain.lidar", "snow.lidar")
FRAMES = 61


class Package:
    """One checkout's package: the scan as its PointCloud, its models, its apply_models."""

    def __init__(self, name: str):
        self.name = name
        types = importlib.import_module(f"{name}.types")
        lidar = importlib.import_module(f"{name}.profiles.lidar")
        self.apply_models = importlib.import_module(f"{name}.compound").apply_models
        self.registry = importlib.import_module(f"{name}.registry")
        a = np.fromfile(SCAN, dtype=np.float32).reshape(-1, 4)
        self.cloud = types.PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3].copy()}, "lidar",
                                      lidar.os1_128_reflectivity())

    def frame(self, model_id: str, i: int) -> tuple[float, float]:
        """(wall, CPU) seconds of one frame; the thread's CPU time leaves out the time other processes hold the
        core, so it is the steadier figure on a shared machine."""
        model = self.registry.get_model(model_id)()
        t0, c0 = time.perf_counter(), time.thread_time()
        self.apply_models([model], self.cloud, seed=1, key=f"bench{i}", sequence_id="s")
        return time.perf_counter() - t0, time.thread_time() - c0


def import_baseline(checkout: Path) -> Package:
    """The baseline's ``roadview_noise`` copied to a temporary folder as ``roadview_noise_baseline`` (its imports
    are relative, so it runs beside this checkout's package)."""
    tmp = Path(tempfile.mkdtemp(prefix="rvnoise-baseline-"))
    shutil.copytree(checkout / "roadview_noise", tmp / "roadview_noise_baseline",
                    ignore=shutil.ignore_patterns("__pycache__"))
    sys.path.insert(0, str(tmp))
    return Package("roadview_noise_baseline")


def gather_ms(pkg: Package, model_id: str) -> float:
    from roadview_noise.annotations import AnnotationsSpec, carry_values, new_classes, weather_classes

    out, _ = pkg.apply_models([pkg.registry.get_model(model_id)()], pkg.cloud, seed=1, key="g", sequence_id="s")
    labels = np.random.default_rng(0).integers(0, 260, len(pkg.cloud)).astype(np.uint32)
    times = []
    for _ in range(31):
        t0 = time.perf_counter()
        carry_values(labels, out, new_classes(out, weather_classes(AnnotationsSpec()), [model_id]))
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main() -> int:
    if not SCAN.is_file():
        print(f"(real OS1-128 scan absent: {SCAN})")
        return 0
    from roadview_noise.allocator import keep_freed_memory

    keep_freed_memory()
    frames = int(sys.argv[sys.argv.index("--frames") + 1]) if "--frames" in sys.argv else FRAMES
    after = Package("roadview_noise")
    before = import_baseline(Path(sys.argv[sys.argv.index("--baseline") + 1]).resolve()) \
        if "--baseline" in sys.argv else None
    print(f"real OS1-128 scan, apply_models, ms per frame, median of {frames} frames"
          + (" in alternation with the baseline (ABBA); difference: median of the paired differences" if before
             else ""))
    for mid in MODELS:
        for pkg in (after, before):
            if pkg is not None:
                pkg.frame(mid, -1)                                  # warm-up: compiled kernels, cached tables
        a, b = [], []
        for i in range(frames):
            order = (after, before) if i % 2 == 0 else (before, after)
            for pkg in order:
                if pkg is after:
                    a.append(pkg.frame(mid, i))
                elif pkg is not None:
                    b.append(pkg.frame(mid, i))
        for k, clock in enumerate(("wall", "CPU")):
            ta, tb = [t[k] for t in a], [t[k] for t in b]
            line = f"{mid:11s} {clock:4s} after {1e3 * statistics.median(ta):6.2f} (min {1e3 * min(ta):5.2f})"
            if before is not None:
                diff = statistics.median(x - y for x, y in zip(ta, tb))
                line += (f"   before {1e3 * statistics.median(tb):6.2f} (min {1e3 * min(tb):5.2f})   "
                         f"difference {1e3 * diff:+.2f} ms ({100 * diff / statistics.median(tb):+.1f} %)")
            print(line)
        print(f"{mid:11s} label gather (uint32 array through the output's provenance) {gather_ms(after, mid):.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
