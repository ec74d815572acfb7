"""Preview and report for every CNF on the sample data (issue 18 target: under 2 minutes on 2 cores).

Runs, as a user would, through the command line (process start included):
1. `rvnoise augment --workers 1` of every shipped CNF recipe (`recipes/cnfNN*.yaml`) on `sample_data/` (3–12
   small files per recipe: starting worker processes would cost more than they save);
2. `rvnoise report` over the folder of those runs (coverage of all 30 CNFs, plots, previews, corner cases);
3. `rvnoise preview --all-cnfs`: one contact sheet per file — camera PNG, raw DNG, OS1-128 list and grid,
   VLS-128, radar — each with a row per CNF of its sensor (a note for a CNF whose model is not implemented yet).
Prints the wall time of each part; the target applies to 2 + 3 (augment is timed for reference).

    .venv/bin/python bench/bench_preview_report.py [--keep DIR]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"
FILES = ["camera/seq0/000001.png", "raw/seq0/000001.dng", "lidar/os1-128/seq0/000001.pcd",
         "lidar/os1-128-grid/seq0/000001.pcd", "lidar/vls-128/seq0/000001.pcd", "radar/seq0/000001.pcd"]


def rvnoise(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "roadview_noise.cli.main", *args], cwd=ROOT, check=True,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--keep", type=Path, help="write the runs, report and sheets here instead of a temp dir")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep or Path(tmp)
        recipes = sorted((ROOT / "recipes").glob("cnf*.yaml"))
        t_aug = sum(rvnoise("augment", "--recipe", str(r), str(SAMPLE), str(out / "runs" / r.stem), "--workers",
                            "1", "--quiet", "--overwrite") for r in recipes)
        t_report = rvnoise("report", str(out / "runs"))
        t_sheets = rvnoise("preview", "--all-cnfs", "--input-root", str(SAMPLE), *(str(SAMPLE / f) for f in FILES),
                           "-o", str(out / "sheets"))
        size = (out / "runs" / "report.html").stat().st_size / 1e6
        print(f"augment of {len(recipes)} CNF recipes (reference): {t_aug:6.1f} s")
        print(f"report of those runs ({size:.1f} MB page):        {t_report:6.1f} s")
        print(f"preview --all-cnfs, {len(FILES)} contact sheets:        {t_sheets:6.1f} s")
        print(f"preview + report:                              {t_report + t_sheets:6.1f} s (target < 120 s)")
        print(f"augment + preview + report:                    {t_aug + t_report + t_sheets:6.1f} s")


if __name__ == "__main__":
    main()
