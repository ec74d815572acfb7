"""Fit the default ray-drop coefficients on the real OS1-128 range image and validate them (issue 16).

    .venv/bin/python bench/fit_ray_drop.py [--data ../shared/data] [--json out.json]

Reads ``os1-128/scan0_grid.npz`` (the full 128×1024 range image with its no-return cells; never committed) with the
unit's own calibration (``beam_intrinsics.json``: 8-bit reflectivity channel), then
1. fits ``physical`` and ``learned`` on every column, with every feature and without the elevation (the defaults of
   ``ray_drop.lidar``, pasted into models/lidar/ray_drop.py: the elevation terms change sign between azimuth sectors —
   scene, not sensor — and leaving them out scores better on held-out sectors);
2. validates both against the constant drop rate: fit on one half of the columns, test on the other (both ways), and
   leave-one-out over 4 disjoint azimuth sectors (other scene content, same sensor);
3. prints the AUC and log-loss of each, and how stable the physical coefficients are across the sector fits;
4. with ``--other-grid FILE`` (repeatable; range images in the same layout, e.g. the other frames of the same Ouster
   capture written by ``bench/ouster_pcap_grids.py``): scores the committed defaults, and both back-ends fitted on
   all of scan0, on each other scan — the check that a fit on one scan generalises to other scans of the sensor.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from roadview_noise.models.lidar.ray_drop import RayDropLidar  # noqa: E402
from roadview_noise.physics.ray_drop import FEATURES  # noqa: E402
from roadview_noise.profiles.lidar import load_lidar_profile  # noqa: E402
from roadview_noise.ray_drop_fit import (azimuth_sectors, column_halves, compare, fit_additive,  # noqa: E402
                                         fit_physical, scan_examples, scores)
from roadview_noise.types import PointCloud  # noqa: E402


def real_grid(data: Path, grid: Path | None = None) -> PointCloud:
    """scan0_grid.npz (or ``grid``, same layout) as a full 128×1024 grid cloud (zero position = no return),
    reflectivity as intensity."""
    g = np.load(grid or data / "os1-128" / "scan0_grid.npz")
    profile = load_lidar_profile(str(data / "os1-128" / "beam_intrinsics.json"))
    rows, cols = g["range_mm"].shape
    xyz = g["xyz_m"].reshape(-1, 3).astype(np.float64)
    xyz[g["range_mm"].reshape(-1) == 0] = 0.0
    return PointCloud(xyz, {"intensity": g["reflectivity"].reshape(-1).astype(np.float32)}, "lidar", profile,
                      grid_shape=(rows, cols))


def _row(name: str, r: dict) -> str:
    return f"{name:<9} AUC {r['auc']:.3f}  log-loss {r['log_loss']:.4f}"


def _summary(title: str, folds: list[dict]) -> dict:
    print(f"\n{title}")
    out = {}
    for k in ("constant", "physical", "learned"):
        auc = [f[k]["auc"] for f in folds]
        ll = [f[k]["log_loss"] for f in folds]
        out[k] = {"auc": auc, "log_loss": ll}
        print(f"  {k:<9} AUC " + " ".join(f"{a:.3f}" for a in auc) + f"  (mean {np.mean(auc):.3f})   log-loss "
              + " ".join(f"{v:.4f}" for v in ll) + f"  (mean {np.mean(ll):.4f})")
    print("  test drop rates " + " ".join(f"{f['test_drop_rate']:.4f}" for f in folds)
          + "; examples " + " ".join(f"{f['train_examples']}/{f['test_examples']}" for f in folds))
    return out


def other_scans(cells, args) -> dict:
    """Fit on all of scan0 (without elevation, as the defaults), score on each other scan; the committed defaults too."""
    print("\n=== other scans of the sensor (fitted on all of scan0, without elevation) ===")
    defaults = RayDropLidar().physical()
    out = {}
    for path in args.other_grid:
        other = scan_examples(real_grid(args.data, path), path.stem)
        r = compare(cells, other, ("elevation_rad",))
        r["defaults"] = scores(other.dropped, defaults.drop_probability(other.features, other.receiver))
        print(f"  {path.name}: {len(other)} rays, drop rate {r['test_drop_rate']:.4f}   "
              + "   ".join(_row(k, r[k]) for k in ("constant", "defaults", "physical", "learned")))
        out[path.name] = r
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    ap.add_argument("--other-grid", type=Path, action="append", default=[],
                    help="another scan of the same sensor (npz in scan0_grid.npz's layout) to test on")
    args = ap.parse_args()
    if not (args.data / "os1-128" / "scan0_grid.npz").is_file():
        sys.exit(f"no {args.data}/os1-128/scan0_grid.npz: the real scan is not available here")
    cells = scan_examples(real_grid(args.data), "scan0_grid")
    note = cells.notes[0]
    print(f"scan0: {note['fired_rays']} fired rays, {note['no_return']} without a return; used (≥ 3 of 8 neighbours "
          f"return) {note['used']}, of which {note['used_no_return']} without a return "
          f"(rate {note['used_no_return'] / note['used']:.4f}); {note['intensity_reading']}")
    f = cells.features
    grazing = f[:, 2] < np.cos(np.radians(85))
    print(f"  incidence > 85° (from the neighbours): {int(grazing.sum())} rays, drop rate "
          f"{cells.dropped[grazing].mean():.3f} — not the 'always drops' of models.md §3.9")
    report = {"features": FEATURES, "notes": cells.notes}
    for without, label in (((), "every feature"), (("elevation_rad",), "without elevation (the defaults)")):
        print(f"\n=== {label} ===")
        physical = fit_physical(cells, without)
        learned = fit_additive(cells, without)
        print("fitted on every column (in-sample):")
        print("  " + _row("physical", scores(cells.dropped, physical.drop_probability(f, cells.receiver))))
        print("  " + _row("learned", scores(cells.dropped, learned.drop_probability(f))))
        print("  physical: " + ", ".join(f"{k}={v:.4g}" for k, v in dataclasses.asdict(physical).items()))
        for name, kn, val in zip(learned.features, learned.knots, learned.values):
            print(f"  learned {name}: knots " + " ".join(f"{k:.3g}" for k in kn) + " | logit "
                  + " ".join(f"{v:+.2f}" for v in val))
        print(f"  learned intercept {learned.intercept:+.3f}")
        halves = _summary("column halves (fit on one half, test on the other; both ways):",
                          column_halves(cells, without))
        sectors = _summary("4 azimuth sectors (leave one out):", azimuth_sectors(cells, 4, without))
        sector = np.minimum((cells.azimuth_fraction() * 4).astype(int), 3)
        coefs = [dataclasses.asdict(fit_physical(cells.subset(sector != k), without)) for k in range(4)]
        print("physical coefficients fitted without each sector:")
        for k in coefs[0]:
            print(f"  {k:<30} " + " ".join(f"{c[k]:+.4g}" for c in coefs))
        report[label] = {"physical": dataclasses.asdict(physical), "halves": halves, "sectors": sectors,
                         "sector_coefficients": coefs}
    if args.other_grid:
        report["other scans"] = other_scans(cells, args)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))

if __name__ == "__main__":
    main()
