"""Outlines and boxes moved through a chain's warps: the one mover of COCO polygons and boxes, of KITTI / YOLO
boxes and of YOLO polygons, so an outline over the same pixels moves identically whatever file it came from.

Points move by each warp's forward map in turn (:meth:`~roadview_noise.physics.warp.Warp.forward`). A map that
bends straight lines (lens or windscreen distortion) bends a box's edges, so moving its corners is not enough: an
edge of a closed outline whose moved midpoint lies more than a tolerance (output pixels) off the moved chord is
split, and its parts are judged again, a limited number of times — ``OUTLINE_TOLERANCE_PX`` and ``MAX_SPLITS``
halvings for polygons, whose vertices are written; ``BOX_TOLERANCE_PX`` and ``BOX_MAX_SPLITS`` for boxes, of
which only the bounds are written (a box's edge is cut at once into as many parts as its bend needs). An affine
map bends no edge and adds no point. Where a moved edge bends one way between two points (convex, as radial
distortion bends a straight edge), its greatest distance from their chord is at most twice the midpoint's, so the
moved outline, and the bounding box of a moved box (:func:`moved_boxes`), lie within twice the tolerance of the
exactly moved edge (tests: against 2 000 moved points per edge; 0.02 px for boxes). Near a fold of the map
(beyond the edge of view of a strong negative k1), where the moved edge is arbitrarily steep, no sampling has
such a bound.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

OUTLINE_TOLERANCE_PX = 0.1      # a polygon's moved edge bent further than this from its chord is halved
MAX_SPLITS = 6                  # so an edge becomes at most 2⁶ = 64 segments
BOX_TOLERANCE_PX = 0.01         # the same for a box's outline: only its bounds are written, extra points are free
BOX_MAX_SPLITS = 8              # ≤ 2⁸ = 256 segments
CORNERS = [0, 1, 2, 1, 2, 3, 0, 3]   # a box's outline from x0, y0, x1, y1: (x0, y0), (x1, y0), (x1, y1), (x0, y1)


def forward_through(warps, points_xy: np.ndarray, shift_px: float = 0.0) -> np.ndarray:
    """Output positions (N, 2) of points ``points_xy`` through every warp in turn; ``shift_px`` is the offset of
    the points' coordinates from the warps' (pixel centres on integers): ½ for COCO's pixel ``i`` on [i, i + 1]."""
    q = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2) - shift_px
    for warp in warps if len(q) else ():
        q = warp.forward(q)
    return q + shift_px


def moved_rings(rings: list[np.ndarray], move: Callable[[np.ndarray], np.ndarray], is_box=False) -> list[np.ndarray]:
    """Closed outlines (each N, 2) through ``move`` (points (M, 2) → (M, 2)), all in one batch, their edges split
    where the map bends them (module docstring) to the precision of polygons, or of boxes where ``is_box`` (one
    for all rings, or one per ring)."""
    if not rings:
        return []
    q, ring = _moved_outlines(np.concatenate(rings), np.repeat(np.arange(len(rings)), [len(r) for r in rings]),
                              move, np.broadcast_to(np.asarray(is_box, dtype=bool), (len(rings),)))
    return np.split(q, np.cumsum(np.bincount(ring, minlength=len(rings)))[:-1])


def box_ring(box_xyxy) -> np.ndarray:
    """The outline (4, 2) of a box x0, y0, x1, y1: corners (x0, y0), (x1, y0), (x1, y1), (x0, y1)."""
    return np.asarray(box_xyxy, dtype=np.float64)[CORNERS].reshape(4, 2)


def moved_boxes(boxes_xyxy: np.ndarray, move: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Boxes (N, 4) x0, y0, x1, y1 through ``move``: the bounding box (N, 4) of each box's moved outline (edges
    split where the map bends them further than ``BOX_TOLERANCE_PX``), not clipped."""
    b = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    if not len(b):
        return b.copy()
    q, ring = _moved_outlines(b[:, CORNERS].reshape(-1, 2), np.repeat(np.arange(len(b)), 4), move,
                              np.ones(len(b), dtype=bool))
    starts = np.flatnonzero(np.r_[True, ring[1:] != ring[:-1]])
    return np.concatenate([np.minimum.reduceat(q, starts), np.maximum.reduceat(q, starts)], axis=1)


def clip_polygon(poly: np.ndarray, width: float, height: float, origin_px: float = 0.0) -> np.ndarray:
    """A polygon (N, 2) clipped to the image ``[o, o + width] × [o, o + height]``, ``o = origin_px`` (0 for COCO's
    pixel edges, −½ for pixel-centre coordinates; Sutherland–Hodgman, one image edge at a time)."""
    lo, hi = origin_px, (origin_px + float(width), origin_px + float(height))
    if len(poly) and poly.min() >= lo and poly[:, 0].max() <= hi[0] and poly[:, 1].max() <= hi[1]:
        return poly
    for axis, bound, sign in ((0, lo, 1.0), (0, hi[0], -1.0), (1, lo, 1.0), (1, hi[1], -1.0)):
        if len(poly) == 0:
            break
        nxt = np.roll(poly, -1, axis=0)
        d0, d1 = sign * (poly[:, axis] - bound), sign * (nxt[:, axis] - bound)
        in0, in1 = d0 >= 0, d1 >= 0
        cross = in0 != in1
        t = np.where(cross, d0 / np.where(cross, d0 - d1, 1.0), 0.0)
        hit = poly + t[:, None] * (nxt - poly)
        hit[:, axis] = bound
        poly = np.stack([poly, hit], axis=1).reshape(-1, 2)[np.stack([in0, cross], axis=1).ravel()]
    return poly


def _moved_outlines(p: np.ndarray, ring: np.ndarray, move, is_box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 2) of closed outlines (grouped by ``ring``, in order) moved, with points added on bent edges (box
    or polygon precision per ring); returns the moved points and their ring.

    One ``move`` call per round: the points a split adds and the midpoints of the new segments, which decide the
    next round. A polygon's bent edge is halved; a box's edge is cut at once into the 2^s segments that leave a
    bend like this one (∝ length²) within the tolerance, 4^s ≥ bend / tolerance, saving rounds."""
    p = np.asarray(p, dtype=np.float64)
    tolerance_px = np.where(is_box, BOX_TOLERANCE_PX, OUTLINE_TOLERANCE_PX)
    cap = np.where(is_box, BOX_MAX_SPLITS, MAX_SPLITS)
    nxt = _next_in_ring(ring)
    both = move(np.concatenate([p, (p + p[nxt]) / 2]))
    q, mid_q = both[: len(p)], both[len(p):]                 # mid_q: the moved midpoint of the edge to the next point
    depth = np.zeros(len(p), dtype=np.intp)                   # splits that made the edge from each point
    pending = cap[ring] > 0                                   # edges whose moved midpoint is yet to be judged
    while pending.any():
        e = np.flatnonzero(pending)
        chord, off = q[nxt[e]] - q[e], mid_q[e] - q[e]
        length = np.hypot(chord[:, 0], chord[:, 1])
        cross = np.abs(chord[:, 0] * off[:, 1] - chord[:, 1] * off[:, 0])
        bent = np.where(length > 0, cross / np.maximum(length, 1e-300), np.hypot(off[:, 0], off[:, 1]))
        over = bent > tolerance_px[ring[e]]
        s = e[over]
        if not len(s):
            break
        room = cap[ring[s]] - depth[s]
        levels = np.where(is_box[ring[s]], np.ceil(np.log(bent[over] / tolerance_px[ring[s]]) / np.log(4)), 1)
        levels = np.clip(levels, 1, room).astype(np.intp)
        m = 1 << levels                                       # segments each split edge becomes
        grp = np.repeat(np.arange(len(s)), 2 * m - 1)         # per split edge: 2m − 1 points at t = k / (2m)
        k = np.arange(len(grp)) - np.repeat(np.cumsum(2 * m - 1) - (2 * m - 1), 2 * m - 1) + 1
        a, b = p[s][grp], p[nxt[s]][grp]
        t = (k / (2 * m[grp]))[:, None]
        new_p = a + t * (b - a)
        is_mid = k == m[grp]                                  # the old midpoint: already moved
        new_q = np.empty_like(new_p)
        new_q[~is_mid] = move(new_p[~is_mid])
        new_q[is_mid] = mid_q[s]
        vertex = k % 2 == 0
        first_mid = k == 1                                    # the midpoint of the split point's first segment
        mid_q[s] = new_q[first_mid]
        depth[s] += levels
        pending[:] = False
        pending[s] = depth[s] < cap[ring[s]]
        vg = grp[vertex]
        key = np.concatenate([np.arange(len(p)), s[vg] + k[vertex] / (2 * m[vg])])
        order = np.argsort(key, kind="stable")
        p = np.concatenate([p, new_p[vertex]])[order]
        q = np.concatenate([q, new_q[vertex]])[order]
        ring = np.concatenate([ring, ring[s][vg]])[order]
        mid_q = np.concatenate([mid_q, new_q[np.flatnonzero(vertex) + 1]])[order]
        depth = np.concatenate([depth, depth[s][vg]])[order]
        pending = np.concatenate([pending, pending[s][vg]])[order]
        nxt = _next_in_ring(ring)
    return q, ring


def _next_in_ring(ring: np.ndarray) -> np.ndarray:
    """Index of each point's successor in its closed ring (points grouped by ring, in order)."""
    nxt = np.arange(1, len(ring) + 1)
    change = ring[1:] != ring[:-1]
    last = np.append(change, True)
    nxt[last] = np.flatnonzero(np.insert(change, 0, True))
    return nxt
