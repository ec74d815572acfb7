"""Every recipe of the README table "Which depth do I have?" (recipes/examples/) runs on the data it is written for:
the sample drive, or a tree built here in that dataset's layout from the sample drive (Cityscapes, KITTI, CARLA,
planar NPY, photos with a monocular model). The depth each loads is checked against the sample's rendered range."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from roadview_noise.dataset import discover, load
from roadview_noise.io.depth import read_depth, write_carla_depth_png
from roadview_noise.manifest import read_manifest
from roadview_noise.profiles.camera import load_camera_profile
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import run
from roadview_noise.units import ray_factor

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_data"
EXAMPLES = ROOT / "recipes" / "examples"
CAM = SAMPLE / "camera" / "seq0"


@pytest.fixture(scope="module")
def sample():
    if not SAMPLE.is_dir():
        pytest.skip("sample_data/ missing")
    profile = load_camera_profile(str(CAM / "camera.yaml"))
    rng = read_depth(CAM / "000000_depth.exr")
    k = ray_factor(profile.width_px, profile.height_px, profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px)
    return profile, rng, rng / k                                         # profile, range, planar z


def _run(recipe, in_root, tmp_path, n=None):
    lines = []
    summary = run(recipe, in_root, tmp_path / "out", workers=1, progress=False, echo=lines.append)
    entries = read_manifest(tmp_path / "out" / "manifest.jsonl")
    assert summary.failed == 0, [e.get("error") for e in entries]
    assert summary.done == len(entries) == (n or len(entries)) > 0
    return entries, lines


def _loaded_depth(recipe, in_root):
    s = discover(in_root, recipe)[0]
    return load(s, in_root, recipe)


def _median_rel(a, b):
    both = np.isfinite(a) & np.isfinite(b)
    return float(np.median(np.abs(a[both] - b[both]) / b[both]))


@pytest.mark.parametrize("name", ["depth-range-exr", "depth-lidar-sample", "depth-ground-plane", "photo-jpeg-only"])
def test_examples_on_the_sample_drive(tmp_path, sample, name):
    recipe = load_recipe(EXAMPLES / f"{name}.yaml")
    entries, lines = _run(recipe, SAMPLE, tmp_path)
    depth = entries[0].get("inputs", {}).get("depth")
    if name == "depth-lidar-sample":
        assert depth["source"] == "lidar" and entries[0]["depth"] is None
        assert _median_rel(_loaded_depth(recipe, SAMPLE).depth_m, sample[1]) < 0.05
    elif name == "depth-ground-plane":
        assert {k: depth[k] for k in ("source", "camera_height_m", "pitch_deg", "sky_distance_m", "objects")} == {
            "source": "ground_plane", "camera_height_m": 1.0, "pitch_deg": 0.0, "sky_distance_m": 100.0,
            "objects": True}
        assert depth["road_seed_pixels"] > 0 and 0 < depth["sky_fraction"] < 1
        assert len(lines) == 1 and "ground-plane prior" in lines[0]
    elif name == "photo-jpeg-only":
        assert depth is None and "camera" not in entries[0].get("inputs", {})
    else:
        assert depth == {"source": "file", "file": "camera/seq0/000000_depth.exr", "format": "exr", "kind": "range",
                         "holes": 0}


def test_planar_npy(tmp_path, sample):
    profile, rng, z = sample
    seq = tmp_path / "in" / "camera" / "seq0"
    seq.mkdir(parents=True)
    shutil.copy(CAM / "000000.png", seq)
    shutil.copy(CAM / "camera.yaml", seq)
    np.save(seq / "000000_z.npy", z)
    recipe = load_recipe(EXAMPLES / "depth-planar-npy.yaml")
    _run(recipe, tmp_path / "in", tmp_path, 1)
    np.testing.assert_allclose(_loaded_depth(recipe, tmp_path / "in").depth_m, rng, rtol=1e-5)


def test_carla_png(tmp_path):
    """A 640×360 frame with a CARLA depth PNG of a flat road (planar z from the recipe's 90° pinhole)."""
    from roadview_noise.depth.ground_plane import ground_plane_range

    recipe = load_recipe(EXAMPLES / "depth-carla-png.yaml")
    w, h = 640, 360
    fx = w / 2                                                           # 90° horizontal FOV
    cx, cy = (w - 1) / 2, (h - 1) / 2
    truth = ground_plane_range((fx, fx, cx, cy), w, h, camera_height_m=1.6, sky_distance_m=900.0)
    truth[: int(cy) + 1] = np.inf                                        # sky above the horizon: the far plane
    root = tmp_path / "in"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    cv2.imwrite(str(root / "rgb" / "000123.png"), np.random.default_rng(0).integers(0, 256, (h, w, 3), np.uint8))
    write_carla_depth_png(root / "depth" / "000123.png", truth / ray_factor(w, h, fx, fx, cx, cy))
    entries, _ = _run(recipe, root, tmp_path, 1)
    assert entries[0]["inputs"]["depth"]["format"] == "carla"
    got = _loaded_depth(recipe, root).depth_m
    assert (np.isinf(got) == np.isinf(truth)).all()
    np.testing.assert_allclose(got[np.isfinite(truth)], truth[np.isfinite(truth)], rtol=1e-4, atol=1e-3)


def test_kitti_depth_png(tmp_path, sample):
    """Sparse KITTI-style depth (15 % of the pixels, the rest 0) with calib_cam_to_cam.txt: holes are filled (one
    warning for the run) and the map is close to the rendered one."""
    profile, rng, z = sample
    drive = tmp_path / "in" / "2011_09_26_drive_0001_sync"
    (drive / "image_02" / "data").mkdir(parents=True)
    (drive / "proj_depth" / "groundtruth" / "image_02").mkdir(parents=True)
    shutil.copy(CAM / "000000.png", drive / "image_02" / "data" / "0000000005.png")
    keep = (np.random.default_rng(0).random(z.shape) < 0.15) & (z < 255)       # KITTI codes end at 256 m
    codes = np.where(keep, np.rint(np.nan_to_num(z, posinf=0) * 256), 0).astype(np.uint16)
    cv2.imwrite(str(drive / "proj_depth" / "groundtruth" / "image_02" / "0000000005.png"), codes)
    (tmp_path / "in" / "calib_cam_to_cam.txt").write_text(
        f"S_rect_02: {profile.width_px} {profile.height_px}\n"
        f"P_rect_02: {profile.fx_px} 0 {profile.cx_px} 0 0 {profile.fy_px} {profile.cy_px} 0 0 0 1 0\n")
    recipe = load_recipe(EXAMPLES / "depth-kitti-png.yaml")
    entries, lines = _run(recipe, tmp_path / "in", tmp_path, 1)
    notes = entries[0]["inputs"]["depth"]
    assert notes["format"] == "kitti" and notes["hole_fraction"] > 0.8 and notes["policy"] == "fill"
    assert len(lines) == 1 and "depth holes filled" in lines[0]
    got = _loaded_depth(recipe, tmp_path / "in").depth_m
    assert np.isfinite(got).all()
    assert _median_rel(got, rng) < 0.05
    np.testing.assert_allclose(got[keep], rng[keep], rtol=2e-3)        # measured pixels: z/256 quantisation


def test_kitti_depth_selection_layout(tmp_path, sample):
    """KITTI's depth_selection/val_selection_cropped: image/…_sync_image_N_image_02.png, its depth
    velodyne_raw/…_sync_velodyne_raw_N_image_02.png (a name no {stem} pattern gives: inputs.depth takes a
    {replace: …} rule) and intrinsics/…_sync_image_N_image_02.txt (K alone, 9 numbers: was refused as a KITTI
    calibration without P2)."""
    from roadview_noise.recipe import parse_recipe

    profile, rng, z = sample
    root = tmp_path / "in" / "val_selection_cropped"
    for d in ("image", "velodyne_raw", "intrinsics"):
        (root / d).mkdir(parents=True)
    name = "2011_09_26_drive_0002_sync_{}_0000000005_image_02"
    shutil.copy(CAM / "000000.png", root / "image" / f"{name.format('image')}.png")
    keep = (np.random.default_rng(1).random(z.shape) < 0.15) & (z < 255)
    cv2.imwrite(str(root / "velodyne_raw" / f"{name.format('velodyne_raw')}.png"),
                np.where(keep, np.rint(np.nan_to_num(z, posinf=0) * 256), 0).astype(np.uint16))
    (root / "intrinsics" / f"{name.format('image')}.txt").write_text(
        f"{profile.fx_px} 0.0 {profile.cx_px} 0.0 {profile.fy_px} {profile.cy_px} 0.0 0.0 1.0\n")
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "chain": [{"model": "fog.camera"}], "inputs": {
        "camera": "val_selection_cropped/image/*.png", "depth_format": "kitti",
        "depth": {"replace": {"/image/": "/velodyne_raw/", "_sync_image_": "_sync_velodyne_raw_"}},
        "calibration": "../intrinsics/{stem}.txt"}})
    entries, _ = _run(recipe, tmp_path / "in", tmp_path, 1)
    depth_file = f"val_selection_cropped/velodyne_raw/{name.format('velodyne_raw')}.png"
    assert entries[0]["inputs"]["depth"]["file"] == depth_file
    got = _loaded_depth(recipe, tmp_path / "in").depth_m
    np.testing.assert_allclose(got[keep], rng[keep], rtol=2e-3)        # z/256 with the intrinsics of the K file


def test_cityscapes_disparity(tmp_path, sample):
    """Cityscapes layout from the sample drive: disparity p = 1 + 256·B·fx/z, sky and a 'hood' strip invalid (0)."""
    profile, rng, z = sample
    baseline = 0.209313
    root = tmp_path / "cityscapes"
    name = "aachen_000000_000019"
    for folder in ("leftImg8bit", "disparity", "camera"):
        (root / folder / "train" / "aachen").mkdir(parents=True)
    shutil.copy(CAM / "000000.png", root / "leftImg8bit" / "train" / "aachen" / f"{name}_leftImg8bit.png")
    with np.errstate(divide="ignore"):
        codes = np.rint(1 + 256 * baseline * profile.fx_px / z)
    codes[~np.isfinite(z)] = 0
    codes[-12:] = 0                                                      # the ego car's hood: invalid
    cv2.imwrite(str(root / "disparity" / "train" / "aachen" / f"{name}_disparity.png"), codes.astype(np.uint16))
    cam = {"extrinsic": {"baseline": baseline, "pitch": 0.0, "roll": 0.0, "x": 1.7, "y": 0.1, "yaw": 0.0, "z": 1.0},
           "intrinsic": {"fx": profile.fx_px, "fy": profile.fy_px, "u0": profile.cx_px, "v0": profile.cy_px}}
    (root / "camera" / "train" / "aachen" / f"{name}_camera.json").write_text(json.dumps(cam))
    recipe = load_recipe(EXAMPLES / "depth-cityscapes.yaml")
    entries, _ = _run(recipe, root, tmp_path, 1)
    notes = entries[0]["inputs"]
    assert notes["depth"]["format"] == "cityscapes" and notes["depth"]["sky"] > 0 and notes["depth"]["filled"] > 0
    assert notes["camera"]["from"].startswith("calibration intrinsics")
    got = _loaded_depth(recipe, root).depth_m
    assert np.mean(np.isinf(got) == np.isinf(rng)) > 0.99                  # sky connected to the top: sky
    assert np.isfinite(got[-12:]).all()                                     # the hood: filled
    assert _median_rel(got[:-12], rng[:-12]) < 0.01


def test_lidar_kitti_layout(tmp_path, sample):
    """KITTI object layout: image_2, velodyne/*.bin (the sample's OS1-128 scan), calib/*.txt written from the sample
    drive's mounts (P2 = K [I | 0], R0_rect = I)."""
    profile, rng, _ = sample
    train = tmp_path / "in" / "training"
    for folder in ("image_2", "velodyne", "calib"):
        (train / folder).mkdir(parents=True)
    shutil.copy(CAM / "000000.png", train / "image_2" / "000000.png")
    shutil.copy(SAMPLE / "lidar" / "os1-128-kitti" / "seq0" / "000000.bin", train / "velodyne" / "000000.bin")
    tr = "0 -1 0 0 0 0 -1 -0.9 1 0 0 -0.3"
    (train / "calib" / "000000.txt").write_text(
        f"P2: {profile.fx_px} 0 {profile.cx_px} 0 0 {profile.fy_px} {profile.cy_px} 0 0 0 1 0\n"
        f"R0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: {tr}\n")
    recipe = load_recipe(EXAMPLES / "depth-lidar-kitti.yaml")
    entries, _ = _run(recipe, tmp_path / "in", tmp_path, 1)
    assert entries[0]["inputs"]["depth"]["densify"] == "bilateral"
    assert _median_rel(_loaded_depth(recipe, tmp_path / "in").depth_m, rng) < 0.05


def test_onnx_photos(tmp_path, tiny_depth_model):
    pytest.importorskip("onnxruntime")
    model = tiny_depth_model(tmp_path / "metric-depth.onnx", weights=(0.0, 0.0, 0.0), bias=12.0)
    photos = tmp_path / "in" / "trip"
    photos.mkdir(parents=True)
    cv2.imwrite(str(photos / "a.jpg"), np.random.default_rng(1).integers(0, 256, (90, 160, 3), np.uint8))
    recipe = load_recipe(EXAMPLES / "depth-onnx.yaml")
    inputs = recipe.spec.inputs.model_copy(update={"onnx_depth": recipe.spec.inputs.onnx_depth.model_copy(
        update={"model": str(model)})})
    recipe = type(recipe)(**{**recipe.__dict__, "spec": recipe.spec.model_copy(update={"inputs": inputs})})
    entries, lines = _run(recipe, tmp_path / "in", tmp_path, 1)
    notes = entries[0]["inputs"]
    assert notes["depth"]["source"] == "onnx" and notes["camera"]["fov_h_deg"] == pytest.approx(70.0)
    assert len(lines) == 1 and "FOV of 70°" in lines[0]
    frame = _loaded_depth(recipe, tmp_path / "in")
    p = frame.profile
    np.testing.assert_allclose(frame.depth_m, 12.0 * ray_factor(160, 90, p.fx_px, p.fy_px, p.cx_px, p.cy_px),
                               rtol=1e-5)


def test_ground_plane_objects_on_the_sample_drive(tmp_path, sample):
    """Against the sample drive's rendered range: vertical objects standing on the road (the default) put the
    buildings above the horizon nearer their range than the flat prior's one distance, keep the road and the sky;
    ``objects: false`` is the flat prior."""
    from roadview_noise.depth.ground_plane import ground_plane_range

    profile, truth, _ = sample
    text = (EXAMPLES / "depth-ground-plane.yaml").read_text()
    (tmp_path / "flat.yaml").write_text(text.replace("sky_distance_m: 100}", "sky_distance_m: 100, objects: false}"))
    objects = _loaded_depth(load_recipe(EXAMPLES / "depth-ground-plane.yaml"), SAMPLE)
    flat = _loaded_depth(load_recipe(tmp_path / "flat.yaml"), SAMPLE)
    k = (profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px)
    np.testing.assert_array_equal(flat.depth_m, ground_plane_range(k, profile.width_px, profile.height_px,
                                                                   camera_height_m=1.0))
    assert flat.input_notes["depth"]["objects"] is False and objects.input_notes["depth"]["objects"] is True
    seen = np.isfinite(truth)
    above = seen & (np.arange(truth.shape[0])[:, None] < profile.cy_px)

    def error(depth):
        return float(np.median(np.abs(np.log(depth[above] / truth[above]))))

    assert error(objects.depth_m) < 0.85 * error(flat.depth_m)
    assert (objects.depth_m[~seen] == 100.0).mean() > 0.99
    road = seen & (truth < 30.0) & (np.arange(truth.shape[0])[:, None] > profile.cy_px + 40)
    assert np.median(np.abs(np.log(objects.depth_m[road] / truth[road]))) < 0.01
