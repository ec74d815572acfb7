"""A local run's outputs are fsynced by its main process (``output_sync``, issue 19), never after their manifest line:
when a line is written every file it lists is on storage as a temporary and none is under its final name yet, so a
crash at any moment leaves no line whose file could be partial and no file without its line; an fsync that fails
fails its entry and leaves nothing of it."""

from __future__ import annotations

import errno
import io
import os
import select
import shutil
import threading
import time
from pathlib import Path

import pytest

from roadview_noise import output_sync, outputs
from roadview_noise.io.atomic import is_temporary
from roadview_noise.manifest import read_manifest, sha256_file
from roadview_noise.outputs import Ledger
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import run

ROOT = Path(__file__).resolve().parents[1]


def _radar_tree(tmp_path: Path, files: int) -> Path:
    """The sample radar sequence with copies of its frames up to ``files`` frames (at least its own 3)."""
    dst = tmp_path / "in" / "radar" / "seq0"
    shutil.copytree(ROOT / "sample_data" / "radar" / "seq0", dst)
    frames = sorted(dst.glob("*.pcd"))
    for k in range(len(frames), files):
        shutil.copy(frames[k % len(frames)], dst / f"{k:06d}.pcd")
    return tmp_path / "in"


@pytest.fixture
def fsynced(monkeypatch):
    """The files this process fsyncs (by name; ``os.fsync`` of every module here), each fsync delayed so that lines
    would overtake it if they could."""
    names: set[str] = set()
    lock = threading.Lock()
    real = os.fsync

    def slow_fsync(fd):
        time.sleep(0.002)
        real(fd)
        with lock:
            names.add(os.path.basename(os.readlink(f"/proc/self/fd/{fd}")))

    monkeypatch.setattr(output_sync.os, "fsync", slow_fsync)
    return names


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name a descriptor's file")
@pytest.mark.parametrize("workers", [1, 2])
def test_a_line_is_written_only_once_its_files_are_on_storage(tmp_path, fsynced, monkeypatch, workers):
    out = tmp_path / "out"
    checked = []
    real_write = Ledger._write

    def write(self, entry):                   # the moment a line is written: what a crash would leave
        for tmp, final in entry.get("staged", ()):
            assert Path(tmp).name in fsynced, f"{final}: its line was written before its fsync"
            assert not (out / final).exists(), f"{final}: under its final name before its line"
        checked.append(entry["output"])
        real_write(self, entry)

    monkeypatch.setattr(Ledger, "_write", write)
    recipe = load_recipe(ROOT / "recipes" / "weather-fog-radar.yaml")
    s = run(recipe, _radar_tree(tmp_path, 24), out, workers=workers, progress=False, echo=lambda m: None)
    entries = read_manifest(out / "manifest.jsonl")
    outputs_synced = {n for n in fsynced if n.endswith(".pcd")}      # (run.json's own fsyncs aside)
    assert s.done == 24 and len(checked) == 24 and len(outputs_synced) == 24
    for e in entries:
        assert e["status"] == "ok" and sha256_file(out / e["output"]) == e["output_sha256"]
    assert not [p for p in out.rglob("*") if is_temporary(p.name)]


@pytest.mark.parametrize("in_worker", [True, False])
def test_a_worker_fsyncs_its_files_only_when_the_main_process_will_not(tmp_path, monkeypatch, in_worker):
    from roadview_noise.dataset import discover
    from roadview_noise.io import atomic
    from roadview_noise.runner import RunContext, Task, process

    calls = []
    real = os.fsync
    monkeypatch.setattr(atomic.os, "fsync", lambda fd: (calls.append(fd), real(fd)))
    tree = _radar_tree(tmp_path, 1)
    recipe = load_recipe(ROOT / "recipes" / "weather-fog-radar.yaml")
    out = (tmp_path / "out").resolve()
    out.mkdir()
    sample = discover(tree, recipe)[0]
    e = process(Task(sample, 0, sample.relpath), RunContext(tree.resolve(), out, recipe, fsync_outputs=in_worker))
    assert e["status"] == "ok" and len(e["staged"]) == 1 and len(calls) == (1 if in_worker else 0)


def test_a_failed_fsync_fails_its_entry_and_leaves_nothing_of_it(tmp_path, monkeypatch):
    real = os.fsync

    def full_on_the_third(fd):
        if os.path.basename(os.readlink(f"/proc/self/fd/{fd}")).startswith(".000002."):
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fd)

    monkeypatch.setattr(output_sync.os, "fsync", full_on_the_third)
    out = tmp_path / "out"
    recipe = load_recipe(ROOT / "recipes" / "weather-fog-radar.yaml")
    s = run(recipe, _radar_tree(tmp_path, 5), out, workers=2, progress=False, echo=lambda m: None)
    entries = {e["input"]: e for e in read_manifest(out / "manifest.jsonl")}
    bad = entries["radar/seq0/000002.pcd"]
    assert s.failed == 1 and s.done == 4 and bad["status"] == "failed" and "files" not in bad
    assert "no space left on device" in bad["error"] and "--resume" in bad["error"]
    assert not (out / "radar/seq0/000002.pcd").exists()
    assert not [p for p in out.rglob("*") if is_temporary(p.name)]
    assert all(e["status"] == "ok" for k, e in entries.items() if k != "radar/seq0/000002.pcd")


def test_the_ledger_keeps_plan_order_while_fsyncs_finish_out_of_order(tmp_path, monkeypatch):
    out = tmp_path / "o"
    out.mkdir()
    gate = threading.Event()
    real = output_sync.fsync_files

    def held(paths):                          # the first file's fsync waits until the test lets it go
        if Path(paths[0]).name == ".a.tmp":
            gate.wait(5)
        real(paths)

    monkeypatch.setattr(output_sync, "fsync_files", held)
    log = io.StringIO()
    sync = output_sync.SyncPool(out)
    ledger = Ledger(out, log, lambda e: None, sync=sync)
    released = []
    for i, name in enumerate("abc"):
        (out / f".{name}.tmp").write_text(name)
        released += ledger.put(i, {"output": f"{name}.pcd", "input": f"{name}.pcd", "status": "ok",
                                   "files": [{"path": f"{name}.pcd", "sha256": "-"}],
                                   "staged": [[f".{name}.tmp", f"{name}.pcd"]]})
    sync.wait(1)
    sync.wait(2)                              # b's and c's fsyncs end first (a sleep was too short at load 12)
    assert released == [] and log.getvalue() == "" and not list(out.glob("*.pcd"))   # a is still on its way
    gate.set()
    assert select.select([sync.wake], [], [], 5)[0]        # the fsync's end wakes the run's main loop (executor.wake)
    sync.wait(0)
    released += ledger.synced()
    assert ledger.drain() == [] and not ledger.pending
    sync.close()
    assert [e["output"] for e in released] == ["a.pcd", "b.pcd", "c.pcd"]
    assert [line.split('"output": "')[1][0] for line in log.getvalue().splitlines()] == ["a", "b", "c"]
    assert {p.name for p in out.iterdir()} == {"a.pcd", "b.pcd", "c.pcd"}


def test_a_dask_or_replay_context_still_fsyncs_in_the_worker():
    from roadview_noise.runner import RunContext

    assert RunContext(Path("."), Path("."), None).fsync_outputs       # the default: the worker's own fsync
    assert outputs.Ledger(Path("."), io.StringIO(), lambda e: None).sync is None


def test_finished_fsyncs_wake_the_main_loop_once_until_it_collects(tmp_path, monkeypatch):
    written = []
    real_write = os.write

    def counted(fd, data):
        written.append(fd)
        return real_write(fd, data)

    monkeypatch.setattr(output_sync.os, "write", counted)
    sync = output_sync.SyncPool(tmp_path)
    wake = lambda wait=0.0: bool(select.select([sync.wake], [], [], wait)[0])          # noqa: E731
    assert not wake()
    for round_ in range(3):
        for i in range(5):
            (tmp_path / f"f{round_}{i}").write_text("x")
            sync.submit(10 * round_ + i, [[f"f{round_}{i}", f"f{round_}{i}"]])
        for i in range(5):
            sync.wait(10 * round_ + i)
        assert wake(5.0)                            # what finished since the last collection wakes the loop …
        assert len(written) == round_ + 1           # … with one byte, however many finished
        sync.woken()
        assert not wake()                           # collected: quiet until the next fsync ends
        assert all(sync.done(10 * round_ + i) == (True, None) for i in range(5))
    sync.close()
