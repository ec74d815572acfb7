"""Write the range images of an Ouster pcap in the layout of ``../shared/data/os1-128/scan0_grid.npz`` (issue 16).

    pip install ouster-sdk        # not a dependency of rvnoise; any venv
    python bench/ouster_pcap_grids.py CAPTURE.pcap METADATA.json OUT_DIR

One ``scan<N>_grid.npz`` per complete frame: ``range_mm`` uint32 (0 = no return), ``reflectivity``, ``near_ir`` and
``xyz_m`` float32 (sensor frame, metres), all 128×columns in measurement (staggered) order, as the sensor sends them.
Frame 0 of the Ouster SDK's test capture ``tests/pcaps/OS-1-128_v2.3.0_1024x10_lb_n3.pcap`` (with
``OS-1-128_v2.3.0_1024x10.json``) is byte-identical to the shared scan0; frames 1 and 2 are the other scans that
``bench/fit_ray_drop.py --other-grid`` tests the ray-drop fit on. The output stays out of the repository.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pcap", type=Path)
    ap.add_argument("metadata", type=Path)
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    from ouster.sdk import core, open_source

    source = open_source(str(args.pcap), meta=[str(args.metadata)])
    info = source.sensor_info[0]
    xyz = core.XYZLut(info)
    args.out.mkdir(parents=True, exist_ok=True)
    for n, frames in enumerate(source):
        scan = frames[0]
        if not scan.complete():
            print(f"frame {n}: incomplete, skipped")
            continue
        path = args.out / f"scan{n}_grid.npz"
        np.savez_compressed(path, range_mm=scan.field(core.ChanField.RANGE).astype(np.uint32),
                            reflectivity=scan.field(core.ChanField.REFLECTIVITY),
                            near_ir=scan.field(core.ChanField.NEAR_IR), xyz_m=xyz(scan).astype(np.float32))
        print(f"frame {n}: {int(np.count_nonzero(scan.field(core.ChanField.RANGE)))} returns → {path}")


if __name__ == "__main__":
    main()
