"""sRGB transfer function (IEC 61966-2-1:1999) between linear radiance and encoded code values.

One implementation for the image readers/writers (``roadview_noise.io``) and for models that must see what a camera
writes (JPEG compression). Linear values are on the 0–1 scale (1.0 = full scale of the encoding).

Integer code values ↔ linear float32 go through tables, never a per-pixel power, in one compiled pass that also
handles any strides (a BGR ↔ RGB view costs no copy):

- code → linear: a 256- or 65 536-entry table of the exact decoded values.
- linear → code: the code is the number of decision levels ``T_c = decode((c + ½) / M)`` at or below the value,
  so it is the exact float64 rounding of ``M · encode(v)``. A float32 value's bit pattern, shifted right by 16
  (8-bit) or 8 (16-bit) bits, indexes a bucket that holds at most one decision level (checked when the table is
  built); the table gives the code at the bucket's start and the next level, so one comparison finishes the job.
  The float32 ``pow`` used before differed from the exact rounding by one code for values within float32
  rounding of a decision level (83 in 10⁷ uniform 8-bit values).

A frame that has not changed since it was decoded keeps its codes (:func:`attach_codes`): the linear array is made
read-only and :func:`linear_to_code` returns the codes it came from, so an unchanged frame (a chain of JPEG
compression only, or the writer after JPEG) is never re-encoded. Any change makes a new array, which has no codes.
"""

from __future__ import annotations

import weakref
from functools import lru_cache

import numpy as np

from ..profiling import span
from .compiled import jit

LINEAR_THRESHOLD = 0.0031308    # linear value where the power segment starts
ENCODED_THRESHOLD = 0.04045     # the same point on the encoded axis (12.92 · 0.0031308)
_BUCKET_SHIFT = {8: 16, 16: 8}  # float32 mantissa bits below the bucket index of linear → code


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


@lru_cache(maxsize=2)
def encode_table(bits: int) -> tuple[int, np.ndarray, np.ndarray]:
    """(first bucket, code at each bucket's start, next decision level above it as float32) for ``bits``."""
    dtype, shift = _uint_dtype(bits), _BUCKET_SHIFT[bits]
    full = 2 ** bits - 1
    levels = decode((np.arange(full) + 0.5) / full)                 # float64 decision levels T_0 … T_{M−1}
    levels32 = levels.astype(np.float32)
    levels32[levels32 < levels] = np.nextafter(levels32[levels32 < levels], np.float32(np.inf))   # v ≥ T ⇔ v ≥ T32
    first = int(np.float32(levels32[0] / 2).view(np.uint32)) >> shift
    last = int(np.float32(1.0).view(np.uint32)) >> shift
    starts = (np.arange(first, last + 1, dtype=np.uint64) << np.uint64(shift)).astype(np.uint32).view(np.float32)
    code = np.searchsorted(levels32, starts, side="right")            # levels at or below each bucket's start
    nxt = np.append(levels32, np.float32(np.inf))[code]
    ends = ((np.arange(first, last + 1, dtype=np.uint64) + 1) << np.uint64(shift)).astype(np.uint32).view(np.float32)
    after = np.append(levels32, [np.float32(np.inf)] * 2)[code + 1]
    if np.any(after < ends[:len(after)]):                              # two levels in one bucket: table too coarse
        raise AssertionError(f"sRGB {bits}-bit encode table: a bucket holds two decision levels")
    code, nxt = code.astype(dtype), nxt.astype(np.float32)
    code.flags.writeable = nxt.flags.writeable = False
    return first, code, nxt


_ONE_BITS = 0x3F800000                  # float32 1.0
_INF_BITS = 0x7F800000                  # float32 +inf; larger patterns are NaN, ≥ 2³¹ negative


@jit
def _encode_kernel(xbits, out, first, shift, code, nxt_bits, full):
    """``out`` = codes of the float32 values whose bit patterns are ``xbits`` (both (H, W, C), any strides)."""
    top = code.size - 1
    for i in range(xbits.shape[0]):
        for j in range(xbits.shape[1]):
            for k in range(xbits.shape[2]):
                b = xbits[i, j, k]
                if b >= _ONE_BITS:                       # ≥ 1 (or NaN / negative, sorted out below)
                    out[i, j, k] = full if b <= _INF_BITS else 0
                else:                                    # 0 ≤ v < 1: bit patterns sort like the values
                    n = np.int64(b >> shift) - first
                    if n < 0:
                        out[i, j, k] = 0
                    else:
                        n = min(n, top)
                        out[i, j, k] = code[n] + 1 if b >= nxt_bits[n] else code[n]


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


def linear_to_code(linear: np.ndarray, bits: int = 8) -> np.ndarray:
    """Integer sRGB code values (uint8 or uint16) of linear radiance: clipped to [0, 1], encoded, rounded to the
    nearest code (exactly; module docstring); NaN gives 0. A new C-order array, or — for an unchanged decoded frame —
    the read-only codes it was decoded from."""
    dtype = _uint_dtype(bits)
    kept = attached_codes(linear, bits)
    if kept is not None:
        return kept
    with span("convert"):
        v = np.asarray(linear, dtype=np.float32)
        first, code, nxt = encode_table(bits)
        out = np.empty(v.shape, dtype)
        _encode_kernel(_as_3d(v).view(np.uint32), _as_3d(out), first, _BUCKET_SHIFT[bits], code,
                       nxt.view(np.uint32), 2 ** bits - 1)
    return out


# --- code → linear ---------------------------------------------------------------------------------------------------


@lru_cache(maxsize=2)
def _decode_table(bits: int) -> np.ndarray:
    table = decode(np.arange(2 ** bits) / (2 ** bits - 1)).astype(np.float32)
    table.flags.writeable = False
    return table


@jit
def _decode_kernel(codes, table, out):
    for i in range(codes.shape[0]):
        for j in range(codes.shape[1]):
            for k in range(codes.shape[2]):
                out[i, j, k] = table[codes[i, j, k]]


def code_to_linear(code: np.ndarray, bits: int = 8) -> np.ndarray:
    """Linear radiance (float32, 0–1, C order) of integer sRGB code values, by table look-up; the result keeps
    ``code`` (:func:`attach_codes`)."""
    dtype = _uint_dtype(bits)
    code = np.asarray(code)
    if code.dtype != dtype:
        raise ValueError(f"expected {np.dtype(dtype).name} code values, got {code.dtype}")
    with span("convert"):
        out = np.empty(code.shape, np.float32)
        src, dst = _kernel_views(code, out)
        _decode_kernel(src, _decode_table(bits), dst)
    return attach_codes(out, code, bits)


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
