"""Argoverse 2 sweeps through LiDAR chains: rows, weather returns per sensor and ms per sweep (round 23, av39).

Reads each sweep as ``rvnoise augment`` does (profile av2-vlp32c; the log's calibration beside it gives each sensor
its own rays) and times ``compound.apply_models`` of each chain on it, metrics on (as augment), the median of
``--repeat`` runs after one warm-up (compilation). Runs with any checkout on PYTHONPATH (the base's too: it has no
per-sensor split, its counts are the sweep's), so base and branch can be run alternately, pinned with taskset:

    PYTHONPATH=/tmp/base23 taskset -c 1 .venv/bin/python bench/bench_av2_sensors.py SWEEP.feather ...
    taskset -c 1 .venv/bin/python bench/bench_av2_sensors.py SWEEP.feather ...

``--count``: instead, the instructions (callgrind Ir, repeatable on a loaded VM) of one ``apply_models`` per chain and
sweep after an uncounted warm-up, for each ``--tree`` (default this checkout), as ``callgrind_lidar_stages.py``
counts (its valgrind switch and numba target):

    .venv/bin/python bench/bench_av2_sensors.py SWEEP.feather --chains fog30 --count --tree /tmp/base23 --tree .
"""

from __future__ import annotations

import argparse
import ctypes
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

from roadview_noise.compound import apply_models, cnf_chain
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.profiles.lidar import load_lidar_profile
from roadview_noise.registry import get_model

CHAINS = {"fog30": [("fog.lidar", {"visibility_m": 30.0})], "fog100": [("fog.lidar", {"visibility_m": 100.0})],
          "rain20": [("rain.lidar", {"rain_rate_mm_per_h": 20.0})], "snow": [("snow.lidar", {})],
          **{f"cnf{n}": [(m, {}) for m in cnf_chain(f"CNF{n}", "lidar")] for n in (20, 21, 22)}}


def counted(path: str, chain: str) -> None:
    """In the counted interpreter: a warm-up run of ``chain`` on the sweep, then one between valgrind's switches."""
    warnings.simplefilter("ignore")
    lib = ctypes.CDLL(os.environ["RVNOISE_VG_LIB"]) if os.environ.get("RVNOISE_VG_LIB") else None
    cloud = read_pointcloud(path, profile=load_lidar_profile("av2-vlp32c"))
    models = [get_model(m)(**p) for m, p in CHAINS[chain]]
    apply_models(models, cloud, seed=1, key=path, sequence_id="s")
    if lib:
        lib.vg_start()
        lib.vg_dump(b"start")
    apply_models(models, cloud, seed=1, key=path, sequence_id="s")
    if lib:
        lib.vg_dump(b"counted")
        lib.vg_stop()


def count(tree: Path, path: str, chain: str, work: Path) -> int:
    """Ir of one counted run of ``chain`` on ``path`` with ``tree``'s package (numba cached first, uncounted)."""
    from callgrind_lidar_stages import TARGET

    key = abs(hash((str(tree.resolve()), path, chain)))
    cache = work / f"numba-{abs(hash(str(tree.resolve())))}"          # compiled once per tree
    env = {**os.environ, **TARGET, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(cache)}
    args = [sys.executable, __file__, "--frame", chain, path]
    subprocess.run(args, env=env, check=True)
    out = work / f"out-{key}"
    out.mkdir()
    subprocess.run(["valgrind", "--tool=callgrind", "--instr-atstart=no", "--dump-instr=no",
                    f"--callgrind-out-file={out}/callgrind.out.%p"] + args,
                   env={**env, "RVNOISE_VG_LIB": str(work / "libvg.so")}, check=True, stderr=subprocess.DEVNULL)
    for f in out.glob("callgrind.out.*"):
        text = f.read_text(errors="replace")
        if re.search(r"^desc: Trigger: Client Request: counted$", text, re.M):
            return int(re.search(r"^(?:totals|summary): (\d+)", text, re.M).group(1))
    raise RuntimeError(f"no counted dump in {out}")


def main() -> None:
    if sys.argv[1:2] == ["--frame"]:
        counted(sys.argv[3], sys.argv[2])
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweeps", nargs="+", help="Argoverse 2 sensors/lidar/<ns>.feather files")
    parser.add_argument("--chains", nargs="+", default=list(CHAINS), choices=list(CHAINS))
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--count", action="store_true", help="callgrind instructions instead of times")
    parser.add_argument("--tree", action="append", type=Path, help="source tree to count (repeatable)")
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    if args.count:
        from callgrind_lidar_stages import VG_LIB

        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            (work / "vg.c").write_text(VG_LIB)
            subprocess.run(["gcc", "-shared", "-fPIC", "-O2", "-o", str(work / "libvg.so"), str(work / "vg.c")],
                           check=True)
            for path in args.sweeps:
                for chain in args.chains:
                    for tree in args.tree or [Path(__file__).resolve().parents[1]]:
                        print(f"{tree} {Path(path).name} {chain}: {count(tree, path, chain, work) / 1e6:.1f} M Ir")
        return
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
