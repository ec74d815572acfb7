"""The CNF table of D3.5 (exactly 30) and every shipped recipe running on the committed sample data."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadview_noise.compound import CNFS
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import load_recipe
from roadview_noise.registry import load_all
from roadview_noise.runner import run

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"
# examples/: tests/test_depth_recipes.py; bag-*.yaml: tests/test_rosbag.py
RECIPES = sorted(p for p in (ROOT / "recipes").glob("*.yaml") if not p.name.startswith("bag-"))


def test_exactly_30_cnfs_in_d35_order():
    assert list(CNFS) == [f"CNF{i:02d}" for i in range(1, 31)]
    assert [CNFS[f"CNF{i:02d}"].weather for i in (1, 2, 3)] == ["rain", "fog", "snow"]
    assert set(CNFS["CNF25"].chains) == {"lidar", "radar"}
    assert CNFS["CNF16"].chains["camera"] == ("wind.camera", "rain.camera")     # Eq. 2: modifier first
    assert CNFS["CNF19"].chains["lidar"] == ("alignment.lidar", "rain.lidar")   # Eq. 1: factor before weather
    assert CNFS["CNF10"].chains["camera"] == ("rain.camera", "compression.camera")  # Eq. 3: after


def test_every_runnable_cnf_has_a_recipe():
    models = load_all()
    names = {p.stem for p in RECIPES}
    for name, cnf in CNFS.items():
        for sensor, ids in cnf.chains.items():
            if all(m in models for m in ids):
                assert name.lower() in names or f"{name.lower()}-{sensor}" in names, (name, sensor)


@pytest.mark.parametrize("recipe_path", RECIPES, ids=[p.stem for p in RECIPES])
def test_recipe_runs_on_sample_data(tmp_path, recipe_path):
    if not SAMPLE.is_dir():
        pytest.skip("sample_data/ missing")
    recipe = load_recipe(recipe_path)  # recipes glob the sample layout: camera/, raw/, lidar/, radar/
    summary = run(recipe, SAMPLE, tmp_path / "out", workers=1, progress=False, echo=lambda s: None)
    entries = read_manifest(tmp_path / "out" / "manifest.jsonl")
    assert summary.failed == 0, [e.get("error") for e in entries]
    assert summary.done == len(entries) > 0
    if recipe.sensor == "camera" and "compression.camera" not in recipe.model_ids:
        # every camera model but JPEG runs natively on raw Bayer: the CNF recipes take the DNGs too
        suffixes = {Path(e["output"]).suffix for e in entries}
        assert {".png", ".dng"} <= suffixes, suffixes


def test_camera_cnfs_all_runnable_and_show_explains_the_order():
    from typer.testing import CliRunner

    from roadview_noise.cli.main import app

    models = load_all()
    camera = [n for n, c in CNFS.items() if "camera" in c.chains]
    assert len(camera) == 18 and all(m in models for n in camera for m in CNFS[n].chains["camera"])
    r = CliRunner().invoke(app, ["show", "CNF14"])
    assert r.exit_code == 0
    assert "order: low_light.camera → fog.camera" in r.output
    assert "low_light.camera: SCENE (scene illumination, before the weather: Eq. 1)" in r.output
    r = CliRunner().invoke(app, ["show", "CNF04"])
    assert "order: rain.camera → windscreen.camera" in r.output and "after the weather: Eq. 3" in r.output
    r = CliRunner().invoke(app, ["list"])
    assert not any(f"{m}*" in r.output for m in ("soiling.camera", "windscreen.camera", "motion_blur.camera",
                                                 "low_light.camera"))


def test_all_twelve_lidar_cnfs_have_recipes_and_no_model_is_missing():
    """CNF19–30 for LiDAR: every model implemented, a shipped recipe each (run on the sample data above), and
    `rvnoise list` marks nothing missing."""
    from typer.testing import CliRunner

    from roadview_noise.cli.main import app

    models = load_all()
    lidar = [n for n, c in CNFS.items() if "lidar" in c.chains]
    assert lidar == [f"CNF{i}" for i in range(19, 31)]
    assert all(m in models for n in lidar for m in CNFS[n].chains["lidar"])
    names = {p.stem for p in RECIPES}
    assert all(n.lower() in names for n in lidar)
    for n in ("cnf25", "cnf26", "cnf27"):
        assert load_recipe(ROOT / "recipes" / f"{n}.yaml").sensor == "lidar"
    r = CliRunner().invoke(app, ["list"])
    assert r.exit_code == 0 and "*" not in r.output.split("Compound noise factors")[1].split(":", 1)[1]
