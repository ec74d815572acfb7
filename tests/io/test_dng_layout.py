"""DNG layouts as cameras write them (built with tifffile): raw image in a SubIFD behind a preview, big-endian,
tiled, per-site and per-row/column black levels, LinearizationTable, ActiveArea, default crop and opcode lists;
what rvnoise refuses and what the written DNG keeps. Real files (/work/realdata/dng, never committed) when present."""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
import rawpy
import tifffile

from roadview_noise.errors import InputError
from roadview_noise.io.raw import BlackLevelWarning, read_dng, write_dng

IDENTITY = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)
COLOUR = (7, 10, -2, 10, -1, 10, -4, 10, 12, 10, 1, 10, -1, 10, 2, 10, 6, 10)
REAL_DNGS = Path("/work/realdata/dng")
# OpcodeList2 with one optional WarpRectilinear opcode (DNG 1.3 §6; always big-endian)
OPCODES = struct.pack(">IIIII", 1, 1, 0x01030000, 1, 68) + struct.pack(">I8d", 1, 1, 0, 0, 0, 0, 0, 0.5, 0.5)


def _dn(shape=(48, 64), seed=0):
    return np.random.default_rng(seed).integers(200, 4000, shape, dtype=np.uint16)


def _cfa_tags(*extra, dim=(2, 2), pattern=(0, 1, 1, 2)):
    return [(33421, "H", 2, dim, True), (33422, "B", len(pattern), bytes(pattern), True),
            (50717, "I", 1, 4095, True), *extra]


def _ifd0_tags():
    return [(50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "Cam X", True), (271, "s", 0, "Maker", True),
            (274, "H", 1, 6, True), (50721, "2i", 9, COLOUR, True), (50728, "2I", 3, (1, 2, 1, 1, 2, 3), True)]


def _single(path, dn, *extra, **kw):
    """Raw image in IFD0 (as PiDNG and small cameras write it)."""
    tifffile.imwrite(path, dn, photometric=32803, metadata=None, subfiletype=0,
                     extratags=_ifd0_tags() + _cfa_tags(*extra), **kw)
    return path


def _camera_layout(path, dn, *extra, byteorder=">"):
    """Preview in IFD0, tiled raw image in its SubIFD (as cameras and Adobe DNG Converter write it)."""
    with tifffile.TiffWriter(path, byteorder=byteorder) as tif:
        tif.write(np.zeros((12, 16, 3), np.uint8), photometric="rgb", subfiletype=1, subifds=1, metadata=None,
                  extratags=_ifd0_tags())
        tif.write(dn, photometric=32803, subfiletype=0, metadata=None, tile=(16, 16), extratags=_cfa_tags(*extra))
    return path


def test_camera_layout_big_endian_keeps_crop_opcodes_and_colour(tmp_path):
    dn = _dn()
    src = _camera_layout(tmp_path / "cam.dng", dn, (50719, "H", 2, (2, 4), True), (50720, "H", 2, (56, 40), True),
                         (51009, "B", len(OPCODES), OPCODES, True), (50714, "H", 1, 64, True))
    back, pattern, black, white = read_dng(src)
    np.testing.assert_array_equal(back, dn)
    assert (pattern, black, white) == ("RGGB", 64.0, 4095.0)
    write_dng(tmp_path / "out.dng", back, pattern, black, white, template=src)
    with tifffile.TiffFile(src) as a, tifffile.TiffFile(tmp_path / "out.dng") as b:
        assert len(b.pages) == 1 and not b.pages[0].pages                # previews dropped, raw image in IFD0
        out, first, raw = b.pages[0].tags, a.pages[0].tags, a.pages[0].pages[0].tags
        for code in (271, 274, 50708, 50721, 50728):
            assert out[code].value == first[code].value, code
        assert out[50719].value == (2, 4) and out[50720].value == (56, 40)
        assert out[51009].value == raw[51009].value == OPCODES
        assert out[50707].value == b"\x01\x03\x00\x00"                   # opcode lists need a DNG 1.3 reader
    with rawpy.imread(str(tmp_path / "out.dng")) as r:
        assert r.camera_whitebalance[:3] == [2.0, 1.0, 1.5] and r.sizes.flip == 6
    np.testing.assert_array_equal(read_dng(tmp_path / "out.dng")[0], dn)


def test_crop_and_opcodes_kept_for_an_odd_active_area(tmp_path):
    # LibRaw starts the visible area of an odd ActiveArea one site later (an even origin); rvnoise reads the whole
    # area, so the crop's and opcodes' coordinates still hold
    src = _single(tmp_path / "aa.dng", _dn(), (50829, "I", 4, (1, 3, 47, 63), True),
                  (50719, "H", 2, (2, 2), True), (51009, "B", len(OPCODES), OPCODES, True))
    dn, pattern, black, white = read_dng(src)
    assert dn.shape == (46, 60)
    write_dng(tmp_path / "out.dng", dn, pattern, black, white, template=src)
    with tifffile.TiffFile(tmp_path / "out.dng") as t:
        assert 50719 in t.pages[0].tags and 51009 in t.pages[0].tags and 50721 in t.pages[0].tags


def test_no_made_up_white_balance(tmp_path):
    src = tmp_path / "nowb.dng"
    tifffile.imwrite(src, _dn(), photometric=32803, metadata=None, subfiletype=0,
                     extratags=[(50706, "B", 4, (1, 4, 0, 0), True)] + _cfa_tags())
    write_dng(tmp_path / "out.dng", *read_dng(src), template=src)
    with tifffile.TiffFile(tmp_path / "out.dng") as t:
        assert 50728 not in t.pages[0].tags


def test_fractional_black_of_per_site_levels_is_written_and_read_back(tmp_path):
    src = _single(tmp_path / "b.dng", _dn(), (50713, "H", 2, (2, 2), True), (50714, "H", 4, (64, 65, 65, 64), True))
    dn, pattern, black, white = read_dng(src)
    assert black == 64.5                                                     # the mean of the four sites
    write_dng(tmp_path / "out.dng", dn, pattern, black, white, template=src)
    assert read_dng(tmp_path / "out.dng")[2] == 64.5


def test_untagged_black_above_zero_is_warned_not_guessed(tmp_path):
    dark = np.full((48, 64), 70, np.uint16)
    dark[::3, ::5] = 900
    with pytest.warns(BlackLevelWarning, match=r"without a BlackLevel tag.*none of its samples is below 1% of white"):
        assert read_dng(_single(tmp_path / "pi.dng", dark))[2] == 0               # the DNG default, not a guess
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_dng(_single(tmp_path / "z.dng", dark - 70))                          # data reaching 0: nothing to say
        read_dng(_single(tmp_path / "t.dng", dark, (50714, "H", 1, 64, True)))    # tagged: the tag holds


def test_rational_black_level_is_read_exactly(tmp_path):
    src = _single(tmp_path / "r.dng", _dn(), (50714, "2I", 1, (1297, 20), True))
    assert read_dng(src)[2] == pytest.approx(64.85)                          # LibRaw alone says 64


@pytest.mark.parametrize("extra,words", [
    (((50714, "H", 1, 60, True), (50715, "2i", 64, tuple(v for i in range(64) for v in (i, 1)), True)),
     r"varies by 63 DN over the frame \(BlackLevel 1×1 \+ BlackLevelDeltaH\)"),
    (((50714, "H", 1, 60, True), (50716, "2i", 48, tuple(v for i in range(48) for v in (i % 2 * 4, 1)), True)),
     r"varies by 4 DN .*BlackLevelDeltaV"),
    (((50713, "H", 2, (4, 4), True), (50714, "H", 16, tuple(range(60, 76)), True)), r"varies by 15 DN .*4×4"),
])
def test_black_levels_varying_by_row_column_or_site_are_refused(tmp_path, extra, words):
    # LibRaw averages the deltas away and reads only the first value of a 4×4 pattern: they would bias the black
    with pytest.raises(InputError, match=words) as err:
        read_dng(_single(tmp_path / "v.dng", _dn(), *extra))
    assert "v.dng" in str(err.value)


def test_small_deltas_are_averaged(tmp_path):
    dh = tuple(v for i in range(64) for v in (i % 2, 2))                    # 0 or ½ DN per column
    assert read_dng(_single(tmp_path / "d.dng", _dn(), (50714, "H", 1, 60, True), (50715, "2i", 64, dh, True)))[2] \
        == 60.25


def test_linearization_table_is_applied_and_not_written(tmp_path):
    dn = _dn()
    table = tuple(min(4095, 2 * i) for i in range(4096))
    src = _single(tmp_path / "lin.dng", dn, (50712, "H", 4096, table, True))
    back = read_dng(src)[0]
    np.testing.assert_array_equal(back, np.minimum(4095, 2 * dn.astype(np.int64)))
    write_dng(tmp_path / "out.dng", back, "RGGB", 0, 4095, template=src)
    with tifffile.TiffFile(tmp_path / "out.dng") as t:
        assert 50712 not in t.pages[0].tags
    np.testing.assert_array_equal(read_dng(tmp_path / "out.dng")[0], back)


def _stripped(path):
    """A tiled raw image whose tiles but the first were removed (as exiftool's sample DNG)."""
    _single(path, _dn(), tile=(16, 16))
    with tifffile.TiffFile(path) as t:
        counts = t.pages[0].tags[325]                                        # TileByteCounts
        fmt = "<" + tifffile.TIFF.DATA_FORMATS[int(counts.dtype)][-1]
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, counts.valueoffset + struct.calcsize(fmt), 0)   # second tile: 0 bytes
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("name,build,words", [
    ("linear.dng", lambda p: tifffile.imwrite(p, np.zeros((32, 32, 3), np.uint16), photometric=34892,
                                              metadata=None, subfiletype=0), "linear DNG: its raw image is already "
     "demosaiced"),
    ("xtrans.dng", lambda p: tifffile.imwrite(p, _dn((48, 60)), photometric=32803, metadata=None, subfiletype=0,
                                              extratags=_cfa_tags(dim=(6, 6), pattern=(1,) * 36)),
     "CFA repeat pattern 6×6"),
    ("float.dng", lambda p: tifffile.imwrite(p, np.zeros((32, 32), np.float32), photometric=32803, metadata=None,
                                             subfiletype=0, extratags=_cfa_tags()), "floating-point DNG"),
    ("deflate.dng", lambda p: tifffile.imwrite(p, _dn(), photometric=32803, metadata=None, subfiletype=0,
                                               compression="zlib", extratags=_cfa_tags()),
     r"compression \d+ \(.*DEFLATE\), which LibRaw cannot decode"),
    ("nocfa.dng", lambda p: tifffile.imwrite(p, _dn(), photometric=32803, metadata=None, subfiletype=0),
     "lacks CFARepeatPatternDim or CFAPattern"),
    ("preview.dng", lambda p: tifffile.imwrite(p, np.zeros((32, 32, 3), np.uint8), photometric="rgb",
                                               metadata=None, subfiletype=1), "holds no raw image"),
    ("bigtiff.dng", lambda p: tifffile.imwrite(p, _dn(), bigtiff=True, photometric=32803, metadata=None,
                                               subfiletype=0, extratags=_cfa_tags()), "BigTIFF DNG"),
    ("stripped.dng", _stripped, r"incomplete raw image: 64×48 px need 12 tiles, the file holds 12 \(1 empty\)"),
])
def test_unusable_dngs_refused_in_words(tmp_path, name, build, words):
    build(tmp_path / name)
    with pytest.raises(InputError, match=words) as err:
        read_dng(tmp_path / name)
    assert name in str(err.value)


@pytest.mark.skipif(not REAL_DNGS.is_dir(), reason="real DNG files (/work/realdata/dng) absent")
@pytest.mark.parametrize("path", sorted(REAL_DNGS.glob("*.dng")) if REAL_DNGS.is_dir() else [],
                         ids=lambda p: p.name)
def test_real_dngs_read_and_write_back_or_fail_in_words(tmp_path, path):
    try:
        dn, pattern, black, white = read_dng(path)
    except InputError as exc:
        assert str(path) in str(exc)
        return
    assert 0 <= black < white and dn.max() > 0                             # not the zeros of missing data
    write_dng(tmp_path / "out.dng", dn, pattern, black, white, template=path)
    back = read_dng(tmp_path / "out.dng")
    np.testing.assert_array_equal(back[0], dn)
    assert back[1:] == (pattern, black, white)
    with rawpy.imread(str(tmp_path / "out.dng")) as r:
        assert r.postprocess(half_size=True).shape[:2] == (dn.shape[0] // 2, dn.shape[1] // 2)
