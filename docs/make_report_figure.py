"""Render the README's screenshot of `rvnoise report`: every shipped CNF recipe augmented on sample_data/ (or the
runs already in RUNS_DIR, e.g. from `bench/bench_preview_report.py --keep DIR`: DIR/runs), the report written, and
its top photographed by headless Chromium (`--screenshot`), scaled to 1000 px.

    .venv/bin/python docs/make_report_figure.py [RUNS_DIR]   # writes docs/images/report.png (needs chromium)
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "images" / "report.png"
WIDTH_PX, HEIGHT_PX, SHOWN_PX = 1400, 1900, 1000


def main() -> None:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        sys.exit("needs chromium (Debian: apt-get install chromium)")
    with tempfile.TemporaryDirectory() as tmp:
        runs = Path(sys.argv[1]).resolve() if len(sys.argv) > 1 else Path(tmp) / "runs"
        for recipe in [] if len(sys.argv) > 1 else sorted((ROOT / "recipes").glob("cnf*.yaml")):
            subprocess.run([sys.executable, "-m", "roadview_noise.cli.main", "augment", "--recipe", str(recipe),
                            "sample_data", str(runs / recipe.stem), "--quiet", "--workers", "2"], cwd=ROOT,
                           check=True, stdout=subprocess.DEVNULL)
        subprocess.run([sys.executable, "-m", "roadview_noise.cli.main", "report", str(runs)], cwd=ROOT, check=True)
        shot = Path(tmp) / "shot.png"
        subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                        f"--window-size={WIDTH_PX},{HEIGHT_PX}", f"--user-data-dir={tmp}/profile",
                        f"--screenshot={shot}", (runs / "report.html").as_uri()], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        img = cv2.imread(str(shot))
        img = cv2.resize(img, (SHOWN_PX, round(img.shape[0] * SHOWN_PX / img.shape[1])), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(OUT), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
