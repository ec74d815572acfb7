"""Paired A/B of KITTI's ring and column recovery (:func:`roadview_noise.physics.laser_order.laser_order`) against
another version of ``laser_order.py`` (e.g. main's: ``git show main:roadview_noise/physics/laser_order.py >
/tmp/laser_order_main.py``), loaded into this package so that both use the same helpers; alternating calls in one
process, then per version: ms per scan (median and min…max), the columns W and the returns sharing a firing cell.

Run: ``.venv/bin/python bench/bench_laser_order_ab.py --baseline /tmp/laser_order_main.py scan.bin [scan.bin …]``
(full 360° KITTI ``.bin`` scans; none ships with rvnoise).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from roadview_noise.physics import laser_order as current  # noqa: E402
from roadview_noise.profiles.lidar import kitti_hdl64  # noqa: E402


def load_baseline(path: str):
    name = "roadview_noise.physics._laser_order_baseline"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def shared(found) -> int:
    cells = found.ring * found.columns + found.column
    return len(cells) - len(np.unique(cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", required=True, help="the other laser_order.py")
    parser.add_argument("--runs", type=int, default=21)
    parser.add_argument("scans", nargs="+")
    args = parser.parse_args()
    versions = {"baseline": load_baseline(args.baseline), "this": current}
    profile = kitti_hdl64()
    for path in args.scans:
        positions = np.fromfile(path, "<f4").reshape(-1, 4)[:, :3].astype(np.float64)
        times = {name: [] for name in versions}
        found = {name: module.laser_order(positions, profile) for name, module in versions.items()}   # warm-up
        for _ in range(args.runs):
            for name, module in versions.items():
                t0 = time.perf_counter()
                module.laser_order(positions, profile)
                times[name].append(1e3 * (time.perf_counter() - t0))
        print(f"{os.path.basename(path)} ({len(positions)} points)")
        for name in versions:
            f = found[name]
            what = f if isinstance(f, str) else (f"W = {f.columns}, {shared(f)} returns share a cell "
                                                 f"({100 * shared(f) / len(positions):.2f} %)")
            t = times[name]
            print(f"  {name:8s} {statistics.median(t):6.2f} ms ({min(t):.2f}–{max(t):.2f}); {what}")


if __name__ == "__main__":
    main()
