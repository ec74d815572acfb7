"""One image's COCO annotations through the warps of the chain's geometric steps (in the worker that ran it).

The same :class:`~roadview_noise.physics.warp.Warp` that resampled the image moves its annotations
(:meth:`Warp.forward`, the model's exact inverse where it has one); photometric chains have no warps and leave the
annotations as read, value for value, as does a warp that is exactly the identity. COCO coordinates put pixel
``i`` on [i, i + 1], the warps pixel centres on integers: points are shifted by ½ px into the warp and back.

- Polygons: each vertex moves; an edge the warps bend is split (:mod:`roadview_noise.physics.outline_warp`, the
  mover of KITTI / YOLO boxes too: split while the moved midpoint lies more than 0.1 px off the moved chord, ≤ 64
  segments per edge), so the polygon follows the bent outline and an affine warp adds no vertex. The moved
  polygon is clipped to the image (Sutherland–Hodgman); a part with nothing left is removed.
- RLE masks (compressed string or uncompressed counts, as read): decoded, resampled nearest-neighbour through the
  warps like label images (0 where the map leaves the image), encoded in the same kind.
- ``bbox``: a box that was the segmentation's box (within 1 px) becomes the moved segmentation's box; any other
  box (no segmentation; an amodal or projected 3-D box) moves as its outline, exactly as KITTI / YOLO boxes do
  (edges split as above, at 0.01 px: only the box's bounds are written) and becomes the box of the moved outline;
  clipped to the image.
- ``area``: scaled by the change of the segmentation's own measure (polygon area, mask pixel count, else box area),
  so an area that was COCO's mask pixel count or mmdetection3d's w·h stays so; mask pixel count exactly for RLE.
- ``keypoints``: labelled points (v > 0) move; one that leaves the image becomes (0, 0, 0), COCO's "not labelled",
  and ``num_keypoints`` is recounted. mmdetection3d's ``center2d`` [u, v, depth] moves (not clipped: a truncated
  object's centre lies outside the image).
- An annotation that had something inside the image and has nothing left (its box clipped to nothing, its polygons
  or mask empty) is dropped: the object is not in the output image. Its id is recorded.
- COCO panoptic (``segments_info``): the image's panoptic PNG, a declared mask moved with the frame, gives each
  segment's ``area`` and ``bbox`` (:mod:`roadview_noise.coco_panoptic`); segments with no pixel left are dropped
  from ``segments_info`` and their ids recorded.

Coordinates written are rounded to ``DECIMALS`` places (1/1000 px).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import coco_camera, coco_panoptic
from .errors import InputError
from .io import coco as coco_io
from .physics.outline_warp import box_ring, clip_polygon, forward_through, moved_rings
from .physics.warp import moving

DECIMALS = 3
SEGMENTATION_BOX_PX = 1.0       # a bbox within this of the segmentation's box is that box
GEOMETRY_KEYS = ("id", "bbox", "segmentation", "area", "keypoints", "num_keypoints", "center2d", "segments_info",
                 "file_name")


@dataclass
class CocoImage:
    """What a worker needs of one image of a COCO file: its record and its annotations' geometry, each with its
    position in the file's ``annotations`` list."""

    image_id: Any
    file_name: str
    width: int | None
    height: int | None
    sha256: str                                    # of the COCO file (a resumed run redoes records of another one)
    annotations: list[tuple[int, dict]] = field(default_factory=list)

    def move(self, shape: tuple[int, int], warps, masks: dict | None = None) -> dict:
        return move_image(self, shape, warps, masks)

    def panoptic_pngs(self) -> frozenset[str]:
        """The file names of the image's panoptic PNGs (masks that get the void fill, :mod:`.coco_panoptic`)."""
        return frozenset(str(ann["file_name"]).rsplit("/", 1)[-1] for _, ann in self.annotations
                         if "segments_info" in ann and ann.get("file_name"))


def move_image(image: CocoImage, shape: tuple[int, int], warps, masks: dict | None = None) -> dict:
    """The manifest record of one image: ``moved`` [[position, changed fields], …], ``dropped`` [[position, id],
    …], ``segments_dropped`` [[position, [segment id, …]], …] (panoptic) and ``distortion`` (the warps as
    :mod:`.coco_camera` states them); none when nothing moves. ``masks``: the frame's masks after the warps
    (values by path), where a panoptic annotation finds its PNG. InputError when the file's size of the image is
    not the image's, an annotation is malformed (naming its id) or a panoptic PNG is not a declared mask. Every
    outline and point of the image moves in one batch."""
    h, w = shape
    warps = moving_warps("COCO", image.file_name, (image.width, image.height), shape, warps)
    record: dict[str, Any] = {"image_id": image.image_id, "sha256": image.sha256}
    if not warps:
        return record
    record["distortion"] = coco_camera.steps(warps)          # the image is no longer pinhole (coco_camera)
    mover = _Mover(warps, w, h)
    panoptic = [(pos, ann) for pos, ann in image.annotations if "segments_info" in ann]
    others = [(pos, ann) for pos, ann in image.annotations if "segments_info" not in ann]
    parsed = []
    for _, ann in others:
        parsed.append(_guarded(ann, image.file_name, _Parsed.of, ann))
    rings = moved_rings([r for g in parsed for r in g.rings_in()], mover.points,
                        [b for g in parsed for b in g.ring_is_box()])
    points = mover.points(np.concatenate([g.points for g in parsed]) if parsed else np.empty((0, 2)))
    moved, dropped, segments_dropped = [], [], []
    for pos, ann in panoptic:
        kept, gone = _moved_panoptic(ann, image.file_name, masks or {})
        moved.append([pos, {"segments_info": kept}])
        if gone:
            segments_dropped.append([pos, gone])
    for (pos, ann), g in zip(others, parsed):
        n = len(g.rings_in())
        g.rings_out, rings = rings[:n], rings[n:]
        g.points_out, points = points[:len(g.points)], points[len(g.points):]
        fields = _guarded(ann, image.file_name, mover.annotation, ann, g)
        if fields is None:
            dropped.append([pos, ann.get("id")])
        elif fields:
            moved.append([pos, fields])
    moved.sort(key=lambda m: m[0])
    return {**record, "moved": moved, "dropped": dropped,
            **({"segments_dropped": segments_dropped} if panoptic else {})}


def _moved_panoptic(ann: dict, image_name: str, masks: dict) -> tuple[list[dict], list]:
    """A panoptic annotation's ``segments_info`` from its moved PNG among ``masks`` (by file name), and the ids of
    the segments dropped; InputError when the PNG is not exactly one declared mask, or the annotation or PNG is
    malformed."""
    try:
        name = coco_panoptic.png_name(ann)
    except ValueError as exc:
        raise InputError(f"{exc} ({image_name!r})") from None
    found = [rel for rel in masks if rel.rsplit("/", 1)[-1] == name]
    if len(found) != 1:
        why = "is not among the masks the recipe declares" if not found else \
            f"matches {len(found)} declared masks ({', '.join(sorted(found))})"
        raise InputError(f"the COCO panoptic PNG {name!r} of {image_name!r} {why}: a geometric step moves the PNG "
                         "and its segments' bbox and area are taken from it; declare the panoptic PNGs once under "
                         "inputs.annotations.masks (e.g. \"../annotations/panoptic_val2017/{stem}.png\")")
    try:
        return coco_panoptic.moved_segments(ann["segments_info"], coco_panoptic.segment_ids(masks[found[0]], name))
    except (ValueError, TypeError) as exc:
        raise InputError(f"the COCO panoptic annotation of {image_name!r} ({name}): {exc}") from None


def moving_warps(kind: str, file_name: str, stated: tuple, shape: tuple[int, int], warps) -> list:
    """The warps that move anything (all but exact identities); InputError when the ``kind`` file states another
    size (W, H) for the image than its ``shape`` (H, W)."""
    h, w = shape
    if tuple(stated) != (None, None) and tuple(stated) != (w, h):
        raise InputError(f"the {kind} file gives {file_name!r} {stated[0]}×{stated[1]} px, the image is {w}×{h} px")
    return moving(warps)


def _guarded(ann: dict, name: str, fn, *args):
    try:
        return fn(*args)
    except (ValueError, TypeError, KeyError, IndexError) as exc:
        raise InputError(f"annotation id {ann.get('id')!r} of {name!r}: {exc}") from None


@dataclass
class _Parsed:
    """One annotation's outlines and points in COCO coordinates (polygon parts, box corners; labelled keypoints,
    then ``center2d``), and after the batch their moved versions."""

    polygons: list[np.ndarray]
    corners: np.ndarray | None
    points: np.ndarray
    rings_out: list[np.ndarray] = field(default_factory=list)
    points_out: np.ndarray | None = None

    @classmethod
    def of(cls, ann: dict) -> "_Parsed":
        seg = ann.get("segmentation")
        polygons = [_ring(p) for p in seg] if isinstance(seg, list) else []
        corners = None
        if ann.get("bbox") is not None:
            corners = box_ring(_xyxy(ann["bbox"]))
        points = [np.empty((0, 2))]
        if ann.get("keypoints"):
            kp = np.asarray(ann["keypoints"], dtype=np.float64).reshape(-1, 3)
            points.append(kp[kp[:, 2] > 0, :2])
        if ann.get("center2d") is not None and len(ann["center2d"]) >= 2:
            points.append(np.asarray(ann["center2d"][:2], dtype=np.float64).reshape(1, 2))
        return cls(polygons, corners, np.concatenate(points))

    def rings_in(self) -> list[np.ndarray]:
        return self.polygons + ([self.corners] if self.corners is not None else [])

    def ring_is_box(self) -> list[bool]:
        return [False] * len(self.polygons) + ([True] if self.corners is not None else [])


class _Mover:
    """Moves annotations through a chain's warps into an image of ``width`` × ``height`` px."""

    def __init__(self, warps, width: int, height: int):
        self.warps, self.width, self.height = warps, width, height

    def points(self, xy: np.ndarray) -> np.ndarray:
        """COCO positions (N, 2) through every warp."""
        return forward_through(self.warps, xy, shift_px=0.5)

    def annotation(self, ann: dict, g: _Parsed) -> dict | None:
        """The changed fields of one annotation, or None to drop it (module docstring)."""
        out: dict[str, Any] = {}
        seg = ann.get("segmentation")
        box_in = _xyxy(ann["bbox"]) if g.corners is not None else None
        seg_in = seg_out = None                                   # (x0, y0, x1, y1) of the segmentation
        measure_in = measure_out = None
        if coco_io.is_rle(seg):
            if coco_io.rle_size(seg) != (self.height, self.width):
                raise ValueError(f"RLE size {seg.get('size')} is not the image's [{self.height}, {self.width}]")
            mask = coco_io.rle_decode(seg)
            seg_in, measure_in = _mask_box(mask), float(mask.sum())
            for warp in self.warps:
                mask = warp.apply_labels(mask, 0)
            seg_out, measure_out = _mask_box(mask), float(mask.sum())
            out["segmentation"] = coco_io.rle_encode(mask, compressed=not isinstance(seg["counts"], list))
        elif g.polygons:
            moved = [clip_polygon(m, self.width, self.height) for m in g.rings_out[:len(g.polygons)]]
            moved = [m for m in moved if len(m) >= 3 and shoelace(m) > 0]
            seg_in, measure_in = _bounds(g.polygons), sum(shoelace(r) for r in g.polygons)
            seg_out, measure_out = _bounds(moved), sum(shoelace(m) for m in moved)
            out["segmentation"] = [_rounded(m).ravel().tolist() for m in moved]
        if box_in is not None:
            if seg_in is not None and np.max(np.abs(np.subtract(box_in, seg_in))) <= SEGMENTATION_BOX_PX:
                box_out = seg_out
            else:
                box_out = _clip_box(_bounds(g.rings_out[-1:]), self.width, self.height)
            if seg_in is None:
                measure_in, measure_out = _box_area(box_in), _box_area(box_out)
            out["bbox"] = _rounded(np.array(_xywh(box_out))).tolist() if box_out is not None else [0.0, 0.0, 0.0, 0.0]
            if self._was_visible(box_in) and (box_out is None or _box_area(box_out) <= 0):
                return None
        if seg_in is not None and measure_in > 0 and measure_out == 0:
            return None
        if ann.get("area") is not None and measure_in is not None:
            out["area"] = _area(ann["area"], measure_in, measure_out, rle=coco_io.is_rle(seg))
        points = g.points_out
        if ann.get("keypoints"):
            kp = np.asarray(ann["keypoints"], dtype=np.float64).reshape(-1, 3)
            n = int((kp[:, 2] > 0).sum())
            out.update(self.keypoints(kp, points[:n], "num_keypoints" in ann))
            points = points[n:]
        if len(points):
            out["center2d"] = _rounded(points[0]).tolist() + list(ann["center2d"][2:])
        return out

    def keypoints(self, kp: np.ndarray, xy: np.ndarray, count: bool) -> dict:
        """Keypoints (K, 3) with the labelled ones at ``xy``; one outside the image becomes (0, 0, 0)."""
        labelled = kp[:, 2] > 0
        inside = (xy[:, 0] >= 0) & (xy[:, 0] < self.width) & (xy[:, 1] >= 0) & (xy[:, 1] < self.height)
        new = kp.copy()
        new[labelled, :2] = np.where(inside[:, None], _rounded(xy), 0.0)
        new[np.flatnonzero(labelled)[~inside]] = 0.0
        flat = [v if i % 3 < 2 else int(v) for i, v in enumerate(new.ravel().tolist())]
        out: dict[str, Any] = {"keypoints": flat}
        if count:
            out["num_keypoints"] = int((new[:, 2] > 0).sum())
        return out

    def _was_visible(self, box) -> bool:
        clipped = _clip_box(box, self.width, self.height)
        return clipped is not None and _box_area(clipped) > 0


# --- outlines and polygons -----------------------------------------------------------------------------------------


def shoelace(poly: np.ndarray) -> float:
    """Area of a simple polygon (N, 2), px²."""
    x, y = poly[:, 0], poly[:, 1]
    return float(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2)


def _ring(flat: list) -> np.ndarray:
    if len(flat) < 6 or len(flat) % 2:
        raise ValueError(f"a polygon has {len(flat)} values; COCO polygons have x, y pairs, at least 3")
    return np.asarray(flat, dtype=np.float64).reshape(-1, 2)


# --- boxes ---------------------------------------------------------------------------------------------------------


def _xyxy(bbox) -> tuple[float, float, float, float]:
    x, y, w, h = (float(v) for v in bbox)
    return x, y, x + w, y + h


def _xywh(box) -> list[float]:
    x0, y0, x1, y1 = box
    return [x0, y0, x1 - x0, y1 - y0]


def _bounds(polys: list[np.ndarray]):
    polys = [p for p in polys if len(p)]
    if not polys:
        return None
    allp = np.concatenate(polys)
    (x0, y0), (x1, y1) = allp.min(axis=0), allp.max(axis=0)
    return float(x0), float(y0), float(x1), float(y1)


def _clip_box(box, width: int, height: int):
    if box is None:
        return None
    x0, y0, x1, y1 = box
    x0, x1 = min(max(x0, 0.0), width), min(max(x1, 0.0), width)
    y0, y1 = min(max(y0, 0.0), height), min(max(y1, 0.0), height)
    return x0, y0, x1, y1


def _box_area(box) -> float:
    return 0.0 if box is None else max(box[2] - box[0], 0.0) * max(box[3] - box[1], 0.0)


def _mask_box(mask: np.ndarray):
    """(x0, y0, x1, y1) of a mask's pixels in COCO coordinates, None when empty."""
    cols, rows = np.flatnonzero(mask.any(axis=0)), np.flatnonzero(mask.any(axis=1))
    if not len(cols):
        return None
    return float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)


def _area(area_in, measure_in: float, measure_out: float, *, rle: bool):
    if rle or measure_in <= 0:
        new = measure_out
    else:
        new = float(area_in) * measure_out / measure_in
    return int(round(new)) if isinstance(area_in, int) else round(new, DECIMALS)


def _rounded(a: np.ndarray) -> np.ndarray:
    return np.round(a, DECIMALS) + 0.0                       # + 0.0: no −0.0 in the file
