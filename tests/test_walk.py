"""The lazy input walk: the same files as ``pathlib`` globs, in sorted order, and every path it cannot use reported."""

from __future__ import annotations

import errno
import os
import re
from pathlib import Path

import numpy as np
import pytest

from roadview_noise.walk import Matcher, WalkFailure, glob_regex, walk

PATTERNS = ["**/*.png", "cam/**/*.png", "*/seq?/*.p[nm]g", "cam/*.png", "**/x*.bin", "cam/[!s]*/*.png",
            "*.png", "cam/seqA/**/*", "**/seq*/**/*.bin", "cam/seqA/000001.png"]


def _random_tree(root: Path, rng) -> None:
    folders = ["", "cam", "cam/seqA", "cam/seqB", "cam/seqA/deep", "lidar", "lidar/seq1", "other", "cam/tmp"]
    names = ["000001.png", "000002.pgm", "x1.bin", "a.png", "b.PNG", ".hidden.png", "y.bin", "seq.png", "z.txt"]
    for folder in folders:
        (root / folder).mkdir(parents=True, exist_ok=True)
        for name in rng.choice(names, size=int(rng.integers(0, len(names))), replace=False):
            (root / folder / name).write_bytes(b"x")


def _any_case_extension(pattern: str) -> str:
    """The pathlib glob whose last segment's literal extension matches in any case (``*.png`` → ``*.[pP][nN][gG]``),
    as rvnoise's patterns do."""
    head, _, name = pattern.rpartition("/")
    m = re.fullmatch(r"(.*?)((?:\.[A-Za-z0-9]+)+)", name)
    if m is None:
        return pattern
    ext = "".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else c for c in m[2])
    return f"{head}/{m[1]}{ext}" if head else f"{m[1]}{ext}"


@pytest.mark.parametrize("seed", range(6))
def test_walk_matches_pathlib_glob(tmp_path, seed):
    root = tmp_path / f"t{seed}"
    _random_tree(root, np.random.default_rng(seed))
    for pattern in PATTERNS:
        want = sorted(p.relative_to(root).as_posix() for p in root.glob(_any_case_extension(pattern))
                      if p.is_file() and not p.name.startswith("."))
        got = [item[0] for item in walk(root, Matcher([("m", pattern)]))]
        assert got == want, pattern


def test_extension_matches_in_any_case_the_rest_does_not():
    rx = glob_regex("raw/**/*.dng")
    assert rx.fullmatch("raw/a/L1000001.DNG") and rx.fullmatch("raw/x.Dng") and rx.fullmatch("raw/b/c.dng")
    assert not rx.fullmatch("RAW/x.dng") and not rx.fullmatch("raw/x.dngx") and not rx.fullmatch("raw/x.DNG.txt")
    rx = glob_regex("lidar/*.pcd.bin")
    assert rx.fullmatch("lidar/a.PCD.BIN") and not rx.fullmatch("lidar/a.bin")
    assert glob_regex("cam/seqA/000001.png").fullmatch("cam/seqA/000001.PNG")
    assert not glob_regex("cam/seqA/000001.png").fullmatch("cam/seqA/000001X.png")


def test_first_matching_modality_wins_and_exclusions():
    m = Matcher([("camera", "**/*.png"), ("raw", "**/*")], exclude=["cam/private/*"])
    assert m.modality("cam/a.png") == "camera" and m.modality("cam/a.dng") == "raw"
    assert m.modality("cam/private/a.png") is None and m.excluded_dir("cam/private")
    assert m.roots == [""]
    assert Matcher([("m", "b/**/*.png"), ("m", "a/x/*.png"), ("m", "a/*.png")]).roots == ["a", "b"]
    assert glob_regex("**/*.png").fullmatch("a.png") and not glob_regex("*.png").fullmatch("a/b.png")


def test_walk_reports_what_it_cannot_use(tmp_path, monkeypatch):
    root = tmp_path / "in"
    (root / "ok").mkdir(parents=True)
    (root / "ok" / "a.png").write_bytes(b"x")
    (root / "locked").mkdir()
    (root / "ok" / "dangling.png").symlink_to(tmp_path / "missing.png")
    (tmp_path / "outside.png").write_bytes(b"x")
    (root / "ok" / "escape.png").symlink_to(tmp_path / "outside.png")
    (root / "ok" / "inside.png").symlink_to(root / "ok" / "a.png")
    (tmp_path / "elsewhere").mkdir()
    (root / "linked").symlink_to(tmp_path / "elsewhere")
    os.mkfifo(root / "ok" / "fifo.png")
    real_scandir = os.scandir

    def scandir(path="."):
        if os.fspath(path).endswith("locked"):
            raise PermissionError(errno.EACCES, "Permission denied")
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", scandir)
    items = list(walk(root, Matcher([("m", "**/*.png")])))
    files = [i[0] for i in items if not isinstance(i, WalkFailure)]
    failures = {f.relpath: f.error for f in items if isinstance(f, WalkFailure)}
    assert files == ["ok/a.png", "ok/inside.png"]
    assert "dangling symlink" in failures["ok/dangling.png"]
    assert "outside the input folder" in failures["ok/escape.png"]
    assert "outside the input folder" in failures["linked"]
    assert "not a regular file" in failures["ok/fifo.png"]
    assert failures["locked"].startswith("cannot read folder: permission denied")


def test_walk_is_lazy(tmp_path, monkeypatch):
    root = tmp_path / "in"
    for i in range(50):
        (root / f"d{i:02d}").mkdir(parents=True)
        (root / f"d{i:02d}" / "a.png").write_bytes(b"x")
    calls = []
    real_scandir = os.scandir

    def counting(path="."):
        calls.append(path)
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", counting)
    first = next(walk(root, Matcher([("m", "**/*.png")])))
    assert first[0] == "d00/a.png" and len(calls) == 2          # the root and the first folder only


@pytest.mark.parametrize("pattern,sidecars", [("{stem}_depth.png", ["cam/a_depth.png", "cam/b_depth.png"]),
                                              ("depth/{stem}.png", ["cam/depth/a.png", "cam/depth/b.png"])])
def test_depth_sidecars_are_not_inputs(tmp_path, pattern, sidecars):
    from roadview_noise.dataset import iter_inputs
    from roadview_noise.recipe import parse_recipe

    root = tmp_path / "in"
    for rel in ["cam/a.png", "cam/b.png", "cam/c.png", *sidecars]:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(b"x")
    recipe = parse_recipe({"chain": [{"model": "compression.camera"}], "inputs": {"depth": pattern}})
    samples = list(iter_inputs(root, recipe))
    assert [s.relpath for s in samples] == ["cam/a.png", "cam/b.png", "cam/c.png"]
    assert [s.depth_relpath for s in samples] == [*sidecars, None]


def test_folders_no_glob_can_reach_are_neither_walked_nor_reported(tmp_path):
    m = Matcher([("m", "cam/*/[0-9]*.png"), ("m", "lidar/**/velodyne/*.bin")])
    assert m.may_contain("cam") and m.may_contain("cam/seqA") and not m.may_contain("cam/seqA/deep")
    assert m.may_contain("lidar/a/b/c") and not m.may_contain("labels")
    root = tmp_path / "in"
    (root / "lidar" / "seq" / "velodyne").mkdir(parents=True)
    (root / "lidar" / "seq" / "velodyne" / "0.bin").write_bytes(b"x" * 16)
    (tmp_path / "outside").mkdir()
    (root / "labels").symlink_to(tmp_path / "outside")            # not where inputs can be: not a failure
    (root / "lidar" / "seq" / "extra").symlink_to(tmp_path / "outside")
    items = list(walk(root, m))
    assert items[0] == WalkFailure("lidar/seq/extra", items[0].error) and items[1][0] == "lidar/seq/velodyne/0.bin"
    assert len(items) == 2
