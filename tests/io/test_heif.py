"""HEIF/HEIC and AVIF photos (roadview_noise/io/heif.py), on tiny files pillow-heif, Pillow and OpenCV write here:
read as stored with the EXIF orientation their transforms state (as JPEG), written back in the same format with the
ICC profile, EXIF and XMP as read; 10/12-bit HEIF and grey HEIF kept at their depth, a 10/12-bit AVIF written at
8 bits with a warning; a run records the quality, depth and chroma written; without the extra, the refusal names
it."""

from __future__ import annotations

import io
import json

import cv2
import numpy as np
import pytest

pillow_heif = pytest.importorskip("pillow_heif")
from PIL import Image, ImageCms, features  # noqa: E402

from roadview_noise.errors import InputError, RecipeError  # noqa: E402
from roadview_noise.io import heif  # noqa: E402
from roadview_noise.io.image import read_image, write_image  # noqa: E402
from roadview_noise.io.image_metadata import orientation  # noqa: E402
from roadview_noise.physics import transfers  # noqa: E402
from roadview_noise.recipe import parse_recipe  # noqa: E402
from roadview_noise.runner import run  # noqa: E402
from roadview_noise.types import ImageEncoding  # noqa: E402

pillow_heif.register_heif_opener()
FORMATS = [("heic", "HEIF"), pytest.param("avif", "AVIF", marks=pytest.mark.skipif(
    not features.check("avif"), reason="this Pillow has no AVIF support"))]
H, W = 48, 64
SRGB_ICC = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()


def _photo(channels: int = 3) -> np.ndarray:
    """A smooth 8-bit picture with a white block at the top left of the stored pixels (where a turn moves it)."""
    v, u = np.mgrid[0:H, 0:W]
    rgb = np.stack([u * 3, v * 4, (u + v) * 2], axis=-1).astype(np.uint8)
    rgb[:8, :16] = 255
    if channels == 4:
        return np.dstack([rgb, np.where(u < W // 2, 255, 90).astype(np.uint8)])
    return rgb


def _file(fmt: str, pixels: np.ndarray, turn: int = 1) -> bytes:
    exif = Image.Exif()
    exif[271], exif[274] = "rvnoise test", turn
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format=fmt, quality=95, exif=exif.tobytes(), icc_profile=SRGB_ICC)
    return buf.getvalue()


@pytest.mark.parametrize("suffix,fmt", FORMATS)
@pytest.mark.parametrize("channels", [3, 4])
def test_round_trip_keeps_format_pixels_alpha_icc_and_exif(tmp_path, suffix, fmt, channels):
    path = tmp_path / f"a.{suffix}"
    path.write_bytes(_file(fmt, _photo(channels)))
    linear, encoding, alpha = read_image(path)
    assert linear.shape == (H, W, 3) and encoding.fmt == heif.FORMATS[f".{suffix}"]
    assert encoding.channels == channels and (alpha is None) == (channels == 3)
    assert encoding.icc_profile == SRGB_ICC and b"rvnoise test" in encoding.exif
    out = tmp_path / f"out.{suffix}"
    write_image(out, linear, encoding, alpha)
    data = out.read_bytes()
    assert data[4:8] == b"ftyp"
    with Image.open(io.BytesIO(data)) as im:
        assert im.format == fmt and im.size == (W, H) and im.info["icc_profile"] == SRGB_ICC
    again, encoding2, alpha2 = read_image(out)
    assert encoding2.exif == encoding.exif and encoding2.channels == channels
    codes = lambda x: np.round(np.clip(x, 0, 1) ** (1 / 2.2) * 255)      # noqa: E731  close enough to sRGB here
    assert np.abs(codes(again) - codes(linear)).mean() < 3                 # lossy at heif.QUALITY
    if channels == 4:
        assert np.abs(alpha2.astype(int) - alpha.astype(int)).max() <= 3


@pytest.mark.parametrize("suffix,fmt", FORMATS)
def test_a_turned_photo_is_read_as_stored_with_its_orientation_like_a_jpeg(tmp_path, suffix, fmt):
    """pillow-heif turns a HEIF by its irot/imir and sets the EXIF tag to 1; Pillow's AVIF plugin keeps the stored
    pixels with the tag. Both are read as stored with orientation 6 and written so: a viewer shows the output
    turned like the input."""
    path = tmp_path / f"a.{suffix}"
    path.write_bytes(_file(fmt, _photo(), turn=6))
    linear, encoding, _ = read_image(path)
    assert orientation(encoding) == 6 and linear.shape == (H, W, 3)
    assert linear[:8, :16].min() > 0.9 and linear[-8:, -16:].max() < 0.9   # the white block where it was stored
    out = tmp_path / f"out.{suffix}"
    write_image(out, linear, encoding)
    with Image.open(path) as a, Image.open(out) as b:
        assert a.size == b.size                                            # displayed alike (turned or not)
    assert orientation(read_image(out)[1]) == 6


@pytest.mark.parametrize("suffix,fmt", FORMATS)
def test_a_run_processes_it_upright_and_records_the_quality_written(tmp_path, suffix, fmt):
    src = tmp_path / "in/phone"
    src.mkdir(parents=True)
    (src / f"IMG_0001.{suffix}").write_bytes(_file(fmt, _photo(), turn=6))
    recipe = parse_recipe({"chain": [{"model": "rain.camera"}], "seed": 3,
                           "inputs": {"camera": f"**/*.{suffix}", "depth_source": "ground_plane"}})
    summary = run(recipe, tmp_path / "in", tmp_path / "out", progress=False, echo=lambda *_: None, workers=1)
    assert summary.failed == 0 and summary.done == 1
    entry = json.loads((tmp_path / "out/manifest.jsonl").read_text().splitlines()[0])
    assert entry["inputs"]["orientation"] == {"exif": 6, "processed": "upright"}
    assert entry["inputs"]["heif_quality"]["value"] == heif.QUALITY
    with Image.open(tmp_path / f"out/phone/IMG_0001.{suffix}") as im:
        assert im.format == fmt


def test_without_the_extra_the_refusal_names_it(tmp_path, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "pillow_heif", None)      # import pillow_heif fails
    heif._codec.cache_clear()
    try:
        path = tmp_path / "a.heic"
        path.write_bytes(_file("HEIF", _photo()))
        with pytest.raises(InputError, match=r"optional extra heif: pip install 'roadview_noise\[heif\]'"):
            read_image(path)
        with pytest.raises(RecipeError, match=r"roadview_noise\[heif\]"):
            parse_recipe({"chain": [{"model": "compression.camera"}], "inputs": {"camera": "phone/**/*.HEIC"}})
    finally:
        heif._codec.cache_clear()


def test_not_a_heif_file_is_refused_by_name(tmp_path):
    path = tmp_path / "a.heic"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(40))
    with pytest.raises(InputError, match="not a HEIF file"):
        read_image(path)
    path.write_bytes(_file("HEIF", _photo())[:300])
    with pytest.raises(InputError, match="cannot decode this HEIF file"):
        read_image(path)


XMP = b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"/>' \
      b'<!-- rvnoise test --></x:xmpmeta>'


def _ramp(bits: int, h: int = 64, w: int = 96) -> np.ndarray:
    """A smooth (h, w, 3) ramp of ``bits``-bit codes in which every code of channel 0 differs (h · w levels)."""
    y, x = np.mgrid[0:h, 0:w]
    t = (x * h + y) / (w * h - 1)
    return np.rint(np.stack([t, t[::-1, ::-1], 0.25 + 0.5 * t], axis=-1) * (2 ** bits - 1)).astype(np.uint16)


def _heif(codes: np.ndarray, bits: int, **save) -> bytes:
    """A ``bits``-bit HEIF of codes (H, W) grey or (H, W, C) RGB(A) by pillow-heif at quality 90."""
    mode = {2: "L", 3: "RGB", 4: "RGBA"}[codes.ndim if codes.ndim == 2 else codes.shape[2]]
    buf = io.BytesIO()
    pillow_heif.from_bytes(mode + (f";{bits}" if bits > 8 else ""), codes.shape[1::-1],
                           np.ascontiguousarray(codes.astype(np.uint16 if bits > 8 else np.uint8)).tobytes()
                           ).save(buf, quality=90, **save)
    return buf.getvalue()


def _heif_codes(path) -> tuple[np.ndarray, dict]:
    """The codes (file scale) and info of a HEIF at its own depth."""
    f = pillow_heif.open_heif(path, convert_hdr_to_8bit=False, hdr_to_16bit=False)
    return np.asarray(f).astype(np.int64), f.info


@pytest.mark.parametrize("bits,mean_bound", [(10, 0.8), (12, 2.4)])
def test_a_10_and_12_bit_heif_keeps_its_depth_through_an_identity_chain(tmp_path, bits, mean_bound):
    """Read at its depth, carried on 16 bits, written at its depth: the encoder gets the file's decoded codes back,
    so the output is pillow-heif's own re-encode of them, and off the input by the codec's loss at that depth
    (quality 90, 4:4:4: mean 0.54 codes of 1023, 1.6 of 4095). Rounding to 8 bits alone adds a mean 1.0 / 4.0
    codes (the bounds are 0.6 of that); read and written at 8 bits the round trip is off by 2.2 / 8.7 (5.1 / 20.2
    at 4:2:0, as rvnoise ≤ round 23 wrote it)."""
    path, out, direct = tmp_path / "hdr.heic", tmp_path / "out.heic", tmp_path / "direct.heic"
    path.write_bytes(_heif(_ramp(bits), bits, chroma=444, xmp=XMP))
    linear, encoding, _ = read_image(path)
    assert encoding.bit_depth == 16 and dict(encoding.metadata)["bit_depth"] == bits
    write_image(out, linear, encoding)
    before, _ = _heif_codes(path)
    after, info = _heif_codes(out)
    assert info["bit_depth"] == bits and info["chroma"] == 444 and info["xmp"] == XMP
    direct.write_bytes(_heif(before, bits, chroma=444))                    # the codec's own loss, nothing else
    assert np.array_equal(after, _heif_codes(direct)[0])
    error = np.abs(after - before)
    assert error.mean() <= mean_bound and error.max() <= 8 * mean_bound
    assert np.array_equal(heif.rescaled(heif.rescaled(before, 2 ** bits - 1, 65535), 65535, 2 ** bits - 1),
                          before)                                          # the 16-bit carry itself is exact


@pytest.mark.parametrize("bits", [8, 10, 12])
def test_a_grey_heif_is_read_and_written_grey_at_its_depth(tmp_path, bits):
    """pillow-heif reads a monochrome HEIF as L (8 bits) or I;10 / I;12: one channel at its depth, written so
    (a 16-bit grey was refused before round 24: Pillow's plugin gave I;16, which its convert would clip)."""
    grey = _ramp(bits)[..., 0]
    path, out = tmp_path / "grey.heic", tmp_path / "out.heic"
    path.write_bytes(_heif(grey, bits))
    linear, encoding, _ = read_image(path)
    assert encoding.channels == 1 and np.array_equal(linear[..., 0], linear[..., 2])
    write_image(out, linear, encoding)
    before, _ = _heif_codes(path)
    after, info = _heif_codes(out)
    assert after.ndim == 2 and info["bit_depth"] == bits
    assert np.abs(after - before).mean() <= 2 ** (bits - 10) + 0.5


@pytest.mark.parametrize("nclx,curve", [((9, 18, 9), "hlg"), ((1, 1, 1), "bt709")])
def test_a_heif_s_nclx_and_chroma_are_kept(tmp_path, nclx, curve):
    """A 10-bit BT.2100 HLG file (primaries 9, transfer 18, matrix 9) or BT.709 one (1, 1, 1), 4:2:2 as Canon's
    .HIF: its codes decoded by the curve's table (round 24; before: read as sRGB with a warning), written back
    tagged so with its codes."""
    path, out = tmp_path / "IMG_0001.HIF", tmp_path / "out.HIF"
    tags = dict(zip(("color_primaries", "transfer_characteristics", "matrix_coefficients"), nclx))
    path.write_bytes(_heif(_ramp(10), 10, chroma=422, **tags))
    linear, encoding, _ = read_image(path)
    assert encoding.transfer == curve and heif.notes(encoding)[1] == []
    before, _ = _heif_codes(path)
    np.testing.assert_array_equal(linear, transfers.decode_table(curve, 16)[heif.rescaled(before, 1023, 65535)])
    write_image(out, linear, encoding)
    direct = tmp_path / "direct.HIF"                       # the codec's own loss on the file's codes, nothing else
    direct.write_bytes(_heif(before, 10, chroma=422, **tags))
    after, info = _heif_codes(out)
    assert np.array_equal(after, _heif_codes(direct)[0])
    (tmp_path / "linear.heic").write_bytes(_heif(_ramp(10), 10, transfer_characteristics=8))     # linear light
    linear, encoding, _ = read_image(tmp_path / "linear.heic")
    before, _ = _heif_codes(tmp_path / "linear.heic")
    assert encoding.transfer == "linear"
    np.testing.assert_allclose(linear, heif.rescaled(before, 1023, 65535) / np.float32(65535), rtol=1e-6)
    assert info["chroma"] == 422 and info["bit_depth"] == 10
    assert {k: info["nclx_profile"][k] for k in tags} == tags


def test_a_turned_10_bit_heif_is_read_as_stored_and_written_turned(tmp_path):
    exif = Image.Exif()
    exif[274] = 6
    codes = _ramp(10)
    codes[:8, :16] = 1023
    path, out = tmp_path / "a.heic", tmp_path / "out.heic"
    path.write_bytes(_heif(codes, 10, exif=exif.tobytes()))
    linear, encoding, _ = read_image(path)
    assert orientation(encoding) == 6 and linear.shape[:2] == codes.shape[:2]
    assert linear[:8, :16].min() > 0.9                                     # the white block where it was stored
    write_image(out, linear, encoding)
    with Image.open(path) as a, Image.open(out) as b:
        assert a.size == b.size                                            # displayed alike (turned)
    assert orientation(read_image(out)[1]) == 6


@pytest.mark.parametrize("suffix,fmt", FORMATS)
def test_xmp_is_copied(tmp_path, suffix, fmt):
    path, out = tmp_path / f"a.{suffix}", tmp_path / f"out.{suffix}"
    buf = io.BytesIO()
    Image.fromarray(_photo()).save(buf, format=fmt, quality=95, xmp=XMP)
    path.write_bytes(buf.getvalue())
    linear, encoding, _ = read_image(path)
    write_image(out, linear, encoding)
    with Image.open(out) as im:
        assert im.info["xmp"] == XMP
    path.write_bytes(_file(fmt, _photo()))                                 # none: none written
    linear, encoding, _ = read_image(path)
    write_image(out, linear, encoding)
    with Image.open(out) as im:
        assert not im.info.get("xmp")


def _avif10(h: int = 48, w: int = 64) -> bytes:
    """A 10-bit AVIF by OpenCV's libavif (Pillow writes 8 bits only)."""
    ok, buf = cv2.imencode(".avif", _ramp(10, h, w), [cv2.IMWRITE_AVIF_DEPTH, 10, cv2.IMWRITE_AVIF_QUALITY, 90])
    assert ok
    return buf.tobytes()


needs_avif10 = pytest.mark.skipif(not features.check("avif") or not cv2.haveImageWriter(".avif"),
                                  reason="needs Pillow's AVIF plugin and OpenCV's AVIF writer")


@needs_avif10
def test_av1_layout_reads_the_depth_and_chroma_the_file_states():
    assert heif.av1_layout(_avif10()) == (10, 420)
    ok, buf = cv2.imencode(".avif", _ramp(12, 48, 64) * 4, [cv2.IMWRITE_AVIF_DEPTH, 12])
    assert heif.av1_layout(buf.tobytes()) == (12, 420)
    assert heif.av1_layout(_file("AVIF", _photo())) == (8, 420)
    assert heif.av1_layout(b"\x00\x00\x00\x10ftypavif") == (8, None)   # no meta box


@needs_avif10
def test_a_10_bit_avif_is_written_at_8_bits_with_a_warning_not_silently(tmp_path):
    """Pillow's AVIF plugin decodes and encodes 8 bits: the run says so per file and once on its output."""
    src = tmp_path / "in"
    src.mkdir()
    (src / "hdr.avif").write_bytes(_avif10())
    (src / "sdr.avif").write_bytes(_file("AVIF", _photo()))
    recipe = parse_recipe({"chain": [{"model": "rain.camera"}], "seed": 3,
                           "inputs": {"camera": "*.avif", "depth_source": "ground_plane"}})
    lines = []
    summary = run(recipe, src, tmp_path / "out", progress=False, echo=lines.append, workers=1)
    assert summary.failed == 0 and summary.done == 2
    notes = {json.loads(e)["input"]: json.loads(e)["inputs"]
             for e in (tmp_path / "out/manifest.jsonl").read_text().splitlines()}
    assert notes["hdr.avif"]["heif_bit_depth"] == {"value": 8, "file": 10, "from": "Pillow's AVIF plugin codes 8 bits"}
    assert "avif_8bit" in notes["hdr.avif"]["warnings"]
    assert notes["sdr.avif"]["heif_bit_depth"]["value"] == 8 and "avif_8bit" not in notes["sdr.avif"].get("warnings",
                                                                                                         ())
    assert sum("1 AVIF file(s) of 10 or 12 bits per sample read and written at 8 bits" in line for line in lines) == 1
    assert heif.av1_layout((tmp_path / "out/hdr.avif").read_bytes())[0] == 8


def test_codes_that_cannot_be_written_at_the_heif_s_depth_are_refused_by_name(tmp_path):
    """16-bit codes with no HEIF depth to go back to (x265 codes 8, 10 or 12 bits): an error naming the file."""
    encoding = ImageEncoding(fmt="heif", bit_depth=16, channels=3)
    with pytest.raises(OSError, match=r"x\.heic: cannot encode HEIF: uint16 codes cannot be written as a 8-bit HEIF"):
        write_image(tmp_path / "x.heic", np.full((8, 8, 3), 0.5, np.float32), encoding)
    assert not (tmp_path / "x.heic").exists()
    encoding = ImageEncoding(fmt="heif", bit_depth=16, channels=3, metadata=(("bit_depth", 16),))
    with pytest.raises(OSError, match="cannot be written as a 16-bit HEIF"):
        write_image(tmp_path / "x.heic", np.full((8, 8, 3), 0.5, np.float32), encoding)


def test_a_run_records_the_depth_chroma_and_transfer_and_warns_of_a_transfer_read_as_srgb(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    (src / "C0001.heif").write_bytes(_heif(_ramp(10), 10, chroma=422))
    (src / "C0002.heif").write_bytes(_heif(_ramp(12), 12, transfer_characteristics=16))     # PQ
    (src / "C0003.heif").write_bytes(_heif(_ramp(10), 10, transfer_characteristics=7))      # SMPTE 240M
    (src / "C0004.heif").write_bytes(_heif(_ramp(10), 10, transfer_characteristics=4))      # gamma 2.2
    recipe = parse_recipe({"chain": [{"model": "rain.camera"}], "seed": 3,
                           "inputs": {"camera": "*.heif", "depth_source": "ground_plane"}})
    lines = []
    assert run(recipe, src, tmp_path / "out", progress=False, echo=lines.append, workers=1).failed == 0
    notes = {json.loads(e)["input"]: json.loads(e)["inputs"]
             for e in (tmp_path / "out/manifest.jsonl").read_text().splitlines()}
    assert notes["C0001.heif"]["heif_bit_depth"] == {"value": 10, "file": 10, "from": "the file"}
    assert notes["C0001.heif"]["heif_chroma"] == {"value": "4:2:2", "from": "the file"}
    assert "transfer" not in notes["C0001.heif"] and "transfer_read_as_srgb" not in notes["C0001.heif"]["warnings"]
    assert notes["C0002.heif"]["heif_bit_depth"]["value"] == 12 and notes["C0002.heif"]["heif_chroma"]["value"] \
        == "4:2:0"
    assert notes["C0002.heif"]["transfer"] == {"value": "pq", "scale": transfers.TRANSFERS["pq"].scale,
                                               "from": "the file (HEIF nclx transfer 16)"}
    assert "transfer_read_as_srgb" not in notes["C0002.heif"]["warnings"]
    assert notes["C0003.heif"]["transfer"]["file"] == "SMPTE 240M (the file (HEIF nclx transfer 7))"
    assert "transfer_read_as_srgb" in notes["C0003.heif"]["warnings"]
    assert notes["C0004.heif"]["transfer"] == {"value": "gamma22", "scale": transfers.TRANSFERS["gamma22"].scale,
                                               "from": "the file (HEIF nclx transfer 4)"}
    assert "transfer_read_as_srgb" not in notes["C0004.heif"]["warnings"]
    assert sum("1 PNG/HEIF file(s) state a transfer function" in line for line in lines) == 1
    _, info = _heif_codes(tmp_path / "out/C0001.heif")
    assert info["bit_depth"] == 10 and info["chroma"] == 422
    _, info = _heif_codes(tmp_path / "out/C0002.heif")
    assert info["bit_depth"] == 12 and info["nclx_profile"]["transfer_characteristics"] == 16
