"""Relative luminance of camera frames box-filtered at the camera metrics' scale (:mod:`roadview_noise.metrics`),
in a read of its own or inside the 8-bit sRGB passes that touch every pixel of a frame anyway.

Y = 0.2126 R + 0.7152 G + 0.0722 B of linear RGB (sRGB / Rec. 709 primaries), averaged over f×f blocks, f the
smallest integer that leaves ≤ 65 536 blocks (:func:`metric_scale`; edge rows/columns that do not fill a block are
left out). Per block and channel the f values of each column are summed first (float32, rows in order), then the
f column sums: every path here — a float frame, 8-bit codes, the decode and encode passes — rounds the same, so
its blocks are bit for bit those of :func:`luminance_area` of the frame's linear values.

While :func:`collect` is on (the runner, for a recipe with metrics), ``physics.srgb`` hands its 8-bit decode
(codes → linear: a file read, a JPEG output read by a later step) and encode (linear → codes: the writer, JPEG
compression) of an (H, W, 3) frame to :class:`SidePass`, which does the same pass and sums the blocks in it — an
encode only for a linear array the metrics asked for (:func:`want`) — and :func:`blocks_of` finds them by the
linear array: the metrics then read no full frame of their own for it. The decoded or encoded values are those of
the plain passes; the linear array is made read-only (its blocks can never go stale; a decoded one is already).
Off (the default), the passes are the plain ones.
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from .physics import srgb
from .physics.compiled import jit
from .physics.srgb import (_BYTE_SHIFTS, _encode8_kernel, _encode8_reversed_kernel, _look_up, _look_up_reversed,
                           decode_table, encode8_table, reversed_rgb)

MAX_METRIC_PIXELS = 1 << 16                 # ≈ 256 × 256, Wang et al.'s SSIM scale
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)  # sRGB / Rec. 709 primaries
RGB, BGR = np.arange(3), np.arange(3)[::-1].copy()   # memory channel of R, G, B

_BLOCKS: dict[int, tuple[weakref.ref, int, np.ndarray]] = {}   # id(linear) → (its weakref, f, blocks)
_WANTED: dict[int, tuple[weakref.ref]] = {}                      # id(linear) → (its weakref,): encode with blocks


def metric_scale(height_px: int, width_px: int) -> int:
    """Integer box-filter factor of the camera metrics: the smallest that leaves ≤ 65 536 pixels."""
    f = max(1, math.ceil(math.sqrt(height_px * width_px / MAX_METRIC_PIXELS)))
    while (height_px // f) * (width_px // f) > MAX_METRIC_PIXELS:
        f += 1
    return f


def _weights() -> np.ndarray:
    return np.asarray(LUMINANCE_WEIGHTS, np.float32)


def luminance_area(rgb: np.ndarray, f: int) -> np.ndarray:
    """Relative luminance of (H, W, 3) linear RGB box-filtered by f×f and decimated (float32; module doc), in one
    read of the frame. The float32 rounding differs from OpenCV's area resize then ``cv2.transform`` by a few
    ulp."""
    h, w = rgb.shape[0] // f, rgb.shape[1] // f
    out = np.empty((h, w), np.float32)
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    _luminance_area(rgb.reshape(rgb.shape[0], -1), f, _weights(), out)
    return out


def codes_luminance_area(codes: np.ndarray, f: int) -> np.ndarray:
    """:func:`luminance_area` of the linear decoding (``srgb.code_to_linear``) of 8-bit sRGB codes (H, W, 3) RGB,
    possibly OpenCV's BGR seen channel-reversed, bit for bit, in one read of the codes (a quarter of the bytes of
    the decoded frame, and no decode)."""
    h, w = codes.shape[0] // f, codes.shape[1] // f
    out = np.empty((h, w), np.float32)
    if reversed_rgb(codes):
        codes, channel = codes[..., ::-1], BGR
    else:
        codes, channel = np.ascontiguousarray(codes), RGB
    rows = codes.reshape(codes.shape[0], codes.shape[1] * 3)
    words = np.ndarray((rows.shape[0], rows.shape[1] // 4), np.uint32, rows, 0, (rows.strides[0], 4))
    _codes_luminance_area(rows, words, f, decode_table(8), channel, _weights(), out)
    return out


def blocks_of(linear: np.ndarray, f: int) -> np.ndarray | None:
    """The f×f luminance blocks an sRGB pass kept for this very (read-only) linear array, else None."""
    item = _BLOCKS.get(id(linear))
    if item is None or item[0]() is not linear or item[1] != f or linear.flags.writeable:
        return None
    return item[2]


def want(linear: np.ndarray) -> None:
    """Ask for the blocks of this linear array when an 8-bit encode passes over it (while collecting)."""
    _WANTED[id(linear)] = (_ref(linear, _WANTED),)


def _wanted(linear: np.ndarray) -> bool:
    item = _WANTED.get(id(linear))
    return item is not None and item[0]() is linear


def _keep(linear: np.ndarray, f: int, blocks: np.ndarray) -> None:
    linear.flags.writeable = False
    _BLOCKS[id(linear)] = (_ref(linear, _BLOCKS), f, blocks)


def _ref(linear: np.ndarray, registry: dict) -> weakref.ref:
    """A weak reference to ``linear`` that removes its entry (keyed by id, the reference first) from ``registry``
    when it dies."""
    key = id(linear)

    def forget(ref):
        if registry.get(key, (None,))[0] is ref:
            del registry[key]

    return weakref.ref(linear, forget)


def collect(on: bool) -> None:
    """Have the 8-bit sRGB passes of frames keep their luminance blocks (``on``), or not (module doc)."""
    srgb.side_pass = SidePass if on else None


class SidePass:
    """The 8-bit sRGB passes of ``physics.srgb`` with the luminance blocks (``srgb.side_pass`` while collecting).
    Each returns False, having done nothing, for what is not an (H, W, 3) frame of the expected layout."""

    @staticmethod
    def decode8(code: np.ndarray, out: np.ndarray) -> bool:
        """``out`` (float32, C order) = the decoding of 8-bit ``code`` (H, W, 3) RGB or its BGR view."""
        if code.ndim != 3 or code.shape[2] != 3 or not out.flags.c_contiguous:
            return False
        reverse = reversed_rgb(code)
        if reverse:
            code = code[..., ::-1]
        elif not code.flags.c_contiguous:
            return False
        f = metric_scale(*code.shape[:2])
        blocks = np.empty((code.shape[0] // f, code.shape[1] // f), np.float32)
        _decode8_blocks(code.reshape(code.shape[0], -1), reverse, decode_table(8), f, _weights(),
                        out.reshape(out.shape[0], -1), blocks)
        _keep(out, f, blocks)
        return True

    @staticmethod
    def encode8(linear: np.ndarray, out: np.ndarray, bgr: bool) -> bool:
        """``out`` (uint8, C order) = the 8-bit codes of float32 ``linear`` (H, W, 3) RGB, in BGR order if ``bgr``,
        when ``linear`` is wanted (:func:`want`)."""
        if not _wanted(linear) or linear.ndim != 3 or linear.shape[2] != 3 \
                or linear.dtype != np.float32 or not linear.flags.c_contiguous:
            return False
        f = metric_scale(*linear.shape[:2])
        blocks = np.empty((linear.shape[0] // f, linear.shape[1] // f), np.float32)
        _encode8_blocks(linear.reshape(linear.shape[0], -1), linear.reshape(-1).view(np.uint32), bgr,
                        *encode8_table(), f, _weights(), out.reshape(-1), blocks)
        _keep(linear, f, blocks)
        return True


@jit
def _strip_luminance(rows, i, f, acc, channel, weights, out_row):       # pragma: no cover - compiled
    """A row of blocks ``out_row`` from rows i … i + f − 1 of a float32 frame (H, W·3): the column sums ``acc`` of
    the f rows in order, then the blocks' luminance."""
    last = i + f - 1
    if f >= 4:                              # three rows per pass over acc: a third of its loads and stores
        _sum4(acc, rows[i], rows[i + 1], rows[i + 2], rows[i + 3])
        i += 3
    else:
        acc[:] = rows[i, :acc.shape[0]]
    while i + 3 <= last:
        _add3_to(acc, rows[i + 1], rows[i + 2], rows[i + 3])
        i += 3
    while i < last:
        i += 1
        _add_to(acc, rows[i])
    _block_luminance(acc, f, channel, weights, out_row)


@jit
def _add_to(acc, row):       # pragma: no cover - compiled
    """acc += row[:len(acc)] (a function of its own: inlined into the passes, the loop is not vectorised)."""
    for j in range(acc.shape[0]):
        acc[j] += row[j]


@jit
def _sum4(acc, a, b, c, d):       # pragma: no cover - compiled
    """acc = ((a + b) + c) + d over acc's length (float32, in this order)."""
    for j in range(acc.shape[0]):
        acc[j] = ((a[j] + b[j]) + c[j]) + d[j]


@jit
def _add3_to(acc, a, b, c):       # pragma: no cover - compiled
    """acc = ((acc + a) + b) + c over acc's length (float32, in this order: three :func:`_add_to` in one pass)."""
    for j in range(acc.shape[0]):
        acc[j] = ((acc[j] + a[j]) + b[j]) + c[j]


@jit
def _luminance_area(rows, f, weights, out):                   # pragma: no cover - compiled
    acc = np.empty(out.shape[1] * f * 3, np.float32)
    channel = np.arange(3)
    for b in range(out.shape[0]):
        _strip_luminance(rows, b * f, f, acc, channel, weights, out[b])


@jit
def _decode8_blocks(codes, reverse, table, f, weights, out, blocks):   # pragma: no cover - compiled
    """``out`` (H, W·3 RGB) = ``table`` of the 8-bit ``codes`` (H, W·3 in memory order; BGR if ``reverse``), and
    its luminance blocks; f rows at a time, summed while in cache."""
    acc = np.empty(blocks.shape[1] * f * 3, np.float32)
    rgb = np.arange(3)
    for b in range(blocks.shape[0] + 1):
        for i in range(b * f, out.shape[0] if b == blocks.shape[0] else (b + 1) * f):
            if reverse:
                _look_up_reversed(codes[i], table, out[i])
            else:
                _look_up(codes[i], table, out[i])
        if b < blocks.shape[0]:
            _strip_luminance(out, b * f, f, acc, rgb, weights, blocks[b])


@jit
def _encode8_blocks(rows, xbits, reverse, table, levels, f, weights, out, blocks):   # pragma: no cover
    """``out`` (flat) = the 8-bit codes of the float32 frame ``rows`` (H, W·3 RGB; ``xbits`` its flat bit
    patterns), BGR if ``reverse``, and its luminance blocks; f rows at a time, summed while in cache."""
    acc = np.empty(blocks.shape[1] * f * 3, np.float32)
    rgb = np.arange(3)
    n = rows.shape[1]
    for b in range(blocks.shape[0] + 1):
        start, stop = b * f * n, (rows.shape[0] if b == blocks.shape[0] else (b + 1) * f) * n
        if reverse:                             # the rows' values two at a time, as srgb.linear_to_code reads them
            part = xbits[start:stop]
            _encode8_reversed_kernel(part, part[:part.size // 2 * 2].view(np.uint64), out[start:stop], table, levels)
        else:
            _encode8_kernel(xbits[start:stop], out[start:stop], table, levels)
        if b < blocks.shape[0]:
            _strip_luminance(rows, b * f, f, acc, rgb, weights, blocks[b])


@jit
def _codes_luminance_area(rows, words, f, table, channel, weights, out):   # pragma: no cover - compiled
    """:func:`codes_luminance_area` of the codes ``rows`` (H, W·3 in memory order), ``words`` the same rows read
    four codes at a time (uint32, possibly unaligned)."""
    n = out.shape[1] * f * 3
    acc = np.empty(n, np.float32)
    for i in range(out.shape[0]):
        _column_sums(words, i * f, f, table, acc)
        for x in range(n // 8 * 8, n):                      # the last columns, one code at a time
            s = table[rows[i * f, x]]
            for k in range(1, f):
                s += table[rows[i * f + k, x]]
            acc[x] = s
        _block_luminance(acc, f, channel, weights, out[i])


@jit(inline="always")
def _four(v, table):
    """The table values of the four 8-bit codes of the 32-bit word ``v``, in memory order."""
    s0, s1, s2, s3 = _BYTE_SHIFTS
    return table[(v >> s0) & 255], table[(v >> s1) & 255], table[(v >> s2) & 255], table[(v >> s3) & 255]


@jit
def _column_sums(words, first, f, table, acc):     # pragma: no cover - compiled
    """acc[x] (x < len(acc) // 8 * 8) = the sum of ``table`` over the codes of column x in rows first … first + f − 1,
    in row order (float32: :func:`_strip_luminance`'s sums): eight columns (two words) at a time, summed in
    registers, so each code costs a load and a look-up (≈ 40 % faster than looking each row up into a buffer)."""
    r = np.uint64(first)                    # unsigned indices: no negative-index wrap-around per load
    for p in range(acc.shape[0] // 8):
        q = np.uint64(2 * p)
        a0, a1, a2, a3 = _four(words[r, q], table)
        b0, b1, b2, b3 = _four(words[r, q + np.uint64(1)], table)
        for k in range(1, f):
            row = r + np.uint64(k)
            x0, x1, x2, x3 = _four(words[row, q], table)
            y0, y1, y2, y3 = _four(words[row, q + np.uint64(1)], table)
            a0, a1, a2, a3 = a0 + x0, a1 + x1, a2 + x2, a3 + x3
            b0, b1, b2, b3 = b0 + y0, b1 + y1, b2 + y2, b3 + y3
        x = 8 * p
        acc[x], acc[x + 1], acc[x + 2], acc[x + 3] = a0, a1, a2, a3
        acc[x + 4], acc[x + 5], acc[x + 6], acc[x + 7] = b0, b1, b2, b3


@jit
def _block_luminance(acc, f, channel, weights, out_row):        # pragma: no cover - compiled
    """One row of blocks from the column sums ``acc`` of its f rows (memory channel ``channel[c]`` of RGB c).
    Unsigned indices: numba then adds no negative-index wrap-around to each load (2.5× faster)."""
    scale = np.float32(1.0) / np.float32(f * f)
    c0, c1, c2 = np.uint64(channel[0]), np.uint64(channel[1]), np.uint64(channel[2])
    step = np.uint64(3 * f)
    for j in range(out_row.shape[0]):
        base = np.uint64(j) * step
        r, g, b = acc[base + c0], acc[base + c1], acc[base + c2]
        for k in range(1, f):
            o = base + np.uint64(3 * k)
            r += acc[o + c0]
            g += acc[o + c1]
            b += acc[o + c2]
        out_row[j] = (r * scale) * weights[0] + (g * scale) * weights[1] + (b * scale) * weights[2]
