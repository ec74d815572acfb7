"""OUT equals the manifest: every file in the output tree is listed, with its sha256, by exactly one manifest entry.

Workers stage their files (temporaries, ``io/atomic.staged_writes``); :class:`Ledger` releases their results in plan
order, so what happens is the same for any number of workers. An entry waits until its temporaries are on storage
(fsynced by its worker, or by the ledger's ``output_sync.SyncPool``: a local run); releasing it then

1. claims its files: a file another input already wrote in this run fails the later entry (two inputs must never
   write one path, e.g. colliding sidecar names), and its temporaries are removed;
2. appends its manifest line (flushed), and only then
3. renames its temporaries onto their final names.

A run killed between 2 and 3 leaves a listed file missing (``--resume`` redoes it) and temporaries (removed by the
next run), never an unlisted file. Files a previous manifest of this folder lists are the only files a run deletes
(:func:`remove_listed`): on ``--overwrite`` all of them, on a completed ``--resume`` those its plan no longer has.

Memory stays flat however many outputs a run has: the claimed files and the previous manifest ``--resume`` consults
live in a private temporary SQLite database (:class:`DiskIndex`), and released entries are written, not kept.
"""

from __future__ import annotations

import _signal
import json
import os
import signal
import sqlite3
import threading
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import Callable, Container, Iterable, Iterator, TextIO

from .input_checks import escapes
from .manifest import entry_line, full_entry, iter_manifest, sha256_file
from .output_folders import OutputFolders
from .output_sync import MAX_WAITING, SyncPool, write_error


def listed_files(entry: dict) -> list[str]:
    """Relative paths of the files an entry says it wrote (manifests before ``files`` list only ``output``)."""
    if entry.get("files"):
        return [f["path"] for f in entry["files"]]
    return [entry["output"]] if entry.get("status") == "ok" and entry.get("output") else []


def owner(entry: dict, rel: str) -> str:
    """Who claims the output file ``rel`` of an entry: its input, or — for an annotation file copied unchanged to
    the same path (a sequence's calib or label file that each of its frames reads, KITTI tracking's
    ``calib/0000.txt``) — that copy, which every input reading the same file writes byte for byte."""
    read = entry.get("annotations_read")
    if not read:
        return entry["input"]
    sha = next((f["sha256"] for f in entry.get("files") or () if f["path"] == rel), None)
    copied = sha is not None and any(a.get("path") == rel and a.get("sha256") == sha
                                     for a in read)
    return f"unchanged copy of {rel} ({sha})" if copied else entry["input"]


def _inside(out_root: Path, rel: str) -> Path | None:
    """``out_root / rel`` if ``rel`` stays inside ``out_root`` (no ``..``, not absolute, no symlinked folder
    leading out), else None."""
    if not rel or escapes(rel) or PurePosixPath(rel).is_absolute():
        return None
    path = out_root / rel
    real_parent = os.path.realpath(path.parent)
    root = os.path.realpath(out_root)
    return path if real_parent == root or real_parent.startswith(root + os.sep) else None


def remove_listed(out_root: Path, entries: Iterable[dict], keep: Container[str] = frozenset()) -> int:
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
    it. With ``fail_fast`` the first failed entry is the last one released (``stopped`` is then set). With ``sync``,
    an entry's staged temporaries are fsynced there and the entry waits for it (:meth:`drain`: the last ones); an
    fsync that fails fails its entry, as a failed write in the worker would."""

    def __init__(self, out_root: Path, log: TextIO, on_log_error: Callable[[OSError], None], *,
                 fail_fast: bool = False, sync: SyncPool | None = None):
        self.out_root = out_root
        self.real_root = Path(os.path.realpath(out_root))
        self.folders = OutputFolders(out_root, self.real_root)     # closed by the run (runner._execute)
        self.log = log
        self.on_log_error = on_log_error
        self.fail_fast = fail_fast
        self.stopped = False
        self.claimed = DiskIndex()                    # file relpath → the input that wrote it
        self.superseded = False                       # a line was followed by one that replaces it
        self.pending: dict[int, dict] = {}
        self.next = 0
        self.sync = sync
        self.syncing: set[int] = set()                # plan indices whose fsync is pending (with ``sync``)

    def put(self, index: int, entry: dict) -> list[dict]:
        if self.sync is not None and entry.get("staged"):
            self.sync.submit(index, entry["staged"])
            self.syncing.add(index)
        self.pending[index] = entry
        if self.sync is not None and self.sync.pending > MAX_WAITING and self.next in self.syncing:
            self.sync.wait(self.next)                  # the storage lags: wait for the oldest one
        return self._release_ready(wait=False)

    def synced(self) -> list[dict]:
        """Release the entries whose fsync has finished since (the executor woke the caller for it)."""
        self.sync.woken()
        return self._release_ready(wait=False)

    def drain(self) -> list[dict]:
        """Release the entries that wait only for their fsync (after the last result)."""
        return self._release_ready(wait=True)

    def _release_ready(self, wait: bool) -> list[dict]:
        released = []
        while not self.stopped and self.next in self.pending:
            if self.next in self.syncing:
                done, error = self.sync.done(self.next)
                if not done:
                    if not wait:
                        break
                    self.sync.wait(self.next)
                    done, error = self.sync.done(self.next)
                self.syncing.discard(self.next)
            else:
                error = None
            entry = self.pending.pop(self.next)
            if error is not None:
                discard(self.out_root, entry)
                entry = _failed(entry, write_error(entry["input"], entry["output"], error))
            entry = self._release(entry)
            released.append(entry)
            self.next += 1
            self.stopped = self.fail_fast and entry["status"] != "ok"
        return released

    def discard_pending(self) -> None:
        """Remove the temporaries of results that will not be released (the run stopped)."""
        for entry in self.pending.values():
            discard(self.out_root, entry)
        self.pending.clear()
        self.syncing.clear()

    def _release(self, entry: dict) -> dict:
        files = listed_files(entry) if entry.get("status") == "ok" else []
        claimed, clash = self._claim(files, entry)
        if clash is not None:
            self._unclaim(claimed)
            discard(self.out_root, entry)
            entry = _failed(entry, f"{entry['input']}: its output file {clash[0]!r} is also written for "
                                   f"{clash[1]!r}; two inputs must not write one file (rename one of them)")
            claimed = []
        with ctrl_c_held():                             # a line and its files' renames: both or neither
            return self._record(entry, claimed)

    def _claim(self, files: list[str], entry: dict) -> tuple[list[str], tuple[str, str] | None]:
        """Claim ``files`` for their :func:`owner`, one SQLite statement per file unless another owner has it:
        (the files claimed here, the first file another owner claimed before and that owner, or None)."""
        claimed = []
        for f in files:
            who = owner(entry, f)
            before = self.claimed.put_new(f, who)
            if before is None:
                claimed.append(f)
            elif before != who:
                return claimed, (f, before)
        return claimed, None

    def _unclaim(self, files: list[str]) -> None:
        for f in files:
            self.claimed.pop(f)

    def _record(self, entry: dict, claimed: list[str]) -> dict:
        """Write the entry's line, then rename its files; on a failure the files it ``claimed`` are released."""
        try:
            self._write(entry)
        except OSError as exc:
            self.on_log_error(exc)
            discard(self.out_root, entry)
            self._unclaim(claimed)
            entry = _failed(entry, f"{entry['input']}: could not record it in the manifest "
                                   f"({exc.strerror or exc}); its output was not kept")
            return entry
        try:
            self.folders.commit(entry)
        except OSError as exc:
            discard(self.out_root, entry)
            self._unclaim(claimed)
            entry = _failed(entry, f"{entry['input']}: could not move its output into place: {exc}")
            try:
                self._write(entry)                      # supersedes the line above (the last line wins)
                self.superseded = True
            except OSError as log_exc:
                self.on_log_error(log_exc)
            return entry
        return entry

    def _write(self, entry: dict) -> None:
        self.log.write(entry_line(entry) + "\n")
        self.log.flush()

    def claim(self, entry: dict) -> None:
        """Files of an entry kept from a previous run (``--resume``)."""
        for f in listed_files(entry):
            self.claimed.put(f, owner(entry, f))

    def close(self) -> None:
        self.claimed.close()


@contextmanager
def ctrl_c_held() -> Iterator[None]:
    """Ctrl-C (SIGINT) in the block takes effect when the block ends (main thread; elsewhere the block runs as is):
    an entry's manifest line and the renames of the files it lists happen both or neither — interrupted between
    them, the line named files whose temporaries the run then removed. The handlers are swapped with ``_signal``'s
    ``signal``, which ``signal.signal`` wraps: the wrapper tries each handler as a ``Handlers`` enum member, and a
    function is not one (a ValueError raised and caught per call: ≈ 12 of the block's 14 µs, per output of a run's
    main process; issue 19)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = _signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        _signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)
        if caught:
            signal.raise_signal(signal.SIGINT)          # the run's own handling (KeyboardInterrupt), now


def _failed(entry: dict, error: str) -> dict:
    entry = {k: v for k, v in full_entry(entry).items() if k not in ("files", "output_sha256", "staged")}
    entry.update(status="failed", error=error)
    return entry


def commit(out_root: Path, entry: dict) -> None:
    """Rename an entry's staged temporaries onto their final names (their folders checked again; a run's ledger keeps
    its :class:`OutputFolders` for the whole run instead)."""
    folders = OutputFolders(out_root, Path(os.path.realpath(out_root)))
    try:
        folders.commit(entry)
    finally:
        folders.close()


def discard(out_root: Path, entry: dict) -> None:
    for tmp, _ in entry.pop("staged", []):
        try:
            (out_root / tmp).unlink()
        except FileNotFoundError:
            pass



class DiskIndex:
    """A string → string map in a private temporary SQLite database (deleted when closed; a 2 MB page cache), with
    a ``seen`` mark per key: what a run must remember per output without holding it in memory."""

    def __init__(self):
        self._db = sqlite3.connect("", isolation_level=None, check_same_thread=False)
        self._db.executescript("PRAGMA journal_mode=OFF; PRAGMA synchronous=OFF; "
                               "CREATE TABLE m (k TEXT PRIMARY KEY, v TEXT, seen INTEGER DEFAULT 0); BEGIN")

    def put(self, key: str, value: str) -> None:
        self._db.execute("INSERT OR REPLACE INTO m (k, v) VALUES (?, ?)", (key, value))

    def put_new(self, key: str, value: str) -> str | None:
        """Map ``key`` to ``value`` unless it is mapped: None when it was not, else its value (left as it is)."""
        if self._db.execute("INSERT OR IGNORE INTO m (k, v) VALUES (?, ?)", (key, value)).rowcount == 1:
            return None
        return self.get(key)

    def __contains__(self, key: str) -> bool:
        return self.get(key) is not None

    def get(self, key: str) -> str | None:
        row = self._db.execute("SELECT v FROM m WHERE k = ?", (key,)).fetchone()
        return None if row is None else row[0]

    def pop(self, key: str) -> None:
        self._db.execute("DELETE FROM m WHERE k = ?", (key,))

    def mark_seen(self, key: str) -> None:
        self._db.execute("UPDATE m SET seen = 1 WHERE k = ?", (key,))

    def unseen(self) -> Iterator[tuple[str, str]]:
        """(key, value) of the keys never marked seen, in key order."""
        return iter(self._db.execute("SELECT k, v FROM m WHERE seen = 0 ORDER BY k"))

    def __len__(self) -> int:
        return self._db.execute("SELECT COUNT(*) FROM m").fetchone()[0]

    def close(self) -> None:
        self._db.close()


class PreviousRun:
    """The ok entries of an earlier run's manifest that ``--resume`` may keep, by output (the last line of an output
    wins), read line by line into a :class:`DiskIndex`."""

    def __init__(self, manifest: Path | None = None):
        self.index = DiskIndex()
        for entry in iter_manifest(manifest) if manifest is not None else ():
            out = entry.get("output")
            if out is None:
                continue
            if entry.get("status") == "ok":
                self.index.put(out, json.dumps(entry))
            else:
                self.index.pop(out)

    def __bool__(self) -> bool:
        return len(self.index) > 0

    def get(self, output: str) -> dict | None:
        """The kept entry of ``output`` (marking it as seen by this run), or None."""
        value = self.index.get(output)
        if value is None:
            return None
        self.index.mark_seen(output)
        return json.loads(value)

    def seen(self, output: str) -> None:
        self.index.mark_seen(output)

    def unseen(self) -> Iterator[dict]:
        """Entries this run's plan never reached, in output order."""
        return (json.loads(v) for _, v in self.index.unseen())

    def close(self) -> None:
        self.index.close()

