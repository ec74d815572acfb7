"""Benchmark of the LiDAR weather models fog.lidar, rain.lidar, snow.lidar (one core).

1. A synthetic full 128×2048 OS1-128 range image (ground plane, two facades, parked cars, no-return sky cells),
   ray-cast analytically with the real beam table, ``signal`` intensities in whole photons (``K ρ cos θ / r²`` with
   the profile's sensor constant K; returns below the datasheet threshold are no returns, as the sensor records).
2. The real OS1-128 scan ../shared/data/os1-128/scan0.bin (107 k points, the OS1's calibrated 8-bit reflectivity,
   profile ``os1-128-reflectivity``: white reads 100, K = 65535 photons·m², receiver overlap 0.5 → 5 m), if present:
   a point list, whose 1024-column firing grid (the profile says 2048) and 23 425 empty rays the models measure;
   its detection threshold calibrated from its weakest returns; the time of that firing grid; a table rate → kept /
   attenuated / moved / removed / added; the acceptance figures of issue 14 (a trace of rain, the spread of fog
   returns, the largest jump of the weather returns between visibilities 1 % apart).
3. The convergence of rain and snow in ``draw_fraction_of_threshold``, and their strongest return drawn from each
   ray's brightest particle against the exhaustive draw (the real scan if present, else the synthetic grid).

Each model is timed in its own process (fresh heap; pin the bench to one core with ``taskset -c 0``). Prints per-model
ms per frame (min and median of 15 frames after a warm-up; the model alone, ``apply_models(metrics=False)``, and apart
the per-step metrics ``augment`` adds by default), the median CPU time of the process's thread (``time.thread_time``:
on a shared, loaded machine it leaves out the time the process waits for a core, so it varies less than the wall
time; cache contention still shows), the tracemalloc peak, the visible particles drawn, and the speed-up of the median
over the MATLAB reference (18 / 24 / 30 s per frame for fog / rain / snow, models.md §6). Rain and snow also print
their stages (CPU ms, median of 15 frames): cloud → rays (:func:`lidar_rays.cloud_rays`), the particle kernel
(:func:`lidar_weather.particle_returns`: draw, summed pulses, detection) and rays → cloud
(:func:`lidar_output.assemble`), and the particle kernel on the no-return rays and on the points alone (CPU ms, ns per
ray, particles drawn per ray).
Run: ``taskset -c 0 .venv/bin/python bench/bench_lidar_weather.py``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from roadview_noise.allocator import keep_freed_memory  # noqa: E402
from roadview_noise.compound import apply_models  # noqa: E402
from roadview_noise.metrics import compare  # noqa: E402
from roadview_noise.models.lidar.fog import FogLidar  # noqa: E402
from roadview_noise.models.lidar.rain import RainLidar  # noqa: E402
from roadview_noise.models.lidar.snow import SnowLidar  # noqa: E402
from roadview_noise.physics.lidar_intensity import sensor_constant  # noqa: E402
from roadview_noise.physics.lidar_output import assemble  # noqa: E402
from roadview_noise.physics.lidar_rays import cloud_rays  # noqa: E402
from roadview_noise.physics.lidar_weather import particle_returns, precipitation  # noqa: E402
from roadview_noise.profiles.lidar import os1_128, os1_128_reflectivity  # noqa: E402
from roadview_noise.provenance import Effect
from roadview_noise.types import PointCloud  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "os1-128"
MATLAB_S = {"fog.lidar": 18.0, "rain.lidar": 24.0, "snow.lidar": 30.0}
D35 = {"fog.lidar": FogLidar(), "rain.lidar": RainLidar(), "snow.lidar": SnowLidar()}
REPEATS = 15


def synthetic_grid(columns: int = 2048) -> PointCloud:
    """Street canyon seen by an OS1-128 at 1.8 m: ground z = −1.8, facades y = ±9 m, 6 cars; photons."""
    prof = dataclasses.replace(os1_128(), columns=columns)
    rows = prof.channels
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))[:, None]
    az = (np.pi - 2 * np.pi * np.arange(columns)[None, :] / columns
          - np.deg2rad(np.asarray(prof.beam_azimuth_offset_deg))[:, None])
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1)
    d = d.reshape(-1, 3)
    best = np.full(len(d), np.inf)
    rho = np.zeros(len(d))
    cos_inc = np.zeros(len(d))

    def plane(axis: int, value: float, reflectance: float, lo: tuple, hi: tuple) -> None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = value / d[:, axis]
        hit = d[:, axis] != 0
        hit &= t > 0
        p = d * t[:, None]
        for k in range(3):
            if k != axis:
                hit &= (p[:, k] >= lo[k]) & (p[:, k] <= hi[k])
        closer = hit & (t < best)
        best[closer], rho[closer], cos_inc[closer] = t[closer], reflectance, np.abs(d[closer, axis])

    inf = np.inf
    plane(2, -1.8, 0.12, (-inf, -inf, 0), (inf, inf, 0))                    # asphalt
    plane(1, 9.0, 0.35, (-80, 0, -1.8), (150, 0, 12))                       # facades
    plane(1, -9.0, 0.35, (-80, 0, -1.8), (150, 0, 12))
    for x0 in (-25.0, -8.0, 6.0, 14.0, 30.0, 55.0):                          # cars: boxes 4.5 × 1.8 × 1.5 m
        y0 = 5.5 if x0 > 0 else -5.5
        box = dict(lo=(x0, y0 - 0.9, -1.8), hi=(x0 + 4.5, y0 + 0.9, -0.3))
        for axis, value in ((0, x0), (0, x0 + 4.5), (1, y0 - 0.9), (1, y0 + 0.9), (2, -0.3)):
            plane(axis, value, 0.6, box["lo"], box["hi"])
    signal = sensor_constant(prof) * rho * cos_inc / np.where(np.isfinite(best), best, 1.0) ** 2
    ok = (best <= prof.max_range_m) & (np.round(signal) >= prof.detection_threshold)
    intensity = np.where(ok, np.round(signal), 0.0)
    pos = np.where(ok[:, None], d * np.where(ok, best, 0.0)[:, None], 0.0)
    ring = np.repeat(np.arange(rows, dtype=np.uint16), columns)
    return PointCloud(pos, {"intensity": np.minimum(intensity, prof.intensity_full_scale).astype(np.float32),
                            "ring": ring}, "lidar", prof, grid_shape=(rows, columns))


def real_scan() -> PointCloud | None:
    path = SHARED / "scan0.bin"
    if not path.is_file():
        return None
    a = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    return PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3].copy()}, "lidar", os1_128_reflectivity())


def time_model(model, cloud: PointCloud) -> tuple[float, float, float, float, dict]:
    """(min, median) ms per frame over REPEATS after one warm-up frame (cached tables), the median CPU ms of the
    thread, the median ms of the per-step metrics that ``augment`` adds by default (:func:`metrics.compare`, timed
    apart: ``output: {metrics: false}`` turns them off), and the diagnostics."""
    apply_models([model], cloud, seed=1, key="warm", sequence_id="s", metrics=False)
    times, cpu_times, metric_times = [], [], []
    for i in range(REPEATS):
        t0, c0 = time.perf_counter(), time.thread_time()
        out, rec = apply_models([model], cloud, seed=1, key=f"bench{i}", sequence_id="s", metrics=False)
        times.append(time.perf_counter() - t0)
        cpu_times.append(time.thread_time() - c0)
        before = dataclasses.replace(cloud)            # a new object: its summary is not cached
        t0 = time.perf_counter()
        compare(before, out)
        metric_times.append(time.perf_counter() - t0)
    return (min(times) * 1e3, statistics.median(times) * 1e3, statistics.median(cpu_times) * 1e3,
            statistics.median(metric_times) * 1e3, rec[0].diagnostics)


def stage_times(model, cloud: PointCloud) -> dict:
    """Median CPU ms per frame of the stages of rain or snow (module doc), REPEATS frames after a warm-up."""
    medium = model.medium()
    times = {"rays": [], "kernel": [], "output": []}
    for i in range(REPEATS + 1):
        c0 = time.thread_time()
        rays = cloud_rays(cloud, model.id, model.empty_rays)
        c1 = time.thread_time()
        returns, _ = particle_returns(np.random.default_rng(i), rays, medium, model.return_mode,
                                      model.draw_fraction_of_threshold)
        c2 = time.thread_time()
        assemble(cloud, rays, returns)
        c3 = time.thread_time()
        if i:
            for key, t in zip(times, (c1 - c0, c2 - c1, c3 - c2)):
                times[key].append(t)
    stages = {key: statistics.median(t) * 1e3 for key, t in times.items()}
    return stages | {"classes": class_times(model, rays)}


def class_times(model, rays) -> dict:
    """Per ray class (the no-return rays, the points: the cloud's returns): rays, median CPU ms of the particle
    kernel on those rays alone and particles drawn per ray, REPEATS frames after a warm-up, the classes alternating."""
    medium = model.medium()
    classes = {"no-return rays": ~rays.has_target & (rays.range_m > 0), "points": rays.has_target}
    subsets = {key: dataclasses.replace(rays, range_m=rays.range_m[m], signal=rays.signal[m],
                                        has_target=rays.has_target[m], listed=None) for key, m in classes.items()}
    times, drawn = {key: [] for key in classes}, {key: [] for key in classes}
    for i in range(REPEATS + 1):
        for key, sub in subsets.items():
            c0 = time.thread_time()
            _, n = particle_returns(np.random.default_rng(i), sub, medium, model.return_mode,
                                    model.draw_fraction_of_threshold)
            if i:
                times[key].append(time.thread_time() - c0)
                drawn[key].append(n)
    return {key: [int(np.count_nonzero(m)), statistics.median(times[key]) * 1e3,
                  statistics.mean(drawn[key]) / max(int(np.count_nonzero(m)), 1)] for key, m in classes.items()}


def peak_memory_mb(model, cloud: PointCloud) -> float:
    tracemalloc.start()
    apply_models([model], cloud, seed=1, key="mem", sequence_id="s")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2 ** 20


def measure(scene: str, model_id: str) -> None:
    """One model on one scene in this (fresh) process: prints a JSON line."""
    keep_freed_memory()                                # as the batch workers do (roadview_noise.runner.process)
    cloud = synthetic_grid() if scene == "synthetic" else real_scan()
    model = D35[model_id]
    lo, med, cpu, metrics_ms, diag = time_model(model, cloud)
    stages = stage_times(model, cloud) if model_id != "fog.lidar" else {}
    print(json.dumps({"min_ms": lo, "median_ms": med, "cpu_ms": cpu, "metrics_ms": metrics_ms,
                      "peak_mb": peak_memory_mb(model, cloud), "stages_cpu_ms": stages, "diag": diag}))


def report(name: str, scene: str, cloud: PointCloud) -> None:
    """Each model in its own process (one core, fresh heap), so no model pays for another's memory layout."""
    print(f"\n{name}: {len(cloud)} rays, {int(np.count_nonzero(cloud.positions_m.any(axis=1)))} returns")
    print(f"{'model':12s} {'min ms':>7s} {'median':>7s} {'cpu ms':>7s} {'metrics':>8s} {'peak MB':>8s} "
          f"{'speed-up':>9s}  kept/attenuated/moved/removed/added  particles")
    stages = {}
    for mid in D35:
        res = subprocess.run([sys.executable, __file__, "--measure", scene, mid], capture_output=True, text=True,
                             check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
        r = json.loads(res.stdout.strip().splitlines()[-1])
        d = r["diag"]
        counts = "/".join(str(d[k]) for k in ("kept", "attenuated", "moved", "removed", "added"))
        print(f"{mid:12s} {r['min_ms']:7.1f} {r['median_ms']:7.1f} {r['cpu_ms']:7.1f} {r['metrics_ms']:8.1f} "
              f"{r['peak_mb']:8.1f} {MATLAB_S[mid] * 1e3 / r['median_ms']:8.0f}×  {counts}  "
              f"{d.get('particles_drawn', '')}")
        if r["stages_cpu_ms"]:
            stages[mid] = r["stages_cpu_ms"]
    print(f"  empty rays: {d['empty_rays']} ({d['empty_rays_source']}); detection threshold "
          f"{d['detection_threshold']:.3g} ({d['detection_threshold_source']})")
    for mid, st in stages.items():
        print(f"  {mid} stages (CPU ms, median): cloud → rays {st['rays']:.1f}, particle kernel {st['kernel']:.1f}, "
              f"rays → cloud {st['output']:.1f}")
        print("    its particle kernel by ray class (CPU ms, median; alone): " + ", ".join(
            f"{n} {key} {ms:.1f} ms ({1e6 * ms / max(n, 1):.0f} ns per ray, {per:.2f} particles per ray)"
            for key, (n, ms, per) in st["classes"].items()))


def firing_grid_time(cloud: PointCloud) -> None:
    """The part of every weather model's time a point list adds: its firing grid (ring recovery included)."""
    keep_freed_memory()
    rays = cloud_rays(cloud, "bench")

    def median_ms(empty_rays: str) -> float:
        times = []
        for _ in range(50):
            t0 = time.perf_counter()
            cloud_rays(cloud, "bench", empty_rays)
            times.append(time.perf_counter() - t0)
        return 1e3 * statistics.median(times)

    print(f"  rays of the list: {median_ms('fill'):.2f} ms with its {rays.empty_source} "
          f"({rays.n_points} points + {len(rays.range_m) - rays.n_points} empty rays), "
          f"{median_ms('ignore'):.2f} ms with empty_rays: ignore")


def rate_table(cloud: PointCloud) -> None:
    sweeps = {
        "fog.lidar": ("visibility_m", [float("inf"), 200.0, 100.0, 50.0, 30.0, 20.0, 10.0], FogLidar),
        "rain.lidar": ("rain_rate_mm_per_h", [0.0, 5.0, 10.0, 20.0, 50.0, 100.0, 150.0], RainLidar),
        "snow.lidar": ("snowfall_rate_mm_per_h", [0.0, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0], SnowLidar),
    }
    total = float(np.sum(cloud.fields["intensity"]))
    for mid, (pname, values, cls) in sweeps.items():
        print(f"\n{mid} on the real scan: {pname} → kept / attenuated / moved / removed / added, "
              "removed %, removed % of the returns above the datasheet threshold, lost (removed + moved) %, "
              "intensity left in place %")
        for v in values:
            out, rec = apply_models([cls(**{pname: v})], cloud, seed=1, key="table", sequence_id="s")
            d = rec[0].diagnostics
            in_place = out.effect <= 1
            left = float(np.sum(out.fields["intensity"][in_place])) / total
            removed, lost = d["removed"] / d["points_in"], (d["removed"] + d["moved"]) / d["points_in"]
            detectable = (d["removed"] - d["removed_below_threshold_in"]) / (d["points_in"] - d["below_threshold_in"])
            print(f"  {v:7g}: {d['kept']:6d} {d['attenuated']:6d} {d['moved']:6d} {d['removed']:6d} {d['added']:6d}"
                  f"   {100 * removed:6.2f} {100 * detectable:6.2f} {100 * lost:6.2f} {100 * left:7.2f}")
        print(f"  (returns below the profile's datasheet threshold in the clear scan, which calibrates it below them: "
              f"{d['below_threshold_in']})")


def draw_fraction_table(cloud: PointCloud, name: str) -> None:
    """Convergence of rain and snow in ``draw_fraction_of_threshold`` (the undrawn particles' backscatter is the
    particle models' one approximation): weather returns (moved + added) and particles per frame, mean of 4 frames."""
    print(f"\ndraw_fraction_of_threshold on the {name}: fraction → particles drawn, weather returns (moved + added)")
    for cls, fractions in ((RainLidar, (1 / 2, 1 / 4, 1 / 16, 1 / 64)), (SnowLidar, (1, 1 / 2, 1 / 4, 1 / 8))):
        for f in fractions:
            diags = [apply_models([cls(draw_fraction_of_threshold=f)], cloud, seed=1, key=f"df{i}",
                                  sequence_id="s")[1][0].diagnostics for i in range(4)]
            print(f"  {cls.id:11s} {f:7.4f}: {np.mean([d['particles_drawn'] for d in diags]):9.0f} "
                  f"{np.mean([d['moved'] + d['added'] for d in diags]):9.1f}")


def exhaustive_table(cloud: PointCloud, name: str) -> None:
    """The strongest return drawn from each ray's brightest particle (the default, :mod:`lidar_strongest`) against
    drawing every particle above the base level (``exhaustive``): particles drawn, weather returns (moved + added),
    targets kept in place (kept + attenuated), mean of 4 frames, D3.5 rates."""
    print(f"\nbrightest-first draw against the exhaustive draw on the {name}: particles, weather returns, targets in "
          "place (mean of 4 frames)")
    for model in (RainLidar(), SnowLidar()):
        for exhaustive in (False, True):
            diags = [precipitation(cloud, model.id, model.medium(), "strongest", np.random.default_rng(i),
                                   model.draw_fraction_of_threshold, exhaustive=exhaustive)[1] for i in range(4)]
            print(f"  {model.id:11s} {'exhaustive' if exhaustive else 'brightest':10s} "
                  f"{np.mean([d['particles_drawn'] for d in diags]):10.0f} "
                  f"{np.mean([d['moved'] + d['added'] for d in diags]):9.1f} "
                  f"{np.mean([d['kept'] + d['attenuated'] for d in diags]):9.1f}")


def acceptance(cloud: PointCloud) -> None:
    """Issue 14's figures on the real scan: points a trace of weather changes, the spread of fog-return ranges at
    MOR 30 m, and the largest change of the weather returns (moved + added) between visibilities 1 % apart."""
    print("\nacceptance figures on the real scan")
    n = len(cloud)
    for model in (RainLidar(rain_rate_mm_per_h=0.001), SnowLidar(snowfall_rate_mm_per_h=0.0001)):
        out, rec = apply_models([model], cloud, seed=1, key="trace", sequence_id="s")
        same = (np.all(out.positions_m[:n] == cloud.positions_m, axis=1) & (out.effect[:n] == Effect.KEPT)
                & (out.fields["intensity"][:n] == cloud.fields["intensity"])) if len(out) >= n else np.zeros(n, bool)
        print(f"  {model.id} at {model.params()[next(iter(model.params()))]:g} mm/h: "
              f"{100 * (n - same.sum() + len(out) - n) / n:.3f} % of the points changed")
    out, _ = apply_models([FogLidar(visibility_m=30.0)], cloud, seed=1, key="fog", sequence_id="s")
    fog = np.isin(out.effect, (Effect.MOVED, Effect.ADDED))
    print(f"  fog MOR 30 m: {fog.sum()} fog returns, range {np.mean(out.ranges_m[fog]):.3f} ± "
          f"{np.std(out.ranges_m[fog]):.3f} m")
    for lo, hi in ((300.0, 400.0), (2000.0, 6000.0)):
        vis = lo * 1.01 ** np.arange(int(np.ceil(np.log(hi / lo) / np.log(1.01))) + 1)
        counts = []
        for v in vis:
            d = apply_models([FogLidar(visibility_m=float(v))], cloud, seed=1, key="sweep", sequence_id="s")[1][0]
            counts.append(d.diagnostics["moved"] + d.diagnostics["added"])
        jump = np.max(np.abs(np.diff(counts)))
        print(f"  fog MOR {lo:g}–{hi:g} m in 1 % steps: weather returns {counts[0]} → {counts[-1]}, largest jump "
              f"{jump} = {100 * jump / 131072:.3f} % of the rays")


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == "--measure":
        measure(sys.argv[2], sys.argv[3])
        return 0
    report("synthetic OS1-128 128×2048 full grid (photons; D3.5 rates: fog 30 m, rain 20 mm/h, snow 2.5 mm/h)",
           "synthetic", synthetic_grid())
    scan = real_scan()
    if scan is None:
        draw_fraction_table(synthetic_grid(), "synthetic grid")
        exhaustive_table(synthetic_grid(), "synthetic grid")
        print("\n(real OS1-128 scan absent: ../shared/data/os1-128/scan0.bin)")
        return 0
    report("real OS1-128 scan0.bin, a point list (os1-128-reflectivity: calibrated 8-bit reflectivity, white 100, "
           "datasheet threshold 3.28 photons, overlap 0.5 → 5 m)", "real", scan)
    firing_grid_time(scan)
    rate_table(scan)
    draw_fraction_table(scan, "real scan")
    exhaustive_table(scan, "real scan")
    acceptance(scan)
    return 0


if __name__ == "__main__":
    sys.exit(main())
