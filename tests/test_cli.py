"""End-to-end CLI and runner: determinism across workers, replay, resume after a kill, per-file errors, exit codes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from roadview_noise.cli.main import app
from roadview_noise.io.image import write_image
from roadview_noise.io.pointcloud import write_pointcloud
from roadview_noise.manifest import read_manifest, sha256_file
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.types import CloudLayout, ImageEncoding, PointCloud

runner = CliRunner()


def _image(rng, h=48, w=64):
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([x / w, y / h, 0.5 + 0.0 * x], axis=-1)
    return np.clip(base + 0.05 * rng.standard_normal((h, w, 3)), 0, 1).astype(np.float32)


def _cloud(rng, n=2000):
    prof = os1_128()
    ring = rng.integers(0, 128, n)
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))[ring]
    r = rng.uniform(2, 60, n)
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    layout = CloudLayout("pcd", (("x", "x", "float32"), ("y", "y", "float32"), ("z", "z", "float32"),
                                 ("intensity", "intensity", "float32"), ("ring", "ring", "uint16")))
    return PointCloud(pos, {"intensity": rng.uniform(1, 200, n).astype(np.float32), "ring": ring.astype(np.uint16)},
                      "lidar", prof, layout)


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    root = tmp_path / "in"
    for seq in ("seqA", "seqB"):
        for i in range(3):
            write_image(root / "cam" / seq / f"{i:06d}.png", _image(rng), ImageEncoding())
            write_pointcloud(root / "lidar" / seq / f"{i:06d}.pcd", _cloud(rng))
    return root


def _recipe(tmp_path: Path, body: dict, name="r.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(body))
    return p


CAMERA = {"chain": [{"model": "compression.camera", "params": {"quality": {"uniform": [10, 60]}}}], "seed": 7,
          "inputs": {"camera": "cam/**/*.png"}}
LIDAR = {"chain": [{"model": "alignment.lidar"}, {"model": "power.lidar"}], "seed": 7,
         "inputs": {"lidar": "lidar/**/*.pcd", "lidar_profile": "os1-128", "intensity_unit": "uint8",
                    "intensity_full_scale": 255}}


def _tree_hashes(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): sha256_file(p) for p in sorted(root.rglob("*"))
            if p.is_file() and p.name not in ("manifest.jsonl", "run.json")}


def _augment(*args) -> "object":
    return runner.invoke(app, ["augment", *map(str, args), "--quiet"])


@pytest.mark.parametrize("body", [CAMERA, LIDAR], ids=["camera", "lidar"])
def test_workers_1_and_2_byte_identical_and_replay(tmp_path, tree, body):
    recipe = _recipe(tmp_path, body)
    r1 = _augment(tree, tmp_path / "o1", "--recipe", recipe, "--workers", 1)
    r2 = _augment(tree, tmp_path / "o2", "--recipe", recipe, "--workers", 2)
    assert r1.exit_code == 0 and r2.exit_code == 0, r1.output + r2.output
    h1, h2 = _tree_hashes(tmp_path / "o1"), _tree_hashes(tmp_path / "o2")
    assert len(h1) == 6 and h1 == h2
    entries = read_manifest(tmp_path / "o1" / "manifest.jsonl")
    assert [e["status"] for e in entries] == ["ok"] * 6
    assert all(e["output_sha256"] == h1[e["output"]] and e["input_sha256"] for e in entries)
    key = entries[3]["output"]
    rr = runner.invoke(app, ["replay", str(tmp_path / "o1" / "manifest.jsonl"), "--key", key])
    assert rr.exit_code == 0 and "match" in rr.output, rr.output


def test_sequence_state_shared_within_sequence(tmp_path, tree):
    recipe = _recipe(tmp_path, LIDAR)
    assert _augment(tree, tmp_path / "o", "--recipe", recipe, "--workers", 1).exit_code == 0
    entries = read_manifest(tmp_path / "o" / "manifest.jsonl")
    states = {}
    for e in entries:
        states.setdefault(e["sequence"], []).append(e["steps"][0]["state"])
    a, b = states["lidar/seqA"], states["lidar/seqB"]
    assert a[0] == a[1] == a[2] and b[0] == b[1] == b[2] and a[0] != b[0]


def test_resume_after_kill_gives_same_tree_and_no_temporaries(tmp_path, tree):
    rng = np.random.default_rng(1)
    for i in range(3, 40):
        write_image(tree / "cam" / "seqA" / f"{i:06d}.png", _image(rng, 240, 320), ImageEncoding())
    recipe = _recipe(tmp_path, CAMERA)
    ref = tmp_path / "ref"
    assert _augment(tree, ref, "--recipe", recipe, "--workers", 1).exit_code == 0
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "roadview_noise.cli.main", "augment", str(tree), str(out), "--recipe", str(recipe),
           "--workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60
    while time.time() < deadline and proc.poll() is None:
        m = out / "manifest.jsonl"
        if m.exists() and len(m.read_text().splitlines()) >= 3:
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    (out / "cam" / "seqA" / ".000039.12345.rvnoise-tmp.png").write_bytes(b"half")  # as a killed write leaves it
    r = _augment(tree, out, "--recipe", recipe, "--workers", 2, "--resume")
    assert r.exit_code == 0, r.output
    assert _tree_hashes(out) == _tree_hashes(ref)
    assert not [p for p in out.rglob("*") if "rvnoise-tmp" in p.name]
    assert len(read_manifest(out / "manifest.jsonl")) == len(read_manifest(ref / "manifest.jsonl"))


def test_bad_inputs_recorded_and_run_goes_on(tmp_path, tree):
    bad = tree / "lidar" / "bad"
    bad.mkdir()
    good = (tree / "lidar" / "seqA" / "000000.pcd").read_bytes()
    (bad / "truncated.pcd").write_bytes(good[: len(good) // 2])
    (bad / "odd.bin").write_bytes(np.zeros(4 * 4 * 10 + 3, np.uint8).tobytes())
    nan = np.zeros((10, 4), np.float32)
    nan[3, 1] = np.nan
    nan.tofile(bad / "nan.bin")
    (bad / "empty.bin").write_bytes(b"")
    body = {**LIDAR, "inputs": {**LIDAR["inputs"], "lidar": ["lidar/**/*.pcd", "lidar/**/*.bin"]}}
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, body), "--workers", 2)
    assert r.exit_code == 1
    entries = {e["input"]: e for e in read_manifest(tmp_path / "o" / "manifest.jsonl")}
    for name in ("truncated.pcd", "odd.bin", "nan.bin", "empty.bin"):
        e = entries[f"lidar/bad/{name}"]
        assert e["status"] == "failed" and name in e["error"], e
        assert not (tmp_path / "o" / "lidar" / "bad" / name).exists()
    assert sum(e["status"] == "ok" for e in entries.values()) == 6


def test_depth_problems_recorded_per_file(tmp_path, tree):
    """fog.camera needs depth: a wrong-size depth map and a missing sidecar fail their own file only."""
    from roadview_noise.io.depth import write_depth_exr

    seq = tree / "cam" / "seqA"
    write_depth_exr(seq / "000000_depth.exr", np.full((48, 64), 20.0, np.float32))    # right size
    write_depth_exr(seq / "000001_depth.exr", np.full((40, 64), 20.0, np.float32))    # wrong size
    body = {"chain": [{"model": "fog.camera", "params": {"visibility_m": 50}}], "seed": 1,
            "inputs": {"camera": "cam/seqA/*.png", "camera_profile": {"width_px": 64, "height_px": 48,
                                                                     "fov_h_deg": 80.8}}}
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, body), "--workers", 2)
    assert r.exit_code == 1
    entries = {e["input"]: e for e in read_manifest(tmp_path / "o" / "manifest.jsonl")}
    assert entries["cam/seqA/000000.png"]["status"] == "ok"
    wrong = entries["cam/seqA/000001.png"]
    assert wrong["status"] == "failed" and "000001_depth.exr" in wrong["error"] and "48" in wrong["error"]
    missing = entries["cam/seqA/000002.png"]
    assert missing["status"] == "failed" and "000002_depth.exr" in missing["error"]
    assert "fog.camera" in missing["error"]


def test_truncated_png_recorded(tmp_path, tree):
    p = tree / "cam" / "seqA" / "000000.png"
    p.write_bytes(p.read_bytes()[:200])
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA))
    assert r.exit_code == 1
    e = {e["input"]: e for e in read_manifest(tmp_path / "o" / "manifest.jsonl")}["cam/seqA/000000.png"]
    assert e["status"] == "failed" and "000000.png" in e["error"]


def test_fail_fast_stops(tmp_path, tree):
    (tree / "cam" / "seqA" / "000000.png").write_bytes(b"not a png")
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA), "--workers", 1, "--fail-fast")
    assert r.exit_code == 1
    assert len(read_manifest(tmp_path / "o" / "manifest.jsonl")) == 1


@pytest.mark.parametrize("body,key", [
    ({**CAMERA, "sede": 1}, "sede"),
    ({"chain": [{"model": "compression.camera", "params": {"quality": -1}}]}, "quality"),
    ({"chain": [{"model": "fog.camra"}]}, "fog.camera"),
])
def test_bad_recipe_exits_2_before_writing(tmp_path, tree, body, key):
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, body))
    assert r.exit_code == 2 and key in r.output
    assert not (tmp_path / "o").exists()


def test_output_inside_input_refused(tmp_path, tree):
    r = _augment(tree, tree / "out", "--recipe", _recipe(tmp_path, CAMERA))
    assert r.exit_code == 2 and "overlap" in r.output
    assert not (tree / "out").exists()


def test_dry_run_and_limit_write_nothing(tmp_path, tree):
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA), "--dry-run", "--limit", 2)
    assert r.exit_code == 0 and r.output.count("→") >= 2 and "2 outputs planned" in r.output
    assert not (tmp_path / "o").exists()


def test_earlier_run_needs_resume_or_overwrite(tmp_path, tree):
    recipe = _recipe(tmp_path, CAMERA)
    assert _augment(tree, tmp_path / "o", "--recipe", recipe).exit_code == 0
    r = _augment(tree, tmp_path / "o", "--recipe", recipe)
    assert r.exit_code == 2 and "--resume" in r.output
    assert _augment(tree, tmp_path / "o", "--recipe", recipe, "--overwrite").exit_code == 0


def test_sweep_writes_one_variant_per_value(tmp_path, tree):
    body = {**CAMERA, "chain": [{"model": "compression.camera"}], "sweep": {"compression.camera.quality": [5, 95]}}
    assert _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, body), "--limit", 1).exit_code == 0
    names = sorted(p.name for p in (tmp_path / "o" / "cam" / "seqA").iterdir())
    assert names == ["000000__quality-5.png", "000000__quality-95.png"]
    a, b = (tmp_path / "o" / "cam" / "seqA" / n for n in names)
    assert a.read_bytes() != b.read_bytes()


def test_list_show_validate():
    r = runner.invoke(app, ["list"])
    assert r.exit_code == 0 and "compression.camera" in r.output and "CNF30" in r.output
    r = runner.invoke(app, ["show", "CNF25"])
    assert r.exit_code == 0 and "[lidar]" in r.output and "[radar]" in r.output
    r = runner.invoke(app, ["show", "alignment.lidar"])
    assert r.exit_code == 0 and "elevation_sd_deg" in r.output and "deg" in r.output
    recipes = sorted(p for p in (Path(__file__).parents[1] / "recipes").rglob("*.yaml") if "calibration" not in p.parts)
    assert recipes
    for p in recipes:
        r = runner.invoke(app, ["validate", str(p)])
        assert r.exit_code == 0, (p, r.output)


def test_help_has_examples():
    for cmd in ("augment", "validate", "list", "show", "replay", "sample-data"):
        r = runner.invoke(app, [cmd, "--help"])
        assert r.exit_code == 0 and "Example" in r.output, cmd


@pytest.mark.parametrize("args,line", [
    (["--workers", "0"], "rvnoise: augment: Invalid value for '--workers' / '-j': Input should be greater than or "
                         "equal to 1"),
    (["--limit", "x"], "rvnoise: augment: Invalid value for '--limit': Input should be a valid integer"),
    (["--bogus"], "rvnoise: augment: No such option: --bogus"),
])
def test_a_bad_option_is_one_line_naming_it_and_its_range(tmp_path, tree, args, line):
    """Typer printed a five-line box for an option out of its range; the module docstring promises one line."""
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA), *args)
    assert r.exit_code == 2 and r.output.strip().count("\n") == 0 and r.output.startswith(line)
    assert not (tmp_path / "o").exists()
