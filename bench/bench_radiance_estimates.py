"""Per-frame cost of the camera weather models' radiance estimates (``physics/photometry.py``): what a fog, rain or
snow step spends on them, thread CPU ms, on ``bench_camera_weather.py``'s synthetic 1936×1464 Lucid frame as RGB
and as a 12-bit RGGB mosaic, each also with depth holes (``depth_valid`` false on 8 % of the pixels).

``airlight`` (fog, snow) and ``raindrop`` (rain) each include the step's depth check (``frame_depth_m``; before round
10 also its ``estimation_depth``, a full-frame depth with NaN holes), not the frame's ``signal()`` (read once per
step for all its uses).
Run on one core::

    taskset -c 0 .venv/bin/python bench/bench_radiance_estimates.py [--repeat N] [--base DIR]

``--base DIR``: an older checkout (e.g. ``git archive main | tar -x -C DIR``) loaded in the same process; its
estimates and this checkout's alternate call by call, and the script says whether their values are identical."""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
ESTIMATES = ("airlight", "raindrop")


def load(checkout: Path):
    """``physics.photometry`` and ``physics.cfa`` of ``checkout``, imported afresh."""
    for name in [n for n in sys.modules if n == "roadview_noise" or n.startswith("roadview_noise.")]:
        del sys.modules[name]
    sys.path.insert(0, str(checkout))
    try:
        return (importlib.import_module("roadview_noise.physics.photometry"),
                importlib.import_module("roadview_noise.physics.cfa"))
    finally:
        sys.path.remove(str(checkout))


def estimate(photometry, cfa, frame, signal, kind: str) -> np.ndarray:
    layout = cfa.SiteLayout(frame.channel_index())
    depth = photometry.frame_depth_m(frame, "bench")
    radiance = photometry.airlight_radiance if kind == "airlight" else photometry.raindrop_radiance
    if hasattr(photometry, "estimation_depth"):            # before round 10: a full-frame depth with NaN holes
        return radiance(layout, signal, photometry.estimation_depth(frame, depth))
    return radiance(layout, signal, depth, frame.depth_valid)


def frames():
    sys.path.insert(0, str(HERE))
    from bench_camera_weather import bayer, synthetic_scene
    from roadview_noise.profiles.camera import lucid_triton_028s
    rgb = synthetic_scene(lucid_triton_028s())
    valid = np.ones(rgb.depth_m.shape, bool)
    valid[700:760] = False
    valid[:, 100:140] = False
    raw = bayer(rgb)
    for name, frame in (("RGB", rgb), ("RGGB", raw)):
        yield name, frame
        yield name + " + holes", dataclasses.replace(frame, depth_valid=valid)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=21)
    ap.add_argument("--base", type=Path, help="older checkout to compare with, paired in this process")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    versions = {"this": load(HERE.parent)}
    if args.base:
        versions = {"base": load(args.base), **versions}
    print(f"thread CPU ms per frame, median [quartiles] of {args.repeat}" +
          (f"; base = {args.base}" if args.base else ""))
    for name, frame in frames():
        signal = frame.signal()
        for kind in ESTIMATES:
            values = {v: estimate(*mods, frame, signal, kind) for v, mods in versions.items()}     # warm-up
            times: dict[str, list[float]] = {v: [] for v in versions}
            order = list(versions)
            for i in range(args.repeat):
                for v in order if i % 2 == 0 else order[::-1]:
                    t0 = time.thread_time()
                    estimate(*versions[v], frame, signal, kind)
                    times[v].append(1e3 * (time.thread_time() - t0))
            cells = "  ".join(f"{v} {statistics.median(ts):6.2f} [{np.percentile(ts, 25):.2f}–"
                              f"{np.percentile(ts, 75):.2f}]" for v, ts in times.items())
            same = "" if len(values) < 2 else "  identical" if np.array_equal(*values.values()) else "  DIFFERENT"
            print(f"  {name:13s} {kind:9s} {cells}{same}")


if __name__ == "__main__":
    main()
