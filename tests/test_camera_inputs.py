"""Camera inputs as users have them, end to end: no profile where none is needed, intrinsics from the image size
and a stated FOV where one is, depth problems that name the options, holes counted in the manifest with one
warning per run, JPEG quality, and the command-line input overrides recorded in run.json (replay included)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from roadview_noise.cli.main import app
from roadview_noise.io.image import read_image
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import load_recipe, parse_recipe
from roadview_noise.runner import run

ROOT = Path(__file__).resolve().parents[1]
cli = CliRunner()


def _photo(path: Path, w=301, h=97, quality=None, seed=0):
    """A textured photo of an odd size (no camera profile matches its aspect ratio)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    y, x = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(seed)
    img = np.clip(np.stack([x % 200, y * 2, (x + y) % 256], -1) + rng.integers(0, 40, (h, w, 3)), 0, 255)
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if quality else []
    assert cv2.imwrite(str(path), img.astype(np.uint8), params)
    return path


def _run(recipe, in_root, out):
    lines = []
    summary = run(recipe, in_root, out, workers=1, progress=False, echo=lines.append)
    return summary, read_manifest(out / "manifest.jsonl"), lines


def test_jpeg_only_recipe_on_a_photo_without_profile_or_depth(tmp_path):
    """Acceptance: the shipped JPEG-only recipe on a 301×97 photo, no profile, no depth: it succeeds, never looks at
    a camera profile (a recipe naming a missing one still works), and writes JPEG at the stated quality."""
    _photo(tmp_path / "in" / "trip" / "IMG_0001.jpg", quality=63)
    recipe = load_recipe(ROOT / "recipes" / "examples" / "photo-jpeg-only.yaml")
    summary, entries, lines = _run(recipe, tmp_path / "in", tmp_path / "out")
    assert summary.failed == 0 and summary.done == 1 and lines == []
    inputs = entries[0]["inputs"]
    assert inputs == {"jpeg_quality": {"value": 90, "from": "recipe output.jpeg_quality"}}
    assert read_image(tmp_path / "out" / "trip" / "IMG_0001.jpg")[1].jpeg_quality == 90

    data = yaml.safe_load((ROOT / "recipes" / "examples" / "photo-jpeg-only.yaml").read_text())
    data["inputs"]["camera_profile"] = "no-such-profile.yaml"
    del data["output"]
    summary, entries, _ = _run(parse_recipe(data), tmp_path / "in", tmp_path / "out2")
    assert summary.failed == 0
    assert entries[0]["inputs"]["jpeg_quality"] == {"value": 63, "from": "input (estimated from its quantisation "
                                                                          "tables)"}
    assert read_image(tmp_path / "out2" / "trip" / "IMG_0001.jpg")[1].jpeg_quality == 63


def _rain_recipe(**inputs):
    return parse_recipe({"chain": [{"model": "rain.camera", "params": {"rain_rate_mm_per_h": 20}}], "seed": 1,
                         "inputs": {"camera": "**/*.png", "depth": "{stem}_depth.npy", **inputs}})


def test_geometry_without_profile_from_image_size_and_fov(tmp_path):
    """Rain needs intrinsics: without a profile they come from the image size and the horizontal FOV (default the
    Lucid's 80.8°, or inputs.camera_fov_h_deg), recorded per file, with one warning line for the whole run."""
    for k in range(2):
        _photo(tmp_path / "in" / f"{k}.png", seed=k)
        np.save(tmp_path / "in" / f"{k}_depth.npy", np.full((97, 301), 12.0, np.float32))
    summary, entries, lines = _run(_rain_recipe(), tmp_path / "in", tmp_path / "out")
    assert summary.failed == 0 and summary.done == 2
    camera = entries[0]["inputs"]["camera"]
    assert camera["fx_px"] == pytest.approx(301 / (2 * math.tan(math.radians(80.8) / 2)), rel=1e-6)
    assert camera["fy_px"] == camera["fx_px"] and camera["cx_px"] == 150.0 and camera["cy_px"] == 48.0
    assert "80.8°" in camera["from"] and entries[1]["inputs"]["warnings"] == ["intrinsics_from_fov"]
    assert len(lines) == 1 and "no camera profile for 2 file(s)" in lines[0] and "80.8°" in lines[0]
    assert ["rvnoise: warning: " + w for w in json.loads((tmp_path / "out" / "run.json").read_text())["warnings"]] \
        == lines

    summary, entries, lines = _run(_rain_recipe(camera_fov_h_deg=50), tmp_path / "in", tmp_path / "out50")
    assert entries[0]["inputs"]["camera"]["fov_h_deg"] == pytest.approx(50.0)


def test_a_profile_that_does_not_fit_still_fails_where_geometry_is_needed(tmp_path):
    _photo(tmp_path / "in" / "a.png")
    np.save(tmp_path / "in" / "a_depth.npy", np.full((97, 301), 12.0, np.float32))
    summary, entries, _ = _run(_rain_recipe(camera_profile="lucid_triton_028s"), tmp_path / "in", tmp_path / "out")
    assert summary.failed == 1 and "aspect ratio differs" in entries[0]["error"]


def test_missing_depth_names_the_options(tmp_path):
    _photo(tmp_path / "in" / "a.png")
    recipe = parse_recipe({"chain": [{"model": "fog.camera"}], "inputs": {"camera": "*.png"}})
    summary, entries, _ = _run(recipe, tmp_path / "in", tmp_path / "out")
    error = entries[0]["error"]
    assert summary.failed == 1 and "a_depth.exr" in error and "fog.camera" in error
    for option in ("--depth", "depth_source", "lidar", "onnx", "ground_plane"):
        assert option in error, option


def test_depth_holes_counted_per_file_and_warned_once_per_run(tmp_path):
    rng = np.random.default_rng(0)
    for k in range(3):
        _photo(tmp_path / "in" / f"{k}.png", seed=k)
        depth = rng.uniform(5, 50, (97, 301)).astype(np.float32)
        depth[20:40, 30:90] = np.nan if k != 1 else 0.0                 # NaN or 0: both holes
        np.save(tmp_path / "in" / f"{k}_depth.npy", depth)
    recipe = parse_recipe({"chain": [{"model": "fog.camera"}], "inputs": {"camera": "*.png",
                                                                          "depth": "{stem}_depth.npy"}})
    summary, entries, lines = _run(recipe, tmp_path / "in", tmp_path / "out")
    assert summary.failed == 0
    for e in entries:
        assert e["inputs"]["depth"] == {"source": "file", "file": e["input"].replace(".png", "_depth.npy"),
                                        "format": "npy", "kind": "range", "holes": 1200,
                                        "hole_fraction": round(1200 / (97 * 301), 6), "policy": "fill",
                                        "filled": 1200, "sky": 0}
    assert len(lines) == 1 and "depth holes filled" in lines[0] and "3 file(s)" in lines[0] and "4.1 %" in lines[0]
    recipe = parse_recipe({"chain": [{"model": "fog.camera"}], "inputs": {"camera": "*.png", "depth_holes": "error",
                                                                          "depth": "{stem}_depth.npy"}})
    summary, entries, _ = _run(recipe, tmp_path / "in", tmp_path / "out_err")
    assert summary.failed == 3 and "1200 holes" in entries[0]["error"] and "0_depth.npy" in entries[0]["error"]


def test_cli_input_overrides_are_recorded_and_replayed(tmp_path):
    """--depth and --camera-profile change the resolved recipe in run.json (and its sha256); replay reproduces the
    output from that record; a bad pattern is refused with exit 2 before anything is written."""
    _photo(tmp_path / "in" / "seq" / "a.png")
    np.save(tmp_path / "in" / "seq" / "a_range.npy", np.full((97, 301), 20.0, np.float32))
    (tmp_path / "cam.yaml").write_text("base: lucid_triton_028s\nwidth_px: 301\nheight_px: 97\nfov_h_deg: 60\n")
    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump({"chain": [{"model": "rain.camera"}], "seed": 3,
                                      "inputs": {"camera": "**/*.png"}}))
    r = cli.invoke(app, ["augment", "-r", str(recipe), str(tmp_path / "in"), str(tmp_path / "out"), "-q", "-j", "1",
                         "--depth", "{stem}_range.npy", "--camera-profile", str(tmp_path / "cam.yaml")])
    assert r.exit_code == 0, r.output
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    assert record["recipe"]["inputs"]["depth"] == "{stem}_range.npy"
    assert record["recipe"]["inputs"]["camera_profile"] == str((tmp_path / "cam.yaml").resolve())
    assert record["recipe_sha256"] != load_recipe(recipe).sha256()
    entry = read_manifest(tmp_path / "out" / "manifest.jsonl")[0]
    assert entry["inputs"]["camera"]["fov_h_deg"] == pytest.approx(60.0) and entry["depth"] == "seq/a_range.npy"
    r = cli.invoke(app, ["replay", str(tmp_path / "out" / "manifest.jsonl"), "--key", "seq/a.png"])
    assert r.exit_code == 0 and "match" in r.output
    r = cli.invoke(app, ["augment", "-r", str(recipe), str(tmp_path / "in"), str(tmp_path / "out3"), "--depth",
                         "{stm}.npy"])
    assert r.exit_code == 2 and "{stm}" in r.output and not (tmp_path / "out3").exists()


def test_a_photo_turned_by_its_exif_orientation_is_processed_upright_unless_stored_is_asked(tmp_path):
    """A phone photo stored sideways (EXIF orientation 6) is processed upright: rain falls down the displayed image
    (its streaks vertical as displayed), the manifest says so, no warning. ``inputs.orientation: stored`` keeps the
    stored processing (streaks horizontal as displayed): the manifest says so and one line per run warns; an
    upright photo (orientation 1) and a chain without a direction (fog on the photo's own depth file) say nothing."""
    from PIL import Image, ImageOps

    for name, turn in (("side.jpg", 6), ("upright.jpg", 1)):
        exif = Image.Exif()
        exif[0x0112] = turn
        Image.open(_photo(tmp_path / "in" / name)).save(tmp_path / "in" / name, exif=exif.tobytes(), quality=90)

    def streaks_across(out: Path) -> float:
        """Mean |∂/∂x| over mean |∂/∂y| of what rain added, as displayed (> 1: vertical streaks)."""
        shown = [np.asarray(ImageOps.exif_transpose(Image.open(p / "side.jpg")).convert("L"), np.float32)
                 for p in (tmp_path / "in", out)]
        added = shown[1] - shown[0]
        return float(np.abs(np.diff(added, axis=1)).mean() / np.abs(np.diff(added, axis=0)).mean())

    rain = {"chain": [{"model": "rain.camera", "params": {"rain_rate_mm_per_h": 50}}], "seed": 1,
            "inputs": {"camera": "*.jpg", "depth_source": "ground_plane"}}
    summary, entries, lines = _run(parse_recipe(rain), tmp_path / "in", tmp_path / "out")
    notes = {Path(e["input"]).name: e["inputs"] for e in entries}
    assert summary.failed == 0 and notes["side.jpg"]["orientation"] == {"exif": 6, "processed": "upright"}
    assert "turned_photo" not in notes["side.jpg"]["warnings"] and "orientation" not in notes["upright.jpg"]
    assert not any("turned" in line for line in lines) and streaks_across(tmp_path / "out") > 1.1

    rain["inputs"]["orientation"] = "stored"
    summary, entries, lines = _run(parse_recipe(rain), tmp_path / "in", tmp_path / "out_stored")
    notes = {Path(e["input"]).name: e["inputs"] for e in entries}
    assert notes["side.jpg"]["orientation"] == {"exif": 6, "processed": "as stored"}
    assert "turned_photo" in notes["side.jpg"]["warnings"] and "orientation" not in notes["upright.jpg"]
    assert sum("1 photo(s) stored turned" in line for line in lines) == 1
    assert streaks_across(tmp_path / "out_stored") < 1
    from roadview_noise.camera_inputs import _orientation_note
    fog = parse_recipe({"chain": [{"model": "fog.camera"}], "inputs": {"depth": "{stem}_depth.npy"}})
    notes: dict = {}
    assert _orientation_note(6, 1, fog, notes) == [] and notes["orientation"]["processed"] == "as stored"


def test_the_alpha_plane_follows_a_geometric_model(tmp_path):
    """An RGBA photo (a cut-out: alpha 0 over a patch) through windscreen distortion: the pixels moved, the alpha
    plane stayed where it was (here the cut-out no longer overlapped the patch). It is resampled through the same
    map now; a uniform alpha (CARLA's 255) stays uniform, corners included."""
    h, w = 120, 200
    bgra = np.zeros((h, w, 4), np.uint8)
    bgra[..., 3] = 255
    bgra[8:40, 10:50, :3] = 255                        # a white patch near the corner, where the map moves most
    bgra[8:40, 10:50, 3] = 0                           # … cut out
    (tmp_path / "in").mkdir()
    cv2.imwrite(str(tmp_path / "in" / "cut.png"), bgra)
    cv2.imwrite(str(tmp_path / "in" / "opaque.png"), np.dstack([bgra[..., :3], np.full((h, w), 255, np.uint8)]))
    recipe = parse_recipe({"chain": [{"model": "windscreen.camera", "params": {"k1": 2e-5}}], "seed": 1,
                           "inputs": {"camera": "*.png"}})
    summary, _, _ = _run(recipe, tmp_path / "in", tmp_path / "out")
    assert summary.failed == 0
    out = cv2.imread(str(tmp_path / "out" / "cut.png"), cv2.IMREAD_UNCHANGED)
    white, cut = out[..., 1] > 127, out[..., 3] < 128
    assert (white & cut).sum() / (white | cut).sum() > 0.95          # the patch and its cut-out still coincide
    assert (white != (bgra[..., 1] > 127)).sum() > 100                  # (the patch did move)
    opaque = cv2.imread(str(tmp_path / "out" / "opaque.png"), cv2.IMREAD_UNCHANGED)
    assert (opaque[..., 3] == 255).all()
