"""A COCO panoptic image's ``segments_info`` from its moved panoptic PNG (:mod:`roadview_noise.coco_warp`).

COCO panoptic format (https://cocodataset.org/#format-data, "Panoptic Segmentation"; Cityscapes' and Mapillary
Vistas v2's panoptic files too): each ``annotations`` entry names its image's PNG (``file_name``) and lists its
segments (``segments_info``: ``id``, ``category_id``, ``area``, ``bbox`` [x, y, w, h], ``iscrowd``, …). A pixel of
the 8-bit RGB PNG belongs to segment ``id = R + 256 G + 256² B``; id 0 is void (unlabeled).

The PNG is a mask the recipe declares (``inputs.annotations.masks``): it moves as label images do (nearest
neighbour, every channel of a pixel from one source pixel, so no id is blended; void where the map leaves the
image). From the moved PNG each segment gets its pixel count as ``area`` and the box of its pixels as ``bbox``
(integers, ``w`` = last column − first column + 1, as Cityscapes' ``createPanopticImgs`` and the COCO API's
``toBbox`` write them); a segment with no pixel left is dropped; every other key is kept.
"""

from __future__ import annotations

from pathlib import PurePosixPath

import numpy as np

VOID_ID = 0                        # a pixel of no segment (COCO panoptic: unlabeled)
VOID_FILL = 0                      # the mask fill that makes a pixel from outside the image void: RGB (0, 0, 0)


def png_name(annotation: dict) -> str:
    """The file name of an annotation's panoptic PNG (``file_name``, a name in the file's PNG folder)."""
    name = annotation.get("file_name")
    if not isinstance(name, str) or not name:
        raise ValueError("a panoptic annotation (segments_info) has no file_name of its PNG")
    return PurePosixPath(name).name


def segment_ids(values: np.ndarray, name: str) -> np.ndarray:
    """The segment id of each pixel (H, W) uint32 of a panoptic PNG's values as OpenCV reads them (H, W, 3)
    uint8 in B, G, R order; ValueError for anything else."""
    if values.dtype != np.uint8 or values.ndim != 3 or values.shape[2] != 3:
        raise ValueError(f"the panoptic PNG {name!r} is not 8-bit RGB (values {values.dtype} of shape "
                         f"{values.shape}); COCO panoptic ids are R + 256 G + 256² B")
    v = values.astype(np.uint32)
    return v[..., 2] | (v[..., 1] << 8) | (v[..., 0] << 16)


def moved_segments(segments: list[dict], ids: np.ndarray) -> tuple[list[dict], list]:
    """``segments`` (``segments_info``) with ``area`` and ``bbox`` of their pixels in the segment-id image
    ``ids`` (H, W), and the ids of the segments with no pixel left (dropped). ValueError for a segment without an
    integer ``id`` or an id listed twice. Vectorised: one sorted lookup of every pixel's id among the K segments,
    then per-segment pixel counts and (K, H) / (K, W) occupancy of rows and columns."""
    seg_ids = np.array([_segment_id(s) for s in segments], dtype=np.int64)
    if len(np.unique(seg_ids)) != len(seg_ids):
        raise ValueError("segments_info lists a segment id twice")
    order = np.argsort(seg_ids)
    sorted_ids = seg_ids[order].astype(ids.dtype) if (seg_ids >= 0).all() and (seg_ids < 1 << 24).all() else \
        seg_ids[order]                     # (a PNG's ids: 24 bits; the lookup in the image's own dtype)
    h, w = ids.shape
    flat = ids.ravel() if sorted_ids.dtype == ids.dtype else ids.ravel().astype(np.int64)
    k = np.minimum(np.searchsorted(sorted_ids, flat), max(len(sorted_ids) - 1, 0))
    hit = (sorted_ids[k] == flat) if len(sorted_ids) else np.zeros(flat.shape, bool)
    k, pixel = k[hit], np.flatnonzero(hit)
    area = np.bincount(k, minlength=len(sorted_ids))
    rows = np.zeros((len(sorted_ids), h), bool)
    cols = np.zeros((len(sorted_ids), w), bool)
    rows[k, pixel // w] = True
    cols[k, pixel % w] = True
    kept, dropped = [], []
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    for seg, r in zip(segments, rank):
        if area[r] == 0:
            dropped.append(seg["id"])
            continue
        ys, xs = np.flatnonzero(rows[r]), np.flatnonzero(cols[r])
        box = [int(xs[0]), int(ys[0]), int(xs[-1] - xs[0] + 1), int(ys[-1] - ys[0] + 1)]
        kept.append({**seg, "area": int(area[r]), "bbox": box})
    return kept, dropped


def _segment_id(segment) -> int:
    if not isinstance(segment, dict) or isinstance(segment.get("id"), bool) or \
            not isinstance(segment.get("id"), (int, float)) or float(segment["id"]) != int(segment["id"]):
        raise ValueError(f"a segment of segments_info has no integer id: {segment!r}")
    return int(segment["id"])
