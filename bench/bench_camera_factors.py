"""Per-frame time of the camera noise factors on one core — windscreen (k1 = 1e-7 px⁻²), motion blur (D3.5 radial,
b 0.002, n 7; and the physical mode at 15 m/s), lens soiling (D3.5 mud), low light (physical: 10 lx, gain 8) — on
a synthetic 1936×1464 Lucid Triton frame and the same frame as an RGGB mosaic. Targets: windscreen ≤ 25 ms,
motion blur ≤ 60 ms, soiling ≤ 30 ms, low light ≤ 60 ms.

Next to them, in the same run, albumentations' OpticalDistortion, ZoomBlur and Spatter(mud) on the same frame as
8-bit RGB (their usual input), when albumentations is installed. Its wheel requires opencv-python-headless, which
would shadow the project's opencv-contrib build, so install it without dependencies:
``.venv/bin/pip install --no-deps albumentations==2.0.8 albucore==0.0.24 stringzilla simsimd``.

Run: ``.venv/bin/python bench/bench_camera_factors.py [--repeat N] [--save DIR]`` (ms per frame: minimum and
median over N frames, after one untimed warm-up frame per case that builds caches and loads numba kernels). The
batch workers' allocator setting (``roadview_noise.allocator``) is applied, as in a run. The models are timed
without the manifest metrics that ``augment`` adds by default (``output: {metrics: false}`` turns them off; their
cost is ``bench/bench_metrics.py``'s subject)."""

from __future__ import annotations

import statistics
import time

import cv2
import numpy as np
from bench_camera_weather import setup

from roadview_noise.allocator import keep_freed_memory
from roadview_noise.compound import apply_models
from roadview_noise.physics import srgb
from roadview_noise.registry import get_model

CASES = {
    "windscreen.camera (k1 1e-7 px⁻²)": ("windscreen.camera", {}),
    "motion_blur.camera (b 0.002, n 7)": ("motion_blur.camera", {}),
    "motion_blur.camera physical (15 m/s, depth)": ("motion_blur.camera", {"mode": "physical",
                                                                            "ego_speed_m_per_s": 15.0}),
    "soiling.camera (D3.5 mud)": ("soiling.camera", {}),
    "low_light.camera (10 lx, gain 8)": ("low_light.camera", {}),
    "raw RGGB windscreen.camera": ("windscreen.camera", {}),
    "raw RGGB motion_blur.camera": ("motion_blur.camera", {}),
    "raw RGGB soiling.camera": ("soiling.camera", {}),
    "raw RGGB low_light.camera": ("low_light.camera", {}),
}


def albumentations_cases() -> dict:
    try:
        import albumentations as A
    except ImportError:
        return {}
    return {  # settings close to the D3.5 values: k1 ≈ 0.13 normalised, zoom range ≈ ±1.4 % in 7 steps, mud
        f"albumentations {A.__version__} OpticalDistortion (0.13)": A.OpticalDistortion(distort_limit=(0.13, 0.13),
                                                                                        p=1.0),
        f"albumentations {A.__version__} ZoomBlur (1.03, step 0.004)": A.ZoomBlur(max_factor=(1.03, 1.03),
                                                                                  step_factor=(0.004, 0.004), p=1.0),
        f"albumentations {A.__version__} Spatter (mud)": A.Spatter(mode="mud", p=1.0),
    }


def timed(run, repeat: int) -> list[float]:
    run(-1)                                                   # warm-up: caches, numba kernels
    times = []
    for i in range(repeat):
        t0 = time.perf_counter()
        run(i)
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    args, frame, raw = setup(__doc__)
    keep_freed_memory()
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
    for name, (mid, params) in CASES.items():
        data = raw if name.startswith("raw") else frame
        model = get_model(mid)(**params)
        out = {}

        def run(i, model=model, data=data, out=out):
            out["data"], _ = apply_models([model], data, seed=0, key=f"frame{i}", sequence_id="bench",
                                          metrics=False)

        t = timed(run, args.repeat)
        print(f"{name:<46} min {1e3 * min(t):6.1f} ms   median {1e3 * statistics.median(t):6.1f} ms")
        if args.save and not name.startswith("raw"):
            png = srgb.linear_to_code(out["data"].linear_rgb, 8)[..., ::-1]
            cv2.imwrite(str(args.save / f"{mid}-{params.get('mode', 'reference')}.png"), png)
    rgb8 = np.ascontiguousarray(srgb.linear_to_code(frame.linear_rgb, 8))
    others = albumentations_cases()
    if not others:
        print("albumentations not installed: no comparison (see the docstring to install it)")
    for name, transform in others.items():
        t = timed(lambda i, transform=transform: transform(image=rgb8), args.repeat)
        print(f"{name:<46} min {1e3 * min(t):6.1f} ms   median {1e3 * statistics.median(t):6.1f} ms   (uint8)")


if __name__ == "__main__":
    main()
