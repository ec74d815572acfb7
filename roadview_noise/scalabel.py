"""A Scalabel-format label file (BDD100K's per-split JSON, ``inputs.annotations.scalabel``) through a run: read once
by the runner, each image's labels sent with its task and moved in the worker, the file assembled and written once
at the end of the run — the plumbing of COCO files (:class:`roadview_noise.coco.CocoRun`).

The file (https://doc.bdd100k.com/format.html, Scalabel's ``Frame`` list): a list of frames, or ``{"frames": […],
"config": …}``; each frame ``name`` (the image, relative to ``scalabel_image_root``, else, when that is no file,
to ``scalabel_image_root/<videoName>``; BDD100K's tracking sets), ``labels`` (a list, or null) with ``id``,
``category``, ``attributes`` … and the geometry:

- ``box2d`` ``{x1, y1, x2, y2}``: pixel positions of the first and last pixel (Scalabel converts it to COCO with
  w = x2 − x1 + 1), moved as KITTI boxes are (:func:`roadview_noise.annotations.warp_boxes`: the bounding box of the
  moved outline, edges split where the map bends them, clipped to 0 … W − 1); dropped when nothing is left.
- ``poly2d`` ``[{vertices: [[x, y], …], types: "LLCC…", closed}]`` (drivable area, lanes, segmentation; pixel
  centres on integers): a closed polygon of straight edges (types all ``L``) moves as Cityscapes polygons do
  (edges split where bent, clipped to the image, types ``L`` for each vertex, a polygon left with no area
  removed); an open polyline (a lane) or one with Bézier control points (``C``) moves vertex by vertex, not clipped
  (a Bézier's control points through the map: exact for an affine map, close for a mild distortion), its types kept.

- ``rle`` ``{counts, size}`` (BDD100K's instance and panoptic segmentation, COCO's compressed RLE): decoded,
  resampled through the map as label images are (0 where nothing maps), encoded again; removed when empty.
- ``graph`` (BDD100K pose keypoints: ``nodes`` with a ``location`` [x, y], ``category``, ``visibility``): each
  node's location moves point by point, not clipped, as a polyline's vertices (round 22; before: the frame failed
  under a geometric step); ``visibility`` and the ``edges`` are kept. A 3-D location (x, y, z) is kept.
  ``box3d`` (camera coordinates, metres) is kept, as COCO's ``bbox_cam3d``.

A label that had geometry and has none left is dropped (its id recorded in the manifest, as COCO's). Every other key
of the file, the frames and the labels is kept as read; the output is compact UTF-8 JSON (the input's bytes when no
label moved), coordinates to 1/1000 px.
"""

from __future__ import annotations

import posixpath
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .coco import CocoRun
from .coco_warp import DECIMALS, moving_warps
from .dataset import output_relpath
from .errors import InputError
from .io import coco as coco_io
from .physics.outline_warp import clip_polygon, forward_through, moved_boxes, moved_rings

BOX_KEYS = ("x1", "y1", "x2", "y2")
GEOMETRY = ("box2d", "poly2d", "rle", "graph")          # label keys in image coordinates (module docstring)


def read_scalabel(path: Path):
    """The parsed file; InputError names the file and the first frame or label that is not Scalabel's."""
    data = coco_io.read_dataset_json(path, "Scalabel", "scalabel")
    frames = data.get("frames") if isinstance(data, dict) else data
    if not isinstance(frames, list):
        raise InputError("not a Scalabel / BDD100K label file: neither a list of frames nor {\"frames\": [...]} "
                         "(a COCO file goes under annotations.coco)", file=str(path))
    for i, frame in enumerate(frames):
        try:
            if not isinstance(frame, dict) or not isinstance(frame.get("name"), str):
                raise ValueError("has no 'name'")
            for j, label in enumerate(frame.get("labels") or []):
                _check_label(label, f"labels[{j}]")
        except (ValueError, TypeError) as exc:
            raise InputError(f"frames[{i}] {exc}", file=str(path)) from None
    return data


def _check_label(label, where: str) -> None:
    if not isinstance(label, dict):
        raise ValueError(f"{where} is not an object")
    box = label.get("box2d")
    if box is not None and not all(isinstance(box.get(k), (int, float)) for k in BOX_KEYS):
        raise ValueError(f"{where}.box2d is not {{x1, y1, x2, y2}}")
    for k, poly in enumerate(label.get("poly2d") or []):
        vertices = poly.get("vertices") if isinstance(poly, dict) else None
        if np.asarray(vertices, dtype=float).reshape(-1, 2).shape[0] != len(vertices or ()) or \
                not isinstance(poly.get("types", ""), str):
            raise ValueError(f"{where}.poly2d[{k}] has no [[x, y], …] vertices with their types")


class ScalabelRun(CocoRun):
    """The Scalabel / BDD100K file of a run (module docstring)."""

    KEY = "inputs.annotations.scalabel"
    ITEMS = "frames"
    WHAT = "Scalabel labels"

    def read(self, path: Path):
        return read_scalabel(path)

    @property
    def frames(self) -> list[dict]:
        return self.data["frames"] if isinstance(self.data, dict) else self.data

    def images(self, in_root: Path) -> list[tuple[Any, str]]:
        out = []
        for i, frame in enumerate(self.frames):
            name = frame["name"]
            video = frame.get("videoName")
            if isinstance(video, str) and video and \
                    not (in_root / posixpath.join(self.image_root, name)).is_file() and \
                    (in_root / posixpath.join(self.image_root, video, name)).is_file():
                name = posixpath.join(video, name)
            out.append((i, name))
        return out

    def index(self) -> None:
        return None

    def payload(self, pos: int) -> "ScalabelImage":
        labels = self.frames[pos].get("labels") or []
        return ScalabelImage(pos, self.names[pos], self.sha256,
                             [(j, {k: lab[k] for k in ("id", *GEOMETRY) if lab.get(k) is not None})
                              for j, lab in enumerate(labels) if any(lab.get(k) for k in GEOMETRY)])

    def complete(self, record: dict) -> bool:
        return True                                      # no distortion stated: every record of this file will do

    def output(self, variant: int) -> tuple[Any, dict]:
        suffix = self.suffixes[variant]
        frames, done, moved_n, dropped_ids = list(self.frames), 0, 0, []
        for pos, frame in enumerate(frames):
            record = self.records.get((variant, pos))
            if record is None:
                continue
            done += 1
            moved = {p: f for p, f in record.get("moved", ())}
            dropped = {p for p, _ in record.get("dropped", ())}
            moved_n += len(moved)
            dropped_ids += [i for _, i in record.get("dropped", ())]
            if moved or dropped:
                frame = {**frame, "labels": [{**lab, **moved[j]} if j in moved else lab
                                             for j, lab in enumerate(frame.get("labels") or []) if j not in dropped]}
            if suffix:
                frame = {**frame, "name": output_relpath(frame["name"], suffix)}
            frames[pos] = frame
        failed = self.failed.get(variant, [])
        summary = {"format": "scalabel", "frames": len(frames), "frames_done": done, "frames_failed": failed,
                   "frames_not_in_run": len(frames) - done - len(failed), "inputs_not_in_file": self.unlisted,
                   "labels_moved": moved_n, "labels_dropped": dropped_ids}
        if not moved_n and not dropped_ids and not (suffix and done):
            return None, summary
        return ({**self.data, "frames": frames} if isinstance(self.data, dict) else frames), summary


@dataclass
class ScalabelImage:
    """What a worker needs of one frame: its position, name, the file's sha256, and its labels' geometry with
    their positions in the frame's ``labels``."""

    image_id: int
    file_name: str
    sha256: str
    labels: list[tuple[int, dict]] = field(default_factory=list)

    def panoptic_pngs(self) -> frozenset[str]:
        """None: panoptic PNGs are COCO's (:meth:`roadview_noise.coco_warp.CocoImage.panoptic_pngs`), and ``move``
        reads no ``masks``."""
        return frozenset()

    def move(self, shape: tuple[int, int], warps, masks: dict | None = None) -> dict:
        """The manifest record: ``moved`` [[label position, changed fields], …], ``dropped`` [[position, id], …];
        none when no warp moves anything. InputError names the frame when a label is malformed."""
        h, w = shape
        warps = moving_warps("Scalabel", self.file_name, (None, None), shape, warps)
        record: dict[str, Any] = {"image_id": self.image_id, "sha256": self.sha256}
        if not warps:
            return record
        try:
            return {**record, **_moved_labels(self.labels, warps, w, h)}
        except (ValueError, TypeError, KeyError) as exc:
            raise InputError(f"a label of frame {self.file_name!r}: {exc}") from None


def _straight_closed(poly: dict) -> bool:
    return bool(poly.get("closed")) and set(poly.get("types", "")) <= {"L"}


def _moved_labels(labels: list[tuple[int, dict]], warps, width: int, height: int) -> dict:
    """Every box, closed polygon, polyline and pose graph of a frame through the warps in one batch each (module
    docstring)."""
    move = lambda xy: forward_through(warps, xy)                                        # noqa: E731
    boxes = [lab["box2d"] for _, lab in labels if "box2d" in lab]
    moved_box = iter(moved_boxes(np.array([[float(b[k]) for k in BOX_KEYS] for b in boxes]).reshape(-1, 4), move))
    polys = [p for _, lab in labels for p in lab.get("poly2d", ())]
    rings = [np.asarray(p["vertices"], dtype=float).reshape(-1, 2) for p in polys if _straight_closed(p)]
    moved_ring = iter(moved_rings(rings, move))
    lines = [part for _, lab in labels for part in _point_sets(lab)]
    moved_line = iter(np.split(move(np.concatenate(lines)), np.cumsum([len(v) for v in lines])[:-1])
                      if lines else ())
    moved, dropped = [], []
    for pos, lab in labels:
        fields, kept = {}, 0
        if "box2d" in lab:
            (x1, y1), (x2, y2) = np.clip(next(moved_box).reshape(2, 2), 0, [width - 1, height - 1])
            if x2 > x1 and y2 > y1:
                kept += 1
            fields["box2d"] = {**lab["box2d"], **dict(zip(BOX_KEYS, _rounded([x1, y1, x2, y2])))}
        if "poly2d" in lab:
            out = []
            for poly in lab["poly2d"]:
                if _straight_closed(poly):
                    ring = clip_polygon(next(moved_ring), width, height, origin_px=-0.5)
                    if len(ring) < 3 or np.any(ring.max(axis=0) - ring.min(axis=0) <= 0):
                        continue
                    out.append({**poly, "vertices": _rounded(ring), "types": "L" * len(ring)})
                else:
                    out.append({**poly, "vertices": _rounded(next(moved_line))})
            kept += len(out)
            fields["poly2d"] = out
        if "graph" in lab:
            nodes = [{**n, "location": _rounded(next(moved_line)[0])} if _flat(n) else n
                     for n in lab["graph"].get("nodes", ())]
            kept += 1
            fields["graph"] = {**lab["graph"], "nodes": nodes}
        if "rle" in lab:
            mask = coco_io.rle_decode(lab["rle"])
            if mask.shape != (height, width):
                raise ValueError(f"rle size {lab['rle'].get('size')} is not the image's [{height}, {width}]")
            for warp in warps:
                mask = warp.apply_labels(mask, 0)
            kept += bool(mask.any())
            fields["rle"] = {**lab["rle"], **coco_io.rle_encode(mask, compressed=not isinstance(lab["rle"]["counts"],
                                                                                                list))}
        if kept:
            moved.append([pos, fields])
        else:
            dropped.append([pos, lab.get("id")])
    return {"moved": moved, "dropped": dropped}


def _point_sets(label: dict) -> list[np.ndarray]:
    """A label's parts moved point by point, in the order :func:`_moved_labels` takes them: its open or curved
    ``poly2d`` vertices, then its graph's 2-D node locations (one point each)."""
    return [np.asarray(p["vertices"], dtype=float).reshape(-1, 2) for p in label.get("poly2d", ())
            if not _straight_closed(p)] + \
        [np.asarray(n["location"], dtype=float).reshape(1, 2) for n in label.get("graph", {}).get("nodes", ())
         if _flat(n)]


def _flat(node: dict) -> bool:
    """A graph node in image coordinates (a 2-D location; a 3-D one is in camera space)."""
    return len(node["location"]) == 2


def _rounded(a) -> list:
    return (np.round(np.asarray(a, dtype=float), DECIMALS) + 0.0).tolist()       # + 0.0: no −0.0 in the file
