"""Cost of point provenance (issue 13) for the LiDAR weather models on the real OS1-128 scan.

Times ``apply_models([model], scan)`` (model + the chain's provenance composition) for fog.lidar, rain.lidar and
snow.lidar at the D3.5 rates on ../shared/data/os1-128/scan0.bin (107 647 points + 23 425 empty rays; profile
os1-128-reflectivity), each run in a fresh process (one core, fresh heap), and the annotation gather that carries a
uint32 label field and a SemanticKITTI-style label sidecar to the output (:func:`annotations.carry_values`).

Before/after: ``--baseline DIR`` runs the same measurement on another checkout (e.g. ``git archive main | tar -x -C
/tmp/base``) interleaved with this one, ROUNDS rounds of REPEATS frames each, and prints the median of the round
medians of both and the difference. The machine is shared and noisy: compare medians of several rounds, and re-run
on an idle machine. Run: ``taskset -c 0 .venv/bin/python bench/bench_provenance.py --baseline /tmp/base
[--rounds 5]``.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

HERE = Path(__file__).resolve()
SCAN = HERE.parents[2] / "shared" / "data" / "os1-128" / "scan0.bin"
MODELS = ("fog.lidar", "rain.lidar", "snow.lidar")
REPEATS = 15
ROUNDS = 5


def measure(model_id: str) -> dict:
    """In a child process: median ms of ``apply_models`` over REPEATS frames after a warm-up (and, where the code
    has provenance, the label gather)."""
    import numpy as np

    from roadview_noise.allocator import keep_freed_memory
    from roadview_noise.compound import apply_models
    from roadview_noise.profiles.lidar import os1_128_reflectivity
    from roadview_noise.registry import get_model
    from roadview_noise.types import PointCloud

    keep_freed_memory()
    a = np.fromfile(SCAN, dtype=np.float32).reshape(-1, 4)
    cloud = PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3].copy()}, "lidar", os1_128_reflectivity())
    model = get_model(model_id)()
    out, _ = apply_models([model], cloud, seed=1, key="warm", sequence_id="s")
    times = []
    for i in range(REPEATS):
        t0 = time.perf_counter()
        out, _ = apply_models([model], cloud, seed=1, key=f"bench{i}", sequence_id="s")
        times.append(time.perf_counter() - t0)
    result = {"ms": 1e3 * statistics.median(times), "min_ms": 1e3 * min(times)}
    try:
        from roadview_noise.annotations import AnnotationsSpec, carry_values, new_classes, weather_classes
    except ImportError:                                  # the baseline has no annotations
        return result
    labels = np.random.default_rng(0).integers(0, 260, len(cloud)).astype(np.uint32)
    gather = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        classes = new_classes(out, weather_classes(AnnotationsSpec()), [model_id])
        carry_values(labels, out, classes)
        gather.append(time.perf_counter() - t0)
    result["gather_ms"] = 1e3 * statistics.median(gather)
    return result


def child(root: Path, model_id: str) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(root)}
    res = subprocess.run([sys.executable, str(HERE), "--measure", model_id], capture_output=True, text=True,
                         check=True, env=env, cwd=str(root))
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> int:
    if len(sys.argv) == 3 and sys.argv[1] == "--measure":
        print(json.dumps(measure(sys.argv[2])))
        return 0
    if not SCAN.is_file():
        print(f"(real OS1-128 scan absent: {SCAN})")
        return 0
    baseline = Path(sys.argv[sys.argv.index("--baseline") + 1]).resolve() if "--baseline" in sys.argv else None
    rounds = int(sys.argv[sys.argv.index("--rounds") + 1]) if "--rounds" in sys.argv else ROUNDS
    here = HERE.parents[1]
    runs: dict[tuple[str, str], list[dict]] = {}
    for r in range(rounds):
        for mid in MODELS:
            for name, root in (("after", here), ("before", baseline)):
                if root is not None:
                    runs.setdefault((mid, name), []).append(child(root, mid))
        print(f"round {r + 1}/{rounds} done", file=sys.stderr)
    print(f"real OS1-128 scan, apply_models, ms per frame: median over {rounds} rounds of each round's median "
          f"(and min) of {REPEATS} frames; round medians in brackets")
    for mid in MODELS:
        for stat in ("ms", "min_ms"):
            after = [x[stat] for x in runs[(mid, "after")]]
            line = f"{mid:11s} {stat:6s} after {statistics.median(after):6.2f} [{' '.join(f'{x:.2f}' for x in after)}]"
            if baseline is not None:
                before = [x[stat] for x in runs[(mid, "before")]]
                b, a = statistics.median(before), statistics.median(after)
                line += (f"   before {b:6.2f} [{' '.join(f'{x:.2f}' for x in before)}]   "
                         f"difference {100 * (a - b) / b:+5.1f} %")
            print(line)
        gather = [x["gather_ms"] for x in runs[(mid, "after")]]
        print(f"{mid:11s} gather of a uint32 label array through the output's provenance: "
              f"{statistics.median(gather):.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
