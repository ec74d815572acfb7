"""Points that snow.lidar changes at trace rates (issue 14: continuous at zero strength; physics/dsd.py
``TRACE_SNOW_SLOPE_PER_MM``): per scan and rate, the input points not kept unchanged plus the points added (as
tests/models/test_lidar_real_scan.py counts them), seed 3 (``--seeds`` for more).

Scans: the real OS1-128 scan ../shared/data/os1-128/scan0.bin as reflectivity (built-in profile and the unit's JSON
metadata) and as photons (``os1-128``), mmdet3d's KITTI 000008 crop (/work/realdata, never committed), each when
present; the synthetic HDL-64E scan of the tests; sample_data's LiDAR trees (their ``lidar.yaml``). Counts, not
times: deterministic, so a loaded machine gives the same figures.
Run: ``.venv/bin/python bench/trace_snow_points.py``; main's figures: ``git archive main | tar -x -C /tmp/base`` and
``PYTHONPATH=/tmp/base .venv/bin/python bench/trace_snow_points.py``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT))          # the tests' scans; appended, so PYTHONPATH's roadview_noise (e.g. main's) wins

from roadview_noise.compound import apply_models  # noqa: E402
from roadview_noise.io.pointcloud import read_pointcloud  # noqa: E402
from roadview_noise.models.lidar.snow import SnowLidar  # noqa: E402
from roadview_noise.profiles.lidar import kitti_hdl64, load_lidar_profile, os1_128  # noqa: E402
from tests.models.test_lidar_real_scan import changed, scan  # noqa: E402
from tests.physics.test_firing_grid_laser_order import kitti_scan  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
KITTI_DEMO = Path("/work/realdata/mmdet3d/demo/data/kitti/000008.bin")
RATES = (1e-5, 1e-4, 1e-3, 3e-3, 1e-2, 0.1, 0.2, 1.0)


def scans() -> dict:
    out = {}
    if (SHARED / "os1-128" / "scan0.bin").is_file():
        out["OS1-128 real, reflectivity"] = scan(SHARED)
        out["OS1-128 real, its JSON"] = scan(SHARED, load_lidar_profile(str(SHARED / "os1-128" /
                                                                            "beam_intrinsics.json")))
        out["OS1-128 real, photons"] = scan(SHARED, os1_128())
    if KITTI_DEMO.is_file():
        out["KITTI 000008"] = read_pointcloud(KITTI_DEMO, profile=kitti_hdl64())
    out["synthetic HDL-64E"] = kitti_scan(0)[0]
    for f in sorted((ROOT / "sample_data" / "lidar").glob("*/seq0/000000.*")):
        out[f"sample_data {f.parent.parent.name}"] = read_pointcloud(
            f, profile=load_lidar_profile(str(f.parent / "lidar.yaml")))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="3", help="comma-separated seeds (counts summed)")
    seeds = [int(s) for s in parser.parse_args().seeds.split(",")]
    warnings.simplefilter("ignore")
    print("scan, points | " + " | ".join(f"{r:g} mm/h" for r in RATES))
    for name, cloud in scans().items():
        counts = [sum(changed(cloud, apply_models([SnowLidar(snowfall_rate_mm_per_h=r)], cloud, seed=s, key="scan0",
                                                  sequence_id="s", metrics=False)[0]) for s in seeds)
                  for r in RATES]
        at = counts[RATES.index(1e-3)] / (len(seeds) * len(cloud))
        print(f"{name}, {len(cloud)} | " + " | ".join(map(str, counts)) + f"   (0.001 mm/h: {100 * at:.3f} %)",
              flush=True)


if __name__ == "__main__":
    main()
