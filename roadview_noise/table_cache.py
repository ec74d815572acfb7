"""Deterministic physics tables kept on disk between runs (issue 19: every worker's first file).

A LiDAR worker's first file builds its strongest-return tables (``lidar_strongest.brightest_tables``: 40–65 ms), a
radar worker's its Mie and Doppler tables (``radar_clutter``: ≈ 60 ms, mostly miepython's pure-Python Mie series), a
camera rain or snow worker's its particle tables (``particles.particle_tables``: ≈ 6 ms, ≈ 0.1 s with motion bands);
with two workers both pay them side by side, and every run pays them again. :func:`disk_cached` is ``lru_cache``
whose misses look on disk first: a table is built once per machine, code and parameters, and every later worker
(other runs, the other worker of this run when it comes second) reads it back in a few milliseconds.

- **Exact**: the file holds the pickled return value, so a worker gets bit for bit what the function would return.
  The key is the SHA-256 of the pickled arguments and of :func:`code_version` (the package's source, Python's,
  NumPy's, SciPy's, miepython's, numba's and llvmlite's versions, the machine): an edit to any module or an
  upgrade builds new tables.
  Arrays read back are read-only (they share the file's buffer): a cached table is shared by every caller of the
  process already, so nothing may write into it.
- **Safe under concurrent runs**: a table is written to a temporary file in the cache folder and renamed onto its
  name (atomic); two writers of one key write the same bytes. A file whose length or CRC-32 does not match (a crash
  mid-write on a filesystem that reorders) is rebuilt and replaced; a folder that cannot be written costs only the
  cache.
- **Bounded**: after a write the folder is pruned to :data:`MAX_BYTES`, least recently written first; a process
  writes at most :data:`MAX_WRITES_PER_PROCESS` tables (a run keyed by parameters drawn per file, or by a value
  fitted per frame, would otherwise write a table per file: it still reads what is there). Only functions whose
  keys repeat across files belong here: the radar clutter's per-frame tables (``radar_clutter._pair_rcs_per_m3``,
  ``_rcs_table``, ``_count_table``, 4–10 ms at a worker's first file) are keyed by the relative wind, which is the
  same for every file when the ego velocity is the recipe's or zero; a frame whose ego velocity is fitted from its
  own data gets keys of its own, and pays a look-up per table (≈ 0.1 ms: key and a missing file) beside a build of
  several milliseconds.

Not ``joblib.Memory``: it keys a call on the function's own source, not on the modules and compiled kernels the
table is computed with, and it does not bound the folder or check a file's integrity.

``RVNOISE_TABLE_CACHE``: the folder (default ``$XDG_CACHE_HOME/rvnoise/tables``, else ``~/.cache/rvnoise/tables``);
``off`` disables it. Workers see the fork server's environment (the ``rvnoise`` command's). The files are
pickles: the folder must be as trusted as the package's own ``__pycache__`` (it is created private, mode 0700).
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
import platform
import struct
import sys
import tempfile
import zlib
from pathlib import Path
from typing import Any, Callable

ENV = "RVNOISE_TABLE_CACHE"
MAX_BYTES = 256 * 1024 ** 2
MAX_WRITES_PER_PROCESS = 12
VERSIONED = ("numpy", "scipy", "miepython", "numba", "llvmlite")     # libraries the tables are computed with
_MAGIC = b"RVNTAB1\n"
_HEADER = struct.Struct("<8sQI")                 # magic, payload length, CRC-32 of the payload
_MISSING = object()
_writes = 0                                      # tables this process wrote


def cache_dir() -> Path | None:
    """The cache folder (see the module docstring); None when disabled."""
    value = os.environ.get(ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "off", "0", "no", "false") else Path(value)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "rvnoise" / "tables"


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """SHA-256 of every module of the package (path and bytes), Python's version, the machine and
    :data:`VERSIONED` libraries' versions: what a table's values may depend on besides its arguments. Computed once
    per process (the fork server's warm-up computes it for its workers)."""
    root = Path(__file__).resolve().parent
    modules = []
    for folder, subfolders, names in os.walk(root):
        subfolders[:] = [d for d in subfolders if d != "__pycache__"]      # numba's cache files live there
        modules += [Path(folder, n) for n in names if n.endswith(".py")]
    digest = hashlib.sha256()
    for path in sorted(modules):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    for name in VERSIONED:
        digest.update(f"{name}={library_version(name)}\0".encode())
    digest.update(f"{sys.version}\0{platform.machine()}\0{sys.byteorder}".encode())
    return digest.hexdigest()


def library_version(name: str) -> str:
    """A library's version: its ``__version__`` when it is imported already (NumPy, SciPy, numba and llvmlite in
    every process that builds tables: no look-up), else its distribution's (``importlib.metadata``: 2–4 ms a
    library, scanning ``sys.path``); "-" when it is not installed."""
    version = getattr(sys.modules.get(name), "__version__", None)
    if isinstance(version, str):
        return version
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "-"


def key(fn: Callable, args: tuple, kwargs: dict) -> str:
    """The file name of ``fn(*args, **kwargs)``'s table: the function's name and a SHA-256 of its pickled
    arguments and :func:`code_version`."""
    blob = pickle.dumps((args, sorted(kwargs.items())), protocol=4)    # 4: an array's bytes whatever its flags
    digest = hashlib.sha256(code_version().encode() + b"\0" + blob).hexdigest()
    return f"{fn.__module__}.{fn.__qualname__}-{digest}.pkl"


def read(path: Path) -> Any:
    """The table stored at ``path``; :data:`_MISSING` when absent, torn or unreadable."""
    try:
        with open(path, "rb") as fh:
            blob = fh.read()
        magic, length, crc = _HEADER.unpack_from(blob)
        payload = memoryview(blob)[_HEADER.size:]
        if magic != _MAGIC or len(payload) != length or zlib.crc32(payload) != crc:
            return _MISSING
        return pickle.loads(payload)
    except Exception:                    # absent, truncated, or written by an incompatible class: rebuild
        return _MISSING


def write(folder: Path, name: str, value: Any) -> None:
    """Store ``value`` as ``folder/name`` atomically (temporary file + rename), then prune the folder; a folder that
    cannot be written (read-only, full) is left as it is."""
    tmp = None
    try:
        payload = pickle.dumps(value, protocol=5)
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=".pkl")
        with os.fdopen(fd, "wb") as fh:
            fh.write(_HEADER.pack(_MAGIC, len(payload), zlib.crc32(payload)))
            fh.write(payload)
        os.replace(tmp, folder / name)
        tmp = None
        prune(folder)
    except Exception:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass


def prune(folder: Path, max_bytes: int = MAX_BYTES) -> None:
    """Delete the least recently written tables of ``folder`` until the rest fit in ``max_bytes``."""
    entries = []
    for entry in os.scandir(folder):
        if entry.name.endswith(".pkl") and not entry.name.startswith(".tmp-"):
            try:
                st = entry.stat()
            except OSError:
                continue
            entries.append((st.st_mtime, st.st_size, entry.path))
    total = sum(size for _, size, _ in entries)
    for _, size, path in sorted(entries):
        if total <= max_bytes:
            break
        try:
            os.unlink(path)
        except OSError:
            pass
        total -= size


def load_or_build(fn: Callable, args: tuple, kwargs: dict) -> Any:
    """``fn(*args, **kwargs)`` from the cache folder, else built and stored."""
    folder = cache_dir()
    if folder is None:
        return fn(*args, **kwargs)
    try:
        name = key(fn, args, kwargs)
    except Exception:                    # an argument that does not pickle: no disk cache for that call
        return fn(*args, **kwargs)
    global _writes
    value = read(folder / name)
    if value is _MISSING:
        value = fn(*args, **kwargs)
        if _writes < MAX_WRITES_PER_PROCESS:
            _writes += 1
            write(folder, name, value)
    return value


def disk_cached(maxsize: int) -> Callable[[Callable], Callable]:
    """``functools.lru_cache(maxsize)`` over :func:`load_or_build`: for pure functions of hashable, picklable
    arguments whose values are worth more than a file read (tables of tens of milliseconds). ``.uncached`` is the
    function itself."""
    def decorate(fn: Callable) -> Callable:
        @functools.lru_cache(maxsize=maxsize)
        @functools.wraps(fn)
        def cached(*args, **kwargs):
            return load_or_build(fn, args, kwargs)

        cached.uncached = fn
        return cached

    return decorate
