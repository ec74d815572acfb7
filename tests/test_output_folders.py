"""A run's output folders are checked once, held open, and files are committed by ``renameat`` on them
(issue 19): the renames land in the checked folder, a folder that leads out of OUT is refused, few stay open."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from roadview_noise import output_folders
from roadview_noise.io.atomic import OutsideRootError
from roadview_noise.output_folders import OutputFolders


def _staged(root: Path, rel: str) -> list[str]:
    folder, _, name = rel.rpartition("/")
    (root / folder).mkdir(parents=True, exist_ok=True)
    tmp = f"{folder}/.{name}.rvnoise-tmp" if folder else f".{name}.rvnoise-tmp"
    (root / tmp).write_text(rel)
    return [tmp, rel]


def test_commits_rename_in_the_checked_folders_and_keep_few_open(tmp_path, monkeypatch):
    monkeypatch.setattr(output_folders, "OPEN_FOLDERS", 3)
    root = tmp_path / "out"
    root.mkdir()
    folders = OutputFolders(root, root.resolve())
    rels = [f"s{k % 5}/f{k}.pcd" for k in range(20)] + ["top.pcd"]
    for rel in rels:
        entry = {"staged": [_staged(root, rel)]}
        folders.commit(entry)
        assert "staged" not in entry and len(folders._open) <= 3
    folders.close()
    assert folders._open == {}
    assert all((root / rel).read_text() == rel for rel in rels)
    assert not [p for p in root.rglob(".*") if p.is_file()]


@pytest.mark.skipif(not OutputFolders.supported, reason="renames by folder descriptor (POSIX)")
def test_a_folder_swapped_for_a_symlink_after_its_check_is_never_written_through(tmp_path):
    """The descriptor is the checked folder: after ``out/s`` is replaced by a symlink to a folder outside OUT, a
    rename goes to the checked folder (the temporary is not there: it fails), never outside."""
    root, outside = tmp_path / "out", tmp_path / "outside"
    root.mkdir()
    outside.mkdir()
    folders = OutputFolders(root, root.resolve())
    folders.commit({"staged": [_staged(root, "s/a.pcd")]})
    os.rename(root / "s", tmp_path / "moved")
    (root / "s").symlink_to(outside)
    (outside / ".b.pcd.rvnoise-tmp").write_text("x")
    with pytest.raises(FileNotFoundError):
        folders.commit({"staged": [["s/.b.pcd.rvnoise-tmp", "s/b.pcd"]]})
    assert sorted(p.name for p in outside.iterdir()) == [".b.pcd.rvnoise-tmp"]
    folders.close()
    fresh = OutputFolders(root, root.resolve())                     # checked anew: refused
    with pytest.raises(OutsideRootError):
        fresh.commit({"staged": [["s/.b.pcd.rvnoise-tmp", "s/b.pcd"]]})
    fresh.close()
