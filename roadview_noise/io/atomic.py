"""Atomic file writes: a temporary file in the destination directory, fsync, then rename.

No half-written output can exist: a killed process leaves at most a ``*.rvnoise-tmp`` file, which the runner removes
at start. Every writer in ``roadview_noise.io`` writes through :func:`atomic_path`."""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

TMP_SUFFIX = ".rvnoise-tmp"


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same suffix, so format-sniffing libraries work); on success it is
    fsynced and renamed onto ``path``; on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}{TMP_SUFFIX}{path.suffix}")
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def remove_stale_temporaries(root: str | os.PathLike) -> int:
    """Delete temporary files left by a killed run under ``root``; returns how many."""
    n = 0
    for p in Path(root).rglob(f"*{TMP_SUFFIX}*"):
        if p.is_file():
            p.unlink()
            n += 1
    return n
