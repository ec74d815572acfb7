"""Per-frame time of every 4D radar model on a synthetic 10 000-point frame (target ≤ 5 ms per model), both clutter
detectors of the precipitation models, and the clutter count against the margin C − t between radar constant and
threshold.

The frame emulates detections of a 77 GHz imaging radar (SNR = C + RCS − 40 log10 r ≥ 12 dB with C = 88 dB, the
generic 120° × 30° profile) seen from a car at 10 m/s. Single-threaded BLAS, as in the runner's workers.
Run: ``.venv/bin/python bench/bench_radar.py``.
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from roadview_noise.compound import apply_models  # noqa: E402
from roadview_noise.profiles.radar import load_radar_profile  # noqa: E402
from roadview_noise.registry import get_model  # noqa: E402
from roadview_noise.types import Conditions, PointCloud  # noqa: E402

N_POINTS = 10_000
REPEATS = 30
THRESHOLD_DB = 12.0
EGO_M_PER_S = (10.0, 0.0, 0.0)
# (model, params, new ego velocity every frame: the per-cell Doppler tables are recomputed, cache misses)
CASES = [
    ("rain.radar", {"detector": "cfar"}, False), ("rain.radar", {"detector": "fixed"}, False),
    ("rain.radar", {"clutter": False}, False),
    ("rain.radar", {"detector": "cfar"}, True), ("rain.radar", {"detector": "fixed"}, True),
    ("snow.radar", {"detector": "cfar"}, False), ("snow.radar", {"detector": "fixed"}, False),
    ("fog.radar", {}, False),
    ("occlusion.radar", {}, False), ("occlusion.radar", {"mode": "attenuate"}, False),
    ("alignment.radar", {"yaw_sd_deg": 1.0, "pitch_sd_deg": 0.5, "roll_sd_deg": 0.5}, False),
    ("power.radar", {"power_sd_db": 1.0}, False),
]
MARGINS_DB = (60.0, 68.0, 76.0, 83.0, 90.0)


def frame(n: int = N_POINTS, radar_constant_db: float = 88.0, threshold_db: float = THRESHOLD_DB) -> PointCloud:
    rng = np.random.default_rng(0)
    m = 4 * n
    r = 2 + 198 * rng.random(m) ** 1.5
    az, el = np.deg2rad(rng.uniform(-58, 58, m)), np.deg2rad(rng.uniform(-14, 14, m))
    rcs = rng.normal(5, 10, m)
    snr = radar_constant_db + rcs - 40 * np.log10(r)
    ok = np.flatnonzero(snr >= threshold_db)[:n]
    r, az, el = r[ok], az[ok], el[ok]
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    fields = {"rcs_dbsm": rcs[ok], "v_r_m_per_s": rng.normal(0, 3, n), "v_r_comp_m_per_s": rng.normal(0, 1, n),
              "snr_db": snr[ok], "power_db": snr[ok] - 90.0, "time_s": np.zeros(n)}
    return PointCloud(pos, {k: v.astype(np.float32) for k, v in fields.items()}, "radar", load_radar_profile(None),
                      conditions=Conditions(ego_velocity_m_per_s=EGO_M_PER_S))


def timings() -> None:
    cloud = frame()
    print(f"{len(cloud)} points per frame; median (and minimum) of {REPEATS} runs after a first run that fills "
          "the caches")
    for model_id, params, varying in CASES:
        model = get_model(model_id)(**params)
        out, rec = apply_models([model], cloud, seed=1, key="warm-up", sequence_id="s")
        times, added = [], []
        for i in range(REPEATS):
            data = cloud
            if varying:
                data = dataclasses.replace(cloud, conditions=Conditions(ego_velocity_m_per_s=(10.0 + 0.1 * i, 0, 0)))
            t0 = time.perf_counter()
            out, rec = apply_models([model], data, seed=1, key=f"frame-{i}", sequence_id="s")
            times.append(time.perf_counter() - t0)
            added.append(rec[0].diagnostics.get("clutter_points", 0))
        label = model_id + (" " + ",".join(f"{k}={v}" for k, v in params.items()) if params else "") + \
            (" (ego speed varying per frame)" if varying else "")
        clutter = f"   clutter points: mean {np.mean(added):8.1f}" if "clutter_points" in rec[0].diagnostics else ""
        print(f"{label:<66s} {1e3 * statistics.median(times):7.2f} ms (min {1e3 * min(times):5.2f})   "
              f"out {len(out):6d} points{clutter}")


def clutter_against_margin() -> None:
    print(f"\nrain 20 mm/h clutter points per frame (1–20 m, ego {EGO_M_PER_S[0]:g} m/s) against C − t "
          f"(t = {THRESHOLD_DB:g} dB): expected, and the mean of 20 frames; real points lost to the CFAR")
    print(f"{'C − t (dB)':>10s} {'fixed expected':>15s} {'fixed drawn':>12s} {'cfar expected':>14s} "
          f"{'cfar drawn':>11s} {'cfar lost':>10s} {'max rise (dB)':>14s}")
    for margin in MARGINS_DB:
        cloud = frame(radar_constant_db=THRESHOLD_DB + margin)
        row = []
        for detector in ("fixed", "cfar"):
            recs = [apply_models([get_model("rain.radar")(detector=detector)], cloud, seed=s, key="f",
                                 sequence_id="s")[1][0].diagnostics for s in range(20)]
            row += [recs[0]["clutter_expected_points"], np.mean([d["clutter_points"] for d in recs])]
        print(f"{margin:10.0f} {row[0]:15.1f} {row[1]:12.1f} {row[2]:14.2f} {row[3]:11.2f} "
              f"{recs[0]['cfar_points_lost']:10d} {recs[0]['cfar_max_threshold_rise_db']:14.1f}")


if __name__ == "__main__":
    timings()
    clutter_against_margin()
