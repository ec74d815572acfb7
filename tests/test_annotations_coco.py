"""A COCO dataset JSON through camera chains: polygons, RLE (both kinds), boxes, crowd regions and keypoints follow
the geometric steps' warps (identity: values unchanged; a known affine map: closed-form coordinates; windscreen:
masks of the moved polygons agree with the moved masks), every other key and the annotation order kept, written
once per run whatever the workers, backend or resuming."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import pytest
from pycocotools import mask as coco_mask
from test_annotations import WarpTestCamera as AffineCamera

from roadview_noise import coco_warp
from roadview_noise.dataset import Sample, load
from roadview_noise.errors import RecipeError
from roadview_noise.io import coco as coco_io
from roadview_noise.io.image import write_image
from roadview_noise.manifest import read_manifest
from roadview_noise.physics.warp import Warp
from roadview_noise.recipe import parse_recipe
from roadview_noise.registry import MODELS
from roadview_noise.runner import run
from roadview_noise.types import ImageEncoding

W, H = 80, 60
REAL_COCO = Path("/work/realdata/mmdet3d/tests/data/kitti/kitti_infos_mono3d.coco.json")


def forward_coco(x, y):
    """COCO coordinates (pixel i on [i, i + 1]) of an input position after :class:`AffineCamera`'s closed-form
    forward map (magnify about the centre by 1/0.93, shift by (6.3, −4.6) px)."""
    fx, fy = AffineCamera().forward(np.asarray(x) - 0.5, np.asarray(y) - 0.5, W, H)
    return fx + 0.5, fy + 0.5


@dataclass(frozen=True)
class IdentityCamera(AffineCamera):
    """Geometric test model whose warp is exactly the identity map."""

    id: ClassVar[str] = "coco_identity_test.camera"

    def warp(self, data, *, state, drawn):
        h, w = data.shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float32)
        return Warp(u, v)


def _mask(x0, y0, x1, y1) -> np.ndarray:
    m = np.zeros((H, W), np.uint8)
    m[y0:y1, x0:x1] = 1
    m[y0 + 2, x0 + 3] = 0                                     # a hole: more than one run per column
    return m


POLY_INSIDE = [20.0, 20.0, 34.5, 18.25, 40.0, 30.0, 22.0, 33.0]
POLY_TOP = [50.0, 1.0, 60.0, 1.0, 60.0, 10.0, 50.0, 10.0]      # the shift takes its top edge out of the image
KEYPOINTS = [25, 25, 2, 0, 0, 0, 2, 1, 1]                       # the third leaves the image (shift −4.6 px in y)


def _dataset() -> dict:
    crowd = _mask(5, 30, 15, 50)
    stuff = _mask(40, 35, 60, 55)
    rle_list = coco_io.rle_encode(crowd, compressed=False)
    rle_str = coco_io.rle_encode(stuff, compressed=True)
    return {
        "info": {"description": "synthetic", "version": "1.0"}, "licenses": [{"id": 1, "name": "CC-BY"}],
        "images": [{"id": 1, "file_name": "a.png", "width": W, "height": H, "license": 1, "extra": [1, 2]},
                   {"id": 2, "file_name": "b.png", "width": W, "height": H},
                   {"id": 3, "file_name": "gone.png", "width": W, "height": H}],
        "annotations": [
            {"id": 11, "image_id": 1, "category_id": 1, "segmentation": [POLY_INSIDE, POLY_TOP],
             "bbox": [20.0, 1.0, 40.0, 32.0], "area": 300.5, "iscrowd": 0, "keypoints": KEYPOINTS,
             "num_keypoints": 2, "score": 0.5},
            {"id": 21, "image_id": 2, "category_id": 2, "bbox": [10.0, 10.0, 20.0, 15.0], "area": 300.0,
             "iscrowd": 0, "segmentation": []},
            {"id": 12, "image_id": 1, "category_id": 2, "segmentation": rle_list, "bbox": [5.0, 30.0, 10.0, 20.0],
             "area": int(crowd.sum()), "iscrowd": 1},
            {"id": 13, "image_id": 1, "category_id": 2, "segmentation": rle_str, "bbox": [40.0, 35.0, 20.0, 20.0],
             "area": int(stuff.sum()), "iscrowd": 0},
            {"id": 14, "image_id": 1, "category_id": 3, "segmentation": [], "bbox": [30.0, 40.0, 12.0, 8.0],
             "area": 96.0, "iscrowd": 0, "center2d": [36.0, 44.0, 12.5], "bbox_cam3d": [1, 2, 3]},
            {"id": 15, "image_id": 1, "category_id": 3, "bbox": [75.0, 20.0, 4.0, 10.0], "area": 40.0,
             "iscrowd": 0},
            {"id": 31, "image_id": 3, "category_id": 1, "bbox": [1.0, 1.0, 2.0, 2.0], "area": 4.0, "iscrowd": 0},
        ],
        "categories": [{"id": 1, "name": "person", "keypoints": ["a", "b", "c"]}, {"id": 2, "name": "car"},
                       {"id": 3, "name": "truck"}],
        "unknown_key": {"kept": True},
    }


@pytest.fixture
def coco_tree(tmp_path: Path, monkeypatch) -> Path:
    """IN/images/{a,b}.png and IN/annotations/instances.json (COCO's layout: images in their own folder)."""
    for cls in (AffineCamera, IdentityCamera):
        monkeypatch.setitem(MODELS, cls.id, cls)
    root = tmp_path / "in"
    rng = np.random.default_rng(4)
    for name in ("a", "b"):
        write_image(root / "images" / f"{name}.png", rng.uniform(0, 1, (H, W, 3)).astype(np.float32), ImageEncoding())
    (root / "annotations").mkdir()
    (root / "annotations" / "instances.json").write_text(json.dumps(_dataset(), indent=1))
    return root


def _recipe(model: str, base: Path, **coco) -> object:
    return parse_recipe({"schema": "rvnoise.recipe/1", "seed": 5, "chain": [{"model": model}],
                         "inputs": {"camera": "images/*.png", "annotations": {
                             "coco": "annotations/instances.json", "coco_image_root": "images", **coco}}},
                        base_dir=base)


def _run(recipe, in_root: Path, out: Path, **kw):
    return run(recipe, in_root, out, progress=False, echo=lambda *_: None, **{"workers": 1, **kw})


def _out(out: Path, name: str = "annotations/instances.json") -> dict:
    return json.loads((out / name).read_text())


def _polygons_mask(polygons: list, h: int, w: int) -> np.ndarray:
    """The mask of a polygon segmentation as the COCO API rasterises it."""
    return coco_mask.decode(coco_mask.merge(coco_mask.frPyObjects(polygons, h, w)))


def _by_id(data: dict) -> dict:
    return {a["id"]: a for a in data["annotations"]}


# --- the encodings ------------------------------------------------------------------------------------------------


@pytest.mark.filterwarnings("ignore::DeprecationWarning")            # pycocotools' decode under NumPy 2
def test_rle_both_kinds_round_trip_with_the_coco_api():
    rng = np.random.default_rng(0)
    m = (rng.uniform(size=(37, 23)) < 0.3).astype(np.uint8)
    m[0, 0] = 1                                               # starts with a foreground pixel: a zero-length run first
    listed = coco_io.rle_encode(m, compressed=False)
    assert listed["counts"][0] == 0 and sum(listed["counts"]) == m.size
    np.testing.assert_array_equal(coco_mask.decode(coco_mask.frPyObjects(listed, 37, 23)), m)  # the COCO API's reading
    string = coco_io.rle_encode(m, compressed=True)
    assert isinstance(string["counts"], str)
    np.testing.assert_array_equal(coco_io.rle_decode(string), m)
    np.testing.assert_array_equal(coco_io.rle_decode(listed), m)
    assert coco_mask.area({"size": [37, 23], "counts": string["counts"].encode()}) == m.sum()


# --- through the runner -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["coco_identity_test.camera", "compression.camera"])
def test_identity_warp_and_photometric_chain_keep_every_value(coco_tree, tmp_path, model):
    out = tmp_path / "out"
    summary = _run(_recipe(model, tmp_path), coco_tree, out)
    assert summary.failed == 0 and summary.done == 3                    # two images and the COCO file
    assert (out / "annotations/instances.json").read_bytes() == (coco_tree / "annotations/instances.json").read_bytes()
    entry = next(e for e in read_manifest(out / "manifest.jsonl") if e["modality"] == "coco")
    assert entry["copied_unchanged"]
    assert entry["coco"]["images_done"] == 2 and entry["coco"]["images_not_in_run"] == 1
    assert entry["files"][0]["path"] == "annotations/instances.json"


def test_affine_warp_moves_every_kind_to_closed_form_positions(coco_tree, tmp_path):
    out = tmp_path / "out"
    assert _run(_recipe("warp_test.camera", tmp_path), coco_tree, out).failed == 0
    src, got = _dataset(), _out(out)
    s = AffineCamera.scale
    assert [a["id"] for a in got["annotations"]] == [11, 21, 12, 13, 14, 31]     # 15 left the image: dropped
    assert {k: v for k, v in got.items() if k not in ("annotations", "images")} == \
        {k: v for k, v in src.items() if k not in ("annotations", "images")}
    assert [{k: v for k, v in i.items() if k != "rv_distortion"} for i in got["images"]] == src["images"]
    assert [i.get("rv_distortion") for i in got["images"]] == [[{"model": "pixel_map"}]] * 2 + [None]  # coco_camera
    ann = _by_id(got)
    # polygon inside: each vertex at the closed-form position, no vertex added (an affine map bends no edge)
    x, y = forward_coco(POLY_INSIDE[0::2], POLY_INSIDE[1::2])
    np.testing.assert_allclose(ann[11]["segmentation"][0], np.stack([x, y], 1).ravel(), atol=6e-4)
    # polygon across the top edge: the moved rectangle clipped at y = 0
    (x0, x1), (y0, y1) = forward_coco([50.0, 60.0], [1.0, 10.0])
    assert y0 < 0
    top = np.array(ann[11]["segmentation"][1]).reshape(-1, 2)
    expected = np.array([[x0, 0], [x1, 0], [x1, y1], [x0, y1]])
    assert len(top) == 4 and all(np.abs(expected - p).sum(axis=1).min() < 2e-3 for p in top)
    assert all(np.abs(top - p).sum(axis=1).min() < 2e-3 for p in expected)
    np.testing.assert_allclose(ann[11]["bbox"], [x[0], 0.0, x1 - x[0], y[3] - 0.0], atol=2e-3)  # the segmentation's box
    shoelace = coco_warp.shoelace
    area_in = shoelace(np.reshape(POLY_INSIDE, (-1, 2))) + 90.0
    area_out = shoelace(np.reshape(POLY_INSIDE, (-1, 2))) * s * s + (x1 - x0) * y1
    assert ann[11]["area"] == pytest.approx(300.5 * area_out / area_in, abs=1e-3)   # the input's own convention kept
    kx, ky = forward_coco([25.0], [25.0])
    assert ann[11]["keypoints"] == [pytest.approx(kx[0], abs=6e-4), pytest.approx(ky[0], abs=6e-4), 2, 0, 0, 0, 0, 0, 0]
    assert ann[11]["num_keypoints"] == 1 and ann[11]["score"] == 0.5
    # box without segmentation: its moved outline; mmdetection3d's center2d moves, depth and 3-D box kept
    (bx0, bx1), (by0, by1) = forward_coco([30.0, 42.0], [40.0, 48.0])
    np.testing.assert_allclose(ann[14]["bbox"], [bx0, by0, bx1 - bx0, by1 - by0], atol=2e-3)
    assert ann[14]["area"] == pytest.approx(96.0 * s * s, rel=1e-4)
    cx, cy = forward_coco([36.0], [44.0])
    np.testing.assert_allclose(ann[14]["center2d"], [cx[0], cy[0], 12.5], atol=6e-4)
    assert ann[14]["bbox_cam3d"] == [1, 2, 3]
    # RLE: nearest-neighbour through the map (the oracle pulls input pixels at the rounded map), same kind out
    warp = AffineCamera().warp(load(Sample("images/a.png", "camera", "images"), coco_tree,
                                    _recipe("warp_test.camera", tmp_path)), state={}, drawn={})
    xs, ys = np.rint(warp.map_x).astype(int), np.rint(warp.map_y).astype(int)
    inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
    for i, kind in ((12, list), (13, str)):
        m_in = coco_io.rle_decode(_by_id(src)[i]["segmentation"])
        oracle = np.where(inside, m_in[np.clip(ys, 0, H - 1), np.clip(xs, 0, W - 1)], 0)
        assert isinstance(ann[i]["segmentation"]["counts"], kind)
        np.testing.assert_array_equal(coco_io.rle_decode(ann[i]["segmentation"]), oracle)
        assert ann[i]["area"] == int(oracle.sum())
        cols, rows = np.flatnonzero(oracle.any(0)), np.flatnonzero(oracle.any(1))
        assert ann[i]["bbox"] == [cols[0], rows[0], cols[-1] + 1 - cols[0], rows[-1] + 1 - rows[0]]
    # the image that is not in the run keeps its annotation as read
    assert ann[31] == _by_id(src)[31]
    entries = read_manifest(out / "manifest.jsonl")
    a = next(e for e in entries if e["input"] == "images/a.png")
    assert a["coco"]["dropped"] == [[5, 15]] and len(a["coco"]["moved"]) == 4
    coco_entry = next(e for e in entries if e["modality"] == "coco")
    assert coco_entry["coco"]["annotations_dropped"] == [15] and coco_entry["coco"]["annotations_moved"] == 5


@pytest.mark.filterwarnings("ignore::DeprecationWarning")            # pycocotools' decode under NumPy 2
def test_windscreen_moved_polygons_agree_with_the_moved_mask(tmp_path):
    """Real lens distortion: the mask of each moved polygon equals the polygon's input mask resampled through the
    image's map, within a pixel everywhere (the polygon's bent edges are followed)."""
    w, h = 320, 240
    root = tmp_path / "in"
    write_image(root / "img" / "f.png", np.full((h, w, 3), 0.5, np.float32), ImageEncoding())
    polys = [[10, 10, 150, 14, 140, 90, 60, 110, 12, 70], [200, 150, 310, 150, 310, 232, 200, 232],
             [150, 100, 170, 100, 170, 140]]
    anns = [{"id": i, "image_id": 0, "category_id": 1, "segmentation": [p], "area": 1.0,
             "bbox": [min(p[0::2]), min(p[1::2]), max(p[0::2]) - min(p[0::2]), max(p[1::2]) - min(p[1::2])],
             "iscrowd": 0} for i, p in enumerate(polys)]
    (root / "img" / "coco.json").write_text(json.dumps({"images": [{"id": 0, "file_name": "f.png", "width": w,
                                                                    "height": h}], "annotations": anns}))
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 1,
                           "chain": [{"model": "windscreen.camera", "params": {"k1": 3e-7}}],
                           "inputs": {"camera": "img/*.png", "camera_fov_h_deg": 80,
                                      "annotations": {"coco": "img/coco.json"}}}, base_dir=tmp_path)
    out = tmp_path / "out"
    assert _run(recipe, root, out).failed == 0
    from roadview_noise.runner import build_models, plan

    task = plan(root, recipe)[0]
    frame = load(task.sample, root, recipe)
    warp = build_models(recipe, task)[0].warp(frame, state={}, drawn={})
    assert np.max(np.hypot(warp.map_x - np.arange(w), warp.map_y - np.arange(h)[:, None])) > 8   # visibly bent
    got = _by_id(_out(out, "img/coco.json"))
    kernel = np.ones((3, 3), np.uint8)
    for i, p in enumerate(polys):
        moved_mask = warp.apply_labels(_polygons_mask([p], h, w), 0)
        poly_mask = _polygons_mask(got[i]["segmentation"], h, w)
        assert (moved_mask & ~cv2.dilate(poly_mask, kernel).astype(bool)).sum() == 0
        assert (poly_mask & ~cv2.dilate(moved_mask, kernel).astype(bool)).sum() == 0
        assert len(got[i]["segmentation"][0]) > len(p) or i == 2              # long edges bend: split
        x, y = np.reshape(got[i]["segmentation"][0], (-1, 2)).T
        assert got[i]["bbox"] == pytest.approx([x.min(), y.min(), x.max() - x.min(), y.max() - y.min()], abs=2e-3)


def test_two_workers_write_what_one_writes(coco_tree, tmp_path):
    recipe = _recipe("warp_test.camera", tmp_path)
    one, two = tmp_path / "one", tmp_path / "two"
    assert _run(recipe, coco_tree, one).failed == 0
    summary = _run(recipe, coco_tree, two, workers=2)
    assert summary.failed == 0 and summary.workers == 2
    assert (one / "annotations/instances.json").read_bytes() == (two / "annotations/instances.json").read_bytes()
    timed = ("seconds", "steps")                                 # wall-clock times, per file and per step
    lines = [[{k: v for k, v in e.items() if k not in timed} for e in read_manifest(d / "manifest.jsonl")]
             for d in (one, two)]
    assert lines[0] == lines[1]


@pytest.mark.slow
def test_dask_backend_writes_the_same_coco_file(coco_tree, tmp_path):
    pytest.importorskip("distributed")
    recipe = _recipe("warp_test.camera", tmp_path)
    local, dask = tmp_path / "local", tmp_path / "dask"
    assert _run(recipe, coco_tree, local).failed == 0
    assert _run(recipe, coco_tree, dask, workers=2, backend="dask").failed == 0
    assert (local / "annotations/instances.json").read_bytes() == (dask / "annotations/instances.json").read_bytes()


def test_failed_image_keeps_its_annotations_and_is_listed(coco_tree, tmp_path):
    data = _dataset()
    data["images"][1]["width"] = 81                             # b.png is 80 px wide: that image fails
    (coco_tree / "annotations/instances.json").write_text(json.dumps(data))
    out = tmp_path / "out"
    summary = _run(_recipe("warp_test.camera", tmp_path), coco_tree, out)
    assert summary.failed == 1 and "81×60" in summary.failures[0] and "80×60" in summary.failures[0]
    got = _by_id(_out(out))
    assert got[21] == _by_id(data)[21] and got[11] != _by_id(data)[11]
    entry = next(e for e in read_manifest(out / "manifest.jsonl") if e["modality"] == "coco")
    assert entry["coco"]["images_failed"] == ["b.png"]
    stopped = _run(_recipe("warp_test.camera", tmp_path), coco_tree, tmp_path / "stopped", fail_fast=True)
    assert not (tmp_path / "stopped/annotations").exists()                 # stopped early: no file, and says so
    assert any("was not written" in n and "--resume" in n for n in stopped.notes)


def test_resumed_run_writes_what_a_full_run_writes(coco_tree, tmp_path):
    recipe = _recipe("warp_test.camera", tmp_path)
    full, part = tmp_path / "full", tmp_path / "part"
    assert _run(recipe, coco_tree, full).failed == 0
    first = _run(recipe, coco_tree, part, limit=1)
    assert first.done == 2                                      # a.png and the COCO file (b.png kept as read)
    assert _by_id(_out(part))[21] == _by_id(_dataset())[21]
    again = _run(recipe, coco_tree, part, resume=True)
    assert again.skipped == 1 and again.done == 2               # a.png kept from its record, b.png and the file
    assert (part / "annotations/instances.json").read_bytes() == (full / "annotations/instances.json").read_bytes()
    entries = read_manifest(part / "manifest.jsonl")
    assert [e["output"] for e in entries] == ["images/a.png", "images/b.png", "annotations/instances.json"]


def test_sweep_variants_get_their_own_coco_file(coco_tree, tmp_path):
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 5, "chain": [{"model": "compression.camera"}],
                           "sweep": {"compression.camera.quality": [40, 80]},
                           "inputs": {"camera": "images/*.png", "annotations": {
                               "coco": "annotations/instances.json", "coco_image_root": "images"}}}, base_dir=tmp_path)
    out = tmp_path / "out"
    assert _run(recipe, coco_tree, out).failed == 0
    files = sorted(p.name for p in (out / "annotations").iterdir())
    assert len(files) == 2 and all(f.startswith("instances") and f.endswith(".json") for f in files)
    for f in files:
        names = [i["file_name"] for i in _out(out, f"annotations/{f}")["images"]]
        suffix = f.removeprefix("instances").removesuffix(".json")
        assert names == [f"a{suffix}.png", f"b{suffix}.png", "gone.png"]
        assert all((out / "images" / n).is_file() for n in names[:2])


def test_file_names_that_do_not_resolve_refuse_the_run(coco_tree, tmp_path):
    with pytest.raises(RecipeError, match="coco_image_root"):
        _run(_recipe("compression.camera", tmp_path, coco_image_root="annotations"), coco_tree, tmp_path / "o")
    assert not (tmp_path / "o").exists()
    with pytest.raises(RecipeError, match="outside|'\\.\\.'"):
        _run(_recipe("compression.camera", tmp_path, coco="../x.json"), coco_tree, tmp_path / "o")
    (coco_tree / "annotations/instances.json").write_text('{"images": [{"id": 1}]}')
    with pytest.raises(RecipeError, match="instances.json.*images\\[0\\] has no 'file_name'"):
        _run(_recipe("compression.camera", tmp_path), coco_tree, tmp_path / "o")
    data = _dataset()
    data["images"][1]["id"] = 1
    (coco_tree / "annotations/instances.json").write_text(json.dumps(data))
    with pytest.raises(RecipeError, match="images\\[1\\] .*repeats an id"):
        _run(_recipe("compression.camera", tmp_path), coco_tree, tmp_path / "o")
    with pytest.raises(RecipeError, match="coco"):
        parse_recipe({"schema": "rvnoise.recipe/1", "chain": [{"model": "rain.lidar"}],
                      "inputs": {"lidar": "*.pcd", "annotations": {"coco": "c.json"}}}, base_dir=tmp_path)


def test_images_of_the_run_without_a_record_are_reported(coco_tree, tmp_path):
    shutil.copy(coco_tree / "images/a.png", coco_tree / "images/c.png")
    out = tmp_path / "out"
    summary = _run(_recipe("warp_test.camera", tmp_path), coco_tree, out)
    assert summary.failed == 0 and any("images/c.png" in n and "no record" in n for n in summary.notes)
    entry = next(e for e in read_manifest(out / "manifest.jsonl") if e["input"] == "images/c.png")
    assert "coco" not in entry


@pytest.mark.skipif(not REAL_COCO.is_file(), reason="mmdetection3d's KITTI mono3d COCO file is not on this machine")
def test_mmdetection3d_kitti_mono3d_file(tmp_path):
    """mmdetection3d's ``kitti_infos_mono3d.coco.json`` (file names relative to its folder, boxes without
    segmentation, ``center2d``): through windscreen distortion every annotation moves, every other key is kept."""
    root = tmp_path / "in" / "kitti"
    shutil.copytree(REAL_COCO.parent / "training" / "image_2", root / "training" / "image_2")
    shutil.copy(REAL_COCO, root)
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 1, "chain": [{"model": "windscreen.camera"}],
                           "inputs": {"camera": "kitti/training/image_2/*.png", "camera_fov_h_deg": 80,
                                      "annotations": {"coco": f"kitti/{REAL_COCO.name}"}}}, base_dir=tmp_path)
    out = tmp_path / "out"
    assert _run(recipe, tmp_path / "in", out).failed == 0
    src, got = json.loads(REAL_COCO.read_text()), _out(out, f"kitti/{REAL_COCO.name}")
    assert [{k: v for k, v in i.items() if k != "rv_distortion"} for i in got["images"]] == src["images"]
    assert got["categories"] == src["categories"]
    assert [a["id"] for a in got["annotations"]] == [a["id"] for a in src["annotations"]]
    for a, b in zip(src["annotations"], got["annotations"]):
        assert a["bbox"] != b["bbox"] and a["center2d"][2] == b["center2d"][2]
        assert {k: v for k, v in a.items() if k not in ("bbox", "area", "center2d")} == \
            {k: v for k, v in b.items() if k not in ("bbox", "area", "center2d")}


def test_resume_redoes_images_whose_record_is_for_another_coco_file(coco_tree, tmp_path):
    recipe = _recipe("warp_test.camera", tmp_path)
    out = tmp_path / "out"
    assert _run(recipe, coco_tree, out).done == 3
    data = _dataset()
    data["annotations"][1]["bbox"] = [12.0, 10.0, 20.0, 15.0]          # b.png's box changed in the file
    (coco_tree / "annotations/instances.json").write_text(json.dumps(data))
    again = _run(recipe, coco_tree, out, resume=True)
    assert again.skipped == 0 and again.done == 3                       # every record was of the old file
    (bx0, _), _ = forward_coco([12.0, 32.0], [10.0, 25.0])
    assert _by_id(_out(out))[21]["bbox"][0] == pytest.approx(bx0, abs=2e-3)


def test_a_coco_panoptic_file_without_its_pngs_declared_fails_under_a_warp_and_is_copied_otherwise(coco_tree,
                                                                                                  tmp_path):
    """COCO panoptic (Mapillary Vistas v2 ``panoptic_2020.json``, Cityscapes' ``cityscapes_panoptic_val.json``):
    ``annotations`` per image with ``file_name`` of the panoptic PNG and ``segments_info`` (id, category_id, area,
    bbox). Under a warp the segments' bbox and area come from the moved PNG (test_annotations_coco_panoptic.py):
    an image whose PNG is not a declared mask fails, named; a photometric chain copies the file."""
    panoptic = {"images": [{"id": 1, "file_name": "a.png", "width": W, "height": H}],
                "annotations": [{"image_id": 1, "file_name": "a_panoptic.png", "segments_info": [
                    {"id": 7, "category_id": 3, "area": 120, "bbox": [10, 12, 15, 8], "iscrowd": 0}]}],
                "categories": [{"id": 3, "name": "car", "isthing": 1, "color": [0, 0, 142]}]}
    (coco_tree / "annotations/instances.json").write_text(json.dumps(panoptic))
    summary = _run(_recipe("warp_test.camera", tmp_path), coco_tree, tmp_path / "out")
    errors = [e.get("error", "") for e in read_manifest(tmp_path / "out/manifest.jsonl")]
    assert summary.failed == 1 and any("the COCO panoptic PNG 'a_panoptic.png' of 'a.png' is not among the masks"
                                       in e for e in errors)
    assert _run(_recipe("compression.camera", tmp_path), coco_tree, tmp_path / "out2").failed == 0
    assert (tmp_path / "out2/annotations/instances.json").read_bytes() == \
        (coco_tree / "annotations/instances.json").read_bytes()
