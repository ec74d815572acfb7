"""mmdetection3d mono3d COCO files through lens distortion: ``center2d`` moves with the image, ``cam_intrinsic`` and
``bbox_cam3d`` stay, and the image entry states the distortion (``rv_distortion``) so that the pinhole projection
of the 3-D centre, pulled through the stated Brown–Conrady map, lands where the moved ``center2d`` says — checked
with the closed form written out here (models.md §2.5), on a synthetic file and on mmdetection3d's KITTI file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from roadview_noise import coco_camera
from roadview_noise.io.image import write_image
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from roadview_noise.types import ImageEncoding

W, H = 160, 120
K = [[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]]
STRONG = {"k1": 0.25, "k2": 0.05, "p1": 0.01, "p2": -0.005, "s1": 0.002}     # normalised (OpenCV) units
CENTRES_M = [[0.0, 0.0, 10.0], [-3.0, 1.5, 5.0], [4.5, -2.8, 6.0], [9.0, 0.5, 6.0]]   # the last projects off-image
REAL_COCO = Path("/work/realdata/mmdet3d/tests/data/kitti/kitti_infos_mono3d.coco.json")


def pull(step: dict, uv) -> np.ndarray:
    """Where the image before a ``brown_conrady`` step showed what ``uv`` (N, 2; COCO coordinates) shows after it:
    ``c + f·D((uv − c)/f)`` with the rational radial, tangential and thin-prism terms."""
    k = {n: step[n] for n in ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "s1", "s2", "s3", "s4")}
    c, f = np.asarray(step["centre_px"]), np.asarray(step["unit_px"])
    x, y = ((np.asarray(uv, dtype=float) - c) / f).T
    r2 = x * x + y * y
    radial = (1 + k["k1"] * r2 + k["k2"] * r2**2 + k["k3"] * r2**3) / (1 + k["k4"] * r2 + k["k5"] * r2**2
                                                                      + k["k6"] * r2**3)
    xd = x * radial + 2 * k["p1"] * x * y + k["p2"] * (r2 + 2 * x * x) + k["s1"] * r2 + k["s2"] * r2**2
    yd = y * radial + k["p1"] * (r2 + 2 * y * y) + 2 * k["p2"] * x * y + k["s3"] * r2 + k["s4"] * r2**2
    return np.stack([c[0] + f[0] * xd, c[1] + f[1] * yd], axis=1)


def _project(k, xyz) -> list[float]:
    """mmdetection3d's ``center2d``: [u, v, depth] of a camera-frame point through the camera matrix."""
    p = np.asarray(k, dtype=float)[:3, :3] @ np.asarray(xyz, dtype=float)
    return [p[0] / p[2], p[1] / p[2], float(xyz[2])]


def _mono3d() -> dict:
    anns = []
    for i, xyz in enumerate(CENTRES_M):
        u, v, d = _project(K, xyz)
        anns.append({"file_name": "image_2/000000.png", "image_id": 0, "id": i, "category_id": 1, "iscrowd": 0,
                     "bbox": [u - 8, v - 6, 16.0, 12.0], "area": 192.0, "segmentation": [],
                     "bbox_cam3d": [*xyz, 3.2, 1.6, 1.7, 0.3], "velo_cam3d": -1, "center2d": [u, v, d],
                     "attribute_id": -1})
    return {"images": [{"file_name": "image_2/000000.png", "id": 0, "cam_intrinsic": K, "width": W, "height": H}],
            "annotations": anns, "categories": [{"id": 1, "name": "Car"}]}


def _run_windscreen(in_root: Path, out: Path, coco: str, camera: str, params: dict, inputs: dict, **kw):
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 3,
                           "chain": [{"model": "windscreen.camera", "params": params}],
                           "inputs": {"camera": camera, "annotations": {"coco": coco}, **inputs}},
                          base_dir=in_root.parent)
    return run(recipe, in_root, out, progress=False, echo=lambda *_: None, workers=1, **kw)


def _synthetic(tmp_path: Path, **kw):
    """The synthetic file and its one image (made on the first call) through the strong distortion into OUT."""
    root = tmp_path / "in"
    if not root.exists():
        write_image(root / "image_2" / "000000.png", np.full((H, W, 3), 0.5, np.float32), ImageEncoding())
        (root / "mono3d.coco.json").write_text(json.dumps(_mono3d()))
    return _run_windscreen(root, tmp_path / "out", "mono3d.coco.json", "image_2/*.png",
                           {**STRONG, "coefficient_units": "normalised"},
                           {"camera_profile": {"width_px": W, "height_px": H, "K": K}}, **kw)


def test_synthetic_mono3d_under_strong_distortion(tmp_path):
    out = tmp_path / "out"
    assert _synthetic(tmp_path).failed == 0
    src, got = _mono3d(), json.loads((out / "mono3d.coco.json").read_text())
    image = got["images"][0]
    assert {k: v for k, v in image.items() if k != coco_camera.KEY} == src["images"][0]     # cam_intrinsic kept
    [step] = image[coco_camera.KEY]
    assert step["model"] == "brown_conrady" and {k: step[k] for k in STRONG} == STRONG
    assert step["centre_px"] == [80.0, 60.0] and step["unit_px"] == [100.0, 100.0]    # K's centre + ½ px, f
    for a, b in zip(src["annotations"], got["annotations"]):
        assert b["bbox_cam3d"] == a["bbox_cam3d"] and b["center2d"][2] == a["center2d"][2]
        moved = np.asarray(b["center2d"][:2])
        # the 3-D centre's pinhole projection is where the moved centre's pixel pulls from
        np.testing.assert_allclose(pull(step, moved[None])[0], _project(K, a["bbox_cam3d"][:3])[:2], atol=2e-3)
    shift = [np.hypot(*np.subtract(b["center2d"][:2], a["center2d"][:2]))
             for a, b in zip(src["annotations"], got["annotations"])]
    assert shift[0] < 1e-3 and min(shift[1:]) > 3.0                  # the optical axis stays, the rest moves
    assert not 0 <= got["annotations"][3]["center2d"][0] <= W         # a truncated object's centre stays outside
    entry = next(e for e in read_manifest(out / "manifest.jsonl") if e.get("modality") == "coco")
    assert entry["coco"]["images_distorted"] == 1


def test_resume_redoes_records_without_the_distortion(tmp_path):
    """A manifest written before images stated their distortion (records without ``distortion``) is not kept by
    ``--resume``: its images are redone, so the file states what the images went through."""
    from roadview_noise.manifest import write_manifest

    out = tmp_path / "out"
    assert _synthetic(tmp_path).done == 2
    old = [{**e, "coco": {k: v for k, v in e["coco"].items() if k != "distortion"}} if "coco" in e and
           e.get("modality") != "coco" else e for e in read_manifest(out / "manifest.jsonl")]
    write_manifest(out / "manifest.jsonl", old)
    again = _synthetic(tmp_path, resume=True)
    assert (again.skipped, again.done) == (0, 2)
    assert coco_camera.KEY in json.loads((out / "mono3d.coco.json").read_text())["images"][0]
    assert _synthetic(tmp_path, resume=True).skipped == 1               # a record with it is kept


def test_a_second_run_appends_its_step():
    """An input that an earlier run distorted keeps that step first (the list is the way from the pinhole)."""
    first = {"model": "brown_conrady", "k1": 0.1}
    image = {"id": 1, "file_name": "a.png", coco_camera.KEY: [first]}
    assert coco_camera.image_entry(image, {"distortion": [{"model": "pixel_map"}]})[coco_camera.KEY] == \
        [first, {"model": "pixel_map"}]
    assert coco_camera.image_entry(image, {"moved": []}) is image                      # no geometric step


@pytest.mark.skipif(not REAL_COCO.is_file(), reason="mmdetection3d's KITTI mono3d COCO file is not on this machine")
def test_real_kitti_mono3d_centres_follow_the_stated_distortion(tmp_path):
    """mmdetection3d's ``kitti_infos_mono3d.coco.json`` (1242×375, 4 objects; cam_intrinsic is KITTI's 4×4 P2)
    under the D3.5 windscreen ×5 (k1 = 5e-7 px⁻², reference pixels) centred on P2's principal point."""
    root = tmp_path / "in" / "kitti"
    shutil.copytree(REAL_COCO.parent / "training" / "image_2", root / "training" / "image_2")
    shutil.copy(REAL_COCO, root)
    src = json.loads(REAL_COCO.read_text())
    k = src["images"][0]["cam_intrinsic"]
    out = tmp_path / "out"
    profile = {"width_px": 1242, "height_px": 375, "K": [row[:3] for row in k[:3]]}
    assert _run_windscreen(tmp_path / "in", out, f"kitti/{REAL_COCO.name}", "kitti/training/image_2/*.png",
                           {"k1": 5e-7}, {"camera_profile": profile}).failed == 0
    got = json.loads((out / "kitti" / REAL_COCO.name).read_text())
    [step] = got["images"][0][coco_camera.KEY]
    assert step["centre_px"] == [k[0][2] + 0.5, k[1][2] + 0.5]
    assert {key: v for key, v in got["images"][0].items() if key != coco_camera.KEY} == src["images"][0]
    for a, b in zip(src["annotations"], got["annotations"]):
        assert b["bbox_cam3d"] == a["bbox_cam3d"] and b["center2d"][2] == a["center2d"][2]
        np.testing.assert_allclose(pull(step, [b["center2d"][:2]])[0], a["center2d"][:2], atol=2e-3)
    shift = [np.hypot(*np.subtract(b["center2d"][:2], a["center2d"][:2]))
             for a, b in zip(src["annotations"], got["annotations"])]
    assert max(shift) > 10.0, shift
