"""Staged writes (io/atomic.staged_writes): each temporary's writeback starts when it is written, and every one is
fsynced before the block returns, so hashing overlaps the disk and a recorded output is always on storage."""

from __future__ import annotations

import errno
import os

import pytest
from test_cli import CAMERA, _recipe, tree  # noqa: F401

from roadview_noise.io import atomic
from roadview_noise.io.atomic import is_temporary, staged_writes, write_bytes_atomic
from roadview_noise.manifest import sha256_file
from roadview_noise.recipe import load_recipe


@pytest.fixture
def synced(monkeypatch):
    """The paths fsynced (by the file each descriptor opens) and the writebacks started, in order."""
    events: list[tuple[str, str]] = []
    real_fsync = os.fsync

    def fsync(fd):
        events.append(("fsync", os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))))
        real_fsync(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    monkeypatch.setattr(atomic, "start_writeback", lambda p: events.append(("writeback", p.name)))
    return events


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name a descriptor's file")
def test_a_staged_file_is_fsynced_when_the_block_ends_not_when_written(tmp_path, synced):
    big = b"a" * atomic.WRITEBACK_MIN_BYTES
    with staged_writes() as stage:
        write_bytes_atomic(tmp_path / "a.bin", big)
        write_bytes_atomic(tmp_path / "b.bin", b"b" * 100)                   # small: no early writeback
        tmps = [t.name for t, _ in stage.files]
        assert synced == [("writeback", tmps[0])]                            # nothing waited for yet
        assert all((tmp_path / t).read_bytes() for t in tmps)                 # readable (hashing) meanwhile
    assert synced[1:] == [("fsync", tmps[0]), ("fsync", tmps[1])]
    assert not (tmp_path / "a.bin").exists() and not stage.unsynced
    stage.commit()
    assert (tmp_path / "a.bin").read_bytes() == big and len(synced) == 3


def test_a_staged_write_in_pieces_is_whole_and_its_sha256_is_its_bytes(tmp_path):
    """Bytes longer than several write() pieces land intact; the sha256 the stage keeps (for the manifest, instead
    of reading the file again) is the file's."""
    data = os.urandom(2 * atomic.WRITE_PIECE_BYTES + 12345)
    with staged_writes() as stage:
        write_bytes_atomic(tmp_path / "a.png", data)
        write_bytes_atomic(tmp_path / "b.json", b"{}")
        for tmp, _ in stage.files:
            assert stage.sha256_of(tmp) == sha256_file(tmp)
    stage.commit()
    assert (tmp_path / "a.png").read_bytes() == data


def test_a_plain_write_is_fsynced_before_its_rename(tmp_path, synced):
    write_bytes_atomic(tmp_path / "a.bin", b"a")
    assert [kind for kind, _ in synced] == ["fsync"] and (tmp_path / "a.bin").read_bytes() == b"a"


def test_a_failed_fsync_at_the_end_of_the_block_removes_every_temporary(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    with pytest.raises(OSError, match="No space"), staged_writes():
        write_bytes_atomic(tmp_path / "a.bin", b"a" * 100)
        write_bytes_atomic(tmp_path / "b.bin", b"b" * 100)
    assert list(tmp_path.iterdir()) == []


def test_a_file_whose_fsync_fails_is_recorded_as_failed_and_leaves_nothing(tmp_path, tree, monkeypatch):  # noqa: F811
    from roadview_noise.dataset import discover
    from roadview_noise.runner import RunContext, Task, process

    recipe = load_recipe(_recipe(tmp_path, CAMERA))
    out = tmp_path / "o"
    out.mkdir()
    real_fsync = os.fsync

    def fsync(fd):
        if is_temporary(os.readlink(f"/proc/self/fd/{fd}")):
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    sample = discover(tree, recipe)[0]
    e = process(Task(sample, 0, sample.relpath), RunContext(tree.resolve(), out.resolve(), recipe))
    assert e["status"] == "failed" and "no space left on device" in e["error"] and "--resume" in e["error"]
    assert "staged" not in e and "output_sha256" not in e
    assert not [p for p in out.rglob("*") if p.is_file()]
