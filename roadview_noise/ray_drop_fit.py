"""Fitting ray drop on real scans (``rvnoise fit ray-drop``; the defaults of ``ray_drop.lidar``: bench/fit_ray_drop.py).

A real scan's no-return rays are its ray-drop pattern: the rays a sensor fired that returned nothing (a full grid's
no-return cells; a point list's empty cells of its firing grid, :mod:`physics.firing_grid`). Each fired ray becomes a
training example — dropped or not — with the features of :mod:`physics.ray_drop` (from its neighbours, the ray left
out, so that dropped and returned rays are described alike). Rays with fewer than :data:`MIN_SUPPORT` returning
neighbours are left out of fitting and evaluation: a ray in the middle of a no-return region is mostly sky (beyond
range: no return in an ideal scan either, the hard rule) or a large dark or specular surface; no feature tells the two
apart.

Classifiers:
- ``physical``: the seven coefficients of :class:`physics.ray_drop.PhysicalRayDrop` by maximum likelihood (L-BFGS-B,
  bounds that keep it physical: more signal never drops more; range and grazing incidence never help).
- ``learned``: :class:`physics.ray_drop.AdditiveLogistic` — logistic regression on piecewise-linear ("hat")
  functions of each feature at quantile knots, the knot values monotone where physics says so (drop probability
  non-increasing in signal and cos θ, non-decreasing in range), a small penalty on their second differences. Why this
  classifier: the LiDAR equation is additive in log signal (``ln S = ln K + ln ρ + ln cos θ − 2 ln R``), so an
  additive model in these features is the right structure; it is convex (one optimum: the same file from the same
  scans), needs few parameters (a handful of scans suffice, where trees or a CNN would learn the scenes), extrapolates
  flat beyond its knots, stores as a few numbers (JSON) and runs as four ``np.interp`` calls.
Metrics: ROC AUC (ties averaged) and log-loss, against the constant rate of the training cells.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.stats import rankdata

from .physics.ray_drop import FEATURES, AdditiveLogistic, PhysicalRayDrop, scan_rays
from .physics.receiver import Receiver
from .types import PointCloud

MIN_SUPPORT = 3                          # returning neighbours (of 8) for a ray to be fitted or evaluated
KNOTS = 8                                # hat-function knots per feature (quantiles 1 … 99 %)
SMOOTHNESS = 1e-3                        # penalty on the second differences of the knot values (per mean log-loss)
#: drop probability against each feature: −1 non-increasing, +1 non-decreasing, 0 free
MONOTONE = {"log_signal": -1, "log_range": 1, "cos_incidence": -1, "elevation_rad": 0}
EPS = 1e-9

#: bounds of the physical coefficients (PhysicalRayDrop field order)
PHYSICAL_BOUNDS = (
    (-15.0, 15.0),      # log_gain
    (-6.0, 1.9),        # range_exponent: with the signal's own R⁻², more range never helps
    (0.0, 8.0),         # incidence_exponent: grazing incidence never helps
    (-20.0, 20.0),      # elevation_linear_per_rad
    (-200.0, 200.0),    # elevation_quadratic_per_rad2
    (0.05, 6.0),        # log_signal_sd
    (0.0, 0.5),         # floor_drop_probability
)
PHYSICAL_START = (0.0, 0.0, 0.5, 0.0, 0.0, 1.0, 0.01)
#: the physical coefficients of each feature (leaving a feature out pins them to 0)
PHYSICAL_TERMS = {"log_range": ("range_exponent",), "cos_incidence": ("incidence_exponent",),
                  "elevation_rad": ("elevation_linear_per_rad", "elevation_quadratic_per_rad2")}


@dataclass(frozen=True, eq=False)
class RayCells:
    """Training examples: ``features`` (n, 4), ``dropped`` (n,), the image ``column`` of each and the scan's column
    count, ``scan`` index; ``receiver`` of the (first) scan's profile; ``notes``: per scan, what was used."""

    features: np.ndarray
    dropped: np.ndarray
    column: np.ndarray
    columns: np.ndarray
    scan: np.ndarray
    receiver: Receiver
    notes: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.dropped)

    def subset(self, mask: np.ndarray) -> RayCells:
        return RayCells(self.features[mask], self.dropped[mask], self.column[mask], self.columns[mask],
                        self.scan[mask], self.receiver, self.notes)

    def azimuth_fraction(self) -> np.ndarray:
        """Each example's column as a fraction of its scan's turn, in [0, 1)."""
        return self.column / self.columns


def scan_examples(cloud: PointCloud, name: str = "scan") -> RayCells:
    """Training examples of one real scan (module doc); ValueError naming it when it has no firing grid."""
    sr = scan_rays(cloud, "rvnoise fit ray-drop")
    if sr.cells is None:
        raise ValueError(f"{name}: {sr.reason}; ray drop is fitted on full grids or point lists of one scan")
    cells = sr.cells
    returned = cells.cell[cells.shown]
    at = np.concatenate([returned, cells.empty])
    dropped = np.concatenate([np.zeros(len(returned), bool), np.ones(len(cells.empty), bool)])
    features, support = sr.features(at, cloud.positions_m)
    keep = support >= MIN_SUPPORT
    n = int(keep.sum())
    note = {"scan": name, "grid": cells.source, "fired_rays": len(at), "no_return": len(cells.empty), "used": n,
            "used_no_return": int(dropped[keep].sum()), "profile": sr.rays.profile.name,
            "intensity_reading": sr.rays.notes.get("intensity_reading", "")}
    return RayCells(features[keep], dropped[keep], at[keep] % cells.columns, np.full(n, cells.columns),
                    np.zeros(n, dtype=np.int64), sr.receiver(), [note])


def combine(scans: list[RayCells]) -> RayCells:
    """The examples of several scans of one sensor (ValueError when their receivers differ)."""
    if not scans:
        raise ValueError("no scans to fit on")
    for s in scans[1:]:
        if s.receiver != scans[0].receiver:
            raise ValueError(f"{s.notes[0]['scan']}: its profile's receiver differs from "
                             f"{scans[0].notes[0]['scan']}'s; fit one sensor at a time")
    return RayCells(*(np.concatenate([getattr(s, k) for s in scans]) for k in ("features", "dropped", "column",
                                                                                 "columns")),
                    np.concatenate([np.full(len(s), i) for i, s in enumerate(scans)]), scans[0].receiver,
                    [n for s in scans for n in s.notes])


# ---------------------------------------------------------------------------------------------------------------
# Metrics


def auc(dropped: np.ndarray, score: np.ndarray) -> float:
    """ROC AUC of ``score`` for the dropped rays (Mann–Whitney, ties averaged); nan without both classes."""
    y = np.asarray(dropped, bool)
    n1 = int(y.sum())
    n0 = len(y) - n1
    if n1 == 0 or n0 == 0:
        return float("nan")
    ranks = rankdata(score)
    return float((ranks[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def log_loss(dropped: np.ndarray, p: np.ndarray) -> float:
    """Mean binary cross-entropy (nats) of drop probabilities ``p``."""
    p = np.clip(np.asarray(p, dtype=np.float64), EPS, 1 - EPS)
    y = np.asarray(dropped, bool)
    return float(-np.mean(np.where(y, np.log(p), np.log1p(-p))))


def scores(dropped: np.ndarray, p: np.ndarray) -> dict:
    return {"auc": auc(dropped, p), "log_loss": log_loss(dropped, p)}


# ---------------------------------------------------------------------------------------------------------------
# Physical


def fit_physical(cells: RayCells, without: tuple[str, ...] = ()) -> PhysicalRayDrop:
    """Maximum-likelihood coefficients of :class:`PhysicalRayDrop` on the examples (bounded L-BFGS-B); the terms of
    the features in ``without`` are pinned to 0."""
    f, y = cells.features, cells.dropped
    names = [fl.name for fl in dataclasses.fields(PhysicalRayDrop)]
    bounds, start = list(PHYSICAL_BOUNDS), list(PHYSICAL_START)
    for feature in without:
        for term in PHYSICAL_TERMS[feature]:
            i = names.index(term)
            bounds[i], start[i] = (0.0, 0.0), 0.0

    def nll(theta):
        return log_loss(y, PhysicalRayDrop(*theta).drop_probability(f, cells.receiver))

    res = minimize(nll, np.asarray(start), method="L-BFGS-B", bounds=bounds, options={"maxiter": 500, "eps": 1e-6})
    return PhysicalRayDrop(*(float(v) for v in res.x))


# ---------------------------------------------------------------------------------------------------------------
# Learned: additive logistic on hat functions


def _knots(x: np.ndarray, n: int) -> np.ndarray:
    return np.unique(np.quantile(x, np.linspace(0.01, 0.99, n)))


def _hat_basis(x: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """(n, K) weights of x on the hat functions at ``knots`` (constant beyond the outer knots)."""
    k = len(knots)
    out = np.zeros((len(x), k))
    if k == 1:
        out[:, 0] = 1.0
        return out
    xc = np.clip(x, knots[0], knots[-1])
    j = np.clip(np.searchsorted(knots, xc, side="right") - 1, 0, k - 2)
    t = (xc - knots[j]) / (knots[j + 1] - knots[j])
    rows = np.arange(len(x))
    out[rows, j] = 1.0 - t
    out[rows, j + 1] = t
    return out


def fit_additive(cells: RayCells, without: tuple[str, ...] = (), *, knots: int = KNOTS,
                 smoothness: float = SMOOTHNESS) -> AdditiveLogistic:
    """The ``learned`` classifier (module doc) on the features not in ``without``. The knot values of each feature are
    the cumulative sums of bounded increments (sign by :data:`MONOTONE`), the first value 0 (one intercept for all)."""
    f, y = cells.features, cells.dropped.astype(np.float64)
    names, knot_sets, blocks = [], [], []
    for j, name in enumerate(FEATURES):
        if name in without:
            continue
        kn = _knots(f[:, j], knots)
        if len(kn) < 2:
            continue                                   # a constant feature carries nothing
        basis = _hat_basis(f[:, j], kn)
        # value_k = Σ_{i ≤ k} d_i (k ≥ 1): the design of increment i is the basis weight on knots i … K−1
        blocks.append(np.cumsum(basis[:, ::-1], axis=1)[:, ::-1][:, 1:])
        names.append(name)
        knot_sets.append(kn)
    design = np.hstack([np.ones((len(y), 1))] + blocks)
    bounds = [(None, None)]
    penalty_pairs = []
    start = 1
    for name, block in zip(names, blocks):
        sign = MONOTONE[name]
        bounds += [(0.0, None) if sign > 0 else (None, 0.0) if sign < 0 else (None, None)] * block.shape[1]
        penalty_pairs += [(start + i, start + i + 1) for i in range(block.shape[1] - 1)]
        start += block.shape[1]
    a, b = (np.asarray(v, dtype=np.int64) for v in zip(*penalty_pairs)) if penalty_pairs else (np.zeros(0, int),) * 2

    def loss(theta):
        z = design @ theta
        p = 1.0 / (1.0 + np.exp(-z))
        value = np.mean(np.logaddexp(0.0, z) - y * z)
        diff = theta[b] - theta[a]
        grad = design.T @ (p - y) / len(y)
        np.add.at(grad, b, 2 * smoothness * diff)
        np.add.at(grad, a, -2 * smoothness * diff)
        return value + smoothness * float(diff @ diff), grad

    rate = float(np.clip(y.mean(), 1e-6, 1 - 1e-6))
    theta0 = np.zeros(design.shape[1])
    theta0[0] = np.log(rate / (1 - rate))
    res = minimize(loss, theta0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 2000})
    theta = res.x
    values, start = [], 1
    for block in blocks:
        values.append(np.concatenate([[0.0], np.cumsum(theta[start:start + block.shape[1]])]))
        start += block.shape[1]
    return AdditiveLogistic(tuple(names), tuple(knot_sets), tuple(values), float(theta[0]))


# ---------------------------------------------------------------------------------------------------------------
# Validation


def compare(train: RayCells, test: RayCells, without: tuple[str, ...] = ()) -> dict:
    """Fit both classifiers (without the features ``without``) and the constant rate on ``train``; their scores on
    ``test``."""
    rate = float(train.dropped.mean())
    physical = fit_physical(train, without)
    learned = fit_additive(train, without)
    return {"train_examples": len(train), "test_examples": len(test), "test_drop_rate": float(test.dropped.mean()),
            "constant": scores(test.dropped, np.full(len(test), rate)),
            "physical": scores(test.dropped, physical.drop_probability(test.features, test.receiver)),
            "learned": scores(test.dropped, learned.drop_probability(test.features))}


def column_halves(cells: RayCells, without: tuple[str, ...] = ()) -> list[dict]:
    """Fit on one half of every scan's columns, test on the other, both ways."""
    first = cells.azimuth_fraction() < 0.5
    return [compare(cells.subset(first), cells.subset(~first), without),
            compare(cells.subset(~first), cells.subset(first), without)]


def azimuth_sectors(cells: RayCells, sectors: int = 4, without: tuple[str, ...] = ()) -> list[dict]:
    """Leave one azimuth sector out: fit on the other sectors, test on it (disjoint scene content)."""
    sector = np.minimum((cells.azimuth_fraction() * sectors).astype(int), sectors - 1)
    return [compare(cells.subset(sector != k), cells.subset(sector == k), without) for k in range(sectors)]


# ---------------------------------------------------------------------------------------------------------------
# Reading real scans (rvnoise fit ray-drop)

SCAN_SUFFIXES = (".pcd", ".ply", ".bin")


def scan_files(root: Path) -> list[Path]:
    """The point-cloud files under ``root`` (or ``root`` itself), sorted."""
    if root.is_file():
        return [root]
    return sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES)


def read_scans(root: Path, lidar_profile: str | None = None) -> tuple[list[RayCells], list[str]]:
    """Training examples of every scan under ``root`` (:func:`scan_examples`); the profile: ``lidar_profile``, else a
    ``lidar.yaml`` next to the file, else the default OS1-128 (intensity unit read from the data). A file that cannot
    be used is skipped and named in the second list with the reason."""
    from .errors import RvNoiseError
    from .io.pointcloud import read_pointcloud
    from .profiles.lidar import load_lidar_profile

    done, skipped = [], []
    files = scan_files(root)
    if not files:
        raise ValueError(f"{root}: no point clouds (.pcd, .ply, .bin, .pcd.bin) found")
    for path in files:
        try:
            sidecar = path.parent / "lidar.yaml"
            spec = lidar_profile or (str(sidecar) if sidecar.is_file() else None)
            cloud = read_pointcloud(path, sensor="lidar", profile=load_lidar_profile(spec))
            done.append(scan_examples(cloud, str(path)))
        except (RvNoiseError, ValueError) as e:
            skipped.append(f"{path}: {e}")
    return done, skipped
