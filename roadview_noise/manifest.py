"""The run record: ``manifest.jsonl`` (one line per output) and ``run.json`` (tool, libraries, recipe, counts).

A manifest line holds the input and output paths and sha256, the chain, every step's parameters, sensor-instance
state, drawn values and diagnostics, the time taken and the status — enough for ``rvnoise replay`` to reproduce the
output byte for byte."""

from __future__ import annotations

import hashlib
import json
import platform
import sys
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from .io.atomic import atomic_path, write_bytes_atomic

MANIFEST_NAME = "manifest.jsonl"
RUN_NAME = "run.json"


def _default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (set, frozenset)):
        return sorted(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


_ENCODER = json.JSONEncoder(default=_default, ensure_ascii=False, allow_nan=True, check_circular=False)
# the C encoder json.dumps makes for each call (≈ 1.5 µs a call, several per manifest line: entry_line), made once
_C_ENCODER = None if json.encoder.c_make_encoder is None else json.encoder.c_make_encoder(
    None, _default, json.encoder.encode_basestring, None, ": ", ", ", False, False, True)


def dumps(obj: Any) -> str:
    """``json.dumps(obj, default=_default, ensure_ascii=False, allow_nan=True)``, the same text (an entry is never
    circular: not checked)."""
    if _C_ENCODER is None or isinstance(obj, str):
        return _ENCODER.encode(obj)
    return "".join(_C_ENCODER(obj, 0))


LINE = "_line"                # a run's entry: its manifest line, encoded by the worker (:func:`encoded`)
# the keys a run's main process gets in the line only (it must not read them from a worker's entry; full_entry
# decodes them when it has to rewrite the entry)
LINE_ONLY = ("steps", "metrics", "profile", "chain", "variant", "library_messages")


_METRICS_MARK = "\x00rvnoise-metrics\x00"   # stands for a one-step chain's metrics while its line is encoded
_METRICS_AT = f'"metrics": {dumps(_METRICS_MARK)}'


def entry_line(entry: dict) -> str:
    """The manifest line of an entry (no newline; its ``staged`` temporaries are not recorded): the one a worker
    encoded (:func:`encoded`), else encoded here. The metrics of a one-step chain, which are its step's (the same
    dict), are encoded once: the line is encoded with a mark in their two places, whose text (``"metrics": "``, NUL,
    …) is then replaced by theirs; a line holding the mark's text elsewhere is encoded whole. One encoder call instead
    of the line in pieces (≈ 12 µs of a radar file's worker, issue 19)."""
    line = entry.get(LINE)
    if line is not None:
        return line
    entry = {k: v for k, v in entry.items() if k != "staged" and k != LINE}
    steps, metrics = entry.get("steps"), entry.get("metrics")
    if not steps or not metrics or len(steps) != 1 or steps[0].get("metrics") is not metrics:
        return dumps(entry)
    entry["metrics"], entry["steps"] = _METRICS_MARK, [{**steps[0], "metrics": _METRICS_MARK}]
    parts = dumps(entry).split(_METRICS_AT)
    if len(parts) != 3:                                  # (a key or value held the mark's text: encoded whole)
        entry["metrics"], entry["steps"] = metrics, steps
        return dumps(entry)
    return f'"metrics": {dumps(metrics)}'.join(parts)


def encoded(entry: dict) -> dict:
    """``entry`` as a run's worker returns it: with its manifest line already encoded (:data:`LINE`) and without
    the keys that only the line needs (:data:`LINE_ONLY`: steps, metrics …), so that the main process, the run's
    one writer, neither unpickles nor encodes them but writes the line as it is (issue 19: with as many workers as
    cores, each millisecond the main process spends per file is taken from a worker)."""
    slim = {k: v for k, v in entry.items() if k not in LINE_ONLY}
    slim[LINE] = entry_line(entry)
    return slim


def full_entry(entry: dict) -> dict:
    """The whole entry of an :func:`encoded` one (read back from its line; ``staged`` kept), for the rare change
    the main process makes to an entry after it ran (a failure it records); any other entry as it is."""
    line = entry.get(LINE)
    if line is None:
        return entry
    full = json.loads(line)
    if "staged" in entry:
        full["staged"] = entry["staged"]
    return full


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_manifest(path: str | Path) -> list[dict]:
    """Entries of a manifest; a line cut short by a killed run is skipped."""
    return list(iter_manifest(path))


def iter_manifest(path: str | Path) -> Iterator[dict]:
    """Entries of a manifest one at a time (nothing when it does not exist); a line cut short is skipped."""
    p = Path(path)
    if not p.is_file():
        return
    with open(p, encoding="utf-8") as fh:
        for line in fh:
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(entry, dict):
                yield entry


def write_manifest(path: str | Path, entries: Iterable[dict]) -> None:
    """Write the entries as the manifest, atomically, one line at a time."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        for e in entries:
            fh.write(dumps(e) + "\n")


def write_run_json(path: str | Path, record: dict) -> None:
    write_bytes_atomic(path, (json.dumps(record, indent=2, default=_default) + "\n").encode("utf-8"))


# distributions that install each library whose version is recorded (read from their metadata, not imported:
# importing open3d alone costs a second)
_VERSIONED = {"scipy": ("scipy",), "open3d": ("open3d", "open3d-cpu"), "rawpy": ("rawpy",),
              "OpenEXR": ("OpenEXR", "openexr"), "tifffile": ("tifffile",), "miepython": ("miepython",),
              "isal": ("isal",), "pillow_heif": ("pillow-heif", "pillow_heif")}


def library_versions() -> dict[str, str]:
    """Versions of everything that can change output bytes ("unavailable": not installed)."""
    import cv2

    from . import __version__

    versions = {"rvnoise": __version__, "python": sys.version.split()[0], "numpy": np.__version__,
                "opencv": cv2.__version__}
    for name, dists in _VERSIONED.items():
        versions[name] = _installed_version(name, dists)
    versions["platform"] = platform.platform()
    versions["cpu_math"] = cpu_math_features()
    return versions


# CPU extensions that select NumPy's SIMD float kernels and glibc's libm variants (exp, atan2 … have FMA versions):
# machines that differ in them may round a transcendental function differently in the last bit.
_MATH_FEATURES = ("FMA3", "AVX2", "AVX512F", "AVX512_SKX", "ASIMD", "ASIMDHP", "SVE", "VSX2", "VSX3", "VX")


def cpu_math_features() -> str:
    """The CPU extensions among ``_MATH_FEATURES`` that NumPy detected here ("baseline" if none)."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:                                     # NumPy < 2
        from numpy.core._multiarray_umath import __cpu_features__ as features
    return " ".join(f for f in _MATH_FEATURES if features.get(f)) or "baseline"


def _installed_version(module: str, dists: tuple[str, ...]) -> str:
    """The version of the first of ``dists`` installed, else of the module if it is imported, else
    "unavailable" (the same answer in every process, whatever it imported)."""
    found = _distribution_version(dists)
    if found is not None:
        return found
    if module in sys.modules:
        return str(getattr(sys.modules[module], "__version__", "unknown"))
    return "unavailable"


@lru_cache(maxsize=None)
def _distribution_version(dists: tuple[str, ...]) -> str | None:
    """The installed version of the first of ``dists`` (None: none is installed), read once per process: the
    metadata look-up costs ≈ 1–2 ms per library, paid by every run's record otherwise."""
    from importlib.metadata import PackageNotFoundError, version

    for dist in dists:
        try:
            return version(dist)
        except PackageNotFoundError:
            continue
    return None
