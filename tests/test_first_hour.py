"""A new user's first hour (round 22, ux38): the mistakes users make on the command line each give exit 2 and one
line that names the problem and what to do, and nothing is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from roadview_noise.cli.main import app
from roadview_noise.io.image import write_image
from roadview_noise.types import ImageEncoding

runner = CliRunner()
FOG_LIDAR = {"chain": [{"model": "fog.lidar"}], "inputs": {"lidar": ["lidar/**/*.pcd", "lidar/**/*.bin"]}}
JPEG = {"chain": [{"model": "compression.camera"}], "inputs": {"camera": ["camera/**/*.png"]}}


@pytest.fixture
def photos(tmp_path: Path) -> Path:
    """A folder of photos at its top level, as a user's own pictures are."""
    rng = np.random.default_rng(0)
    for i in range(2):
        write_image(tmp_path / "photos" / f"IMG_{i}.png", rng.uniform(0, 1, (16, 24, 3)).astype(np.float32),
                    ImageEncoding())
    return tmp_path / "photos"


def _augment(tmp_path: Path, body: dict, in_dir: Path, *extra) -> object:
    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump(body))
    return runner.invoke(app, ["augment", "--recipe", str(recipe), str(in_dir), str(tmp_path / "out"), "--quiet",
                               *map(str, extra)])


def test_a_single_file_as_input_is_named_a_file(tmp_path, photos):
    r = _augment(tmp_path, JPEG, photos / "IMG_0.png")
    assert r.exit_code == 2 and "is a file" in r.output and "does not exist" not in r.output
    assert "rvnoise preview" in r.output and not (tmp_path / "out").exists()


def test_a_lidar_recipe_on_photos_says_what_the_folder_holds(tmp_path, photos):
    r = _augment(tmp_path, FOG_LIDAR, photos)
    assert r.exit_code == 2 and not (tmp_path / "out").exists()
    assert "2 camera image(s)" in r.output and "'IMG_0.png'" in r.output and "is for lidar data" in r.output


def test_globs_that_miss_the_photos_get_a_glob_that_takes_them(tmp_path, photos):
    r = _augment(tmp_path, JPEG, photos)
    assert r.exit_code == 2 and "2 camera image(s) or raw frame(s) they miss" in r.output
    assert "set inputs.camera to a glob that matches them, e.g. '**/*.png'" in r.output
    body = {**JPEG, "inputs": {"camera": "**/*.png"}}                  # the suggested glob runs
    assert _augment(tmp_path, body, photos).exit_code == 0 and (tmp_path / "out" / "IMG_1.png").is_file()


def test_an_empty_folder_says_it_holds_nothing_readable(tmp_path):
    (tmp_path / "empty").mkdir()
    r = _augment(tmp_path, JPEG, tmp_path / "empty")
    assert r.exit_code == 2 and "holds no file rvnoise reads" in r.output and not (tmp_path / "out").exists()


def test_a_short_write_without_errno_is_named_a_full_disk():
    """numpy's tofile (tifffile's DNG pixel data) reports a full disk as a bare short write."""
    from roadview_noise.output_sync import write_error

    text = write_error("raw/a.dng", "raw/a.dng", OSError("177144 requested and 32528 written"))
    assert "no space left on device" in text and "32528 of 177144 bytes" in text and "--resume" in text
    assert "--resume" not in write_error("a.png", "a.png", OSError("cannot encode"))


def test_a_full_disk_under_dng_outputs_says_so_in_each_entry_and_in_run_json(tmp_path):
    import json
    import shutil
    import subprocess

    from roadview_noise.manifest import read_manifest

    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(mnt)],
                      capture_output=True).returncode != 0:
        pytest.skip("needs permission to mount a tmpfs")
    try:
        shutil.copytree(Path(__file__).parents[1] / "sample_data" / "raw", tmp_path / "in" / "raw")
        body = {"chain": [{"model": "fog.camera"}], "inputs": {"raw": "raw/**/*.dng", "depth": "{stem}_depth.exr"}}
        (tmp_path / "r.yaml").write_text(yaml.safe_dump(body))
        r = runner.invoke(app, ["augment", "--recipe", str(tmp_path / "r.yaml"), str(tmp_path / "in"),
                                str(mnt / "out"), "--quiet", "--workers", "1"])
        assert r.exit_code == 1 and "Traceback" not in r.output, r.output
        failed = [e for e in read_manifest(mnt / "out" / "manifest.jsonl") if e["status"] == "failed"]
        assert failed and all("no space left on device" in e["error"] and "--resume" in e["error"] for e in failed)
        assert any("disk filled up" in n for n in json.loads((mnt / "out" / "run.json").read_text())["notes"])
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_more_workers_than_cores_are_run_and_said_to_share_them():
    from roadview_noise.resources import WORKER_PEAK_BYTES, choose_workers

    n, why = choose_workers(8, 100, available=100 * WORKER_PEAK_BYTES, cores=2)
    assert n == 8 and "8 workers on 2 cores" in why and "no faster than --workers 2" in why
    n, why = choose_workers(64, 6, available=100 * WORKER_PEAK_BYTES, cores=2)
    assert n == 6 and "capped to 6: 6 output(s) to write" in why and "6 workers on 2 cores" in why
    assert choose_workers(None, 100, available=100 * WORKER_PEAK_BYTES, cores=3) == (3, None)
    assert choose_workers(2, 100, available=100 * WORKER_PEAK_BYTES, cores=2) == (2, None)


def test_the_default_workers_follow_the_cpus_this_process_may_use(monkeypatch):
    import os

    from roadview_noise import resources

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)   # taskset -c 0 on any machine
    assert resources.usable_cores() == 1
    assert resources.choose_workers(None, 100, available=100 * resources.WORKER_PEAK_BYTES)[0] == 1


@pytest.mark.parametrize("workers", ["0", "-1", "two"])
def test_workers_zero_or_not_a_number_is_refused_before_anything_is_written(tmp_path, photos, workers):
    r = _augment(tmp_path, {**JPEG, "inputs": {"camera": "*.png"}}, photos, "--workers", workers)
    assert r.exit_code == 2 and "--workers" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "out").exists()


def test_replay_of_a_folder_of_runs_names_its_runs_and_a_run_folder_replays(tmp_path, photos):
    body = {**JPEG, "inputs": {"camera": "*.png"}}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(body))
    for name in ("a", "b"):                            # make demo's layout: out/demo/<run>/manifest.jsonl
        r = runner.invoke(app, ["augment", "--recipe", str(tmp_path / "r.yaml"), str(photos),
                                str(tmp_path / "demo" / name), "--quiet"])
        assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["replay", str(tmp_path / "demo" / "manifest.jsonl"), "--key", "IMG_0.png"])
    assert r.exit_code == 2 and "a/manifest.jsonl, b/manifest.jsonl" in r.output and "run.json" not in r.output
    r = runner.invoke(app, ["replay", str(tmp_path / "demo" / "a"), "--key", "IMG_0.png"])
    assert r.exit_code == 0 and r.output.startswith("match: IMG_0.png")


def test_the_same_command_again_says_what_the_earlier_run_did(tmp_path, photos):
    import json

    body = {**JPEG, "inputs": {"camera": "*.png"}}
    assert _augment(tmp_path, body, photos).exit_code == 0
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    record.update(state="interrupted", counts={"planned": 2, "done": 1, "skipped": 0, "failed": 0})
    (tmp_path / "out" / "run.json").write_text(json.dumps(record))      # as a Ctrl-C after the first file leaves it
    r = _augment(tmp_path, body, photos)
    assert r.exit_code == 2 and "(interrupted: 1 of 2 outputs done)" in r.output and "--resume" in r.output
    r = _augment(tmp_path, {**body, "seed": 5}, photos)
    assert r.exit_code == 2 and "(interrupted: 1 of 2 outputs done, another recipe)" in r.output
    assert _augment(tmp_path, body, photos, "--resume").exit_code == 0


@pytest.mark.parametrize("recipe, says", [
    ("CNF5", "neither a recipe file nor a CNF id (did you mean 'CNF05'?)"),
    ("CNF20", "is a camera image, but the recipe's chain (alignment.lidar → fog.lidar) is for lidar data"),
])
def test_preview_names_a_cnf_without_its_zero_and_a_recipe_for_another_sensor(tmp_path, photos, recipe, says):
    r = runner.invoke(app, ["preview", "--recipe", recipe, str(photos / "IMG_0.png"), "-o", str(tmp_path / "p.png")])
    assert r.exit_code == 2 and says in r.output and "Traceback" not in r.output
    assert not (tmp_path / "p.png").exists()


def test_a_contact_sheet_shows_its_progress_one_step_per_cnf(photos, capsys):
    from roadview_noise.preview import contact_sheet

    contact_sheet(photos / "IMG_0.png", "camera", progress=True, panel_px=120, depth_source="ground_plane")
    err = capsys.readouterr().err
    assert "0/18 " in err and "CNF/s" in err                        # CNF01–CNF18 on a camera frame


def test_show_keeps_its_columns_apart_for_long_names_and_defaults():
    """fog.lidar's backscatter_times_visibility_per_sr ran into its unit, 'default sensor_constant' into its range."""
    r = runner.invoke(app, ["show", "fog.lidar"])
    rows = [line for line in r.output.splitlines() if " default " in line]
    assert r.exit_code == 0 and len(rows) >= 7
    assert len({line.index(" default ") for line in rows}) == 1                  # the default column is aligned
    assert all("backscatter_times_visibility_per_sr sr" not in line for line in rows)
    assert any("default sensor_constant  " in line for line in rows)


def test_preview_never_writes_over_its_input_and_takes_a_folder_for_one_file(tmp_path, photos):
    from roadview_noise.manifest import sha256_file

    photo = photos / "IMG_0.png"
    before = sha256_file(photo)
    r = runner.invoke(app, ["preview", "--recipe", "CNF11", str(photo), "-o", str(photo), "--depth-source",
                            "ground_plane"])
    assert r.exit_code == 2 and "is an input file" in r.output and sha256_file(photo) == before
    (tmp_path / "sheets").mkdir()                    # README: `--all-cnfs FILE -o sheets/` (was a traceback)
    r = runner.invoke(app, ["preview", "--all-cnfs", str(photo), "-o", str(tmp_path / "sheets"), "--depth-source",
                            "ground_plane", "--panel-px", "120"])
    assert r.exit_code == 0 and "Traceback" not in r.output and len(list((tmp_path / "sheets").glob("*.png"))) == 1


def test_replay_and_report_never_write_over_the_inputs(tmp_path, photos):
    from roadview_noise.manifest import sha256_file

    body = {**JPEG, "inputs": {"camera": "*.png"}}
    assert _augment(tmp_path, body, photos).exit_code == 0
    before = {p.name: sha256_file(p) for p in photos.iterdir()}
    for target, where in ((photos / "IMG_0.png", "input tree"), (tmp_path / "out" / "x.png", "output folder")):
        r = runner.invoke(app, ["replay", str(tmp_path / "out"), "--key", "IMG_0.png", "--out", str(target)])
        assert r.exit_code == 2 and f"inside the run's {where}" in r.output
    assert not (tmp_path / "out" / "x.png").exists()
    r = runner.invoke(app, ["report", str(tmp_path / "out"), "-o", str(photos / "IMG_1.png")])
    assert r.exit_code == 2 and "give a .html name" in r.output
    assert {p.name: sha256_file(p) for p in photos.iterdir()} == before
    r = runner.invoke(app, ["replay", str(tmp_path / "out"), "--key", "IMG_0.png", "--out", str(tmp_path / "r.png")])
    assert r.exit_code == 0 and sha256_file(tmp_path / "r.png") == sha256_file(tmp_path / "out" / "IMG_0.png")


def test_a_run_started_inside_another_checkout_runs_the_installed_code_in_its_workers(tmp_path, photos):
    """The fork server imported its preloads from the current folder: run from a folder holding another
    roadview_noise (another checkout, an older copy), every worker ran that copy."""
    import shutil
    import subprocess
    import sys

    import roadview_noise

    other = tmp_path / "checkout"
    shutil.copytree(Path(roadview_noise.__file__).parent, other / "roadview_noise",
                    ignore=shutil.ignore_patterns("__pycache__"))
    with open(other / "roadview_noise" / "runner.py", "a") as fh:
        fh.write("\n\ndef _process(*a, **k):\n    raise RuntimeError('the checkout in the current folder ran')\n")
    (tmp_path / "r.yaml").write_text(yaml.safe_dump({**JPEG, "inputs": {"camera": "*.png"}}))
    rvnoise = Path(sys.executable).parent / "rvnoise"
    if not rvnoise.is_file():
        pytest.skip("needs the installed rvnoise script")
    r = subprocess.run([str(rvnoise), "augment", "--recipe", str(tmp_path / "r.yaml"), str(photos),
                        str(tmp_path / "out"), "--quiet", "--workers", "1"], cwd=other, capture_output=True, text=True)
    assert r.returncode == 0 and "checkout in the current folder" not in r.stderr, r.stderr
    assert (tmp_path / "out" / "IMG_0.png").is_file()
