"""A run's output folders, checked once and held open, so that the main process commits a file with one ``renameat``
on its folder's descriptor (issue 19: the path-based rename checked the folder's real path per file, ≈ 6 ``lstat``
and 20–70 µs of the main process per output).

A folder is checked (:func:`io.atomic.ensure_dir_inside`: its real path inside the output root) when the run first
commits into it, then opened; later renames go through that descriptor, so they act on the checked folder itself
even if a path component were swapped for a symlink later (the path-based rename re-checked, then renamed by path:
a window per file; here one per folder). A staged temporary always lies in its final file's folder
(``io.atomic.atomic_path``). Where the platform lacks ``dir_fd`` renames (Windows), each file's folder is checked
and the file renamed by path.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path

from .io.atomic import ensure_dir_inside
from .real_folders import FOLDER_FLAGS

OPEN_FOLDERS = 32           # descriptors kept at once (least recently used closed first)


class OutputFolders:
    """Commits entries' staged temporaries (``entry["staged"]``: temporary → final, relative to ``out_root``) into
    folders checked once and held open; :meth:`close` at the run's end."""

    supported = os.rename in os.supports_dir_fd      # renameat (os.replace is the same call; not listed there)

    def __init__(self, out_root: Path, real_root: Path):
        self.out_root, self.real_root = out_root, real_root
        self._open: OrderedDict[str, int] = OrderedDict()

    def _fd(self, folder: str) -> int:
        fd = self._open.get(folder)
        if fd is not None:
            self._open.move_to_end(folder)
            return fd
        real = ensure_dir_inside(self.out_root / folder, self.real_root)
        fd = os.open(real, FOLDER_FLAGS)
        self._open[folder] = fd
        if len(self._open) > OPEN_FOLDERS:
            os.close(self._open.popitem(last=False)[1])
        return fd

    def commit(self, entry: dict) -> None:
        """Rename the entry's temporaries onto their final names (``staged`` removed from the entry)."""
        for tmp, final in entry.pop("staged", []):
            if not self.supported:
                target = self.out_root / final
                ensure_dir_inside(target.parent, self.real_root)
                os.replace(self.out_root / tmp, target)
                continue
            folder, _, name = final.rpartition("/")
            tmp_folder, _, tmp_name = tmp.rpartition("/")
            if tmp_folder != folder:
                raise OSError(f"staged file {tmp!r} is not in the folder of {final!r}")
            fd = self._fd(folder)
            os.replace(tmp_name, name, src_dir_fd=fd, dst_dir_fd=fd)

    def close(self) -> None:
        while self._open:
            os.close(self._open.popitem()[1])
