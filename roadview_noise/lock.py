"""One run per output folder: an exclusive lock on ``OUT/.rvnoise.lock`` for the whole run.

The lock file holds the owner's pid, host and start time (JSON) and is locked with ``flock``, which the kernel
releases when the owner dies, however it dies. A second run finds the lock taken and is refused (exit 2) with the
holder named. A lock file whose ``flock`` is free was left by a dead run: on this host it is taken over with a
message; a lock left by another host is refused (its run may be alive there, on a file system whose locks this host
cannot see) and the message says how to remove it.

The lock file also reserves ``RESERVE_BYTES`` of disk (``posix_fallocate``): :meth:`OutputLock.release_reserve`
frees them so the run record can still be written when the disk fills up during the run.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from pathlib import Path
from typing import Callable

from .errors import OutputError

LOCK_NAME = ".rvnoise.lock"
RESERVE_BYTES = 1 << 20


class OutputLock:
    """``with OutputLock(out_root, echo=...) as lock:`` — raises :class:`OutputError` when another run holds it."""

    def __init__(self, out_root: Path, *, echo: Callable[[str], None] = print):
        self.path = Path(out_root) / LOCK_NAME
        self.echo = echo
        self.fd: int | None = None
        self.taken_over: dict | None = None

    def __enter__(self) -> "OutputLock":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> None:
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
            except OSError as exc:
                raise OutputError(f"cannot create the lock file {str(self.path)!r}: {exc.strerror or exc}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read(fd)
                os.close(fd)
                raise OutputError(f"{str(self.path.parent)!r} is in use by another rvnoise run "
                                  f"({_describe(holder)}); wait for it to finish or use another output folder")
            try:                                # the file may have been removed by its owner in between
                same = os.fstat(fd).st_ino == os.stat(self.path, follow_symlinks=False).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        previous = _read(fd)
        if previous:
            if previous.get("host") != socket.gethostname():
                os.close(fd)
                raise OutputError(f"{str(self.path.parent)!r} has the lock of a run on another host "
                                  f"({_describe(previous)}); if that run is over, delete {str(self.path)!r}")
            self.taken_over = previous
            self.echo(f"rvnoise: taking over the stale lock of a run that is no longer running "
                      f"({_describe(previous)})")
        record = {"pid": os.getpid(), "host": socket.gethostname(), "started_unix": round(time.time(), 3)}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
        try:
            os.posix_fallocate(fd, 0, RESERVE_BYTES)
        except (OSError, AttributeError):     # a full disk or a file system without fallocate: no reserve
            pass
        os.fsync(fd)
        self.fd = fd

    def release_reserve(self) -> None:
        """Give the reserved disk space back (before writing the run record on a full disk)."""
        if self.fd is not None:
            content = _read(self.fd)
            os.ftruncate(self.fd, len(json.dumps(content)) + 1 if content else 0)

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        os.close(self.fd)            # closing drops the flock
        self.fd = None


def _read(fd: int) -> dict:
    try:
        text = os.pread(fd, 4096, 0).split(b"\n", 1)[0]
        return json.loads(text) if text.strip(b"\0 ") else {}
    except (OSError, ValueError):
        return {}


def _describe(holder: dict) -> str:
    if not holder:
        return "owner unknown"
    started = holder.get("started_unix")
    when = time.strftime(" since %Y-%m-%d %H:%M:%S", time.localtime(started)) if started else ""
    return f"pid {holder.get('pid')} on host {holder.get('host')}{when}"
