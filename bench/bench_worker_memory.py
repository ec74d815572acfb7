"""Peak memory of one batch worker per shipped recipe, on the sample drive at the sensors' full resolutions.

Renders one full-resolution frame (camera 1936×1464 + raw DNG, OS1-128 128×2048, VLS-128, radar) into a temporary
folder, then runs each recipe in a fresh process that does what a worker does (imports, read → chain → write, one
file after another) and prints the process's peak resident set size (``VmHWM`` of ``/proc/self/status``; Linux,
``ru_maxrss`` would include the parent's peak, kept across ``exec``) next to its size after the imports. ``resources.WORKER_PEAK_BYTES`` (the memory rule of ``--workers``) is set from the largest figure.

    .venv/bin/python bench/bench_worker_memory.py
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, tempfile
from pathlib import Path
from roadview_noise.executor import worker_setup
from roadview_noise.recipe import load_recipe
from roadview_noise.registry import load_all
from roadview_noise.runner import RunContext, iter_tasks, process
import cv2, open3d  # noqa: F401  (what a worker has imported)
def hwm_kb():
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))
load_all()
worker_setup()
base = hwm_kb()
recipe = load_recipe(sys.argv[1])
data = Path(sys.argv[2])
with tempfile.TemporaryDirectory() as out:
    ctx = RunContext(data, Path(out), recipe)
    entries = [process(t, ctx) for t in iter_tasks(data, recipe)]
peak = hwm_kb()
print(json.dumps({"base_kb": base, "peak_kb": peak, "files": len(entries),
                  "failed": sum(e["status"] != "ok" for e in entries)}))
"""


def main() -> None:
    from roadview_noise.resources import WORKER_PEAK_BYTES
    from roadview_noise.sampledata.generate import generate

    with tempfile.TemporaryDirectory() as data:
        generate(Path(data), frames=1, seed=0)
        print("input: 1 frame at full resolution (camera 1936×1464, raw DNG, OS1-128 2048 columns, VLS-128, radar)")
        print(f"{'recipe':<28} {'files':>5} {'after imports MB':>17} {'peak MB':>8}")
        worst = 0.0
        for path in sorted((ROOT / "recipes").glob("*.yaml")):
            if "topics" in yaml.safe_load(path.read_text()):
                continue                                    # a ROS-bag recipe (bench/bench_rosbag.py)
            out = subprocess.run([sys.executable, "-c", CHILD, str(path), data], capture_output=True, text=True)
            if out.returncode:
                print(f"{path.name:<28} failed: {out.stderr.strip().splitlines()[-1]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            worst = max(worst, r["peak_kb"] / 1024)
            print(f"{path.name:<28} {r['files']:>5} {r['base_kb'] / 1024:>17.0f} {r['peak_kb'] / 1024:>8.0f}"
                  + (f"  ({r['failed']} failed)" if r["failed"] else ""))
        print(f"largest peak {worst:.0f} MB; resources.WORKER_PEAK_BYTES = {WORKER_PEAK_BYTES / 2**20:.0f} MB")


if __name__ == "__main__":
    main()
