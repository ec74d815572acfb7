"""What a run promises (README "Guarantees"), one section per item of issue 12: never write outside OUT, survive a
dying worker, bound every resource, one run per OUT, say what went wrong in words, never change data silently."""

from __future__ import annotations

import errno
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time
import tracemalloc
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
from test_cli import CAMERA, LIDAR, _augment, _cloud, _image, _recipe, _tree_hashes, runner, tree  # noqa: F401

from roadview_noise.cli.main import app
from roadview_noise.io.image import write_image
from roadview_noise.io.pointcloud import write_pointcloud
from roadview_noise.manifest import read_manifest, sha256_file
from roadview_noise.recipe import load_recipe, parse_recipe
from roadview_noise.registry import MODELS, register
from roadview_noise.types import ImageEncoding

TESTS = Path(__file__).resolve().parent


@pytest.fixture
def injected():
    """The test-only models of tests/injected_models.py, registered for this test only."""
    import injected_models

    for cls in injected_models.INJECTED:
        register(cls)
    yield injected_models
    for cls in injected_models.INJECTED:
        MODELS.pop(cls.id, None)


def _poison(path: Path, h=48, w=64) -> None:
    img = _image(np.random.default_rng(5), h, w)
    img[0, 0] = 1.0
    write_image(path, img, ImageEncoding())


def _files(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): sha256_file(p) for p in sorted(root.rglob("*"))
            if p.is_file() and p.name not in ("manifest.jsonl", "run.json")}


def assert_out_equals_manifest(out: Path, last_line_wins: bool = False) -> list[dict]:
    """Every file in OUT is listed once, with its sha256, by an ok entry; nothing else is there. ``last_line_wins``:
    read the manifest as ``--resume`` and ``replay`` do (a later line of an output replaces an earlier one)."""
    entries = read_manifest(out / "manifest.jsonl")
    if last_line_wins:
        entries = list({e["output"]: e for e in entries}.values())
    listed: dict[str, str] = {}
    for e in entries:
        if e["status"] != "ok":
            assert "files" not in e, e
            continue
        for f in e["files"]:
            assert f["path"] not in listed, f"{f['path']} listed twice"
            listed[f["path"]] = f["sha256"]
    assert _files(out) == listed
    assert (out / "run.json").is_file()
    return entries


# --- 1. inputs only inside IN: '..' and absolute globs ---------------------------------------------------------------


def test_dotdot_and_absolute_patterns_refused_before_anything_is_written(tmp_path, tree):
    victim = tmp_path / "victim"
    write_image(victim / "a.png", _image(np.random.default_rng(1)), ImageEncoding())
    before = _files(victim)
    for inputs, words in [({"camera": "../victim/*.png"}, "'..'"), ({"camera": str(victim / "*.png")}, "absolute"),
                          ({"camera": "cam/**/*.png", "exclude": ["/etc/*"]}, "absolute")]:
        recipe = _recipe(tmp_path, {**CAMERA, "inputs": inputs})
        v = runner.invoke(app, ["validate", str(recipe)])
        assert v.exit_code == 2 and words in v.output and "inputs." in v.output, v.output
        r = _augment(tree, tmp_path / "o", "--recipe", recipe)
        assert r.exit_code == 2 and words in r.output and "Traceback" not in r.output, r.output
        assert not (tmp_path / "o").exists()
    assert _files(victim) == before


def test_a_sidecar_outside_the_input_folder_is_not_read(tmp_path, tree):
    from roadview_noise.io.depth import write_depth_exr

    write_depth_exr(tmp_path / "000000_depth.exr", np.full((48, 64), 20.0, np.float32))
    (tree / "cam" / "seqA" / "000000_depth.exr").symlink_to(tmp_path / "000000_depth.exr")
    body = {"chain": [{"model": "fog.camera"}], "seed": 1,
            "inputs": {"camera": "cam/seqA/000000.png", "camera_profile": {"width_px": 64, "height_px": 48}}}
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, body))
    assert r.exit_code == 1
    e = read_manifest(tmp_path / "o" / "manifest.jsonl")[0]
    assert "000000_depth.exr" in e["error"] and "outside the input folder" in e["error"]


# --- 2. outputs only inside OUT: a symlink in OUT is never followed out of it ------------------------------------------


def test_symlink_in_out_to_the_input_is_not_followed(tmp_path, tree):
    before = _files(tree)
    out = tmp_path / "o"
    (out / "cam").mkdir(parents=True)
    (out / "cam" / "seqA").symlink_to(tree / "cam" / "seqA")      # a folder inside OUT leading into IN
    (out / "lidar").symlink_to(tree / "lidar")
    for body in (CAMERA, LIDAR):
        r = _augment(tree, out, "--recipe", _recipe(tmp_path, body), "--workers", 2, "--overwrite")
        assert r.exit_code == 1, r.output
    assert _files(tree) == before
    entries = read_manifest(out / "manifest.jsonl")          # the last run: LiDAR, all behind the symlink
    assert entries and all(e["status"] == "failed" and "outside the output folder" in e["error"] for e in entries)
    assert all(e["input"].startswith("lidar/") for e in entries)
    assert not [p for p in tree.rglob("*") if "rvnoise-tmp" in p.name or p.suffix == ".label"]


def test_camera_outputs_beside_a_symlinked_folder_still_written(tmp_path, tree):
    out = tmp_path / "o"
    (out / "cam").mkdir(parents=True)
    (out / "cam" / "seqA").symlink_to(tree / "cam" / "seqA")
    r = _augment(tree, out, "--recipe", _recipe(tmp_path, CAMERA), "--workers", 2)
    assert r.exit_code == 1
    status = {e["input"]: e["status"] for e in read_manifest(out / "manifest.jsonl")}
    assert {k for k, v in status.items() if v == "ok"} == {f"cam/seqB/{i:06d}.png" for i in range(3)}


# --- 3. decompression bombs and oversized clouds fail on their header -------------------------------------------------


def _png_header_only(path: Path, width: int, height: int) -> None:
    """A tiny PNG whose IHDR declares width × height RGB pixels (its data is a few bytes of deflate)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 4096))
                     + chunk(b"IEND", b""))


def test_pixel_bomb_and_point_cap_fail_on_the_header(tmp_path, tree):
    _png_header_only(tree / "cam" / "seqA" / "bomb.png", 60000, 60000)
    _png_header_only(tree / "cam" / "seqA" / "big.png", 12000, 10000)      # 120 MP, under OpenCV's own limit
    t0 = time.perf_counter()
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA), "--workers", 2)
    assert r.exit_code == 1
    entries = {e["input"]: e for e in read_manifest(tmp_path / "o" / "manifest.jsonl")}
    for name, mp in (("bomb.png", "3600.0"), ("big.png", "120.0")):
        e = entries[f"cam/seqA/{name}"]
        assert e["status"] == "failed" and f"{mp} megapixels" in e["error"] and "--max-pixels" in e["error"], e
        assert "traceback" not in e and e["seconds"] < 1.0
    assert time.perf_counter() - t0 < 60
    r = _augment(tree, tmp_path / "o2", "--recipe", _recipe(tmp_path, LIDAR), "--max-points", 1000)
    assert r.exit_code == 1
    entries = read_manifest(tmp_path / "o2" / "manifest.jsonl")
    assert entries and all(e["status"] == "failed" and "2,000 points" in e["error"] and "--max-points" in e["error"]
                           for e in entries)


# --- 4. a dying worker fails its own file only --------------------------------------------------------------------------


def test_worker_killed_on_one_file_fails_that_file_only(tmp_path, tree, injected):
    _poison(tree / "cam" / "seqA" / "000001.png")
    trace = tmp_path / "trace.txt"
    body = {"chain": [{"model": "test_crash.camera", "params": {"trace_path": str(trace)}}], "seed": 1,
            "inputs": {"camera": "cam/**/*.png"}}
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, body), "--workers", 2)
    assert r.exit_code == 1, r.output
    assert "Traceback" not in r.output
    entries = assert_out_equals_manifest(tmp_path / "o")
    assert len(entries) == 6
    bad = [e for e in entries if e["status"] != "ok"]
    assert [e["input"] for e in bad] == ["cam/seqA/000001.png"]
    assert "worker died: signal 9" in bad[0]["error"] and "out of memory" in bad[0]["error"]
    assert bad[0]["worker_deaths"] == 2
    calls = trace.read_text().split()
    assert calls.count("poison") == 2                        # tried twice, never a third time
    assert json.loads((tmp_path / "o" / "run.json").read_text())["state"] == "complete"
    assert not list((tmp_path / "o").rglob("*rvnoise-tmp*"))


def test_task_timeout_stops_a_stuck_worker(tmp_path, tree, injected):
    _poison(tree / "cam" / "seqA" / "000002.png")                 # SleepCamera sleeps for an hour on it
    body = {"chain": [{"model": "test_sleep.camera", "params": {"sleep_s": 0}}], "seed": 1,
            "inputs": {"camera": "cam/seqA/*.png"}}
    from roadview_noise.runner import Limits, run

    s = run(load_recipe(_recipe(tmp_path, body)), tree, tmp_path / "o", workers=2, progress=False,
            limits=Limits(task_timeout_s=3), echo=lambda m: None)
    assert (s.done, s.failed) == (2, 1)
    assert "took longer than 3 s" in s.failures[0]


# --- 5. --workers is capped at the outputs and at the memory ------------------------------------------------------------


def test_workers_capped_at_outputs_and_memory(tmp_path, tree, monkeypatch):
    from roadview_noise import resources
    from roadview_noise.runner import run

    said = []
    s = run(load_recipe(_recipe(tmp_path, CAMERA)), tree, tmp_path / "o", workers=1000, progress=False,
            echo=lambda m: None, warn=said.append)
    assert s.workers == 6 and s.done == 6
    assert any("--workers 1000 capped to 6" in m and "6 output(s)" in m for m in said), said
    peak = resources.WORKER_PEAK_BYTES
    n, why = resources.choose_workers(8, 100, available=int(2.5 * peak))
    assert n == 2 and "holds 2 workers" in why
    assert resources.choose_workers(None, 100, available=10 * peak) == (min(resources.usable_cores(), 10), None)
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: int(1.2 * peak))
    assert resources.choose_workers(4, 100)[0] == 1


# --- 6. --resume continues only the same recipe and redoes changed inputs -----------------------------------------------


def test_resume_refuses_another_recipe_and_redoes_changed_inputs(tmp_path, tree):
    recipe = _recipe(tmp_path, CAMERA)
    out = tmp_path / "o"
    assert _augment(tree, out, "--recipe", recipe).exit_code == 0
    other = _recipe(tmp_path, {**CAMERA, "seed": 8}, "r2.yaml")
    r = _augment(tree, out, "--recipe", other, "--resume")
    assert r.exit_code == 2 and "another recipe" in r.output and "--overwrite" in r.output
    changed = tree / "cam" / "seqB" / "000002.png"
    write_image(changed, _image(np.random.default_rng(99)), ImageEncoding())
    r = _augment(tree, out, "--recipe", recipe, "--resume")
    assert r.exit_code == 0 and "1 written, 5 skipped" in r.output, r.output
    assert _augment(tree, tmp_path / "fresh", "--recipe", recipe).exit_code == 0
    assert _files(out) == _files(tmp_path / "fresh")
    e = {e["input"]: e for e in assert_out_equals_manifest(out)}["cam/seqB/000002.png"]
    assert e["input_sha256"] == sha256_file(changed)
    r = _augment(tree, out, "--recipe", recipe, "--resume", "--limit", 1)     # a partial plan deletes nothing
    assert r.exit_code == 0 and "0 written, 1 skipped" in r.output and len(assert_out_equals_manifest(out)) == 6


# --- 7. one run per OUT ------------------------------------------------------------------------------------------------


def test_second_run_on_a_locked_output_exits_2_naming_the_holder(tmp_path, tree):
    from roadview_noise.lock import LOCK_NAME, OutputLock

    out = tmp_path / "o"
    out.mkdir()
    with OutputLock(out):
        r = _augment(tree, out, "--recipe", _recipe(tmp_path, CAMERA))
        assert r.exit_code == 2 and f"pid {os.getpid()}" in r.output and socket.gethostname() in r.output
        assert not (out / "manifest.jsonl").exists()
    assert not (out / LOCK_NAME).exists()


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path, tree):
    from roadview_noise.lock import LOCK_NAME

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "o"
    out.mkdir()
    (out / LOCK_NAME).write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(), "started_unix": 1}))
    r = runner.invoke(app, ["augment", str(tree), str(out), "--recipe", str(_recipe(tmp_path, CAMERA)), "--quiet"])
    assert r.exit_code == 0 and f"stale lock" in r.output and f"pid {dead.pid}" in r.output, r.output
    assert not (out / LOCK_NAME).exists()
    (out / LOCK_NAME).write_text(json.dumps({"pid": 1, "host": "elsewhere.example", "started_unix": 1}))
    r = _augment(tree, out, "--recipe", _recipe(tmp_path, CAMERA), "--overwrite")
    assert r.exit_code == 2 and "another host" in r.output and "elsewhere.example" in r.output


# --- 8. every path the walk cannot read is a failed entry ---------------------------------------------------------------


def test_unreadable_folder_and_dangling_symlink_are_failed_entries(tmp_path, tree, monkeypatch):
    (tree / "cam" / "seqA" / "gone.png").symlink_to(tmp_path / "nowhere.png")
    locked = str(tree / "cam" / "seqB")
    real_scandir = os.scandir

    def scandir(path="."):
        if os.fspath(path) == locked:
            raise PermissionError(errno.EACCES, "Permission denied", locked)
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", scandir)
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA), "--workers", 1)
    assert r.exit_code == 1, r.output
    entries = {e["input"]: e for e in read_manifest(tmp_path / "o" / "manifest.jsonl")}
    assert entries["cam/seqB"]["status"] == "failed" and "permission denied" in entries["cam/seqB"]["error"]
    assert "dangling symlink" in entries["cam/seqA/gone.png"]["error"]
    assert sum(e["status"] == "ok" for e in entries.values()) == 3


# --- 9. environment errors: one line, exit 2 when nothing was done; the run record survives a full disk --------------


def test_output_that_is_a_file_or_unwritable_exits_2_in_one_line(tmp_path, tree, monkeypatch):
    (tmp_path / "o").write_text("a file")
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA))
    assert r.exit_code == 2 and "is not a folder" in r.output and len(r.output.strip().splitlines()) == 1

    def refuse(self, *a, **k):
        raise PermissionError(errno.EACCES, "Permission denied", str(self))

    monkeypatch.setattr(Path, "mkdir", refuse)
    r = _augment(tree, tmp_path / "ro" / "out", "--recipe", _recipe(tmp_path, CAMERA))
    assert r.exit_code == 2 and "permission denied" in r.output and len(r.output.strip().splitlines()) == 1


def test_disk_full_at_the_final_manifest_still_writes_run_json(tmp_path, tree, monkeypatch):
    from roadview_noise import runner as runner_module

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    recipe = _recipe(tmp_path, CAMERA)
    assert _augment(tree, tmp_path / "o", "--recipe", recipe, "--limit", "1").exit_code == 0
    monkeypatch.setattr(runner_module, "write_manifest", full)    # a resumed run rewrites the manifest at the end
    r = _augment(tree, tmp_path / "o", "--recipe", recipe, "--resume")
    assert r.exit_code == 1 and "no space left on device" in r.output and "Traceback" not in r.output
    record = json.loads((tmp_path / "o" / "run.json").read_text())
    counts = record["counts"]
    assert record["state"] == "complete" and counts["done"] + counts["skipped"] == 6 and record["notes"]
    assert_out_equals_manifest(tmp_path / "o", last_line_wins=True)   # the appended manifest lists every file


def test_disk_full_while_writing_fails_that_file(tmp_path, tree, monkeypatch):
    from roadview_noise.dataset import discover
    from roadview_noise.io import image
    from roadview_noise.runner import RunContext, Task, process

    recipe = load_recipe(_recipe(tmp_path, CAMERA))
    real_write = image.write_bytes_atomic

    def write(path, data):
        real_write(path, data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(image, "write_bytes_atomic", write)
    out = tmp_path / "o"
    out.mkdir()
    sample = discover(tree, recipe)[0]
    e = process(Task(sample, 0, sample.relpath), RunContext(tree.resolve(), out.resolve(), recipe))
    assert e["status"] == "failed" and "no space left on device" in e["error"] and "--resume" in e["error"]
    assert "internal error" not in e["error"] and not [p for p in out.rglob("*") if p.is_file()]


def _mount_tmpfs(path: Path, size: str) -> bool:
    path.mkdir()
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                          capture_output=True).returncode == 0


def test_disk_full_on_a_real_small_file_system(tmp_path, tree):
    mnt = tmp_path / "small"
    if os.geteuid() != 0 or not _mount_tmpfs(mnt, "2200k"):
        pytest.skip("needs permission to mount a tmpfs")
    try:
        rng = np.random.default_rng(3)
        big = tmp_path / "big"
        for i in range(8):
            write_image(big / "cam" / f"{i:06d}.png", rng.uniform(0, 1, (300, 400, 3)).astype(np.float32),
                        ImageEncoding())
        body = {"chain": [{"model": "compression.camera", "params": {"quality": 100}}], "seed": 1,
                "inputs": {"camera": "cam/*.png"}}
        out = mnt / "out"
        r = _augment(big, out, "--recipe", _recipe(tmp_path, body), "--workers", 2)
        assert r.exit_code == 1 and "Traceback" not in r.output, r.output
        record = json.loads((out / "run.json").read_text())
        assert record["counts"]["failed"] >= 1 and record["counts"]["done"] >= 1
        entries = read_manifest(out / "manifest.jsonl")
        assert len(entries) == 8
        assert any("no space left on device" in e.get("error", "") and "--resume" in e["error"] for e in entries)
        assert not list(out.rglob("*rvnoise-tmp*"))
        listed = {f["path"] for e in entries if e["status"] == "ok" for f in e["files"]}
        assert set(_files(out)) <= listed | {"manifest.jsonl"}
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


# --- 10. recipe errors that validate must catch --------------------------------------------------------------------


@pytest.mark.parametrize("body,words", [
    ({"chain": [{"model": "fog.lidar"}], "inputs": {"lidar_profile": "os1-64"}}, "os1-128"),
    ({"chain": [{"model": "rain.camera"}], "inputs": {"camera_profile": "cams/front.yaml"}}, "does not exist"),
    ({"chain": [{"model": "fog.camera", "params": {"visibility_m": {"normal": [30, 20]}}}]}, "sd ≤"),
    ({"chain": [{"model": "fog.camera"}], "sweep": {"fog.camera.airlight": [0.5, "0.5"]}}, "same file-name suffix"),
])
def test_validate_catches_what_used_to_fail_every_file(tmp_path, body, words):
    r = runner.invoke(app, ["validate", str(_recipe(tmp_path, body))])
    assert r.exit_code == 2 and words in r.output and "Traceback" not in r.output, r.output


def test_normal_draws_stay_inside_the_range():
    from roadview_noise.recipe import NORMAL_TAIL_SD, draw_value

    parse_recipe({"chain": [{"model": "fog.camera", "params": {"visibility_m": {"normal": [300, 50]}}}]})
    rng = np.random.default_rng(0)
    v = np.array([draw_value({"normal": [0.0, 1.0]}, rng) for _ in range(200_000)])
    assert v.min() >= -NORMAL_TAIL_SD and v.max() <= NORMAL_TAIL_SD and abs(v.std() - 1) < 0.01


def test_profile_file_next_to_the_recipe_is_checked(tmp_path):
    (tmp_path / "lidar.yaml").write_text("base: os1-128\nbeams: 3\n")
    r = runner.invoke(app, ["validate", str(_recipe(tmp_path, {"chain": [{"model": "fog.lidar"}],
                                                              "inputs": {"lidar_profile": "lidar.yaml"}}))])
    assert r.exit_code == 2 and "beams" in r.output
    ok = {"chain": [{"model": "fog.lidar"}], "inputs": {"lidar_profile": "{dir}/lidar.yaml"}}
    assert runner.invoke(app, ["validate", str(_recipe(tmp_path, ok))]).exit_code == 0


# --- 11. per-file messages name the file and the problem in words -------------------------------------------------------


def _process_one(tmp_path, tree_root: Path, body: dict, relpath: str) -> dict:
    from roadview_noise.dataset import discover
    from roadview_noise.runner import RunContext, Task, process

    recipe = parse_recipe(body)
    sample = next(s for s in discover(tree_root, recipe) if s.relpath == relpath)
    out = tmp_path / "single"
    out.mkdir(exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                     # nothing may escape to stderr
        return process(Task(sample, 0, relpath), RunContext(tree_root.resolve(), out.resolve(), recipe))


def test_messages_in_words(tmp_path, tree, monkeypatch):
    from roadview_noise import runner as runner_module

    def denied(path, *args, **kwargs):                            # root reads any file: fake the refusal
        if Path(path).name == "000000.png":
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return open(path, *args, **kwargs)

    monkeypatch.setattr(runner_module, "open", denied, raising=False)
    e = _process_one(tmp_path, tree, CAMERA, "cam/seqA/000000.png")
    assert e["error"].endswith("cam/seqA/000000.png: cannot read the file: permission denied"), e["error"]
    monkeypatch.undo()

    _png_header_only(tree / "cam" / "seqA" / "huge.png", 60000, 60000)
    e = _process_one(tmp_path, tree, CAMERA, "cam/seqA/huge.png")
    assert "huge.png: declares 60000×60000 = 3600.0 megapixels" in e["error"] and "traceback" not in e

    from roadview_noise.io.raw import write_dng

    raw = tree / "raw" / "a.dng"
    raw.parent.mkdir()
    write_dng(raw, np.full((48, 64), 500, np.uint16), "RGGB", 64, 4095)
    raw.write_bytes(raw.read_bytes()[: raw.stat().st_size // 2])
    e = _process_one(tmp_path, tree, {"chain": [{"model": "compression.camera"}], "inputs": {"raw": "raw/*.dng"}},
                     "raw/a.dng")
    assert "a.dng" in e["error"] and "truncated" in e["error"] and "Input/output error" not in e["error"], e


# --- 12. no silent change to the data ------------------------------------------------------------------------------------


def test_pcd_with_fewer_points_in_the_header_than_in_the_data_fails(tmp_path, tree):
    p = tree / "lidar" / "seqA" / "000000.pcd"
    text = p.read_bytes()
    head, body = text.split(b"DATA binary\n", 1)
    head = head.replace(b"WIDTH 2000", b"WIDTH 1000").replace(b"POINTS 2000", b"POINTS 1000")
    p.write_bytes(head + b"DATA binary\n" + body)
    e = _process_one(tmp_path, tree, LIDAR, "lidar/seqA/000000.pcd")
    assert e["status"] == "failed" and "declares 1000 points" in e["error"] and "does not match" in e["error"]


def _spoil_intensity(tree: Path, value: float) -> int:
    """Set the first 7 intensities of a scan to ``value``; returns the scan's point count."""
    from roadview_noise.io.pointcloud import read_pointcloud

    p = tree / "lidar" / "seqA" / "000000.pcd"
    cloud = read_pointcloud(p)
    inten = cloud.fields["intensity"].copy()
    inten[:7] = value
    write_pointcloud(p, cloud.with_fields(intensity=inten))
    return len(cloud)


def test_invalid_points_are_counted_under_their_own_name(tmp_path, tree):
    _spoil_intensity(tree, np.nan)
    e = _process_one(tmp_path, tree, LIDAR, "lidar/seqA/000000.pcd")
    assert e["status"] == "ok" and e["input_warnings"] == {"dropped_nonfinite_intensity": 7}
    radar = _radar_with_nan_velocity(tree)
    e = _process_one(tmp_path, tree, {"chain": [{"model": "rain.radar"}], "inputs": {"radar": "radar/*.pcd"}},
                     radar)
    assert e["status"] == "ok" and e["input_warnings"] == {"dropped_nonfinite_v_r_m_per_s": 5}
    assert "warnings" not in e


def test_dropped_points_reach_the_output_and_the_summary(tmp_path, tree):
    from roadview_noise.io.pointcloud import read_pointcloud

    n = _spoil_intensity(tree, np.inf)
    r = runner.invoke(app, ["augment", str(tree), str(tmp_path / "o"), "--recipe", str(_recipe(tmp_path, LIDAR)),
                            "--quiet"])
    assert r.exit_code == 0 and "1 output(s) had invalid input points removed" in r.output
    assert len(read_pointcloud(tmp_path / "o" / "lidar" / "seqA" / "000000.pcd")) == n - 7


def _radar_with_nan_velocity(tree: Path) -> str:
    from roadview_noise.io.pointcloud import read_pointcloud

    src = TESTS.parent / "sample_data" / "radar" / "seq0" / "000000.pcd"
    cloud = read_pointcloud(src, sensor="radar")
    v = cloud.fields["v_r_m_per_s"].copy()
    v[:5] = np.nan
    write_pointcloud(tree / "radar" / "a.pcd", cloud.with_fields(v_r_m_per_s=v))
    return "radar/a.pcd"


# --- 13. OUT equals the manifest -----------------------------------------------------------------------------------------


def test_overwrite_removes_what_the_previous_run_wrote_and_nothing_else(tmp_path, tree):
    out = tmp_path / "o"
    sweep = {**CAMERA, "chain": [{"model": "compression.camera"}], "sweep": {"compression.camera.quality": [5, 95]}}
    assert _augment(tree, out, "--recipe", _recipe(tmp_path, sweep)).exit_code == 0
    assert len(_files(out)) == 12
    (out / "notes.txt").write_text("mine")                      # not written by rvnoise: never deleted
    assert _augment(tree, out, "--recipe", _recipe(tmp_path, CAMERA, "r2.yaml"), "--overwrite").exit_code == 0
    files = _files(out)
    assert "notes.txt" in files and len(files) == 7 and not [f for f in files if "__quality" in f]


def test_fail_fast_leaves_no_unrecorded_output(tmp_path, tree):
    rng = np.random.default_rng(2)
    for i in range(3, 12):
        write_image(tree / "cam" / "seqA" / f"{i:06d}.png", _image(rng, 120, 160), ImageEncoding())
    (tree / "cam" / "seqA" / "000004.png").write_bytes(b"not a png")
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, CAMERA), "--workers", 2, "--fail-fast")
    assert r.exit_code == 1
    entries = read_manifest(tmp_path / "o" / "manifest.jsonl")
    assert entries[-1]["input"] == "cam/seqA/000004.png" and entries[-1]["status"] == "failed"
    assert [e["input"] for e in entries] == [f"cam/seqA/{i:06d}.png" for i in range(5)]   # plan order, then stop
    assert_out_equals_manifest(tmp_path / "o")
    assert json.loads((tmp_path / "o" / "run.json").read_text())["state"].startswith("stopped")


def test_two_inputs_never_write_one_file(tmp_path, tree):
    """``x.bin`` and ``x.pcd.bin`` in one folder: every file in OUT is listed by exactly one entry, with its
    sha256; a file name two inputs would share fails the later one with a message naming both."""
    from roadview_noise.io.pointcloud import read_pointcloud

    src = read_pointcloud(tree / "lidar" / "seqA" / "000000.pcd")
    pos = src.positions_m.astype(np.float32)
    inten = src.fields["intensity"].astype(np.float32)[:, None]
    np.hstack([pos, inten]).tofile(tree / "lidar" / "seqA" / "x.bin")
    np.hstack([pos, inten, src.fields["ring"].astype(np.float32)[:, None]]).tofile(tree / "lidar" / "seqA" /
                                                                                  "x.pcd.bin")
    body = {"chain": [{"model": "fog.lidar"}], "seed": 3,
            "inputs": {"lidar": "lidar/seqA/x*.bin", "lidar_profile": "os1-128", "intensity_unit": "uint8"}}
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, body), "--workers", 2)
    entries = assert_out_equals_manifest(tmp_path / "o")
    for e in entries:
        if e["status"] != "ok":
            assert "also written for 'lidar/seqA/x.bin'" in e["error"] and e["input"] == "lidar/seqA/x.pcd.bin"
    assert r.exit_code == (1 if any(e["status"] != "ok" for e in entries) else 0)


def test_ledger_fails_the_later_of_two_entries_claiming_one_file(tmp_path):
    import io

    from roadview_noise.outputs import Ledger

    out = tmp_path / "o"
    out.mkdir()
    for name in ("a", "b"):
        (out / f".{name}.tmp").write_text(name)
    log = io.StringIO()
    ledger = Ledger(out, log, lambda e: None)
    b = {"input": "b.pcd", "output": "b.pcd", "status": "ok", "files": [{"path": "x.label", "sha256": "2"}],
         "staged": [[".b.tmp", "x.label"]]}
    a = {"input": "a.pcd", "output": "a.pcd", "status": "ok", "files": [{"path": "x.label", "sha256": "1"}],
         "staged": [[".a.tmp", "x.label"]]}
    assert ledger.put(1, b) == []                             # waits for entry 0: release is in plan order
    first, second = ledger.put(0, a)
    assert first["status"] == "ok" and (out / "x.label").read_text() == "a"
    assert second["status"] == "failed" and "'x.label' is also written for 'a.pcd'" in second["error"]
    assert sorted(p.name for p in out.iterdir()) == ["x.label"]
    assert [json.loads(line)["status"] for line in log.getvalue().splitlines()] == ["ok", "failed"]


def test_a_file_whose_entry_failed_to_be_recorded_or_moved_is_free_for_the_next_input(tmp_path, monkeypatch):
    """Claims are taken before the line is written (one SQLite statement per file): an entry that then fails gives
    them back, as an entry that never claimed them."""
    import io

    from roadview_noise import output_folders
    from roadview_noise.outputs import Ledger

    out = tmp_path / "o"
    out.mkdir()
    for name in "abc":
        (out / f".{name}.tmp").write_text(name)
    log = io.StringIO()
    ledger = Ledger(out, log, lambda e: None)
    entry = lambda name: {"input": f"{name}.pcd", "output": f"{name}.pcd", "status": "ok",      # noqa: E731
                          "files": [{"path": "x.label", "sha256": name}], "staged": [[f".{name}.tmp", "x.label"]]}
    real_commit = output_folders.OutputFolders.commit

    def failing_commit(self, e):
        if e["input"] == "a.pcd":
            raise OSError(errno.EIO, "the rename failed")
        return real_commit(self, e)

    monkeypatch.setattr(output_folders.OutputFolders, "commit", failing_commit)
    real_write = Ledger._write
    monkeypatch.setattr(Ledger, "_write", lambda self, e: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full"))
                        if e["input"] == "b.pcd" else real_write(self, e))
    a, b, c = ledger.put(0, entry("a")) + ledger.put(1, entry("b")) + ledger.put(2, entry("c"))
    assert a["status"] == "failed" and "could not move its output" in a["error"]
    assert b["status"] == "failed" and "could not record it" in b["error"]
    assert c["status"] == "ok" and (out / "x.label").read_text() == "c"
    assert ledger.claimed.get("x.label") == "c.pcd"


def test_ctrl_c_between_a_line_and_its_renames_waits_for_the_renames(tmp_path, monkeypatch):
    """Ctrl-C right after an entry's manifest line is written: the files it names are moved into place first, then
    the run stops (KeyboardInterrupt) — the line never names a file whose temporary the run then removes."""
    import io
    import signal

    from roadview_noise import outputs

    out = tmp_path / "o"
    out.mkdir()
    (out / ".a.tmp").write_text("a")
    write = outputs.Ledger._write

    def write_then_ctrl_c(self, entry):
        write(self, entry)
        signal.raise_signal(signal.SIGINT)                  # delivered here, between the line and the renames

    monkeypatch.setattr(outputs.Ledger, "_write", write_then_ctrl_c)
    log = io.StringIO()
    ledger = outputs.Ledger(out, log, lambda e: None)
    entry = {"input": "a.pcd", "output": "a.pcd", "status": "ok", "files": [{"path": "a.pcd", "sha256": "1"}],
             "staged": [[".a.tmp", "a.pcd"]]}
    with pytest.raises(KeyboardInterrupt):
        ledger.put(0, entry)
    assert sorted(p.name for p in out.iterdir()) == ["a.pcd"] and (out / "a.pcd").read_text() == "a"
    assert json.loads(log.getvalue())["files"][0]["path"] == "a.pcd"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler      # the handler is back


# --- 14. workers die with their parent; large plans are streamed and refused without --yes -------------------------


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def _running(pid: int) -> bool:
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_exit_when_the_main_process_is_killed(tmp_path, tree):
    pid_dir = tmp_path / "pids"
    pid_dir.mkdir()
    body = {"chain": [{"model": "test_sleep.camera", "params": {"sleep_s": 30, "pid_dir": str(pid_dir)}}],
            "seed": 1, "inputs": {"camera": "cam/**/*.png"}}
    recipe = _recipe(tmp_path, body)
    code = (f"import sys; sys.path.insert(0, {str(TESTS)!r}); import injected_models; from roadview_noise.registry import register; "
            "[register(c) for c in injected_models.INJECTED]; "
            "from roadview_noise.recipe import load_recipe; from roadview_noise.runner import run; "
            f"run(load_recipe({str(recipe)!r}), {str(tree)!r}, {str(tmp_path / 'o')!r}, workers=2, progress=False)")
    main = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        while time.time() < deadline and len(list(pid_dir.iterdir())) < 2:
            time.sleep(0.05)
        workers = {int(p.name) for p in pid_dir.iterdir()}
        assert len(workers) == 2 and workers <= _descendants(main.pid)
        helpers = _descendants(main.pid)
    finally:
        main.send_signal(signal.SIGKILL)
        main.wait()
    deadline = time.time() + 60
    while time.time() < deadline and any(_running(p) for p in helpers):
        time.sleep(0.05)
    assert not [p for p in helpers if _running(p)]


def test_interrupted_run_is_recorded(tmp_path, tree):
    trace = tmp_path / "calls"
    body = {"chain": [{"model": "test_sleep.camera", "params": {"sleep_s": 1.0, "trace_path": str(trace)}}],
            "seed": 1, "inputs": {"camera": "cam/**/*.png"}}
    code = (f"import sys; sys.path.insert(0, {str(TESTS)!r}); import injected_models; from roadview_noise.registry import register; "
            "[register(c) for c in injected_models.INJECTED]; "
            "from roadview_noise.recipe import load_recipe; from roadview_noise.runner import run; "
            f"run(load_recipe({str(_recipe(tmp_path, body))!r}), {str(tree)!r}, {str(tmp_path / 'o')!r}, "
            "workers=1, progress=False)")
    main = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    # interrupted once the first file is recorded (its manifest line) and the second one started; 1 s tasks leave
    # ≥ 3 s of the run after that (a loaded machine may be slow to see it: with 0.5 s tasks the run once ended first)
    manifest = tmp_path / "o" / "manifest.jsonl"
    deadline = time.time() + 60
    while time.time() < deadline and not (manifest.is_file() and manifest.read_text().endswith("\n")
                                          and trace.is_file() and len(trace.read_text().splitlines()) >= 2):
        time.sleep(0.05)
    main.send_signal(signal.SIGINT)
    _, err = main.communicate(timeout=60)
    assert b"KeyboardInterrupt" in err
    record = json.loads((tmp_path / "o" / "run.json").read_text())
    assert record["state"] == "interrupted" and 0 < record["counts"]["done"] < 6
    assert_out_equals_manifest(tmp_path / "o")
    assert not (tmp_path / "o" / ".rvnoise.lock").exists()


def test_an_interrupt_between_an_entrys_line_and_its_count_is_counted(tmp_path, tree, monkeypatch):
    # Ctrl-C lands after the ledger wrote the second file's manifest line, before the run counted it: run.json
    # still counts what the manifest holds
    from roadview_noise import runner

    add, calls = runner._Tally.add, []

    def interrupted_add(self, e, *, released=True):
        calls.append(e)
        if len(calls) == 2:
            raise KeyboardInterrupt
        add(self, e, released=released)

    monkeypatch.setattr(runner._Tally, "add", interrupted_add)
    body = {"chain": [{"model": "compression.camera"}], "seed": 1, "inputs": {"camera": "cam/**/*.png"}}
    with pytest.raises(KeyboardInterrupt):
        runner.run(load_recipe(_recipe(tmp_path, body)), tree, tmp_path / "o", workers=1, progress=False)
    record = json.loads((tmp_path / "o" / "run.json").read_text())
    entries = read_manifest(tmp_path / "o" / "manifest.jsonl")
    assert record["state"] == "interrupted" and len(entries) >= 2
    assert record["counts"]["done"] == sum(e["status"] == "ok" for e in entries) >= 2
    assert_out_equals_manifest(tmp_path / "o")


def test_huge_sweep_is_planned_lazily_and_refused_without_yes(tmp_path, tree):
    from roadview_noise.runner import iter_tasks

    hundred = list(range(100))
    body = {"chain": [{"model": "wind.camera"}, {"model": "rain.camera"}, {"model": "compression.camera"}],
            "seed": 1, "inputs": {"camera": "cam/**/*.png"},
            "sweep": {"wind.camera.wind_speed_m_per_s": [v / 2 for v in hundred],
                      "wind.camera.wind_direction_deg": [v * 3 for v in hundred],
                      "compression.camera.quality": [v + 1 for v in hundred]}}
    tracemalloc.start()
    recipe = parse_recipe(body)
    first = next(iter_tasks(tree, recipe))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(recipe.variants) == 10**6 and peak < 5e6
    assert first.out_relpath == "cam/seqA/000000__wind_speed_m_per_s-0.0__wind_direction_deg-0__quality-1.png"
    assert recipe.variants[-1].suffix == "__wind_speed_m_per_s-49.5__wind_direction_deg-297__quality-100"
    t0 = time.perf_counter()
    r = _augment(tree, tmp_path / "o", "--recipe", _recipe(tmp_path, body), "--dry-run")
    assert r.exit_code == 2 and "more than 100,000 outputs" in r.output and "--yes" in r.output
    assert time.perf_counter() - t0 < 20 and not (tmp_path / "o").exists()
