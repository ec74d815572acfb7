"""Cost of moving one image's COCO annotations through windscreen distortion, against the windscreen step itself.

A KITTI-size frame (1242 × 375 px) with a COCO-like load: ``--polygons`` instance polygons of 24 vertices, two RLE
crowd masks (one compressed string, one counts list), ``--boxes`` box-only annotations with mmdetection3d's
``center2d``. Times, alternating in one process (so the load of a shared machine hits both alike), the windscreen
step (``apply_models``: warp and resample) and :func:`coco_warp.move_image` through the same warp; prints medians
and quartiles of the thread's CPU time. Run: ``taskset -c 0 .venv/bin/python bench/bench_coco.py [--frames 41]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from roadview_noise.coco_warp import CocoImage, move_image  # noqa: E402
from roadview_noise.compound import apply_models  # noqa: E402
from roadview_noise.io import coco as coco_io  # noqa: E402
from roadview_noise.models.camera.windscreen import WindscreenCamera  # noqa: E402
from roadview_noise.profiles.camera import carla_pinhole  # noqa: E402
from roadview_noise.types import CameraFrame  # noqa: E402

W, H = 1242, 375


def annotations(polygons: int, boxes: int, rng) -> list[tuple[int, dict]]:
    out = []
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    for i in range(polygons):
        cx, cy, r = rng.uniform(60, W - 60), rng.uniform(40, H - 40), rng.uniform(10, 40)
        ring = np.stack([cx + r * np.cos(t), cy + 0.7 * r * np.sin(t)], 1)
        x0, y0 = ring.min(0)
        x1, y1 = ring.max(0)
        out.append({"id": i, "segmentation": [ring.ravel().tolist()], "bbox": [x0, y0, x1 - x0, y1 - y0],
                    "area": 1.0, "iscrowd": 0})
    for k, compressed in enumerate((True, False)):
        m = np.zeros((H, W), np.uint8)
        m[100 + 100 * k: 180 + 100 * k, 200: 500] = 1
        out.append({"id": polygons + k, "segmentation": coco_io.rle_encode(m, compressed), "area": int(m.sum()),
                    "bbox": [200, 100 + 100 * k, 300, 80], "iscrowd": 1})
    for j in range(boxes):
        x, y = rng.uniform(0, W - 80), rng.uniform(0, H - 60)
        out.append({"id": polygons + 2 + j, "bbox": [x, y, 60, 40], "area": 2400.0, "iscrowd": 0,
                    "center2d": [x + 30, y + 20, 20.0]})
    return list(enumerate(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=41)
    ap.add_argument("--polygons", type=int, default=30)
    ap.add_argument("--boxes", type=int, default=10)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    frame = CameraFrame(rng.uniform(0, 1, (H, W, 3)).astype(np.float32), carla_pinhole(W, H))
    image = CocoImage(7, "000007.png", W, H, "", annotations(args.polygons, args.boxes, rng))
    model = WindscreenCamera(k1=1e-7)
    chain, move = [], []
    for i in range(args.frames):
        c0 = time.thread_time()
        out, _ = apply_models([model], frame, seed=1, key=f"f{i}", sequence_id="s")
        c1 = time.thread_time()
        record = move_image(image, frame.shape, out.warps)
        c2 = time.thread_time()
        chain.append(c1 - c0)
        move.append(c2 - c1)
    assert len(record["moved"]) + len(record["dropped"]) == len(image.annotations)
    for name, xs in (("windscreen step", chain), ("COCO annotations", move)):
        q = statistics.quantiles(xs, n=4)
        print(f"{name:>17}: median {1e3 * statistics.median(xs):7.2f} ms CPU (quartiles {1e3 * q[0]:.2f}–"
              f"{1e3 * q[2]:.2f}), {len(xs)} frames")
    print(f"annotations: {args.polygons} polygons × 24 vertices, 2 RLE masks, {args.boxes} boxes; ratio of medians "
          f"{statistics.median(move) / statistics.median(chain):.2f}")


if __name__ == "__main__":
    main()
