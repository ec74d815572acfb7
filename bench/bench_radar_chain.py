"""Per-frame time of radar chains in one process (issue 19): ``apply_models`` (metrics on, as in a run) on the sample
radar files, optionally against a second checkout of the code (``--base DIR``: e.g. ``git archive main | tar -x -C
DIR``), the versions alternating run by run, each in a fresh process with its code on ``PYTHONPATH`` and its folder
as the working directory. Printed per chain: ms per frame, the second-best of ``--batches`` batches of ``--frames``
frames, per run, and the median over the rounds.

    .venv/bin/python bench/bench_radar_chain.py [--rounds 3] [--base /tmp/main-code]
                                                [--chains rain.radar,snow.radar,rain.radar+occlusion.radar,fog.radar]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

ONE_RUN = r"""
import json, sys, time
from pathlib import Path
from roadview_noise.compound import apply_models
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.profiles.radar import load_radar_profile
from roadview_noise.registry import get_model
src = Path({src!r})
profile = load_radar_profile(src / "radar.yaml")
clouds = [read_pointcloud(p, sensor="radar", profile=profile) for p in sorted(src.glob("*.pcd"))]
out = {{}}
for chain in {chains!r}:
    models = [get_model(m)() for m in chain.split("+")]
    def frames(n):
        for i in range(n):
            apply_models(models, clouds[i % len(clouds)], seed=1, key=f"f{{i}}", sequence_id="s")
    frames(20)
    times = []
    for _ in range({batches}):
        t0 = time.perf_counter()
        frames({frames})
        times.append((time.perf_counter() - t0) / {frames} * 1e3)
    out[chain] = sorted(times)[1]
print(json.dumps(out))
"""


def one_run(code: Path, chains: list[str], frames: int, batches: int) -> dict[str, float]:
    script = ONE_RUN.format(src=str(ROOT / "sample_data" / "radar" / "seq0"), chains=chains, frames=frames,
                            batches=batches)
    return run_script(code, script)


def run_script(code: Path, script: str) -> dict:
    """The JSON last printed by ``script`` run in a fresh process with ``code`` on PYTHONPATH and as its folder."""
    env = {**os.environ, "PYTHONPATH": str(code)}
    done = subprocess.run([sys.executable, "-c", script], env=env, cwd=code, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(done.stderr)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--batches", type=int, default=5)
    ap.add_argument("--chains", default="rain.radar,snow.radar,rain.radar+occlusion.radar,fog.radar")
    ap.add_argument("--base", type=Path, help="a second checkout's root (its roadview_noise/ is run as 'base')")
    args = ap.parse_args()
    chains = args.chains.split(",")
    versions = {"this": ROOT} | ({"base": args.base.resolve()} if args.base else {})
    got: dict[str, dict[str, list[float]]] = {v: {c: [] for c in chains} for v in versions}
    for _ in range(args.rounds):
        for name, code in versions.items():
            for chain, ms in one_run(code, chains, args.frames, args.batches).items():
                got[name][chain].append(ms)
    print(f"ms per frame (apply_models, metrics on), {args.rounds} rounds: median (runs)")
    print("| chain | " + " | ".join(versions) + " |")
    print("|---|" + "---|" * len(versions))
    for chain in chains:
        cells = [f"{statistics.median(got[v][chain]):.3f} ({', '.join(f'{x:.3f}' for x in got[v][chain])})"
                 for v in versions]
        print(f"| {chain} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
