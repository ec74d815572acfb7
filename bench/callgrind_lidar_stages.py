"""Instruction counts (callgrind) of a LiDAR weather step's stages on the real OS1-128 scan, repeatable on a loaded VM.

The stages of ``bench_lidar_weather.py`` — cloud → rays (:func:`lidar_rays.cloud_rays`), the particle kernel
(:func:`lidar_weather.particle_returns`) and rays → cloud (:func:`lidar_output.assemble`) — of rain or snow at the D3.5
rates on ``../shared/data/os1-128/scan0.bin``, one frame after an uninstrumented warm-up frame, each stage's
instructions (Ir) dumped apart; ``--split`` also dumps on entering and leaving the Python-level functions of the stages
(:data:`SPLIT`: the segment that ends at ``leave f`` is f's own count, its wrapped callees' apart). Each source tree
(``--tree``, default this checkout; give the base's export to compare) runs in a fresh interpreter under valgrind,
numba compiled for an AVX2 target (valgrind emulates no AVX-512) and cached first by a run without valgrind in a cache
folder of its own; valgrind starts uninstrumented (``--instr-atstart=no``) and a 4-line C library built with ``gcc``
against ``valgrind/callgrind.h`` switches it on around the counted frame. ≈ 2 min (rain) to 4 min (snow) per tree.

    .venv/bin/python bench/callgrind_lidar_stages.py rain [--split] [--tree /tmp/base21] [--tree .]
"""

from __future__ import annotations

import argparse
import ctypes
import functools
import importlib
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCAN = ROOT.parent / "shared" / "data" / "os1-128" / "scan0.bin"
VG_LIB = """#include <valgrind/callgrind.h>
void vg_start(void) { CALLGRIND_START_INSTRUMENTATION; }
void vg_stop(void) { CALLGRIND_STOP_INSTRUMENTATION; }
void vg_dump(const char *label) { CALLGRIND_DUMP_STATS_AT(label); }
"""
TARGET = {"NUMBA_CPU_NAME": "haswell", "NUMBA_CPU_FEATURES": "", "PYTHONHASHSEED": "0", "OMP_NUM_THREADS": "1"}
#: the Python-level functions of the stages that --split dumps around (module of roadview_noise.physics, attribute)
SPLIT = ["lidar_rays.chain_intensity_scale", "lidar_rays.list_points", "firing_grid._rings_and_azimuths",
         "lidar_rays.firing_grid", "firing_grid.firing_columns", "firing_grid.beam_gaps", "firing_grid.measured_step_rad",
         "firing_grid._beam_phase", "firing_grid.empty_rays", "firing_grid._cells", "firing_grid._empty_cells",
         "firing_grid._nearest_filled", "lidar_rays._ray_signals", "lidar_output.stored_signal", "lidar_output._place",
         "lidar_output._write_listed", "lidar_output.empty_ray_counts"]
STAGES = ("rays", "kernel", "output")


def frame(model_id: str, split: bool) -> None:
    """In the counted interpreter: a warm-up frame, then one frame with its stages' counts dumped."""
    import numpy as np

    from roadview_noise.models.lidar.rain import RainLidar
    from roadview_noise.models.lidar.snow import SnowLidar
    from roadview_noise.physics.lidar_output import assemble
    from roadview_noise.physics.lidar_rays import cloud_rays
    from roadview_noise.physics.lidar_weather import particle_returns
    from roadview_noise.profiles.lidar import os1_128_reflectivity
    from roadview_noise.types import PointCloud

    lib = ctypes.CDLL(os.environ["RVNOISE_VG_LIB"]) if os.environ.get("RVNOISE_VG_LIB") else None
    counting = [False]

    def dump(label: str) -> None:
        if lib and counting[0]:
            lib.vg_dump(label.encode())

    if split:
        for path in SPLIT:
            module, name = path.split(".")
            owner = importlib.import_module(f"roadview_noise.physics.{module}")
            if hasattr(owner, name):
                setattr(owner, name, _dumping(getattr(owner, name), path, dump))
    model = {"rain": RainLidar(), "snow": SnowLidar()}[model_id]
    a = np.fromfile(SCAN, dtype=np.float32).reshape(-1, 4)
    cloud = PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3].copy()}, "lidar", os1_128_reflectivity())
    for i in range(2):
        if i == 1 and lib:
            counting[0] = True
            lib.vg_start()
        dump("start")
        rays = cloud_rays(cloud, model.id, model.empty_rays)
        dump("rays")
        returns, _ = particle_returns(np.random.default_rng(i), rays, model.medium(), model.return_mode,
                                      model.draw_fraction_of_threshold)
        dump("kernel")
        assemble(cloud, rays, returns)
        dump("output")
    if lib:
        lib.vg_stop()


def _dumping(f, path: str, dump):
    @functools.wraps(f)
    def wrapped(*args, **kwargs):
        dump(f"enter {path}")
        try:
            return f(*args, **kwargs)
        finally:
            dump(f"leave {path}")
    return wrapped


def count(tree: Path, model_id: str, split: bool, work: Path, lib: Path) -> list[tuple[str, int]]:
    """(label, Ir) of every dump of one counted run of ``tree``'s package."""
    env = {**os.environ, **TARGET, "PYTHONPATH": str(tree),
           "NUMBA_CACHE_DIR": str(work / f"numba-{abs(hash(str(tree.resolve())))}")}
    args = [sys.executable, __file__, "--frame", model_id] + (["--split"] if split else [])
    subprocess.run(args, env=env, check=True)                         # compiles and caches the kernels first
    out = work / f"out-{abs(hash(str(tree.resolve())))}"
    out.mkdir()
    subprocess.run(["valgrind", "--tool=callgrind", "--instr-atstart=no", "--dump-instr=no",
                    f"--callgrind-out-file={out}/callgrind.out.%p"] + args, env={**env, "RVNOISE_VG_LIB": str(lib)},
                   check=True, stderr=subprocess.DEVNULL)
    rows = []
    for f in sorted(out.glob("callgrind.out.*"), key=lambda p: [int(x) for x in re.findall(r"\d+", p.name)]):
        text = f.read_text(errors="replace")
        label = re.search(r"^desc: Trigger: Client Request: (.*)$", text, re.M)
        total = re.search(r"^(?:totals|summary): (\d+)", text, re.M)
        if label and total:
            rows.append((label.group(1).strip(), int(total.group(1))))
    return rows


def stage_totals(rows: list[tuple[str, int]]) -> dict:
    """Ir per stage: the dumps from ``start`` to ``rays`` are cloud → rays, and so on."""
    totals, stage = dict.fromkeys(STAGES, 0), None
    for label, ir in rows:
        if label == "start":
            stage = STAGES[0]
        elif stage is not None:
            totals[stage] += ir
            if label in STAGES:
                at = STAGES.index(label) + 1
                stage = STAGES[at] if at < len(STAGES) else None
    return totals


def main() -> int:
    if sys.argv[1:2] == ["--frame"]:
        frame(sys.argv[2], "--split" in sys.argv)
        return 0
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", choices=("rain", "snow"))
    parser.add_argument("--split", action="store_true")
    parser.add_argument("--tree", action="append", type=Path)
    a = parser.parse_args()
    if not SCAN.is_file():
        print(f"the real scan {SCAN} is absent")
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (work / "vg.c").write_text(VG_LIB)
        subprocess.run(["gcc", "-shared", "-fPIC", "-O2", "-o", str(work / "libvg.so"), str(work / "vg.c")], check=True)
        for tree in a.tree or [ROOT]:
            rows = count(tree, a.model, a.split, work, work / "libvg.so")
            print(f"{tree}: {a.model}, one frame of the real scan (M instructions)")
            if a.split:
                for label, ir in rows:
                    print(f"  {ir / 1e6:8.3f}  {label}")
            print("  " + ", ".join(f"{k} {v / 1e6:.3f}" for k, v in stage_totals(rows).items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
