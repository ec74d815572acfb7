"""A "CVAT for images 1.1" XML (one file for a task, ``inputs.annotations.cvat``) through a run, with the plumbing of
COCO files (:class:`roadview_noise.coco.CocoRun`): read once, each image's shapes moved in the worker that ran it,
the file written once after the last image.

The file (CVAT's export format, https://docs.cvat.ai/docs/manual/advanced/xml_format/): ``annotations`` with
``image`` elements (``id``, ``name`` relative to ``cvat_image_root``, ``width``, ``height``) holding shapes whose
coordinates are continuous pixel positions, pixel ``i`` on [i, i + 1] (CVAT's COCO export writes ``xtl, ytl,
xbr − xtl, ybr − ytl`` as the box), written with two decimals:

- ``box`` (``xtl ytl xbr ybr``): the bounding box of its moved outline (edges split where the map bends them, as
  KITTI / COCO boxes), clipped to the image; removed when nothing is left.
- ``polygon`` (``points="x,y;x,y;…"``): moved as COCO polygons (edges split where bent), clipped to the image;
  removed with no area left.
- ``polyline`` and ``points``: point by point, not clipped.
- ``skeleton`` (round 22; before: its image failed under a geometric step): each of its ``points`` children point by
  point, not clipped, as ``points`` shapes; a point moved out of the image gets ``outside="1"`` (CVAT's mark of a
  skeleton point not in the frame), as COCO keypoints leaving the image become "not labelled".
- ``cuboid`` (round 22; before: refused): its eight corners (``xtl1 ytl1 … xbr2 ybr2``) point by point, not clipped.
- ``mask`` (``rle`` run lengths over its box, row by row, starting with a run of 0; ``left top width height``):
  placed in the frame, resampled as label images are (0 where nothing maps) and cut to the box of what is left.
- ``tag``: kept. ``ellipse``: an image that has one fails under a geometric step (named), since a distortion does not
  map an ellipse to an ellipse; a photometric chain copies the file byte for byte.

Every other element and attribute (``meta``, ``attribute`` children, ``occluded``, ``z_order``, ``source`` …) is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import numpy as np

from .coco import CocoRun
from .coco_warp import moving_warps
from .annotations import moved_bitmap
from .errors import InputError
from .io.atomic import write_bytes_atomic
from .physics.outline_warp import clip_polygon, forward_through, moved_boxes, moved_rings

BOX = ("xtl", "ytl", "xbr", "ybr")
CUBOID = tuple(f"{c}{k}" for k in "12" for corner in ("tl", "bl", "tr", "br") for c in (f"x{corner}", f"y{corner}"))
MOVED = ("box", "polygon", "polyline", "points", "mask", "skeleton", "cuboid")
KEPT = ("tag",)


def read_cvat(path: Path) -> bytes:
    """The file's bytes, checked to be a CVAT for images XML (InputError names the file and the problem)."""
    try:
        data = Path(path).read_bytes()
        root = ElementTree.fromstring(data)
    except FileNotFoundError:
        raise InputError("the CVAT file of inputs.annotations.cvat does not exist", file=str(path)) from None
    except OSError as exc:
        raise InputError(f"cannot read the CVAT file: {exc.strerror or exc}", file=str(path)) from None
    except ElementTree.ParseError as exc:
        raise InputError(f"not XML ({exc})", file=str(path)) from None
    if root.tag != "annotations" or any(img.get("name") is None for img in root.iter("image")):
        raise InputError("not a CVAT for images XML: <annotations> with <image name=…> elements", file=str(path))
    if root.find("track") is not None:
        raise InputError("a CVAT for video XML (<track> elements) is not read: export the task as CVAT for images",
                         file=str(path))
    return data


class CvatRun(CocoRun):
    """The CVAT file of a run (module docstring)."""

    KEY = "inputs.annotations.cvat"
    ITEMS = "image elements"
    WHAT = "CVAT shapes"

    def read(self, path: Path) -> bytes:
        return read_cvat(path)

    def images(self, in_root: Path) -> list[tuple[Any, str]]:
        self.elements = list(ElementTree.fromstring(self.data).iter("image"))       # parsed once, read by attach
        return [(i, img.get("name")) for i, img in enumerate(self.elements)]

    def index(self) -> None:
        return None

    def payload(self, pos: int) -> "CvatImage":
        img = self.elements[pos]
        size = tuple(int(float(img.get(k))) if img.get(k) else None for k in ("width", "height"))
        shapes = [(k, s.tag, _skeleton_points(s) if s.tag == "skeleton" else dict(s.attrib))
                  for k, s in enumerate(img) if s.tag not in KEPT]
        return CvatImage(pos, self.names[pos], self.sha256, size, shapes)

    def complete(self, record: dict) -> bool:
        return True                                      # no distortion stated: every record of this file will do

    def output(self, variant: int) -> tuple[Any, dict]:
        from .dataset import output_relpath

        suffix = self.suffixes[variant]
        root = ElementTree.fromstring(self.data)
        done, moved_n, dropped_n = 0, 0, 0
        for pos, img in enumerate(root.iter("image")):
            record = self.records.get((variant, pos))
            if record is None:
                continue
            done += 1
            children = list(img)
            for k, attrs, *inner in record.get("moved", ()):
                children[k].attrib.update(attrs)
                parts = list(children[k])
                for j, part_attrs in inner[0] if inner else ():       # a skeleton's points
                    parts[j].attrib.update(part_attrs)
            for k in sorted((k for k, _ in record.get("dropped", ())), reverse=True):
                img.remove(children[k])
            moved_n, dropped_n = moved_n + len(record.get("moved", ())), dropped_n + len(record.get("dropped", ()))
            if suffix:
                img.set("name", output_relpath(img.get("name"), suffix))
        failed = self.failed.get(variant, [])
        summary = {"format": "cvat", "images": len(self.names), "images_done": done, "images_failed": failed,
                   "images_not_in_run": len(self.names) - done - len(failed), "inputs_not_in_file": self.unlisted,
                   "shapes_moved": moved_n, "shapes_dropped": dropped_n}
        if not moved_n and not dropped_n and not (suffix and done):
            return None, summary
        head = b'<?xml version="1.0" encoding="utf-8"?>\n' if self.data.lstrip().startswith(b"<?xml") else b""
        return head + ElementTree.tostring(root, encoding="utf-8", xml_declaration=False), summary

    def write(self, path: Path, data: bytes) -> None:
        write_bytes_atomic(path, data)


@dataclass
class CvatImage:
    """What a worker needs of one ``image`` element: its position, name, the file's sha256, its stated size and its
    shapes (position among the element's children, tag, attributes; a skeleton's: :func:`_skeleton_points`)."""

    image_id: int
    file_name: str
    sha256: str
    size: tuple[int | None, int | None]
    shapes: list[tuple[int, str, dict]] = field(default_factory=list)

    def panoptic_pngs(self) -> frozenset[str]:
        """None: panoptic PNGs are COCO's (:meth:`roadview_noise.coco_warp.CocoImage.panoptic_pngs`), and ``move``
        reads no ``masks``."""
        return frozenset()

    def move(self, shape: tuple[int, int], warps, masks: dict | None = None) -> dict:
        """The manifest record: ``moved`` [[child position, changed attributes(, [[a skeleton's point position,
        its changed attributes], …])], …], ``dropped`` [[position, tag],
        …]; none when no warp moves anything. InputError for a size that is not the image's, a shape not moved
        under a geometric step, or a malformed one."""
        h, w = shape
        warps = moving_warps("CVAT", self.file_name, self.size, shape, warps)
        record: dict[str, Any] = {"image_id": self.image_id, "sha256": self.sha256}
        if not warps:
            return record
        other = sorted({tag for _, tag, _ in self.shapes if tag not in MOVED})
        if other:
            raise InputError(f"CVAT {', '.join(other)} shapes of {self.file_name!r} are not moved by a geometric step; "
                             "convert them to polygons or boxes, or use a photometric chain")
        try:
            return {**record, **_moved_shapes(self.shapes, warps, w, h)}
        except (ValueError, TypeError, KeyError) as exc:
            raise InputError(f"a shape of {self.file_name!r} in the CVAT file: {exc}") from None


def _skeleton_points(skeleton) -> dict:
    """``{position among the skeleton's children: points attribute}`` of a skeleton element's ``points``."""
    return {j: part.get("points") for j, part in enumerate(skeleton) if part.tag == "points"}


def _points(text: str) -> np.ndarray:
    return np.array([[float(v) for v in p.split(",")] for p in text.split(";")], dtype=np.float64).reshape(-1, 2)


def _text(points: np.ndarray) -> str:
    return ";".join(f"{x:.2f},{y:.2f}" for x, y in np.round(points, 2) + 0.0)


def _moved_mask(attributes: dict, warps, width: int, height: int) -> dict | None:
    """A CVAT mask's ``rle``, ``left``, ``top``, ``width``, ``height`` after the warps (None: nothing left)."""
    x0, y0, w, h = (int(float(attributes[k])) for k in ("left", "top", "width", "height"))
    runs = np.array([int(v) for v in attributes["rle"].split(",")], dtype=np.int64)
    if runs.sum() != w * h:
        raise ValueError(f"mask rle covers {runs.sum()} pixels, its box {w}×{h}")
    moved = moved_bitmap(np.repeat(np.arange(len(runs), dtype=np.uint8) & 1, runs).reshape(h, w), x0, y0, warps,
                         width, height)
    if moved is None:
        return None
    cut, left, top = moved
    flat = cut.ravel()
    runs = np.diff(np.concatenate([[0], np.flatnonzero(np.diff(flat)) + 1, [flat.size]])).tolist()
    return {"rle": ", ".join(map(str, [0] + runs if flat[0] else runs)), "left": str(left), "top": str(top),
            "width": str(cut.shape[1]), "height": str(cut.shape[0])}


def _moved_shapes(shapes: list[tuple[int, str, dict]], warps, width: int, height: int) -> dict:
    """Every box, polygon, polyline, point set, skeleton and cuboid of an image through the warps in one batch
    each."""
    move = lambda xy: forward_through(warps, xy, shift_px=0.5)                          # noqa: E731
    boxes = iter(moved_boxes(np.array([[float(a[k]) for k in BOX] for _, t, a in shapes if t == "box"]).reshape(-1, 4),
                             move))
    rings = iter(moved_rings([_points(a["points"]) for _, t, a in shapes if t == "polygon"], move))
    loose = [part for _, t, a in shapes for part in _point_sets(t, a)]
    lines = iter(np.split(move(np.concatenate(loose)), np.cumsum([len(p) for p in loose])[:-1]) if loose else ())
    moved, dropped = [], []
    for k, tag, attributes in shapes:
        if tag == "box":
            box = np.clip(next(boxes), 0, [width, height, width, height])
            attrs = None if box[2] <= box[0] or box[3] <= box[1] else \
                {key: f"{v:.2f}" for key, v in zip(BOX, np.round(box, 2) + 0.0)}
        elif tag == "mask":
            attrs = _moved_mask(attributes, warps, width, height)
        elif tag == "polygon":
            ring = clip_polygon(next(rings), width, height)
            attrs = None if len(ring) < 3 or np.any(ring.max(axis=0) - ring.min(axis=0) <= 0) else \
                {"points": _text(ring)}
        elif tag == "skeleton":
            attrs = {}, [[j, _skeleton_point(next(lines), width, height)] for j in attributes]
        elif tag == "cuboid":
            attrs = {key: f"{v:.2f}" for key, v in zip(CUBOID, np.round(next(lines), 2).ravel() + 0.0)}
        else:
            attrs = {"points": _text(next(lines))}
        if attrs is None:
            dropped.append([k, tag])
        else:
            moved.append([k, *attrs] if isinstance(attrs, tuple) else [k, attrs])
    return {"moved": moved, "dropped": dropped}


def _point_sets(tag: str, attributes: dict) -> list[np.ndarray]:
    """The point sets of a shape moved point by point, in the order :func:`_moved_shapes` takes them."""
    if tag in ("polyline", "points"):
        return [_points(attributes["points"])]
    if tag == "skeleton":
        return [_points(text) for text in attributes.values()]
    if tag == "cuboid":
        return [np.array([float(attributes[k]) for k in CUBOID]).reshape(-1, 2)]
    return []


def _skeleton_point(point: np.ndarray, width: int, height: int) -> dict:
    """A moved skeleton point's attributes: ``outside="1"`` when it left the image [0, W] × [0, H]."""
    (x, y), = point
    inside = 0 <= x <= width and 0 <= y <= height
    return {"points": _text(point)} if inside else {"points": _text(point), "outside": "1"}
