"""PNG codec for the kinds a camera pipeline reads and writes most: 8/16-bit grey, RGB and RGBA, not interlaced.

Same pixels as OpenCV (libpng), a fraction of its time: the compressed stream is inflated and deflated by ISA-L
(``isal``); the PNG filters are the W3C PNG spec's (§9: None, Sub, Up, Average, Paeth), undone by one compiled pass.
Written files use OpenCV's IDAT chunks (8192 bytes) and, instead of its Sub filter on every row, Sub or Up for the
whole image, whichever leaves fewer non-zero residuals on a sample of rows (issue 19 round 10). Deflate is ISA-L's
level 1 with a 4-byte window (``_HIST_BITS``): matches reach back at most 4 bytes, close to the RLE strategy of
OpenCV's level 1 (zlib: distance 1) — long-distance matches in noise cost more bits than they save — at ≈ 3× the
speed of zlib-ng's RLE (a noisy 1936×1464 snow frame 37 → 12 ms, issue 19 round 23); on the bench frames the files
are within −8 … +9 % of that RLE encoder's (snow +0.02 %, rain −0.3 %, fog −1.2 %, JPEG-compressed −0.7 … −7.5 %,
the smallest +4 … +9 %).

:func:`decode_png` returns None for a kind it does not handle (palette, grey + alpha, bit depths 1–4, Adam7
interlacing, a ``tRNS`` transparency chunk, an animated PNG, an unknown critical chunk): the caller decodes those
with OpenCV. Code values come in the file's channel order (grey, RGB, RGBA), native byte order. The stream is
inflated into the image's size, then to its end in pieces that are dropped: a decompression bomb stays small.
"""

from __future__ import annotations

import sys

import cv2
import numpy as np
from isal import igzip_lib, isal_zlib
from zlib_ng import zlib_ng

from ..physics.compiled import jit
from ..physics.srgb import reversed_rgb

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 6: 4}                  # colour type → samples per pixel (grey, RGB, RGBA)
_COLOUR_TYPE = {v: k for k, v in _CHANNELS.items()}
_OTHER_KIND_CHUNKS = (b"tRNS", b"acTL")        # transparency → an added alpha plane; an animation: OpenCV's
_CRITICAL = (b"IHDR", b"PLTE", b"IDAT", b"IEND")  # the critical chunks a decoder knows (PNG spec §5.6)
_IDAT_BYTES = 8192                              # libpng's (and so OpenCV's) IDAT chunk size
_EXTRA_BYTES = 1 << 20                          # inflated at a time past the image's bytes (then discarded)
_SUB, _UP = 1, 2                                # PNG filter types
_LEVEL, _HIST_BITS = 1, 2                       # ISA-L's deflate level and window (2² bytes back)
_MEM_LEVEL = igzip_lib.MEM_LEVEL_MEDIUM         # its buffer (the Huffman blocks): the sizes of zlib-ng's RLE, level 1
_SAMPLE_ROWS = 16                               # every 16th row decides an image's filter


class PNGError(ValueError):
    """A PNG whose structure or compressed data is damaged."""


def _chunks(data: bytes):
    """``(type, offset of the body, length)`` of each chunk up to IEND; the CRC of IHDR and IDAT is checked."""
    pos = len(PNG_SIGNATURE)
    while pos + 8 <= len(data):
        length, kind = int.from_bytes(data[pos:pos + 4], "big"), data[pos + 4:pos + 8]
        end = pos + 8 + length
        if end + 4 > len(data):
            raise PNGError(f"chunk {kind!r} at byte {pos} runs past the end of the file")
        if kind in (b"IHDR", b"IDAT") and \
                zlib_ng.crc32(memoryview(data)[pos + 4:end]) != int.from_bytes(data[end:end + 4], "big"):
            raise PNGError(f"CRC error in the {kind.decode()} chunk at byte {pos}")
        yield kind, pos + 8, length
        if kind == b"IEND":
            return
        pos = end + 4


def decode_png(data: bytes) -> np.ndarray | None:
    """Code values (H, W) grey or (H, W, 3|4) RGB(A), uint8 or uint16, of a PNG file's bytes; None for a kind this
    codec leaves to OpenCV (module docstring); :class:`PNGError` for a damaged file."""
    if not data.startswith(PNG_SIGNATURE):
        raise PNGError("not a PNG file (bad signature)")
    chunks = _chunks(data)
    kind, pos, length = next(chunks, (None, 0, 0))
    if kind != b"IHDR" or length != 13:
        raise PNGError("the first chunk is not a 13-byte IHDR")
    width, height = int.from_bytes(data[pos:pos + 4], "big"), int.from_bytes(data[pos + 4:pos + 8], "big")
    bit_depth, colour_type, compression, filtering, interlace = data[pos + 8:pos + 13]
    if colour_type not in _CHANNELS or bit_depth not in (8, 16) or (compression, filtering, interlace) != (0, 0, 0):
        return None
    idat = []
    for kind, pos, length in chunks:
        if kind in _OTHER_KIND_CHUNKS or (kind[:1].isupper() and kind not in _CRITICAL):
            return None                             # (an unknown critical chunk: libpng's call)
        if kind == b"IDAT":
            idat.append(memoryview(data)[pos:pos + length])
    channels = _CHANNELS[colour_type]
    pixel_bytes = channels * bit_depth // 8
    row_bytes = width * pixel_bytes
    size = height * (row_bytes + 1)
    inflate = isal_zlib.decompressobj()
    try:                     # the image's bytes, then the rest in 1 MB pieces (a bomb stays small) to the stream's end
        stream = inflate.decompress(b"".join(idat), size)
        while not inflate.eof and inflate.decompress(inflate.unconsumed_tail, _EXTRA_BYTES):
            pass
    except isal_zlib.error as exc:
        raise PNGError(f"corrupt compressed image data ({exc})") from None
    if size == 0 or len(stream) < size:
        raise PNGError(f"not enough image data: {len(stream)} bytes for {height} rows of {width} pixels")
    if not inflate.eof:
        raise PNGError("corrupt compressed image data (the stream stops before its end and checksum)")
    filtered = np.frombuffer(stream, np.uint8).reshape(height, row_bytes + 1)
    out = np.empty((height, row_bytes), np.uint8)
    bad_row = _unfilter(filtered, pixel_bytes, out)
    if bad_row >= 0:
        raise PNGError(f"unknown filter type {filtered[bad_row, 0]} on row {bad_row}")
    if bit_depth == 16:                              # big-endian samples → native, in place
        out = out.view(">u2").byteswap(inplace=True).view(np.uint16) if sys.byteorder == "little" else \
            out.view(np.uint16)
    return out.reshape(height, width, channels) if channels > 1 else out.reshape(height, width)


def encode_png(codes: np.ndarray) -> bytes:
    """PNG bytes of (H, W) grey or (H, W, 3|4) RGB(A) uint8/uint16 code values (any memory layout), every row
    filtered by Sub or by Up, whichever :func:`_filter_type` picks for the image (module docstring)."""
    if codes.dtype not in (np.uint8, np.uint16) or codes.ndim not in (2, 3) or \
            (codes.ndim == 3 and codes.shape[2] not in (3, 4)):
        raise ValueError(f"encode_png takes (H, W) or (H, W, 3|4) uint8/uint16 codes, got {codes.shape} {codes.dtype}")
    height, width = codes.shape[:2]
    channels = 1 if codes.ndim == 2 else codes.shape[2]
    if channels == 3 and reversed_rgb(codes):      # the RGB view of OpenCV's BGR: one fast reorder beats strides
        codes = cv2.cvtColor(codes[..., ::-1], cv2.COLOR_BGR2RGB)
    pixels = np.ascontiguousarray(codes).reshape(height, width, channels)
    if codes.dtype == np.uint16:                    # PNG samples are big-endian: filter the bytes as stored
        pixels = pixels.astype(">u2").view(np.uint8)
    pixel_bytes = pixels.shape[2]
    filtered = np.empty((height, 1 + width * pixel_bytes), np.uint8)
    body = filtered[:, 1:].reshape(height, width, pixel_bytes)
    if _filter_type(pixels) == _UP:                 # Up: byte − the byte above (zero above the first row), mod 256
        filtered[:, 0] = _UP
        body[:1] = pixels[:1]
        np.subtract(pixels[1:], pixels[:-1], out=body[1:])
    else:                                           # Sub: byte − the byte one pixel left, mod 256
        filtered[:, 0] = _SUB if width > 1 else 0  # libpng drops Sub for a one-pixel row: the same bytes, type None
        body[:, :1] = pixels[:, :1]
        np.subtract(pixels[:, 1:], pixels[:, :-1], out=body[:, 1:])
    stream = igzip_lib.compress(filtered, level=_LEVEL, flag=igzip_lib.COMP_ZLIB, mem_level=_MEM_LEVEL,
                                hist_bits=_HIST_BITS)      # its zlib header states a 256-byte window, zlib's least
    header = width.to_bytes(4, "big") + height.to_bytes(4, "big") + \
        bytes([8 * codes.dtype.itemsize, _COLOUR_TYPE[channels], 0, 0, 0])
    view = memoryview(stream)
    parts = [PNG_SIGNATURE, *_chunk(b"IHDR", header)]
    for k in range(0, len(stream), _IDAT_BYTES):
        parts += _chunk(b"IDAT", view[k:k + _IDAT_BYTES])
    parts += _chunk(b"IEND", b"")
    return b"".join(parts)


def _filter_type(pixels: np.ndarray) -> int:
    """Sub or Up for an image (H, W, bytes per pixel): the one that leaves fewer non-zero residuals over every
    ``_SAMPLE_ROWS``-th row (zeros are what the RLE deflate packs; on the bench frames this picks the smaller file
    in 16 of 17 cases, where libpng's sum of |residuals| misses the noisy and smooth photos). Up wins where rows
    repeat (JPEG blocks, streaks, vertical structure), Sub on smooth and noisy rows; Up also undoes faster (no
    dependency along the row)."""
    rows, above = pixels[1::_SAMPLE_ROWS, 1:], pixels[:-1:_SAMPLE_ROWS, 1:]
    if rows.size == 0:
        return _SUB
    sub = np.subtract(rows, pixels[1::_SAMPLE_ROWS, :-1])
    up = np.subtract(rows, above)                   # the same bytes as ``sub``, so the counts compare like with like
    return _UP if np.count_nonzero(up) < np.count_nonzero(sub) else _SUB


def png_chunk(kind: bytes, body: bytes) -> bytes:
    """One PNG chunk: length, type, ``body``, CRC-32 of type and body (PNG spec §5.3)."""
    return b"".join(_chunk(kind, body))


def _chunk(kind: bytes, body) -> tuple:
    """The pieces of a chunk (length and type, the body as given, CRC), to be joined once with the file's others."""
    return len(body).to_bytes(4, "big") + kind, body, zlib_ng.crc32(body, zlib_ng.crc32(kind)).to_bytes(4, "big")


@jit
def _unfilter(filtered: np.ndarray, bpp: int, out: np.ndarray) -> int:
    """Undo the per-row filters (PNG spec §9.2) of ``filtered`` (H, 1 + row bytes) into ``out`` (H, row bytes);
    ``bpp`` is the bytes per complete pixel. Returns the first row with an unknown filter type, else −1. Byte sums
    wrap modulo 256 on the store."""
    height, n = out.shape
    zero = np.zeros(n, np.uint8)                    # the row above the first one
    for y in range(height):
        kind = filtered[y, 0]
        src = filtered[y, 1:]
        row = out[y]
        above = out[y - 1] if y > 0 else zero
        if kind == 0:                               # None
            row[:] = src
        elif kind == 1:                             # Sub: a running sum per byte of the pixel, kept in a register
            for c in range(bpp):
                acc = np.uint8(0)
                for i in range(c, n, bpp):
                    acc = np.uint8(acc + src[i])
                    row[i] = acc
        elif kind == 2:                             # Up
            for i in range(n):
                row[i] = src[i] + above[i]
        elif kind == 3:                             # Average
            for i in range(bpp):
                row[i] = src[i] + (above[i] >> 1)
            for i in range(bpp, n):
                row[i] = src[i] + ((np.int32(row[i - bpp]) + np.int32(above[i])) >> 1)
        elif kind == 4:
            _paeth_row(src, row, above, bpp)
        else:
            return y
    return -1


@jit
def _paeth_row(src: np.ndarray, row: np.ndarray, above: np.ndarray, bpp: int) -> None:
    """Paeth: each byte predicted by the nearest of a (left), b (above), c (above left) to a + b − c, chosen without
    branches (noisy rows mispredict them)."""
    for i in range(bpp):
        row[i] = src[i] + above[i]
    for i in range(bpp, row.size):
        a, b, c = np.int32(row[i - bpp]), np.int32(above[i]), np.int32(above[i - bpp])
        pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - c - c)
        near_bc = b if pb <= pc else c
        nearest = pb if pb <= pc else pc
        row[i] = src[i] + np.uint8(a if pa <= nearest else near_bc)
