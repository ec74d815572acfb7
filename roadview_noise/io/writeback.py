"""Early writeback of a file being written: the kernel starts writing its dirty pages to storage every
``every_bytes`` (Linux ``sync_file_range(SYNC_FILE_RANGE_WRITE)``, which does not wait), so the fsync before the
atomic rename (``io/rosbag.bag_output``) finds little left to write and the end of a run does not wait for the whole
bag. A no-op where the call does not exist."""

from __future__ import annotations

import ctypes
import os
from functools import lru_cache
from pathlib import Path

SYNC_FILE_RANGE_WRITE = 2
EVERY_BYTES = 32 << 20


@lru_cache(maxsize=1)
def _sync_file_range():
    try:
        fn = ctypes.CDLL(None, use_errno=True).sync_file_range
    except (OSError, AttributeError):
        return None
    fn.argtypes = (ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint)
    return fn


def start_writeback(path: Path) -> None:
    """Have the kernel start writing ``path``'s dirty pages to storage now, without waiting (nothing where the call
    does not exist; an error only loses the head start: the fsync that follows reports it)."""
    call = _sync_file_range()
    if call is None:
        return
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        call(fd, 0, 0, SYNC_FILE_RANGE_WRITE)
    finally:
        os.close(fd)


class Writeback:
    """Count the bytes written to ``path`` (:meth:`wrote`) and start their writeback every ``every_bytes``."""

    def __init__(self, path: Path | None, every_bytes: int = EVERY_BYTES):
        self.every, self.pending, self.fd = every_bytes, 0, None
        self.call = _sync_file_range() if path is not None else None
        if self.call is not None:
            try:
                self.fd = os.open(path, os.O_RDONLY)
            except OSError:
                self.call = None

    def wrote(self, n: int) -> None:
        self.pending += n
        if self.pending >= self.every and self.fd is not None:
            self.pending = 0
            self.call(self.fd, 0, 0, SYNC_FILE_RANGE_WRITE)         # an error only loses the head start

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
