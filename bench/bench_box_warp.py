"""Cost of moving 2-D boxes through a geometric camera step: KITTI / YOLO (``annotations.warp_boxes``) and COCO
boxes without segmentation, mmdetection3d's kind (``coco_warp.move_image``).

A KITTI-size frame (1242 × 375 px) through windscreen distortion (Brown–Conrady pull map with its Newton forward
map, :class:`~roadview_noise.physics.brown_conrady.LensWarp`) at D3.5's k1 = 1e-7 px⁻² and at a strong k1 = 1e-6
px⁻² (reference units of a 1936-px-wide image), with 100 and 500 boxes of 4–400 px (fixed seed, some crossing the
border). Reports the thread's CPU time per call, ms, median and quartiles over the calls.

Before/after: ``--baseline DIR`` imports the package of another checkout (``git archive main | tar -x -C
/tmp/base``) under another name into the same process and times its calls and this checkout's in alternation
(ABBA), so the load of a shared machine hits both alike; the difference is the median of the paired differences.
Run: ``taskset -c 0 .venv/bin/python bench/bench_box_warp.py --baseline /tmp/base [--calls 101]``.
"""

from __future__ import annotations

import atexit
import importlib
import itertools
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

WIDTH, HEIGHT = 1242, 375
REFERENCE_WIDTH_PX = 1936
K1 = {"D3.5 k1=1e-7": 1e-7, "strong k1=1e-6": 1e-6}
CALLS = 101


def boxes_xyxy(n: int) -> np.ndarray:
    rng = np.random.default_rng(7)
    size = np.exp(rng.uniform(np.log(4), np.log(400), (n, 2))) * [1, 0.6]
    centre = rng.uniform([0, 0], [WIDTH, HEIGHT], (n, 2))
    return np.concatenate([centre - size / 2, centre + size / 2], axis=1)


class Package:
    """One checkout's box mover with its own warps and box records."""

    def __init__(self, name: str):
        self.warp_boxes = importlib.import_module(f"{name}.annotations").warp_boxes
        self.coco = importlib.import_module(f"{name}.coco_warp")
        self.io = importlib.import_module(f"{name}.io.annotations")
        self.bc = importlib.import_module(f"{name}.physics.brown_conrady")

    def case(self, fmt: str, k1: float, n: int):
        coefficients = (k1,) + (0.0,) * (len(self.bc.COEFFICIENTS) - 1)
        unit = WIDTH / REFERENCE_WIDTH_PX
        warp = self.bc.BrownConrady(coefficients, ((WIDTH - 1) / 2, (HEIGHT - 1) / 2), (unit, unit)).pull_map(
            HEIGHT, WIDTH)
        b = boxes_xyxy(n)
        if fmt == "coco":
            anns = [(i, {"id": i, "bbox": [x0, y0, x1 - x0, y1 - y0], "area": 1.0})
                    for i, (x0, y0, x1, y1) in enumerate(b + 0.5)]
            return self.coco.CocoImage(0, "f.png", WIDTH, HEIGHT, "", anns), [warp]
        return self.io.Boxes2D("kitti", [["Car"] * 15 for _ in b], [x.reshape(2, 2) for x in b], [True] * n), [warp]

    def call(self, case) -> float:
        boxes, warps = case
        c0 = time.thread_time()
        if isinstance(boxes, self.coco.CocoImage):
            self.coco.move_image(boxes, (HEIGHT, WIDTH), warps)
        else:
            self.warp_boxes(boxes, warps, WIDTH, HEIGHT)
        return time.thread_time() - c0


def import_baseline(checkout: Path) -> Package:
    """The baseline's ``roadview_noise`` copied to a temporary folder (removed at exit) as
    ``roadview_noise_baseline``."""
    tmp = Path(tempfile.mkdtemp(prefix="rvnoise-baseline-"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    shutil.copytree(checkout / "roadview_noise", tmp / "roadview_noise_baseline",
                    ignore=shutil.ignore_patterns("__pycache__"))
    sys.path.insert(0, str(tmp))
    return Package("roadview_noise_baseline")


def _quartiles(ms: list[float]) -> str:
    q1, q2, q3 = statistics.quantiles(ms, n=4)
    return f"{q2:7.2f} ({q1:.2f}–{q3:.2f})"


def main() -> int:
    calls = int(sys.argv[sys.argv.index("--calls") + 1]) if "--calls" in sys.argv else CALLS
    after = Package("roadview_noise")
    before = import_baseline(Path(sys.argv[sys.argv.index("--baseline") + 1]).resolve()) \
        if "--baseline" in sys.argv else None
    print(f"boxes on {WIDTH}×{HEIGHT} px, CPU ms per call, median (quartiles) of {calls} calls"
          + (", ABBA with the baseline; difference: median of paired differences" if before else ""))
    for fmt, label, n in itertools.product(("kitti", "coco"), K1, (100, 500)):
        cases = {pkg: pkg.case(fmt, K1[label], n) for pkg in (after, before) if pkg is not None}
        for pkg, case in cases.items():
            pkg.call(case)                                       # warm-up: compiled kernels
        a, b = [], []
        for i in range(calls):
            for pkg in ((after, before) if i % 2 == 0 else (before, after)):
                if pkg is not None:
                    (a if pkg is after else b).append(1e3 * pkg.call(cases[pkg]))
        line = f"{fmt:5s} {label:15s} {n:3d} boxes  after {_quartiles(a)}"
        if before is not None:
            diff = statistics.median(x - y for x, y in zip(a, b))
            line += f"   before {_quartiles(b)}   difference {diff:+.2f} ms"
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
