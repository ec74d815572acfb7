"""Camera image reader/writer: PNG, JPEG, TIFF (8/16-bit sRGB, float32 linear TIFF) ↔ linear RGB float32.

Decoding with OpenCV (``IMREAD_UNCHANGED``: no EXIF rotation, no bit-depth reduction); BGR ↔ RGB and sRGB ↔ linear
happen here and nowhere else. 8/16-bit files are sRGB encoded (IEC 61966-2-1, ``physics/srgb.py``); float32 TIFF is
linear. 1.0 is the full scale of the encoding. Grey files are replicated to three channels and written back as Rec. 709
luminance Y = 0.2126 R + 0.7152 G + 0.0722 B of the linear RGB (identity for equal channels).

OpenCV decodes some truncated files without an error (a JPEG cut short gets a grey bottom), so the structure is checked
first: PNG needs its IEND chunk, JPEG its EOI marker, TIFF strips/tiles inside the file.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import cv2
import numpy as np
import tifffile

from ..errors import InputError
from ..physics import srgb
from ..types import ImageEncoding
from .atomic import write_bytes_atomic

SUFFIX_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".tif": "tiff", ".tiff": "tiff"}
_EXTENSION = {"png": ".png", "jpeg": ".jpg", "tiff": ".tiff"}
_LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"            # chunk type + CRC of the (empty) IEND chunk
_JPEG_SOI, _JPEG_EOI = b"\xff\xd8", b"\xff\xd9"
_TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def image_format(path: str | os.PathLike) -> str:
    """``png`` | ``jpeg`` | ``tiff`` from the file suffix (case-insensitive)."""
    fmt = SUFFIX_FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise InputError(f"unknown image suffix {Path(path).suffix!r}; expected one of {sorted(SUFFIX_FORMATS)}",
                         file=str(path))
    return fmt


def read_image(path: str | os.PathLike) -> tuple[np.ndarray, ImageEncoding, np.ndarray | None]:
    """Read an image as (H, W, 3) float32 linear RGB, its encoding, and the alpha plane as stored (or None)."""
    fmt = image_format(path)
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read image: {exc.strerror or exc}", file=str(path)) from exc
    return decode_image(data, fmt, source=path)


def decode_image(data: bytes, fmt: str, *, source) -> tuple[np.ndarray, ImageEncoding, np.ndarray | None]:
    """:func:`read_image` of the bytes of a ``fmt`` file (also a ROS CompressedImage); ``source`` names it in
    errors."""
    check_structure(data, fmt, source)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"OpenCV cannot decode this {fmt.upper()} file (corrupt or unsupported variant)",
                         file=str(source))
    quality = _jpeg_quality(data) if fmt == "jpeg" else ImageEncoding.jpeg_quality
    return image_from_codes(img, fmt, source=source, jpeg_quality=quality)


def image_from_codes(img: np.ndarray, fmt: str, *, source, jpeg_quality: int = ImageEncoding.jpeg_quality
                     ) -> tuple[np.ndarray, ImageEncoding, np.ndarray | None]:
    """Linear RGB, encoding and alpha of decoded code values in OpenCV order (grey, BGR or BGRA; uint8/uint16
    sRGB, or float32 linear for TIFF) stored as ``fmt``."""
    if img.dtype == np.uint8 or img.dtype == np.uint16:
        bit_depth, transfer = 8 * img.dtype.itemsize, "srgb"
    elif img.dtype == np.float32 and fmt == "tiff":
        bit_depth, transfer = 32, "linear"
    else:
        raise InputError(f"unsupported sample type {img.dtype} (expected uint8, uint16 or float32 TIFF)",
                         file=str(source))
    channels = 1 if img.ndim == 2 else img.shape[2]
    if channels not in (1, 3, 4):
        raise InputError(f"unsupported channel count {channels} (expected 1, 3 or 4)", file=str(source))
    alpha = img[..., 3].copy() if channels == 4 else None
    codes = img if channels == 1 else img[..., 2::-1]          # BGR(A) → RGB
    linear = srgb.code_to_linear(codes, bit_depth) if transfer == "srgb" else codes.astype(np.float32)
    if channels == 1:
        linear = np.repeat(linear[..., None], 3, axis=2)
    encoding = ImageEncoding(fmt=fmt, bit_depth=bit_depth, transfer=transfer, channels=channels,
                             jpeg_quality=jpeg_quality)
    return np.ascontiguousarray(linear, dtype=np.float32), encoding, alpha


def write_image(path: str | os.PathLike, linear_rgb: np.ndarray, encoding: ImageEncoding,
                alpha: np.ndarray | None = None) -> None:
    """Encode (H, W, 3) linear RGB like ``encoding`` (sRGB or linear, bit depth, channels, JPEG quality) and write it
    atomically. Integer encodings are clipped to [0, 1] and rounded here, once; float32 TIFF is written unclipped.
    A 4-channel encoding without ``alpha`` gets an opaque alpha plane."""
    if image_format(path) != encoding.fmt:
        raise ValueError(f"{Path(path).name}: suffix does not match the encoding format {encoding.fmt!r}")
    write_bytes_atomic(path, encode_image(linear_rgb, encoding, alpha, name=Path(path).name))


def encode_image(linear_rgb: np.ndarray, encoding: ImageEncoding, alpha: np.ndarray | None = None, *,
                 name: str = "image") -> bytes:
    """The file bytes :func:`write_image` writes (also the data of a ROS CompressedImage)."""
    codes = codes_from_image(linear_rgb, encoding, alpha, name=name)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(encoding.jpeg_quality)] if encoding.fmt == "jpeg" else []
    ok, buf = cv2.imencode(_EXTENSION[encoding.fmt], codes, params)
    if not ok:
        raise OSError(f"{name}: OpenCV could not encode {encoding}")
    return buf.tobytes()


def codes_from_image(linear_rgb: np.ndarray, encoding: ImageEncoding, alpha: np.ndarray | None = None, *,
                     name: str = "image") -> np.ndarray:
    """Code values of linear RGB for ``encoding`` in OpenCV order (grey, BGR or BGRA), the inverse of
    :func:`image_from_codes`; ``name`` identifies the image in errors."""
    linear_rgb = np.asarray(linear_rgb)
    if linear_rgb.ndim != 3 or linear_rgb.shape[2] != 3:
        raise ValueError(f"expected linear RGB of shape (H, W, 3), got {linear_rgb.shape}")
    n_nan = int(np.count_nonzero(np.isnan(linear_rgb)))
    if n_nan:
        raise ValueError(f"{name}: image has {n_nan} NaN values; a model produced invalid radiance")
    pixels = linear_rgb @ _LUMA_709 if encoding.channels == 1 else linear_rgb
    codes = encode_pixels(pixels, encoding)
    if encoding.channels == 3:
        codes = codes[..., ::-1]
    elif encoding.channels == 4:
        if alpha is None:
            alpha = np.full(codes.shape[:2], 1.0 if codes.dtype == np.float32 else np.iinfo(codes.dtype).max)
        codes = np.dstack([codes[..., ::-1], np.asarray(alpha).astype(codes.dtype)])
    elif encoding.channels != 1:
        raise ValueError(f"unsupported channel count {encoding.channels}")
    return np.ascontiguousarray(codes)


def encode_pixels(linear: np.ndarray, encoding: ImageEncoding) -> np.ndarray:
    """Code values of linear pixels for ``encoding``: uint8/uint16 (clipped, rounded) or float32 (linear TIFF)."""
    if encoding.bit_depth == 32:
        if encoding.transfer != "linear":
            raise ValueError("float32 images are stored linear")
        return np.asarray(linear, dtype=np.float32)
    if encoding.transfer == "srgb":
        return srgb.linear_to_code(linear, encoding.bit_depth)
    if encoding.transfer == "linear" and encoding.bit_depth in (8, 16):
        full = 2 ** encoding.bit_depth - 1
        dtype = np.uint8 if encoding.bit_depth == 8 else np.uint16
        return np.rint(np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0) * np.float32(full)).astype(dtype)
    raise ValueError(f"unsupported encoding {encoding}")


# --- structure checks ---------------------------------------------------------------------------------------------


def check_structure(data: bytes, fmt: str, path) -> None:
    """Raise :class:`InputError` for a file that is not ``fmt`` or is cut short (see module docstring)."""
    if fmt == "png":
        if not data.startswith(_PNG_SIGNATURE):
            raise InputError("not a PNG file (bad signature)", file=str(path))
        if data.rfind(_PNG_IEND) < 0:
            raise InputError("truncated PNG: the IEND chunk is missing", file=str(path))
    elif fmt == "jpeg":
        if not data.startswith(_JPEG_SOI):
            raise InputError("not a JPEG file (no SOI marker FF D8)", file=str(path))
        if not data.rstrip(b"\x00\r\n").endswith(_JPEG_EOI):
            raise InputError("truncated JPEG: the end-of-image marker FF D9 is missing", file=str(path))
    else:
        if not data.startswith(_TIFF_SIGNATURES):
            raise InputError("not a TIFF file (bad byte-order header)", file=str(path))
        try:
            with tifffile.TiffFile(io.BytesIO(data)) as tif:
                page = tif.pages[0]
                end = max((o + c for o, c in zip(page.dataoffsets, page.databytecounts)), default=0)
                expected = len(page.dataoffsets)
        except Exception as exc:                      # tifffile raises several types for a damaged directory
            raise InputError(f"corrupt or truncated TIFF: {exc}", file=str(path)) from exc
        if expected == 0 or end > len(data):
            raise InputError(f"truncated TIFF: image data ends at byte {end}, the file has {len(data)} bytes",
                             file=str(path))


# --- JPEG quality estimate -----------------------------------------------------------------------------------------

# ITU-T T.81 Annex K.1 luminance quantisation table (natural order); libjpeg scales it by the IJG quality rule.
_K1_LUMINANCE = np.array([
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57, 69, 56,
    14, 17, 22, 29, 51, 87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92,
    49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99], dtype=np.int64)


def _zigzag_order() -> np.ndarray:
    """Natural (row-major) index of each zig-zag position of an 8×8 block (T.81 Figure 5)."""
    i, j = np.divmod(np.arange(64), 8)
    s = i + j
    return np.lexsort((np.where(s % 2 == 1, i, -i), s))


def _ijg_tables() -> np.ndarray:
    """(100, 64) luminance tables in zig-zag order for IJG qualities 1…100 (baseline, clamped to 1…255)."""
    q = np.arange(1, 101)[:, None]
    scale = np.where(q < 50, 5000 // q, 200 - 2 * q)
    return np.clip((_K1_LUMINANCE[_zigzag_order()][None, :] * scale + 50) // 100, 1, 255)


def _jpeg_quality(data: bytes) -> int:
    """IJG quality (1–100) whose luminance table is closest to the file's table 0; 95 when the file has none."""
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker, length = data[pos + 1], int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker == 0xDA:                              # start of scan: no more tables before the entropy data
            break
        if marker == 0xDB:
            seg, k = data[pos + 4:pos + 2 + length], 0
            while k < len(seg):
                precision, table_id = seg[k] >> 4, seg[k] & 15
                n = 128 if precision else 64
                values = np.frombuffer(seg[k + 1:k + 1 + n], ">u2" if precision else "u1").astype(np.int64)
                if table_id == 0 and len(values) == 64:
                    return int(np.argmin(np.abs(_ijg_tables() - values).sum(axis=1))) + 1
                k += 1 + n
        pos += 2 + length
    return ImageEncoding.jpeg_quality
