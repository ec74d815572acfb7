"""Benchmark of KITTI's ring recovery (:mod:`roadview_noise.physics.laser_order`) and what it gives the LiDAR weather.

For each KITTI / SemanticKITTI ``.bin`` scan given (N×4 float32, ring-less; none ships with rvnoise — pass full 360°
scans, e.g. KITTI raw ``velodyne_points/data/*.bin``):

1. the recovery alone, ``laser_order(positions, profile)``: ms per scan (median and min…max of 15 runs after a
   warm-up), the rings found, the measured firing columns, the returns sharing a cell (dual returns, the seam);
2. fog (MOR 30 m), rain (20 mm/h) and snow (2.5 mm/h), each run once per profile, paired A/B in one process:
   *before* = the profile main had (uniform +2° … −24.8° beam table, rings from elevations, no storage order),
   *after* = ``kitti-hdl64`` (fitted table, rings and columns from the storage order): empty rays, weather returns
   added on them, where the empty rays came from, and the step's ms (alternating A/B, median of 5 each).

Run: ``.venv/bin/python bench/bench_kitti_rings.py scan.bin [scan.bin …]`` (same seed: reproducible counts).
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import sys
import time
import warnings

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from roadview_noise.compound import apply_models  # noqa: E402
from roadview_noise.io.pointcloud import read_pointcloud  # noqa: E402
from roadview_noise.physics.laser_order import LaserOrderWarning, laser_order  # noqa: E402
from roadview_noise.profiles.lidar import kitti_hdl64  # noqa: E402
from roadview_noise.registry import get_model  # noqa: E402

WEATHER = (("fog.lidar", {"visibility_m": 30.0}), ("rain.lidar", {"rain_rate_mm_per_h": 20.0}),
           ("snow.lidar", {"snowfall_rate_mm_per_h": 2.5}))


def before_profile():
    """The kitti-hdl64 profile of main c78d1c8: 64 beams evenly from +2° to −24.8°, no storage order."""
    after = kitti_hdl64()
    return dataclasses.replace(after, beam_elevation_deg=tuple(float(e) for e in np.linspace(2.0, -24.8, 64)),
                               storage_order="")


def recovery(path: str) -> None:
    positions = np.fromfile(path, "<f4").reshape(-1, 4)[:, :3].astype(np.float64)
    profile = kitti_hdl64()
    found = laser_order(positions, profile)
    times = []
    for _ in range(15):
        t0 = time.perf_counter()
        laser_order(positions, profile)
        times.append(1e3 * (time.perf_counter() - t0))
    if isinstance(found, str):
        print(f"  recovery: {found}")
    else:
        cells = found.ring * found.columns + found.column
        shared = len(cells) - len(np.unique(cells))
        print(f"  recovery: {found.ring.max() + 1} rings, {found.columns} columns, {shared} returns share a cell")
    print(f"  recovery time: median {statistics.median(times):.1f} ms (min {min(times):.1f}, max {max(times):.1f}) "
          f"for {len(positions)} points")


def weather(path: str) -> None:
    clouds = {name: read_pointcloud(path, profile=profile) for name, profile in
              (("before", before_profile()), ("after", kitti_hdl64()))}
    for model_id, params in WEATHER:
        model = get_model(model_id)(**params)
        times = {"before": [], "after": []}
        counts = {}
        for rep in range(5):
            for name in ("before", "after") if rep % 2 == 0 else ("after", "before"):
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", LaserOrderWarning)
                    _, records = apply_models([model], clouds[name], seed=1, key=path, sequence_id="s",
                                              metrics=False)
                times[name].append(1e3 * (time.perf_counter() - t0))
                counts[name] = records[0].diagnostics
        for name in ("before", "after"):
            d = counts[name]
            print(f"  {model_id:10s} {name:6s}: empty rays {d.get('empty_rays', 0):6d}, added {d.get('added', 0):6d}, "
                  f"step {statistics.median(times[name]):7.1f} ms (min {min(times[name]):.1f}, "
                  f"max {max(times[name]):.1f}); {d.get('empty_rays_source', '')}")


def main(paths: list[str]) -> None:
    for path in paths:
        print(path)
        recovery(path)
        weather(path)


if __name__ == "__main__":
    main(sys.argv[1:] or ["/work/realdata/mmdet3d/demo/data/kitti/000008.bin"])
