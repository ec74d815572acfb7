"""Folders' real paths resolved once per process (roadview_noise.real_folders): recognised by one stat afterwards,
resolved anew when a path component was swapped for a symlink, the folder replaced or the file is a symlink; and the
checks built on them (io.atomic.ensure_dir_inside, runner.input_path) still refuse what leads out of their root."""

import os

import pytest

from roadview_noise import real_folders
from roadview_noise.errors import InputError
from roadview_noise.io.atomic import OutsideRootError, confined_to, write_bytes_atomic
from roadview_noise.real_folders import real_file, real_folder
from roadview_noise.runner import input_path


def test_a_known_folder_costs_one_stat_and_equals_realpath(tmp_path, monkeypatch):
    (tmp_path / "a" / "b").mkdir(parents=True)
    os.symlink(tmp_path / "a", tmp_path / "link")
    folder = str(tmp_path / "link" / "b")
    assert real_folder(folder) == os.path.realpath(folder)
    calls = []
    monkeypatch.setattr(os.path, "realpath", lambda p: calls.append(p) or p)
    assert real_folder(folder) == str(tmp_path / "a" / "b")
    assert calls == []


def test_a_swapped_component_or_a_replaced_folder_is_resolved_anew(tmp_path):
    for name in ("a/b", "c/b"):
        (tmp_path / name).mkdir(parents=True)
    os.symlink(tmp_path / "a", tmp_path / "link")
    folder = str(tmp_path / "link" / "b")
    assert real_folder(folder) == str(tmp_path / "a" / "b")
    os.remove(tmp_path / "link")
    os.symlink(tmp_path / "c", tmp_path / "link")
    assert real_folder(folder) == str(tmp_path / "c" / "b")
    os.rmdir(tmp_path / "c" / "b")
    with pytest.raises(FileNotFoundError):
        real_folder(folder)
    (tmp_path / "c" / "b").write_text("x")
    with pytest.raises(NotADirectoryError):
        real_folder(folder)


def test_real_file_resolves_a_symlinked_file_in_full(tmp_path):
    (tmp_path / "in").mkdir()
    (tmp_path / "outside.pcd").write_text("x")
    (tmp_path / "in" / "plain.pcd").write_text("x")
    os.symlink(tmp_path / "outside.pcd", tmp_path / "in" / "link.pcd")
    assert real_file(str(tmp_path / "in" / "plain.pcd")) == str(tmp_path / "in" / "plain.pcd")
    assert real_file(str(tmp_path / "in" / "link.pcd")) == str(tmp_path / "outside.pcd")
    assert real_file(str(tmp_path / "in" / "missing.pcd")) == str(tmp_path / "in" / "missing.pcd")


def test_input_path_still_refuses_a_symlink_out_after_its_folder_is_known(tmp_path):
    root = tmp_path / "in"
    (root / "seq").mkdir(parents=True)
    (root / "seq" / "a.pcd").write_text("x")
    (tmp_path / "secret.pcd").write_text("x")
    assert input_path(root, "seq/a.pcd") == root / "seq" / "a.pcd"        # the folder is known now
    os.symlink(tmp_path / "secret.pcd", root / "seq" / "b.pcd")
    with pytest.raises(InputError, match="outside the input folder"):
        input_path(root, "seq/b.pcd")
    os.rename(root / "seq", root / "moved")                                # the folder swapped for a symlink out
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "a.pcd").write_text("x")
    os.symlink(tmp_path / "elsewhere", root / "seq")
    with pytest.raises(InputError, match="outside the input folder"):
        input_path(root, "seq/a.pcd")


def test_writes_stay_confined_when_a_checked_folder_is_swapped_for_a_symlink(tmp_path):
    out, outside = tmp_path / "out", tmp_path / "outside"
    (out / "seq").mkdir(parents=True)
    outside.mkdir()
    with confined_to(out):
        write_bytes_atomic(out / "seq" / "a.bin", b"1")                   # checked and remembered
        os.rename(out / "seq", out / "old")
        os.symlink(outside, out / "seq")
        with pytest.raises(OutsideRootError):
            write_bytes_atomic(out / "seq" / "b.bin", b"2")
    assert list(outside.iterdir()) == []


def test_the_memory_is_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr(real_folders, "MAX_KNOWN", 4)
    for i in range(10):
        (tmp_path / str(i)).mkdir()
        real_folder(str(tmp_path / str(i)))
    assert len(real_folders._known) <= 4
