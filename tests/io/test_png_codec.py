"""PNG codec (io/png.py): OpenCV's pixels for every PNG kind we accept, OpenCV's file size (within 1 %, or smaller
by the filter choice) when writing, the kinds it leaves to OpenCV, and damaged files."""

from __future__ import annotations

import io
import zlib

import cv2
import numpy as np
import pytest

from roadview_noise.errors import InputError
from roadview_noise.io.image import decode_codes, read_image
from roadview_noise.io.png import decode_png, encode_png

FILTERS = {"none": cv2.IMWRITE_PNG_FILTER_NONE, "sub": cv2.IMWRITE_PNG_FILTER_SUB, "up": cv2.IMWRITE_PNG_FILTER_UP,
           "avg": cv2.IMWRITE_PNG_FILTER_AVG, "paeth": cv2.IMWRITE_PNG_FILTER_PAETH,
           "all": cv2.IMWRITE_PNG_ALL_FILTERS}


def _photo(shape, dtype, seed=0) -> np.ndarray:
    """A smooth gradient with noise (every filter type pays off somewhere), full code range."""
    rng = np.random.default_rng(seed)
    h, w = shape[:2]
    top = np.iinfo(dtype).max
    ramp = np.add.outer(np.linspace(0, 0.6, h), np.linspace(0, 0.4, w))
    if len(shape) == 3:
        ramp = ramp[..., None] * np.linspace(0.7, 1.0, shape[2])
    noisy = ramp * top + rng.normal(0, 0.02 * top, shape)
    img = np.clip(np.rint(noisy), 0, top).astype(dtype)
    img.flat[:2] = [0, top]
    return img


def _opencv_order(codes: np.ndarray) -> np.ndarray:
    """RGB(A) codes in OpenCV's BGR(A) order."""
    if codes.ndim == 2:
        return codes
    return np.ascontiguousarray(codes[..., [2, 1, 0, 3][:codes.shape[2]]])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("filt", sorted(FILTERS))
def test_decode_gives_opencvs_pixels_for_every_filter_and_kind(dtype, channels, filt):
    shape = (37, 53) if channels == 1 else (37, 53, channels)
    bgr = _opencv_order(_photo(shape, dtype))
    for level in (1, 6):
        ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, level, cv2.IMWRITE_PNG_FILTER, FILTERS[filt]])
        ref = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        codes = decode_png(buf.tobytes())
        assert codes is not None and codes.dtype == dtype and codes.flags.c_contiguous
        np.testing.assert_array_equal(_opencv_order(codes), ref)


def test_decode_follows_the_filter_chosen_per_row():
    """Adaptive filtering (OpenCV's ALL_FILTERS) mixes the five types: each row is undone by its own."""
    bgr = _opencv_order(_photo((120, 90, 3), np.uint8, seed=3))
    ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_FILTER,
                                         cv2.IMWRITE_PNG_ALL_FILTERS])
    data = buf.tobytes()
    types = set(zlib.decompress(_idat(data))[::1 + 90 * 3])
    assert len(types) >= 3, types                                   # the test exercises several filter types
    np.testing.assert_array_equal(_opencv_order(decode_png(data)), bgr)


@pytest.mark.parametrize("mode", ["L", "RGB", "RGBA", "I;16"])
@pytest.mark.parametrize("level", [0, 1, 9])
def test_decode_of_another_writer_gives_opencvs_pixels(mode, level):
    """Pillow's own encoder (its filter heuristics, its deflate levels): another writer's streams and row filters."""
    Image = pytest.importorskip("PIL.Image")
    dtype = np.uint16 if mode == "I;16" else np.uint8
    shape = (45, 66) if mode in ("L", "I;16") else (45, 66, len(mode))
    codes = _photo(shape, dtype, seed=level)
    buf = io.BytesIO()
    Image.fromarray(codes).save(buf, format="PNG", compress_level=level)
    data = buf.getvalue()
    colour_type = {"L": 0, "I;16": 0, "RGB": 2, "RGBA": 6}[mode]
    assert data[24:26] == bytes([8 * np.dtype(dtype).itemsize, colour_type])     # IHDR: the kind we asked for
    ref = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(_opencv_order(decode_png(data)), ref)
    np.testing.assert_array_equal(decode_png(data), codes)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_encode_has_opencvs_pixels_and_size(dtype, channels):
    shape = (64, 81) if channels == 1 else (64, 81, channels)
    codes = _photo(shape, dtype, seed=channels)
    data = encode_png(codes)
    ok, ref = cv2.imencode(".png", _opencv_order(codes))                    # OpenCV's default settings
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED),
                                  _opencv_order(codes))
    assert abs(len(data) - ref.size) <= 0.01 * ref.size, (len(data), ref.size)
    assert data == encode_png(codes.copy())                                  # deterministic



def test_encode_of_a_noisy_photo_is_no_larger_than_opencvs():
    """A frame with σ = 2 codes of sensor noise (bench/run.py's photo-like frames): the deflate's 4-byte window keeps
    the file at OpenCV's size (ISA-L's default 32 KB window spends bits on far matches in the noise: +12 % here)."""
    rng = np.random.default_rng(5)
    h, w = 256, 384
    ramp = np.add.outer(np.linspace(30, 200, h), np.linspace(0, 40, w))[..., None] * np.array([0.8, 1.0, 0.9])
    codes = np.clip(np.rint(ramp + rng.normal(0, 2, (h, w, 3))), 0, 255).astype(np.uint8)
    data = encode_png(codes)
    ok, ref = cv2.imencode(".png", _opencv_order(codes))
    np.testing.assert_array_equal(decode_png(data), codes)
    assert len(data) <= 1.01 * ref.size, (len(data), ref.size)

def _filter_types(data: bytes, row_bytes: int) -> set[int]:
    """The filter types of a PNG's rows (its IDAT inflated)."""
    chunks, pos = [], 8
    while pos < len(data):
        n = int.from_bytes(data[pos:pos + 4], "big")
        if data[pos + 4:pos + 8] == b"IDAT":
            chunks.append(data[pos + 8:pos + 8 + n])
        pos += 12 + n
    rows = np.frombuffer(zlib.decompress(b"".join(chunks)), np.uint8).reshape(-1, 1 + row_bytes)
    return set(rows[:, 0].tolist())


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_encode_filters_by_up_where_rows_repeat_and_by_sub_where_rows_are_smooth(dtype):
    """Rows that repeat the row above (8-row blocks, as a JPEG leaves them) get Up, rows smooth along themselves
    get Sub; the Up file is smaller than OpenCV's Sub-only one, both decode to the codes."""
    rng = np.random.default_rng(3)
    top = np.iinfo(dtype).max
    blocks = np.repeat(rng.integers(0, top, (8, 96, 3), dtype=dtype), 8, axis=0)       # 64 rows, 8 repeats each
    smooth = np.broadcast_to(rng.integers(0, top, (64, 1, 3), dtype=dtype), (64, 96, 3)).copy()
    for codes, kind in ((blocks, 2), (smooth, 1)):
        data = encode_png(codes)
        assert _filter_types(data, 96 * 3 * codes.itemsize) == {kind}
        np.testing.assert_array_equal(decode_png(data), codes)
        np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED),
                                      _opencv_order(codes))
    ok, sub_only = cv2.imencode(".png", _opencv_order(blocks))
    assert len(encode_png(blocks)) < 0.5 * sub_only.size


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 40, 3), (40, 1, 3), (3, 2), (200, 150, 4)])
def test_encode_round_trips_odd_shapes_and_layouts(shape):
    codes = _photo(shape, np.uint8, seed=7)
    np.testing.assert_array_equal(decode_png(encode_png(codes)), codes)
    if codes.ndim == 3 and codes.shape[2] == 3:
        bgr = np.ascontiguousarray(codes[..., ::-1])
        assert encode_png(bgr[..., ::-1]) == encode_png(codes)               # the RGB view of BGR storage
        assert encode_png(np.asfortranarray(codes)) == encode_png(codes)


def test_encode_refuses_other_sample_types():
    with pytest.raises(ValueError, match="uint8/uint16"):
        encode_png(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError, match="uint8/uint16"):
        encode_png(np.zeros((4, 4, 2), np.uint8))


@pytest.mark.parametrize("extra", [b"gAMA", b"sBIT", b"sRGB+gAMA"])
def test_colour_chunks_opencv_ignores_are_ignored(extra):
    """IMREAD_UNCHANGED applies no gamma, significant-bits shift or rendering intent: nor does the codec."""
    bodies = {b"gAMA": (100000).to_bytes(4, "big"), b"sBIT": bytes([5, 6, 5]), b"sRGB": b"\x00"}
    codes = _photo((20, 30, 3), np.uint8, seed=9)
    data = encode_png(codes)
    added = b"".join(_chunk(k, bodies[k]) for k in extra.split(b"+"))
    data = data[:33] + added + data[33:]                                     # after the 25-byte IHDR chunk
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED),
                                  _opencv_order(codes))
    np.testing.assert_array_equal(decode_png(data), codes)


# --- the kinds left to OpenCV ------------------------------------------------------------------------------------


def _pillow_png(mode: str, **save) -> bytes:
    Image = pytest.importorskip("PIL.Image")
    rgb = _photo((29, 31, 3), np.uint8, seed=11)
    img = Image.fromarray(rgb)
    img = img.convert(mode) if mode not in ("P",) else img.quantize(17)
    buf = io.BytesIO()
    img.save(buf, format="PNG", **save)
    return buf.getvalue()


def _interlaced_png(rgb: np.ndarray) -> bytes:
    """An 8-bit RGB Adam7-interlaced PNG (PNG spec §8.2), every pass row with filter type None."""
    passes = [(0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)]
    raw = b""
    for x0, y0, dx, dy in passes:
        sub = rgb[y0::dy, x0::dx]
        if sub.size:
            raw += b"".join(b"\x00" + row.tobytes() for row in sub)
    h, w = rgb.shape[:2]
    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8, 2, 0, 0, 1])
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b"")


@pytest.mark.parametrize("kind", ["palette", "palette+tRNS", "grey+alpha", "1-bit", "rgb+tRNS", "interlaced"])
def test_other_kinds_are_decoded_by_opencv(kind):
    if kind == "interlaced":
        data = _interlaced_png(_photo((21, 19, 3), np.uint8, seed=4))
    else:
        mode, save = {"palette": ("P", {}), "palette+tRNS": ("P", {"transparency": 3}), "grey+alpha": ("LA", {}),
                      "1-bit": ("1", {}), "rgb+tRNS": ("RGB", {"transparency": (10, 20, 30)})}[kind]
        data = _pillow_png(mode, **save)
    assert decode_png(data) is None
    ref = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    codes = decode_codes(data, "png", source="x.png")
    np.testing.assert_array_equal(_opencv_order(codes), ref)


def test_an_unknown_critical_chunk_is_left_to_opencv():
    """A decoder must not decode past a critical chunk it does not know (PNG spec §5.4): libpng refuses the file."""
    data = encode_png(_photo((8, 8, 3), np.uint8))
    data = data[:33] + _chunk(b"ZZZZ", b"\x00") + data[33:]
    assert decode_png(data) is None
    with pytest.raises(InputError, match="OpenCV cannot decode") as err:
        decode_codes(data, "png", source="odd.png")
    assert "odd.png" in str(err.value)


# --- damaged files -----------------------------------------------------------------------------------------------


def _chunk(kind: bytes, body: bytes) -> bytes:
    return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")


def _idat(data: bytes) -> bytes:
    out, pos = b"", 8
    while pos < len(data):
        n = int.from_bytes(data[pos:pos + 4], "big")
        if data[pos + 4:pos + 8] == b"IDAT":
            out += data[pos + 8:pos + 8 + n]
        pos += 12 + n
    return out


def _rebuilt(data: bytes, stream: bytes) -> bytes:
    """``data`` with its image data replaced by one IDAT chunk holding ``stream``."""
    ihdr_end = 8 + 25
    return data[:ihdr_end] + _chunk(b"IDAT", stream) + _chunk(b"IEND", b"")


def test_a_stream_longer_than_the_image_is_inflated_only_as_far_as_the_image():
    """libpng stops at the last row; so does the codec: 60 MB of zeros behind 16×12 pixels cost no memory."""
    import tracemalloc

    codes = _photo((16, 12, 3), np.uint8)
    rows = zlib.decompress(_idat(encode_png(codes)))
    data = _rebuilt(encode_png(codes), zlib.compress(rows + bytes(60_000_000), 9))
    tracemalloc.start()
    try:
        decoded = decode_png(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(decoded, codes)
    assert peak < 2_000_000, peak


@pytest.mark.parametrize("damage, match", [
    ("crc", "CRC error in the IDAT"),
    ("stream", "corrupt compressed image data"),
    ("short", "not enough image data"),
    ("filter", "unknown filter type 7 on row 5"),
])
def test_damaged_files_raise_naming_the_file(tmp_path, damage, match):
    codes = _photo((16, 12, 3), np.uint8)
    data = encode_png(codes)
    raw = bytearray(zlib.decompress(_idat(data)))
    if damage == "crc":
        pos = data.index(b"IDAT") + 10
        data = data[:pos] + bytes([data[pos] ^ 1]) + data[pos + 1:]
    elif damage == "stream":
        data = _rebuilt(data, zlib.compress(bytes(raw))[:-30] + b"\x00" * 30)
    elif damage == "short":
        data = _rebuilt(data, zlib.compress(bytes(raw[:-40])))
    else:
        raw[5 * (1 + 12 * 3)] = 7
        data = _rebuilt(data, zlib.compress(bytes(raw)))
    path = tmp_path / "damaged.png"
    path.write_bytes(data)
    with pytest.raises(InputError, match=match) as err:
        read_image(path)
    assert "damaged.png" in str(err.value)
