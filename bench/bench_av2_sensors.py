"""Argoverse 2 sweeps through LiDAR chains: rows, weather returns per sensor and ms per sweep (round 23, av39).

Reads each sweep as ``rvnoise augment`` does (profile av2-vlp32c; the log's calibration beside it gives each sensor
its own rays) and times ``compound.apply_models`` of each chain on it, metrics on (as augment), the median of
``--repeat`` runs after one warm-up (compilation). Runs with any checkout on PYTHONPATH (the base's too: it has no
per-sensor split, its counts are the sweep's), so base and branch can be run alternately, pinned with taskset:

    PYTHONPATH=/tmp/base23 taskset -c 1 .venv/bin/python bench/bench_av2_sensors.py SWEEP.feather ...
    taskset -c 1 .venv/bin/python bench/bench_av2_sensors.py SWEEP.feather ...
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

from roadview_noise.compound import apply_models, cnf_chain
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.profiles.lidar import load_lidar_profile
from roadview_noise.registry import get_model

CHAINS = {"fog30": [("fog.lidar", {"visibility_m": 30.0})], "fog100": [("fog.lidar", {"visibility_m": 100.0})],
          "rain20": [("rain.lidar", {"rain_rate_mm_per_h": 20.0})], "snow": [("snow.lidar", {})],
          **{f"cnf{n}": [(m, {}) for m in cnf_chain(f"CNF{n}", "lidar")] for n in (20, 21, 22)}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweeps", nargs="+", help="Argoverse 2 sensors/lidar/<ns>.feather files")
    parser.add_argument("--chains", nargs="+", default=list(CHAINS), choices=list(CHAINS))
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    for path in args.sweeps:
        cloud = read_pointcloud(path, profile=load_lidar_profile("av2-vlp32c"))
        for name in args.chains:
            models = [get_model(m)(**p) for m, p in CHAINS[name]]
            out, records = apply_models(models, cloud, seed=1, key=path, sequence_id="s")
            seconds = []
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                apply_models(models, cloud, seed=1, key=path, sequence_id="s")
                seconds.append(time.perf_counter() - t0)
            d = records[-1].diagnostics
            per = d.get("sensors") or {"sweep": d}
            counts = "; ".join(f"{s}: {x.get('points_in')} in, {x.get('added')} added on {x.get('empty_rays')} "
                               f"empty rays, {x.get('moved')} moved, {x.get('removed')} removed"
                               for s, x in per.items())
            print(f"{path.rsplit('/', 1)[-1]} {name}: {len(cloud)} → {len(out)} rows, "
                  f"{1e3 * statistics.median(seconds):.1f} ms (median of {args.repeat}) | {counts}")


if __name__ == "__main__":
    main()
