"""rvnoise preview and rvnoise report: same results as augment, partial runs and failures, the page in Chromium."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from roadview_noise.cli.main import app
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.manifest import read_manifest
from roadview_noise.physics.srgb import linear_to_code
from roadview_noise.metrics import Effect, compare, with_effect_codes
from roadview_noise.preview import (ADDED_BGR, MOVED_BGR, RADAR_REMOVED_BGR, REMOVED_BGR, ChainRun, _changed_region,
                                    applicable_cnfs, recipe_from, render, render_cloud, run_chain, sample_for)
from roadview_noise.recipe import load_recipe
from roadview_noise.report import build, corner_cases, data_loss, find_runs, read_run, write_report
from roadview_noise.runner import run
from roadview_noise.types import PointCloud

from browser import Page, chromium_path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"
RUNS = {"cnf16": 2, "cnf19": 1, "cnf25-radar": 1}          # recipe → inputs (--limit)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs")
    for name, limit in RUNS.items():
        run(load_recipe(ROOT / "recipes" / f"{name}.yaml"), SAMPLE, out / name, workers=1, limit=limit,
            progress=False, echo=lambda m: None)
    return out


def _cnfs_of(root: Path) -> list[str]:
    return sorted({read_run(p, root).cnf for p in find_runs(root)})


# --- preview ------------------------------------------------------------------------------------------------------


def test_preview_final_stage_is_what_augment_wrote(runs):
    for name in RUNS:
        recipe = load_recipe(ROOT / "recipes" / f"{name}.yaml")
        entry = read_manifest(runs / name / "manifest.jsonl")[0]
        sample, root = sample_for(SAMPLE / entry["input"], recipe, SAMPLE)
        assert sample.sequence_id == entry["sequence"] and sample.depth_relpath == entry.get("depth")
        chain = run_chain(recipe, sample, root)
        final = chain.stages[-1][1]
        written = runs / name / entry["output"]
        if recipe.sensor == "camera":
            code = cv2.cvtColor(cv2.imread(str(written), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB)
            assert np.array_equal(linear_to_code(final.linear_rgb, 8), code)
        else:
            cloud = read_pointcloud(written, sensor=recipe.sensor)
            assert np.allclose(cloud.positions_m, final.positions_m, atol=1e-4)
        # per-step metrics of the preview are those of the manifest
        for rec, step in zip(chain.records, entry["steps"]):
            assert json.loads(json.dumps(rec.metrics)) == step["metrics"]
        assert [s for s, _ in chain.stages] == ["input", *recipe.model_ids]
        img = render(chain, 200)
        assert img.dtype == np.uint8 and img.shape[1] >= 3 * 200


def test_applicable_cnfs_cover_the_table_per_sensor():
    names = {s: [n for n, _ in applicable_cnfs(s)] for s in ("camera", "lidar", "radar")}
    assert len(names["camera"]) == 18 and len(names["lidar"]) == 12 and names["radar"] == ["CNF25", "CNF26", "CNF27"]
    assert len(set(names["camera"]) | set(names["lidar"])) == 30
    for sensor in names:
        for name, recipe in applicable_cnfs(sensor):
            assert isinstance(recipe, str) and "not implemented" in recipe or recipe.sensor == sensor


def test_recipe_from_cnf_id_needs_a_sensor_when_ambiguous():
    assert recipe_from("CNF16", None, 0).model_ids == ("wind.camera", "rain.camera")
    assert recipe_from("cnf25", "radar", 3).seed == 3
    with pytest.raises(Exception, match="--sensor"):
        recipe_from("CNF25", None, 0)


def test_cli_preview_recipe_cnf_id_and_contact_sheets(tmp_path):
    cli = CliRunner()
    image = SAMPLE / "camera" / "seq0" / "000001.png"
    out = tmp_path / "p.png"
    r = cli.invoke(app, ["preview", "--recipe", str(ROOT / "recipes" / "cnf16.yaml"), str(image),
                         "--input-root", str(SAMPLE), "-o", str(out), "--panel-px", "200"])
    assert r.exit_code == 0, r.output
    assert cv2.imread(str(out)).shape[1] >= 600
    radar = SAMPLE / "radar" / "seq0" / "000001.pcd"
    r = cli.invoke(app, ["preview", "--recipe", "CNF25", str(radar), "-o", str(tmp_path / "radar.jpg")])
    assert r.exit_code == 0, r.output                    # sensor guessed from the radar fields
    r = cli.invoke(app, ["preview", "--all-cnfs", "--input-root", str(SAMPLE), str(image), str(radar),
                         "-o", str(tmp_path / "sheets"), "--panel-px", "160"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "sheets").iterdir()) == ["camera_seq0_000001-camera.png",
                                                                        "radar_seq0_000001-radar.png"]
    r = cli.invoke(app, ["preview", str(image)])
    assert r.exit_code == 2 and "--recipe" in r.output
    r = cli.invoke(app, ["preview", "--recipe", "CNF16", str(tmp_path / "missing.png")])
    assert r.exit_code == 2 and "missing.png" in r.output


def test_cli_preview_guesses_a_view_of_delft_radar_bin_from_its_folder(tmp_path):
    """View-of-Delft keeps its radar as ``radar/training/velodyne/NNNNN.bin`` (N×7 float32): ``preview -r CNF25``
    (a CNF of LiDAR and radar) reads it as radar, as augment's ``radar/**/*.bin`` globs do. Before: read as a LiDAR
    .bin and refused ("not a multiple of the 16-byte point … name its columns with inputs.bin_fields")."""
    from roadview_noise.preview import guess_sensor

    rng = np.random.default_rng(3)
    n = 161
    r, az = rng.uniform(2, 60, n), rng.uniform(-1, 1, n)
    vr = rng.uniform(-5, 5, n)
    table = np.stack([r * np.cos(az), r * np.sin(az), rng.uniform(-1, 1, n), rng.uniform(-20, 20, n), vr,
                      vr + 3 * np.cos(az), np.zeros(n)], 1).astype("<f4")
    path = tmp_path / "view_of_delft" / "radar" / "training" / "velodyne" / "00549.bin"
    path.parent.mkdir(parents=True)
    table.tofile(path)
    assert guess_sensor(path) == "radar"
    assert guess_sensor(tmp_path / "radar_scans" / "lidar" / "x.bin") == "lidar"    # the nearest sensor folder
    assert guess_sensor(tmp_path / "x.bin") == "lidar"
    r = CliRunner().invoke(app, ["preview", "--recipe", "CNF25", str(path), "-o", str(tmp_path / "p.png"),
                                 "--panel-px", "160"])
    assert r.exit_code == 0, r.output


def test_cli_preview_names_a_failing_file_and_previews_the_others(tmp_path):
    """A ti_mmwave_rospkg radar cloud (x y z intensity velocity: no SNR field until the recipe's field_map says so)
    among several files: the error names that file, the other files are still previewed, the exit status is 2.
    Before: ``rvnoise: rain.radar: a radar cloud needs snr_db …`` without the file, and the run stopped there."""
    from roadview_noise.io.pointcloud import write_pointcloud

    rng = np.random.default_rng(6)
    n = 40
    bad = tmp_path / "ti" / "000000.pcd"
    bad.parent.mkdir()
    write_pointcloud(bad, PointCloud(rng.uniform(1, 20, (n, 3)), {"intensity": rng.uniform(6, 40, n).astype("<f4"),
                                                                  "velocity": rng.normal(0, 1, n).astype("<f4")},
                                     "radar", None))
    good = SAMPLE / "radar" / "seq0" / "000001.pcd"
    r = CliRunner().invoke(app, ["preview", "--recipe", "CNF25", "--sensor", "radar", str(bad), str(good),
                                 "-o", str(tmp_path / "p"), "--panel-px", "160"])
    assert r.exit_code == 2
    assert f"rvnoise: {bad}: rain.radar: a radar cloud needs snr_db" in r.output.replace("\n", "")
    assert [p.name for p in (tmp_path / "p").iterdir()] == ["seq0_000001-radar.png"]


def test_cli_preview_prints_a_model_warning_once_as_one_line(tmp_path, capsys):
    """A cloud whose intensity unit nothing states warns (IntensityWarning): preview prints it like augment does,
    once, not as Python's file:line plus source line."""
    rng = np.random.default_rng(5)
    r, az = rng.uniform(3, 40, 3000), rng.uniform(-np.pi, np.pi, 3000)
    table = np.stack([r * np.cos(az), r * np.sin(az), rng.uniform(-1.5, 1, 3000), rng.integers(1, 200, 3000)], 1)
    table.astype("<f4").tofile(tmp_path / "000000.bin")
    app(["preview", "--recipe", "CNF19", str(tmp_path / "000000.bin"), "-o", str(tmp_path / "p.png"),
         "--panel-px", "160"], standalone_mode=False)         # as the console script calls it (CliRunner does not)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "IntensityWarning" in line]
    assert len(lines) == 1 and lines[0].startswith("rvnoise: warning: IntensityWarning: rain.lidar: "), err
    assert ".py:" not in err


# --- report -------------------------------------------------------------------------------------------------------


def test_report_page_and_numbers(runs, tmp_path):
    page_path = write_report(runs, tmp_path / "r" / "report.html")
    page = page_path.read_text()
    numbers = json.loads((tmp_path / "r" / "report.json").read_text())
    assert _cnfs_of(runs) == ["CNF16", "CNF19", "CNF25"]
    for cnf in ("CNF16", "CNF19", "CNF25"):
        assert f"<b>{cnf}</b>" in page                              # run here, in the coverage table
    assert "CNF01" in page and "not in this run" in page             # the rest of Table 6 is listed
    assert not re.search(r'(src|href)="(https?:)?//', page)          # nothing fetched from the network
    assert page.count("data:image/png;base64,") >= 2 and "data:image/jpeg;base64," in page
    for target in set(re.findall(r'href="#([\w-]+)"', page)):        # every link lands on the page
        assert f'id="{target}"' in page
    by_cnf = {r["cnf"]: r for r in numbers["runs"]}
    assert by_cnf["CNF16"]["outputs_ok"] == 2 and by_cnf["CNF16"]["ssim_mean"] < 1
    assert by_cnf["CNF19"]["points_in_total"] > 0 and by_cnf["CNF25"]["sensor"] == "radar"
    assert numbers["corner_cases"] and all(c["loss"] >= 0 for c in numbers["corner_cases"])
    assert json.loads(json.dumps(numbers, allow_nan=False)) == numbers      # strict JSON


def test_corner_cases_ranked_by_data_loss(runs):
    rs = [read_run(p, runs) for p in find_runs(runs)]
    cases = corner_cases(rs, per_sensor=3)
    for sensor in ("camera", "lidar", "radar"):
        losses = [c["loss"] for c in cases if c["sensor"] == sensor]
        assert losses == sorted(losses, reverse=True) and 0 < len(losses) <= 3
    assert data_loss({"ssim": 0.75}, "camera") == 0.25
    assert data_loss({"points_in": 200, "removed": 30, "moved": 20}, "lidar") == 0.25
    assert data_loss({}, "radar") is None


def test_report_on_a_partial_run_with_failures(runs, tmp_path):
    src = tmp_path / "in"
    shutil.copytree(SAMPLE / "radar", src / "radar")
    (src / "radar" / "seq0" / "000002.pcd").write_bytes(b"not a point cloud")
    out = tmp_path / "out"
    run(load_recipe(ROOT / "recipes" / "cnf25-radar.yaml"), src, out / "broken", workers=1, progress=False,
        echo=lambda m: None)
    shutil.copytree(runs / "cnf16", out / "killed")
    (out / "killed" / "run.json").unlink()                          # as after a kill: manifest lines only
    page, numbers = build(out)
    assert "000002.pcd" in page and 'class="l bad"' in page           # the failure and its message
    assert "partial: no run.json" in page
    failures = numbers["failures"]
    assert len(failures) == 1 and failures[0]["run"] == "broken" and "000002.pcd" in failures[0]["error"]
    assert {r["name"]: r["partial"] for r in numbers["runs"]} == {"broken": False, "killed": True}


def test_report_names_a_path_that_failed_before_it_had_an_output(tmp_path):
    """A path the walk refuses (here a label image a camera glob swept up) has a failed entry with no output: the
    report crashed on it (`'NoneType' object has no attribute 'replace'`); it now names the input."""
    from roadview_noise.recipe import parse_recipe

    src = tmp_path / "in"
    (src / "masks").mkdir(parents=True)
    cv2.imwrite(str(src / "a.png"), np.full((24, 32, 3), 90, np.uint8))
    cv2.imwrite(str(src / "masks" / "a.png"), np.zeros((24, 32), np.uint8))
    recipe = parse_recipe({"chain": [{"model": "compression.camera"}], "inputs": {"camera": "**/*.png"}})
    assert run(recipe, src, tmp_path / "out" / "r", workers=1, progress=False, echo=lambda m: None).failed == 1
    page, numbers = build(tmp_path / "out")
    assert "masks/a.png" in page and "looks like a label image" in numbers["failures"][0]["error"]


def test_cli_report_and_augment_report(runs, tmp_path):
    cli = CliRunner()
    r = cli.invoke(app, ["report", str(tmp_path)])
    assert r.exit_code == 2 and "nothing to report" in r.output
    r = cli.invoke(app, ["augment", "--recipe", str(ROOT / "recipes" / "cnf26-radar.yaml"), str(SAMPLE),
                         str(tmp_path / "a"), "--limit", "1", "--workers", "1", "--quiet", "--report"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "a" / "report.html").is_file() and (tmp_path / "a" / "report.json").is_file()
    assert "CNF26" in (tmp_path / "a" / "report.html").read_text()
    r = cli.invoke(app, ["report", str(tmp_path / "a"), "-o", str(tmp_path / "a" / "second.html")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "a" / "second.json").is_file() and "second.json" in r.output    # report.json not overwritten


def test_metrics_off_leaves_them_out(tmp_path):
    recipe = tmp_path / "r.yaml"
    recipe.write_text((ROOT / "recipes" / "cnf25-radar.yaml").read_text() + "output: {metrics: false}\n")
    run(load_recipe(recipe), SAMPLE, tmp_path / "o", workers=1, limit=1, progress=False, echo=lambda m: None)
    entry = read_manifest(tmp_path / "o" / "manifest.jsonl")[0]
    assert entry["metrics"] == {} and all(s["metrics"] == {} for s in entry["steps"])


# --- the page in a browser ----------------------------------------------------------------------------------------


needs_chromium = pytest.mark.skipif(chromium_path() is None, reason="chromium is not installed (.ci/run installs it)")


@needs_chromium
def test_console_errors_are_caught(tmp_path):
    bad = tmp_path / "bad.html"
    bad.write_text('<!DOCTYPE html><html><body><p>x</p><script>console.error("boom"); nope();</script>'
                   '<img src="missing.png"></body></html>')
    with Page(bad.as_uri()) as page:
        text = " ".join(page.errors)
    assert "boom" in text and "nope" in text and "missing.png" in text


@needs_chromium
def test_report_renders_in_chromium_without_errors(runs, tmp_path):
    path = write_report(runs, tmp_path / "report.html")
    with Page(path.as_uri()) as page:
        assert page.errors == []
        assert all(u.startswith(("file:", "data:")) for u in page.requests)
        text = page.evaluate("document.body.innerText")
        broken = page.evaluate("Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0))"
                               ".length")
        shown = page.evaluate("document.images.length")
    for cnf in _cnfs_of(runs):
        assert cnf in text
    assert broken == 0 and shown >= 5


# --- rendering ------------------------------------------------------------------------------------------------------


def _has_colour(img: np.ndarray, bgr) -> bool:
    return bool(np.all(img == np.array(bgr, np.uint8), axis=2).any())


@pytest.mark.parametrize("sensor", ["lidar", "radar"])
def test_cloud_preview_highlights_added_moved_and_removed(sensor):
    rng = np.random.default_rng(0)
    n = 400
    pos = np.column_stack([rng.uniform(5, 40, n), rng.uniform(-20, 20, n), rng.uniform(-1, 1, n)])
    fields = {"snr_db": rng.uniform(10, 30, n)} if sensor == "radar" else {"intensity": rng.uniform(0, 1, n)}
    before = PointCloud(pos, fields, sensor)
    label = np.zeros(n, np.uint8)
    label[:20] = Effect.MOVED
    moved_pos = pos.copy()
    moved_pos[:20] *= 0.3
    keep = np.arange(n) >= 0
    keep[100:140] = False
    after = dataclasses.replace(before, positions_m=moved_pos).select(keep)
    after = after.concat(np.array([[12.0, 3.0, 0.0], [20.0, -5.0, 0.5]]), {})
    after = with_effect_codes(after, np.concatenate([label[keep], np.full(2, Effect.ADDED)]))
    run_ = ChainRun("t", [("input", before), ("weather", after)], [], compare(before, after))
    img = render_cloud(run_, 240)
    assert _has_colour(img, ADDED_BGR)
    if sensor == "lidar":
        assert _has_colour(img, MOVED_BGR) and _has_colour(img, REMOVED_BGR)
    else:
        assert _has_colour(img, RADAR_REMOVED_BGR)


def test_camera_inset_follows_the_change():
    rng = np.random.default_rng(1)
    before = np.full((300, 400, 3), 120, np.uint8)
    after = before.copy()
    after[220:280, 300:380] = rng.integers(0, 255, (60, 80, 3))            # streaks in the lower right only
    x, y, w, h = _changed_region(before, after)
    assert x <= 300 < 380 <= x + w + 40 and y <= 220 < 280 <= y + h + 40
    assert _changed_region(before, before) == ((400 - 80) // 2, (300 - 60) // 2, 80, 60)   # no change: centre
