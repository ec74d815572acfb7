"""sRGB transfer function (IEC 61966-2-1:1999) between linear radiance and encoded code values.

One implementation for the image readers/writers (``roadview_noise.io``) and for models that must see what a camera
writes (JPEG compression). Linear values are on the 0–1 scale (1.0 = full scale of the encoding).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

LINEAR_THRESHOLD = 0.0031308    # linear value where the power segment starts
ENCODED_THRESHOLD = 0.04045     # the same point on the encoded axis (12.92 · 0.0031308)


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


def linear_to_code(linear: np.ndarray, bits: int = 8) -> np.ndarray:
    """Integer sRGB code values of linear radiance: clip to [0, 1], encode, round (uint8 or uint16).

    Float32 arithmetic with OpenCV's vectorised ``pow`` (3.5× faster than NumPy's: ≈ 40 ms for a 1936×1464 frame
    on one core); a value within float32 rounding of a code boundary may land one code from the float64 result."""
    dtype = _uint_dtype(bits)
    scale = np.float32(2 ** bits - 1)
    v = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    code = cv2.pow(v.reshape(-1, 1), 1 / 2.4).reshape(v.shape)
    code *= np.float32(1.055) * scale
    code -= np.float32(0.055) * scale
    low = v <= np.float32(LINEAR_THRESHOLD)
    code[low] = v[low] * (np.float32(12.92) * scale)
    return np.rint(code, out=code).astype(dtype)


@lru_cache(maxsize=2)
def _decode_table(bits: int) -> np.ndarray:
    table = decode(np.arange(2 ** bits) / (2 ** bits - 1)).astype(np.float32)
    table.flags.writeable = False
    return table


def code_to_linear(code: np.ndarray, bits: int = 8) -> np.ndarray:
    """Linear radiance (float32, 0–1) of integer sRGB code values, by table look-up."""
    dtype = _uint_dtype(bits)
    code = np.asarray(code)
    if code.dtype != dtype:
        raise ValueError(f"expected {np.dtype(dtype).name} code values, got {code.dtype}")
    return _decode_table(bits)[code]
