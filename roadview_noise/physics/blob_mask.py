"""Procedural blob masks: irregular, clustered splatters on any (H, W) grid (models.md §2.4 mask generator).

Used by lens soiling on camera images, and meant for the sensor-window obstruction of LiDAR/radar range images
(models.md §3.8, §4.4: pass the range image's (rows, columns), ``column_scale`` for its angular aspect and
``wrap_columns=True`` for a 360° scan).

A blob of size S (its diameter, px) is the union of 6–20 ellipses with full axes 0.2–0.6·S at random
orientations, their centres uniform in the disc that keeps each ellipse inside diameter S; then softened with a
Gaussian of σ = ``softness``·S (defocus). Blobs combine as coverage, ``M = 1 − Π(1 − m_i)``, so overlapping
blobs never exceed 1.

How many blobs — one of two parametrisations:
- ``count``: exactly this many (lens soiling draws it from a Poisson law of mean 12);
- ``seed_probability``: each grid cell seeds a blob with this probability, ``K ~ Binomial(H·W, p)`` (D3.5's
  obstruction parameter: p = 6·10⁻⁵ on a 128×2048 OS1-128 range image → 15.7 blobs per frame on average).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

ELLIPSES_PER_BLOB = (6, 20)          # inclusive range of ellipses in one blob
AXIS_FRACTION = (0.2, 0.6)           # full ellipse axes as a fraction of the blob size
SUBPIXEL_BITS = 4                    # cv2.ellipse fixed-point precision (1/16 px)


@dataclass(frozen=True, eq=False)
class BlobMask:
    """``mask``: (H, W) float32 coverage in [0, 1]; ``count``: blobs drawn; ``sizes_px``: their sizes."""

    mask: np.ndarray
    count: int
    sizes_px: np.ndarray

    def covered_fraction(self, threshold: float = 0.5) -> float:
        """Share of cells covered more than ``threshold``."""
        return float(np.count_nonzero(self.mask > threshold)) / max(1, self.mask.size)


def blob_mask(shape: tuple[int, int], rng: np.random.Generator, *, size_px: tuple[float, float],
              count: int | None = None, seed_probability: float | None = None, softness: float = 0.05,
              vertical_bias: float = 0.0, column_scale: float = 1.0, wrap_columns: bool = False) -> BlobMask:
    """Draw and render blobs on an (H, W) grid.

    ``size_px``: (S_min, S_max) blob diameters in grid cells (rows), S ~ U(S_min, S_max). Give exactly one of
    ``count`` or ``seed_probability`` (module docstring). ``vertical_bias`` ∈ [0, 1] tilts the centres towards the
    bottom rows (density ∝ 1 − β + 2β·y/H; spray from the road), 0 = uniform. ``column_scale`` stretches blobs
    horizontally (cells per row-cell: a round spot on a window is wider in columns when the column step is the finer
    angle). ``wrap_columns``: blobs leaving one side re-enter on the other (360° range image); otherwise they are
    clipped at the border. Deterministic for a given ``rng`` state."""
    h, w = int(shape[0]), int(shape[1])
    s_min, s_max = float(size_px[0]), float(size_px[1])
    if h < 1 or w < 1:
        raise ValueError(f"grid must be at least 1×1, got {w}×{h}")
    if not 0 < s_min <= s_max:
        raise ValueError(f"size_px must be 0 < S_min ≤ S_max, got {size_px}")
    if not 0 <= vertical_bias <= 1 or column_scale <= 0 or softness < 0:
        raise ValueError("need 0 ≤ vertical_bias ≤ 1, column_scale > 0, softness ≥ 0")
    if (count is None) == (seed_probability is None):
        raise ValueError("give exactly one of count or seed_probability")
    if count is None:
        if not 0 <= seed_probability <= 1:
            raise ValueError(f"seed_probability must be in [0, 1], got {seed_probability}")
        count = int(rng.binomial(h * w, seed_probability))
    elif count < 0:
        raise ValueError(f"count must be ≥ 0, got {count}")
    mask = np.zeros((h, w), np.float32)
    sizes = rng.uniform(s_min, s_max, count)
    cols = rng.uniform(0, w, count)
    rows = h * _biased_unit(rng.random(count), vertical_bias) - 0.5
    for size, col, row in zip(sizes, cols, rows):
        _add_blob(mask, rng, size, col - 0.5, row, softness, column_scale, wrap_columns)
    return BlobMask(mask, count, sizes)


def _biased_unit(u: np.ndarray, bias: float) -> np.ndarray:
    """Inverse CDF of the density 1 − β + 2β·t on [0, 1]."""
    if bias == 0:
        return u
    return (-(1 - bias) + np.sqrt((1 - bias) ** 2 + 4 * bias * u)) / (2 * bias)


def _add_blob(mask: np.ndarray, rng: np.random.Generator, size: float, col: float, row: float, softness: float,
              column_scale: float, wrap: bool) -> None:
    """Render one blob in a local window and merge it into ``mask`` as coverage."""
    h, w = mask.shape
    sigma = softness * size
    half_h = int(math.ceil(size / 2 + 3 * sigma)) + 1
    half_w = int(math.ceil((size / 2 + 3 * sigma) * column_scale)) + 1
    local = np.zeros((2 * half_h + 1, 2 * half_w + 1), np.float32)
    n = int(rng.integers(ELLIPSES_PER_BLOB[0], ELLIPSES_PER_BLOB[1] + 1))
    axes = rng.uniform(*AXIS_FRACTION, (n, 2)) * size / 2                 # semi-axes
    reach = np.maximum(size / 2 - axes.max(axis=1), 0.0)                 # keep every ellipse inside diameter S
    radius = reach * np.sqrt(rng.random(n))
    phi = rng.uniform(0, 2 * np.pi, n)
    angle = rng.uniform(0, 180, n)
    scale = 1 << SUBPIXEL_BITS
    for (a, b), r, p, ang in zip(axes, radius, phi, angle):
        cx = half_w + (r * math.cos(p)) * column_scale
        cy = half_h + r * math.sin(p)
        cv2.ellipse(local, (round(cx * scale), round(cy * scale)),
                    (max(1, round(a * column_scale * scale)), max(1, round(b * scale))), float(ang), 0, 360, 1.0,
                    thickness=-1, lineType=cv2.LINE_8, shift=SUBPIXEL_BITS)
    if sigma > 0:
        local = cv2.GaussianBlur(local, (0, 0), sigmaX=sigma * column_scale, sigmaY=sigma)
    np.clip(local, 0.0, 1.0, out=local)
    top, left = round(row) - half_h, round(col) - half_w
    r0, r1 = max(top, 0), min(top + local.shape[0], h)
    if r0 >= r1:
        return
    local = local[r0 - top:r1 - top]
    for start in range(0, local.shape[1], w if wrap else local.shape[1]):
        part = local[:, start:start + w] if wrap else local
        columns = np.arange(left + start, left + start + part.shape[1])
        if wrap:
            columns %= w                     # chunks of ≤ W columns: each index once, the union stays right
        else:
            keep = (columns >= 0) & (columns < w)
            part, columns = part[:, keep], columns[keep]
        if columns.size:
            region = mask[r0:r1, columns]
            mask[r0:r1, columns] = 1.0 - (1.0 - region) * (1.0 - part)      # coverage union
