"""A lazy, sorted walk of the input tree that reports what it could not read.

``Path.glob`` skips unreadable folders and dangling symlinks without a word and builds its whole result before the
first file is seen. :func:`walk` yields matching files one by one, in the order of their sorted relative paths (the
folders of a level are visited in the order ``name + "/"``, which is the order of the full paths), and yields a
:class:`WalkFailure` for every folder it could not list and every matching name it could not use: dangling
symlinks, symlinked folders (never followed: they would lead out of the input tree or visit files twice), entries
it could not stat. Only the folders where some pattern can match a file are walked (and only their problems are reported).

Patterns are ``pathlib`` globs relative to the input root (``*``, ``?``, ``[...]`` within one name; ``**`` a whole
segment matching any number of folders), case-sensitive but for a pattern's file extension (``*.jpg`` matches
``IMG_0001.JPG``, ``*.dng`` a Leica's ``L1000001.DNG``: cameras write upper-case extensions, and every reader
takes the suffix in any case); names starting with ``.`` are never inputs.
"""

from __future__ import annotations

import errno
import fnmatch
import os
import re
from dataclasses import dataclass
from typing import Iterator, Sequence

from .io.atomic import is_temporary

_WILDCARD = re.compile(r"[*?\[]")


@dataclass(frozen=True)
class WalkFailure:
    """A path the walk could not read or use; ``relpath`` is POSIX, relative to the input root."""

    relpath: str
    error: str


def os_error_text(exc: OSError) -> str:
    """An OSError in words (``permission denied``, ``no such file``, …) without Python's class name."""
    text = exc.strerror or (errno.errorcode.get(exc.errno, "") if exc.errno else "") or str(exc)
    return text[:1].lower() + text[1:]


def _segment_regex(segment: str) -> str:
    out, i = [], 0
    while i < len(segment):
        c = segment[i]
        if c == "*":
            out.append("[^/]*")
        elif c == "?":
            out.append("[^/]")
        elif c == "[":
            j = segment.find("]", i + 2 if segment[i + 1:i + 2] in ("!", "]") else i + 1)
            if j < 0:
                out.append(re.escape(c))
            else:
                body = segment[i + 1:j]
                body = "^" + body[1:] if body.startswith("!") else body
                out.append(f"[{body.replace(chr(92), chr(92) * 2)}]")
                i = j
        else:
            out.append(re.escape(c))
        i += 1
    return "".join(out)


def _segments(pattern: str) -> list[str]:
    return [p for p in pattern.split("/") if p not in ("", ".")]


EXTENSION = re.compile(r"(.*?)((?:\.[A-Za-z0-9]+)+)")     # a name segment's literal trailing extension(s)


def glob_regex(pattern: str) -> re.Pattern:
    """The compiled regex of a pathlib glob over POSIX relative paths; the last segment's literal extension
    (``.jpg``, ``.pcd.bin``) matches in any case."""
    parts = _segments(pattern)
    rx = ""
    for k, seg in enumerate(parts):
        last = k == len(parts) - 1
        if seg == "**":
            rx += "(?:[^/]+/)*"
        elif last and (m := EXTENSION.fullmatch(seg)):
            rx += _segment_regex(m[1]) + f"(?i:{re.escape(m[2])})"
        else:
            rx += _segment_regex(seg) + ("" if last else "/")
    return re.compile(rx)


def literal_prefix(pattern: str) -> str:
    """The folder part of ``pattern`` before its first wildcard (``cam/seqA`` for ``cam/seqA/*.png``)."""
    parts = _segments(pattern)[:-1]
    prefix = []
    for p in parts:
        if _WILDCARD.search(p):
            break
        prefix.append(p)
    return "/".join(prefix)


def _prefix_matches(folders: list[str], parts: list) -> bool:
    """Whether ``folders`` can be the leading folders of a path matching the pattern ``parts`` (a compiled regex per
    folder segment, None for ``**``, then the file segment as False, or None when the pattern ends in ``**``)."""
    if not folders:
        return True
    head = parts[0]
    if head is False:
        return False
    if head is None:                                  # ** : skip it, or let it absorb one more folder
        return _prefix_matches(folders, parts[1:]) or _prefix_matches(folders[1:], parts)
    return bool(head.fullmatch(folders[0])) and _prefix_matches(folders[1:], parts[1:])


def _sort_key(entry: os.DirEntry) -> str:
    try:
        return entry.name + ("/" if entry.is_dir(follow_symlinks=False) else "")
    except OSError:
        return entry.name


class Matcher:
    """Which modality's globs a relative path matches first, and the exclusions."""

    def __init__(self, globs: Sequence[tuple[str, str]], exclude: Sequence[str] = ()):
        self.globs = [(modality, glob_regex(p)) for modality, p in globs]
        self._folder_parts = [[re.compile(_segment_regex(x)) if x != "**" else None for x in _segments(p)[:-1]]
                              + [None if _segments(p)[-1:] == ["**"] else False] for _, p in globs]
        self.exclude = list(exclude)
        roots = sorted({literal_prefix(p) for _, p in globs}, key=lambda r: r + "/")
        self.roots = [r for r in roots if not any(r != o and (o == "" or r.startswith(o + "/")) for o in roots)]

    def modality(self, rel: str) -> str | None:
        if self.excluded(rel):
            return None
        return next((m for m, rx in self.globs if rx.fullmatch(rel)), None)

    def excluded(self, rel: str) -> bool:
        return any(fnmatch.fnmatch(rel, x) for x in self.exclude)

    def may_contain(self, rel: str) -> bool:
        """Whether some glob can match a file below the folder ``rel`` (the walk skips the other folders and reports
        no problem with them)."""
        folders = rel.split("/") if rel else []
        return any(_prefix_matches(folders, p) for p in self._folder_parts)

    def excluded_dir(self, rel: str) -> bool:
        return any(fnmatch.fnmatch(rel, x) or fnmatch.fnmatch(rel + "/", x) for x in self.exclude)


def walk(in_root: str | os.PathLike, matcher: Matcher) -> Iterator[tuple[str, str, list[str]] | WalkFailure]:
    """Yield ``(relpath, modality, sibling_names)`` for every file matching the globs, in sorted order, and a
    :class:`WalkFailure` for every path under a walk root the walk could not read or use (see module docstring).
    ``sibling_names`` are the names in the file's folder (for sidecar lookups without another listing)."""
    root = os.path.realpath(in_root)
    for top in matcher.roots:
        path = os.path.join(root, top) if top else root
        if not top:
            yield from _walk_dir(root, "", root, matcher)
        elif os.path.lexists(path):
            failure = _symlink_failure(path, top, root) if os.path.islink(path) else None
            if failure is not None:
                yield failure
            elif os.path.isdir(path):
                yield from _walk_dir(path, top, root, matcher)


def _symlink_failure(path: str, rel: str, root: str) -> WalkFailure | None:
    """Why a symlink cannot be used (dangling, or leading out of the input tree), or None. A symlinked folder
    inside the tree is not followed (its target is walked on its own)."""
    if not os.path.exists(path):
        return WalkFailure(rel, f"dangling symlink: its target {os.readlink(path)!r} does not exist")
    real = os.path.realpath(path)
    if not (real == root or real.startswith(root + os.sep)):
        what = "folder" if os.path.isdir(path) else "file"
        return WalkFailure(rel, f"is a symlink to the {what} {real!r} outside the input folder; rvnoise reads "
                                "only inside the input folder (copy it in or give its own folder as input)")
    return None


def _walk_dir(path: str, rel: str, root: str, matcher: Matcher) -> Iterator:
    try:
        with os.scandir(path) as it:
            entries = sorted(it, key=_sort_key)
    except OSError as exc:
        yield WalkFailure(rel or ".", f"cannot read folder: {os_error_text(exc)}; its files were not processed")
        return
    names = [e.name for e in entries]
    for entry in entries:
        child = f"{rel}/{entry.name}" if rel else entry.name
        try:
            is_link = entry.is_symlink()
            is_dir = entry.is_dir()                  # follows a symlink (False when dangling)
        except OSError as exc:
            yield WalkFailure(child, f"cannot inspect: {os_error_text(exc)}")
            continue
        if is_dir:
            if matcher.excluded_dir(child) or not matcher.may_contain(child):
                continue
        else:
            modality = None if entry.name.startswith(".") or is_temporary(entry.name) else matcher.modality(child)
            if modality is None:
                continue
        if is_link:
            failure = _symlink_failure(entry.path, child, root)
            if failure is not None:
                yield failure
                continue
            if is_dir:                               # inside the input tree: its target is walked on its own
                continue
        if is_dir:
            yield from _walk_dir(entry.path, child, root, matcher)
            continue
        try:
            regular = entry.is_file()                # from the listing, no stat (a symlink's target is stat'ed)
        except OSError:
            regular = False
        if not regular:
            yield WalkFailure(child, "is not a regular file (device, pipe or socket)")
            continue
        yield child, modality, names
