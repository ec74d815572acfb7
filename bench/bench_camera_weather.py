"""Per-frame time of the camera weather models on one core: fog, rain (50 mm/h), snow (3.03 mm/h), the CNF16
wind + rain chain, and fog/rain on the same frame as an RGGB mosaic; a synthetic 1936×1464 Lucid Triton frame
with a range map (sky, ground, walls). Targets: fog ≤ 30 ms, rain and snow ≤ 60 ms.

Run: ``.venv/bin/python bench/bench_camera_weather.py [--repeat N] [--save DIR]`` (prints ms per frame:
minimum and median over N frames, each with a different seed). A warm-up frame per case, not timed, builds the
cached tables and loads the numba kernels (compiled once per install, ~2 s, then read from numba's cache)."""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from roadview_noise.allocator import keep_freed_memory
from roadview_noise.compound import apply_models
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.registry import get_model
from roadview_noise.types import CameraFrame, CameraProfile, RawFrame, cfa_index_map


def synthetic_scene(profile: CameraProfile, seed: int = 0) -> CameraFrame:
    """Sky (range inf), a flat road at the camera height, and three textured walls at 8, 15 and 40 m."""
    h, w = profile.height_px, profile.width_px
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - profile.cx_px) / profile.fx_px, (v - profile.cy_px) / profile.fy_px
    ray = np.sqrt(1 + x * x + y * y)
    with np.errstate(divide="ignore"):
        z = np.where(y > 0, profile.height_above_ground_m / y, np.inf)      # ground plane, planar depth
    img = np.empty((h, w, 3))
    img[:] = (0.55, 0.65, 0.85)                                             # sky
    ground = np.isfinite(z)
    img[ground] = 0.12 + 0.04 * rng.random((int(ground.sum()), 1))
    for z_wall, (x0, x1), colour in ((8.0, (-4.0, -1.5), (0.5, 0.2, 0.15)), (15.0, (1.0, 5.0), (0.2, 0.35, 0.2)),
                                     (40.0, (-12.0, 12.0), (0.3, 0.3, 0.32))):
        on = (x * z_wall >= x0) & (x * z_wall <= x1) & (y * z_wall >= -3.0) & (z_wall < z)
        z = np.where(on, z_wall, z)
        stripes = 0.8 + 0.2 * (np.sin(2 * math.pi * u / 24.0) > 0)
        img[on] = np.asarray(colour) * stripes[on, None]
    return CameraFrame(img.astype(np.float32), profile, (z * ray).astype(np.float32))


def bayer(frame: CameraFrame) -> RawFrame:
    """The frame as a 12-bit RGGB mosaic (black 64, white 4095 DN)."""
    ch = cfa_index_map("RGGB", *frame.shape)
    site = np.take_along_axis(frame.linear_rgb, ch[..., None].astype(np.int64), axis=2)[..., 0]
    return RawFrame((64 + site * (4095 - 64)).astype(np.float32), "RGGB", 64.0, 4095.0, frame.profile, frame.depth_m)


CASES = {
    "fog.camera (V = 30 m)": [("fog.camera", {})],
    "rain.camera (50 mm/h)": [("rain.camera", {})],
    "snow.camera (3.03 mm/h)": [("snow.camera", {})],
    "wind.camera + rain.camera (CNF16)": [("wind.camera", {}), ("rain.camera", {})],
    "raw RGGB fog.camera": [("fog.camera", {})],
    "raw RGGB rain.camera": [("rain.camera", {})],
}


def setup(doc: str) -> tuple[argparse.Namespace, CameraFrame, RawFrame]:
    """Command line (--repeat, --save), one OpenCV thread, and the synthetic frame with its RGGB mosaic."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--save", type=Path, help="write one sRGB PNG per case here")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    keep_freed_memory()                                        # as in the runner's workers
    frame = synthetic_scene(lucid_triton_028s())
    print(f"frame {frame.shape[1]}×{frame.shape[0]}, {args.repeat} frames per case, one core")
    return args, frame, bayer(frame)


def main() -> None:
    args, frame, raw = setup(__doc__)
    for name, steps in CASES.items():
        data = raw if name.startswith("raw") else frame
        models = [get_model(mid)(**params) for mid, params in steps]
        apply_models(models, data, seed=0, key="warm-up", sequence_id="bench")   # tables and caches
        times = []
        for i in range(args.repeat):
            t0 = time.perf_counter()
            out, records = apply_models(models, data, seed=i, key="bench", sequence_id="bench")
            times.append(1e3 * (time.perf_counter() - t0))
        drawn = records[-1].diagnostics.get("particles_drawn")
        print(f"{name:36s} min {min(times):6.1f} ms   median {statistics.median(times):6.1f} ms"
              + (f"   {drawn} explicit particles" if drawn is not None else ""))
        if args.save and not name.startswith("raw"):
            args.save.mkdir(parents=True, exist_ok=True)
            lin = np.clip(out.linear_rgb, 0, 1)
            srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
            fname = args.save / (steps[-1][0].split(".")[0] + ("_wind" if len(steps) > 1 else "") + ".png")
            cv2.imwrite(str(fname), cv2.cvtColor((srgb * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    main()
