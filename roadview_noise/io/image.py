"""Camera image reader/writer: PNG, JPEG, TIFF (8/16-bit sRGB, float32 linear TIFF), OpenEXR (half/float linear),
WebP (:mod:`.webp`), HEIF and AVIF (:mod:`.heif`, an optional extra) ↔ linear RGB float32.

Decoding with OpenCV (``IMREAD_UNCHANGED``: no EXIF rotation, no bit-depth reduction) — the common PNG kinds (8/16-bit
grey, RGB, RGBA) by :mod:`.png`, which gives OpenCV's pixels in half its time; BGR ↔ RGB and sRGB ↔ linear
happen here and nowhere else (the sRGB arithmetic itself is ``physics/srgb.py``). 8/16-bit files are sRGB encoded
(IEC 61966-2-1) unless they state linear or another curve — BT.709/601/2020, gamma 2.2/2.8, BT.2100 PQ or HLG
(:func:`.image_metadata.stated_transfer`; ``physics/transfers.py``, reference white at 1.0, PQ/HLG highlights above
it kept up to the curve's peak); float32 TIFF and EXR are linear and are written back unclipped (HDR stays HDR),
EXR with the same half/float channel type. 1.0 is the full scale of the encoding (of a PQ/HLG one: reference white). Grey files are replicated to three channels and
written back as Rec. 709 luminance Y = 0.2126 R + 0.7152 G + 0.0722 B of the linear RGB (identity for equal
channels).

Written back like the input: bit depth, channels, alpha plane, JPEG quality (estimated from the input's
quantisation tables unless the recipe states one), JPEG chroma subsampling and progressive mode, the embedded ICC
colour profile (PNG ``iCCP`` chunk, JPEG ``APP2 ICC_PROFILE`` segments, TIFF tag 34675) and the EXIF data (JPEG
``APP1 Exif``, PNG ``eXIf``; with the orientation tag, as pixels are read and written as stored), copied unchanged,
with a PNG's text, ``pHYs`` and colour chunks and a TIFF's orientation, resolution and descriptive tags
(:mod:`.image_metadata`).
A palette TIFF is read as RGB, a CMYK one as RGB (OpenCV's conversion), a grey PNG's ``tRNS`` level as an alpha
plane. TIFF is written by tifffile (Deflate), PNG by
:mod:`.png` (OpenCV's deflate settings, Sub or Up filter per image: OpenCV's file size or smaller), JPEG by OpenCV.

OpenCV decodes some truncated files without an error (a JPEG cut short gets a grey bottom), so the structure is checked
first: PNG needs its IEND chunk, JPEG its EOI marker after its first scan (data may follow it), TIFF strips/tiles
inside the file and one full-resolution page.
"""

from __future__ import annotations

import dataclasses
import io
import os
import zlib
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import tifffile

from .. import luminance
from ..errors import InputError
from ..physics import srgb, transfers
from ..physics.srgb import bgr_order
from ..types import CameraFrame, ImageEncoding
from . import heif, image_metadata, webp
from .atomic import atomic_path, write_bytes_atomic
from .png import PNG_SIGNATURE, PNGError, decode_png, encode_png, png_chunk

SUFFIX_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".tif": "tiff", ".tiff": "tiff", ".exr": "exr",
                  ".webp": "webp", **heif.FORMATS}
_LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
_RGB_ORDER = {3: slice(None, None, -1), 4: [2, 1, 0, 3]}    # OpenCV's BGR(A) → RGB(A) (3 channels: a view)

_PNG_IEND = b"IEND\xaeB`\x82"            # chunk type + CRC of the (empty) IEND chunk
_JPEG_SOI, _JPEG_EOI = b"\xff\xd8", b"\xff\xd9"
_TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_ICC_TIFF_TAG = 34675
_ICC_JPEG_HEADER = b"ICC_PROFILE\x00"
_ICC_JPEG_CHUNK = 65519                   # 65535 − 2 (length) − 14 (header, sequence number, count)
_EXIF_JPEG_HEADER = b"Exif\x00\x00"
# luma H×V sampling (chroma 1×1) → OpenCV IMWRITE_JPEG_SAMPLING_FACTOR: 4:4:4, 4:2:2, 4:2:0, 4:4:0, 4:1:1
_OPENCV_SAMPLING = {0x11: cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444, 0x21: cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422,
                    0x22: cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420, 0x12: cv2.IMWRITE_JPEG_SAMPLING_FACTOR_440,
                    0x41: cv2.IMWRITE_JPEG_SAMPLING_FACTOR_411}


def image_format(path: str | os.PathLike) -> str:
    """``png`` | ``jpeg`` | ``tiff`` | ``exr`` | ``webp`` | ``heif`` | ``avif`` from the file suffix
    (case-insensitive)."""
    fmt = SUFFIX_FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise InputError(f"unknown image suffix {Path(path).suffix!r}; expected one of {sorted(SUFFIX_FORMATS)}",
                         file=str(path))
    return fmt


def read_image(path: str | os.PathLike, data: bytes | None = None, *, untagged_transfer: str = "srgb"
               ) -> tuple[np.ndarray, ImageEncoding, np.ndarray | None]:
    """Read an image as (H, W, 3) float32 linear RGB, its encoding, and the alpha plane as stored (or None);
    ``data``: the file's bytes when the caller has already read them (the runner, to hash them; an EXR image is read
    by OpenEXR from its path); ``untagged_transfer``: the transfer of a PNG or TIFF that states none."""
    fmt = image_format(path)
    if fmt == "exr":
        return _read_exr_image(Path(path))
    try:
        data = Path(path).read_bytes() if data is None else data
    except OSError as exc:
        raise InputError(f"cannot read image: {exc.strerror or exc}", file=str(path)) from exc
    return decode_image(data, fmt, source=path, untagged_transfer=untagged_transfer)


def decode_image(data: bytes, fmt: str, *, source, untagged_transfer: str = "srgb"
                 ) -> tuple[np.ndarray, ImageEncoding, np.ndarray | None]:
    """:func:`read_image` of the bytes of a PNG, JPEG, TIFF, WebP, HEIF or AVIF file (also a ROS CompressedImage's
    data);
    ``source`` names it in errors. Integer codes are sRGB unless the file states linear
    (:func:`.image_metadata.stated_transfer`) or, stating nothing, ``untagged_transfer`` says so (a JPEG or WebP is
    sRGB)."""
    check_structure(data, fmt, source)
    if fmt in ("heif", "avif"):                     # io/heif.py: codes as stored, ICC, EXIF, the file's settings
        codes, icc, exif, settings = heif.decode(data, fmt, source)
        linear, encoding, alpha = image_from_codes(codes, fmt, source=source, icc=icc,
                                                   transfer=image_metadata.stated_transfer(fmt, settings, icc))
        return linear, dataclasses.replace(encoding, exif=exif, metadata=settings), alpha
    if fmt == "tiff":                               # the first page's directory, parsed once
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            page = tif.pages[0]
            photometric, metadata = page.photometric, image_metadata.tiff_tags(page)
            icc, tiled, extras = _tiff_icc(page), page.is_tiled, tuple(page.extrasamples)
    else:
        photometric, icc, extras = None, icc_profile(data, fmt), ()
        metadata = image_metadata.png_chunks(data) if fmt == "png" else webp.metadata(data)[2] if fmt == "webp" \
            else image_metadata.jfif_density(data) + _jpeg_descriptive_segments(data)
    alpha_tiff = fmt == "tiff" and len(extras) == 1 and photometric in _TIFF_ALPHA_PHOTOMETRICS
    codes = _tiff_with_alpha(data) if alpha_tiff else None
    if codes is None:
        codes = decode_codes(data, fmt, source=source, photometric=photometric)
        if fmt == "tiff" and photometric != tifffile.PHOTOMETRIC.PALETTE:
            codes = _tiff_as_stored(codes, image_metadata.tiff_orientation(metadata), tiled, source)
        if alpha_tiff and extras[0] == tifffile.EXTRASAMPLE.UNASSALPHA:
            codes = _unpremultiplied(codes)
    quality = _jpeg_quality(data) if fmt == "jpeg" else ImageEncoding.jpeg_quality
    transfer = "srgb" if fmt in ("jpeg", "webp") else \
        image_metadata.stated_transfer(fmt, metadata, icc) or untagged_transfer
    linear, encoding, alpha = image_from_codes(codes, fmt, source=source, jpeg_quality=quality, icc=icc,
                                               transfer=transfer)
    layout = _jpeg_frame_layout(data) if fmt == "jpeg" else {"webp_quality": webp.quality(data)} if fmt == "webp" \
        else {}
    if alpha_tiff and extras[0] == tifffile.EXTRASAMPLE.ASSOCALPHA:
        layout["tiff_associated_alpha"] = True
    return linear, dataclasses.replace(encoding, exif=exif_block(data, fmt), metadata=metadata, **layout), alpha


def decode_codes(data: bytes, fmt: str, *, source, photometric=None) -> np.ndarray:
    """Code values of a PNG, JPEG or TIFF file's bytes, grey (H, W) or RGB(A) (H, W, C) as stored: the common PNG
    kinds by :mod:`.png`, the rest by OpenCV; ``photometric``: a TIFF's photometric interpretation (palette and
    CMYK are read otherwise)."""
    if fmt == "png":
        try:
            codes = decode_png(data)
        except PNGError as exc:
            raise InputError(f"corrupt PNG: {exc}", file=str(source)) from None
        if codes is not None:
            return codes
    if photometric == tifffile.PHOTOMETRIC.PALETTE:
        return _palette_tiff_rgb(data)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"OpenCV cannot decode this {fmt.upper()} file ({_undecoded_variant(data, fmt)})",
                         file=str(source))
    if photometric == tifffile.PHOTOMETRIC.SEPARATED and img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]                          # CMYK → OpenCV's BGR + an opaque alpha it adds: RGB, as a JPEG's
    key = image_metadata.png_grey_key(data, img.dtype) if fmt == "png" and img.ndim == 2 else None
    if key is not None:                             # grey + tRNS: grey + alpha, RGBA as OpenCV gives LA PNGs
        alpha = np.where(img == key, 0, np.iinfo(img.dtype).max).astype(img.dtype)
        return np.dstack([img, img, img, alpha])
    return img if img.ndim == 2 else img[..., _RGB_ORDER.get(img.shape[2], slice(None))]


def _tiff_as_stored(codes: np.ndarray, turn: int, tiled: bool, source) -> np.ndarray:
    """A TIFF's codes as stored: OpenCV turns a TIFF's pixels as displayed by its orientation tag (libtiff's oriented
    read; a PNG's and JPEG's it leaves as stored with ``IMREAD_UNCHANGED``), rvnoise reads every file's pixels as
    stored (:mod:`roadview_noise.orientation` turns them for the chain and back). A tiled TIFF with an orientation
    it decodes scrambled (whole tiles flipped in place, OpenCV 5.0): refused."""
    if turn == 1:
        return codes
    if tiled:
        raise InputError(f"a tiled TIFF with orientation {turn} (OpenCV decodes its tiles misplaced): write it in "
                         "strips (tiffcp -s) or store it upright", file=str(source))
    from ..orientation import stored

    return stored(codes, turn)


_TIFF_ALPHA_PHOTOMETRICS = (tifffile.PHOTOMETRIC.RGB, tifffile.PHOTOMETRIC.MINISBLACK)


def _tiff_with_alpha(data: bytes) -> np.ndarray | None:
    """RGBA codes of an RGB or grey TIFF with one alpha sample, as stored (tifffile): OpenCV (libtiff's RGBA read)
    multiplies 8-bit colours by an unassociated alpha — a half-transparent pixel came out half as bright — and turns
    the pixels by the orientation tag. Grey + alpha becomes RGBA, as a grey + alpha PNG does. None when tifffile
    cannot decode it (LZW and JPEG need the ``imagecodecs`` package): OpenCV's then, :func:`_unpremultiplied`."""
    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            page = tif.pages[0]
            codes = page.asarray()
            if page.planarconfig == tifffile.PLANARCONFIG.SEPARATE:
                codes = np.moveaxis(codes, 0, -1)
    except Exception:                                  # a codec tifffile lacks; several exception types
        return None
    if codes.shape[-1] == 2:
        codes = codes[..., [0, 0, 0, 1]]
    return np.ascontiguousarray(codes)


def _unpremultiplied(codes: np.ndarray) -> np.ndarray:
    """8-bit RGBA codes OpenCV multiplied by their unassociated alpha (libtiff: round(c · a / 255)) divided back,
    to within 255 / (2a) codes (exact at full alpha; a colour under alpha 0 is lost); 16-bit ones it leaves."""
    if codes.dtype != np.uint8 or codes.ndim != 3 or codes.shape[2] != 4:
        return codes
    alpha = codes[..., 3:].astype(np.float32)
    colour = np.where(alpha > 0, np.rint(codes[..., :3] * (np.float32(255) / np.maximum(alpha, 1))), 0)
    return np.concatenate([np.clip(colour, 0, 255).astype(np.uint8), codes[..., 3:]], axis=2)


def _palette_tiff_rgb(data: bytes) -> np.ndarray:
    """8-bit RGB codes of a palette TIFF (its 16-bit colour map's high bytes, TIFF 6.0 §5); OpenCV reads the
    palette's grey levels instead of its colours."""
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        page = tif.pages[0]
        index, colormap = page.asarray(), page.colormap
    return np.ascontiguousarray((colormap[:, index] >> 8).astype(np.uint8).transpose(1, 2, 0))


def _undecoded_variant(data: bytes, fmt: str) -> str:
    """Why OpenCV may have refused a file: a JPEG's sample precision or lossless process (T.81 B.2.2), which its
    decoder (8-bit) does not read, else "corrupt or unsupported variant"."""
    marker, seg = _start_of_frame(data) if fmt == "jpeg" else (None, b"")
    if marker in (0xC3, 0xC7, 0xCB, 0xCF):
        return "a lossless JPEG (SOF3): convert it to a 16-bit PNG or TIFF"
    if seg and seg[0] != 8:
        return f"a {seg[0]}-bit JPEG: OpenCV reads 8-bit ones; convert it to a 16-bit PNG or TIFF"
    if fmt == "tiff":
        try:
            with tifffile.TiffFile(io.BytesIO(data)) as tif:
                page = tif.pages[0]
                bits, kind, stated = page.bitspersample, page.sampleformat, 262 in page.tags
        except Exception:                              # tifffile raises several types for a damaged directory
            return "corrupt or unsupported variant"
        if not stated:
            return "no PhotometricInterpretation tag (262), which OpenCV needs: add it (tiffset -s 262 1)"
        if (bits, int(kind)) not in ((8, 1), (16, 1), (32, 3)):
            what = {1: "unsigned", 2: "signed", 3: "floating-point"}.get(int(kind), "")
            return (f"{bits}-bit {what} samples: rvnoise reads 8- and 16-bit unsigned and 32-bit float TIFFs; "
                    "convert it (e.g. to an 8-bit PNG)")
    return "corrupt or unsupported variant"


def image_from_codes(codes: np.ndarray, fmt: str, *, source, jpeg_quality: int = ImageEncoding.jpeg_quality,
                     icc: bytes | None = None, transfer: str = "srgb"
                     ) -> tuple[np.ndarray, ImageEncoding, np.ndarray | None]:
    """Linear RGB, encoding and alpha of code values — grey (H, W) or RGB(A) (H, W, C); uint8/uint16 with the
    ``transfer`` function (``srgb``; ``linear``: code / full scale; ``bt709``, ``gamma22``, ``gamma28``, ``pq``,
    ``hlg``: reference white 1.0, :mod:`..physics.transfers`), or float32 linear for TIFF — stored as ``fmt`` (also
    the pixels of a ROS Image)."""
    if codes.dtype == np.uint8 or codes.dtype == np.uint16:
        bit_depth = 8 * codes.dtype.itemsize
    elif codes.dtype == np.float32 and fmt == "tiff":
        bit_depth, transfer = 32, "linear"
    else:
        raise InputError(f"unsupported sample type {codes.dtype} (expected uint8, uint16 or float32 TIFF)",
                         file=str(source))
    channels = 1 if codes.ndim == 2 else codes.shape[2]
    if channels not in (1, 3, 4):
        raise InputError(f"unsupported channel count {channels} (expected 1, 3 or 4)", file=str(source))
    alpha = codes[..., 3].copy() if channels == 4 else None
    rgb = codes if channels == 1 else codes[..., :3]
    if transfer == "srgb":
        linear = srgb.code_to_linear(rgb, bit_depth)
    elif transfer in transfers.CURVES:
        linear = transfers.code_to_linear(rgb, transfer, bit_depth)
    elif bit_depth == 32:
        linear = rgb.astype(np.float32)
    else:
        linear = rgb * np.float32(1 / (2 ** bit_depth - 1))
    if channels == 1:
        linear = np.repeat(linear[..., None], 3, axis=2)
    encoding = ImageEncoding(fmt=fmt, bit_depth=bit_depth, transfer=transfer, channels=channels,
                             jpeg_quality=jpeg_quality, icc_profile=image_metadata.fitting_icc(icc, channels))
    return np.ascontiguousarray(linear, dtype=np.float32), encoding, alpha


def write_image(path: str | os.PathLike, linear_rgb: np.ndarray, encoding: ImageEncoding,
                alpha: np.ndarray | None = None) -> bytes | None:
    """Encode (H, W, 3) linear RGB like ``encoding`` (sRGB or linear, bit depth, channels, JPEG quality, ICC
    profile) and write it atomically; returns the bytes written (None for EXR, written by OpenEXR). Integer
    encodings are clipped to [0, 1] and rounded here, once; float32 TIFF and EXR are written unclipped. A 4-channel
    encoding without ``alpha`` gets an opaque alpha plane."""
    name = _checked_name(path, encoding)
    if encoding.fmt == "exr":
        _write_exr_image(path, _stored_pixels(linear_rgb, encoding, name), encoding, alpha)
        return None
    data = encode_image(linear_rgb, encoding, alpha, name=name)
    write_bytes_atomic(path, data)
    return data


def write_frame(path: str | Path, frame: CameraFrame) -> bytes | None:
    """:func:`write_image` of a camera frame (the bytes written, None for EXR); for an 8-bit sRGB colour encoding,
    the codes the frame holds (:meth:`CameraFrame.srgb8_codes`: a JPEG output, an unchanged decoded file) are
    stored as they are and its linear values are never decoded."""
    enc = frame.encoding
    kept = frame.srgb8_codes() if (enc.transfer, enc.bit_depth) == ("srgb", 8) and enc.channels in (3, 4) \
        and enc.fmt != "exr" else None
    if kept is None:
        return write_image(path, frame.linear_rgb, enc, alpha=frame.alpha)
    name = _checked_name(path, enc)
    data = encode_codes(_with_alpha(kept, enc, frame.alpha), enc, name=name)
    write_bytes_atomic(path, data)
    return data


def _checked_name(path: str | Path, encoding: ImageEncoding) -> str:
    """The file name of ``path``; ValueError when its suffix is not ``encoding``'s format."""
    name = Path(path).name
    if image_format(path) != encoding.fmt:
        raise ValueError(f"{name}: suffix does not match the encoding format {encoding.fmt!r}")
    return name


def encode_image(linear_rgb: np.ndarray, encoding: ImageEncoding, alpha: np.ndarray | None = None, *,
                 name: str = "image") -> bytes:
    """The PNG, JPEG, TIFF or WebP file bytes :func:`write_image` writes (also a ROS CompressedImage's data); only
    OpenCV's JPEG and WebP encoders get the codes stored in BGR order."""
    return encode_codes(codes_from_image(linear_rgb, encoding, alpha, name=name,
                                         bgr=encoding.fmt in ("jpeg", "webp")), encoding, name=name)


def codes_from_image(linear_rgb: np.ndarray, encoding: ImageEncoding, alpha: np.ndarray | None = None, *,
                     name: str = "image", bgr: bool = True) -> np.ndarray:
    """Code values of linear RGB for an integer or float32 TIFF ``encoding``, grey (H, W) or RGB(A) (H, W, C): the
    inverse of :func:`image_from_codes`; ``name`` identifies the image in errors; ``bgr``: sRGB colour codes stored
    in OpenCV's BGR order (:func:`encode_pixels`), else in RGB order."""
    colour = encoding.channels != 1
    pixels = _stored_pixels(linear_rgb, encoding, name, refuse_nan=not colour)
    codes = encode_pixels(pixels, encoding, bgr=bgr)
    if colour:                                      # after the encode: from the luminance blocks it may have kept
        _refuse_nan(pixels, name)
    return _with_alpha(codes, encoding, alpha)


def _with_alpha(codes: np.ndarray, encoding: ImageEncoding, alpha: np.ndarray | None) -> np.ndarray:
    """``codes`` with the alpha plane appended for a 4-channel encoding (opaque without ``alpha``)."""
    if encoding.channels == 4:
        if alpha is None:
            alpha = np.full(codes.shape[:2], 1.0 if codes.dtype == np.float32 else np.iinfo(codes.dtype).max)
        codes = np.dstack([codes, np.asarray(alpha).astype(codes.dtype)])
    return codes


def encode_codes(codes: np.ndarray, encoding: ImageEncoding, *, name: str = "image") -> bytes:
    """PNG, JPEG (``encoding.jpeg_quality``), TIFF or WebP (``encoding.webp_quality``, None: lossless) bytes of grey
    or RGB(A) code values, with ``encoding.icc_profile`` embedded."""
    if encoding.fmt == "tiff":
        return _encode_tiff(codes, encoding.icc_profile, encoding.metadata, encoding.tiff_associated_alpha)
    if encoding.fmt == "webp":
        return _encode_webp(codes, encoding, name)
    if encoding.fmt in ("heif", "avif"):
        return heif.encode(codes, encoding.fmt, encoding.icc_profile, encoding.exif, encoding.metadata, name)
    if encoding.fmt not in ("png", "jpeg"):
        raise ValueError(f"{name}: {encoding.fmt} images are written to files only (write_image)")
    if encoding.fmt == "png":
        png = embed_exif(embed_icc_profile(encode_png(codes), "png", encoding.icc_profile), "png", encoding.exif)
        return image_metadata.embed_png_chunks(png, encoding.metadata)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(encoding.jpeg_quality),
              cv2.IMWRITE_JPEG_PROGRESSIVE, int(encoding.jpeg_progressive)]
    if codes.ndim == 3:
        codes = bgr_order(codes)
        if encoding.jpeg_sampling is not None:
            params += [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, encoding.jpeg_sampling]
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(codes), params)
    if not ok:
        raise OSError(f"{name}: OpenCV could not encode {encoding}")
    jpeg = image_metadata.with_jfif_density(buf.tobytes(), encoding.metadata)
    jpeg = embed_exif(embed_icc_profile(jpeg, encoding.fmt, encoding.icc_profile), "jpeg", encoding.exif)
    return _with_segments_before_tables(jpeg, b"".join(m for m in encoding.metadata if m.startswith(b"\xff")))


def _encode_webp(codes: np.ndarray, encoding: ImageEncoding, name: str) -> bytes:
    """WebP bytes of RGB(A) codes (a grey encoding's written as colour: WebP has no grey), lossless or at the
    encoding's quality (OpenCV: a quality above 100 is lossless), with the input's ICC, EXIF and XMP chunks."""
    if codes.ndim == 2:
        codes = np.repeat(codes[..., None], 3, axis=2)
    quality = 101 if encoding.webp_quality is None else int(encoding.webp_quality)
    ok, buf = cv2.imencode(".webp", np.ascontiguousarray(bgr_order(codes)), [cv2.IMWRITE_WEBP_QUALITY, quality])
    if not ok:
        raise OSError(f"{name}: OpenCV could not encode {encoding}")
    h, w = codes.shape[:2]
    return webp.with_metadata(buf.tobytes(), w, h, encoding.icc_profile, encoding.exif, encoding.metadata)


def _stored_pixels(linear_rgb: np.ndarray, encoding: ImageEncoding, name: str, *, refuse_nan: bool = True
                   ) -> np.ndarray:
    """The linear pixels to store: RGB, or Rec. 709 luminance for a grey encoding; ValueError for a wrong shape,
    NaN (unless ``refuse_nan`` is False: the caller checks after its encode) or an unsupported channel count."""
    linear_rgb = np.asarray(linear_rgb)
    if linear_rgb.ndim != 3 or linear_rgb.shape[2] != 3:
        raise ValueError(f"expected linear RGB of shape (H, W, 3), got {linear_rgb.shape}")
    if refuse_nan:
        _refuse_nan(linear_rgb, name)
    if encoding.channels not in (1, 3, 4):
        raise ValueError(f"unsupported channel count {encoding.channels}")
    return linear_rgb @ _LUMA_709 if encoding.channels == 1 else linear_rgb


def _refuse_nan(linear: np.ndarray, name: str) -> None:
    """ValueError naming the image when ``linear`` holds NaN. A NaN makes its f×f luminance block NaN, so when an
    8-bit sRGB pass kept the blocks of this very array (:func:`luminance.blocks_of`, the metrics' encode) only
    they and the edge rows and columns outside them are read; else the minimum, NaN when any value is (one pass,
    half the time of counting NaN)."""
    if linear.size == 0:
        return
    blocks = luminance.blocks_of(linear, luminance.metric_scale(*linear.shape[:2])) if linear.ndim == 3 else None
    if blocks is None:
        suspect = np.isnan(np.min(linear))
    else:
        f = luminance.metric_scale(*linear.shape[:2])
        h, w = blocks.shape[0] * f, blocks.shape[1] * f
        suspect = np.isnan(blocks).any() or any(np.isnan(np.min(edge)) for edge in (linear[h:], linear[:h, w:])
                                                 if edge.size)
    n_nan = int(np.count_nonzero(np.isnan(linear))) if suspect else 0
    if n_nan:
        raise ValueError(f"{name}: image has {n_nan} NaN values; a model produced invalid radiance")


def _encode_tiff(codes: np.ndarray, icc: bytes | None, metadata: tuple = (), associated: bool = False) -> bytes:
    """TIFF bytes (Deflate) of RGB(A) or grey code values, with an unassociated alpha (associated: premultiplied,
    as the input stated), the ICC profile and the input's kept tags (:func:`.image_metadata.tiff_tags`)."""
    buf = io.BytesIO()
    colour = codes.ndim == 3
    tifffile.imwrite(buf, codes, photometric="rgb" if colour else "minisblack",
                     extrasamples=("assocalpha" if associated else "unassalpha",) if colour and codes.shape[2] == 4
                     else None,
                     compression="zlib", metadata=None, iccprofile=icc,
                     **image_metadata.tiff_write_args(metadata))
    return buf.getvalue()


# --- OpenEXR -------------------------------------------------------------------------------------------------------


def read_exr_channels(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], list[str]]:
    """Every channel of a scanline/tiled EXR as arrays, and the channel names in file order; InputError if
    unreadable."""
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            order = [c.name for c in exr.header()["channels"]]
            return {name: np.asarray(c.pixels) for name, c in exr.channels().items()}, order
    except (RuntimeError, OSError, ValueError) as exc:      # OpenEXR raises all three for damaged files
        raise InputError(f"corrupt or truncated EXR, OpenEXR cannot read it ({exc})", file=str(path)) from exc


def write_exr_channels(path: str | os.PathLike, channels: dict[str, np.ndarray]) -> None:
    """Write channels (their dtype: float16 → HALF, float32 → FLOAT) as a ZIP-compressed scanline EXR, atomically."""
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in channels.items()}
                                                ) as exr:
        exr.write(str(tmp))


def _read_exr_image(path: Path) -> tuple[np.ndarray, ImageEncoding, np.ndarray | None]:
    channels, order = read_exr_channels(path)
    names = ("R", "G", "B") if {"R", "G", "B"} <= set(channels) else ("Y",) if "Y" in channels else None
    if names is None:
        raise InputError(f"an EXR image has R, G, B (and A) or Y channels; got {order} (a depth EXR is a sidecar: "
                         f"see inputs.depth)", file=str(path))
    planes = [channels[n] for n in names]
    kinds = {p.dtype for p in planes}
    if not kinds <= {np.dtype(np.float16), np.dtype(np.float32)}:
        raise InputError(f"EXR image channels must be half or float, got {sorted(map(str, kinds))}", file=str(path))
    linear = np.dstack(planes * (3 if len(planes) == 1 else 1)).astype(np.float32)
    alpha = channels["A"].astype(np.float32) if "A" in channels and len(names) == 3 else None
    encoding = ImageEncoding(fmt="exr", bit_depth=16 if kinds == {np.dtype(np.float16)} else 32, transfer="linear",
                             channels=len(names) + (alpha is not None))
    return np.ascontiguousarray(linear), encoding, alpha


def _write_exr_image(path, pixels: np.ndarray, encoding: ImageEncoding, alpha: np.ndarray | None) -> None:
    dtype = np.float16 if encoding.bit_depth == 16 else np.float32
    if encoding.channels == 1:
        channels = {"Y": pixels.astype(dtype)}
    else:
        channels = {c: pixels[..., k].astype(dtype) for k, c in enumerate("RGB")}
        if encoding.channels == 4:
            channels["A"] = (np.ones(pixels.shape[:2]) if alpha is None else np.asarray(alpha)).astype(dtype)
    write_exr_channels(path, channels)


# --- ICC colour profiles -------------------------------------------------------------------------------------------


def icc_profile(data: bytes, fmt: str) -> bytes | None:
    """The ICC profile embedded in a PNG (``iCCP``; None when its stream does not inflate, and the file is read as
    sRGB), JPEG (``APP2 ICC_PROFILE``, in sequence), TIFF (tag 34675) or WebP (``ICCP``)."""
    if fmt == "webp":
        return webp.metadata(data)[0]
    if fmt == "png":
        pos = len(PNG_SIGNATURE)
        while pos + 8 <= len(data):
            length, kind = int.from_bytes(data[pos:pos + 4], "big"), data[pos + 4:pos + 8]
            if kind == b"iCCP":
                body = data[pos + 8:pos + 8 + length]
                name_end = body.find(b"\x00")
                try:                                               # name, NUL, compression method 0, zlib stream
                    return zlib.decompress(body[name_end + 2:]) if name_end > 0 else None
                except zlib.error:         # not a zlib stream (Pillow's icc_profile_none.png): no profile, as Pillow
                    return None
            if kind == b"IDAT":
                return None
            pos += 12 + length
        return None
    if fmt == "jpeg":
        chunks = {}
        for marker, segment in _jpeg_segments(data):
            if marker == 0xE2 and segment.startswith(_ICC_JPEG_HEADER):
                chunks[segment[12]] = segment[14:]
        return b"".join(chunks[k] for k in sorted(chunks)) or None
    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            return _tiff_icc(tif.pages[0])
    except Exception:                                 # a damaged directory was reported by check_structure already
        return None


def _tiff_icc(page) -> bytes | None:
    """The ICC profile of a TIFF page (tag 34675)."""
    tag = page.tags.get(_ICC_TIFF_TAG)
    return bytes(tag.value) if tag is not None else None


def embed_icc_profile(data: bytes, fmt: str, icc: bytes | None) -> bytes:
    """PNG or JPEG bytes with ``icc`` embedded: an ``iCCP`` chunk after IHDR (PNG 1.2 §4.2.2.4), or APP2
    ``ICC_PROFILE`` segments after SOI and any JFIF APP0 (ICC.1 Annex B.4)."""
    if not icc:
        return data
    if fmt == "png":
        return _insert_png_chunk(data, b"iCCP", b"ICC Profile\x00\x00" + zlib.compress(icc))
    parts = [icc[i:i + _ICC_JPEG_CHUNK] for i in range(0, len(icc), _ICC_JPEG_CHUNK)]
    segments = b"".join(b"\xff\xe2" + (len(p) + 16).to_bytes(2, "big") + _ICC_JPEG_HEADER + bytes([k + 1, len(parts)])
                        + p for k, p in enumerate(parts))
    return _insert_jpeg_segments(data, segments)


def _insert_png_chunk(data: bytes, kind: bytes, body: bytes) -> bytes:
    """PNG bytes with the chunk ``kind`` holding ``body`` right after IHDR (before any IDAT)."""
    ihdr_end = len(PNG_SIGNATURE) + 12 + int.from_bytes(data[8:12], "big")
    return data[:ihdr_end] + png_chunk(kind, body) + data[ihdr_end:]


def _insert_jpeg_segments(data: bytes, segments: bytes) -> bytes:
    """JPEG bytes with marker ``segments`` after SOI and the JFIF APP0 segment, which must stay first."""
    pos = 2
    if data[2:4] == b"\xff\xe0":
        pos += 2 + int.from_bytes(data[4:6], "big")
    return data[:pos] + segments + data[pos:]


# --- EXIF metadata and the JPEG frame layout ------------------------------------------------------------------------


def exif_block(data: bytes, fmt: str) -> bytes | None:
    """The EXIF data (a TIFF structure: byte order, IFD0 with the orientation tag 274, …) of a JPEG (``APP1
    Exif``, CIPA DC-008 §4.7.2), PNG (``eXIf`` chunk, PNG 1.5 extensions) or WebP (``EXIF`` chunk); None for TIFF
    and files without.

    Pixels are read as stored (no EXIF rotation), so the EXIF is written back unchanged: a viewer shows the output
    turned like the input, and boxes and masks in stored pixel coordinates stay aligned. Its thumbnail, if any, is
    the input's."""
    if fmt == "webp":
        return webp.metadata(data)[1]
    if fmt == "jpeg":
        for marker, segment in _jpeg_segments(data):
            if marker == 0xE1 and segment.startswith(_EXIF_JPEG_HEADER):
                return segment[len(_EXIF_JPEG_HEADER):] or None
        return None
    if fmt == "png":
        pos = len(PNG_SIGNATURE)
        while pos + 8 <= len(data):
            length, kind = int.from_bytes(data[pos:pos + 4], "big"), data[pos + 4:pos + 8]
            if kind == b"eXIf":
                return data[pos + 8:pos + 8 + length] or None
            if kind == b"IDAT":
                return None
            pos += 12 + length
    return None


def embed_exif(data: bytes, fmt: str, exif: bytes | None) -> bytes:
    """PNG or JPEG bytes with ``exif`` (:func:`exif_block`) embedded: an ``eXIf`` chunk after IHDR, or an
    ``APP1 Exif`` segment after SOI and JFIF APP0. EXIF too long for one JPEG segment is left out."""
    if not exif:
        return data
    if fmt == "png":
        return _insert_png_chunk(data, b"eXIf", exif)
    body = _EXIF_JPEG_HEADER + exif
    if len(body) + 2 > 0xFFFF:
        return data
    return _insert_jpeg_segments(data, b"\xff\xe1" + (len(body) + 2).to_bytes(2, "big") + body)


_JPEG_DESCRIPTIVE = ((0xE1, b"http://ns.adobe.com/xap/1.0/\x00"), (0xE1, b"http://ns.adobe.com/xmp/extension/\x00"),
                     (0xED, b"Photoshop 3.0\x00"), (0xFE, b""))      # XMP, extended XMP, IPTC, comment


def _jpeg_descriptive_segments(data: bytes) -> tuple[bytes, ...]:
    """The XMP, IPTC and comment marker segments of a JPEG, whole (marker, length, payload), in file order
    (:mod:`.image_metadata`)."""
    return tuple(b"\xff" + bytes([marker]) + (len(seg) + 2).to_bytes(2, "big") + seg
                 for marker, seg in _jpeg_segments(data)
                 if any(marker == m and seg.startswith(head) for m, head in _JPEG_DESCRIPTIVE))


def _with_segments_before_tables(data: bytes, segments: bytes) -> bytes:
    """JPEG bytes with marker ``segments`` after the application segments (APP0–APP15) that open the file, before
    its first table."""
    if not segments:
        return data
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF and 0xE0 <= data[pos + 1] <= 0xEF:
        pos += 2 + int.from_bytes(data[pos + 2:pos + 4], "big")
    return data[:pos] + segments + data[pos:]


def _jpeg_frame_layout(data: bytes) -> dict:
    """``jpeg_sampling`` (OpenCV's code of the luma sampling factors, chroma at 1 × 1) and ``jpeg_progressive``
    from the JPEG's start-of-frame segment (T.81 B.2.2); no sampling code for grey, CMYK or unusual factors."""
    marker, seg = _start_of_frame(data)
    if marker is None:
        return {}
    comps = [seg[6 + 3 * i:9 + 3 * i] for i in range(seg[5])] if len(seg) > 5 else []
    factors = [c[1] for c in comps if len(c) == 3]
    sampling = None
    if len(factors) == 3 and factors[1] == factors[2] == 0x11 and factors[0] in _OPENCV_SAMPLING:
        sampling = _OPENCV_SAMPLING[factors[0]]
    return {"jpeg_sampling": sampling, "jpeg_progressive": marker in (0xC2, 0xC6, 0xCA, 0xCE)}


def _start_of_frame(data: bytes) -> tuple[int | None, bytes]:
    """``(marker, payload)`` of a JPEG's start-of-frame segment (SOF0–SOF15 but DHT, JPG, DAC); (None, b"")
    without one."""
    for marker, seg in _jpeg_segments(data):
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            return marker, seg
    return None, b""


def _jpeg_segments(data: bytes):
    """``(marker, payload)`` of the JPEG marker segments before the first scan."""
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker, length = data[pos + 1], int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker == 0xDA:                              # start of scan: no more tables before the entropy data
            return
        yield marker, data[pos + 4:pos + 2 + length]
        pos += 2 + length


def display_srgb(linear: np.ndarray) -> np.ndarray:
    """sRGB-encoded float32 values in [0, 1] (8-bit codes / 255) of linear radiance: the image as a display, a JPEG
    or a depth network sees it (monocular depth input, edge guides)."""
    return srgb.linear_to_code(linear, 8).astype(np.float32) * np.float32(1 / 255)


def encode_pixels(linear: np.ndarray, encoding: ImageEncoding, *, bgr: bool = True) -> np.ndarray:
    """Code values of linear pixels for ``encoding``: uint8/uint16 (clipped to the full code: 1.0, a BT.2100 curve's
    peak; rounded) or float32 (linear TIFF); sRGB
    colour codes are the RGB view of an array in OpenCV's BGR order (``bgr``), written so by one compiled pass, or a
    plain RGB array (the PNG and TIFF writers: no reorder before the encoder, 1.6–2 ms less a 1936×1464 frame)."""
    if encoding.bit_depth == 32:
        if encoding.transfer != "linear":
            raise ValueError("float32 images are stored linear")
        return np.asarray(linear, dtype=np.float32)
    if encoding.transfer == "srgb":
        if bgr and np.ndim(linear) == 3 and np.shape(linear)[2] == 3:
            # the RGB view of BGR codes: bgr_order hands their storage to OpenCV as it is
            return srgb.linear_to_code(linear, encoding.bit_depth, bgr=True)[..., ::-1]
        return srgb.linear_to_code(linear, encoding.bit_depth)
    if encoding.transfer in transfers.CURVES:               # RGB order whatever ``bgr`` (never JPEG or WebP)
        return transfers.linear_to_code(linear, encoding.transfer, encoding.bit_depth)
    if encoding.transfer == "linear" and encoding.bit_depth in (8, 16):
        full = 2 ** encoding.bit_depth - 1
        dtype = np.uint8 if encoding.bit_depth == 8 else np.uint16
        return np.rint(np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0) * np.float32(full)).astype(dtype)
    raise ValueError(f"unsupported encoding {encoding}")


# --- structure checks ---------------------------------------------------------------------------------------------


def check_structure(data: bytes, fmt: str, path) -> None:
    """Raise :class:`InputError` for a file that is not ``fmt`` or is cut short (see module docstring; HEIF and
    AVIF: the decoder reports a file cut short)."""
    if fmt == "webp":
        webp.check_structure(data, path)
    elif fmt in ("heif", "avif"):
        heif.check_structure(data, fmt, path)
    elif fmt == "png":
        if not data.startswith(PNG_SIGNATURE):
            raise InputError("not a PNG file (bad signature)", file=str(path))
        if data.rfind(_PNG_IEND) < 0:
            raise InputError("truncated PNG: the IEND chunk is missing", file=str(path))
    elif fmt == "jpeg":
        if not data.startswith(_JPEG_SOI):
            raise InputError("not a JPEG file (no SOI marker FF D8)", file=str(path))
        if not data.rstrip(b"\x00\r\n").endswith(_JPEG_EOI) and data.find(_JPEG_EOI, _first_scan(data)) < 0:
            raise InputError("truncated JPEG: the end-of-image marker FF D9 is missing", file=str(path))
    else:
        if not data.startswith(_TIFF_SIGNATURES):
            raise InputError("not a TIFF file (bad byte-order header)", file=str(path))
        try:
            with tifffile.TiffFile(io.BytesIO(data)) as tif:
                page = tif.pages[0]
                end = max((o + c for o, c in zip(page.dataoffsets, page.databytecounts)), default=0)
                expected = len(page.dataoffsets)
                pages = image_metadata.full_resolution_pages(tif)
        except Exception as exc:                      # tifffile raises several types for a damaged directory
            raise InputError(f"corrupt or truncated TIFF: {exc}", file=str(path)) from exc
        if expected == 0 or end > len(data):
            raise InputError(f"truncated TIFF: image data ends at byte {end}, the file has {len(data)} bytes",
                             file=str(path))
        if pages > 1:
            raise InputError(f"a TIFF with {pages} pages: rvnoise augments one image per file and would drop the "
                             f"other pages; split it into single-page files first (tiffsplit, tifffile)",
                             file=str(path))


def _first_scan(data: bytes) -> int:
    """Offset of the first start-of-scan marker of a JPEG (the end of :func:`_jpeg_segments`); the entropy-coded
    data after it cannot hold FF D9 (T.81 B.1.1.5: an FF there is followed by 00 or a restart marker), so an FF D9
    after it ends the image even when a phone appended data (Samsung's trailer, a Motion Photo's MP4)."""
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF and data[pos + 1] != 0xDA:
        pos += 2 + int.from_bytes(data[pos + 2:pos + 4], "big")
    return pos


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
    for marker, seg in _jpeg_segments(data):
        if marker != 0xDB:
            continue
        k = 0
        while k < len(seg):
            precision, table_id = seg[k] >> 4, seg[k] & 15
            n = 128 if precision else 64
            values = np.frombuffer(seg[k + 1:k + 1 + n], ">u2" if precision else "u1").astype(np.int64)
            if table_id == 0 and len(values) == 64:
                return int(np.argmin(np.abs(_ijg_tables() - values).sum(axis=1))) + 1
            k += 1 + n
    return ImageEncoding.jpeg_quality
