"""Whitespace-separated text point tables: optional blank lines, one header line naming the columns (after a ``#``
if it starts with one, as ``numpy.savetxt`` writes it), then one point per line (Astyx HiRes2019
``radar_6455/*.txt``: a blank line, ``X Y Z V_r Mag``, values printed with ``%.18g``).

The values are read as float64 (:func:`parse`); :class:`TextTable` keeps what writing back needs: the bytes up to
the first row, each row's text and value, the line terminator and what follows the last row. The writer
(:func:`table_bytes`) puts back a row's own text when the point descends from that row (``origin``) with every value
bit for bit unchanged, so an identity chain gives the input byte for byte; a new or changed row is printed with
the table's format, the first (most precise) of :data:`FORMATS` that reproduces every value of the first
:data:`FORMAT_SAMPLE_ROWS` rows as the file has them (else ``%.17g``, which round-trips any float64). Columns
whose stored sign is the opposite of the canonical field's (``negated``; io/radar_formats.py) are negated on
reading and back on writing.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Iterable

import numpy as np

from ..errors import InputError

FORMATS = ("%.18g", "%.17g", "%.9g", "%.6g")      # C's printf / std::setprecision of float64 and float32 writers
ROUND_TRIP = "%.17g"
FORMAT_SAMPLE_ROWS = 256          # a writer prints every row alike; checking all of them costs most of the read
_SPACE = np.array([b" "[0], b"\t"[0], b"\r"[0], b"\n"[0], b"\v"[0], b"\f"[0]], np.uint8)


@dataclasses.dataclass(frozen=True, eq=False)
class TextTable:
    """What a text table holds besides its values, to write it back (module docstring)."""

    names: tuple[str, ...]
    preamble: bytes              # blank lines and the header line, with its terminator
    rows: np.ndarray             # (N,) object: each row's bytes without its terminator
    values: np.ndarray           # (N, columns) float64 as stored (before ``negated``)
    number_format: str           # printf format of new and changed rows
    negated: tuple[bool, ...]    # per column
    newline: bytes = b"\n"
    trailer: bytes = b"\n"       # after the last row: its terminator (b"" without one) and any blank lines


def parse(data: bytes, path, negate: Callable[[tuple[str, ...]], Iterable[str]] = lambda names: ()
          ) -> tuple[list[tuple[str, str, np.ndarray]], TextTable]:
    """The columns (name, ``<f8``, values; the columns ``negate(header names)`` negated) and the
    :class:`TextTable` of a text table; :class:`InputError` naming ``path`` for a table without a header or with
    ragged or bad rows."""
    newline = b"\r\n" if b"\r\n" in data else b"\n"
    lines = data.split(newline)
    start = next((i for i, line in enumerate(lines) if line.strip()), None)
    if start is None:
        raise InputError("not a text point table: the file holds only blank lines", file=str(path))
    try:
        names = tuple(lines[start].decode("ascii").lstrip().lstrip("#").split())    # numpy.savetxt: "# a b"
    except UnicodeDecodeError:
        raise InputError("not a text point table (non-ASCII bytes in the first line)", file=str(path)) from None
    if _numeric(names):
        raise InputError(f"no header line naming the columns: the first line holds numbers ({' '.join(names)!r}); a "
                         "text point table starts with the column names (Astyx: 'X Y Z V_r Mag')", file=str(path))
    if len(set(names)) != len(names):
        raise InputError(f"the header names a column twice: {list(names)}", file=str(path))
    end = len(lines)
    while end > start + 1 and not lines[end - 1].strip():
        end -= 1
    rows = lines[start + 1:end]
    blank = [start + 2 + i for i, row in enumerate(rows) if not row.strip()]
    if blank:
        raise InputError(f"line {blank[0]} is blank, between the rows of the table", file=str(path))
    counts = _token_counts(rows)
    ragged = np.flatnonzero(counts != len(names))
    if ragged.size:
        i = int(ragged[0])
        raise InputError(f"line {start + 2 + i} has {counts[i]} values, the header names {len(names)} columns "
                         f"({' '.join(names)})", file=str(path))
    tokens, values = _values(rows, len(names), start, path)
    flipped = set(negate(names))
    negated = tuple(name in flipped for name in names)
    columns = [(name, "<f8", -values[:, j] if neg else values[:, j].copy())
               for j, (name, neg) in enumerate(zip(names, negated))]
    table = TextTable(names, newline.join(lines[:start + 1]) + newline, _object_array(rows), values,
                      _format(tokens[:FORMAT_SAMPLE_ROWS], values[:FORMAT_SAMPLE_ROWS]),
                      negated, newline, newline.join([b""] + lines[end:]) if end < len(lines) else b"")
    return columns, table


def table_bytes(columns: list[tuple[str, str, np.ndarray]], table: TextTable, origin: np.ndarray | None) -> bytes:
    """The file bytes of ``columns`` (the table's, in its order) laid out as ``table``; ``origin``: the input row
    each point descends from (−1: new; None: row i is point i, a cloud built in memory has none)."""
    names = tuple(name for name, _, _ in columns)
    if names != table.names:
        raise ValueError(f"columns {list(names)} are not the text table's {list(table.names)}")
    stored = np.stack([-np.asarray(c, np.float64) if neg else np.asarray(c, np.float64)
                       for (_, _, c), neg in zip(columns, table.negated)], axis=1)
    n = len(stored)
    src = np.arange(n) if origin is None else np.asarray(origin, np.int64)
    keep = (src >= 0) & (src < len(table.rows))
    same = np.zeros(n, bool)
    if keep.any():
        before = table.values[src[keep]]
        same[keep] = (stored[keep].view(np.int64) == before.view(np.int64)).all(axis=1)
    out = np.empty(n, object)
    out[same] = table.rows[src[same]]
    if not same.all():
        fresh = stored[~same]
        text = np.char.mod(table.number_format, fresh[:, 0])
        for j in range(1, fresh.shape[1]):
            text = np.char.add(np.char.add(text, " "), np.char.mod(table.number_format, fresh[:, j]))
        out[~same] = [line.encode("ascii") for line in text.tolist()]
    body = table.newline.join(out.tolist())
    return table.preamble + body + (table.trailer if n else b"")


def new_table(names: tuple[str, ...]) -> TextTable:
    """The layout of a table built in memory: the header ``names``, ``%.17g`` values, ``\\n`` line ends."""
    return TextTable(names, (" ".join(names) + "\n").encode("ascii"), np.empty(0, object),
                     np.empty((0, len(names))), ROUND_TRIP, (False,) * len(names))


def _numeric(tokens) -> bool:
    try:
        np.array(tokens, dtype=np.float64)
    except ValueError:
        return False
    return True


def _token_counts(rows: list[bytes]) -> np.ndarray:
    """Whitespace-separated values in each row (vectorised over the joined rows)."""
    if not rows:
        return np.zeros(0, np.int64)
    buf = np.frombuffer(b"\n".join(rows), np.uint8)
    space = np.isin(buf, _SPACE)
    starts = ~space & np.concatenate([[True], space[:-1]])
    line = np.cumsum(buf == b"\n"[0]) - (buf == b"\n"[0])
    return np.bincount(line[starts], minlength=len(rows))


def _values(rows: list[bytes], k: int, start: int, path) -> tuple[np.ndarray, np.ndarray]:
    """The (N, k) tokens and their float64 values."""
    tokens = np.array(b" ".join(rows).split()).reshape(len(rows), k) if rows else np.empty((0, k), "S1")
    try:
        return tokens, tokens.astype(np.float64)
    except ValueError:
        for i, row in enumerate(tokens):
            for j, token in enumerate(row):
                if not _numeric([token]):
                    raise InputError(f"line {start + 2 + i}, column {j + 1}: {token.decode('ascii', 'replace')!r} "
                                     "is not a number", file=str(path)) from None
        raise


def _format(tokens: np.ndarray, values: np.ndarray) -> str:
    """The first of :data:`FORMATS` that prints every one of ``values`` as its token, else ``%.17g`` (a writer
    prints all columns alike: a column of short values such as ``48``, which any format reproduces, does not
    decide)."""
    if not len(values):
        return ROUND_TRIP
    text = tokens.astype("U")
    return next((f for f in FORMATS if (np.char.mod(f, values) == text).all()), ROUND_TRIP)


def _object_array(rows: list[bytes]) -> np.ndarray:
    out = np.empty(len(rows), object)
    out[:] = rows
    return out
