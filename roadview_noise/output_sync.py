"""The outputs' fsync in the run's main process (issue 19): a local run's workers write their staged temporaries
(``io/atomic.staged_writes(sync=False)``) and answer at once; a few threads here wait for the storage while the
worker runs its next file, and :class:`outputs.Ledger` writes an entry's manifest line only once every temporary it
lists is on storage, then renames them. So, as when a worker fsyncs: a manifest line never names a file whose bytes
could be lost, and a file never appears under its final name before its line.

The workers of a local run share this machine's page cache, so an fsync by the main process makes their bytes
durable; a Dask worker's files may be on another machine's cache (NFS), which is why that backend's workers still
fsync their own files. Concurrent fsyncs of one file system share its journal commits (ext4, XFS), so the threads
also cost the disk fewer flushes than one fsync per file in turn.
"""

from __future__ import annotations

import errno
import os
import queue
import re
import threading
from pathlib import Path

from .walk import os_error_text

SYNC_THREADS = 8            # fsyncs in flight at once (each thread waits on the storage, not on a core)
MAX_WAITING = 64            # entries whose fsync is pending before the ledger waits for the oldest one (8 threads: a
                            # deeper queue would not fsync faster, only hold more entries in memory)


def fsync_files(paths: list[str | Path]) -> None:
    """fsync each file (opened read-only: fsync needs no write access on Linux)."""
    for p in paths:
        fd = os.open(p, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class SyncPool:
    """fsync of entries' staged temporaries (``entry["staged"]``: temporary → final, relative to ``out_root``) in
    :data:`SYNC_THREADS` daemon threads, keyed by the entry's plan index: :meth:`submit`, then :meth:`done` (no
    wait) after :meth:`wait` or on its own. Per file the main thread pays a queue put and a set look-up."""

    def __init__(self, out_root: Path, threads: int = SYNC_THREADS):
        self.out_root = out_root
        self._root = os.fspath(out_root)
        self.pending = 0                                   # submitted, not yet collected by :meth:`done`
        self._todo: queue.SimpleQueue = queue.SimpleQueue()
        self._finished = threading.Condition()
        self._done: set[int] = set()
        self._errors: dict[int, Exception] = {}
        self.wake, self._wake_w = os.pipe()                # readable: an fsync finished (ProcessExecutor.wake)
        self._signalled = False                            # a byte is in the pipe since the last :meth:`woken`
        os.set_blocking(self.wake, False)
        os.set_blocking(self._wake_w, False)
        self._threads = [threading.Thread(target=self._work, name="rvnoise-fsync", daemon=True)
                         for _ in range(threads)]
        for t in self._threads:
            t.start()

    def _work(self) -> None:
        while True:
            job = self._todo.get()
            if job is None:
                return
            index, paths = job
            error = None
            try:
                fsync_files(paths)
            except Exception as exc:                       # noqa: BLE001 - failed here, reported by its entry
                error = exc
            with self._finished:
                if error is not None:
                    self._errors[index] = error
                self._done.add(index)
                self._finished.notify_all()
                wake, self._signalled = not self._signalled, True
            if wake:
                try:
                    os.write(self._wake_w, b"s")
                except BlockingIOError:                     # full: the reader is woken already
                    pass

    def submit(self, index: int, staged: list[list[str]]) -> None:
        self.pending += 1
        root = self._root
        self._todo.put((index, [f"{root}/{tmp}" for tmp, _ in staged]))   # no pathlib per file (issue 19)

    def woken(self) -> None:
        """Empty the :attr:`wake` pipe (the caller is about to collect what finished). A finished fsync writes its
        byte only when none is pending since the caller's last call (one system call per wake-up, not per file:
        behind short tasks the executor does not watch the pipe and the caller collects after each result); the mark
        is cleared after the pipe is emptied, so an fsync that finishes meanwhile wakes it again."""
        try:
            while os.read(self.wake, 4096):
                pass
        except BlockingIOError:
            pass
        with self._finished:
            self._signalled = False

    def done(self, index: int) -> tuple[bool, Exception | None]:
        """Whether entry ``index``'s fsync finished, and its error (collected: ask once after it is done)."""
        if index not in self._done:
            return False, None
        with self._finished:
            self._done.discard(index)
            self.pending -= 1
            return True, self._errors.pop(index, None)

    def wait(self, index: int) -> None:
        """Until entry ``index``'s fsync (submitted) has finished."""
        with self._finished:
            self._finished.wait_for(lambda: index in self._done)

    def close(self) -> None:
        """Stop the threads after the fsyncs queued (a stopped run's temporaries may be gone: their errors are not
        collected) and wait for them."""
        for _ in self._threads:
            self._todo.put(None)
        for t in self._threads:
            t.join()
        os.close(self.wake)
        os.close(self._wake_w)


# numpy's ``tofile`` (tifffile writes DNG/TIFF pixel data with it) reports a short write without an errno: on a
# regular file only a full disk or quota cuts a write short
SHORT_WRITE = re.compile(r"(\d+) requested and (\d+) written")


def write_error(relpath: str, out_relpath: str, exc: BaseException) -> str:
    """A manifest entry's error for an output that could not be written (disk full: how to go on)."""
    what = os_error_text(exc) if getattr(exc, "strerror", None) else str(exc)
    short = SHORT_WRITE.search(str(exc)) if getattr(exc, "errno", None) is None else None
    if short:
        what = f"no space left on device or quota (short write: {short[2]} of {short[1]} bytes)"
    full = short or getattr(exc, "errno", None) == errno.ENOSPC
    return f"{relpath}: cannot write {out_relpath}: {what}{'; free space and run again with --resume' if full else ''}"
