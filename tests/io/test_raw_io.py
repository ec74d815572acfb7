"""Raw Bayer I/O: DNG written with tifffile and read back by LibRaw, plain .raw + YAML sidecar, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import rawpy
import tifffile
import yaml

from roadview_noise.errors import InputError
from roadview_noise.io.raw import read_dng, read_plain_raw, read_raw, write_dng, write_plain_raw, write_raw
from roadview_noise.types import CFA_PATTERNS, RawEncoding, cfa_index_map


def _dn(shape=(48, 64), top=65536, seed=0):
    return np.random.default_rng(seed).integers(0, top, shape, dtype=np.uint16)


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_dng_roundtrip_every_pattern(tmp_path, pattern):
    dn = _dn()
    write_dng(tmp_path / "f.dng", dn, pattern, 512, 65535)
    back, pat, black, white = read_dng(tmp_path / "f.dng")
    assert (pat, black, white) == (pattern, 512.0, 65535.0)
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, dn)
    with rawpy.imread(str(tmp_path / "f.dng")) as raw:      # LibRaw's own colour map agrees site by site
        desc = raw.color_desc.decode()
        colours = np.array(["RGB".index(desc[c]) for c in raw.raw_colors_visible.ravel()]).reshape(dn.shape)
    np.testing.assert_array_equal(colours, cfa_index_map(pattern, *dn.shape))


def test_dng_12bit_levels_and_float_input(tmp_path):
    dn = _dn(top=4096).astype(np.float32) + 0.4
    dn[0, :3] = [-7.0, 70000.0, 2.5]                          # clipped to uint16, rounded half to even
    write_dng(tmp_path / "g.dng", dn, "GRBG", 64, 4095)
    back, pat, black, white = read_dng(tmp_path / "g.dng")
    assert (pat, black, white) == ("GRBG", 64.0, 4095.0)
    np.testing.assert_array_equal(back, np.clip(np.rint(dn), 0, 65535).astype(np.uint16))
    assert back[0, :3].tolist() == [0, 65535, 2]


def test_dng_rejects_spread_black_levels(tmp_path):
    dn = _dn()
    tags = [(33421, "H", 2, (2, 2), True), (33422, "B", 4, bytes([0, 1, 1, 2]), True),
            (50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "test", True),
            (50713, "H", 2, (2, 2), True), (50714, "I", 4, (500, 504, 508, 512), True),
            (50717, "I", 1, 65535, True),
            (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True)]
    tifffile.imwrite(tmp_path / "b.dng", dn, photometric=32803, extratags=tags, metadata=None, subfiletype=0)
    with pytest.raises(InputError, match="black level varies by 12 DN") as err:
        read_dng(tmp_path / "b.dng")
    assert "b.dng" in str(err.value)


def test_dng_writer_refuses_frames_libraw_cannot_read(tmp_path):
    with pytest.raises(ValueError, match="at least 22 px"):
        write_dng(tmp_path / "small.dng", _dn(shape=(21, 64)), "RGGB", 0, 65535)
    with pytest.raises(ValueError, match="integer"):
        write_dng(tmp_path / "frac.dng", _dn(), "RGGB", 64, 4095.5)
    with pytest.raises(ValueError, match="0…65535"):
        write_dng(tmp_path / "neg.dng", _dn(), "RGGB", -1, 65535)


def test_dng_bad_files(tmp_path):
    write_dng(tmp_path / "t.dng", _dn(), "RGGB", 0, 65535)
    data = (tmp_path / "t.dng").read_bytes()
    (tmp_path / "t.dng").write_bytes(data[: len(data) // 2])
    (tmp_path / "junk.dng").write_bytes(b"hello" * 50)
    for name, words in (("t.dng", "truncated DNG: its image data ends at byte"),
                        ("junk.dng", "corrupt or truncated DNG"), ("missing.dng", "No such file")):
        with pytest.raises(InputError, match=words) as err:
            read_dng(tmp_path / name)
        assert name in str(err.value)


def test_plain_raw_roundtrip_and_sidecar(tmp_path):
    dn = _dn(shape=(7, 9))
    write_plain_raw(tmp_path / "p.raw", dn, "BGGR", 256.0, 16383.0)
    assert (tmp_path / "p.raw").stat().st_size == 7 * 9 * 2
    assert yaml.safe_load((tmp_path / "p.yaml").read_text()) == {
        "width": 9, "height": 7, "dtype": "uint16", "byte_order": "little", "cfa_pattern": "BGGR",
        "black_level_dn": 256.0, "white_level_dn": 16383.0}
    back, pat, black, white = read_plain_raw(tmp_path / "p.raw")
    np.testing.assert_array_equal(back, dn)
    assert (pat, black, white) == ("BGGR", 256.0, 16383.0)


def test_plain_raw_big_endian(tmp_path):
    dn = _dn(shape=(4, 6))
    (tmp_path / "be.raw").write_bytes(dn.astype(">u2").tobytes())
    (tmp_path / "be.yaml").write_text(yaml.safe_dump({
        "width": 6, "height": 4, "dtype": "uint16", "byte_order": "big", "cfa_pattern": "RGGB",
        "black_level_dn": 0, "white_level_dn": 65535}))
    np.testing.assert_array_equal(read_plain_raw(tmp_path / "be.raw")[0], dn)


def test_plain_raw_written_back_like_its_sidecar(tmp_path):
    """A big-endian frame with a user's keys: written back big-endian with the same sidecar (it was written
    little-endian, the extra keys dropped and 64 turned into 64.0); a changed level is written as a float."""
    dn = _dn(shape=(4, 6))
    (tmp_path / "be.raw").write_bytes(dn.astype(">u2").tobytes())
    sidecar = ("exposure_s: 0.01\nwidth: 6\nheight: 4\ndtype: uint16\nbyte_order: big\ncfa_pattern: RGGB\n"
               "black_level_dn: 64\nwhite_level_dn: 4095\ntimestamp_ns: 1532402927612460000\n")
    (tmp_path / "be.yaml").write_text(sidecar)
    back, pattern, black, white, encoding = read_raw(tmp_path / "be.raw")
    write_raw(tmp_path / "out.raw", back, pattern, black, white, encoding)
    assert (tmp_path / "out.raw").read_bytes() == (tmp_path / "be.raw").read_bytes()
    assert (tmp_path / "out.yaml").read_text() == sidecar
    write_raw(tmp_path / "new.raw", back, pattern, 60.5, white, encoding)
    assert "black_level_dn: 60.5\nwhite_level_dn: 4095\n" in (tmp_path / "new.yaml").read_text()


@pytest.mark.parametrize("fmt,name", [("dng", "r.dng"), ("raw", "r.raw")])
def test_read_raw_write_raw_dispatch(tmp_path, fmt, name):
    dn = _dn(shape=(24, 30))
    write_raw(tmp_path / name, dn, "GBRG", 16, 1023, RawEncoding(fmt=fmt))
    back, pat, black, white, enc = read_raw(tmp_path / name)
    np.testing.assert_array_equal(back, dn)
    assert (pat, black, white, enc.fmt) == ("GBRG", 16.0, 1023.0, fmt)


def test_plain_raw_errors(tmp_path):
    dn = _dn(shape=(4, 6))
    (tmp_path / "nos.raw").write_bytes(dn.tobytes())
    with pytest.raises(InputError, match="sidecar nos.yaml") as err:
        read_plain_raw(tmp_path / "nos.raw")
    assert "nos.raw" in str(err.value)

    write_plain_raw(tmp_path / "s.raw", dn, "RGGB", 0, 4095)
    (tmp_path / "s.raw").write_bytes(dn.tobytes()[:-2])
    with pytest.raises(InputError, match="46 bytes.*6×4 uint16 = 48 bytes") as err:
        read_plain_raw(tmp_path / "s.raw")
    assert "s.raw" in str(err.value)

    meta = yaml.safe_load((tmp_path / "s.yaml").read_text())
    meta.update(cfa_pattern="RGBW", dtype="float32")
    del meta["white_level_dn"]
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(InputError, match="lacks.*white_level_dn"):
        read_plain_raw(tmp_path / "s.raw")
    meta["white_level_dn"] = 4095
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(InputError, match="dtype 'float32'.*cfa_pattern 'RGBW'"):
        read_plain_raw(tmp_path / "s.raw")

    with pytest.raises(InputError, match="unknown raw suffix"):
        read_raw(tmp_path / "x.cr2")


def test_dng_template_metadata_is_copied(tmp_path):
    dn = _dn(shape=(32, 40), top=4096)
    colour = (7, 10, -2, 10, -1, 10, -4, 10, 12, 10, 1, 10, -1, 10, 2, 10, 6, 10)
    tags = [(33421, "H", 2, (2, 2), True), (33422, "B", 4, bytes([0, 1, 1, 2]), True),
            (50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "Cam X", True), (271, "s", 0, "Maker", True),
            (272, "s", 0, "Model 1", True), (274, "H", 1, 6, True), (50714, "I", 1, 64, True),
            (50717, "I", 1, 4095, True), (50721, "2i", 9, colour, True), (50728, "2I", 3, (1, 2, 1, 1, 2, 3), True),
            (50778, "H", 1, 17, True)]
    tifffile.imwrite(tmp_path / "src.dng", dn, photometric=32803, extratags=tags, metadata=None, subfiletype=0)
    write_raw(tmp_path / "out.dng", dn, "RGGB", 64, 4095, RawEncoding("dng"), template=tmp_path / "src.dng")
    with tifffile.TiffFile(tmp_path / "src.dng") as a, tifffile.TiffFile(tmp_path / "out.dng") as b:
        for code in (271, 272, 274, 50708, 50721, 50728, 50778):
            assert a.pages[0].tags[code].value == b.pages[0].tags[code].value, code
    with rawpy.imread(str(tmp_path / "src.dng")) as a, rawpy.imread(str(tmp_path / "out.dng")) as b:
        assert a.camera_whitebalance == b.camera_whitebalance and a.sizes.flip == b.sizes.flip == 6
    back, pattern, black, white = read_dng(tmp_path / "out.dng")
    np.testing.assert_array_equal(back, dn)
    assert (pattern, black, white) == ("RGGB", 64.0, 4095.0)
