"""Annotations survive augmentation: per-point label fields and sidecars follow the point provenance, masks and 2-D
boxes follow the geometric camera steps, 3-D boxes count their points before and after the chain.

No model handles annotations. After the chain (:func:`compound.apply_models`), the output cloud's provenance
(:mod:`roadview_noise.provenance`: ``origin`` into the chain input, ``effect``) carries every per-point annotation of
the input with one gather (:func:`carry_values`):

- a point that is the input's return (effect KEPT or ATTENUATED) keeps its value and dtype;
- a new point (MOVED to a particle, ADDED weather return or radar clutter) shows the particle, not the object: its
  *class* annotations get the weather class of the step that made it (``weather_class``), its *instance*
  annotations 0, while its sensor fields (ring, time stamp …) stay those of its ray (the models carry them);
- a full grid's cell whose return was lost (REMOVED) gets 0 (SemanticKITTI "unlabeled"), as ``PointCloud.drop``
  zeroes its fields.

Which fields are annotations (:func:`field_role`): ``class`` — label, label_id (RadarScenes), semantic,
semantic_label, sem_label, class, class_id, classification (LAS, PDAL exports), category, category_id, ObjTag,
semantic_tag; ``instance`` — instance, instance_id, inst_label, ObjIdx, object_id, track_id (case-insensitive, after
CloudCompare's ``scalar_`` prefix); every other field is a sensor field. ``inputs.annotations.field_roles``
({name: class | instance | sensor}) overrides the rule for any field name. A packed ``label`` (class | instance
<< 16, PCL ``PointXYZL``, SemanticKITTI ``.label``) is a class field: new points get class | 0 << 16.

Weather class of new points (``weather_class``, keys rain, snow, fog, clutter; radar weather adds clutter): by
default SemanticSTF's "invalid" id 20 (SemanticSTF marks adverse-weather noise with it), and for nuScenes-lidarseg
and -panoptic sidecars class 0 "noise" (nuScenes puts fog, rain drops and spray there; panoptic: class · 1000 with
instance 0). Raw SemanticKITTI ids (0–259) use 20 for
other-vehicle: give ``weather_class`` (e.g. 1, "outlier") for such data.

Sidecar paths (``point_labels``, ``masks``, ``boxes_2d``, ``boxes_3d``, ``calib``) are a pattern relative to the
input file's folder (``{stem}``, ``{name}``, ``{base}``, ``{parent}``: the folder's name — KITTI tracking's
sequence —, ``{parts[i]}``; ``..`` allowed), ``{replace: {old: new, …}}`` applied in order to the
input's path relative to the input root, or for nuScenes-lidarseg ``{nuscenes: v1.0-trainval}`` (the tables
``sample_data.json`` and ``lidarseg.json`` under that folder of the input root; nuScenes-panoptic: ``{nuscenes:
v1.0-trainval, table: panoptic}``, ``panoptic.json``). Every path must resolve inside
the input root. Outputs go to the same relative path under the output root (a sweep variant's suffix before the
file suffix, as for the data), in the same format, atomically.
"""

from __future__ import annotations

import dataclasses
import mmap
import posixpath
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Any, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_serializer, model_validator

from .errors import InputError
from .io import annotations as ann_io
from .io.atomic import write_bytes_atomic
from .physics.outline_warp import clip_polygon, forward_through, moved_boxes, moved_rings
from .physics.warp import moving
from .provenance import MADE_BY_STEP, REMOVED, gather, is_new
from .types import CameraFrame, PointCloud, RawFrame

ROLES = ("class", "instance", "sensor")
CLASS_FIELDS = frozenset({"label", "label_id", "semantic", "semantic_label", "sem_label", "class", "class_id",
                          "classification", "category", "category_id", "objtag", "semantic_tag"})
INSTANCE_FIELDS = frozenset({"instance", "instance_id", "inst_label", "objidx", "object_id", "track_id"})
SCALAR_PREFIX = "scalar_"                 # CloudCompare's PLY export names scalar fields so (Toronto-3D: scalar_Label)
WEATHERS = ("rain", "snow", "fog", "clutter")
DATASET_FILES = ("coco", "scalabel", "cvat")   # one annotation file for the whole dataset or split (coco.open_run)
UNSET_LEFT_OUT = ("scalabel", "scalabel_image_root", "cvat", "cvat_image_root")   # round 21's keys (AnnotationsSpec)
SEMANTICSTF_INVALID = 20                 # SemanticSTF's adverse-weather ("invalid") class id
NUSCENES_NOISE = 0                       # nuScenes-lidarseg "noise": dust, fog, rain drops, spray, reflections


# --- recipe ----------------------------------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ReplaceRule(_Strict):
    """``{replace: {old: new, …}}``: the input's path relative to the input root with each ``old`` replaced."""

    replace: dict[str, str]

    def applied(self, relpath: str) -> str:
        """``relpath`` with each ``old`` replaced by its ``new``, in the rule's order."""
        for old, new in self.replace.items():
            relpath = relpath.replace(old, new)
        return relpath


class NuscenesRule(_Strict):
    """``{nuscenes: v1.0-trainval}``: the lidarseg file of the cloud's sample_data record (nuScenes tables);
    ``table: panoptic``: its nuScenes-panoptic file (``panoptic.json``)."""

    nuscenes: str
    table: Literal["lidarseg", "panoptic"] = "lidarseg"


PathRule = Union[str, ReplaceRule, NuscenesRule]


class MaskRule(_Strict):
    """A mask with its fill value: ``{pattern: "../inst/{stem}.png", fill: 0}`` or ``{replace: {…}, fill: 0}``."""

    pattern: str | None = None
    replace: dict[str, str] | None = None
    fill: int = Field(ge=0)

    @model_validator(mode="after")
    def _one_path(self):
        if (self.pattern is None) == (self.replace is None):
            raise ValueError("a mask with its fill gives either pattern or replace")
        return self

    def path_rule(self) -> PathRule:
        return self.pattern if self.pattern is not None else ReplaceRule(replace=self.replace)


UNLABELED_FILL = 0        # Cityscapes' class 0 "unlabeled" / instance 0: the ids its devkit knows (255 is none)
UNLABELED_MASK_ENDINGS = ("_labelids", "_instanceids")           # Cityscapes, KITTI-360 (label ids, not train ids)
UNLABELED_MASK_FOLDERS = frozenset({"instance", "instances"})    # KITTI semantics' instance/, KITTI-MOTS instances/


def mask_fill(rule, spec: "AnnotationsSpec", relpath: str, mask: ann_io.Mask) -> int:
    """What a mask pixel with no source pixel in a warp gets: the rule's ``fill``; else 0 for Cityscapes-style
    label-id and instance-id maps (named ``*_labelIds`` / ``*_instanceIds``, or in an ``instance(s)/`` folder:
    Cityscapes' devkit maps every id through its label table, which has no 255) and for a mask whose bit depth cannot
    hold ``ignore_index`` (a 1-bit binary mask); else ``ignore_index``. InputError when the fill does not fit."""
    path = PurePosixPath(relpath)
    if isinstance(rule, MaskRule):
        fill = rule.fill
    elif path.stem.lower().endswith(UNLABELED_MASK_ENDINGS) or \
            any(f.lower() in UNLABELED_MASK_FOLDERS for f in path.parts[:-1]):
        fill = UNLABELED_FILL
    else:
        top = mask.max_level
        fill = spec.ignore_index if top is None or spec.ignore_index <= top else 0
    kind = mask.values.dtype.kind
    top = mask.max_level if mask.max_level is not None else \
        np.iinfo(mask.values.dtype).max if kind in "iu" else 1 if kind == "b" else None
    if top is not None and fill > top:
        raise InputError(f"fill {fill} of mask {relpath} does not fit its values (0 … {top}); give the mask a fill "
                         "it can hold", file=relpath)
    return fill


def panoptic_fill(rule, relpath: str) -> int:
    """A COCO panoptic PNG's fill: 0, the void id (:mod:`.coco_panoptic`); InputError for another fill given."""
    from .coco_panoptic import VOID_FILL

    if isinstance(rule, MaskRule) and rule.fill != VOID_FILL:
        raise InputError(f"fill {rule.fill} of the COCO panoptic PNG {relpath}: a pixel a warp brings in from outside "
                         f"the image is void, id {VOID_FILL} (RGB 0, 0, 0); give fill {VOID_FILL} or none",
                         file=relpath)
    return VOID_FILL


BOX_FILES_NOT_READ = {        # box files a user may have whose lines are not KITTI's or YOLO's: refused at validate
    ".xml": "Pascal VOC XML is read with boxes_2d_format: voc",
    ".json": "a COCO JSON (one file for the dataset) goes under annotations.coco, a BDD100K / Scalabel JSON (one "
             "file for the split) under annotations.scalabel; other JSON boxes are not read",
}

MASK_FILES_NOT_READ = {      # label files a user may name as masks that are no label images: refused at validate
    ".json": "a per-image polygon JSON (Cityscapes' *_gtFine_polygons.json, Mapillary Vistas v2) goes under "
             "annotations.polygons; here name the label images (Cityscapes' *_gtFine_labelIds.png and "
             "*_gtFine_instanceIds.png)",
    ".txt": "KITTI-MOTS / KITTI-STEP run-length text (one file per sequence) is not read; name the PNG instance maps "
            "(instances/<sequence>/<frame>.png)",
    ".mat": "MATLAB masks (SBD's cls/ and inst/) are not read; convert them to PNG",
}


# Label images a camera glob may sweep up with the photos: folders and name endings of the datasets' label trees
# (Cityscapes gtFine/gtCoarse *_labelIds, *_instanceIds, *_labelTrainIds, *_color; Pascal VOC SegmentationClass/
# SegmentationObject; BDD100K, Mapillary Vistas, KITTI-STEP, mmsegmentation and CamVid label folders; KITTI and
# KITTI-360 semantics' instance/, semantic_rgb/, confidence/; ACDC's and Dark Zurich's *_gt_labelColor,
# *_gt_invIds, *_gt_invGray, *_gt_panoptic in gt/). Not "gt": dehazing sets (RESIDE, O-HAZE) keep their clear
# photos in GT/.
LABEL_FOLDERS = frozenset({"gtfine", "gtcoarse", "segmentationclass", "segmentationclassaug", "segmentationobject",
                           "labels", "label", "masks", "mask", "instances", "instance", "panoptic", "panoptic_maps",
                           "gt_panoptic", "bitmasks", "semantic", "semantic_rgb", "confidence", "ann_dir",
                           "annotations", "trainannot", "valannot", "testannot"})
LABEL_NAME_ENDINGS = ("_labelids", "_instanceids", "_labeltrainids", "_gtfine_color", "_gtcoarse_color",
                      "_gt_labelcolor", "_gt_invids", "_gt_invgray", "_gt_panoptic")


def label_image_reason(relpath: str, globs: list[str]) -> str | None:
    """Why a camera input looks like a label image (a folder or name ending of LABEL_FOLDERS /
    LABEL_NAME_ENDINGS), None when it does not or when a glob names that folder or ending literally (the user
    asked for those files as photos)."""
    named = {seg.lower() for g in globs for seg in g.split("/") if not any(c in seg for c in "*?[")}
    ends = " ".join(g.lower() for g in globs)
    path = PurePosixPath(relpath)
    folders = [f for f in path.parts[:-1] if f.lower() in LABEL_FOLDERS]
    if any(f.lower() in named for f in folders):
        return None
    if folders:
        return f"in a label folder, {folders[0]}/"
    stem = path.stem.lower()
    ending = next((e for e in LABEL_NAME_ENDINGS if stem.endswith(e) and e not in ends), None)
    return None if ending is None else f"named like a label image, *{path.stem[-len(ending):]}{path.suffix}"


def _rule_ends(rule) -> list[str]:
    """The texts a path rule ends a sidecar's name with: the pattern, or the ``new`` parts of a replace rule."""
    rule = rule.path_rule() if isinstance(rule, MaskRule) else rule
    return [rule] if isinstance(rule, str) else list(rule.replace.values()) if isinstance(rule, ReplaceRule) else []


class AnnotationsSpec(_Strict):
    """``inputs.annotations`` of a recipe (module docstring)."""

    point_labels: PathRule | None = None
    point_labels_format: Literal["semantickitti", "nuscenes_lidarseg", "nuscenes_panoptic", "npy"] | None = None
    #                      None: by the name
    weather_class: dict[Literal["rain", "snow", "fog", "clutter"], int] = Field(default_factory=dict)
    field_roles: dict[str, Literal["class", "instance", "sensor"]] = Field(default_factory=dict)
    masks: list[Union[PathRule, MaskRule]] = Field(default_factory=list)   # MaskRule: with its fill
    polygons: list[PathRule] = Field(default_factory=list)   # per-image polygon JSON (Cityscapes, Mapillary v2)
    ignore_index: int = Field(255, ge=0)
    boxes_2d: PathRule | None = None
    boxes_2d_format: Literal["kitti", "yolo", "voc"] = "kitti"
    boxes_3d: PathRule | None = None
    boxes_3d_format: Literal["kitti", "json", "csv"] | None = None     # None: .json, .csv, else KITTI
    calib: PathRule | None = None
    coco: str | None = None                  # one COCO JSON for the dataset, relative to IN (roadview_noise.coco)
    coco_image_root: str | None = None       # folder under IN its file_name values are relative to (default: its own)
    scalabel: str | None = None              # one Scalabel / BDD100K JSON for the split (roadview_noise.scalabel)
    scalabel_image_root: str | None = None   # folder under IN its frames' names are relative to (default: its own)
    cvat: str | None = None                  # one "CVAT for images 1.1" XML for the task (roadview_noise.cvat)
    cvat_image_root: str | None = None       # folder under IN its images' names are relative to (default: its own)

    @model_serializer(mode="wrap")
    def _dump(self, handler) -> dict[str, Any]:
        """Keys added since round 21 are left out while unset, so run.json and the recipe's sha256 (``--resume``)
        stay those of a recipe written before they existed."""
        d = handler(self)
        for key in UNSET_LEFT_OUT:
            if d.get(key) is None:
                d.pop(key, None)
        return d

    @field_validator("masks", "polygons", mode="before")
    @classmethod
    def _one_or_many(cls, v):
        return [v] if isinstance(v, (str, dict)) else v

    def check_sensor(self, sensor: str) -> None:
        """RecipeError for annotations the chain's sensor has none of (masks of a cloud, point labels of an image)."""
        from .errors import RecipeError
        from .input_checks import escapes
        from .recipe import check_pattern

        wrong = ("point_labels", "boxes_3d", "calib") if sensor == "camera" else ("masks", "polygons",
                                                                                   *DATASET_FILES)
        for name in wrong:
            if getattr(self, name):
                raise RecipeError(f"{name} annotate {'point clouds' if sensor == 'camera' else 'images'}; this "
                                  f"chain acts on {sensor} data", key=f"inputs.annotations.{name}")
        for role, rule in self.rules():
            if isinstance(rule, str):
                try:
                    check_pattern(rule)
                except ValueError as e:
                    raise RecipeError(str(e), key=f"inputs.annotations.{role}") from None
        if self.calib is not None and self.boxes_3d is None:
            raise RecipeError("calib goes with boxes_3d (KITTI)", key="inputs.annotations.calib")
        ends = _rule_ends(self.boxes_2d)
        for suffix, why in BOX_FILES_NOT_READ.items():
            if any(e.lower().endswith(suffix) for e in ends) and not (suffix == ".xml" and self.boxes_2d_format ==
                                                                       "voc"):
                raise RecipeError(f"boxes_2d reads KITTI label_2, YOLO .txt or Pascal VOC .xml files; {why}",
                                  key="inputs.annotations.boxes_2d")
        for k, rule in enumerate(self.masks):
            for suffix, why in MASK_FILES_NOT_READ.items():
                if any(e.lower().endswith(suffix) for e in _rule_ends(rule)):
                    raise RecipeError(f"masks are PNG/TIFF label images or .npy arrays; {why}",
                                      key=f"inputs.annotations.masks[{k}]")
        for name in DATASET_FILES:
            if getattr(self, f"{name}_image_root") is not None and getattr(self, name) is None:
                raise RecipeError(f"{name}_image_root goes with {name}", key=f"inputs.annotations.{name}_image_root")
        given = [name for name in DATASET_FILES if getattr(self, name) is not None]
        if len(given) > 1:
            raise RecipeError(f"one dataset file per run: {' or '.join(DATASET_FILES)}",
                              key=f"inputs.annotations.{given[1]}")
        for name in [k for name in DATASET_FILES for k in (name, f"{name}_image_root")]:
            why = escapes(getattr(self, name) or "")
            if why:
                raise RecipeError(f"{getattr(self, name)!r} {why}", key=f"inputs.annotations.{name}")

    def rules(self) -> list[tuple[str, PathRule]]:
        """(role, rule) of every sidecar declared."""
        out = [(r, getattr(self, r)) for r in ("point_labels", "boxes_2d", "boxes_3d", "calib")]
        out += [("mask", m) for m in self.masks] + [("polygons", m) for m in self.polygons]
        return [(r, rule) for r, rule in out if rule is not None]


# --- paths -----------------------------------------------------------------------------------------------------------


def sidecar_relpath(rule: PathRule, relpath: str, in_root: Path) -> str:
    """Path (relative to the input root, POSIX) of the sidecar of input ``relpath``; InputError if it leaves the
    input root."""
    rule = rule.path_rule() if isinstance(rule, MaskRule) else rule
    if isinstance(rule, (str, ReplaceRule)):
        from .dataset import depth_relpath_for

        rel = depth_relpath_for(relpath, rule)
    else:
        rel = _nuscenes_index(str(Path(in_root).resolve() / rule.nuscenes), rule.table).get(relpath)
        if rel is None:
            raise InputError(f"no {rule.table} record for this sample_data file in {rule.nuscenes}/{rule.table}.json",
                             file=relpath)
    rel = posixpath.normpath(rel)
    if rel.startswith("../") or rel == ".." or posixpath.isabs(rel):
        raise InputError(f"annotation path {rel!r} leaves the input root", file=relpath)
    if rel == relpath:
        raise InputError("annotation path is the input file itself", file=relpath)
    return rel


def sidecar_files(in_root: Path, spec: AnnotationsSpec, relpaths) -> set[str]:
    """Every annotation file of the given inputs (so that discovery does not take a mask or a lidarseg file for an
    input); inputs whose sidecar cannot be resolved are skipped here and fail when processed."""
    found = set()
    for _, rule in spec.rules():
        for rel in relpaths:
            try:
                found.add(sidecar_relpath(rule, rel, in_root))
            except InputError:
                continue
    return found


@lru_cache(maxsize=4)
def _nuscenes_index(tables: str, table: str = "lidarseg") -> dict[str, str]:
    """sample_data filename → lidarseg (or panoptic) filename, from ``lidarseg.json`` (``panoptic.json``) and the
    LiDAR records of ``sample_data.json`` (scanned, not parsed: the trainval table holds millions of camera
    records)."""
    import json

    tables_dir = Path(tables)
    try:
        records = json.loads((tables_dir / f"{table}.json").read_text())
        by_token = {r["sample_data_token"]: r["filename"] for r in records}
        with open(tables_dir / "sample_data.json", "rb") as fh, \
                mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            pairs = re.finditer(rb'"token":\s*"(\w+)"[^{}]*?"filename":\s*"([^"]+)"', mm)
            return {f.decode(): by_token[t.decode()] for t, f in (m.groups() for m in pairs)
                    if t.decode() in by_token}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read the nuScenes tables ({exc})", file=tables) from None


# --- field roles and weather classes ---------------------------------------------------------------------------------


def field_role(name: str, overrides: dict[str, str] | None = None) -> str:
    """``class``, ``instance`` or ``sensor`` (module docstring)."""
    if overrides and name in overrides:
        return overrides[name]
    low = name.lower().removeprefix(SCALAR_PREFIX)
    return "class" if low in CLASS_FIELDS else "instance" if low in INSTANCE_FIELDS else "sensor"


@lru_cache(maxsize=64)
def _roles(names: tuple[str, ...], overrides: tuple[tuple[str, str], ...]) -> dict[str, str]:
    """:func:`field_role` of each field of a cloud, once per field list (every file of a run has the same fields);
    the dict is shared: read it, do not change it."""
    given = dict(overrides)
    return {k: field_role(k, given) for k in names}


def weather_classes(spec: AnnotationsSpec, fmt: str | None = None) -> dict[str, int]:
    """Class id of new points per weather: the recipe's, else the default for the label format."""
    default = NUSCENES_NOISE if fmt in ("nuscenes_lidarseg", "nuscenes_panoptic") else SEMANTICSTF_INVALID
    return {w: int(spec.weather_class.get(w, default)) for w in WEATHERS}


def step_weathers(model_ids) -> list[str]:
    """The weather of each chain step for its new points: radar steps make clutter, LiDAR steps the phenomenon of
    their id (``rain.lidar`` → rain)."""
    from .registry import get_model

    out = []
    for m in model_ids:
        phenomenon = m.split(".")[0]
        out.append("clutter" if get_model(m).sensor == "radar" or phenomenon not in WEATHERS else phenomenon)
    return out


def carry_values(values: np.ndarray, cloud: PointCloud, new_value) -> np.ndarray:
    """Per-point values of the chain input carried to the output ``cloud`` by its provenance: gathered at
    ``origin``, ``new_value`` (scalar or per point) on new points, 0 on REMOVED grid cells."""
    values = np.asarray(values)
    out = values.copy() if cloud.origin is None else gather(values, cloud.origin, 0)
    if cloud.effect is not None:
        new = is_new(cloud.effect)
        if new.any():
            out[new] = new_value[new] if np.ndim(new_value) else new_value
        out[cloud.effect == REMOVED] = 0
    return out


def new_classes(cloud: PointCloud, classes: dict[str, int], model_ids) -> Any:
    """Class of each new point (scalar when one step made them all): the weather of the step that made it."""
    by_step = np.array([classes[w] for w in step_weathers(model_ids)], dtype=np.int64)
    made = cloud.attributes.get(MADE_BY_STEP)
    if made is None:
        return 0
    if made.strides == (0,):
        return by_step[int(made[0])] if len(made) else 0
    return by_step[np.clip(made, 0, None)]


# --- reading, carrying, writing ------------------------------------------------------------------------------------


NO_YOLO_FILE = "no YOLO label file: an image without objects"
KITTI_TRACKING = "kitti_tracking"      # a boxes_2d file of KITTI tracking (label_02: one per sequence), not moved


@dataclass
class Sidecar:
    """One annotation file: its role, path relative to the input root, sha256 (None: a YOLO label file that does
    not exist, which YOLO reads as an image without objects), format and content."""

    role: str
    relpath: str
    path: Path
    sha256: str | None
    fmt: str = ""
    data: Any = None
    fill: int = 0                    # a mask's value where a warp maps from outside the image (mask_fill)

    def copy_to(self, dest: Path) -> None:
        write_bytes_atomic(dest, self.path.read_bytes())


@dataclass
class Annotated:
    """What the annotations of one output are: files to write (absolute path, writer), files that embed the output
    image (absolute path, writer of the path and the image file's bytes: a LabelMe ``imageData``), manifest
    records, and the masks moved by the frame's warps (values by path relative to the input root: where a COCO
    panoptic annotation finds its PNG, :mod:`.coco_panoptic`)."""

    writes: list[tuple[Path, Any]] = field(default_factory=list)
    embedding: list[tuple[Path, Any]] = field(default_factory=list)
    read: list[dict] = field(default_factory=list)
    objects: list[dict] | None = None
    masks: dict[str, np.ndarray] = field(default_factory=dict)


def read(relpath: str, in_root: Path, spec: AnnotationsSpec, data, void_masks: frozenset[str] = frozenset()) \
        -> list[Sidecar]:
    """Read the sidecars of one input (InputError names the file and the problem); an image's are in its stored
    pixel coordinates, also when it is processed upright (:mod:`.orientation`). Masks named in ``void_masks`` (the
    image's COCO panoptic PNGs) get the fill 0, the void id."""
    from .manifest import sha256_file
    from .dataset import split_suffix
    from .orientation import stored_shape

    out = []
    for role, rule in spec.rules():
        rel = sidecar_relpath(rule, relpath, in_root)
        path = in_root / rel
        if Path(in_root).resolve() not in path.resolve().parents:
            raise InputError(f"annotation path {rel!r} leaves the input root through a link", file=relpath)
        if not path.is_file():
            if role == "boxes_2d" and spec.boxes_2d_format == "yolo" and not path.exists():
                out.append(Sidecar(role, rel, path, None, "yolo"))     # YOLO's image without objects: no file
                continue
            raise InputError(f"annotation {role} {rel!r} declared in the recipe's inputs does not exist", file=relpath)
        sc = Sidecar(role, rel, path, sha256_file(path))
        if role == "point_labels":
            sc.fmt = ann_io.point_label_format(path, spec.point_labels_format)
            sc.data = ann_io.read_point_labels(path, sc.fmt)
            if len(sc.data) != len(data):
                raise InputError(f"{rel} has {len(sc.data)} point labels for the {len(data)} points of {relpath}",
                                 file=str(in_root / relpath))
        elif role == "mask":
            sc.data = ann_io.read_mask(path)
            h, w = stored_shape(data)
            if sc.data.shape[:2] != (h, w):
                raise InputError(f"mask {rel} is {sc.data.shape[1]}×{sc.data.shape[0]} px, the image {relpath} "
                                 f"{w}×{h}", file=str(in_root / relpath))
            sc.fill = panoptic_fill(rule, rel) if PurePosixPath(rel).name in void_masks else \
                mask_fill(rule, spec, rel, sc.data)
        elif role == "polygons":
            sc.data = ann_io.read_polygons(path)
            h, w = labelme_shape(data)
            size = (sc.data.get("imageWidth"), sc.data.get("imageHeight")) if "shapes" in sc.data else (w, h)
            if size not in ((w, h), (None, None)):
                shown = f" as displayed (EXIF orientation {labelme_turn(data)})" if labelme_turn(data) != 1 else ""
                raise InputError(f"LabelMe file {rel} is for a {size[0]}×{size[1]} px image, {relpath} is {w}×{h}"
                                 f"{shown}", file=str(in_root / relpath))
        elif role == "boxes_2d" and isinstance(data, PointCloud):
            sc.fmt = spec.boxes_2d_format                     # image boxes of a scan's frame: copied (carry)
        elif role == "boxes_2d" and spec.boxes_2d_format == "kitti" and ann_io.is_kitti_tracking(path):
            sc.fmt = KITTI_TRACKING                           # a sequence's file: copied unless a warp moves boxes
        elif role == "boxes_2d":
            sc.fmt = spec.boxes_2d_format
            h, w = stored_shape(data)
            sc.data = ann_io.read_boxes_2d(path, sc.fmt, w, h)
        out.append(sc)
    boxes = next((s for s in out if s.role == "boxes_3d"), None)
    if boxes is not None:
        calib = next((in_root / s.relpath for s in out if s.role == "calib"), None)
        suffix = PurePosixPath(boxes.relpath).suffix.lower().lstrip(".")
        boxes.fmt = spec.boxes_3d_format or (suffix if suffix in ("json", "csv") else "kitti")
        boxes.data = ann_io.read_boxes_3d(in_root / boxes.relpath, boxes.fmt, calib,
                                          split_suffix(PurePosixPath(relpath).name)[0])
    return out


def carry(sidecars: list[Sidecar], spec: AnnotationsSpec, data_in, data_out, model_ids, out_root: Path,
          variant_suffix: str = ""):
    """The output with its annotation fields carried, and the annotation files to write (:class:`Annotated`): point
    labels carried, masks and 2-D boxes through the frame's warps (copied as they are without one, or when every
    warp is exactly the identity), 3-D boxes and calib copied (they describe the scene, which the chain does not
    move)."""
    from .dataset import output_relpath

    result = Annotated(read=[{"role": s.role, "path": s.relpath, "sha256": s.sha256} if s.sha256 is not None else
                             {"role": s.role, "path": s.relpath, "absent": NO_YOLO_FILE} for s in sidecars])
    sidecars = [s for s in sidecars if s.sha256 is not None]              # an absent YOLO file: none written either
    camera = isinstance(data_out, (CameraFrame, RawFrame))
    warps = moving(data_out.warps) if camera and sidecars else []
    upright = labelme_turn(data_in) == 1     # a turned photo's bytes are not what LabelMe shows: imageData null
    for s, entry in zip(sidecars, [e for e in result.read if "absent" not in e]):
        if s.role == "boxes_2d" and (not camera or s.fmt == KITTI_TRACKING):
            if camera and warps:
                raise InputError(f"{s.relpath} is a KITTI tracking label file (frame track_id first: every frame of "
                                 f"the sequence in one file); this frame's warp ({', '.join(model_ids)}) would move "
                                 f"its boxes, which one file shared by the sequence's frames cannot hold: give "
                                 f"per-frame label_2 files, or a chain without geometric steps", file=str(s.path))
            entry["unchanged"] = ("image boxes: a point-cloud chain moves none, copied as they are" if not camera else
                                  "KITTI tracking sequence file: copied as it is, the chain warps no frame")
        if camera and not warps and _is_labelme(s) and (_embeds_image(s) or variant_suffix):
            result.embedding.append((out_root / output_relpath(s.relpath, variant_suffix),
                                     _labelme_writer(s, None, variant_suffix, upright)))
        elif s.role in ("boxes_3d", "calib") or (camera and not warps) or \
                (s.role == "boxes_2d" and not camera):
            result.writes.append((out_root / output_relpath(s.relpath, variant_suffix), s.copy_to))
    if isinstance(data_out, PointCloud):
        label_fmt = next((s.fmt for s in sidecars if s.role == "point_labels"), None)
        roles = _roles(tuple(data_in.fields), tuple(spec.field_roles.items()))
        wanted = "class" in roles.values() or any(s.role == "point_labels" for s in sidecars)   # else none given
        classes = new_classes(data_out, weather_classes(spec, label_fmt), model_ids) \
            if wanted and data_out.effect is not None else 0
        fields = {}
        for k, v in data_in.fields.items():
            role = roles[k]
            if role != "sensor" and k in data_out.fields:
                fields[k] = carry_values(v, data_out, classes if role == "class" else 0).astype(v.dtype, copy=False)
        if fields:
            data_out = data_out.with_fields(**fields)
        for s in sidecars:
            if s.role == "point_labels":
                new = classes * ann_io.PANOPTIC_CLASS_SCALE if s.fmt == "nuscenes_panoptic" else classes
                values = carry_values(s.data, data_out, new).astype(s.data.dtype, copy=False)
                result.writes.append((out_root / output_relpath(s.relpath, variant_suffix),
                                      lambda p, v=values, f=s.fmt: ann_io.write_point_labels(p, v, f)))
            elif s.role == "boxes_3d":
                result.objects = object_counts(s.data, data_in, data_out)
    elif camera and warps:
        h, w = data_out.shape
        for s in sidecars:
            dest = out_root / output_relpath(s.relpath, variant_suffix)
            if s.role == "mask":
                values = s.data.values
                for warp in warps:
                    values = warp.apply_labels(values, s.fill)
                mask = dataclasses.replace(s.data, values=values)
                result.masks[s.relpath] = values
                result.writes.append((dest, lambda p, m=mask: ann_io.write_mask(p, m)))
            elif _is_labelme(s):
                moved = warp_labelme_displayed(s.data, warps, (h, w), labelme_turn(data_in))
                result.embedding.append((dest, _labelme_writer(s, moved, variant_suffix, upright)))
            elif s.role == "polygons":
                moved = warp_polygon_objects(s.data, warps, w, h)
                result.writes.append((dest, lambda p, d=moved: ann_io.write_polygons(p, d)))
            elif s.role == "boxes_2d":
                boxes = warp_boxes(s.data, warps, w, h)
                result.writes.append((dest, lambda p, b=boxes: ann_io.write_boxes_2d(p, b, w, h)))
    return data_out, result


def _is_labelme(s: Sidecar) -> bool:
    return s.role == "polygons" and "shapes" in s.data


def _embeds_image(s: Sidecar) -> bool:
    """A LabelMe file holding its image (``imageData`` not null): written with the output image's bytes there."""
    return _is_labelme(s) and s.data.get("imageData") is not None


def _labelme_writer(s: Sidecar, moved: dict | None, suffix: str, upright: bool):
    """The writer (path, output image bytes) of a LabelMe file, ``moved`` by the warps or (None) as read: an
    ``imageData`` it held becomes the output image's (null for a turned photo, ``upright`` False), ``imagePath``
    names a sweep variant's image (``suffix``); as read, without a variant, only the base64 string is swapped."""
    from .dataset import output_relpath

    def write(path: Path, image: bytes | None) -> None:
        shown = image if upright else None
        if moved is None and not suffix:
            write_bytes_atomic(path, ann_io.labelme_with_image(s.path.read_bytes(), shown))
            return
        doc = dict(s.data if moved is None else moved)
        if doc.get("imageData") is not None:
            doc["imageData"] = ann_io.labelme_image_data(shown)
        if suffix and isinstance(doc.get("imagePath"), str):
            doc["imagePath"] = output_relpath(doc["imagePath"], suffix)
        ann_io.write_polygons(path, doc)

    return write


def write(annotated: Annotated | None, image: bytes | None = None) -> list[Path]:
    """Write the annotation files (atomically, by the io writers), those embedding the image with ``image``, the
    output image file's bytes; returns their paths."""
    if annotated is None:
        return []
    for path, writer in annotated.writes:
        writer(path)
    for path, writer in annotated.embedding:
        writer(path, image)
    return [p for p, _ in annotated.writes + annotated.embedding]


# --- camera boxes --------------------------------------------------------------------------------------------------

def warp_boxes(boxes: ann_io.Boxes2D, warps, width: int, height: int) -> ann_io.Boxes2D:
    """Boxes and polygons moved through the warps' point maps, all in one batch, by the mover of COCO outlines
    (:mod:`~roadview_noise.physics.outline_warp`: edges split where the map bends them): a box becomes the bounding
    box of its moved outline, clipped to the image (KITTI: pixel coordinates 0 … W − 1; YOLO: the image edges); a
    polygon becomes its moved outline clipped to the image edges (Sutherland–Hodgman). Boxes and polygons left with
    no area are dropped."""
    if not warps:
        return boxes
    lo_px, hi_px = (0.0, [width - 1, height - 1]) if boxes.fmt in ("kitti", "voc") else \
        (-0.5, [width - 0.5, height - 0.5])
    is_box = np.asarray(boxes.is_box, dtype=bool)
    move = lambda xy: forward_through(warps, xy)                                        # noqa: E731
    moved_box = iter(moved_boxes(np.reshape([p for p, b in zip(boxes.points_px, is_box) if b], (-1, 4)), move))
    moved_poly = iter(moved_rings([p for p, b in zip(boxes.points_px, is_box) if not b], move))
    tokens, points, kinds = [], [], []
    for words, box in zip(boxes.tokens, is_box):
        if box:
            pts = np.clip(next(moved_box).reshape(2, 2), lo_px, hi_px)
        else:
            pts = clip_polygon(next(moved_poly), width, height, origin_px=-0.5)
        if len(pts) < (2 if box else 3) or np.any(pts.max(axis=0) - pts.min(axis=0) <= 0):
            continue
        tokens.append(words)
        points.append(pts)
        kinds.append(bool(box))
    return ann_io.Boxes2D(boxes.fmt, tokens, points, kinds, boxes.document)


def warp_polygon_objects(data: dict, warps, width: int, height: int) -> dict:
    """A per-image polygon file (:func:`~roadview_noise.io.annotations.read_polygons`) moved through the warps: each
    object's polygon by the outline mover (edges split where the map bends them), clipped to the image (pixel
    centres on integers: edges at −½ and W − ½), to 1/1000 px; an object left with no area is dropped, one without
    a polygon (fewer than 3 points) kept as read; every other key as read (a LabelMe file:
    :func:`warp_labelme_displayed`)."""
    objects = data["objects"]
    moving = [k for k, o in enumerate(objects) if len(o["polygon"]) >= 3]
    rings = [np.asarray(objects[k]["polygon"], dtype=float).reshape(-1, 2) for k in moving]
    moved = dict(zip(moving, moved_rings(rings, lambda xy: forward_through(warps, xy))))
    kept = []
    for k, obj in enumerate(objects):
        if k in moved:
            ring = _clipped_ring(moved[k], width, height)
            if ring is None:
                continue
            obj = {**obj, "polygon": ring}
        kept.append(obj)
    return {**data, "objects": kept}


def _clipped_ring(ring: np.ndarray, width: int, height: int) -> list | None:
    """A moved polygon clipped to the image (pixel centres on integers), to 1/1000 px; None when no area is left."""
    ring = clip_polygon(ring, width, height, origin_px=-0.5)
    if len(ring) < 3 or np.any(ring.max(axis=0) - ring.min(axis=0) <= 0):
        return None
    return np.round(ring, 3).tolist()


def warp_labelme(data: dict, warps, width: int, height: int) -> dict:
    """A LabelMe file moved through the warps (pixel centres on integers, as labelme rasterises its shapes): a
    polygon as Cityscapes polygons move; a rectangle (two corners) becomes the bounding box of its moved outline,
    clipped to the image; lines, line strips, points and circles (centre, a point on the rim) move point by point,
    not clipped; a mask (a base64 PNG of its box, placed at the box's first point) is resampled as label images
    are and cut to the box of what is left. A polygon, rectangle or mask left with nothing is dropped.
    ``imageWidth``/``imageHeight`` become the output's; ``imageData`` (the image, base64) is the writer's:
    :func:`carry` puts the output image there. InputError for a shape type not listed here."""
    shapes = data["shapes"]
    kinds = [s.get("shape_type") or "polygon" for s in shapes]
    refused = sorted({k for k in kinds if k not in ann_io.LABELME_SHAPES})
    if refused:
        raise InputError(f"LabelMe shapes of type {', '.join(refused)} are not moved by a geometric step; convert "
                         "them to polygons, or use a photometric chain")
    pts = [np.asarray(s["points"], dtype=float).reshape(-1, 2) for s in shapes]
    move = lambda xy: forward_through(warps, xy)                                        # noqa: E731
    rings = iter(moved_rings([p for p, k in zip(pts, kinds) if k == "polygon"], move))
    boxes = iter(moved_boxes(np.reshape([np.r_[p.min(axis=0), p.max(axis=0)] for p, k in zip(pts, kinds)
                                         if k == "rectangle"], (-1, 4)), move))
    loose = [p for p, k in zip(pts, kinds) if k not in ("polygon", "rectangle", "mask")]
    moved = iter(np.split(move(np.concatenate(loose)), np.cumsum([len(p) for p in loose])[:-1]) if loose else ())
    kept = []
    for shape, kind in zip(shapes, kinds):
        if kind == "polygon":
            points = _clipped_ring(next(rings), width, height)
        elif kind == "rectangle":
            box = np.clip(next(boxes).reshape(2, 2), -0.5, [width - 0.5, height - 0.5])
            points = None if np.any(box[1] - box[0] <= 0) else np.round(box, 3).tolist()
        elif kind == "mask":
            shape = _moved_labelme_mask(shape, warps, width, height)
            points = None if shape is None else shape["points"]
        else:
            points = np.round(next(moved), 3).tolist()
        if points is not None:
            kept.append({**shape, "points": points})
    return {**data, "shapes": kept, "imageWidth": width, "imageHeight": height}


def labelme_turn(data) -> int:
    """The EXIF orientation of a photo as read: labelme shows a photo turned by it (``apply_exif_orientation`` when
    it loads the file), so a LabelMe file's shapes, ``imageWidth`` and ``imageHeight`` are the photo's as displayed,
    whether rvnoise processes it upright or as stored."""
    from .io.image_metadata import orientation

    return orientation(data.encoding) if isinstance(data, CameraFrame) else 1


def labelme_shape(data) -> tuple[int, int]:
    """(H, W) of the photo as labelme displays it (:func:`labelme_turn`)."""
    from .orientation import stored_shape, transposes

    h, w = stored_shape(data)
    return (w, h) if transposes(labelme_turn(data)) else (h, w)


def warp_labelme_displayed(data: dict, warps, stored_shape: tuple[int, int], turn: int) -> dict:
    """:func:`warp_labelme` of a file in the displayed coordinates of a photo with EXIF orientation ``turn``: its
    points turned to stored pixels, moved by the stored warps, turned back (``imageWidth``/``imageHeight`` the
    displayed size). InputError for a ``mask`` shape of a turned photo (its bitmap is not turned)."""
    from .orientation import stored_xy, transposes, upright_xy

    h, w = stored_shape
    if turn == 1:
        return warp_labelme(data, warps, w, h)
    if any(s.get("shape_type") == "mask" for s in data["shapes"]):
        raise InputError(f"LabelMe mask shapes of a photo with EXIF orientation {turn} are not moved by a geometric "
                         "step; convert them to polygons, or use a photometric chain")
    shown = (w, h) if transposes(turn) else (h, w)
    stored = warp_labelme(_labelme_points(data, lambda q: stored_xy(q, turn, shown)), warps, w, h)
    return {**_labelme_points(stored, lambda q: upright_xy(q, turn, (h, w))), "imageWidth": shown[1],
            "imageHeight": shown[0]}


def _labelme_points(data: dict, convert) -> dict:
    """A LabelMe file with every shape's points through ``convert`` ((N, 2) → (N, 2)), to 1/1000 px; a rectangle
    as its lowest and highest corner."""
    shapes = []
    for shape in data["shapes"]:
        q = convert(np.asarray(shape["points"], dtype=float).reshape(-1, 2))
        if shape.get("shape_type") == "rectangle":
            q = np.stack([q.min(axis=0), q.max(axis=0)])
        shapes.append({**shape, "points": (np.round(q, 3) + 0.0).tolist()})
    return {**data, "shapes": shapes}


def _moved_labelme_mask(shape: dict, warps, width: int, height: int) -> dict | None:
    """A LabelMe ``mask`` shape through the warps (labelme places its bitmap at the integer part of the first
    point): resampled in the whole frame (0 where nothing maps), cut to the box of what is left, written back as a
    1-bit PNG; None when nothing is left."""
    import base64

    values = ann_io.read_mask_bytes(base64.b64decode(shape["mask"]), "LabelMe mask").values
    x0, y0 = (int(v) for v in np.asarray(shape["points"][0], dtype=float))
    moved = moved_bitmap(values.any(axis=2) if values.ndim == 3 else values != 0, x0, y0, warps, width, height)
    if moved is None:
        return None
    cut, left, top = moved
    return {**shape, "points": [[float(left), float(top)], [float(left + cut.shape[1] - 1),
                                                             float(top + cut.shape[0] - 1)]],
            "mask": base64.b64encode(ann_io.packed_png(cut, 1)).decode("ascii")}


def moved_bitmap(bitmap: np.ndarray, left: int, top: int, warps, width: int, height: int):
    """A bitmap (h, w) of a box whose first pixel is (left, top), placed in the frame (cut at its edges), resampled
    through the warps as label images are (0 where nothing maps) and cut to the box of what is left: ``(cut uint8,
    left, top)``, or None when nothing is left (LabelMe and CVAT mask shapes)."""
    frame = np.zeros((height, width), np.uint8)
    h, w = bitmap.shape[:2]
    frame[max(top, 0):top + h, max(left, 0):left + w] = \
        bitmap[max(-top, 0):height - top, max(-left, 0):width - left]
    for warp in warps:
        frame = warp.apply_labels(frame, 0)
    rows, cols = np.flatnonzero(frame.any(axis=1)), np.flatnonzero(frame.any(axis=0))
    if not len(rows):
        return None
    return frame[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1], int(cols[0]), int(rows[0])


# --- objects -------------------------------------------------------------------------------------------------------


def points_in_boxes(positions_m: np.ndarray, boxes: ann_io.Boxes3D) -> np.ndarray:
    """(boxes, points) bool: which points lie inside which box (closed box)."""
    n = len(positions_m)
    p = positions_m @ boxes.to_box_frame[:3, :3].T + boxes.to_box_frame[:3, 3]
    inside = np.zeros((len(boxes.ids), n), dtype=bool)
    h = boxes.up_axis
    a, b = (0, 1) if h == 2 else (0, 2)
    for k, (c, size, yaw) in enumerate(zip(boxes.center_m, boxes.size_m, boxes.yaw_rad)):
        d = p - c
        cos, sin = np.cos(yaw), np.sin(yaw)
        if h == 2:                       # about z (x forward, y left): box x along (cos, sin)
            u, v = cos * d[:, a] + sin * d[:, b], -sin * d[:, a] + cos * d[:, b]
        else:                            # KITTI camera frame, rotation_y: box x along (cos, −sin) in (x, z)
            u, v = cos * d[:, a] - sin * d[:, b], sin * d[:, a] + cos * d[:, b]
        half = size / 2
        inside[k] = (np.abs(u) <= half[0]) & (np.abs(d[:, h]) <= half[1 if h == 1 else 2]) & \
            (np.abs(v) <= half[2 if h == 1 else 1])
    return inside


def object_counts(boxes: ann_io.Boxes3D, cloud_in: PointCloud, cloud_out: PointCloud) -> list[dict]:
    """Per object: the input's points inside its box, and after the chain the points inside it that are still the
    input's returns (KEPT or ATTENUATED) and the new (weather) points inside it. An object whose points all went is
    what D3.5 calls a corner case (``lost``)."""
    before = points_in_boxes(cloud_in.positions_m, boxes).sum(axis=1)
    inside = points_in_boxes(cloud_out.positions_m, boxes)
    if cloud_out.effect is None:
        after, weather = inside.sum(axis=1), np.zeros(len(boxes.ids), int)
    else:
        after = (inside & (cloud_out.effect <= 1)).sum(axis=1)
        weather = (inside & is_new(cloud_out.effect)).sum(axis=1)
    return [{"id": i, "class": c, "points_before": int(n0), "points_after": int(n1), "weather_points": int(nw),
             "lost": bool(n0 > 0 and n1 == 0)}
            for i, c, n0, n1, nw in zip(boxes.ids, boxes.classes, before, after, weather)]
