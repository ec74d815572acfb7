"""Atomic file writes: a temporary file in the destination directory, fsync, then rename.

No half-written output can exist: a killed process leaves at most a ``*.rvnoise-tmp*`` file, which the runner removes
(under its lock on the output folder). Every writer in ``roadview_noise.io`` writes through :func:`atomic_path`, so
two process-wide settings the batch runner makes here apply to all of them:

- :func:`confined_to` (the output root): every write's real parent folder must lie inside it; folders are created one
  by one and a symlink that leads out of the root is refused, never followed (:func:`ensure_dir_inside`).
- :func:`recorded_writes`: the list of files a block wrote (``dataset.save`` returns it).
- :func:`staged_writes`: writes stop at the temporary and are listed (``(temporary, final)`` pairs); the caller
  renames them with :meth:`Staged.commit` after recording them, or removes them with :meth:`Staged.discard`.
  So a run records every file before it appears under its final name. Each temporary's writeback starts when it is
  written and the block's end waits for all of them (fsync): what the block does after writing (hashing the
  outputs) overlaps the disk's work, and a temporary is on storage before the block returns.
  (A local run's workers leave that fsync to the main process, which does it in threads before it records them:
  ``roadview_noise.output_sync``.)
"""

from __future__ import annotations

import hashlib
import itertools
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Iterator

from ..profiling import span
from ..real_folders import real_folder
from .writeback import start_writeback

TMP_SUFFIX = ".rvnoise-tmp"
_TEMPORARIES = itertools.count()     # a temporary's name is its process's own: two outputs staged by one worker
#                                      that both hold the same file (a sequence's calib copied per frame) do not share it
WRITE_PIECE_BYTES = 1 << 20         # write() size of write_bytes_atomic (see there)
WRITEBACK_MIN_BYTES = 64 * 1024      # a staged file this large starts its writeback at once (below: the fsync's I/O
                                     # is a few pages, not worth a system call more per file)

_root: Path | None = None            # real path every write must stay inside (None: unconfined)
_stage: "Staged | None" = None       # collects writes instead of renaming them
_records: list[list[Path]] = []       # open recorded_writes() blocks


class OutsideRootError(OSError):
    """A write would land outside the confined root (through ``..``, an absolute path or a symlink)."""


@dataclass
class Staged:
    """Files written (temporaries, on storage after :meth:`sync`) but not yet renamed to their final names."""

    files: list[tuple[Path, Path]] = field(default_factory=list)     # (temporary, final)
    unsynced: list[Path] = field(default_factory=list)                # temporaries not fsynced yet
    written: dict[Path, memoryview] = field(default_factory=dict)     # temporary → its bytes, when written whole

    def sync(self) -> None:
        """Wait until every temporary is on storage (fsync; their writeback started when they were written)."""
        for tmp in self.unsynced:
            _fsync(tmp, "sync")
        self.unsynced = []

    def sha256_of(self, tmp: Path) -> str | None:
        """The sha256 of a temporary written from bytes at hand (:func:`write_bytes_atomic`: no second read), once;
        None for the others."""
        data = self.written.pop(tmp, None)
        return None if data is None else hashlib.sha256(data).hexdigest()

    def finals(self) -> list[Path]:
        return [final for _, final in self.files]

    def commit(self) -> None:
        """Rename every temporary onto its final name (checking the final folder again), once on storage."""
        self.sync()
        for tmp, final in self.files:
            if _root is not None:
                _check_inside(final.parent, _root)
            os.replace(tmp, final)
        self.files = []

    def discard(self) -> None:
        for tmp, _ in self.files:
            _unlink_quietly(tmp)
        self.files, self.unsynced, self.written = [], [], {}


@contextmanager
def confined_to(root: str | os.PathLike) -> Iterator[Path]:
    """Refuse (``OutsideRootError``) every write whose real folder is not inside ``root`` while the block runs."""
    global _root
    try:
        real = real_folder(os.fspath(root))
    except OSError:
        real = os.path.realpath(root)
    previous, _root = _root, _path_of(real)
    try:
        yield _root
    finally:
        _root = previous


@contextmanager
def staged_writes(sync: bool = True) -> Iterator[Staged]:
    """Collect the writes of the block as temporaries, on storage when the block ends (see the module docstring); on
    an error, the fsync's included, they are removed. ``sync=False``: the block ends without the fsync, which the
    caller then owes before it records them (a run's main process, ``output_sync``)."""
    global _stage
    previous, _stage = _stage, Staged()
    stage = _stage
    try:
        yield stage
        if sync:
            stage.sync()
    except BaseException:
        stage.discard()
        raise
    finally:
        _stage = previous


@contextmanager
def recorded_writes() -> Iterator[list[Path]]:
    """The final paths of every file written in the block (staged or not), in write order."""
    written: list[Path] = []
    _records.append(written)
    try:
        yield written
    finally:
        _records.pop()                   # blocks nest, so the last one is ours


def ensure_dir_inside(folder: Path, root: Path) -> Path:
    """Create ``folder`` (and missing parents) below the real ``root`` one component at a time; refuse any existing
    component that is not a folder or whose real path leaves ``root``. Returns the folder's real path. A folder that
    is there and resolves inside ``root`` costs one ``stat`` after the first time (:mod:`roadview_noise.real_folders`;
    every output of a run lands in a few folders)."""
    folder = Path(os.path.abspath(folder))
    try:
        real = real_folder(str(folder))
    except OSError:                 # missing, or not a folder: created or refused below
        real = None
    if real is not None and (real == str(root) or real.startswith(str(root).rstrip(os.sep) + os.sep)):
        return _path_of(real)
    try:
        rel = folder.relative_to(root)
    except ValueError:
        rel = None
    if rel is None:
        real = Path(os.path.realpath(folder))
        _check_inside(real, root)
        folder, rel = real, real.relative_to(root)
    current = root
    for part in rel.parts:
        current = current / part
        if not os.path.lexists(current):
            try:
                os.mkdir(current)
            except FileExistsError:
                pass
        real = Path(os.path.realpath(current))
        _check_inside(real, root)
        if not real.is_dir():
            raise NotADirectoryError(f"{current} exists and is not a folder")
        current = real
    return current


@lru_cache(maxsize=64)
def _path_of(real: str) -> Path:
    """``Path(real)`` of a real folder path, made once (a run writes into a few folders; pathlib parses the text
    each time, ≈ 2 µs, twice per file)."""
    return Path(real)


def _check_inside(folder: Path, root: Path) -> None:
    real = Path(os.path.realpath(folder))
    if real != root and root not in real.parents:
        raise OutsideRootError(f"refusing to write into {folder}: it resolves to {real}, outside the output "
                               f"folder {root} (a symlink or '..' leads out of it)")


def _unlink_quietly(p: Path) -> None:
    try:
        p.unlink()
    except FileNotFoundError:
        pass


@contextmanager
def atomic_path(path: str | os.PathLike, size: int | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same suffix, so format-sniffing libraries work); on success it is
    fsynced and renamed onto ``path`` (or listed, under :func:`staged_writes`); on error it is removed. ``size``:
    the bytes the caller writes, when it knows them (no ``stat`` of the staged file to decide its writeback)."""
    path = Path(path)
    if _root is not None:
        path = ensure_dir_inside(path.parent, _root) / path.name
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
    if _stage is not None and path in _stage.finals():
        raise ValueError(f"{path.name} is written twice for one output (a sidecar name collides)")
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{next(_TEMPORARIES)}{TMP_SUFFIX}{path.suffix}")
    done = False
    try:
        yield tmp
        if _stage is not None:
            with span("write"):
                if (os.stat(tmp).st_size if size is None else size) >= WRITEBACK_MIN_BYTES:
                    start_writeback(tmp)
            _stage.files.append((tmp, path))
            _stage.unsynced.append(tmp)
        else:
            _fsync(tmp, "write")
            os.replace(tmp, path)
        done = True
        for written in _records:
            written.append(path)
    finally:
        if not done:
            _unlink_quietly(tmp)


def _fsync(path: Path, span_name: str) -> None:
    with span(span_name), open(path, "rb+") as fh:
        os.fsync(fh.fileno())


def write_bytes_atomic(path: str | os.PathLike, data: bytes | memoryview) -> None:
    """Write ``data`` atomically, in pieces of ``WRITE_PIECE_BYTES``; staged ``bytes`` (or a read-only byte view whose
    owner no longer changes it) are kept for their sha256 (:meth:`Staged.sha256_of`: no second read for the
    manifest). One large write() lets the page cache take 2 MB
    folios: on the 2-core VM (Linux 6.18, virtio-balloon) a 4.5 MB PNG written so took 8–25 ms in half or more of
    the writes, 1.1–1.8 ms in the others — the time spent copying into the new folios, presumably free blocks the
    host had taken back. Alternating in one worker: whole 20 of 24 slow (median 11.3 ms), 1 MB pieces 1 of 30
    (median 1.8 ms; issue 19 round 10). The file is opened unbuffered (a buffered one costs an ``ioctl`` and an
    ``fstat`` more: ≈ 5 µs of a small radar file's write), each piece written until its end."""
    view = memoryview(data)
    with atomic_path(path, view.nbytes) as tmp, span("write"), open(tmp, "wb", buffering=0) as fh:
        for k in range(0, len(view), WRITE_PIECE_BYTES):
            piece = view[k:k + WRITE_PIECE_BYTES]
            while piece:
                piece = piece[fh.write(piece):]
    if _stage is not None and (isinstance(data, bytes) or view.readonly):   # (immutable: the hash is the file's)
        _stage.written[tmp] = view


def is_temporary(name: str) -> bool:
    return TMP_SUFFIX in name


def remove_stale_temporaries(root: str | os.PathLike) -> int:
    """Delete temporary files left by a killed run or worker under ``root``; returns how many. Call it only while
    holding the lock on ``root`` (another run's temporaries are in flight otherwise)."""
    n = 0
    for dirpath, dirnames, filenames in os.walk(root):          # does not follow symlinked folders
        for name in filenames:
            if is_temporary(name):
                _unlink_quietly(Path(dirpath) / name)
                n += 1
    return n
