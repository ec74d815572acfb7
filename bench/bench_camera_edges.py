"""The camera path's edges on one 1936×1464 frame: sRGB conversions, ``compression.camera`` against the JPEG codec
alone and albumentations' ``ImageCompression`` (issue 19: ≤ 2×), the depth EXR read.

Each figure is the median over ``--repeat`` calls of the wall time and of the thread's CPU time (the CPU time is the
steadier figure on a shared machine; neither counts other processes' waits). ``--against DIR`` runs the same
script in another checkout (its own ``.venv``) and this one alternately, ``--rounds`` times each, and prints both
side by side (medians over the rounds): a paired A/B in the same time window. albumentations is optional
(``.venv/bin/pip install --no-deps albumentations==2.0.8 albucore==0.0.24 stringzilla simsimd``).

    .venv/bin/python bench/bench_camera_edges.py [--repeat N] [--against /work/main --rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def timed(fn, repeat: int) -> tuple[float, float]:
    """(wall ms, thread CPU ms), medians of ``repeat`` calls after one warm-up call."""
    fn()
    wall, cpu = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.thread_time()
        fn()
        cpu.append(time.thread_time() - c)
        wall.append(time.perf_counter() - w)
    return 1e3 * statistics.median(wall), 1e3 * statistics.median(cpu)


def measure(repeat: int) -> dict[str, tuple[float, float]]:
    """Every row of the table in this checkout."""
    from roadview_noise.allocator import keep_freed_memory
    from roadview_noise.io.depth import read_depth, write_depth_exr
    from roadview_noise.io.image import read_image
    from roadview_noise.models.camera.compression import CompressionCamera
    from roadview_noise.physics import srgb
    from roadview_noise.profiles.camera import lucid_triton_028s
    from roadview_noise.types import CameraFrame
    from bench_foundation import camera_frame

    keep_freed_memory()
    cv2.setNumThreads(1)                                       # as in the runner's workers
    rng = np.random.default_rng(0)
    base = camera_frame().linear_rgb
    codes = srgb.linear_to_code(base)                          # photo-like: σ = 2 codes of sensor noise
    codes = np.clip(np.rint(codes + rng.normal(0, 2, codes.shape)), 0, 255).astype(np.uint8)
    with tempfile.TemporaryDirectory() as tmp:
        png, exr = Path(tmp) / "f.png", Path(tmp) / "f_depth.exr"
        cv2.imwrite(str(png), codes[..., ::-1])
        h, w = codes.shape[:2]
        depth = np.where(np.arange(h)[:, None] < h // 3, np.inf, 5 + 50 * rng.random((h, w))).astype(np.float32)
        write_depth_exr(exr, depth)
        decoded, _, _ = read_image(png)                        # an unchanged frame: keeps its codes
        changed = decoded * np.float32(0.9)                    # a frame a weather step changed
        profile = lucid_triton_028s()
        model = CompressionCamera(quality=15)
        frames = {"changed": CameraFrame(changed, profile), "unchanged": CameraFrame(decoded, profile)}
        bgr = np.ascontiguousarray(srgb.linear_to_code(changed)[..., ::-1])
        jpeg = [cv2.IMWRITE_JPEG_QUALITY, 15]
        rows = {
            "compression.camera Q15, changed frame": lambda: model.apply(frames["changed"], state={}, drawn={},
                                                                         rng=None),
            "compression.camera Q15, unchanged frame": lambda: model.apply(frames["unchanged"], state={}, drawn={},
                                                                           rng=None),
            "OpenCV JPEG encode + decode alone (Q15)": lambda: cv2.imdecode(cv2.imencode(".jpg", bgr, jpeg)[1],
                                                                            cv2.IMREAD_COLOR),
            "sRGB linear → 8-bit codes": lambda: srgb.linear_to_code(changed),
            "sRGB linear → 16-bit codes": lambda: srgb.linear_to_code(changed, 16),
            "sRGB 8-bit codes → linear": lambda: srgb.code_to_linear(codes),
            "sRGB 8-bit BGR codes → linear RGB (reversed view)": lambda: srgb.code_to_linear(bgr[..., ::-1]),
            "read_image PNG (decode + convert)": lambda: read_image(png),
            "read_depth EXR": lambda: read_depth(exr),
        }
        try:
            import albumentations as A

            t = A.ImageCompression(quality_range=(15, 15), p=1)
            rgb = np.ascontiguousarray(bgr[..., ::-1])
            rows[f"albumentations {A.__version__} ImageCompression (Q15)"] = lambda: t(image=rgb)
        except ImportError:
            pass
        return {label: timed(fn, repeat) for label, fn in rows.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--against", type=Path, help="another checkout to compare with, alternately (paired A/B)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", action="store_true", help="print the raw figures as JSON (used by --against)")
    args = ap.parse_args()
    if args.json:
        print(json.dumps(measure(args.repeat)))
        return
    checkouts = {"this": ROOT} if args.against is None else {"other": args.against.resolve(), "this": ROOT}
    runs: dict[str, list[dict]] = {k: [] for k in checkouts}
    for _ in range(args.rounds if args.against else 1):
        for key, root in checkouts.items():
            out = subprocess.run([str(root / ".venv" / "bin" / "python"), str(Path(__file__).resolve()), "--json",
                                  "--repeat", str(args.repeat)], cwd=root, check=True, capture_output=True,
                                 text=True, env={**os.environ, "PYTHONPATH": str(root)})
            runs[key].append(json.loads(out.stdout.strip().splitlines()[-1]))
    labels = list(dict.fromkeys(label for r in runs.values() for run in r for label in run))
    names = {"this": str(ROOT), "other": str(args.against)}
    print("| one 1936×1464 frame (medians; wall / thread CPU ms) | " +
          " | ".join(names[k] for k in checkouts) + " |")
    print("|---|" + "---|" * len(checkouts))
    for label in labels:
        cells = []
        for key in checkouts:
            got = [r[label] for r in runs[key] if label in r]
            cells.append(f"{statistics.median(g[0] for g in got):.1f} / {statistics.median(g[1] for g in got):.1f}"
                         if got else "–")
        print(f"| {label} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
