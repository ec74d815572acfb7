"""A new user with dataset photos and no depth files (nuScenes CAM_* JPEGs, 1600 × 900, 4:2:0): the weather
recipes fail with the way out, and that way out exists on the command line of `augment` and `preview`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image
from typer.testing import CliRunner

from cli.main import app

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()


def _photos(tmp_path: Path) -> Path:
    root = tmp_path / "in"
    folder = root / "camera" / "CAM_FRONT"
    folder.mkdir(parents=True)
    y, x = np.mgrid[0:90, 0:160]
    sky = y < 45
    ground = np.stack([90 + x % 40, 90 + x % 40, 95 + x % 40], axis=-1)
    rgb = np.where(sky[..., None], np.array([170, 180, 190]), ground).astype(np.uint8)
    Image.fromarray(rgb).save(folder / "n015__CAM_FRONT__1532402927612460.jpg", quality=90)
    return root


def test_weather_recipe_without_depth_names_both_ways_out(tmp_path):
    root = _photos(tmp_path)
    r = runner.invoke(app, ["augment", "--recipe", str(ROOT / "recipes" / "weather-fog.yaml"), str(root),
                            str(tmp_path / "out"), "--quiet"])
    assert r.exit_code == 1
    line = json.loads((tmp_path / "out" / "manifest.jsonl").read_text().splitlines()[0])
    assert "inputs.depth_source (or --depth-source)" in line["error"] and "ground_plane" in line["error"]


def test_depth_source_on_the_command_line(tmp_path):
    root = _photos(tmp_path)
    out = tmp_path / "out"
    r = runner.invoke(app, ["augment", "--recipe", str(ROOT / "recipes" / "weather-fog.yaml"), str(root), str(out),
                            "--quiet", "--depth-source", "ground_plane"])
    assert r.exit_code == 0, r.output
    line = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
    assert line["inputs"]["depth"]["source"] == "ground_plane"
    assert line["inputs"]["depth"]["camera_height_from"].startswith("camera profile")      # not the user's camera
    assert "profile's height 1 m, not your camera's" in r.output
    run = json.loads((out / "run.json").read_text())
    assert "ground_plane" in json.dumps(run)                          # the resolved recipe carries it
    bad = runner.invoke(app, ["augment", "--recipe", str(ROOT / "recipes" / "weather-fog.yaml"), str(root),
                              str(tmp_path / "o2"), "--quiet", "--depth-source", "stereo"])
    assert bad.exit_code == 2 and "depth_source" in bad.output


def test_preview_every_cnf_of_a_photo_with_a_depth_source(tmp_path):
    root = _photos(tmp_path)
    photo = next(root.rglob("*.jpg"))
    sheet = tmp_path / "sheet.png"
    r = runner.invoke(app, ["preview", "--all-cnfs", str(photo), "-o", str(sheet), "--depth-source", "ground_plane"])
    assert r.exit_code == 0, r.output
    without = runner.invoke(app, ["preview", "--all-cnfs", str(photo), "-o", str(tmp_path / "s2.png")])
    assert without.exit_code == 0
    # every CNF rendered (three panels a row) is much taller than 18 one-line notes "no depth file"
    assert Image.open(sheet).height > 4 * Image.open(tmp_path / "s2.png").height
    bad = runner.invoke(app, ["preview", "--all-cnfs", str(photo), "--depth-source", "stereo"])
    assert bad.exit_code == 2 and "--depth-source" in bad.output


def test_missing_onnx_model_says_what_to_do(tmp_path):
    root = _photos(tmp_path)
    recipe = tmp_path / "r.yaml"
    recipe.write_text('schema: rvnoise.recipe/1\nchain: [{model: fog.camera}]\n'
                      'inputs: {camera: "**/*.jpg", depth_source: onnx, onnx_depth: {model: depth.onnx}}\n')
    r = runner.invoke(app, ["augment", "--recipe", str(recipe), str(root), str(tmp_path / "out"), "--quiet"])
    assert r.exit_code == 1
    error = json.loads((tmp_path / "out" / "manifest.jsonl").read_text().splitlines()[0])["error"]
    assert str(tmp_path / "depth.onnx") in error and "export a metric monocular depth network to ONNX" in error


def test_a_dataset_layout_the_recipe_globs_miss_is_named(tmp_path):
    """nuScenes keeps its photos in samples/CAM_*/: the shipped recipes' camera/** globs find nothing there; the
    message names the photos they miss and a glob that takes them."""
    root = tmp_path / "nuscenes"
    (root / "samples" / "CAM_FRONT").mkdir(parents=True)
    Image.fromarray(np.zeros((9, 16, 3), np.uint8)).save(root / "samples" / "CAM_FRONT" / "a.jpg")
    r = runner.invoke(app, ["augment", "--recipe", str(ROOT / "recipes" / "weather-fog.yaml"), str(root),
                            str(tmp_path / "out"), "--quiet"])
    assert r.exit_code == 2
    out = " ".join(r.output.split())
    assert "inputs.camera: ['camera/**/*.png', 'camera/**/*.jpg']" in out and "'samples/CAM_FRONT/a.jpg'" in out
    assert "set inputs.camera to a glob that matches them, e.g. '**/*.jpg'" in out
