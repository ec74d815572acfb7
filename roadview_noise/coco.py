"""A COCO-format dataset file (``inputs.annotations.coco``) through a run: read once by the runner, each image's
annotations sent with its task, moved in the worker (:mod:`roadview_noise.coco_warp`), assembled and written once
at the end of the run.

- ``coco``: the JSON's path relative to IN (inside IN). ``coco_image_root``: the folder, relative to IN, that the
  images' ``file_name`` is relative to; by default the JSON's folder (mmdetection3d: ``kitti/kitti_infos_*.coco.json``
  with ``training/image_2/000007.png``). COCO's own layout (``annotations/instances_val2017.json``, images in
  ``val2017/``) says ``coco_image_root: val2017``. The run refuses to start when no ``file_name`` resolves to a file,
  and warns with a count and an example for file names that do not, and for images of the run with no record.
- An image that a geometric step moved gets ``rv_distortion`` in its ``images`` entry (:mod:`.coco_camera`).
- Each output image's manifest entry records its annotations' moves (``coco``: changed fields by position in the
  file's ``annotations``, dropped ones with their id), so a resumed run rebuilds the file from kept entries too.
- After the last image the file is written to OUT at the same relative path (a sweep variant's suffix before its
  suffix, its images' ``file_name`` with that variant's suffix), atomically, with its own manifest entry: every key
  as read, annotations in their order with their ids (copied byte for byte when nothing moved); an image that
  failed, or is not in the run, keeps its annotations as read (listed in the entry). A run that stops early
  (``--fail-fast``, Ctrl-C) does not write it: ``--resume`` does. The main process holds the parsed file and one
  record per image until then.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import posixpath
from collections import defaultdict
from pathlib import Path
from typing import Any

from . import coco_camera
from .coco_warp import GEOMETRY_KEYS, CocoImage
from .dataset import output_relpath
from .errors import InputError, RecipeError
from .input_checks import escapes
from .io import coco as coco_io
from .io.atomic import confined_to, staged_writes, write_bytes_atomic
from .manifest import sha256_file

EXAMPLES = 3                      # example paths in a warning


class CocoRun:
    """The COCO file of a run: its images by input path, the per-image records of the run's entries. Subclasses
    (:class:`roadview_noise.scalabel.ScalabelRun`) read other one-file-per-split layouts with the same plumbing."""

    KEY = "inputs.annotations.coco"
    ITEMS = "images"                  # what the file calls its image records
    WHAT = "COCO annotations"

    def __init__(self, in_root: Path, relpath: str, image_root: str | None, suffixes: list[str]):
        key = self.KEY
        self.relpath = posixpath.normpath(relpath)
        path = in_root / self.relpath
        if Path(os.path.realpath(in_root)) not in Path(os.path.realpath(path)).parents:
            raise RecipeError(f"{relpath!r} resolves outside the input folder; rvnoise reads only inside it", key=key)
        try:
            self.data = self.read(path)
        except InputError as exc:
            raise RecipeError(str(exc), key=key) from None
        self.path, self.sha256 = path, sha256_file(path)
        self.image_root = posixpath.normpath(image_root if image_root is not None else posixpath.dirname(self.relpath)
                                             or ".")
        self.suffixes = suffixes
        self.by_path: dict[str, int] = {}
        self.names: list[str] = []
        ids = set()
        for i, (image_id, name) in enumerate(self.images(in_root)):
            rel = posixpath.normpath(posixpath.join(self.image_root, str(name)))
            if not isinstance(image_id, (int, float, str)) or _key(image_id) in ids or rel in self.by_path:
                raise RecipeError(f"{self.relpath}: {self.ITEMS}[{i}] (id {image_id!r}, file_name {name!r}) "
                                  "repeats an id or a file_name, or its id is neither a number nor a string", key=key)
            self.by_path[rel] = i
            self.names.append(str(name))
            ids.add(_key(image_id))
        self.index()
        self.missing = [rel for rel in self.by_path if escapes(rel) or not (in_root / rel).is_file()]
        if self.by_path and len(self.missing) == len(self.by_path):
            first, name = next(iter(self.by_path)), self.names[0]
            hint = ("the file names are absolute paths: rvnoise reads them relative to the image root, so rewrite "
                    "them relative to a folder of IN" if posixpath.isabs(name) else
                    f"set {key}_image_root to the folder the file names are relative to")
            raise RecipeError(f"none of the {len(self.by_path)} images of {self.relpath} is a file under the image "
                              f"root {self.image_root!r} (e.g. file_name {name!r} → {first!r}); {hint}",
                              key=f"{key}_image_root")
        self.records: dict[tuple[int, int], dict] = {}            # (variant, image position) → record
        self.failed: dict[int, list[str]] = defaultdict(list)     # variant → file names
        self.unlisted, self.unlisted_examples = 0, []             # inputs of the run the file does not list

    def read(self, path: Path):
        return coco_io.read_coco(path)

    def write(self, path: Path, data) -> None:
        """The output file of ``data`` (what :meth:`output` made), atomically."""
        coco_io.write_coco(path, data)

    def images(self, in_root: Path) -> list[tuple[Any, str]]:
        """(id, file name relative to the image root) of each image record, in file order."""
        return [(img["id"], img["file_name"]) for img in self.data["images"]]

    def index(self) -> None:
        """The positions of each image's annotations in the file."""
        self.annotations_of: dict[Any, list[int]] = defaultdict(list)
        for i, ann in enumerate(self.data.get("annotations", [])):
            if not isinstance(ann["image_id"], (int, float, str)):
                raise RecipeError(f"{self.relpath}: annotations[{i}] has image_id {ann['image_id']!r}, neither a "
                                  "number nor a string", key=self.KEY)
            self.annotations_of[_key(ann["image_id"])].append(i)

    def notes(self) -> list[str]:
        """What the user should know before the run (file names that resolve to no file)."""
        if not self.missing:
            return []
        return [f"{len(self.missing)} of the {len(self.by_path)} images of {self.relpath} do not exist under the "
                f"image root {self.image_root!r} (e.g. {', '.join(self.missing[:EXAMPLES])}); they keep their "
                "annotations"]

    # --- the plan and the results -------------------------------------------------------------------------------

    def attach(self, task):
        """The task with its image's payload (:meth:`payload`; unchanged when the file does not list the image)."""
        pos = self.by_path.get(task.sample.relpath)
        if pos is None:
            if task.variant_index == 0:
                self.unlisted += 1
                self.unlisted_examples = (self.unlisted_examples + [task.sample.relpath])[:EXAMPLES]
            return task
        return dataclasses.replace(task, coco=self.payload(pos))

    def payload(self, pos: int) -> CocoImage:
        """What the worker needs of the image at ``pos`` (its ``move(shape, warps)`` makes the record)."""
        img = self.data["images"][pos]
        anns = self.data.get("annotations", [])
        return CocoImage(img["id"], str(img["file_name"]), img.get("width"), img.get("height"), self.sha256,
                         [(i, {k: anns[i][k] for k in GEOMETRY_KEYS if k in anns[i]})
                          for i in self.annotations_of.get(_key(img["id"]), ())])

    def keeps(self, task, entry: dict) -> bool:
        """Whether ``--resume`` may keep an earlier entry: it has the record of this file for a listed image (with
        the distortion of a moved image, :mod:`.coco_camera`)."""
        listed = task.sample.relpath in self.by_path
        record = entry.get("coco")
        if not listed:
            return record is None
        return record is not None and record.get("sha256") == self.sha256 and self.complete(record)

    def complete(self, record: dict) -> bool:
        """Whether a kept record is of this version: a COCO record of a moved image without its distortion is from
        a version that did not state it (redone)."""
        return "moved" not in record or "distortion" in record

    def collect(self, entry: dict) -> None:
        """Take the record of a released entry (fresh or kept), or its failure."""
        pos = self.by_path.get(entry.get("input"))
        if pos is None or entry.get("output") is None or entry.get("modality") == "coco":
            return
        if entry.get("status") == "ok" and "coco" in entry:
            self.records[(entry.get("variant_index", 0), pos)] = entry["coco"]
        elif entry.get("status") != "ok":
            self.failed[entry.get("variant_index", 0)].append(self.names[pos])

    # --- the output ----------------------------------------------------------------------------------------------

    def output(self, variant: int) -> tuple[dict | None, dict]:
        """The output dataset of one variant (None: the file as read, nothing moved or renamed) and the summary for
        its manifest entry."""
        suffix = self.suffixes[variant]
        images, done = list(self.data["images"]), {}
        for pos, img in enumerate(images):
            record = self.records.get((variant, pos))
            if record is not None:
                done[_key(img["id"])] = record
                images[pos] = coco_camera.image_entry(img, record)
                if suffix:
                    images[pos] = {**images[pos], "file_name": output_relpath(str(img["file_name"]), suffix)}
        changes: dict[int, dict | None] = {}
        for record in done.values():
            changes.update({p: f for p, f in record.get("moved", ())})
            changes.update({p: None for p, _ in record.get("dropped", ())})
        annotations, dropped = [], []
        for pos, ann in enumerate(self.data.get("annotations", [])):
            record = done.get(_key(ann["image_id"]))
            if record is not None and suffix and "file_name" in ann:
                ann = {**ann, "file_name": output_relpath(str(ann["file_name"]), suffix)}
            if pos in changes and changes[pos] is None:
                dropped.append(ann.get("id"))
                continue
            annotations.append({**ann, **changes[pos]} if pos in changes else ann)
        data = {k: images if k == "images" else annotations if k == "annotations" else v
                for k, v in self.data.items()}
        distorted = sum(bool(r.get("distortion")) for r in done.values())
        summary = {"images": len(images), "images_done": len(done), "images_distorted": distorted,
                   "images_failed": self.failed.get(variant, []),
                   "images_not_in_run": len(images) - len(done) - len(self.failed.get(variant, [])),
                   "inputs_not_in_file": self.unlisted,
                   "annotations": len(annotations), "annotations_moved": sum(f is not None for f in changes.values()),
                   "annotations_dropped": dropped}
        panoptic = [ids for r in done.values() for _, ids in r.get("segments_dropped", ())]
        if any("segments_dropped" in r for r in done.values()):           # COCO panoptic under a warp
            summary["segments_dropped"] = sum(len(ids) for ids in panoptic)
        return (None if not changes and not distorted and not (suffix and done) else data), summary

    def release(self, ledger, out_root: Path, previous) -> list[dict]:
        """Write the output file of every variant as an entry of the ledger (staged, recorded, renamed); returns
        the released entries."""
        released = []
        for variant, suffix in enumerate(self.suffixes):
            out_rel = output_relpath(self.relpath, suffix)
            data, summary = self.output(variant)
            entry = {"output": out_rel, "input": self.relpath, "modality": "coco", "variant_index": variant,
                     "input_sha256": self.sha256, "coco": summary}
            try:
                with confined_to(out_root), staged_writes() as stage:
                    raw = self.path.read_bytes() if data is None else b""
                    if data is None and hashlib.sha256(raw).hexdigest() == self.sha256:
                        write_bytes_atomic(out_root / out_rel, raw)          # byte for byte, as masks are
                        entry["copied_unchanged"] = True
                    else:
                        self.write(out_root / out_rel, data or self.data)
                files = [(tmp.relative_to(out_root).as_posix(), final.relative_to(out_root).as_posix())
                         for tmp, final in stage.files]
                entry.update(status="ok", files=[{"path": f, "sha256": sha256_file(out_root / t)} for t, f in files],
                             staged=[list(p) for p in files])
                entry["output_sha256"] = entry["files"][0]["sha256"]
                previous.seen(out_rel)          # replaced: an earlier run's entry of it is neither kept nor pruned
            except OSError as exc:
                entry.update(status="failed", error=f"{self.relpath}: cannot write {out_rel}: {exc.strerror or exc}")
            released += ledger.put(ledger.next, entry)
        return released

    def run_notes(self, written: bool) -> list[str]:
        """What the run's summary says about the file: not written (the run stopped early), inputs without a
        record."""
        notes = [] if written else [f"{self.relpath} was not written (the run stopped early); --resume writes it"]
        if self.unlisted:
            notes.append(f"{self.unlisted} input image(s) have no record in {self.relpath} under the image root "
                         f"{self.image_root!r} (e.g. {', '.join(self.unlisted_examples)}): they are augmented "
                         f"without {self.WHAT}")
        return notes


def _key(image_id: Any) -> Any:
    """An image id as a dictionary key (ids are integers or strings; a JSON float id such as 7.0 is 7)."""
    return int(image_id) if isinstance(image_id, float) and image_id.is_integer() else image_id


def open_run(in_root: Path, recipe) -> CocoRun | None:
    """The run's dataset file — COCO, Scalabel / BDD100K (:mod:`.scalabel`) or CVAT for images (:mod:`.cvat`) —
    (RecipeError when it cannot be used), or None when the recipe has none."""
    spec = recipe.spec.inputs.annotations
    suffixes = [v.suffix for v in recipe.variants]
    if spec.scalabel is not None:
        from .scalabel import ScalabelRun

        return ScalabelRun(in_root, spec.scalabel, spec.scalabel_image_root, suffixes)
    if spec.cvat is not None:
        from .cvat import CvatRun

        return CvatRun(in_root, spec.cvat, spec.cvat_image_root, suffixes)
    if spec.coco is None:
        return None
    return CocoRun(in_root, spec.coco, spec.coco_image_root, suffixes)
