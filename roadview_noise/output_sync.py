"""The outputs' fsync in the run's main process (issue 19): a local run's workers write their staged temporaries
(``io/atomic.staged_writes(sync=False)``) and answer at once; a thread here waits for the storage while the workers
run their next files, and :class:`outputs.Ledger` writes an entry's manifest line only once every temporary it lists
is on storage, then renames them. So, as when a worker fsyncs: a manifest line never names a file whose bytes could
be lost, and a file never appears under its final name before its line.

**Group commit** (issue 19 round 15). The run's main loop gathers the entries it handles between two waits for
results (:meth:`SyncPool.kick`, called by ``ProcessExecutor`` before it waits: a worker's batch of answers) and the
pool's committer thread makes all it was handed since its last commit durable together, with one ``syncfs(2)`` of the
output root's file system: the kernel writes back its dirty files and commits its journal once for all of them
(≈ 100 µs of the main process's CPU per small file went into one ``open``/``fsync``/``close`` each, its threads and
their wake-ups). The batch grows with the rate of results and needs no timer (a pause of 10 ms between commits to
gather more made the workers' files slower on the loaded VM, round 15). ``syncfs`` is used only where it is as safe as an
fsync per file and bounded in cost:

- Linux ≥ 5.8, where ``syncfs`` reports writeback errors (through a descriptor opened before the run's files are
  written, so an error another process saw first is still reported); an error fails no entry by itself: that batch
  is fsynced file by file, which names the files it hit;
- files whose folder is on the output root's file system (a mount point inside OUT: file by file);
- while the file system is quiet: ``syncfs`` writes back everything of its file system, other programs' data too,
  and queues behind the kernel's flusher, so on a busy shared disk it could wait for far more than this run's
  files. Batches are fsynced file by file while the machine's page cache holds more than
  :data:`SYNCFS_MAX_DIRTY_BYTES` waiting for writeback (``/proc/meminfo`` Dirty + Writeback, read at most every
  :data:`DIRTY_CHECK_S`), and for :data:`SYNCFS_PAUSE_S` after a ``syncfs`` that took longer than
  :data:`SYNCFS_SLOW_S`.

Elsewhere (and for those batches) :data:`SYNC_THREADS` threads fsync each file: concurrent fsyncs of one file system
share its journal commits (ext4, XFS). The workers of a local run share this machine's page cache, so a sync by the
main process makes their bytes durable; a Dask worker's files may be on another machine's cache (NFS), which is why
that backend's workers still fsync their own files.
"""

from __future__ import annotations

import ctypes
import os
import queue
import re
import sys
import threading
import time
from pathlib import Path
from typing import Callable

from .walk import os_error_text

SYNC_THREADS = 8            # per-file fsyncs in flight at once (each thread waits on the storage, not on a core)
MAX_WAITING = 64            # entries whose sync is pending before the ledger waits for the oldest one (a deeper
                            # queue would not sync faster, only hold more entries in memory)
SYNCFS_MAX_DIRTY_BYTES = 64 << 20   # page cache awaiting writeback above which a batch is fsynced file by file
DIRTY_CHECK_S = 0.1         # how often the committer reads that amount (≈ 0.1 ms of CPU a read)
SYNCFS_SLOW_S = 0.02        # a syncfs slower than this (idle: a few ms) means others keep the disk busy: ...
SYNCFS_PAUSE_S = 1.0        # ... the batches of the next second are fsynced file by file
SYNCFS_KERNEL = (5, 8)      # the first Linux whose syncfs reports writeback errors


def _libc_syncfs() -> Callable[[int], int] | None:
    """libc's ``syncfs`` where it reports writeback errors (Linux ≥ :data:`SYNCFS_KERNEL`), else None."""
    release = re.match(r"(\d+)\.(\d+)", os.uname().release) if hasattr(os, "uname") else None
    if not sys.platform.startswith("linux") or release is None or \
            tuple(map(int, release.groups())) < SYNCFS_KERNEL:
        return None
    try:
        fn = ctypes.CDLL(None, use_errno=True).syncfs
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_int], ctypes.c_int
    return fn


SYNCFS = _libc_syncfs()     # None: every file is fsynced on its own


def syncfs(fd: int) -> None:
    """``syncfs(2)`` of the file system holding ``fd`` (OSError on a writeback error since ``fd`` was opened)."""
    if SYNCFS(fd) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


def dirty_bytes() -> int:
    """The machine's page cache waiting for or under writeback (``/proc/meminfo`` Dirty + Writeback, bytes)."""
    with open("/proc/meminfo", "rb") as fh:
        text = fh.read()
    return 1024 * sum(int(kb) for kb in re.findall(rb"^(?:Dirty|Writeback):\s+(\d+)", text, re.M))


def fsync_files(paths: list[str | Path]) -> None:
    """fsync each file (opened read-only: fsync needs no write access on Linux)."""
    for p in paths:
        fd = os.open(p, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class SyncPool:
    """Sync of entries' staged temporaries (``entry["staged"]``: temporary → final, relative to ``out_root``), keyed
    by the entry's plan index: :meth:`submit` (gathered until :meth:`kick`), then :meth:`done` (no wait) after
    :meth:`wait` or on its own. Per file the main thread pays a list append and a set look-up; the committer thread
    syncs what it was handed in batches (module docstring)."""

    def __init__(self, out_root: Path, threads: int = SYNC_THREADS):
        self.out_root = out_root
        self._root = os.fspath(out_root)
        self.pending = 0                                   # submitted, not yet collected by :meth:`done`
        self._gathered: list = []                          # submitted, not handed to the committer yet
        self._todo: queue.SimpleQueue = queue.SimpleQueue()          # lists of jobs for the committer
        self._by_file: queue.SimpleQueue = queue.SimpleQueue()       # jobs for the fsync threads
        self._finished = threading.Condition()
        self._done: set[int] = set()
        self._errors: dict[int, Exception] = {}
        self.wake, self._wake_w = os.pipe()                # a byte per finished batch (ProcessExecutor.wake)
        os.set_blocking(self.wake, False)
        os.set_blocking(self._wake_w, False)
        self._root_fd = None                               # opened before any of the run's files is written
        if SYNCFS is not None:
            self._root_fd = os.open(self._root, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
            self._root_dev = os.fstat(self._root_fd).st_dev
        self._checked, self._below = -DIRTY_CHECK_S, False  # when dirty_bytes() was read, and whether it was low
        self._pause_until = 0.0                            # no syncfs before then (a slow one was seen)
        self._threads = threads
        self._fsyncers: list[threading.Thread] = []        # started on the first file synced on its own
        self._committer = threading.Thread(target=self._commit, name="rvnoise-sync", daemon=True)
        self._committer.start()

    def submit(self, index: int, staged: list[list[str]]) -> None:
        self.pending += 1
        root = self._root
        self._gathered.append((index, [f"{root}/{tmp}" for tmp, _ in staged]))   # no pathlib per file (issue 19)

    def kick(self) -> None:
        """Hand the entries submitted since to the committer (the main loop, before it waits for results)."""
        if self._gathered:
            self._todo.put(self._gathered)
            self._gathered = []

    def _commit(self) -> None:
        while True:
            handed = [self._todo.get()]
            while True:                                    # what came meanwhile joins this commit
                try:
                    handed.append(self._todo.get_nowait())
                except queue.Empty:
                    break
            stop = handed[-1] is None                      # close() puts it last
            jobs = [job for jobs in handed if jobs is not None for job in jobs]
            together, alone = self._split(jobs)
            if together:
                try:
                    start = time.monotonic()
                    syncfs(self._root_fd)
                    if time.monotonic() - start > SYNCFS_SLOW_S:
                        self._pause_until = time.monotonic() + SYNCFS_PAUSE_S
                    self._finish([(index, None) for index, _ in together])
                except OSError:                            # someone's writeback failed: find whose, file by file
                    alone += together
            for job in alone:
                self._fsync_alone(job)
            if stop:
                return

    def _split(self, jobs: list) -> tuple[list, list]:
        """The jobs one ``syncfs`` may cover, and those to fsync file by file (module docstring)."""
        if not jobs or self._root_fd is None or time.monotonic() < self._pause_until or not self._calm():
            return [], jobs
        devices: dict[str, int | None] = {}
        together, alone = [], []
        for job in jobs:
            same = True
            for p in job[1]:
                folder = p.rpartition("/")[0]
                if folder not in devices:
                    try:
                        devices[folder] = os.stat(folder).st_dev
                    except OSError:                        # its fsync will say what is wrong
                        devices[folder] = None
                same = same and devices[folder] == self._root_dev
            (together if same else alone).append(job)
        return together, alone

    def _calm(self) -> bool:
        """Whether the page cache's writeback backlog is below :data:`SYNCFS_MAX_DIRTY_BYTES` (read at most every
        :data:`DIRTY_CHECK_S`)."""
        now = time.monotonic()
        if now - self._checked >= DIRTY_CHECK_S:
            self._checked, self._below = now, dirty_bytes() <= SYNCFS_MAX_DIRTY_BYTES
        return self._below

    def _fsync_alone(self, job: tuple[int, list[str]]) -> None:
        while len(self._fsyncers) < self._threads:
            t = threading.Thread(target=self._fsync_work, name="rvnoise-fsync", daemon=True)
            t.start()
            self._fsyncers.append(t)
        self._by_file.put(job)

    def _fsync_work(self) -> None:
        while True:
            job = self._by_file.get()
            if job is None:
                return
            index, paths = job
            try:
                fsync_files(paths)
                self._finish([(index, None)])
            except Exception as exc:                       # noqa: BLE001 - failed here, reported by its entry
                self._finish([(index, exc)])

    def _finish(self, results: list[tuple[int, Exception | None]]) -> None:
        with self._finished:
            for index, error in results:
                if error is not None:
                    self._errors[index] = error
                self._done.add(index)
            self._finished.notify_all()
        try:
            os.write(self._wake_w, b"s")
        except BlockingIOError:                            # full: the reader is woken already
            pass

    def woken(self) -> None:
        """Empty the :attr:`wake` pipe (the caller is about to collect what finished)."""
        try:
            while os.read(self.wake, 4096):
                pass
        except BlockingIOError:
            pass

    def done(self, index: int) -> tuple[bool, Exception | None]:
        """Whether entry ``index``'s sync finished, and its error (collected: ask once after it is done)."""
        if index not in self._done:
            return False, None
        with self._finished:
            self._done.discard(index)
            self.pending -= 1
            return True, self._errors.pop(index, None)

    def wait(self, index: int) -> None:
        """Until entry ``index``'s sync (submitted) has finished."""
        self.kick()
        with self._finished:
            self._finished.wait_for(lambda: index in self._done)

    def close(self) -> None:
        """Stop the threads after the syncs queued (a stopped run's temporaries may be gone: their errors are not
        collected) and wait for them."""
        self.kick()
        self._todo.put(None)
        self._committer.join()
        for _ in self._fsyncers:
            self._by_file.put(None)
        for t in self._fsyncers:
            t.join()
        if self._root_fd is not None:
            os.close(self._root_fd)
        os.close(self.wake)
        os.close(self._wake_w)


def write_error(relpath: str, out_relpath: str, exc: BaseException) -> str:
    """A manifest entry's error for an output that could not be written (disk full: how to go on)."""
    what = os_error_text(exc) if getattr(exc, "strerror", None) else str(exc)
    hint = "; free space and run again with --resume" if getattr(exc, "errno", None) == 28 else ""
    return f"{relpath}: cannot write {out_relpath}: {what}{hint}"
