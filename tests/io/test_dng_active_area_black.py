"""DNG ActiveArea at any origin (the whole area read, the CFA phase taken at its origin as the DNG specification
and LibRaw's colour map put it) and the recipe's black-level override (``inputs.raw_black_level_dn``) for files
whose BlackLevel is wrong or missing. Real files (/work/realdata/dng, never committed) when present."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import rawpy
import tifffile
from test_dng_layout import _cfa_tags, _dn, _ifd0_tags, _single

from roadview_noise.errors import InputError
from roadview_noise.io.raw import BlackLevelWarning, read_dng, read_raw, write_dng, write_plain_raw
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from roadview_noise.types import cfa_index_map

PI_DNG = Path("/work/realdata/dng/minhtcai_camera_test.dng")     # PiDNG: 10-bit, no BlackLevel tag
PATTERN_BYTES = {"RGGB": (0, 1, 1, 2), "GBRG": (1, 2, 0, 1), "BGGR": (2, 1, 1, 0), "GRBG": (1, 0, 2, 1)}


@pytest.mark.parametrize("area", [(1, 3, 47, 63), (0, 1, 48, 64), (1, 0, 47, 64), (3, 5, 45, 61), (2, 2, 46, 62)])
@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_odd_active_area_is_read_whole_with_the_pattern_at_its_origin(tmp_path, area, pattern):
    top, left, bottom, right = area
    dn = _dn()
    src = tmp_path / "aa.dng"
    tifffile.imwrite(src, dn, photometric=32803, metadata=None, subfiletype=0, extratags=_ifd0_tags() + _cfa_tags(
        (50829, "I", 4, area, True), (50714, "H", 1, 64, True), (50719, "H", 2, (2, 2), True),
        pattern=PATTERN_BYTES[pattern]))
    frame, got, black, white = read_dng(src)
    np.testing.assert_array_equal(frame, dn[top:bottom, left:right])          # no row or column lost
    assert (got, black, white) == (pattern, 64.0, 4095.0)                    # CFAPattern starts at the area's origin
    with rawpy.imread(str(src)) as raw:                                      # LibRaw's own (even-origin) reading
        s = raw.sizes
        dy, dx = s.top_margin - top, s.left_margin - left
        np.testing.assert_array_equal(raw.raw_image_visible, frame[dy:dy + s.height, dx:dx + s.width])
        desc = raw.color_desc.decode()
        colours = np.array(["RGB".index(desc[c]) for c in raw.raw_colors_visible.ravel()]).reshape(s.height, s.width)
    np.testing.assert_array_equal(colours, cfa_index_map(got, *frame.shape)[dy:dy + s.height, dx:dx + s.width])
    write_dng(tmp_path / "out.dng", frame, got, black, white, template=src)
    back = read_dng(tmp_path / "out.dng")
    np.testing.assert_array_equal(back[0], frame)
    assert back[1:] == (pattern, 64.0, 4095.0)
    with tifffile.TiffFile(tmp_path / "out.dng") as t:                       # the whole active area: crop kept
        assert t.pages[0].tags[50719].value == (2, 2)


def test_black_level_override_replaces_a_wrong_or_missing_tag(tmp_path):
    dark = np.full((48, 64), 70, np.uint16)
    dark[::3, ::5] = 900
    src = _single(tmp_path / "pi.dng", dark)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                                      # stated: no BlackLevelWarning
        assert read_dng(src, 64)[2] == 64.0
        assert read_dng(src, (64, 64.5, 64.5, 65))[2] == 64.5               # per CFA site: their mean
    wrong = _single(tmp_path / "w.dng", dark, (50713, "H", 2, (2, 2), True), (50714, "H", 4, (0, 8, 16, 24), True))
    with pytest.raises(InputError, match="varies by 24 DN"):
        read_dng(wrong)                                                     # refused as read …
    assert read_dng(wrong, 66.0)[2] == 66.0                                 # … read with the stated level
    with pytest.raises(InputError, match=r"\[60.0, 64.0, 64.0, 68.0\] differs by more than 1.0 DN") as err:
        read_dng(src, (60, 64, 64, 68))
    assert "pi.dng" in str(err.value)
    with pytest.raises(InputError, match="not below the white level 4095"):
        read_dng(src, 5000)
    write_plain_raw(tmp_path / "p.raw", dark, "RGGB", 0, 1023)
    assert read_raw(tmp_path / "p.raw", 64)[2] == 64.0 and read_raw(tmp_path / "p.raw")[2] == 0.0


@pytest.mark.parametrize("value,words", [((64, 64, 64), "has 3 values"), (-1, "greater than or equal to 0")])
def test_black_level_override_checked_in_the_recipe(value, words):
    with pytest.raises(Exception, match=words):
        parse_recipe({"chain": [{"model": "compression.camera"}],
                      "inputs": {"raw": "*.dng", "raw_black_level_dn": value}})


def _pi_tree(root: Path) -> Path:
    if PI_DNG.is_file():
        (root / "raw").mkdir(parents=True)
        (root / "raw" / "pi.dng").write_bytes(PI_DNG.read_bytes())
    else:
        dark = np.full((48, 64), 70, np.uint16)
        dark[::3, ::5] = 900
        (root / "raw").mkdir(parents=True)
        _single(root / "raw" / "pi.dng", dark, (50717, "I", 1, 1023, True))
    return root


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_run_with_stated_black_level_writes_it_and_records_it(tmp_path):
    """A Raspberry Pi PiDNG without BlackLevel (the real file when present): the stated 64 DN is used, recorded in
    the manifest and written to the output DNG; without it the run warns."""
    root = _pi_tree(tmp_path / "in")
    runs = {}
    for name, stated in (("with", {"raw_black_level_dn": [64, 64, 64, 64]}), ("without", {})):
        recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 2, "chain": [{"model": "low_light.camera"}],
                               "inputs": {"raw": "raw/*.dng", **stated}})
        out = tmp_path / name
        assert run(recipe, root, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
        runs[name] = (out, next(iter(read_manifest(out / "manifest.jsonl"))))
    out, entry = runs["with"]
    assert entry["inputs"]["black_level"] == {"value_dn": 64.0, "from": "recipe inputs.raw_black_level_dn"}
    assert "BlackLevelWarning" not in json.dumps(entry)
    assert read_dng(out / "raw" / "pi.dng")[2] == 64.0
    _, plain = runs["without"]
    assert "black_level" not in plain.get("inputs", {}) and BlackLevelWarning.__name__ in json.dumps(plain)
