"""Annotations survive augmentation (issue 13): label fields and sidecars follow the point provenance through every
LiDAR/radar CNF, SemanticKITTI and nuScenes-lidarseg trees, masks and 2-D boxes follow a geometric camera model,
3-D boxes count their points before and after the chain, replay reproduces every annotation."""

from __future__ import annotations

import base64
import dataclasses
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import pytest

from roadview_noise import annotations
from roadview_noise.compound import apply_models
from roadview_noise.dataset import Sample, discover, load
from roadview_noise.errors import InputError, RecipeError
from roadview_noise.io import annotations as ann_io
from roadview_noise.io.image import read_image, write_image
from roadview_noise.io.pointcloud import read_pointcloud, write_pointcloud
from roadview_noise.manifest import read_manifest
from roadview_noise.model import Model, Stage
from roadview_noise.physics import outline_warp
from roadview_noise.physics.warp import Warp
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.provenance import Effect, is_new
from roadview_noise.recipe import parse_recipe
from roadview_noise.registry import MODELS
from roadview_noise.runner import build_models, plan, replay, run
from roadview_noise.types import CloudLayout, ImageEncoding, PointCloud

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"
CLASSES = {"rain": 41, "snow": 42, "fog": 43, "clutter": 44}
LIDAR_CNFS = [f"CNF{n}" for n in range(19, 25)]
RADAR_CNFS = ["CNF25", "CNF26", "CNF27"]


def _recipe(body: dict, base: Path):
    return parse_recipe({"schema": "rvnoise.recipe/1", "seed": 7, **body}, base_dir=base)


def _with_label(cloud: PointCloud, seed: int) -> PointCloud:
    """The cloud as a PCL PointXYZL-style PCD: a uint32 ``label`` = class | instance << 16 after its fields."""
    rng = np.random.default_rng(seed)
    label = (rng.integers(0, 260, len(cloud)) | (rng.integers(1, 50, len(cloud)) << 16)).astype(np.uint32)
    layout = dataclasses.replace(cloud.layout, fields=cloud.layout.fields + (("label", "label", "<u4"),))
    return dataclasses.replace(cloud.with_fields(label=label), layout=layout)


@pytest.fixture
def xyzl_tree(tmp_path: Path) -> Path:
    """LiDAR and radar sample frames with a PCL ``label`` field and a per-point ``.npy`` sidecar."""
    root = tmp_path / "in"
    for sensor, src in (("lidar", SAMPLE / "lidar" / "os1-128" / "seq0"), ("radar", SAMPLE / "radar" / "seq0")):
        dest = root / sensor / "seq0"
        dest.mkdir(parents=True)
        shutil.copy(src / f"{sensor}.yaml", dest)
        for i in range(2):
            cloud = _with_label(read_pointcloud(src / f"{i:06d}.pcd", sensor=sensor), seed=i)
            write_pointcloud(dest / f"{i:06d}.pcd", cloud)
            np.save(dest / f"{i:06d}_ids.npy", np.arange(len(cloud), dtype=np.int64) * 3 + 1)
    return root


def _chain_result(recipe, in_root: Path, sample: Sample, out_root: Path):
    """What the runner does for one sample, keeping the arrays: input, output with provenance, annotations."""
    spec = recipe.spec.inputs.annotations
    data = load(sample, in_root, recipe)
    sidecars = annotations.read(sample.relpath, in_root, spec, data)
    task = next(t for t in plan(in_root, recipe) if t.sample == sample)
    out, _ = apply_models(build_models(recipe, task), data, seed=recipe.seed, key=task.out_relpath,
                          sequence_id=sample.sequence_id)
    carried, result = annotations.carry(sidecars, spec, data, out, recipe.model_ids, out_root)
    return data, out, carried, sidecars, result


HEAVY = {"rain": {"rain_rate_mm_per_h": 100}, "snow": {"snowfall_rate_mm_per_h": 10}, "fog": {}}


@pytest.mark.parametrize("cnf", LIDAR_CNFS + RADAR_CNFS)
def test_pcl_label_and_sidecar_through_every_lidar_and_radar_cnf(xyzl_tree, tmp_path, cnf):
    """Every point that came from the input keeps its label value and dtype (checked through the provenance);
    new points (moved to a particle, added, clutter) get the configured class of their weather; the written file
    and the ``.npy`` sidecar line up with the written cloud."""
    from roadview_noise.compound import CNFS

    sensor = "radar" if cnf in RADAR_CNFS else "lidar"
    weather = CNFS[cnf].weather
    recipe = _recipe({"cnf": cnf, "sensor": sensor, "params": {f"{weather}.{sensor}": HEAVY[weather]},
                      "inputs": {sensor: f"{sensor}/**/*.pcd", "annotations": {
                          "point_labels": "{stem}_ids.npy", "weather_class": CLASSES}}}, tmp_path)
    samples = discover(xyzl_tree, recipe)
    assert [s.relpath for s in samples] == [f"{sensor}/seq0/000000.pcd", f"{sensor}/seq0/000001.pcd"]
    new_class = CLASSES["clutter" if sensor == "radar" else weather]
    n_new = 0
    for s in samples:
        data, out, carried, sidecars, result = _chain_result(recipe, xyzl_tree, s, tmp_path / "api")
        label_in = data.fields["label"]
        origin = np.arange(len(out)) if out.origin is None else out.origin
        effect = np.zeros(len(out), np.uint8) if out.effect is None else out.effect
        own, new = effect <= Effect.ATTENUATED, is_new(effect)
        assert own.sum() + new.sum() == len(out)                        # lists: removal is absence
        assert carried.fields["label"].dtype == np.uint32
        np.testing.assert_array_equal(carried.fields["label"][own], label_in[origin[own]])
        assert np.all(carried.fields["label"][new] == new_class)
        annotations.write(result)
        ids = np.load(tmp_path / "api" / s.relpath.replace(".pcd", "_ids.npy"))
        assert ids.dtype == np.int64 and len(ids) == len(out)
        np.testing.assert_array_equal(ids[own], sidecars[0].data[origin[own]])
        assert np.all(ids[new] == new_class)
        n_new += int(new.sum())
    if sensor == "lidar" or weather != "fog":
        assert n_new > 0, "the chain made no new points: the test would not test them"
    # the runner writes exactly these arrays
    out_root = tmp_path / "out"
    summary = run(recipe, xyzl_tree, out_root, workers=1, progress=False, echo=lambda *_: None)
    assert summary.failed == 0
    for s in samples:
        _, _, carried, _, _ = _chain_result(recipe, xyzl_tree, s, out_root)
        back = read_pointcloud(out_root / s.relpath, sensor=sensor)
        np.testing.assert_array_equal(back.fields["label"], carried.fields["label"])
        np.testing.assert_array_equal(back.fields["rv_effect"], carried.effect)
        assert len(np.load(out_root / s.relpath.replace(".pcd", "_ids.npy"))) == len(back)
    entry = read_manifest(out_root / "manifest.jsonl")[0]
    assert [f["path"] for f in entry["files"]] == [entry["output"], entry["output"].replace(".pcd", "_ids.npy")]
    assert entry["annotations_read"][0]["path"] == entry["input"].replace(".pcd", "_ids.npy")


# --- SemanticKITTI ---------------------------------------------------------------------------------------------------


@pytest.fixture
def semantickitti(tmp_path: Path) -> Path:
    """sequences/00/velodyne/*.bin (KITTI float32 x y z i) with sequences/00/labels/*.label (uint32) beside it."""
    root = tmp_path / "in"
    velo, labels = root / "sequences" / "00" / "velodyne", root / "sequences" / "00" / "labels"
    velo.mkdir(parents=True)
    labels.mkdir(parents=True)
    src = SAMPLE / "lidar" / "os1-128-kitti" / "seq0"
    shutil.copy(src / "lidar.yaml", velo)
    rng = np.random.default_rng(3)
    for i in range(2):
        shutil.copy(src / f"{i:06d}.bin", velo)
        n = (src / f"{i:06d}.bin").stat().st_size // 16
        (rng.choice([10, 40, 48, 50, 70, 252], n).astype("<u4") | (rng.integers(0, 9, n).astype("<u4") << 16)
         ).tofile(labels / f"{i:06d}.label")
    return root


def _sk_recipe(model: str, tmp_path: Path, **annotations_spec):
    return _recipe({"chain": [{"model": model}], "inputs": {
        "lidar": "sequences/*/velodyne/*.bin",
        "annotations": {"point_labels": "../labels/{stem}.label", **annotations_spec}}}, tmp_path)


@pytest.mark.parametrize("model", ["fog.lidar", "rain.lidar", "snow.lidar"])
def test_semantickitti_tree_keeps_labels_aligned(semantickitti, tmp_path, model):
    """``OUT/…/labels/000000.label`` lines up with ``OUT/…/velodyne/000000.bin``: one label per point, the input's
    label on every point still at its input position (KEPT/ATTENUATED in the ``.bin.rv_effect`` sidecar), SemanticSTF's
    20 on weather points."""
    params = {"rain.lidar": {"rain_rate_mm_per_h": 100}, "snow.lidar": {"snowfall_rate_mm_per_h": 10}}
    recipe = _sk_recipe(model, tmp_path)
    recipe = _recipe({**recipe.spec.model_dump(by_alias=True, exclude={"schema_"}), "seed": 7,
                      "params": {model: params.get(model, {"visibility_m": 20})}}, tmp_path)
    out = tmp_path / "out"
    assert run(recipe, semantickitti, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    for i in range(2):
        velo = f"sequences/00/velodyne/{i:06d}.bin"
        cloud_in = read_pointcloud(semantickitti / velo)
        labels_in = np.fromfile(semantickitti / f"sequences/00/labels/{i:06d}.label", "<u4")
        cloud = read_pointcloud(out / velo)
        labels = np.fromfile(out / f"sequences/00/labels/{i:06d}.label", "<u4")
        effect = np.fromfile(out / (velo + ".rv_effect"), np.uint8)
        assert len(labels) == len(cloud) == len(effect)
        where = {p.tobytes(): k for k, p in enumerate(cloud_in.positions_m.astype(np.float32))}
        own = np.flatnonzero(effect <= Effect.ATTENUATED)
        src = np.array([where[p.tobytes()] for p in cloud.positions_m[own].astype(np.float32)])
        np.testing.assert_array_equal(labels[own], labels_in[src])
        new = is_new(effect)
        assert new.any() and np.all(labels[new] == 20)
    entry = read_manifest(out / "manifest.jsonl")[0]
    assert {f["path"] for f in entry["files"]} == {
        "sequences/00/velodyne/000000.bin", "sequences/00/velodyne/000000.bin.rv_effect",
        "sequences/00/labels/000000.label"}
    # replay reproduces the cloud, its effect sidecar and the labels
    result = replay(out / "manifest.jsonl", "sequences/00/velodyne/000001.bin")
    assert result["match"] and len(result["files"]) == 3 and all(f["got"] == f["expected"] for f in result["files"])


def test_wrong_length_sidecar_fails_that_file_only(semantickitti, tmp_path):
    bad = semantickitti / "sequences/00/labels/000001.label"
    bad.write_bytes(bad.read_bytes()[:-8])
    out = tmp_path / "out"
    summary = run(_sk_recipe("fog.lidar", tmp_path), semantickitti, out, workers=1, progress=False,
                  echo=lambda *_: None)
    assert summary.done == 1 and summary.failed == 1
    err = summary.failures[0]
    assert "sequences/00/labels/000001.label" in err and "velodyne/000001.bin" in err and "point labels" in err
    assert not (out / "sequences/00/velodyne/000001.bin").exists()
    assert not (out / "sequences/00/labels/000001.label").exists()
    assert (out / "sequences/00/labels/000000.label").is_file()


def test_sweep_variants_get_their_own_label_files(semantickitti, tmp_path):
    recipe = _recipe({"chain": [{"model": "fog.lidar"}], "sweep": {"fog.lidar.visibility_m": [20, 200]},
                      "inputs": {"lidar": "sequences/*/velodyne/*.bin",
                                 "annotations": {"point_labels": "../labels/{stem}.label"}}}, tmp_path)
    out = tmp_path / "out"
    assert run(recipe, semantickitti, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    for v in ("20", "200"):
        cloud = read_pointcloud(out / f"sequences/00/velodyne/000000__visibility_m-{v}.bin")
        assert len(np.fromfile(out / f"sequences/00/labels/000000__visibility_m-{v}.label", "<u4")) == len(cloud)


def test_sidecar_outside_the_input_root_is_refused(semantickitti, tmp_path):
    recipe = _recipe({"chain": [{"model": "fog.lidar"}], "inputs": {
        "lidar": "sequences/*/velodyne/*.bin", "annotations": {"point_labels": "../../../../x/{stem}.label"}}},
        tmp_path)
    summary = run(recipe, semantickitti, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None)
    assert summary.failed == 2 and "leaves the input root" in summary.failures[0]
    outside = tmp_path / "elsewhere"
    shutil.move(semantickitti / "sequences/00/labels", outside)
    (semantickitti / "sequences/00/labels").symlink_to(outside)
    summary = run(_sk_recipe("fog.lidar", tmp_path), semantickitti, tmp_path / "out2", workers=1, progress=False,
                  echo=lambda *_: None)
    assert summary.failed == 2 and "through a link" in summary.failures[0]


def test_annotations_that_do_not_fit_the_recipe_are_recipe_errors(tmp_path):
    from roadview_noise.errors import RecipeError

    with pytest.raises(RecipeError, match="point_label.*did you mean 'point_labels'"):
        _recipe({"cnf": "CNF19", "inputs": {"annotations": {"point_label": "x"}}}, tmp_path)
    with pytest.raises(RecipeError, match="inputs.annotations.masks: masks annotate images; this chain acts on lidar"):
        _recipe({"cnf": "CNF19", "inputs": {"annotations": {"masks": "{stem}.png"}}}, tmp_path)
    with pytest.raises(RecipeError, match="point_labels annotate point clouds"):
        _recipe({"cnf": "CNF10", "inputs": {"annotations": {"point_labels": "{stem}.label"}}}, tmp_path)
    with pytest.raises(RecipeError, match="weather_class"):
        _recipe({"cnf": "CNF19", "inputs": {"annotations": {"weather_class": {"hail": 3}}}}, tmp_path)
    # box files a user has that boxes_2d cannot read: at validate, not "line 1: 1 values, KITTI label_2 has 15" per file
    with pytest.raises(RecipeError, match="boxes_2d: .*Pascal VOC XML is read with boxes_2d_format: voc"):
        _recipe({"cnf": "CNF05", "inputs": {"annotations": {"boxes_2d": "../Annotations/{stem}.xml"}}}, tmp_path)
    assert _recipe({"cnf": "CNF05", "inputs": {"annotations": {"boxes_2d": "../Annotations/{stem}.xml",
                                                               "boxes_2d_format": "voc"}}}, tmp_path)
    with pytest.raises(RecipeError, match="boxes_2d: .*goes under annotations.coco"):
        _recipe({"cnf": "CNF05", "inputs": {"annotations": {"boxes_2d": {"replace": {".jpg": ".JSON"}}}}}, tmp_path)
    # Cityscapes' polygons next to its label images (round 19): validate passed, then every image failed with "not
    # an image OpenCV can decode"
    polygons = {"replace": {"leftImg8bit/": "gtFine/", "_leftImg8bit.png": "_gtFine_polygons.json"}}
    with pytest.raises(RecipeError, match=r"masks\[1\]: .*_gtFine_polygons.json.*goes under annotations.polygons"):
        _recipe({"cnf": "CNF05", "inputs": {"annotations": {"masks": ["{stem}_labelIds.png", polygons]}}}, tmp_path)
    assert _recipe({"cnf": "CNF05", "inputs": {"annotations": {"polygons": polygons}}}, tmp_path)
    with pytest.raises(RecipeError, match="polygons annotate images"):
        _recipe({"cnf": "CNF19", "inputs": {"annotations": {"polygons": polygons}}}, tmp_path)


# --- nuScenes-lidarseg -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("table", ["lidarseg", "panoptic"])
def test_nuscenes_lidarseg_through_the_tables(tmp_path, table):
    """``{nuscenes: v1.0-mini}``: the cloud's sample_data record gives its lidarseg file; uint8 classes; new points
    get nuScenes' class 0 "noise"; the lidarseg files are not taken for clouds. nuScenes-panoptic (``table:
    panoptic``): ``panoptic.json`` gives its ``.npz`` of uint16 ``class · 1000 + instance`` under ``data``, written
    back so (instances kept, new points 0 · 1000 + 0; the same bytes on a second run); before, not read."""
    root = tmp_path / "in"
    src = SAMPLE / "lidar" / "os1-128" / "seq0" / "000000.pcd"
    cloud = read_pointcloud(src)
    data = np.column_stack([cloud.positions_m, cloud.fields["intensity"], cloud.fields["ring"]]).astype("<f4")
    name = "samples/LIDAR_TOP/n008-2018-08-01-15-16-36-0400__LIDAR_TOP__1533151603547590.pcd.bin"
    (root / name).parent.mkdir(parents=True)
    data.tofile(root / name)
    shutil.copy(src.parent / "lidar.yaml", (root / name).parent)
    token = "9d9bf11fb0e144c8b446d54a8a00184f"
    (root / f"{table}/v1.0-mini").mkdir(parents=True)
    rng = np.random.default_rng(1)
    classes = rng.integers(1, 32, len(cloud)).astype(np.uint8)
    labels_name = f"{table}/v1.0-mini/{token}_{table}" + (".bin" if table == "lidarseg" else ".npz")
    if table == "lidarseg":
        classes.tofile(root / labels_name)
    else:
        np.savez_compressed(root / labels_name, data=classes.astype("u2") * 1000 + rng.integers(0, 9, len(cloud), "u2"))
    (root / "v1.0-mini").mkdir()
    (root / f"v1.0-mini/{table}.json").write_text(json.dumps(
        [{"token": "aa" * 16, "sample_data_token": token, "filename": labels_name}]))
    (root / "v1.0-mini/sample_data.json").write_text(json.dumps([
        {"token": "bb" * 16, "sample_token": "s", "filename": "samples/CAM_FRONT/x.jpg", "prev": ""},
        {"token": token, "sample_token": "s", "ego_pose_token": "e", "is_key_frame": True, "filename": name,
         "prev": "", "next": ""}], indent=2))
    rule = {"nuscenes": "v1.0-mini"} if table == "lidarseg" else {"nuscenes": "v1.0-mini", "table": "panoptic"}
    recipe = _recipe({"chain": [{"model": "rain.lidar", "params": {"rain_rate_mm_per_h": 100}}],
                      "inputs": {"annotations": {"point_labels": rule}}}, tmp_path)
    assert [s.relpath for s in discover(root, recipe)] == [name]
    for out in (tmp_path / "out", tmp_path / "again"):
        assert run(recipe, root, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    if table == "lidarseg":
        labels = np.fromfile(tmp_path / "out" / labels_name, np.uint8)
    else:
        labels = np.load(tmp_path / "out" / labels_name)["data"]
        assert labels.dtype == np.uint16
        assert (tmp_path / "out" / labels_name).read_bytes() == (tmp_path / "again" / labels_name).read_bytes()
    effect = np.fromfile(tmp_path / "out" / (name + ".rv_effect"), np.uint8)
    assert len(labels) == len(read_pointcloud(tmp_path / "out" / name)) == len(effect)
    assert is_new(effect).any() and np.all(labels[is_new(effect)] == 0)
    assert np.all(labels[~is_new(effect)] > 0)
    if table == "panoptic":
        source = np.load(root / labels_name)["data"]
        assert set(np.unique(labels[~is_new(effect)])) <= set(np.unique(source))
        assert len(np.unique(labels[~is_new(effect)] % 1000)) > 1             # instances carried


# --- field roles -----------------------------------------------------------------------------------------------------


def test_field_roles_class_instance_sensor_and_override(tmp_path):
    """CARLA semantic fields: ObjTag (class) gets the weather class, ObjIdx (instance) 0 on new points; sensor fields
    (t, ring) keep their ray's value; ``field_roles`` turns an unknown field into an annotation."""
    prof = os1_128()
    src = read_pointcloud(SAMPLE / "lidar" / "os1-128" / "seq0" / "000000.pcd", profile=prof)
    n = len(src)
    rng = np.random.default_rng(5)
    extra = {"ObjIdx": rng.integers(1, 90, n).astype(np.uint32), "ObjTag": rng.integers(1, 20, n).astype(np.uint32),
             "t": np.arange(n, dtype=np.uint32), "my_tag": np.full(n, 7, np.int16)}
    cloud = dataclasses.replace(src.with_fields(**extra), layout=dataclasses.replace(
        src.layout, fields=src.layout.fields + tuple((k, k, v.dtype.str) for k, v in extra.items())))
    spec = annotations.AnnotationsSpec(field_roles={"my_tag": "class"}, weather_class={"fog": 99})
    out, _ = apply_models([MODELS["fog.lidar"](visibility_m=15.0)], cloud, seed=1, key="k", sequence_id="s")
    carried, _ = annotations.carry([], spec, cloud, out, ["fog.lidar"], tmp_path)
    new = is_new(carried.effect)
    moved = carried.effect == Effect.MOVED
    assert moved.any() and new.any()
    assert np.all(carried.fields["ObjTag"][new] == 99) and np.all(carried.fields["ObjIdx"][new] == 0)
    assert np.all(carried.fields["my_tag"][new] == 99) and carried.fields["my_tag"].dtype == np.int16
    np.testing.assert_array_equal(carried.fields["t"][moved], extra["t"][carried.origin[moved]])
    np.testing.assert_array_equal(carried.fields["ring"][moved], cloud.fields["ring"][carried.origin[moved]])
    own = ~new
    for k in ("ObjIdx", "ObjTag", "t"):
        np.testing.assert_array_equal(carried.fields[k][own], extra[k][carried.origin[own]])
    assert annotations.field_role("Label") == "class" and annotations.field_role("label", {"label": "sensor"}) == \
        "sensor" and annotations.field_role("ambient") == "sensor"
    # RadarScenes' label_id, LAS classification, CloudCompare's scalar_ prefix (Toronto-3D's scalar_Label)
    assert [annotations.field_role(k) for k in ("label_id", "Classification", "scalar_Label", "scalar_Intensity",
                                                "scalar_track_id")] == ["class", "class", "class", "sensor",
                                                                        "instance"]


def test_removed_grid_cells_lose_their_annotation(tmp_path):
    """A full grid keeps its cells: a cell whose return the weather removed is REMOVED and its label 0."""
    src = read_pointcloud(SAMPLE / "lidar" / "os1-128-grid" / "seq0" / "000000.pcd", profile=os1_128())
    label = (np.arange(len(src)) % 250 + 1).astype(np.uint16)
    cloud = src.with_fields(label=label)
    out, _ = apply_models([MODELS["rain.lidar"](rain_rate_mm_per_h=100.0)], cloud, seed=1, key="k", sequence_id="s")
    carried, _ = annotations.carry([], annotations.AnnotationsSpec(), cloud, out, ["rain.lidar"], tmp_path)
    assert out.origin is None and len(out) == len(cloud)
    removed = carried.effect == Effect.REMOVED
    assert removed.any() and np.all(carried.fields["label"][removed] == 0)
    assert np.all(carried.positions_m[removed] == 0)
    kept = carried.effect <= Effect.ATTENUATED
    np.testing.assert_array_equal(carried.fields["label"][kept], label[kept])


# --- camera: masks and 2-D boxes through a geometric model -------------------------------------------------------


@dataclass(frozen=True)
class WarpTestCamera(Model):
    """A geometric test model (registered only in these tests): magnify about the centre by 1/0.93, shift by
    (6.3, −4.6) px. Pull map ``x_in = cx + 0.93 (x_out − 6.3 − cx)``; its forward map is the closed form."""

    id: ClassVar[str] = "warp_test.camera"
    stage: ClassVar[Stage] = Stage.WINDSCREEN
    sensor: ClassVar[str] = "camera"
    scale: ClassVar[float] = 1 / 0.93
    shift: ClassVar[tuple[float, float]] = (6.3, -4.6)

    def warp(self, data, *, state, drawn):
        h, w = data.shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        cx, cy = (w - 1) / 2, (h - 1) / 2
        return Warp(((u - self.shift[0] - cx) / self.scale + cx).astype(np.float32),
                    ((v - self.shift[1] - cy) / self.scale + cy).astype(np.float32))

    def forward(self, x, y, w, h):
        cx, cy = (w - 1) / 2, (h - 1) / 2
        return (x - cx) * self.scale + cx + self.shift[0], (y - cy) * self.scale + cy + self.shift[1]

    def apply(self, data, *, state, drawn, rng):
        return data.with_signal(self.warp(data, state=state, drawn=drawn).apply(data.signal())), {}


@pytest.fixture
def cityscapes(tmp_path: Path, monkeypatch) -> Path:
    monkeypatch.setitem(MODELS, WarpTestCamera.id, WarpTestCamera)
    root = tmp_path / "in"
    rng = np.random.default_rng(2)
    h, w = 60, 80
    img = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    write_image(root / "leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png", img, ImageEncoding())
    labels = rng.integers(0, 34, (h, w)).astype(np.uint8)
    instances = rng.integers(0, 30000, (h, w)).astype(np.uint16)
    gt = root / "gtFine/val/lindau"
    gt.mkdir(parents=True)
    cv2.imwrite(str(gt / "lindau_000001_000019_gtFine_labelIds.png"), labels)
    cv2.imwrite(str(gt / "lindau_000001_000019_gtFine_instanceIds.png"), instances)
    (gt / "lindau_000001_000019_label_2.txt").write_text(
        "Car 0.00 0 -1.58 10.00 12.50 40.25 30.00 1.50 1.60 3.90 -1.00 1.70 12.00 -1.59\n"
        "Pedestrian 0.00 1 0.20 70.00 50.00 79.00 59.00 1.70 0.60 0.80 3.00 1.70 9.00 0.10\n"
        "Cyclist 0.00 0 0.20 0.00 0.00 2.00 2.00 1.70 0.60 0.80 3.00 1.70 9.00 0.10\n")
    (gt / "lindau_000001_000019_yolo.txt").write_text("2 0.25 0.5 0.2 0.3\n0 0.1 0.1 0.4 0.1 0.4 0.4\n")
    return root


def _gt(suffix: str) -> dict:
    """Cityscapes: leftImg8bit/… /X_leftImg8bit.png → gtFine/… /X_<suffix>."""
    return {"replace": {"leftImg8bit/": "gtFine/", "_leftImg8bit.png": f"_{suffix}"}}


def test_mask_through_a_geometric_model_equals_the_image_map(cityscapes, tmp_path):
    """The mask is resampled through the very map that moved the image (nearest neighbour; where the map leaves
    the image Cityscapes' label-id and instance-id maps get 0, "unlabeled", not 255, an id their devkit does not
    know), pixel for pixel; the image is the map applied to the input; the masks are no inputs."""
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "**/*.png", "annotations": {"masks": [_gt("gtFine_labelIds.png"), _gt("gtFine_instanceIds.png")],
                                              "boxes_2d": _gt("label_2.txt")}}}, tmp_path)
    image_rel = "leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png"
    assert [s.relpath for s in discover(cityscapes, recipe)] == [image_rel]
    out = tmp_path / "out"
    assert run(recipe, cityscapes, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    model = WarpTestCamera()
    frame = load(Sample(image_rel, "camera", "leftImg8bit/val/lindau"), cityscapes, recipe)
    warp = model.warp(frame, state={}, drawn={})
    frac = np.abs(np.concatenate([warp.map_x.ravel(), warp.map_y.ravel()]) % 1 - 0.5)
    assert frac.min() > 1e-3                                          # no rounding ties in the oracle
    write_image(tmp_path / "expected.png", warp.apply(frame.linear_rgb), frame.encoding)
    np.testing.assert_array_equal(read_image(out / image_rel)[0], read_image(tmp_path / "expected.png")[0])
    xs, ys = np.rint(warp.map_x).astype(int), np.rint(warp.map_y).astype(int)
    inside = (xs >= 0) & (xs < 80) & (ys >= 0) & (ys < 60)
    for name in ("labelIds", "instanceIds"):
        mask_in = cv2.imread(str(cityscapes / f"gtFine/val/lindau/lindau_000001_000019_gtFine_{name}.png"),
                             cv2.IMREAD_UNCHANGED)
        mask_out = cv2.imread(str(out / f"gtFine/val/lindau/lindau_000001_000019_gtFine_{name}.png"),
                              cv2.IMREAD_UNCHANGED)
        assert mask_out.dtype == mask_in.dtype and mask_out.shape == mask_in.shape
        oracle = np.where(inside, mask_in[np.clip(ys, 0, 59), np.clip(xs, 0, 79)], 0)      # class 0 "unlabeled"
        np.testing.assert_array_equal(mask_out, oracle)
        assert np.any(~inside)
    # KITTI boxes: corners through the closed-form forward map, clipped; other fields kept; a box pushed off the
    # image is dropped
    lines = (out / "gtFine/val/lindau/lindau_000001_000019_label_2.txt").read_text().splitlines()
    assert [ln.split()[0] for ln in lines] == ["Car", "Pedestrian"]
    car = lines[0].split()
    x0, y0 = model.forward(10.0, 12.5, 80, 60)
    x1, y1 = model.forward(40.25, 30.0, 80, 60)
    np.testing.assert_allclose([float(v) for v in car[4:8]], [x0, y0, x1, y1], atol=0.01)
    assert car[8:] == "1.50 1.60 3.90 -1.00 1.70 12.00 -1.59".split() and car[:4] == ["Car", "0.00", "0", "-1.58"]
    ped = [float(v) for v in lines[1].split()[4:8]]
    assert ped[2] == 79.0 and ped[0] < 79.0                          # clipped to the image
    entry = read_manifest(out / "manifest.jsonl")[0]
    assert len(entry["files"]) == 4 and {a["role"] for a in entry["annotations_read"]} == {"mask", "boxes_2d"}
    assert replay(out / "manifest.jsonl", image_rel)["match"]


def test_palette_and_rgba_masks_keep_their_kind_through_a_warp(cityscapes, tmp_path):
    """A palette PNG (Pascal VOC SegmentationClass: 21 colours) stays a palette PNG of class indices with its
    palette, extended to the fill index; an RGBA bitmask (BDD100K: category, attributes, instance) gets the fill
    value in every channel. OpenCV decoded the palette to colours, written back as an RGB image, and filled the
    first channel only."""
    from PIL import Image

    gt = cityscapes / "gtFine/val/lindau"
    rng = np.random.default_rng(5)
    classes = rng.integers(0, 21, (60, 80)).astype(np.uint8)
    voc = Image.fromarray(classes, "P")
    palette = rng.integers(0, 256, 3 * 21).astype(np.uint8).tolist()
    voc.putpalette(palette)
    voc.save(gt / "lindau_000001_000019_voc.png", transparency=0)
    bitmask = rng.integers(0, 200, (60, 80, 4)).astype(np.uint8)
    cv2.imwrite(str(gt / "lindau_000001_000019_bitmask.png"), bitmask)
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {"masks": [_gt("voc.png"), _gt("bitmask.png")]}}}, tmp_path)
    out = tmp_path / "out"
    assert run(recipe, cityscapes, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    frame = load(Sample("leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png", "camera",
                        "leftImg8bit/val/lindau"), cityscapes, recipe)
    warp = WarpTestCamera().warp(frame, state={}, drawn={})
    xs, ys = np.rint(warp.map_x).astype(int), np.rint(warp.map_y).astype(int)
    inside = (xs >= 0) & (xs < 80) & (ys >= 0) & (ys < 60)
    assert np.any(~inside)
    with Image.open(out / "gtFine/val/lindau/lindau_000001_000019_voc.png") as written:
        assert written.mode == "P" and written.info.get("transparency") == 0
        assert written.getpalette()[:3 * 21] == palette and len(written.getpalette()) == 3 * 256
        np.testing.assert_array_equal(np.asarray(written), np.where(inside, classes[np.clip(ys, 0, 59),
                                                                                     np.clip(xs, 0, 79)], 255))
    small = Image.fromarray(classes % 11, "P")                    # 11 colours: PIL writes a 4-bit palette PNG
    small.putpalette(palette[:33])
    small.save(tmp_path / "4bit.png", bits=4)
    assert (tmp_path / "4bit.png").read_bytes()[24] == 4
    np.testing.assert_array_equal(ann_io.read_mask(tmp_path / "4bit.png").values, classes % 11)
    moved = cv2.imread(str(out / "gtFine/val/lindau/lindau_000001_000019_bitmask.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(moved, np.where(inside[..., None], bitmask[np.clip(ys, 0, 59), np.clip(xs, 0, 79)],
                                                  255))


def _warp_test_inside(root: Path, recipe):
    """The pull map of WarpTestCamera on the Cityscapes fixture's image, rounded, and where it lies in the image."""
    frame = load(Sample("leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png", "camera",
                        "leftImg8bit/val/lindau"), root, recipe)
    warp = WarpTestCamera().warp(frame, state={}, drawn={})
    xs, ys = np.rint(warp.map_x).astype(int), np.rint(warp.map_y).astype(int)
    return np.clip(xs, 0, 79), np.clip(ys, 0, 59), (xs >= 0) & (xs < 80) & (ys >= 0) & (ys < 60)


def test_one_bit_and_four_bit_masks_keep_their_bit_depth_through_a_warp(cityscapes, tmp_path):
    """A 1-bit grey PNG (a binary segmentation mask) and a 4-bit palette PNG come out with their bit depth (and
    palette), their values the input's levels through the map; where nothing maps they get 0, since the default
    ignore_index 255 does not fit. Before, both were written 8-bit, the binary mask as 0/255 with 255 fill."""
    from PIL import Image

    gt = cityscapes / "gtFine/val/lindau"
    rng = np.random.default_rng(12)
    binary = rng.integers(0, 2, (60, 80)).astype(bool)
    Image.fromarray(binary).save(gt / "lindau_000001_000019_binary.png")            # mode "1": 1-bit grey
    classes = rng.integers(0, 11, (60, 80)).astype(np.uint8)
    small = Image.fromarray(classes, "P")
    palette = rng.integers(0, 256, 33).astype(np.uint8).tolist()
    small.putpalette(palette)
    small.save(gt / "lindau_000001_000019_p4.png", bits=4)
    head = {n: (gt / f"lindau_000001_000019_{n}.png").read_bytes()[24:26] for n in ("binary", "p4")}
    assert head == {"binary": b"\x01\x00", "p4": b"\x04\x03"}                      # bit depth, colour type
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {"masks": [_gt("binary.png"), _gt("p4.png")]}}}, tmp_path)
    out = tmp_path / "out/gtFine/val/lindau"
    assert run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    xs, ys, inside = _warp_test_inside(cityscapes, recipe)
    for name, levels in (("binary", binary.astype(np.uint8)), ("p4", classes)):
        data = (out / f"lindau_000001_000019_{name}.png").read_bytes()
        assert data[24:26] == head[name]
        with Image.open(out / f"lindau_000001_000019_{name}.png") as written:
            values = np.asarray(written).astype(np.uint8)
            if name == "p4":
                assert written.mode == "P" and written.getpalette()[:33] == palette
        np.testing.assert_array_equal(values, np.where(inside, levels[ys, xs], 0))
        np.testing.assert_array_equal(ann_io.read_mask(out / f"lindau_000001_000019_{name}.png").values,
                                      np.where(inside, levels[ys, xs], 0))


def test_one_bit_tiff_masks_keep_their_bit_depth_and_white_level(cityscapes, tmp_path):
    """A 1-bit TIFF mask — Pillow's mode "1" with CCITT group 4 (a scanner's or GIS tool's binary mask) and a
    MinIsWhite one (fax convention: 0 is white) — comes out 1-bit with its photometric interpretation, reading as
    the input read (Pillow: white = True) through the map, 0 where nothing maps. Before round 22 both came out
    8-bit 0/255 with fill 255, the MinIsWhite one as MinIsBlack."""
    import tifffile
    from PIL import Image

    gt = cityscapes / "gtFine/val/lindau"
    binary = np.random.default_rng(13).integers(0, 2, (60, 80)).astype(bool)
    Image.fromarray(binary).save(gt / "lindau_000001_000019_g4.tif", compression="group4")
    tifffile.imwrite(gt / "lindau_000001_000019_white0.tif", ~binary, photometric="miniswhite")
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {"masks": [_gt("g4.tif"), _gt("white0.tif")]}}}, tmp_path)
    assert run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    xs, ys, inside = _warp_test_inside(cityscapes, recipe)
    oracle = np.where(inside, binary[ys, xs], False)
    for name, photometric in (("g4", tifffile.PHOTOMETRIC.MINISBLACK), ("white0", tifffile.PHOTOMETRIC.MINISWHITE)):
        path = tmp_path / f"out/gtFine/val/lindau/lindau_000001_000019_{name}.tif"
        with tifffile.TiffFile(path) as tif:
            assert (tif.pages[0].bitspersample, tif.pages[0].photometric) == (1, photometric)
        with Image.open(gt / path.name) as read_in, Image.open(path) as written:
            assert read_in.mode == written.mode == "1"
            np.testing.assert_array_equal(np.asarray(read_in), binary)
            np.testing.assert_array_equal(np.asarray(written), oracle)


def test_a_mask_fill_value_is_per_mask_and_must_fit(cityscapes, tmp_path):
    """``{replace: …, fill: N}`` (or ``{pattern: …, fill: N}``) sets what an uncovered pixel of that mask gets;
    a fill the mask's values cannot hold fails that image naming the mask."""
    fill_7 = {**_gt("gtFine_labelIds.png"), "fill": 7}
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {"masks": [fill_7, {**_gt("gtFine_instanceIds.png"),
                                                                             "fill": 40000}]}}}, tmp_path)
    out = tmp_path / "out/gtFine/val/lindau"
    assert run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    xs, ys, inside = _warp_test_inside(cityscapes, recipe)
    for name, fill in (("labelIds", 7), ("instanceIds", 40000)):
        mask_in = cv2.imread(str(cityscapes / f"gtFine/val/lindau/lindau_000001_000019_gtFine_{name}.png"),
                             cv2.IMREAD_UNCHANGED)
        mask_out = cv2.imread(str(out / f"lindau_000001_000019_gtFine_{name}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(mask_out, np.where(inside, mask_in[ys, xs], fill))
    bad = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {"camera": "leftImg8bit/**/*.png",
                   "annotations": {"masks": {"pattern": "../../../gtFine/val/lindau/{stem}.png", "fill": 300}}}},
                  tmp_path)
    cv2.imwrite(str(cityscapes / "gtFine/val/lindau/lindau_000001_000019_leftImg8bit.png"),
                np.zeros((60, 80), np.uint8))
    summary = run(bad, cityscapes, tmp_path / "out2", workers=1, progress=False, echo=lambda *_: None)
    assert summary.failed == 1
    error = read_manifest(tmp_path / "out2/manifest.jsonl")[0]["error"]
    assert "fill 300" in error and "lindau_000001_000019_leftImg8bit.png" in error and "0 … 255" in error


def test_yolo_boxes_and_polygons_follow_the_map(cityscapes, tmp_path):
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {
            "boxes_2d": _gt("yolo.txt"),
            "boxes_2d_format": "yolo"}}}, tmp_path)
    out = tmp_path / "out"
    assert run(recipe, cityscapes, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    model = WarpTestCamera()
    box, poly = [ln.split() for ln in (out / "gtFine/val/lindau/lindau_000001_000019_yolo.txt").read_text()
                 .splitlines()]
    (x0, x1), (y0, y1) = model.forward(np.array([0.15, 0.35]) * 80 - 0.5, np.array([0.35, 0.65]) * 60 - 0.5, 80, 60)
    x0, x1, y0, y1 = (x0 + 0.5) / 80, (x1 + 0.5) / 80, (y0 + 0.5) / 60, (y1 + 0.5) / 60
    np.testing.assert_allclose([float(v) for v in box[1:]], [(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0],
                               atol=1e-5)
    # the polygon: an affine map moves its vertices exactly; two are pushed above the image, whose top edge cuts
    # the two edges to the third (Sutherland–Hodgman), not the vertices' own y (that would move the edges)
    px, py = model.forward(np.array([0.1, 0.4, 0.4]) * 80 - 0.5, np.array([0.1, 0.1, 0.4]) * 60 - 0.5, 80, 60)
    a, b, c = np.stack([(px + 0.5) / 80, (py + 0.5) / 60], 1)
    assert a[1] < 0 and b[1] < 0 < c[1]
    cut = [p + (c - p) * (0 - p[1]) / (c[1] - p[1]) for p in (a, b)]
    got = np.array(poly[1:], float).reshape(-1, 2)
    assert len(got) == 3
    np.testing.assert_allclose(got[np.lexsort(got.T[::-1])], np.array(sorted(map(tuple, [*cut, c]))), atol=1e-5)


VOC_XML = """<?xml version="1.0" encoding="utf-8"?>
<annotation>
  <folder>VOC2012</folder><filename>lindau_000001_000019_leftImg8bit.png</filename>
  <source><database>The VOC2007 Database</database></source>
  <size><width>80</width><height>60</height><depth>3</depth></size>
  <segmented>0</segmented>
  <object><name>person</name><pose>Left</pose><truncated>0</truncated><difficult>0</difficult>
    <bndbox><xmin>11</xmin><ymin>13</ymin><xmax>41</xmax><ymax>31</ymax></bndbox>
    <part><name>head</name><bndbox><xmin>20.5</xmin><ymin>14</ymin><xmax>26</xmax><ymax>19</ymax></bndbox></part>
    <part><name>hand</name><bndbox><xmin>1</xmin><ymin>1</ymin><xmax>3</xmax><ymax>3</ymax></bndbox></part>
  </object>
  <object><name>car</name><truncated>1</truncated><bndbox><xmin>1</xmin><ymin>1</ymin><xmax>3</xmax><ymax>2</ymax>
    </bndbox></object>
</annotation>
"""


def test_pascal_voc_boxes_and_parts_follow_the_map(cityscapes, tmp_path):
    """Pascal VOC XML (was refused): object and part boxes (1-based pixel indices) move as KITTI boxes do, integers
    stay integers, a box pushed off the image drops its part or object, every other element is kept; a file for
    another image size fails the image naming both sizes."""
    from xml.etree import ElementTree

    gt = cityscapes / "gtFine/val/lindau"
    (gt / "lindau_000001_000019_voc.xml").write_text(VOC_XML)
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {"camera": "leftImg8bit/**/*.png",
                      "annotations": {"boxes_2d": _gt("voc.xml"), "boxes_2d_format": "voc"}}}, tmp_path)
    assert run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    root = ElementTree.parse(tmp_path / "out/gtFine/val/lindau/lindau_000001_000019_voc.xml").getroot()
    objects = root.findall("object")
    assert [o.findtext("name") for o in objects] == ["person"]                    # the car left the image
    assert [p.findtext("name") for p in objects[0].findall("part")] == ["head"]
    assert root.findtext("source/database") == "The VOC2007 Database" and root.findtext("size/width") == "80"
    assert objects[0].findtext("pose") == "Left"
    model = WarpTestCamera()
    box = objects[0].find("bndbox")
    x0, y0 = model.forward(10.0, 12.0, 80, 60)                                   # 1-based index − 1
    x1, y1 = model.forward(40.0, 30.0, 80, 60)
    assert [box.findtext(k) for k in ("xmin", "ymin", "xmax", "ymax")] == \
        [str(int(round(v + 1))) for v in (x0, y0, x1, y1)]
    head = objects[0].find("part/bndbox")
    hx0, hy0 = model.forward(19.5, 13.0, 80, 60)
    assert float(head.findtext("xmin")) == pytest.approx(hx0 + 1, abs=1e-3) and head.findtext("ymin") == \
        str(int(round(hy0 + 1)))
    (gt / "lindau_000001_000019_voc.xml").write_text(VOC_XML.replace("<width>80</width>", "<width>800</width>"))
    assert run(recipe, cityscapes, tmp_path / "out2", workers=1, progress=False, echo=lambda *_: None).failed == 1
    assert "its size is 800×60 px, the image 80×60" in read_manifest(tmp_path / "out2/manifest.jsonl")[0]["error"]


def test_a_yolo_image_without_a_label_file_is_an_image_without_objects(cityscapes, tmp_path):
    """YOLO writes no label file for an image without objects (a background image); such an image failed ("does
    not exist"). It is augmented, no label file is written for it, its entry says so and one warning counts them;
    a KITTI label_2 file that does not exist still fails its image."""
    write_image(cityscapes / "leftImg8bit/val/lindau/lindau_000002_000019_leftImg8bit.png",
                np.full((60, 80, 3), 0.4, np.float32), ImageEncoding())
    lines = []
    for fmt, suffix in (("yolo", "yolo.txt"), ("kitti", "label_2.txt")):
        recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
            "camera": "leftImg8bit/**/*.png", "annotations": {"boxes_2d": _gt(suffix), "boxes_2d_format": fmt}}},
            tmp_path)
        out = tmp_path / f"out_{fmt}"
        summary = run(recipe, cityscapes, out, workers=1, progress=False, echo=lines.append)
        assert summary.failed == (fmt == "kitti") and summary.done == 1 + (fmt == "yolo")
    entry = read_manifest(tmp_path / "out_yolo" / "manifest.jsonl")[1]
    assert entry["status"] == "ok" and entry["annotations_read"][0]["absent"].startswith("no YOLO label file")
    assert not (tmp_path / "out_yolo/gtFine/val/lindau/lindau_000002_000019_yolo.txt").exists()
    assert (tmp_path / "out_yolo/gtFine/val/lindau/lindau_000001_000019_yolo.txt").is_file()
    assert sum("1 image(s) have no YOLO label file" in ln for ln in lines) == 1


def test_yolo_polygon_follows_a_bending_map():
    """A radial map bends a polygon's straight edges: the moved polygon gains vertices on them and stays within
    2 × the outline tolerance of the exactly moved edges (each sampled at 2 000 points)."""
    class Radial:
        def forward(self, q):
            d = q - [40.0, 30.0]
            return [40.0, 30.0] + d * (1 + 4e-4 * (d ** 2).sum(axis=1, keepdims=True))
    square = np.array([[20.0, 15.0], [60.0, 15.0], [60.0, 45.0], [20.0, 45.0]])
    boxes = ann_io.Boxes2D("yolo", [["0"]], [square], [False])
    (moved,) = annotations.warp_boxes(boxes, [Radial()], 400, 300).points_px
    t = np.linspace(0, 1, 2000)[:, None]
    dense = Radial().forward(np.concatenate([p + t * (q - p) for p, q in zip(square, np.roll(square, -1, 0))]))
    assert len(moved) > 3 * len(square)
    s = np.linspace(0, 1, 50)[:, None]
    chords = np.concatenate([p + s * (q - p) for p, q in zip(moved, np.roll(moved, -1, 0))])
    gap = np.min(np.hypot(*(chords[:, None, :] - dense[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert gap.max() < 2 * outline_warp.OUTLINE_TOLERANCE_PX


def test_photometric_chain_copies_masks_byte_for_byte(cityscapes, tmp_path):
    rel = "gtFine/val/lindau/lindau_000001_000019_gtFine_labelIds.png"
    recipe = _recipe({"chain": [{"model": "compression.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {"masks": _gt("gtFine_labelIds.png")}}}, tmp_path)
    out = tmp_path / "out"
    assert run(recipe, cityscapes, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    assert (out / rel).read_bytes() == (cityscapes / rel).read_bytes()


def test_npy_and_wide_integer_masks_keep_their_dtype_through_a_warp(cityscapes, tmp_path):
    """A .npy mask (labelme's SegmentationClassNpy, int32) and uint32 / int64 ids: nearest-neighbour like PNG masks,
    dtype kept (OpenCV refused uint32 and returned int64 as int32); the same pixels as the PNG mask of the ids."""
    gt = cityscapes / "gtFine/val/lindau"
    ids = np.random.default_rng(9).integers(0, 2**40, (60, 80)).astype(np.int64)
    np.save(gt / "lindau_000001_000019_wide.npy", ids)
    np.save(gt / "lindau_000001_000019_u32.npy", (ids % 2**32).astype(np.uint32))
    cv2.imwrite(str(gt / "lindau_000001_000019_small.png"), (ids % 60000 + 256).astype(np.uint16))   # never 255
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {"camera": "leftImg8bit/**/*.png",
                      "annotations": {"masks": [_gt("wide.npy"), _gt("u32.npy"), _gt("small.png")]}}}, tmp_path)
    out = tmp_path / "out" / "gtFine/val/lindau"
    assert run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    wide, u32 = np.load(out / "lindau_000001_000019_wide.npy"), np.load(out / "lindau_000001_000019_u32.npy")
    small = cv2.imread(str(out / "lindau_000001_000019_small.png"), cv2.IMREAD_UNCHANGED)
    assert wide.dtype == np.int64 and u32.dtype == np.uint32
    moved = small != 255
    np.testing.assert_array_equal((wide % 60000 + 256)[moved], small[moved])
    np.testing.assert_array_equal(wide[~moved], 255)
    np.testing.assert_array_equal(u32, np.where(moved, wide % 2**32, 255))
    from roadview_noise.errors import RecipeError
    with pytest.raises(RecipeError, match=r"masks\[0\]: .*KITTI-MOTS"):
        _recipe({"cnf": "CNF05", "inputs": {"annotations": {"masks": "../instances_txt/{parent}.txt"}}}, tmp_path)


def test_cityscapes_polygons_follow_the_map_and_are_copied_by_photometric_chains(cityscapes, tmp_path):
    """A per-image polygon JSON (Cityscapes *_gtFine_polygons.json) was refused; its polygons now move through the
    image's own map (vertices by the forward map, clipped to the image), an object pushed off the image is dropped,
    every other key is kept; a photometric chain copies the file byte for byte."""
    rel = "gtFine/val/lindau/lindau_000001_000019_gtFine_polygons.json"
    data = {"imgHeight": 60, "imgWidth": 80, "objects": [
        {"label": "car", "polygon": [[10, 12], [40, 12], [40, 30], [10, 30]], "deleted": 0},
        {"label": "sky", "polygon": [[0, 0], [79, 0], [79, 59], [0, 59]]},
        {"label": "pole", "polygon": [[0, 0], [1, 0], [1, 1]]}]}
    (cityscapes / rel).write_text(json.dumps(data))
    spec = {"camera": "leftImg8bit/**/*.png", "annotations": {"polygons": _gt("gtFine_polygons.json")}}
    out = tmp_path / "out"
    assert run(_recipe({"chain": [{"model": "warp_test.camera"}], "inputs": spec}, tmp_path), cityscapes, out,
               workers=1, progress=False, echo=lambda *_: None).failed == 0
    moved = json.loads((out / rel).read_text())
    assert moved["imgHeight"] == 60 and [o["label"] for o in moved["objects"]] == ["car", "sky"]
    model = WarpTestCamera()
    car = np.array([model.forward(x, y, 80, 60) for x, y in data["objects"][0]["polygon"]])
    np.testing.assert_allclose(moved["objects"][0]["polygon"], car, atol=2e-3)
    assert moved["objects"][0]["deleted"] == 0
    sky = np.array(moved["objects"][1]["polygon"])
    assert sky.min() >= -0.5 and sky[:, 0].max() <= 79.5 and sky[:, 1].max() <= 59.5
    out2 = tmp_path / "out2"
    assert run(_recipe({"chain": [{"model": "compression.camera"}], "inputs": spec}, tmp_path), cityscapes, out2,
               workers=1, progress=False, echo=lambda *_: None).failed == 0
    assert (out2 / rel).read_bytes() == (cityscapes / rel).read_bytes()


def test_labelme_shapes_follow_the_map(cityscapes, tmp_path):
    """A LabelMe JSON (shapes with points and shape_type) under ``polygons``: polygons move and are clipped, a
    rectangle becomes the box of its moved outline, lines, points and circles move point by point (closed-form
    oracle), a shape pushed off the image is dropped, imageData (the image, base64) holds the augmented image's file
    (before round 22: null), every other key is kept; a shape type LabelMe does not have fails the image naming it;
    a file for another image size fails naming both sizes."""
    gt = cityscapes / "gtFine/val/lindau"
    shapes = [{"label": "car", "points": [[10, 12], [40, 12.5], [38, 30], [11, 29]], "group_id": None,
               "shape_type": "polygon", "flags": {}, "description": ""},
              {"label": "sign", "points": [[50, 20], [60, 35]], "group_id": 3, "shape_type": "rectangle", "flags": {}},
              {"label": "lane", "points": [[5, 55], [20, 40], [30, 33]], "shape_type": "linestrip", "flags": {}},
              {"label": "light", "points": [[44, 7]], "shape_type": "point", "flags": {}},
              {"label": "wheel", "points": [[25, 25], [28, 25]], "shape_type": "circle", "flags": {}},
              {"label": "gone", "points": [[0, 0], [2, 0], [1, 2]], "shape_type": "polygon", "flags": {}}]
    data = {"version": "5.4.1", "flags": {"night": False}, "shapes": shapes, "imagePath": "../x.png",
            "imageData": "iVBORw0KGgo=", "imageHeight": 60, "imageWidth": 80}
    (gt / "lindau_000001_000019_labelme.json").write_text(json.dumps(data))
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {"polygons": _gt("labelme.json")}}}, tmp_path)
    assert run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    out = json.loads((tmp_path / "out/gtFine/val/lindau/lindau_000001_000019_labelme.json").read_text())
    image = tmp_path / "out/leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png"
    kept = ("version", "flags", "imagePath", "imageHeight", "imageWidth")
    assert base64.b64decode(out["imageData"]) == image.read_bytes()
    assert {k: out[k] for k in kept} == {k: data[k] for k in kept}
    model = WarpTestCamera()
    forward = lambda p: np.stack(model.forward(*np.asarray(p, float).T, 80, 60), axis=1)   # noqa: E731
    moved = {sh["label"]: sh for sh in out["shapes"]}
    assert list(moved) == ["car", "sign", "lane", "light", "wheel"]                  # "gone" left the image
    assert {k: v for k, v in moved["sign"].items() if k != "points"} == \
        {k: v for k, v in shapes[1].items() if k != "points"}
    np.testing.assert_allclose(moved["car"]["points"], forward(shapes[0]["points"]), atol=2e-3)     # affine
    np.testing.assert_allclose(moved["sign"]["points"], forward(shapes[1]["points"]), atol=2e-3)
    for k in (2, 3, 4):
        np.testing.assert_allclose(moved[shapes[k]["label"]]["points"], forward(shapes[k]["points"]), atol=2e-3)
    data["shapes"].append({"label": "blob", "points": [[1, 1], [5, 5]], "shape_type": "ellipse"})
    (gt / "lindau_000001_000019_labelme.json").write_text(json.dumps(data))
    assert run(recipe, cityscapes, tmp_path / "out2", workers=1, progress=False, echo=lambda *_: None).failed == 1
    assert "shapes of type ellipse" in read_manifest(tmp_path / "out2/manifest.jsonl")[0]["error"]
    data["shapes"].pop()
    data["imageWidth"] = 640
    (gt / "lindau_000001_000019_labelme.json").write_text(json.dumps(data))
    assert run(recipe, cityscapes, tmp_path / "out3", workers=1, progress=False, echo=lambda *_: None).failed == 1
    assert "640×60 px image" in read_manifest(tmp_path / "out3/manifest.jsonl")[0]["error"]


def test_a_labelme_file_embeds_the_augmented_image_under_a_photometric_chain(cityscapes, tmp_path):
    """LabelMe shows ``imageData`` when a file has it, not ``imagePath``: under fog the file copied as read (before
    round 22) showed the clear input with the foggy file beside it. The augmented image's bytes go there, every
    other byte of the file as read; a file without imageData (null) is copied byte for byte."""
    gt = cityscapes / "gtFine/val/lindau"
    source = cityscapes / "leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png"
    text = ('{\n  "version": "5.4.1",\n  "flags": {},\n  "shapes": [\n    {"label": "car", "points": [[10, 12], '
            '[40, 12], [40, 30]], "shape_type": "polygon"}\n  ],\n  "imagePath": "../x.png",\n  "imageData": "'
            + base64.b64encode(source.read_bytes()).decode() + '",\n  "imageHeight": 60,\n  "imageWidth": 80\n}')
    (gt / "a_labelme.json").write_text(text)
    (gt / "b_labelme.json").write_text(text.replace(text[text.index('"imageData"'):text.index(',\n  "imageH')],
                                                    '"imageData": null'))
    for name, want in (("a", "a_labelme.json"), ("b", "b_labelme.json")):
        recipe = _recipe({"chain": [{"model": "compression.camera", "params": {"quality": 40}}], "inputs": {
            "camera": "leftImg8bit/**/*.png", "annotations": {"polygons": "../../../gtFine/val/lindau/" + want}}},
            tmp_path)
        out = tmp_path / f"out_{name}"
        assert run(recipe, cityscapes, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
        written = (out / "gtFine/val/lindau" / want).read_text()
        if name == "b":
            assert written == (gt / want).read_text()
            continue
        augmented = (out / "leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png").read_bytes()
        assert augmented != source.read_bytes()
        assert written == text.replace(base64.b64encode(source.read_bytes()).decode(),
                                       base64.b64encode(augmented).decode())


def test_a_sweep_variant_labelme_file_names_its_own_image(cityscapes, tmp_path):
    """Under a sweep each variant's LabelMe file (``x__quality-40.json``) says ``imagePath`` of its own image
    (``x__quality-40.png``) and embeds that image; before round 22 every variant named the unsuffixed input image,
    which the output tree does not have."""
    gt = cityscapes / "gtFine/val/lindau"
    source = cityscapes / "leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png"
    doc = {"version": "5.4.1", "flags": {}, "shapes": [{"label": "car", "points": [[10, 12], [40, 12], [40, 30]],
                                                        "shape_type": "polygon"}],
           "imagePath": "../../../leftImg8bit/val/lindau/lindau_000001_000019_leftImg8bit.png",
           "imageData": base64.b64encode(source.read_bytes()).decode(), "imageHeight": 60, "imageWidth": 80}
    (gt / "lindau_000001_000019_labelme.json").write_text(json.dumps(doc))
    recipe = _recipe({"chain": [{"model": "compression.camera"}], "sweep": {"compression.camera.quality": [40, 80]},
                      "inputs": {"camera": "leftImg8bit/**/*.png", "annotations": {"polygons": _gt("labelme.json")}}},
                     tmp_path)
    assert run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    written = sorted((tmp_path / "out/gtFine/val/lindau").glob("*labelme*.json"))
    assert len(written) == 2
    for path in written:
        out = json.loads(path.read_text())
        image = (path.parent / out["imagePath"]).resolve()
        suffix = path.stem.removeprefix("lindau_000001_000019_labelme")
        assert suffix and image.name == f"lindau_000001_000019_leftImg8bit{suffix}.png" and image.is_file()
        assert base64.b64decode(out["imageData"]) == image.read_bytes() and out["shapes"] == doc["shapes"]


def test_labelme_shapes_of_a_turned_phone_photo_are_in_displayed_coordinates(tmp_path, monkeypatch):
    """labelme turns a photo by its EXIF orientation when it opens it, so a phone JPEG stored 80×60 with orientation
    6 is labelled as a 60×80 image. Such a file failed ("for a 60×80 px image, … is 80×60"); now its shapes move as
    the displayed photo's (oracle: the test warp's closed form on the 60×80 upright frame, which the chain warps),
    its size stays the displayed one, and imageData becomes null (the output's bytes are stored turned, which
    LabelMe would show unturned)."""
    from PIL import Image

    monkeypatch.setitem(MODELS, WarpTestCamera.id, WarpTestCamera)
    root = tmp_path / "in"
    (root / "phone").mkdir(parents=True)
    exif = Image.Exif()
    exif[274] = 6
    stored = (np.random.default_rng(5).uniform(0, 255, (60, 80, 3))).astype(np.uint8)
    Image.fromarray(stored).save(root / "phone/IMG_1.jpg", quality=95, exif=exif.tobytes())
    shapes = [{"label": "car", "points": [[10, 12], [40, 12.5], [38, 50], [11, 49]], "shape_type": "polygon"},
              {"label": "sign", "points": [[45, 60], [30, 20]], "shape_type": "rectangle"},
              {"label": "light", "points": [[20, 7]], "shape_type": "point"}]
    (root / "phone/IMG_1.json").write_text(json.dumps(
        {"version": "5.4.1", "flags": {}, "shapes": shapes, "imagePath": "IMG_1.jpg", "imageData": "/9j/",
         "imageHeight": 80, "imageWidth": 60}))
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "phone/*.jpg", "annotations": {"polygons": "{stem}.json"}}}, tmp_path)
    assert run(recipe, root, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    out = json.loads((tmp_path / "out/phone/IMG_1.json").read_text())
    assert (out["imageWidth"], out["imageHeight"], out["imageData"]) == (60, 80, None)
    forward = lambda p: np.stack(WarpTestCamera().forward(*np.asarray(p, float).T, 60, 80), axis=1)  # noqa: E731
    moved = {sh["label"]: np.array(sh["points"]) for sh in out["shapes"]}
    np.testing.assert_allclose(moved["car"], forward(shapes[0]["points"]), atol=2e-3)
    np.testing.assert_allclose(moved["sign"], forward([[30, 20], [45, 60]]), atol=2e-3)
    np.testing.assert_allclose(moved["light"], forward(shapes[2]["points"]), atol=2e-3)


def test_a_labelme_mask_shape_is_resampled_like_a_label_image(cityscapes, tmp_path):
    """A LabelMe ``mask`` shape (labelme ≥ 5.3: a 1-bit PNG of its box in base64, placed at the box's first point,
    as in labelme's examples/primitives) goes through the image's map as masks do (nearest neighbour, 0 where
    nothing maps) and is cut to the box of what is left; one pushed off the image is dropped."""
    import io

    from PIL import Image

    blob = np.random.default_rng(3).integers(0, 2, (20, 30)).astype(bool)
    shapes = [{"label": "blob", "points": [[30.6, 20.0], [59.6, 39.0]], "shape_type": "mask", "flags": {},
               "mask": base64.b64encode(_png_of(blob)).decode()},
              {"label": "gone", "points": [[0, 0], [1, 1]], "shape_type": "mask",
               "mask": base64.b64encode(_png_of(np.ones((2, 2), bool))).decode()}]
    (cityscapes / "gtFine/val/lindau/lindau_000001_000019_labelme.json").write_text(json.dumps(
        {"version": "5.7.0", "flags": {}, "shapes": shapes, "imagePath": "x.png", "imageData": None,
         "imageHeight": 60, "imageWidth": 80}))
    recipe = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {"polygons": _gt("labelme.json")}}}, tmp_path)
    assert run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None).failed == 0
    out = json.loads((tmp_path / "out/gtFine/val/lindau/lindau_000001_000019_labelme.json").read_text())
    assert [s["label"] for s in out["shapes"]] == ["blob"]
    xs, ys, inside = _warp_test_inside(cityscapes, recipe)
    frame = np.zeros((60, 80), bool)
    frame[20:40, 30:60] = blob
    oracle = frame[ys, xs] & inside
    rows, cols = np.flatnonzero(oracle.any(axis=1)), np.flatnonzero(oracle.any(axis=0))
    moved = out["shapes"][0]
    assert moved["points"] == [[cols[0], rows[0]], [cols[-1], rows[-1]]]
    with Image.open(io.BytesIO(base64.b64decode(moved["mask"]))) as written:
        assert written.mode == "1"
        np.testing.assert_array_equal(np.asarray(written), oracle[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1])


def _png_of(bitmap: np.ndarray) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(bitmap).save(buf, format="PNG")
    return buf.getvalue()


def test_label_images_a_camera_glob_sweeps_up_fail_alone_naming_the_fix(cityscapes, tmp_path):
    """`camera: "**/*.png"` on a Cityscapes root fogged gtFine's label images as photos, without a word. Each one
    now fails alone, saying why and what to do; a mask declared under annotations is a sidecar, not an input; a glob
    that names the label folder reads its files as photos (the user asked for them)."""
    recipe = _recipe({"chain": [{"model": "compression.camera"}], "inputs": {
        "camera": "**/*.png", "annotations": {"masks": _gt("gtFine_labelIds.png")}}}, tmp_path)
    summary = run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None)
    assert summary.done == 1 and summary.failed == 1
    assert "gtFine_instanceIds.png: looks like a label image, not a photo (in a label folder, gtFine/)" in \
        summary.failures[0] and "inputs.annotations.masks" in summary.failures[0]
    assert not (tmp_path / "out/gtFine/val/lindau/lindau_000001_000019_gtFine_instanceIds.png").exists()
    asked = _recipe({"chain": [{"model": "compression.camera"}], "inputs": {"camera": "gtFine/**/*.png"}}, tmp_path)
    assert len(discover(cityscapes, asked)) == 2
    for rel, why in (("VOC2012/SegmentationClass/2007_000032.png", "in a label folder, SegmentationClass/"),
                     ("bdd100k/labels/lane/masks/val/a.png", "in a label folder, labels/"),
                     ("x/aachen_000000_000019_gtFine_labelTrainIds.png", "named like a label image, "
                                                                         "*_labelTrainIds.png"),
                     ("VOC2012/JPEGImages/2007_000032.jpg", None), ("kitti/training/image_2/000001.png", None)):
        assert annotations.label_image_reason(rel, ["**/*.png", "**/*.jpg"]) == why
    assert annotations.label_image_reason("x/a_gtFine_labelIds.png", ["**/*_labelIds.png"]) is None


@pytest.mark.parametrize("rel,why", [
    ("gt/fog/train/GOPR0475/GOPR0475_frame_000041_gt_invIds.png", "named like a label image, *_gt_invIds.png"),
    ("gt/fog/train/GOPR0475/GOPR0475_frame_000041_gt_labelColor.png", "named like a label image, *_gt_labelColor.png"),
    ("gt/val/night/GOPR0356/GOPR0356_frame_000321_gt_invGray.png", "named like a label image, *_gt_invGray.png"),
    ("data_2d_semantics/train/2013_05_28_drive_0000_sync/image_00/semantic_rgb/0000000250.png",
     "in a label folder, semantic_rgb/"),
    ("data_2d_semantics/train/2013_05_28_drive_0000_sync/image_00/confidence/0000000250.png",
     "in a label folder, confidence/"),
    ("data_semantics/training/instance/000000_10.png", "in a label folder, instance/"),
    ("rgb_anon/fog/train/GOPR0475/GOPR0475_frame_000041_rgb_anon.png", None),
    ("leftImg8bit_foggy/train/aachen/aachen_000000_000019_leftImg8bit_foggy_beta_0.02.png", None),
    ("data_2d_raw/2013_05_28_drive_0000_sync/image_00/data_rect/0000000250.png", None)])
def test_adverse_weather_and_kitti_360_label_images_are_not_photos(rel, why):
    """ACDC's and Dark Zurich's gt/ (invalid-pixel masks, colour label images: not named *_labelIds), KITTI-360's
    and KITTI semantics' semantic_rgb/, confidence/, instance/ folders: a ``**/*.png`` camera glob on such a root
    fogged them as photos before round 22; their photos (rgb_anon/, leftImg8bit_foggy/, data_rect/) stay photos."""
    assert annotations.label_image_reason(rel, ["**/*.png"]) == why


def test_mask_of_another_size_fails_that_image(cityscapes, tmp_path):
    rel = "gtFine/val/lindau/lindau_000001_000019_gtFine_labelIds.png"
    cv2.imwrite(str(cityscapes / rel), np.zeros((30, 40), np.uint8))
    recipe = _recipe({"chain": [{"model": "compression.camera"}], "inputs": {
        "camera": "leftImg8bit/**/*.png", "annotations": {"masks": _gt("gtFine_labelIds.png")}}}, tmp_path)
    summary = run(recipe, cityscapes, tmp_path / "out", workers=1, progress=False, echo=lambda *_: None)
    assert summary.failed == 1 and "40×30" in summary.failures[0] and "80×60" in summary.failures[0]


# --- objects: 3-D boxes ----------------------------------------------------------------------------------------------


def _object_scene() -> tuple[PointCloud, list[dict]]:
    """Rings × columns of an OS1-128 seeing two cars (near at 8 m, far at 45 m) on a ground plane."""
    prof = os1_128()
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))
    az = np.linspace(-0.6, 0.6, 400)
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    ring = np.repeat(np.arange(len(el)), len(az)).astype(np.uint16)
    boxes = [{"id": "near", "class": "car", "center_m": [8.0, 1.0, -1.0], "size_m": [4.0, 1.8, 1.6], "yaw_rad": 0.3},
             {"id": "far", "class": "car", "center_m": [45.0, -3.0, -1.0], "size_m": [4.0, 1.8, 1.6],
              "yaw_rad": -0.2}]
    best = np.full(len(d), np.inf)
    with np.errstate(divide="ignore"):
        t = np.where(d[:, 2] < 0, -1.8 / d[:, 2], np.inf)
    best = np.minimum(best, t)
    for b in boxes:                                  # box faces: sample by marching the ray (fine enough here)
        c, s, yaw = np.array(b["center_m"]), np.array(b["size_m"]) / 2, b["yaw_rad"]
        for r in np.arange(2.0, 60.0, 0.02):
            p = d * r - c
            u = np.cos(yaw) * p[:, 0] + np.sin(yaw) * p[:, 1]
            v = -np.sin(yaw) * p[:, 0] + np.cos(yaw) * p[:, 1]
            hit = (np.abs(u) <= s[0]) & (np.abs(v) <= s[1]) & (np.abs(p[:, 2]) <= s[2]) & (r < best)
            best[hit] = r
    keep = np.isfinite(best) & (best < 80)
    pos = d[keep] * best[keep, None]
    intensity = np.rint(2000.0 / best[keep] ** 2 * 40).astype(np.float32)     # whole photons (fractions: refused)
    layout = CloudLayout("pcd", (("x", "x", "<f4"), ("y", "y", "<f4"), ("z", "z", "<f4"),
                                 ("intensity", "intensity", "<f4"), ("ring", "ring", "<u2")))
    cloud = PointCloud(pos.astype(np.float32).astype(np.float64), {"intensity": intensity, "ring": ring[keep]},
                       "lidar", prof, layout)
    return cloud, boxes


def test_kitti_boxes_read_the_calibration_files_datasets_ship(tmp_path):
    """KITTI 3-D boxes are in the rectified reference camera (camera 0): Waymo in mmdetection3d's KITTI format names
    its transform ``Tr_velo_to_cam_0`` (… ``_4``, one per camera; no plain ``Tr_velo_to_cam``), View-of-Delft leaves
    ``Tr_imu_to_velo:`` empty, the raw recordings write ``calib_time: 09-Jan-2012 13:57:47``: each gives the same
    LiDAR → box-frame transform as KITTI's object calib (before: the Waymo file was refused, the time line failed
    with a ValueError)."""
    tr = "0 -1 0 0.1 0 0 -1 -0.2 1 0 0 -0.3"
    rect = "R0_rect: 1 0 0 0 1 0 0 0 1\n"
    label = tmp_path / "000000.txt"
    label.write_text("Car 0 0 0 0 0 10 10 1.5 1.6 3.9 1 1.2 10 0.3\n")
    files = {"kitti": f"P2: {' '.join(['0'] * 12)}\n{rect}Tr_velo_to_cam: {tr}\n",
             "waymo": "".join(f"P{i}: {' '.join(['0'] * 12)}\n" for i in range(5)) + rect
             + "".join(f"Tr_velo_to_cam_{i}: {tr if i == 0 else ' '.join(['1'] * 12)}\n" for i in range(5)),
             "vod": f"P2: {' '.join(['0'] * 12)}\n{rect}Tr_velo_to_cam: {tr}\nTr_imu_to_velo: \n",
             "raw": f"calib_time: 09-Jan-2012 13:57:47\n{rect}Tr_velo_to_cam: {tr}\n"}
    transforms = {}
    for name, text in files.items():
        (tmp_path / f"{name}.txt").write_text(text)
        transforms[name] = ann_io.read_boxes_3d(label, "kitti", tmp_path / f"{name}.txt").to_box_frame
    for name in files:
        np.testing.assert_array_equal(transforms[name], transforms["kitti"])
    (tmp_path / "none.txt").write_text(rect + "Tr_velo_to_cam_1: " + tr + "\n")
    with pytest.raises(InputError, match="Tr_velo_to_cam"):
        ann_io.read_boxes_3d(label, "kitti", tmp_path / "none.txt")


def test_kitti_tracking_sequence_files_reach_every_frame(tmp_path):
    """KITTI tracking ships one calib and one label file per sequence (``training/velodyne/0000/000001.bin``,
    ``calib/0000.txt`` with KITTI tracking's colon-less ``R_rect`` and ``Tr_velo_cam`` lines, ``label_02/0000.txt``
    whose lines lead with ``frame track_id``): ``{parent}`` (the scan's folder: the sequence) reaches them, each
    frame counts the boxes of its own lines (ids: track ids; DontCare, track −1, skipped), and the two files are
    written once per frame, unchanged, no clash between the frames (nor on --resume). Before: the pattern knew only ``{stem}``/``{name}``, so no frame could name
    its sequence's files, and the calib's colon-less lines were refused. The same file named as 2-D boxes of an
    image is refused (it was read shifted by two columns: the track id as the box's left edge)."""
    cloud, boxes = _object_scene()
    root = tmp_path / "in" / "training"
    for frame in ("000000", "000001"):
        write_pointcloud(root / "velodyne" / "0000" / f"{frame}.pcd", cloud)
    (root / "calib").mkdir()
    (root / "calib" / "0000.txt").write_text(
        "".join(f"P{i}: {' '.join(['0'] * 12)}\n" for i in range(4))
        + "R_rect 1 0 0 0 1 0 0 0 1\nTr_velo_cam 0 -1 0 0 0 0 -1 0 1 0 0 0\nTr_imu_velo 1 0 0 0 0 1 0 0 0 0 1 0\n")
    lines = ["0 -1 DontCare -1 -1 -10 0 0 10 10 -1000 -1000 -1000 -10 -10 -10 -10"]
    for frame, track, b in ((0, 3, boxes[0]), (1, 3, boxes[0]), (1, 7, boxes[1])):
        (x, y, z), (ln, wd, ht) = b["center_m"], b["size_m"]
        lines.append(f"{frame} {track} Car 0 0 0 0 0 10 10 {ht} {wd} {ln} {-y} {-z + ht / 2} {x} "
                     f"{-b['yaw_rad'] - np.pi / 2}")
    (root / "label_02").mkdir()
    (root / "label_02" / "0000.txt").write_text("\n".join(lines) + "\n")
    recipe = _recipe({"chain": [{"model": "fog.lidar", "params": {"visibility_m": 12.0}}],
                      "inputs": {"lidar": "training/velodyne/*/*.pcd", "annotations": {
                          "boxes_3d": "../../label_02/{parent}.txt", "calib": "../../calib/{parent}.txt"}}}, tmp_path)
    out = tmp_path / "out"
    assert run(recipe, tmp_path / "in", out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    objects = {e["input"].rsplit("/", 1)[-1]: e["objects"] for e in read_manifest(out / "manifest.jsonl")}
    assert [o["id"] for o in objects["000000.pcd"]] == ["3"] and [o["id"] for o in objects["000001.pcd"]] == ["3", "7"]
    assert objects["000000.pcd"][0]["points_before"] == objects["000001.pcd"][0]["points_before"] > 50
    for rel in ("label_02/0000.txt", "calib/0000.txt"):
        assert (out / "training" / rel).read_bytes() == (root / rel).read_bytes()
    write_pointcloud(root / "velodyne" / "0000" / "000002.pcd", cloud)             # a frame added: --resume
    again = run(recipe, tmp_path / "in", out, workers=1, resume=True, progress=False, echo=lambda *_: None)
    assert (again.done, again.skipped, again.failed) == (1, 2, 0)
    with pytest.raises(InputError, match="KITTI tracking label .* a sequence file's are not moved"):
        ann_io.read_boxes_2d(root / "label_02" / "0000.txt", "kitti", 1242, 375)    # before: garbage boxes
    with pytest.raises(InputError, match="frame numbers"):
        ann_io.read_boxes_3d(root / "label_02" / "0000.txt", "kitti", root / "calib" / "0000.txt", "scan_a")
    with pytest.raises(RecipeError, match="parts"):
        _recipe({"chain": [{"model": "fog.lidar"}], "inputs": {"lidar": "*.pcd", "annotations": {
            "boxes_3d": "../{folder}.txt", "calib": "c.txt"}}}, tmp_path)


def test_kitti_tracking_2d_boxes_are_copied_where_no_warp_moves_them(tmp_path, monkeypatch):
    """KITTI tracking's ``label_02/0000.txt`` (frame track_id type truncated occluded alpha left top right bottom …,
    every frame of a sequence in one file) named as ``boxes_2d``: a chain without a geometric step moves no box, so
    the file is copied as it is, once per frame, and the manifest says so (``unchanged``); a LiDAR chain may name the
    image boxes of its scans too (copied, said so). Only a camera warp, which would have to move them in a file the
    sequence's frames share, fails the frame, naming the file. Before (round 21): every such frame failed, whatever
    the chain, and a LiDAR recipe refused boxes_2d ("annotate images")."""
    monkeypatch.setitem(MODELS, WarpTestCamera.id, WarpTestCamera)
    root = tmp_path / "in" / "training"
    rng = np.random.default_rng(4)
    for frame in ("000000", "000001"):
        write_image(root / "image_02" / "0000" / f"{frame}.png", rng.random((60, 80, 3)), ImageEncoding())
    (root / "label_02").mkdir()
    label = root / "label_02" / "0000.txt"
    label.write_text("0 -1 DontCare -1 -1 -10.000000 5.0 6.0 20.0 30.0 -1000 -1000 -1000 -10 -10 -10 -10\n"
                     "0 3 Car 0 0 -1.57 10.5 12.0 40.25 30.0 1.50 1.60 3.90 -1.00 1.70 12.00 -1.59\n"
                     "1 3 Car 0 0 -1.57 11.5 12.0 41.25 30.0 1.50 1.60 3.90 -1.00 1.70 11.00 -1.59\n")
    spec = {"camera": "training/image_02/*/*.png", "annotations": {"boxes_2d": "../../label_02/{parent}.txt"}}
    photometric = _recipe({"chain": [{"model": "compression.camera"}], "inputs": spec}, tmp_path)
    out = tmp_path / "out"
    assert run(photometric, tmp_path / "in", out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    assert (out / "training" / "label_02" / "0000.txt").read_bytes() == label.read_bytes()
    for entry in read_manifest(out / "manifest.jsonl"):
        read, = entry["annotations_read"]
        assert read["role"] == "boxes_2d" and "KITTI tracking sequence file: copied" in read["unchanged"]
    warped = _recipe({"chain": [{"model": "warp_test.camera"}], "inputs": spec}, tmp_path)
    result = run(warped, tmp_path / "in", tmp_path / "out_w", workers=1, progress=False, echo=lambda *_: None)
    assert result.failed == 2
    errors = [e["error"] for e in read_manifest(tmp_path / "out_w" / "manifest.jsonl")]
    assert all("label_02/0000.txt is a KITTI tracking label file" in e and "warp_test.camera" in e for e in errors)
    assert not (tmp_path / "out_w" / "training" / "label_02").exists()
    # a LiDAR chain: its scans' image boxes are copied, said so
    cloud, _ = _object_scene()
    write_pointcloud(root / "velodyne" / "0000" / "000000.pcd", cloud)
    lidar = _recipe({"chain": [{"model": "fog.lidar", "params": {"visibility_m": 30.0}}], "inputs": {
        "lidar": "training/velodyne/*/*.pcd", "annotations": {"boxes_2d": "../../label_02/{parent}.txt"}}}, tmp_path)
    assert run(lidar, tmp_path / "in", tmp_path / "out_l", workers=1, progress=False, echo=lambda *_: None).failed == 0
    assert (tmp_path / "out_l" / "training" / "label_02" / "0000.txt").read_bytes() == label.read_bytes()
    read, = read_manifest(tmp_path / "out_l" / "manifest.jsonl")[0]["annotations_read"]
    assert read["unchanged"].startswith("image boxes: a point-cloud chain moves none")


def test_objects_count_their_points_before_and_after(tmp_path):
    """JSON boxes in the sensor frame and the same boxes as KITTI label_2 + calib give the same counts; in dense fog
    the far car keeps none of its points: the manifest marks it lost."""
    cloud, boxes = _object_scene()
    root = tmp_path / "in" / "lidar"
    write_pointcloud(root / "000000.pcd", cloud)
    (root / "000000.json").write_text(json.dumps({"boxes": boxes}))
    # KITTI: camera x = −y_velo, y = −z_velo, z = x_velo; bottom-centre; rotation_y = −yaw − π/2 (KITTI devkit)
    calib = "P2: " + " ".join(["0"] * 12) + "\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n"
    (root / "000000_calib.txt").write_text(calib)
    lines = []
    for b in boxes:
        (x, y, z), (ln, wd, ht) = b["center_m"], b["size_m"]
        lines.append(f"Car 0 0 0 0 0 10 10 {ht} {wd} {ln} {-y} {-z + ht / 2} {x} {-b['yaw_rad'] - np.pi / 2}")
    (root / "000000_label.txt").write_text("\n".join(lines) + "\n")
    counts = {}
    for fmt, spec in (("json", {"boxes_3d": "{stem}.json"}),
                      ("kitti", {"boxes_3d": "{stem}_label.txt", "calib": "{stem}_calib.txt"})):
        recipe = _recipe({"chain": [{"model": "fog.lidar", "params": {"visibility_m": 12.0}}],
                          "inputs": {"lidar": "lidar/*.pcd", "annotations": spec}}, tmp_path)
        out = tmp_path / f"out-{fmt}"
        assert run(recipe, tmp_path / "in", out, workers=1, progress=False, echo=lambda *_: None).failed == 0
        counts[fmt] = read_manifest(out / "manifest.jsonl")[0]["objects"]
        assert (out / "lidar" / ("000000.json" if fmt == "json" else "000000_calib.txt")).is_file()
    near, far = counts["json"]
    # independent count: points of the input inside each box, by rotating the points into the box frame
    for b, obj in zip(boxes, (near, far)):
        p = cloud.positions_m - b["center_m"]
        c, s = np.cos(b["yaw_rad"]), np.sin(b["yaw_rad"])
        local = np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]], 1)
        assert obj["points_before"] == int(np.all(np.abs(local) <= np.array(b["size_m"]) / 2, axis=1).sum()) > 50
    assert near["points_after"] > 0 and not near["lost"]
    assert far["points_after"] == 0 and far["lost"]
    assert [(o["points_before"], o["points_after"]) for o in counts["kitti"]] == \
        [(o["points_before"], o["points_after"]) for o in counts["json"]]


def test_a_box_json_of_another_layout_is_refused_naming_the_expected_one(tmp_path):
    """View-of-Delft's radar ``label_2/*.json`` (segments.ai: className, geometry.center/size/quaternion) is not
    rvnoise's box JSON: the refusal names the missing key and the layout expected, not ``KeyError('center_m')``."""
    (tmp_path / "00549.json").write_text(json.dumps([{"id": "d3b9", "className": "bicycle", "geometry": {
        "size": {"height": 1.2, "width": 0.77, "length": 2.08}, "center": {"x": 11.5, "y": 2.9, "z": -0.4},
        "quaternion": {"x": 0, "y": 0, "z": 0.04, "w": 0.999}}}]))
    with pytest.raises(InputError, match=r"no 'center_m'\); expected \[\{.*KITTI label_2"):
        ann_io.read_boxes_3d(tmp_path / "00549.json", "json")
    (tmp_path / "b.csv").write_text("id,class,x,y,z\n1,car,1,2,3\n")
    with pytest.raises(InputError, match="no 'x_m'.*header id,class,x_m"):
        ann_io.read_boxes_3d(tmp_path / "b.csv", "csv")
