"""Where a camera rain/snow frame's time goes: thread CPU ms per stage of
:func:`roadview_noise.physics.particles.render_precipitation` (exclusive of the stages it calls), on
``bench_camera_weather.py``'s synthetic 1936×1464 Lucid frame.

Run on one core: ``taskset -c 0 .venv/bin/python bench/bench_precipitation_stages.py [--model snow.camera]
[--repeat N] [--ego-m-per-s V] [--cross-wind-m-per-s V]`` (medians over N frames, seeds 0 … N−1, after an untimed
warm-up frame, which also builds the tables of the camera, medium and conditions). The stages are the module
functions of ``physics/particles.py`` and ``physics/photometry.py`` that the frame calls (those absent from the
code under test are skipped, so the same script times an older checkout put first on ``PYTHONPATH``);
``other`` is the rest of the model step (depth, radiance estimate, diagnostics) and ``apply_models``' metrics of
the step (their luminance reads of the input and output frames: ≈ 4 ms of a snow frame)."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(1, str(Path(__file__).resolve().parent))      # after PYTHONPATH: an old checkout can come first

import cv2                                                    # noqa: E402

from bench_camera_weather import synthetic_scene              # noqa: E402
from roadview_noise.allocator import keep_freed_memory        # noqa: E402
from roadview_noise.compound import apply_models              # noqa: E402
from roadview_noise.physics import particles                  # noqa: E402
from roadview_noise.profiles.camera import lucid_triton_028s  # noqa: E402
from roadview_noise.registry import get_model                 # noqa: E402
from roadview_noise.types import Conditions                   # noqa: E402

STAGES = ("particle_tables", "explicit_depth_limits", "sample_particles", "block_keys", "_render_streaks", "add_upsampled",
          "render_coverage", "resolved_depth_limits", "unresolved_field", "transmit_through_particles", "veil_optical_depth_table",
          "veil_transmission", "composite", "blend_through_particles")


def instrument(totals: dict[str, float]) -> None:
    """Wrap the stages found in the particles module so that ``totals[name]`` accumulates their exclusive CPU ms."""
    stack: list[float] = []                  # time spent in children of each open stage

    def wrap(name, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            stack.append(0.0)
            t0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent = time.thread_time() - t0
                children = stack.pop()
                totals[name] = totals.get(name, 0.0) + 1e3 * (spent - children)
                if stack:
                    stack[-1] += spent
        return timed

    for name in STAGES:
        if hasattr(particles, name):
            setattr(particles, name, wrap(name, getattr(particles, name)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="snow.camera")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--ego-m-per-s", type=float, default=0.0, help="ego speed forward (conditions)")
    ap.add_argument("--cross-wind-m-per-s", type=float, default=0.0, help="wind from the right (conditions)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    keep_freed_memory()
    frame = dataclasses.replace(synthetic_scene(lucid_triton_028s()), conditions=Conditions(
        ego_velocity_m_per_s=(args.ego_m_per_s, 0.0, 0.0), wind_velocity_m_per_s=(0.0, args.cross_wind_m_per_s, 0.0)))
    model = get_model(args.model)()
    totals: dict[str, float] = {}
    instrument(totals)
    apply_models([model], frame, seed=0, key="warm-up", sequence_id="bench")
    rows: dict[str, list[float]] = {}
    for i in range(args.repeat):
        totals.clear()
        t0 = time.thread_time()
        _, records = apply_models([model], frame, seed=i, key="bench", sequence_id="bench")
        step = 1e3 * (time.thread_time() - t0)
        for name, ms in totals.items():
            rows.setdefault(name, []).append(ms)
        rows.setdefault("other", []).append(step - sum(totals.values()))
        rows.setdefault("total", []).append(step)
    diag = records[-1].diagnostics
    print(f"{args.model} (ego {args.ego_m_per_s} m/s, cross wind {args.cross_wind_m_per_s} m/s): "
          f"{diag.get('particles_drawn')} explicit particles; CPU ms per frame, median [min–max] of {args.repeat}")
    for name, ms in rows.items():
        print(f"  {name:26s} {statistics.median(ms):7.1f}  [{min(ms):6.1f}–{max(ms):6.1f}]")


if __name__ == "__main__":
    main()
