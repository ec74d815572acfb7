"""Bag overhead: augmenting a ROS bag against augmenting the same messages as files (issue 20 target: ≤ 10 %).

Renders a drive with ``rvnoise sample-data`` (default: the sensors' full resolutions, camera 1936×1464, OS1-128
128×2048; ``--sample`` for the committed preset), writes it as a ROS 1 bag and a ROS 2 MCAP bag (every frame
``--repeat`` times with new stamps; topics of ``roadview_noise.sampledata.bag``), exports each bag to an input tree
with ``rvnoise export``, and times ``--runs`` runs of each, alternating, with 1 and 2 workers (``--workers``; every
run starts its own workers as a command does, after one warm-up run of each that starts the fork server):

- files: ``runner.run`` per mapped topic (CNF16 on both cameras, CNF20 LiDAR, CNF25 radar) over the exported tree;
- bag:   ``run_bag`` with the same chains and seed over the bag (also copying the depth and diagnostics topics).

Prints per runner the median and the minimum wall time, the in-worker time (sum of the manifests' seconds) and the
CPU time of this process: with one worker everything, which a busy shared machine disturbs far less than wall
time; with more, the main process's serial work (for a bag: reading, hand-off to the workers, writing). And the
overhead bag / files − 1. The files side is one ``run`` per topic (its own workers each), as a user would run it.
Re-run on an idle machine for the record.

    .venv/bin/python bench/bench_rosbag.py [--sample] [--frames 3] [--repeat 2] [--runs 5] [--workers 1 2]
"""

from __future__ import annotations

import argparse
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

    def files_run(tag: str, workers: int) -> tuple[float, float, float, int]:
        t0, c0, inner, n = time.perf_counter(), time.process_time(), 0.0, 0
        for topic, r in files_recipes.items():
            dest = out / f"{tag}-{topic.strip('/').replace('/', '_')}"
            s = run(r, tree, dest, workers=workers, progress=False, overwrite=True, echo=lambda m: None)
            inner += sum(e["seconds"] for e in read_manifest(dest / "manifest.jsonl"))
            n += s.done
        return time.perf_counter() - t0, time.process_time() - c0, inner, n

    def bag_run(tag: str, workers: int) -> tuple[float, float, float, int]:
        dest = out / f"{tag}{bag.suffix or '-ros2'}"
        t0, c0 = time.perf_counter(), time.process_time()
        s = run_bag(recipe, bag, dest, workers=workers, progress=False, overwrite=True, echo=lambda m: None)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        return wall, cpu, sum(e["seconds"] for e in read_manifest(manifest_path(dest))), s.done

    size_mb = sum(p.stat().st_size for p in ([bag] if bag.is_file() else bag.iterdir())) / 1e6
    for workers in args.workers:
        times: dict[str, list] = {"files": [], "bag": []}
        runners = (("files", files_run), ("bag", bag_run))
        for name, once in runners:                                       # fork server, imports, page cache
            once("warm", workers)
        for _ in range(args.runs):                                       # alternating, so that the load drift
            for name, once in runners:                                   # of a shared machine hits both
                times[name].append(once(name[0], workers))
        n = times["bag"][0][3]
        print(f"\n{kind}: {n} augmented messages ({size_mb:.0f} MB bag), {workers} worker(s), {args.runs} runs")
        stats = {}
        for name in ("files", "bag"):
            wall = [x[0] for x in times[name]]
            cpu = statistics.median(x[1] for x in times[name])
            stats[name] = (statistics.median(wall), min(wall), cpu)
            print(f"  {name + ':':<6} wall median {stats[name][0]:6.2f} s ({stats[name][0] / n * 1e3:6.1f} ms/message),"
                  f" min {min(wall):6.2f} s, in-worker {statistics.median(x[2] for x in times[name]):6.2f} s"
                  + (f", CPU {cpu:6.2f} s" if workers == 1 else f", main-process CPU {cpu:5.2f} s")
                  + f"; runs {', '.join(f'{w:.2f}' for w in wall)}")
        overhead = [f"wall median {100 * (stats['bag'][0] / stats['files'][0] - 1):+.1f} %",
                    f"wall min {100 * (stats['bag'][1] / stats['files'][1] - 1):+.1f} %"]
        if workers == 1:
            overhead.append(f"CPU {100 * (stats['bag'][2] / stats['files'][2] - 1):+.1f} %")
        print(f"  bag overhead over files: {', '.join(overhead)} (target ≤ +10 %)")


if __name__ == "__main__":
    main()
