"""A BDD100K / Scalabel per-split label JSON (``det_val.json``, ``bdd100k_labels_images_val.json``: a list of frames
with ``name`` and ``labels`` of ``box2d`` / ``poly2d``) through camera chains: boxes and closed polygons follow the
geometric steps' map (closed-form oracle of the affine test model), lanes move vertex by vertex, every other key
kept; a photometric chain copies the file byte for byte; a label left with nothing is dropped."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_annotations import WarpTestCamera as AffineCamera

from roadview_noise.errors import RecipeError
from roadview_noise.io import coco as coco_io
from roadview_noise.io.image import write_image
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import parse_recipe
from roadview_noise.registry import MODELS
from roadview_noise.runner import run
from roadview_noise.types import ImageEncoding

W, H = 80, 60
DRIVABLE = [[20.0, 20.0], [34.5, 18.25], [40.0, 30.0], [22.0, 33.0]]
LANE = [[78.0, 59.0], [30.0, 35.0], [33.0, 31.0], [35.0, 29.0]]


MASK = np.zeros((H, W), np.uint8)
MASK[30:50, 40:70] = 1
RLE = coco_io.rle_encode(MASK, compressed=True)          # BDD100K ins_seg: COCO's compressed RLE under "rle"


def _frames() -> list:
    """Two frames in BDD100K's layout (attributes, timestamps, manualShape …), a third whose image is absent."""
    return [
        {"name": "a.png", "attributes": {"weather": "clear", "scene": "city street", "timeofday": "daytime"},
         "timestamp": 10000, "labels": [
             {"id": "1", "category": "car", "attributes": {"occluded": False, "truncated": False},
              "manualShape": True, "box2d": {"x1": 10.0, "y1": 12.5, "x2": 40.25, "y2": 30.0}},
             {"id": "2", "category": "drivable area", "attributes": {"areaType": "direct"},
              "poly2d": [{"vertices": DRIVABLE, "types": "LLLL", "closed": True}]},
             {"id": "3", "category": "lane", "attributes": {"laneDirection": "parallel"},
              "poly2d": [{"vertices": LANE, "types": "LCCC", "closed": False}]},
             {"id": "4", "category": "pedestrian", "box2d": {"x1": 0.0, "y1": 0.0, "x2": 2.0, "y2": 2.0}},
             {"id": "5", "category": "traffic sign"},
             {"id": "6", "category": "car", "rle": RLE}]},
        {"name": "b.png", "labels": None},
        {"name": "gone.png", "labels": [{"id": "9", "category": "car",
                                         "box2d": {"x1": 1.0, "y1": 1.0, "x2": 3.0, "y2": 3.0}}]},
    ]


def two_images(root: Path, folder: str, monkeypatch) -> Path:
    """IN/<folder>/{a,b}.png, W × H random photos, with the affine test model registered; returns IN."""
    monkeypatch.setitem(MODELS, AffineCamera.id, AffineCamera)
    rng = np.random.default_rng(4)
    for name in ("a", "b"):
        write_image(root / folder / f"{name}.png", rng.uniform(0, 1, (H, W, 3)).astype(np.float32), ImageEncoding())
    return root


@pytest.fixture
def bdd_tree(tmp_path: Path, monkeypatch) -> Path:
    """IN/images/100k/val/{a,b}.png and IN/labels/det_20/det_val.json (BDD100K's layout)."""
    root = two_images(tmp_path / "in", "images/100k/val", monkeypatch)
    (root / "labels/det_20").mkdir(parents=True)
    (root / "labels/det_20/det_val.json").write_text(json.dumps(_frames(), indent=2))
    return root


def _recipe(model: str, base: Path, **extra) -> object:
    return parse_recipe({"schema": "rvnoise.recipe/1", "seed": 5, "chain": [{"model": model}],
                         "inputs": {"camera": "images/100k/val/*.png", "annotations": {
                             "scalabel": "labels/det_20/det_val.json", "scalabel_image_root": "images/100k/val",
                             **extra}}}, base_dir=base)


def _run(recipe, in_root: Path, out: Path):
    return run(recipe, in_root, out, progress=False, echo=lambda *_: None, workers=1)


def _forward(xy) -> np.ndarray:
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    return np.stack(AffineCamera().forward(xy[:, 0], xy[:, 1], W, H), axis=1)


def test_boxes_polygons_and_lanes_follow_the_map_and_every_other_key_is_kept(bdd_tree, tmp_path):
    summary = _run(_recipe("warp_test.camera", tmp_path), bdd_tree, tmp_path / "out")
    assert summary.failed == 0
    out = json.loads((tmp_path / "out/labels/det_20/det_val.json").read_text())
    frames = _frames()
    assert [f["name"] for f in out] == ["a.png", "b.png", "gone.png"]
    assert out[1:] == frames[1:]                                  # no labels; not in the run: as read
    a_in, a_out = frames[0], out[0]
    assert {k: v for k, v in a_out.items() if k != "labels"} == {k: v for k, v in a_in.items() if k != "labels"}
    labels = {lab["id"]: lab for lab in a_out["labels"]}
    assert list(labels) == ["1", "2", "3", "5", "6"]             # the pedestrian box left the image: dropped
    car = labels["1"]
    assert {k: v for k, v in car.items() if k != "box2d"} == \
        {k: v for k, v in a_in["labels"][0].items() if k != "box2d"}
    (x0, y0), (x1, y1) = _forward([[10.0, 12.5], [40.25, 30.0]])
    np.testing.assert_allclose([car["box2d"][k] for k in ("x1", "y1", "x2", "y2")], [x0, y0, x1, y1], atol=2e-3)
    area = labels["2"]["poly2d"][0]
    assert area["closed"] and area["types"] == "LLLL"
    np.testing.assert_allclose(area["vertices"], _forward(DRIVABLE), atol=2e-3)     # affine: no vertex added
    lane = labels["3"]["poly2d"][0]
    assert lane["types"] == "LCCC" and lane["closed"] is False
    moved = _forward(LANE)
    assert moved[0, 0] > W - 0.5                                   # a lane vertex leaves the image: not clipped
    np.testing.assert_allclose(lane["vertices"], moved, atol=2e-3)
    assert labels["5"] == a_in["labels"][4]                      # no geometry: as read
    warp = AffineCamera().warp(type("Frame", (), {"shape": (H, W)})(), state={}, drawn={})
    xs, ys = np.rint(warp.map_x).astype(int), np.rint(warp.map_y).astype(int)
    inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
    np.testing.assert_array_equal(coco_io.rle_decode(labels["6"]["rle"]),
                                  np.where(inside, MASK[np.clip(ys, 0, H - 1), np.clip(xs, 0, W - 1)], 0))
    assert isinstance(labels["6"]["rle"]["counts"], str)
    entries = {e["output"]: e for e in read_manifest(tmp_path / "out/manifest.jsonl")}
    record = entries["images/100k/val/a.png"]["coco"]
    assert record["dropped"] == [[3, "4"]]
    file_entry = entries["labels/det_20/det_val.json"]
    assert file_entry["coco"]["format"] == "scalabel" and file_entry["coco"]["frames_done"] == 2
    assert file_entry["coco"]["labels_dropped"] == ["4"] and file_entry["coco"]["frames_not_in_run"] == 1


def test_a_photometric_chain_copies_the_file_and_frames_wrappers_are_read(bdd_tree, tmp_path):
    """Compression moves nothing: the file's bytes come out as read. Scalabel's ``{"frames": …, "config": …}``
    layout is read too, and a polygon split by the border is clipped to the image."""
    assert _run(_recipe("compression.camera", tmp_path), bdd_tree, tmp_path / "out").failed == 0
    src = bdd_tree / "labels/det_20/det_val.json"
    assert (tmp_path / "out/labels/det_20/det_val.json").read_bytes() == src.read_bytes()
    wrapped = {"frames": _frames(), "config": {"categories": [{"name": "car"}]}}
    wrapped["frames"][0]["labels"][1]["poly2d"][0]["vertices"] = [[70.0, 10.0], [79.0, 10.0], [79.0, 20.0]]
    src.write_text(json.dumps(wrapped))
    assert _run(_recipe("warp_test.camera", tmp_path), bdd_tree, tmp_path / "out2").failed == 0
    out = json.loads((tmp_path / "out2/labels/det_20/det_val.json").read_text())
    assert out["config"] == wrapped["config"]
    ring = np.array(out["frames"][0]["labels"][1]["poly2d"][0]["vertices"])
    assert ring[:, 0].max() == pytest.approx(W - 0.5) and len(ring) >= 3
    assert out["frames"][0]["labels"][1]["poly2d"][0]["types"] == "L" * len(ring)


def test_what_is_not_a_scalabel_file_is_refused_naming_it(bdd_tree, tmp_path):
    """A COCO file, a box without its corners: refused before the run; a pose graph node without its location
    fails its frame, named."""
    src = bdd_tree / "labels/det_20/det_val.json"
    src.write_text(json.dumps({"images": [], "annotations": []}))
    with pytest.raises(RecipeError, match="not a Scalabel / BDD100K label file.*annotations.coco"):
        _run(_recipe("warp_test.camera", tmp_path), bdd_tree, tmp_path / "out")
    frames = _frames()
    frames[0]["labels"][0]["box2d"] = {"x1": 1, "y1": 2}
    src.write_text(json.dumps(frames))
    with pytest.raises(RecipeError, match=r"frames\[0\] labels\[0\].box2d is not"):
        _run(_recipe("warp_test.camera", tmp_path), bdd_tree, tmp_path / "out")
    frames = _frames()
    frames[0]["labels"].append({"id": "7", "category": "pedestrian", "graph": {"nodes": [{"category": "head"}]}})
    src.write_text(json.dumps(frames))
    assert _run(_recipe("warp_test.camera", tmp_path), bdd_tree, tmp_path / "out5").failed == 1
    assert any("a label of frame 'a.png'" in e.get("error", "") and "location" in e["error"]
               for e in read_manifest(tmp_path / "out5/manifest.jsonl"))
    with pytest.raises(RecipeError, match="one dataset file per run"):
        _recipe("warp_test.camera", tmp_path, coco="x.json")


POSE = [[30.0, 20.0], [79.0, 59.0], [33.5, 40.25]]


def test_pose_graph_nodes_move_as_points(bdd_tree, tmp_path):
    """BDD100K pose (``graph`` nodes, ``Pose2D-18Joints_Pretty``): every 2-D node location moves through the map
    point by point, unclipped (one leaves the image), visibility, edges and every other key kept, in a label that
    also has a box and a lane (the point sets are taken in label order); before round 22 the frame failed."""
    frames = _frames()
    nodes = [{"location": xy, "category": c, "visibility": v, "id": str(k)}
             for k, (xy, c, v) in enumerate(zip(POSE, ("head", "left_ankle", "right_ankle"), "VNV"))]
    graph = {"nodes": nodes, "edges": [{"source": "0", "target": "2", "type": "body"}],
             "type": "Pose2D-18Joints_Pretty"}
    frames[0]["labels"].insert(0, {"id": "7", "category": "pedestrian", "graph": graph,
                                   "box2d": {"x1": 25.0, "y1": 15.0, "x2": 40.0, "y2": 45.0},
                                   "poly2d": [{"vertices": LANE, "types": "LLLL", "closed": False}]})
    frames[0]["labels"].append({"id": "8", "category": "pedestrian",
                                "graph": {"nodes": [{"location": [1.0, 2.0, 3.0], "category": "head", "id": "0"}],
                                          "edges": []}})
    (bdd_tree / "labels/det_20/det_val.json").write_text(json.dumps(frames))
    assert _run(_recipe("warp_test.camera", tmp_path), bdd_tree, tmp_path / "out").failed == 0
    labels = {lab["id"]: lab for lab in json.loads((tmp_path / "out/labels/det_20/det_val.json").read_text())[0]
              ["labels"]}
    moved = labels["7"]["graph"]
    assert moved["edges"] == graph["edges"] and moved["type"] == graph["type"]
    assert [{k: v for k, v in n.items() if k != "location"} for n in moved["nodes"]] == \
        [{k: v for k, v in n.items() if k != "location"} for n in nodes]
    expected = _forward(POSE)
    assert expected[1, 0] > W                                     # the ankle leaves the image: kept, not clipped
    np.testing.assert_allclose([n["location"] for n in moved["nodes"]], expected, atol=2e-3)
    np.testing.assert_allclose(labels["7"]["poly2d"][0]["vertices"], _forward(LANE), atol=2e-3)
    assert labels["8"]["graph"]["nodes"][0]["location"] == [1.0, 2.0, 3.0]    # 3-D: camera space, kept


def test_unset_dataset_file_keys_leave_the_recorded_recipe_as_it_was():
    """``scalabel``, ``cvat`` and their image roots, unset, are left out of run.json and the recipe's sha256, so
    ``--resume`` continues a run made before round 21 (CNF05's sha256 as round 20 recorded it)."""
    from roadview_noise.recipe import load_recipe

    recipe = load_recipe(Path(__file__).resolve().parents[1] / "recipes/cnf05.yaml")
    annotations = recipe.resolved_dict()["inputs"]["annotations"]
    assert not {"scalabel", "scalabel_image_root", "cvat", "cvat_image_root"} & set(annotations)
    assert recipe.sha256() == "f2e709bc464ec5e5ad151d322a5277d73ab20057b91f4fbca77916265368f71b"
    given = parse_recipe({"schema": "rvnoise.recipe/1", "chain": [{"model": "fog.camera"}],
                          "inputs": {"camera": "*.png", "annotations": {"scalabel": "det.json"}}})
    assert given.resolved_dict()["inputs"]["annotations"]["scalabel"] == "det.json"
