"""Holes in depth maps — pixels without a valid measurement (NaN) — and what to do with them (recipe
``inputs.depth_holes``):

- ``fill`` (default): interpolate the inverse depth from the valid neighbours (:func:`fill_from_neighbours`).
  Filling keeps the image's own texture under fog, rain and snow (a hole treated as sky becomes a flat patch of
  airlight) and the transmission continuous across the hole.
- ``sky``: holes connected to the top border of the image (8-connected) are sky (range ``inf``) — the usual case
  of stereo or LiDAR depth, which has no value in the sky; the other holes are filled.
- ``error``: the frame fails with the count and fraction of holes.

The validity mask returned with the depth is False on filled pixels: scene radiances (airlight, sky) are never
estimated from them (:class:`roadview_noise.physics.photometry.FrameSample`). Sky declared by ``sky`` counts
as sky there.

Interpolation is pull–push (Gortler et al. 1996, "The Lumigraph", §3.3; :func:`pull_push`): smooth (no flat
patches, no Voronoi edges), exact on valid pixels, local where data is dense and O(pixels). At 1936×1464 with 7 %
of the pixels in hole blobs it takes 30–90 ms on the shared 2-core VM (busy: noisy), OpenCV's Telea inpainting
(``cv2.inpaint``) of the same holes 180–360 ms (``bench/bench_camera_inputs.py``); on a sparse map (KITTI-style,
15 % valid) the median error against the full map is 0.16 %. Inverse depth is interpolated because it is affine in
the image for a plane and keeps sky (inverse 0) finite.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import InputError

HOLE_POLICIES = ("fill", "sky", "error")


def resolve_holes(depth_m: np.ndarray, policy: str, *, source: str = "") -> tuple[np.ndarray, np.ndarray | None,
                                                                                  dict]:
    """``(depth, valid, notes)``: depth without NaN (range, ``inf`` for sky), the (H, W) validity mask (None when
    there was no hole) and what was done (``holes``, ``hole_fraction``, ``filled``, ``sky``), for the manifest.
    InputError (naming ``source``) for policy ``error`` or a map without any valid pixel."""
    if policy not in HOLE_POLICIES:
        raise ValueError(f"unknown depth_holes policy {policy!r}; expected one of {HOLE_POLICIES}")
    if not depth_m.size or not np.isnan(depth_m.min()):     # NaN propagates through min: one pass without holes
        return depth_m, None, {"holes": 0}
    holes = np.isnan(depth_m)
    n = int(np.count_nonzero(holes))
    fraction = n / holes.size
    notes = {"holes": n, "hole_fraction": round(fraction, 6), "policy": policy}
    if policy == "error" or n == holes.size:
        why = "no pixel has a valid depth" if n == holes.size else "inputs.depth_holes is error"
        raise InputError(f"depth has {n} holes ({100 * fraction:.1f} % of the pixels: NaN, 0 or negative, or the "
                         f"format's invalid code) and {why}; depth_holes: fill interpolates them, sky makes those "
                         f"connected to the top border sky", file=source or None)
    sky = connected_to_top(holes) if policy == "sky" else np.zeros_like(holes)
    fill = holes & ~sky
    out = depth_m.copy()
    out[sky] = np.inf
    if fill.any():
        out = fill_from_neighbours(out, fill)
    notes.update(filled=int(np.count_nonzero(fill)), sky=int(np.count_nonzero(sky)))
    return out, ~fill, notes


def connected_to_top(mask: np.ndarray) -> np.ndarray:
    """The pixels of ``mask`` whose 8-connected component touches the first row."""
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    top = np.unique(labels[0][mask[0]])
    return np.isin(labels, top[top > 0])


def fill_from_neighbours(depth_m: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """``depth_m`` (range, ``inf`` = sky allowed outside the holes) with the ``holes`` pixels interpolated in
    inverse depth by pull–push (module docstring); an interpolated inverse depth of 0 is sky."""
    with np.errstate(divide="ignore"):
        inverse = np.float32(1.0) / depth_m.astype(np.float32)
    filled = pull_push(inverse, ~holes)
    out = depth_m.astype(np.float32, copy=True)
    with np.errstate(divide="ignore"):
        out[holes] = np.float32(1.0) / np.maximum(filled[holes], 0.0)
    return out


def pull_push(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(H, W) float32 ``values`` with the pixels where ``known`` is False interpolated from the known ones
    (Gortler et al. 1996 §3.3); known pixels keep their value exactly. ``known`` must have a True pixel.

    Pull: each coarser cell holds the weighted mean of its 2×2 children and the sum of their weights clamped to 1,
    so a cell with any known child is fully determined by its own children. Push: each level's value is blended
    with the upsampled coarser one by ``1 − weight``: a hole takes the nearest scale that has data, no coarser."""
    x = np.where(known, values, np.float32(0.0)).astype(np.float32, copy=False)
    w = known.astype(np.float32)
    levels = []
    while True:
        levels.append((x, w))
        if w.min() > 0 or max(x.shape) == 1:
            break
        size = ((x.shape[1] + 1) // 2, (x.shape[0] + 1) // 2)
        mean_w = cv2.resize(w, size, interpolation=cv2.INTER_AREA)     # area means over 2×2 cells
        mean_wx = cv2.resize(x if len(levels) == 1 else w * x, size, interpolation=cv2.INTER_AREA)  # w·x = x at 0
        x = mean_wx / np.maximum(mean_w, np.float32(1e-30))
        w = np.minimum(np.float32(4.0) * mean_w, np.float32(1.0))       # Σ child weights, clamped to 1
    estimate = levels[-1][0]
    for x, w in reversed(levels[1:-1]):
        up = cv2.resize(estimate, (x.shape[1], x.shape[0]), interpolation=cv2.INTER_LINEAR)
        estimate = w * x + (np.float32(1.0) - w) * up
    if len(levels) == 1:
        return estimate
    x, _ = levels[0]                                                     # full resolution: weights are 0 or 1
    out = cv2.resize(estimate, (x.shape[1], x.shape[0]), interpolation=cv2.INTER_LINEAR)
    np.copyto(out, x, where=known)
    return out
