"""Where a camera file's time goes outside the models, paired with another checkout (issue 19 round 10): the
``augment --profile`` split (read, hash, decode, convert, metrics, encode, write) per recipe, the output PNG sizes,
and the PNG encode alone (thread CPU ms) of those outputs' pixels.

The camera tree is ``bench/run.py``'s (rendered 1936×1464 frames made photo-like with σ = 2 codes of noise, range
EXR). Each round runs every recipe once with this checkout's code and once with ``--against``'s (its package first
on ``PYTHONPATH``, this interpreter), in alternating order; figures are the medians over the files and rounds of a
side, with the rounds' spread of the per-file medians in brackets. Outputs' pixels must be the same on both sides
(checked); their PNG bytes may differ (the encoder's filter choice).

    .venv/bin/python bench/bench_camera_file_edges.py --against /tmp/main [--rounds 3] [--recipes weather-snow,cnf12]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PHASES = ("read", "hash", "decode", "convert", "metrics", "encode", "write", "other")


def one_side(recipe_name: str, tree: Path, out: Path) -> dict:
    """Run ``recipe_name`` on ``tree`` with the code on ``sys.path`` (1 worker, ``--profile``); the split, file ms,
    output sizes and the PNG encode time of the outputs' pixels."""
    import numpy as np
    from run import augment        # bench/run.py: the table's own augment call

    from roadview_noise.allocator import keep_freed_memory
    from roadview_noise.io.png import decode_png, encode_png
    from roadview_noise.manifest import read_manifest

    r = augment(recipe_name, "camera", tree, out, 1)
    entries = [e for e in read_manifest(out / "manifest.jsonl") if e["status"] == "ok"]
    outputs = sorted(out.rglob("*.png"))
    keep_freed_memory()
    encode_ms, pixels_sha = [], []
    for p in outputs:
        rgb = decode_png(p.read_bytes())
        bgr = np.ascontiguousarray(rgb[..., ::-1])[..., ::-1]          # as the writer hands the codes over
        encode_png(bgr)
        t = time.thread_time()
        encode_png(bgr)
        encode_ms.append(1e3 * (time.thread_time() - t))
        pixels_sha.append(hashlib.sha256(rgb.tobytes()).hexdigest())
    return {"split": {k: r["split_ms"][k] for k in PHASES}, "file_ms": r["file_ms"], "cpu_ms": r["cpu_ms"],
            "mb": statistics.median(p.stat().st_size for p in outputs) / 1e6,
            "encode_ms": statistics.median(encode_ms), "pixels": pixels_sha, "files": len(entries)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--against", type=Path, help="the other checkout (its roadview_noise package); required")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--recipes", default="weather-fog,weather-rain,weather-snow,cnf10,cnf12")
    ap.add_argument("--files", type=int, default=8, help="camera files (copies of 4 rendered frames)")
    ap.add_argument("--one", nargs=3, metavar=("RECIPE", "TREE", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one_side(args.one[0], Path(args.one[1]), Path(args.one[2]))))
        return
    if args.against is None:
        ap.error("--against is required")
    from run import build_trees

    sides = {"other": args.against.resolve(), "this": ROOT}
    recipes = args.recipes.split(",")
    figures: dict[tuple[str, str], list[dict]] = {}
    with tempfile.TemporaryDirectory(prefix="rvnoise-edges-") as tmp:
        tree = build_trees(Path(tmp), 4, {"camera": args.files})["camera"]
        for k in range(args.rounds):
            for name in recipes:
                for side in (("other", "this") if k % 2 == 0 else ("this", "other")):
                    out = Path(tmp) / f"out-{side}"
                    shutil.rmtree(out, ignore_errors=True)
                    env = {**os.environ, "PYTHONPATH": f"{sides[side]}{os.pathsep}{ROOT / 'bench'}"}
                    done = subprocess.run([sys.executable, __file__, "--one", name, str(tree), str(out)], env=env,
                                          capture_output=True, text=True, cwd=sides[side])
                    if done.returncode:
                        sys.exit(f"{name} with {sides[side]} failed:\n{done.stderr[-3000:]}")
                    figures.setdefault((name, side), []).append(json.loads(done.stdout.strip().splitlines()[-1]))
                    shutil.rmtree(out, ignore_errors=True)
    print(f"# bench_camera_file_edges.py: {args.files} camera files, {args.rounds} rounds, 1 worker; "
          f"'other' = {sides['other']}, 'this' = {ROOT}; ms per file (medians, [spread of the rounds])")
    print("| recipe | side | " + " | ".join(PHASES) + " | file ms | worker CPU ms | PNG encode ms | output MB |")
    print("|---|---|" + "---|" * (len(PHASES) + 4))

    def cell(runs: list[dict], get) -> str:
        v = [get(r) for r in runs]
        return f"{statistics.median(v):.1f} [{min(v):.1f}–{max(v):.1f}]" if len(v) > 1 else f"{v[0]:.1f}"

    for name in recipes:
        same = figures[(name, "other")][0]["pixels"] == figures[(name, "this")][0]["pixels"]
        for side in ("other", "this"):
            runs = figures[(name, side)]
            cells = [cell(runs, lambda r, k=k: r["split"][k]) for k in PHASES]
            cells += [cell(runs, lambda r: r["file_ms"]), cell(runs, lambda r: r["cpu_ms"]),
                      cell(runs, lambda r: r["encode_ms"]), f"{runs[0]['mb']:.3f}"]
            print(f"| {name}{'' if same else ' (PIXELS DIFFER)'} | {side} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
