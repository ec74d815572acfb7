"""Bag overhead: augmenting a ROS bag against augmenting the same messages as files (issue 20 target: ≤ 10 %).

Renders a drive with ``rvnoise sample-data`` (default: the sensors' full resolutions, camera 1936×1464, OS1-128
128×2048; ``--sample`` for the committed preset), writes it as a ROS 1 bag and a ROS 2 MCAP bag (every frame
``--repeat`` times with new stamps; topics of ``roadview_noise.sampledata.bag``), exports each bag to an input tree
with ``rvnoise export``, and times ``--runs`` runs of each, alternating, with 1 and 2 workers (``--workers``; every
run starts its own workers as a command does, after one warm-up run of each that starts the fork server):

- files: ``runner.run`` per mapped topic (CNF16 on both cameras, CNF20 LiDAR, CNF25 radar) over the exported tree;
- bag:   ``run_bag`` with the same chains and seed over the bag (also copying the depth and diagnostics topics).

Prints per runner the median and the minimum wall time, the in-worker time (sum of the manifests' seconds), the
CPU time of the whole run (this process and its workers), which a busy shared machine disturbs far less than wall
time, and of the main process alone (for a bag: reading, hand-off to the workers, writing). And the overhead
bag / files − 1. The files side is one ``run`` per topic (its own workers each), as a user would run it.
Re-run on an idle machine for the record.

    .venv/bin/python bench/bench_rosbag.py [--sample] [--frames 3] [--repeat 2] [--runs 5] [--workers 1 2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from roadview_noise.bag_export import export_bag
from roadview_noise.bag_recipe import parse_bag_recipe
from roadview_noise.bag_runner import manifest_path, run_bag
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from roadview_noise.sampledata.bag import RECIPE_TOPICS, write_sample_bag
from roadview_noise.sampledata.generate import generate

CHAINS = {"camera": "CNF16", "lidar": "CNF20", "radar": "CNF25"}
GLOBS = {"/camera/image/compressed": ("camera", "*.jpg"), "/camera/image_raw": ("raw", "*.raw"),
         "/os_cloud_node/points": ("lidar", "*.pcd"), "/radar/points": ("radar", "*.pcd")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sample", action="store_true", help="committed sample-data preset instead of full resolution")
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="rvnoise-bench-bag-") as tmp:
        tmp = Path(tmp)
        size = dict(camera_size=(484, 366), lidar_columns=256) if args.sample else {}
        t0 = time.perf_counter()
        generate(tmp / "drive", frames=args.frames, seed=0, **size)
        print(f"drive: {args.frames} frames × {args.repeat} ({'sample preset' if args.sample else 'full resolution'}),"
              f" rendered in {time.perf_counter() - t0:.1f} s")
        topics = dict(RECIPE_TOPICS)
        if not args.sample:
            topics["/os_cloud_node/points"] = {"sensor": "lidar", "lidar_profile": "os1-128"}
        recipe = parse_bag_recipe({"seed": 1, "topics": topics, "chains": CHAINS})
        for kind, name in (("ROS 1", "drive.bag"), ("ROS 2 MCAP", "drive-ros2")):
            bench(tmp, kind, tmp / name, recipe, args)


def bench(tmp: Path, kind: str, bag: Path, recipe, args) -> None:
    write_sample_bag(tmp / "drive", bag, ros2=bag.suffix != ".bag", repeat=args.repeat)
    tree = tmp / f"{bag.name}-tree"
    export_bag(bag, tree, recipe=recipe)
    files_recipes = {t: parse_recipe({**recipe.topics[t].recipe.resolved_dict(),
                                      "inputs": {m: f"{t.strip('/')}/{g}"}}) for t, (m, g) in GLOBS.items()}
    out = tmp / "out"

    def files_run(tag: str, workers: int) -> tuple[float, float, float, float, int]:
        inner, n = 0.0, 0

        def each_topic():
            nonlocal inner, n
            for topic, r in files_recipes.items():
                dest = out / f"{tag}-{topic.strip('/').replace('/', '_')}"
                s = run(r, tree, dest, workers=workers, progress=False, overwrite=True, echo=lambda m: None)
                inner += sum(e["seconds"] for e in read_manifest(dest / "manifest.jsonl") if "seconds" in e)
                n += s.done

        wall, cpu, total = timed(each_topic)
        return wall, cpu, total, inner, n

    def bag_run(tag: str, workers: int) -> tuple[float, float, float, float, int]:
        dest = out / f"{tag}{bag.suffix or '-ros2'}"
        done = []
        wall, cpu, total = timed(lambda: done.append(run_bag(recipe, bag, dest, workers=workers, progress=False,
                                                             overwrite=True, echo=lambda m: None)))
        return wall, cpu, total, sum(e["seconds"] for e in read_manifest(manifest_path(dest))), done[0].done

    size_mb = sum(p.stat().st_size for p in ([bag] if bag.is_file() else bag.iterdir())) / 1e6
    for workers in args.workers:
        times: dict[str, list] = {"files": [], "bag": []}
        runners = (("files", files_run), ("bag", bag_run))
        for name, once in runners:                                       # fork server, imports, page cache
            once("warm", workers)
        for _ in range(args.runs):                                       # alternating, so that the load drift
            for name, once in runners:                                   # of a shared machine hits both
                times[name].append(once(name[0], workers))
        n = times["bag"][0][4]
        print(f"\n{kind}: {n} augmented messages ({size_mb:.0f} MB bag), {workers} worker(s), {args.runs} runs")
        stats = {}
        for name in ("files", "bag"):
            wall = [x[0] for x in times[name]]
            main_cpu, total = (statistics.median(x[k] for x in times[name]) for k in (1, 2))
            stats[name] = (statistics.median(wall), min(wall), total)
            print(f"  {name + ':':<6} wall median {stats[name][0]:6.2f} s ({stats[name][0] / n * 1e3:6.1f} ms/message),"
                  f" min {min(wall):6.2f} s, in-worker {statistics.median(x[3] for x in times[name]):6.2f} s, "
                  f"CPU {total:6.2f} s (main process {main_cpu:5.2f} s); runs {', '.join(f'{w:.2f}' for w in wall)}")
        print(f"  bag overhead over files: wall median {100 * (stats['bag'][0] / stats['files'][0] - 1):+.1f} %, "
              f"wall min {100 * (stats['bag'][1] / stats['files'][1] - 1):+.1f} %, "
              f"CPU {100 * (stats['bag'][2] / stats['files'][2] - 1):+.1f} % (target ≤ +10 %)")


def timed(fn) -> tuple[float, float, float]:
    """``(wall s, CPU s of this process, CPU s of this process and of the worker processes)``: workers are children
    of the fork server (roadview_noise.executor), which reaps them, so their CPU is in its children's times once
    they have exited (Linux /proc)."""
    t0, c0, w0 = time.perf_counter(), time.process_time(), _workers_cpu()
    fn()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    time.sleep(0.3)                                                      # let the fork server reap the workers
    return wall, cpu, cpu + _workers_cpu() - w0


def _workers_cpu() -> float:
    from multiprocessing import forkserver

    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)
    if pid is None:
        return 0.0
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[13]) + int(fields[14])) / os.sysconf("SC_CLK_TCK")          # cutime + cstime


if __name__ == "__main__":
    main()
