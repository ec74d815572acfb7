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
_buffer = None          # one temporary file per process, truncated before each use


@contextmanager
def captured_output(enabled: bool = True) -> Iterator[list[str]]:
    """Redirect file descriptors 1 and 2 into a temporary file for the block; the yielded list then holds its
    distinct lines (at most ``MAX_LINES``). A no-op yielding an empty list when not ``enabled``."""
    global _buffer
    lines: list[str] = []
    if not enabled:
        yield lines
        return
    if _buffer is None:
        _buffer = tempfile.TemporaryFile()
    _buffer.seek(0)
    _buffer.truncate()
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    os.dup2(_buffer.fileno(), 1)
    os.dup2(_buffer.fileno(), 2)
    try:
        yield lines
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        for fd, copy in zip((1, 2), saved):
            os.dup2(copy, fd)
            os.close(copy)
        _buffer.seek(0)
        text = _buffer.read(1 << 16).decode("utf-8", errors="replace")
        for line in dict.fromkeys(x.strip() for x in text.splitlines()):
            if line and len(lines) < MAX_LINES:
                lines.append(line)
