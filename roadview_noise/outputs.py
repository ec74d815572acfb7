"""OUT equals the manifest: every file in the output tree is listed, with its sha256, by exactly one manifest entry.

Workers stage their files (fsynced temporaries, ``io/atomic.staged_writes``); :class:`Ledger` releases their results
in plan order, so what happens is the same for any number of workers. Releasing an entry

1. claims its files: a file another input already wrote in this run fails the later entry (two inputs must never
   write one path, e.g. colliding sidecar names), and its temporaries are removed;
2. appends its manifest line (flushed), and only then
3. renames its temporaries onto their final names.

A run killed between 2 and 3 leaves a listed file missing (``--resume`` redoes it) and temporaries (removed by the
next run), never an unlisted file. Files a previous manifest of this folder lists are the only files a run deletes
(:func:`remove_listed`): on ``--overwrite`` all of them, on a completed ``--resume`` those its plan no longer has.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath
from typing import Callable, Iterable, TextIO

from .input_checks import escapes
from .io.atomic import ensure_dir_inside
from .manifest import dumps, sha256_file


def listed_files(entry: dict) -> list[str]:
    """Relative paths of the files an entry says it wrote (manifests before ``files`` list only ``output``)."""
    if entry.get("files"):
        return [f["path"] for f in entry["files"]]
    return [entry["output"]] if entry.get("status") == "ok" and entry.get("output") else []


def _inside(out_root: Path, rel: str) -> Path | None:
    """``out_root / rel`` if ``rel`` stays inside ``out_root`` (no ``..``, not absolute, no symlinked folder
    leading out), else None."""
    if not rel or escapes(rel) or PurePosixPath(rel).is_absolute():
        return None
    path = out_root / rel
    real_parent = os.path.realpath(path.parent)
    root = os.path.realpath(out_root)
    return path if real_parent == root or real_parent.startswith(root + os.sep) else None


def remove_listed(out_root: Path, entries: Iterable[dict], keep: set[str] = frozenset()) -> int:
    """Delete the files the entries list (never anything else, never outside ``out_root``, never a path in
    ``keep``); returns how many."""
    n = 0
    for entry in entries:
        for rel in listed_files(entry):
            path = _inside(out_root, rel)
            if rel in keep or path is None:
                continue
            try:
                if path.is_symlink() or path.is_file():
                    path.unlink()
                    n += 1
            except FileNotFoundError:
                pass
    return n


def files_intact(out_root: Path, entry: dict) -> bool:
    """Every file the entry lists exists with its recorded sha256."""
    files = entry.get("files") or [{"path": entry.get("output"), "sha256": entry.get("output_sha256")}]
    for f in files:
        path = _inside(out_root, f.get("path") or "")
        if path is None or not path.is_file() or sha256_file(path) != f.get("sha256"):
            return False
    return True


class Ledger:
    """Releases results in plan order (see module docstring). ``put(index, entry)`` returns the entries released by
    it. With ``fail_fast`` the first failed entry is the last one released (``stopped`` is then set)."""

    def __init__(self, out_root: Path, log: TextIO, on_log_error: Callable[[OSError], None], *,
                 fail_fast: bool = False):
        self.out_root = out_root
        self.log = log
        self.on_log_error = on_log_error
        self.fail_fast = fail_fast
        self.stopped = False
        self.claimed: dict[str, str] = {}             # file relpath → the input that wrote it
        self.pending: dict[int, dict] = {}
        self.next = 0

    def put(self, index: int, entry: dict) -> list[dict]:
        self.pending[index] = entry
        released = []
        while not self.stopped and self.next in self.pending:
            entry = self._release(self.pending.pop(self.next))
            released.append(entry)
            self.next += 1
            self.stopped = self.fail_fast and entry["status"] != "ok"
        return released

    def discard_pending(self) -> None:
        """Remove the temporaries of results that will not be released (the run stopped)."""
        for entry in self.pending.values():
            discard(self.out_root, entry)
        self.pending.clear()

    def _release(self, entry: dict) -> dict:
        files = listed_files(entry) if entry.get("status") == "ok" else []
        clash = next((f for f in files if f in self.claimed and self.claimed[f] != entry["input"]), None)
        if clash is not None:
            discard(self.out_root, entry)
            entry = _failed(entry, f"{entry['input']}: its output file {clash!r} is also written for "
                                   f"{self.claimed[clash]!r}; two inputs must not write one file (rename one of "
                                   "them)")
            files = []
        try:
            self._write(entry)
        except OSError as exc:
            self.on_log_error(exc)
            discard(self.out_root, entry)
            entry = _failed(entry, f"{entry['input']}: could not record it in the manifest "
                                   f"({exc.strerror or exc}); its output was not kept")
            return entry
        try:
            commit(self.out_root, entry)
        except OSError as exc:
            discard(self.out_root, entry)
            entry = _failed(entry, f"{entry['input']}: could not move its output into place: {exc}")
            try:
                self._write(entry)                      # supersedes the line above (the last line wins)
            except OSError as log_exc:
                self.on_log_error(log_exc)
            return entry
        for f in files:
            self.claimed[f] = entry["input"]
        return entry

    def _write(self, entry: dict) -> None:
        self.log.write(dumps({k: v for k, v in entry.items() if k != "staged"}) + "\n")
        self.log.flush()

    def claim(self, entry: dict) -> None:
        """Files of an entry kept from a previous run (``--resume``)."""
        for f in listed_files(entry):
            self.claimed[f] = entry["input"]


def _failed(entry: dict, error: str) -> dict:
    entry = {k: v for k, v in entry.items() if k not in ("files", "output_sha256", "staged")}
    entry.update(status="failed", error=error)
    return entry


def commit(out_root: Path, entry: dict) -> None:
    """Rename an entry's staged temporaries onto their final names (their folders checked again)."""
    for tmp, final in entry.pop("staged", []):
        target = out_root / final
        ensure_dir_inside(target.parent, Path(os.path.realpath(out_root)))
        os.replace(out_root / tmp, target)


def discard(out_root: Path, entry: dict) -> None:
    for tmp, _ in entry.pop("staged", []):
        try:
            (out_root / tmp).unlink()
        except FileNotFoundError:
            pass

