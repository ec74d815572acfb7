"""A local run's outputs are synced by its main process (``output_sync``, issue 19), never after their manifest line:
when a line is written every file it lists is on storage as a temporary and none is under its final name yet, so a
crash at any moment leaves no line whose file could be partial and no file without its line; a sync that fails
fails its entry and leaves nothing of it. Both ways are checked: a ``syncfs`` per batch (group commit, Linux) and an
fsync per file (elsewhere, and for the batches ``syncfs`` may not cover)."""

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


needs_syncfs = pytest.mark.skipif(output_sync.SYNCFS is None, reason="syncfs with error reports: Linux ≥ 5.8")


def _temporaries(root: Path) -> set[str]:
    return {p.name for p in root.rglob("*") if is_temporary(p.name)}


@pytest.fixture(params=["syncfs", "fsync"])
def fsynced(request, monkeypatch, tmp_path):
    """The files this process has made durable (by name), each sync delayed so that lines would overtake it if they
    could: each file fsynced (``os.fsync`` of every module here), and with ``syncfs`` (param "syncfs"; "fsync":
    ``syncfs`` absent) every temporary of the output tree there when a ``syncfs`` began, counted once it returned."""
    names: set[str] = set()
    lock = threading.Lock()
    real = os.fsync

    def slow_fsync(fd):
        time.sleep(0.002)
        real(fd)
        with lock:
            names.add(os.path.basename(os.readlink(f"/proc/self/fd/{fd}")))

    monkeypatch.setattr(output_sync.os, "fsync", slow_fsync)
    if request.param == "syncfs":
        if output_sync.SYNCFS is None:
            pytest.skip("syncfs with error reports: Linux ≥ 5.8")
        real_syncfs = output_sync.syncfs

        def slow_syncfs(fd):
            there = _temporaries(tmp_path / "out")
            time.sleep(0.002)
            real_syncfs(fd)
            with lock:
                names.update(there)

        monkeypatch.setattr(output_sync, "syncfs", slow_syncfs)
        monkeypatch.setattr(output_sync, "dirty_bytes", lambda: 0)      # the machine's other writers aside
    else:
        monkeypatch.setattr(output_sync, "SYNCFS", None)
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


@pytest.mark.parametrize("syncfs", ["absent", "failing"])
def test_a_failed_fsync_fails_its_entry_and_leaves_nothing_of_it(tmp_path, monkeypatch, syncfs):
    # without syncfs, or when a syncfs reports a writeback error (whose? the batch is then fsynced file by file)
    if syncfs == "absent":
        monkeypatch.setattr(output_sync, "SYNCFS", None)
    elif output_sync.SYNCFS is None:
        pytest.skip("syncfs with error reports: Linux ≥ 5.8")
    else:
        monkeypatch.setattr(output_sync, "dirty_bytes", lambda: 0)

        def eio(fd):
            raise OSError(errno.EIO, "Input/output error")

        monkeypatch.setattr(output_sync, "syncfs", eio)
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
    monkeypatch.setattr(output_sync, "SYNCFS", None)                   # a file by file pool: fsyncs end in any order
    log = io.StringIO()
    sync = output_sync.SyncPool(out)
    ledger = Ledger(out, log, lambda e: None, sync=sync)
    released = []
    for i, name in enumerate("abc"):
        (out / f".{name}.tmp").write_text(name)
        released += ledger.put(i, {"output": f"{name}.pcd", "input": f"{name}.pcd", "status": "ok",
                                   "files": [{"path": f"{name}.pcd", "sha256": "-"}],
                                   "staged": [[f".{name}.tmp", f"{name}.pcd"]]})
    sync.kick()                               # as the run's main loop does before it waits for results
    sync.wait(1)
    sync.wait(2)                              # b's and c's fsyncs end first
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


def _job(out: Path, name: str) -> list[list[str]]:
    (out / f".{name}.tmp").write_text(name)
    return [[f".{name}.tmp", f"{name}.pcd"]]


@needs_syncfs
def test_what_the_main_loop_hands_over_while_a_syncfs_runs_joins_the_next_one(tmp_path, monkeypatch):
    calls, gate = [], threading.Event()
    real = output_sync.syncfs

    def held(fd):                             # the first syncfs waits until the test lets it go
        calls.append(fd)
        if len(calls) == 1:
            gate.wait(5)
        real(fd)

    monkeypatch.setattr(output_sync, "syncfs", held)
    monkeypatch.setattr(output_sync, "dirty_bytes", lambda: 0)
    monkeypatch.setattr(output_sync, "SYNCFS_SLOW_S", 60.0)            # the held one is not "slow"
    fsynced = []
    monkeypatch.setattr(output_sync.os, "fsync", fsynced.append)
    sync = output_sync.SyncPool(tmp_path)
    sync.submit(0, _job(tmp_path, "a"))
    sync.kick()
    while not calls:
        time.sleep(0.001)
    for i, name in enumerate("bcdef", start=1):
        sync.submit(i, _job(tmp_path, name))
        if i % 2:
            sync.kick()                       # three hand-overs: b, c + d, e + f
    assert not any(sync.done(i)[0] for i in range(6))
    gate.set()
    sync.wait(5)
    assert [sync.done(i) for i in range(6)] == [(True, None)] * 6 and len(calls) == 2 and not fsynced
    sync.close()


@needs_syncfs
@pytest.mark.parametrize("why", ["another file system", "much unwritten data", "a slow syncfs just before"])
def test_a_batch_goes_file_by_file_where_syncfs_may_not_cover_it_or_may_wait_long(tmp_path, monkeypatch, why):
    fsynced, syncfs_calls, real = [], [], os.fsync

    def slow_syncfs(fd):                      # slow (only one is expected: syncfs_calls is checked)
        syncfs_calls.append(fd)
        time.sleep(output_sync.SYNCFS_SLOW_S * 1.5)

    monkeypatch.setattr(output_sync, "syncfs", slow_syncfs)
    monkeypatch.setattr(output_sync.os, "fsync", lambda fd: (fsynced.append(fd), real(fd)))
    dirty = output_sync.SYNCFS_MAX_DIRTY_BYTES + (1 if why == "much unwritten data" else -1)
    monkeypatch.setattr(output_sync, "dirty_bytes", lambda: dirty)
    sync = output_sync.SyncPool(tmp_path)
    if why == "another file system":
        sync._root_dev = -1                   # as if every folder were a mount point inside OUT
    if why == "a slow syncfs just before":
        sync.submit(9, _job(tmp_path, "z"))
        sync.wait(9)
        assert sync.done(9) == (True, None) and len(syncfs_calls) == 1 and not fsynced
    for i, name in enumerate("abc"):
        sync.submit(i, _job(tmp_path, name))
    for i in range(3):
        sync.wait(i)
    assert [sync.done(i) for i in range(3)] == [(True, None)] * 3 and len(fsynced) == 3
    assert len(syncfs_calls) == (1 if why == "a slow syncfs just before" else 0)
    sync.close()


def test_a_dask_or_replay_context_still_fsyncs_in_the_worker():
    from roadview_noise.runner import RunContext

    assert RunContext(Path("."), Path("."), None).fsync_outputs       # the default: the worker's own fsync
    assert outputs.Ledger(Path("."), io.StringIO(), lambda e: None).sync is None
