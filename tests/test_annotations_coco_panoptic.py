"""A COCO panoptic file through camera chains: its PNGs (declared masks) move as label images, each segment's
``area`` and ``bbox`` come from the moved PNG (closed form for integer shifts and 2:1 subsampling; the PNG itself
for a fractional affine map), segments that leave the frame are dropped and counted, every other key kept; the
identity and photometric chains leave the JSON and PNG bytes as read."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import pytest
from test_annotations import WarpTestCamera as AffineCamera

from roadview_noise import coco_panoptic
from roadview_noise.io.image import write_image
from roadview_noise.manifest import read_manifest
from roadview_noise.physics.warp import Warp
from roadview_noise.recipe import parse_recipe
from roadview_noise.registry import MODELS
from roadview_noise.runner import run
from roadview_noise.types import ImageEncoding

W, H = 80, 60
DX, DY = 7, -5                                  # ShiftCamera's whole-pixel shift
BIG_ID = 26 + 256 * 3 + 256 ** 2 * 2            # every channel of the PNG used
# segment id: (x0, y0, x1, y1) inclusive pixel ranges of its rectangle
RECTS = {1: (10, 5, 19, 14), BIG_ID: (30, 20, 49, 39), 5000: (74, 40, 79, 49), 7: (0, 50, 79, 59)}
SEGMENTS = [{"id": 1, "category_id": 1, "iscrowd": 0, "area": 100, "bbox": [10, 5, 10, 10], "note": "kept"},
            {"id": BIG_ID, "category_id": 2, "iscrowd": 1, "area": 400, "bbox": [30, 20, 20, 20]},
            {"id": 5000, "category_id": 2, "iscrowd": 0, "area": 60, "bbox": [74, 40, 6, 10]},
            {"id": 7, "category_id": 21, "iscrowd": 0, "area": 800, "bbox": [0, 50, 80, 10]}]


@dataclass(frozen=True)
class ShiftCamera(AffineCamera):
    """Moves the image by (DX, DY) whole pixels (pull map x_in = u − DX, y_in = v − DY)."""

    id: ClassVar[str] = "panoptic_shift_test.camera"

    def warp(self, data, *, state, drawn):
        v, u = np.mgrid[0:H, 0:W].astype(np.float32)
        return Warp(u - DX, v - DY)


@dataclass(frozen=True)
class HalfCamera(AffineCamera):
    """Output pixel (u, v) shows input pixel (2u, 2v): the image halved about its corner."""

    id: ClassVar[str] = "panoptic_half_test.camera"

    def warp(self, data, *, state, drawn):
        v, u = np.mgrid[0:H, 0:W].astype(np.float32)
        return Warp(2 * u, 2 * v)


@dataclass(frozen=True)
class IdentityCamera(AffineCamera):
    id: ClassVar[str] = "panoptic_identity_test.camera"

    def warp(self, data, *, state, drawn):
        v, u = np.mgrid[0:H, 0:W].astype(np.float32)
        return Warp(u, v)




def _ids_png(path: Path) -> None:
    """An 8-bit RGB panoptic PNG (id = R + 256 G + 256² B) of the RECTS segments, void elsewhere."""
    ids = np.zeros((H, W), np.uint32)
    for seg_id, (x0, y0, x1, y1) in RECTS.items():
        ids[y0:y1 + 1, x0:x1 + 1] = seg_id
    bgr = np.stack([(ids >> 16) & 255, (ids >> 8) & 255, ids & 255], axis=-1).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), bgr)


def _read_ids(path: Path) -> np.ndarray:
    return coco_panoptic.segment_ids(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), path.name)


@pytest.fixture
def panoptic_tree(tmp_path: Path, monkeypatch) -> Path:
    """COCO's panoptic layout: IN/images/a.jpg, IN/annotations/panoptic.json with its PNGs in
    IN/annotations/panoptic/ (``file_name`` a.png)."""
    for cls in (AffineCamera, ShiftCamera, HalfCamera, IdentityCamera):
        monkeypatch.setitem(MODELS, cls.id, cls)
    root = tmp_path / "in"
    write_image(root / "images/a.jpg", np.random.default_rng(3).uniform(0, 1, (H, W, 3)).astype(np.float32),
                ImageEncoding(fmt="jpeg"))
    _ids_png(root / "annotations/panoptic/a.png")
    data = {"info": {"description": "synthetic panoptic"}, "licenses": [],
            "images": [{"id": 139, "file_name": "a.jpg", "width": W, "height": H}],
            "annotations": [{"image_id": 139, "file_name": "a.png", "segments_info": SEGMENTS}],
            "categories": [{"id": 1, "name": "person", "isthing": 1, "color": [220, 20, 60]},
                           {"id": 2, "name": "car", "isthing": 1, "color": [0, 0, 142]},
                           {"id": 21, "name": "road", "isthing": 0, "color": [128, 64, 128]}]}
    (root / "annotations/panoptic.json").write_text(json.dumps(data, indent=1))
    return root


def _recipe(model: str, base: Path, masks=("../annotations/panoptic/{stem}.png",)):
    annotations = {"coco": "annotations/panoptic.json", "coco_image_root": "images"}
    if masks:
        annotations["masks"] = list(masks)
    return parse_recipe({"schema": "rvnoise.recipe/1", "seed": 5, "chain": [{"model": model}],
                         "inputs": {"camera": "images/*.jpg", "annotations": annotations}}, base_dir=base)


def _run(recipe, in_root: Path, out: Path):
    return run(recipe, in_root, out, progress=False, echo=lambda *_: None, workers=1)


def _segments(out: Path) -> dict:
    data = json.loads((out / "annotations/panoptic.json").read_text())
    return {s["id"]: s for s in data["annotations"][0]["segments_info"]}


def _closed_form(cols, rows) -> dict:
    """Expected {id: (area, bbox)} when input column x goes to the output columns ``cols(x0, x1)`` (an inclusive
    range, possibly empty) and likewise rows."""
    expected = {}
    for seg_id, (x0, y0, x1, y1) in RECTS.items():
        (u0, u1), (v0, v1) = cols(x0, x1), rows(y0, y1)
        if u1 >= u0 and v1 >= v0:
            expected[seg_id] = ((u1 - u0 + 1) * (v1 - v0 + 1), [u0, v0, u1 - u0 + 1, v1 - v0 + 1])
    return expected


def _assert_consistent(out: Path, segments: dict) -> None:
    """The segments' areas and boxes are the moved PNG's: areas sum to its non-void pixels, and each id's
    pixels (found by np.nonzero, not the module's lookup) give its area and box; no id outside the input's."""
    ids = _read_ids(out / "annotations/panoptic/a.png")
    assert set(np.unique(ids).tolist()) <= set(RECTS) | {0}                 # no blended id
    assert sum(s["area"] for s in segments.values()) == int((ids != 0).sum())
    for seg_id, seg in segments.items():
        ys, xs = np.nonzero(ids == seg_id)
        assert seg["area"] == len(xs)
        assert seg["bbox"] == [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]


@pytest.mark.parametrize("model", ["panoptic_identity_test.camera", "compression.camera"])
def test_identity_and_photometric_chains_keep_json_and_png_bytes(panoptic_tree, tmp_path, model):
    out = tmp_path / "out"
    summary = _run(_recipe(model, tmp_path), panoptic_tree, out)
    assert summary.failed == 0 and summary.done == 2                         # the image and the JSON
    for rel in ("annotations/panoptic.json", "annotations/panoptic/a.png"):
        assert (out / rel).read_bytes() == (panoptic_tree / rel).read_bytes()


def test_an_integer_shift_gives_closed_form_areas_and_boxes_and_drops_what_left(panoptic_tree, tmp_path):
    out = tmp_path / "out"
    assert _run(_recipe(ShiftCamera.id, tmp_path), panoptic_tree, out).failed == 0
    expected = _closed_form(lambda a, b: (max(a + DX, 0), min(b + DX, W - 1)),
                            lambda a, b: (max(a + DY, 0), min(b + DY, H - 1)))
    assert 5000 not in expected                                              # it left the frame on the right
    segments = _segments(out)
    assert {k: (s["area"], s["bbox"]) for k, s in segments.items()} == expected
    src = {s["id"]: s for s in SEGMENTS}
    for seg_id, seg in segments.items():                                     # every other key as read
        assert {k: v for k, v in seg.items() if k not in ("area", "bbox")} == \
            {k: v for k, v in src[seg_id].items() if k not in ("area", "bbox")}
    assert [s["id"] for s in json.loads((out / "annotations/panoptic.json").read_text())["annotations"][0][
        "segments_info"]] == [1, BIG_ID, 7]                                  # order kept
    _assert_consistent(out, segments)
    entries = read_manifest(out / "manifest.jsonl")
    coco_entry = next(e for e in entries if e.get("modality") == "coco")
    assert coco_entry["coco"]["segments_dropped"] == 1
    image_entry = next(e for e in entries if e.get("input") == "images/a.jpg")
    assert image_entry["coco"]["segments_dropped"] == [[0, [5000]]]


def test_subsampling_by_two_gives_closed_form_areas_and_boxes(panoptic_tree, tmp_path):
    out = tmp_path / "out"
    assert _run(_recipe(HalfCamera.id, tmp_path), panoptic_tree, out).failed == 0
    half = lambda a, b: (-(-a // 2), b // 2)                                 # noqa: E731  u with a ≤ 2u ≤ b
    segments = _segments(out)
    assert {k: (s["area"], s["bbox"]) for k, s in segments.items()} == _closed_form(half, half)
    _assert_consistent(out, segments)
    ids_in, ids_out = _read_ids(panoptic_tree / "annotations/panoptic/a.png"), _read_ids(out / "annotations/panoptic/a.png")
    np.testing.assert_array_equal(ids_out[:H // 2, :W // 2], ids_in[::2, ::2])
    assert not ids_out[H // 2:].any() and not ids_out[:, W // 2:].any()      # from outside the image: void


def test_a_fractional_affine_map_keeps_ids_whole_and_areas_from_the_png(panoptic_tree, tmp_path):
    out = tmp_path / "out"
    assert _run(_recipe(AffineCamera.id, tmp_path), panoptic_tree, out).failed == 0
    segments = _segments(out)
    assert set(segments) == {1, BIG_ID, 7}
    _assert_consistent(out, segments)


def test_an_undeclared_png_or_a_non_void_fill_fails_the_image_by_name(panoptic_tree, tmp_path):
    out = tmp_path / "out"
    assert _run(_recipe(ShiftCamera.id, tmp_path, masks=()), panoptic_tree, out).failed == 1
    errors = [e.get("error", "") for e in read_manifest(out / "manifest.jsonl")]
    assert any("the COCO panoptic PNG 'a.png' of 'a.jpg' is not among the masks the recipe declares" in e
               for e in errors)
    masks = ({"pattern": "../annotations/panoptic/{stem}.png", "fill": 255},)
    assert _run(_recipe(ShiftCamera.id, tmp_path, masks=masks), panoptic_tree, tmp_path / "out2").failed == 1
    errors = [e.get("error", "") for e in read_manifest(tmp_path / "out2/manifest.jsonl")]
    assert any("fill 255 of the COCO panoptic PNG annotations/panoptic/a.png" in e for e in errors)
