"""What native libraries print: libpng, LibRaw and OpenEXR write their complaints about a damaged file straight to
file descriptors 1 and 2, around Python. In a batch worker that lands on the user's terminal, interleaved with the
progress bar and without the file's name; :func:`captured_output` collects it for the file's manifest entry
(``library_messages``) instead."""

from __future__ import annotations

import os
import sys
import tempfile
from contextlib import contextmanager
from typing import Iterator

MAX_LINES = 20
_buffer = None          # one temporary file per process, empty and at offset 0 between uses


def _forget_buffer() -> None:
    global _buffer
    _buffer = None      # a forked child makes its own (a shared one would share the parent's offset)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_buffer)


@contextmanager
def captured_output(enabled: bool = True) -> Iterator[list[str]]:
    """Redirect file descriptors 1 and 2 into a temporary file for the block; the yielded list then holds its
    distinct lines (at most ``MAX_LINES``). A no-op yielding an empty list when not ``enabled``. The file is made
    once per process and read (then emptied) only when the block wrote to it: per block 8 system calls and one
    ``lseek``, most blocks print nothing."""
    global _buffer
    lines: list[str] = []
    if not enabled:
        yield lines
        return
    if _buffer is None:
        _buffer = tempfile.TemporaryFile()
    fileno = _buffer.fileno()
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    os.dup2(fileno, 1)
    os.dup2(fileno, 2)
    try:
        yield lines
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        for fd, copy in zip((1, 2), saved):
            os.dup2(copy, fd)
            os.close(copy)
        if os.lseek(fileno, 0, os.SEEK_CUR):           # something was written
            _read_lines(lines)


def _read_lines(lines: list[str]) -> None:
    """Append the buffer's distinct lines to ``lines`` and empty it."""
    fileno = _buffer.fileno()
    os.lseek(fileno, 0, os.SEEK_SET)
    text = os.read(fileno, 1 << 16).decode("utf-8", errors="replace")
    os.ftruncate(fileno, 0)
    os.lseek(fileno, 0, os.SEEK_SET)
    for line in dict.fromkeys(x.strip() for x in text.splitlines()):
        if line and len(lines) < MAX_LINES:
            lines.append(line)
