"""sRGB transfer function (IEC 61966-2-1:1999) between linear radiance and encoded code values.

One implementation for the image readers/writers (``roadview_noise.io``) and for models that must see what a camera
writes (JPEG compression). Linear values are on the 0–1 scale (1.0 = full scale of the encoding).

Integer code values ↔ linear float32 go through tables, never a per-pixel power, in one compiled pass; OpenCV's BGR
order is written (``bgr=True``) and read (a channel-reversed view) in the same pass, never by a separate copy:

- code → linear: a 256- or 65 536-entry table of the exact decoded values; a C-order or BGR-view frame of 8-bit
  codes is read four codes per 32-bit load (:func:`_look_up`, shared with ``roadview_noise.luminance``).
- linear → code: the code is the number of decision levels ``T_c = decode((c + ½) / M)`` at or below the value,
  so it is the exact float64 rounding of ``M · encode(v)``. A float32 value's bit pattern, shifted right, indexes a
  bucket that holds at most one decision level (checked when the table is built); the table gives the code at the
  bucket's start and, if the bucket holds a level, one comparison with it finishes the job. 8 bit: all 2²⁰ patterns
  >> 12 (2 MB, negatives and NaN included, no range checks: ~0.5 ns a value); 16 bit: patterns >> 8 from the
  bucket of T_0 / 2 to 1.0, with range checks. The float32 ``pow`` used before differed from the exact rounding by
  one code for values within float32 rounding of a decision level (83 in 10⁷ uniform 8-bit values).

A frame that has not changed since it was decoded keeps its codes (:func:`attach_codes`): the linear array is made
read-only and :func:`linear_to_code` returns the codes it came from, so an unchanged frame (a chain of JPEG
compression only, or the writer after JPEG) is never re-encoded. Any change makes a new array, which has no codes.
"""

from __future__ import annotations

import sys
import weakref
from functools import lru_cache

import cv2
import numpy as np

from ..profiling import span
from .compiled import jit

LINEAR_THRESHOLD = 0.0031308    # linear value where the power segment starts
ENCODED_THRESHOLD = 0.04045     # the same point on the encoded axis (12.92 · 0.0031308)
_SHIFT8, _SHIFT16 = 12, 8        # float32 bits below the bucket index of 8- and 16-bit linear → code
_ONE_BITS = 0x3F800000          # float32 1.0
_SRGB16_TOP = (np.uint32(_ONE_BITS), np.uint16(65535))     # top of 16-bit sRGB's bucket table: 1.0 → 65 535
_INF_BITS = 0x7F800000          # float32 +inf; larger patterns are NaN, ≥ 2³¹ negative
_PAIR_SHIFTS = (0, 32) if sys.byteorder == "little" else (32, 0)   # 1st and 2nd float32 of a uint64
_BYTE_SHIFTS = (0, 8, 16, 24) if sys.byteorder == "little" else (24, 16, 8, 0)   # bytes 0–3 of a uint32

#: While the camera metrics collect (``roadview_noise.luminance.collect``): the object whose ``decode8(code, out)`` /
#: ``encode8(linear, out, bgr)`` do the 8-bit passes of an (H, W, 3) frame (the same values) and keep its luminance
#: blocks, returning False for what they do not take; None otherwise.
side_pass = None


def encode(linear: np.ndarray) -> np.ndarray:
    """Encoded sRGB value (0–1) of a linear value (0–1); float in, float out, no clipping."""
    v = np.asarray(linear, dtype=float)
    return np.where(v <= LINEAR_THRESHOLD, 12.92 * v, 1.055 * np.abs(v) ** (1 / 2.4) - 0.055)


def decode(encoded: np.ndarray) -> np.ndarray:
    """Linear value (0–1) of an encoded sRGB value (0–1); float in, float out, no clipping."""
    c = np.asarray(encoded, dtype=float)
    return np.where(c <= ENCODED_THRESHOLD, c / 12.92, ((np.abs(c) + 0.055) / 1.055) ** 2.4)


def _uint_dtype(bits: int) -> type:
    if bits not in (8, 16):
        raise ValueError(f"sRGB code values are 8 or 16 bit, got {bits}")
    return np.uint8 if bits == 8 else np.uint16


# --- linear → code ---------------------------------------------------------------------------------------------------


def decision_levels(bits: int, decoded=decode) -> np.ndarray:
    """The float32 bit patterns of the decision levels T_0 … T_{M−1} of the transfer function ``decoded`` (code /
    full scale → linear, float64), each rounded up to a float32 (so that v ≥ T ⇔ v ≥ T32 for a float32 v),
    followed by the pattern just above +inf (NaN)."""
    full = 2 ** bits - 1
    levels = decoded((np.arange(full) + 0.5) / full)                # float64 decision levels
    levels32 = levels.astype(np.float32)
    levels32[levels32 < levels] = np.nextafter(levels32[levels32 < levels], np.float32(np.inf))
    return np.append(levels32.view(np.uint32), np.uint32(_INF_BITS + 1))


def _bucket_codes(levels: np.ndarray, shift: int, first: int, last: int) -> tuple[np.ndarray, np.ndarray]:
    """For the buckets ``first … last`` of bit patterns >> ``shift``: the number of ``levels`` (sorted bit patterns)
    at or below each bucket's first pattern (its code) and the number inside the rest of the bucket."""
    bucket = (levels >> np.uint32(shift)).astype(np.int64)
    on_start = (levels & np.uint32((1 << shift) - 1)) == 0
    code = np.cumsum(np.bincount(np.clip(bucket + ~on_start - first, 0, None), minlength=last - first + 2))
    inside = np.bincount(bucket[~on_start] - first, minlength=last - first + 2)
    return code[:last - first + 1], inside[:last - first + 1]


@lru_cache(maxsize=1)
def encode8_table() -> tuple[np.ndarray, np.ndarray]:
    """(entry of every bucket, decision levels) of 8-bit linear → code. A float32 value's bit pattern shifted right
    by 12 indexes one of 2²⁰ buckets (2 MB; negatives and NaN included). An entry < 256 is the code of the whole
    bucket; 256 + c marks a bucket that holds the decision level ``levels[c]``: the code is c + (v ≥ level). The
    bucket of +inf also holds the NaN patterns: +inf → 255, NaN → 256, which wraps to 0."""
    levels = decision_levels(8)
    code, inside = _bucket_codes(levels, _SHIFT8, 0, _INF_BITS >> _SHIFT8)     # 0 … +inf
    if inside.max() > 1:                                               # table too coarse for one comparison
        raise AssertionError("sRGB 8-bit encode table: a bucket holds two decision levels")
    table = np.zeros(1 << (32 - _SHIFT8), np.uint16)                  # negative and NaN patterns: code 0
    table[:code.size] = code + 256 * inside
    table.flags.writeable = levels.flags.writeable = False
    return table, levels


@jit(inline="always")
def _code8(b, table, levels):
    """8-bit code of the float32 value with bit pattern ``b`` (:func:`encode8_table`)."""
    e = table[b >> np.uint32(_SHIFT8)]
    if e < 256:
        return e
    c = e - 256
    return (c + (b >= levels[c])) & 255


@jit
def _encode8_kernel(xbits, out, table, levels):
    """``out`` = 8-bit codes of the float32 values whose bit patterns are ``xbits`` (1-D, same size)."""
    for i in range(xbits.size):
        out[i] = _code8(xbits[i], table, levels)


@jit(inline="always")
def _half(pair, shift):
    """The float32 bit pattern ``shift`` bits up in a uint64 (:data:`_PAIR_SHIFTS`)."""
    return np.uint32((pair >> np.uint64(shift)) & np.uint64(0xFFFFFFFF))


@jit
def _encode8_reversed_kernel(xbits, pairs, out, table, levels):
    """As :func:`_encode8_kernel` for pixels of 3 values (``xbits``, flat), written with the channel order reversed
    (RGB → BGR). ``pairs`` is ``xbits`` read two values at a time (uint64): one load per two values, ≈ 15 % faster."""
    first, second = _PAIR_SHIFTS
    for q in range(pairs.size // 3):                      # two pixels from three loads
        a, b, c = pairs[3 * q], pairs[3 * q + 1], pairs[3 * q + 2]
        r0, g0 = _code8(_half(a, first), table, levels), _code8(_half(a, second), table, levels)
        b0, r1 = _code8(_half(b, first), table, levels), _code8(_half(b, second), table, levels)
        g1, b1 = _code8(_half(c, first), table, levels), _code8(_half(c, second), table, levels)
        i = 6 * q
        out[i], out[i + 1], out[i + 2], out[i + 3], out[i + 4], out[i + 5] = b0, g0, r0, b1, g1, r1
    for i in range(6 * (pairs.size // 3), xbits.size):    # an odd last pixel
        out[i + 2 - 2 * (i % 3)] = _code8(xbits[i], table, levels)


@lru_cache(maxsize=1)
def encode16_table() -> tuple[int, np.ndarray, np.ndarray]:
    """(first bucket, code at each bucket's start, next decision level above it) of 16-bit sRGB linear → code
    (:func:`bucket_table`, whose top is 1.0: :func:`_code16`)."""
    return bucket_table(decision_levels(16), 1.0, "sRGB 16-bit")[:3]


def bucket_table(levels: np.ndarray, top: float, name: str) -> tuple:
    """(first bucket, code at each bucket's start, next decision level above it, bit pattern of ``top``, full
    code) of linear → code for the decision ``levels`` (:func:`decision_levels`) of a transfer function whose
    full code decodes to ``top``: the bit pattern shifted right by 8 indexes a bucket that holds at most one
    decision level (2²⁴ buckets would take 64 MB, so the table starts at the bucket of T_0 / 2 and ends at
    ``top``). Also the encoder of other transfer functions (``physics/transfers.py``) and of 8-bit codes there."""
    top_bits = int(np.float32(top).view(np.uint32))
    first = int((levels[:1].view(np.float32) / np.float32(2)).view(np.uint32)[0]) >> _SHIFT16
    code, inside = _bucket_codes(levels, _SHIFT16, first, top_bits >> _SHIFT16)
    if inside.max() > 1:                                               # table too coarse for one comparison
        raise AssertionError(f"{name} encode table: a bucket holds two decision levels")
    nxt = levels[code]                                                 # (the level above the last is +inf + 1)
    code = code.astype(np.uint16)
    code.flags.writeable = nxt.flags.writeable = False
    return first, code, nxt, np.uint32(top_bits), np.uint16(levels.size - 1)


@jit(inline="always")
def _code16(b, first, code, nxt_bits):
    """16-bit sRGB code of the float32 value with bit pattern ``b`` (:func:`encode16_table`)."""
    return _bucket_code(b, first, code, nxt_bits, _ONE_BITS, 65535)


@jit(inline="always")
def _bucket_code(b, first, code, nxt_bits, top_bits, full):
    """Code of the float32 value with bit pattern ``b`` (:func:`bucket_table`)."""
    if b >= top_bits:                                    # ≥ top (or NaN / negative, sorted out here)
        return full if b <= _INF_BITS else 0
    n = np.int64(b >> _SHIFT16) - first                 # 0 ≤ v < 1: bit patterns sort like the values
    if n < 0:
        return 0
    n = min(n, code.size - 1)
    return code[n] + 1 if b >= nxt_bits[n] else code[n]


@jit
def _encode16_kernel(xbits, out, first, code, nxt_bits, top_bits, full):
    """``out`` = codes of the float32 values whose bit patterns are ``xbits`` (1-D, same size;
    :func:`bucket_table`)."""
    for i in range(xbits.size):
        out[i] = _bucket_code(xbits[i], first, code, nxt_bits, top_bits, full)


@jit
def _encode16_reversed_kernel(xbits, out, first, code, nxt_bits, top_bits, full):
    """As :func:`_encode16_kernel` for (N, 3) pixels, written with the channel order reversed (RGB → BGR)."""
    for p in range(xbits.shape[0]):
        for k in range(3):
            out[p, 2 - k] = _bucket_code(xbits[p, k], first, code, nxt_bits, top_bits, full)


def _as_3d(a: np.ndarray) -> np.ndarray:
    """A (H, W, C) view of an image-like array (copies only arrays of other dimensions)."""
    if a.ndim == 3:
        return a
    if a.ndim == 2:
        return a[:, :, None]
    return np.ascontiguousarray(a).reshape(1, -1, 1)


def _kernel_views(src: np.ndarray, out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, C) views of a kernel's input and output of one shape: (1, 1, N) when both are C-contiguous, so the
    kernel's inner loop runs over the whole frame (the table look-up of code → linear: 2× faster than 3 channels at
    a time), else :func:`_as_3d`."""
    if src.flags.c_contiguous and out.flags.c_contiguous:
        return src.reshape(1, 1, -1), out.reshape(1, 1, -1)
    return _as_3d(src), _as_3d(out)


def reversed_rgb(a: np.ndarray) -> bool:
    """Whether ``a`` is the channel-reversed view of a C-contiguous (H, W, 3) array (OpenCV's BGR seen as RGB)."""
    return a.ndim == 3 and a.shape[2] == 3 and not a.flags.c_contiguous and a[..., ::-1].flags.c_contiguous


def linear_to_code(linear: np.ndarray, bits: int = 8, *, bgr: bool = False, table: tuple | None = None
                   ) -> np.ndarray:
    """Integer sRGB code values (uint8 or uint16) of linear radiance: clipped to [0, 1], encoded, rounded to the
    nearest code (exactly; module docstring); NaN gives 0. A new C-order array, or — for an unchanged decoded frame —
    the read-only codes it was decoded from. ``bgr``: (H, W, 3) RGB in, C-order BGR codes out (OpenCV's order).
    ``table``: the :func:`bucket_table` of another transfer function (``physics/transfers.py``), clipped to [0, its
    top] instead (no kept codes, no side pass)."""
    dtype = _uint_dtype(bits)
    if bgr and (np.ndim(linear) != 3 or np.shape(linear)[2] != 3):
        raise ValueError(f"bgr codes need (H, W, 3) RGB, got shape {np.shape(linear)}")
    kept = attached_codes(linear, bits) if table is None else None
    if kept is not None:
        return bgr_order(kept) if bgr else kept
    with span("convert"):
        v = np.asarray(linear, dtype=np.float32)
        xbits = np.ascontiguousarray(v).view(np.uint32)
        out = np.empty(v.shape, dtype)
        eight = table is None and bits == 8             # else the bucket kernels (at the table's own depth)
        if table is None:
            table = encode8_table() if eight else encode16_table() + _SRGB16_TOP
        if eight and side_pass is not None and side_pass.encode8(v, out, bgr):
            pass                                        # with the metrics' luminance (roadview_noise.luminance)
        elif bgr and eight:
            flat = xbits.reshape(-1)
            _encode8_reversed_kernel(flat, flat[:flat.size // 2 * 2].view(np.uint64), out.reshape(-1), *table)
        elif bgr:
            _encode16_reversed_kernel(xbits.reshape(-1, 3), out.reshape(-1, 3), *table)
        else:
            (_encode8_kernel if eight else _encode16_kernel)(xbits.reshape(-1), out.reshape(-1), *table)
    return out


def bgr_order(codes: np.ndarray) -> np.ndarray:
    """RGB(A) code values in OpenCV's BGR(A) order, C-order: the storage itself when ``codes`` is the RGB view of
    BGR codes (:func:`..io.image.encode_pixels`, a decoded file's kept codes, a JPEG output), else a new array."""
    if codes.shape[2] == 3 and codes[..., ::-1].flags.c_contiguous:
        return codes[..., ::-1]
    return cv2.cvtColor(codes, cv2.COLOR_RGB2BGR if codes.shape[2] == 3 else cv2.COLOR_RGBA2BGRA)


# --- code → linear ---------------------------------------------------------------------------------------------------


@lru_cache(maxsize=2)
def decode_table(bits: int) -> np.ndarray:
    table = decode(np.arange(2 ** bits) / (2 ** bits - 1)).astype(np.float32)
    table.flags.writeable = False
    return table


@jit
def _look_up(row, table, out):
    """out = table[row[:len(out)]] (8-bit codes), four codes per 32-bit load (≈ 15 % faster than byte loads)."""
    m = out.shape[0] // 4
    words = row[:4 * m].view(np.uint32)
    s0, s1, s2, s3 = _BYTE_SHIFTS
    for j in range(m):
        v = words[j]
        out[4 * j] = table[(v >> s0) & 255]
        out[4 * j + 1] = table[(v >> s1) & 255]
        out[4 * j + 2] = table[(v >> s2) & 255]
        out[4 * j + 3] = table[(v >> s3) & 255]
    for j in range(4 * m, out.shape[0]):
        out[j] = table[row[j]]


@jit
def _look_up_reversed(row, table, out):
    """out = table of the pixels of ``row`` (BGR codes, 3 per pixel) in RGB order, four pixels per three 32-bit
    loads."""
    m = out.shape[0] // 12
    words = row[:12 * m].view(np.uint32)
    s0, s1, s2, s3 = _BYTE_SHIFTS
    for q in range(m):                      # bytes B0 G0 R0 B1 | G1 R1 B2 G2 | R2 B3 G3 R3
        a, b, c = words[3 * q], words[3 * q + 1], words[3 * q + 2]
        i = 12 * q
        out[i], out[i + 1], out[i + 2] = table[(a >> s2) & 255], table[(a >> s1) & 255], table[(a >> s0) & 255]
        out[i + 3], out[i + 4], out[i + 5] = table[(b >> s1) & 255], table[(b >> s0) & 255], table[(a >> s3) & 255]
        out[i + 6], out[i + 7], out[i + 8] = table[(c >> s0) & 255], table[(b >> s3) & 255], table[(b >> s2) & 255]
        out[i + 9], out[i + 10], out[i + 11] = table[(c >> s3) & 255], table[(c >> s2) & 255], table[(c >> s1) & 255]
    for j in range(12 * m, out.shape[0]):
        out[j] = table[row[j + 2 - 2 * (j % 3)]]


@jit
def _decode_kernel(codes, table, out):
    for i in range(codes.shape[0]):
        for j in range(codes.shape[1]):
            for k in range(codes.shape[2]):
                out[i, j, k] = table[codes[i, j, k]]


@jit
def _decode_reversed_kernel(codes, table, out):
    """As :func:`_decode_kernel` for (N, 3) pixels read with the channel order reversed (BGR → RGB)."""
    for p in range(codes.shape[0]):
        for k in range(3):
            out[p, k] = table[codes[p, 2 - k]]


def code_to_linear(code: np.ndarray, bits: int = 8, *, table: np.ndarray | None = None) -> np.ndarray:
    """Linear radiance (float32, 0–1, C order) of integer sRGB code values, by table look-up; the result keeps
    ``code`` (:func:`attach_codes`). ``table``: the 2^bits decoded values of another transfer function
    (``physics/transfers.py``; no kept codes, no side pass)."""
    dtype = _uint_dtype(bits)
    code = np.asarray(code)
    if code.dtype != dtype:
        raise ValueError(f"expected {np.dtype(dtype).name} code values, got {code.dtype}")
    srgb_codes = table is None
    table = decode_table(bits) if srgb_codes else table
    with span("convert"):
        out = np.empty(code.shape, np.float32)
        if bits == 8 and srgb_codes and side_pass is not None and side_pass.decode8(code, out):
            pass                                        # with the metrics' luminance (roadview_noise.luminance)
        elif reversed_rgb(code):                          # OpenCV's BGR seen as RGB: read it in place
            if bits == 8:
                _look_up_reversed(code[..., ::-1].reshape(-1), table, out.reshape(-1))
            else:
                _decode_reversed_kernel(code[..., ::-1].reshape(-1, 3), table, out.reshape(-1, 3))
        elif bits == 8 and code.flags.c_contiguous:
            _look_up(code.reshape(-1), table, out.reshape(-1))
        else:
            src, dst = _kernel_views(code, out)
            _decode_kernel(src, table, dst)
    return attach_codes(out, code, bits) if srgb_codes else out


# --- codes kept with an unchanged frame ------------------------------------------------------------------------------

_ATTACHED: dict[int, tuple[weakref.ref, np.ndarray, int]] = {}


def attach_codes(linear: np.ndarray, codes: np.ndarray, bits: int) -> np.ndarray:
    """Remember that ``linear`` is exactly the decoding of ``codes`` (``bits``-bit sRGB, same shape); ``linear`` is
    made read-only, so it can never change while the codes are kept. Returns ``linear``."""
    if codes.shape != linear.shape:
        return linear
    linear.flags.writeable = False
    codes.flags.writeable = False
    key = id(linear)

    def forget(ref, key=key):
        if _ATTACHED.get(key, (None,))[0] is ref:
            del _ATTACHED[key]

    _ATTACHED[key] = (weakref.ref(linear, forget), codes, bits)
    return linear


def attached_codes(linear, bits: int) -> np.ndarray | None:
    """The codes ``linear`` was decoded from, if it is that very (read-only) array and ``bits`` match, else None."""
    item = _ATTACHED.get(id(linear))
    if item is None or item[0]() is not linear or item[2] != bits or linear.flags.writeable:
        return None
    return item[1]
