"""Two versions of rain.lidar's or snow.lidar's strongest-return sampler compared in law on the real OS1-128 scan: many
frames (seeds)
of :func:`lidar_weather.particle_returns` per source tree, each tree in a process of its own (``PYTHONPATH``), then the
per-frame counts of weather returns (all, on the points), kept targets and drawn flakes (means, difference in
standard errors of the difference), and over all frames the weather returns' ranges and signals (units of K) and the
kept targets' signal ratios (stored / recorded): means, difference in standard errors, two-sample Kolmogorov–Smirnov
statistic and p-value, 10/50/90 % quantiles. ``--rate`` compares the first tree at two rates (mm/h) instead (what a
change of the rate does, the yardstick of a law change); without it, the model's default rate. ``--exhaustive``: the
first run draws every particle above the base level instead (``particle_returns(…, exhaustive=True)``, the law the
sampler approximates).

    .venv/bin/python bench/compare_precipitation_law.py snow --tree /tmp/base23 --tree . [--frames 200]
    .venv/bin/python bench/compare_precipitation_law.py snow --tree /tmp/base23 --rate 2.5 --rate 2.525
    .venv/bin/python bench/compare_precipitation_law.py snow --exhaustive --tree . --tree .
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

SCAN = Path(__file__).resolve().parents[2] / "shared" / "data" / "os1-128" / "scan0.bin"
FIRST_SEED = 1000


def frames(model_id: str, out: str, count: int, rate: float | None, exhaustive: bool) -> None:
    """In a tree's process: ``count`` frames of rain or snow (``model_id``) at ``rate`` mm/h (None: the default), every
    particle drawn when ``exhaustive``, saved to the npz ``out``."""
    from roadview_noise.models.lidar.rain import RainLidar
    from roadview_noise.models.lidar.snow import SnowLidar
    from roadview_noise.physics.lidar_echo import TARGET, WEATHER
    from roadview_noise.physics.lidar_rays import cloud_rays
    from roadview_noise.physics.lidar_weather import particle_returns
    from roadview_noise.profiles.lidar import os1_128_reflectivity
    from roadview_noise.types import PointCloud

    a = np.fromfile(SCAN, dtype=np.float32).reshape(-1, 4)
    cloud = PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3].copy()}, "lidar", os1_128_reflectivity())
    kind, name = {"rain": (RainLidar, "rain_rate_mm_per_h"), "snow": (SnowLidar, "snowfall_rate_mm_per_h")}[model_id]
    model = kind() if rate is None else kind(**{name: rate})
    medium = model.medium()
    rays = cloud_rays(cloud, model.id, model.empty_rays)
    counts, w_range, w_signal, t_ratio = [], [], [], []
    for seed in range(FIRST_SEED, FIRST_SEED + count):
        ret, drawn = particle_returns(np.random.default_rng(seed), rays, medium, model.return_mode,
                                      model.draw_fraction_of_threshold, exhaustive)
        w, t = ret.kind == WEATHER, ret.kind == TARGET
        counts.append((w.sum(), (w & rays.has_target).sum(), t.sum(), drawn))
        w_range.append(ret.range_m[w])
        w_signal.append(ret.signal[w])
        t_ratio.append(ret.signal[t] / rays.signal[t])
    np.savez(out, counts=np.array(counts, dtype=float), w_range=np.concatenate(w_range),
             w_signal=np.concatenate(w_signal), t_ratio=np.concatenate(t_ratio))


def compare(a, b) -> None:
    """Print the comparison of two saved runs (module doc)."""
    from scipy import stats

    def diff(x, y):
        d = y.mean() - x.mean()
        return d, d / np.sqrt(x.var(ddof=1) / len(x) + y.var(ddof=1) / len(y))

    for j, name in enumerate(("weather returns", "… on points", "targets kept", "flakes drawn")):
        x, y = a["counts"][:, j], b["counts"][:, j]
        d, se = diff(x, y)
        print(f"  {name:16s} {x.mean():10.1f} → {y.mean():10.1f} per frame: {d:+8.1f} ({100 * d / x.mean():+.3f} %, "
              f"{se:+.1f} SE; frame SD {x.std(ddof=1):.1f} / {y.std(ddof=1):.1f})")
    for key, name in (("w_range", "weather range m"), ("w_signal", "weather signal K"),
                      ("t_ratio", "kept target ratio")):
        x, y = a[key], b[key]
        d, se = diff(x, y)
        ks = stats.ks_2samp(x, y)
        q = [np.percentile(v, [10, 50, 90]) for v in (x, y)]
        print(f"  {name:18s} mean {x.mean():.5g} → {y.mean():.5g} ({100 * d / x.mean():+.3f} %, {se:+.1f} SE); "
              f"KS D {ks.statistic:.5f} (p {ks.pvalue:.2g}); 10/50/90 % {q[0].round(4)} → {q[1].round(4)}")


def main() -> int:
    if sys.argv[1:2] == ["--frames-of"]:
        frames(sys.argv[2], sys.argv[3], int(sys.argv[4]), None if sys.argv[5] == "default" else float(sys.argv[5]),
               sys.argv[6] == "exhaustive")
        return 0
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", choices=("rain", "snow"))
    parser.add_argument("--tree", action="append", type=Path, required=True)
    parser.add_argument("--rate", action="append", type=float)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--exhaustive", action="store_true")
    a = parser.parse_args()
    if not SCAN.is_file():
        print(f"the real scan {SCAN} is absent")
        return 1
    runs = [(tree, rate) for tree in a.tree for rate in (a.rate or ["default"])][:2]
    if len(runs) != 2:
        parser.error("give two trees, or one tree and two rates")
    with tempfile.TemporaryDirectory() as tmp:
        saved = []
        for i, (tree, rate) in enumerate(runs):
            out = os.path.join(tmp, f"{i}.npz")
            subprocess.run([sys.executable, __file__, "--frames-of", a.model, out, str(a.frames), str(rate),
                            "exhaustive" if a.exhaustive and i == 0 else "sampler"], check=True,
                           env={**os.environ, "PYTHONPATH": str(tree.resolve()), "OMP_NUM_THREADS": "1"})
            saved.append(np.load(out))
        print(f"{a.model} on the real scan, {a.frames} frames (seeds {FIRST_SEED}…), tree and rate (mm/h): {runs[0]}"
              f"{' (every particle drawn)' if a.exhaustive else ''} → "
              f"{runs[1]}")
        compare(*saved)
    return 0


if __name__ == "__main__":
    sys.exit(main())
