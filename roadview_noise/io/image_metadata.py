"""Image metadata beyond the ICC profile and EXIF that a camera file carries and rvnoise writes back unchanged
(:attr:`..types.ImageEncoding.metadata`), and the checks of what the pixels mean that OpenCV does not make.

- PNG: the ancillary chunks that describe the image, not its encoding (PNG 3rd ed. §11.3): text (``tEXt``, ``zTXt``,
  ``iTXt`` — where ImageMagick keeps the EXIF, ``Raw profile type exif``, and Adobe the XMP, both with the
  orientation), ``pHYs`` (pixel size) and the colour chunks ``gAMA``, ``cHRM``, ``sRGB``, ``cICP`` (the same colour
  encoding is written back). Left out: what depends on the colour type or palette (``tRNS`` is the alpha plane,
  ``bKGD``, ``sBIT``, ``hIST``, ``sPLT``), ``tIME`` (the last modification) and animation chunks.
- TIFF: orientation (274), description, make, model, date, artist, copyright, XMP (700), the resolution and the
  GeoTIFF tags (an aerial or mapping camera's georeference: 33550, 33922, 34264, 34735–34737).
- JPEG: the JFIF density (APP0: units and X, Y density, the dots per inch viewers show), which OpenCV writes 1:1,
  and the descriptive marker segments, whole: XMP (APP1 ``http://ns.adobe.com/xap/1.0/``, extended XMP), IPTC
  (APP13 ``Photoshop 3.0``) and comments (COM). Left out: MPF (APP2: offsets of the images a phone appends after
  the end of the image, which are not written) and other application segments.
- An ICC profile whose colour space the written image cannot have (a grey profile on the RGBA file a grey + alpha
  PNG becomes, a CMYK profile on the RGB file OpenCV decodes a CMYK JPEG to) is dropped: ICC.1 §7.2.6, a viewer
  would reject or misread it (an RGB profile on a grey file is kept, as the input had it).
"""

from __future__ import annotations

import numpy as np
import tifffile

from .png import PNG_SIGNATURE

_PNG_KEPT = (b"tEXt", b"zTXt", b"iTXt", b"pHYs", b"gAMA", b"cHRM", b"sRGB", b"cICP")
_TIFF_KEPT = (270, 271, 272, 274, 306, 315, 700, 33432,  # description … orientation, datetime, artist, XMP, copyright
              33550, 33922, 34264, 34735, 34736, 34737)  # GeoTIFF: pixel scale, tie points, transformation, geo keys
_TIFF_RESOLUTION = (282, 283, 296)                       # XResolution, YResolution, ResolutionUnit
_ICC_NEVER_WRITTEN = (b"CMYK", b"CMY ")                     # ICC data colour spaces rvnoise never writes


def png_chunk_spans(data: bytes):
    """``(type, offset of the chunk, length of its body)`` of a PNG's chunks before IEND, in file order."""
    pos = len(PNG_SIGNATURE)
    while pos + 8 <= len(data):
        length, kind = int.from_bytes(data[pos:pos + 4], "big"), data[pos + 4:pos + 8]
        if kind == b"IEND":
            return
        yield kind, pos, length
        pos += 12 + length


def png_chunks(data: bytes) -> tuple[bytes, ...]:
    """The kept ancillary chunks of a PNG file (module docstring), whole (length, type, body, CRC), in file order."""
    return tuple(data[pos:pos + 12 + length] for kind, pos, length in png_chunk_spans(data) if kind in _PNG_KEPT)


def png_grey_key(data: bytes, dtype) -> int | None:
    """The grey level a grey PNG's ``tRNS`` chunk makes transparent (PNG 3rd ed. §11.3.1.5), scaled as OpenCV
    decodes grey of 1–4 bits (to 0–255); None for another colour type or without ``tRNS``. OpenCV ignores it, so a
    transparent background came out opaque (an RGB PNG's ``tRNS`` it turns into an alpha plane)."""
    bit_depth, colour_type = data[24], data[25]
    if colour_type != 0:
        return None
    for kind, pos, length in png_chunk_spans(data):
        if kind == b"tRNS" and length == 2:
            key = int.from_bytes(data[pos + 8:pos + 10], "big")
            return key * 255 // (2 ** bit_depth - 1) if bit_depth < 8 and np.dtype(dtype) == np.uint8 else key
        if kind == b"IDAT":
            return None
    return None


def embed_png_chunks(data: bytes, chunks: tuple[bytes, ...]) -> bytes:
    """PNG bytes with ``chunks`` right after IHDR (every kept chunk may precede PLTE and IDAT)."""
    if not chunks:
        return data
    ihdr_end = len(PNG_SIGNATURE) + 12 + int.from_bytes(data[8:12], "big")
    return data[:ihdr_end] + b"".join(chunks) + data[ihdr_end:]


_JFIF = b"\xff\xd8\xff\xe0"                 # SOI, then an APP0 segment …
_JFIF_ID, _JFIF_DENSITY = slice(6, 11), slice(13, 18)     # … "JFIF\0"; units, X density, Y density (JFIF 1.02)


def jfif_density(data: bytes) -> tuple[bytes, ...]:
    """A JPEG's JFIF density — units (0 aspect ratio, 1 dots per inch, 2 per cm), X and Y density: the "dpi" viewers
    and print layouts read — as a one-item metadata tuple (empty without a JFIF APP0 segment)."""
    if data.startswith(_JFIF) and data[_JFIF_ID] == b"JFIF\x00" and len(data) > _JFIF_DENSITY.stop:
        return (data[_JFIF_DENSITY],)
    return ()


def with_jfif_density(data: bytes, metadata: tuple) -> bytes:
    """JPEG bytes (OpenCV writes a JFIF APP0 with a 1:1 aspect ratio) with the input's JFIF density
    (:func:`jfif_density`: the one item of a JPEG's metadata that is no marker segment)."""
    density = next((m for m in metadata if not m.startswith(b"\xff")), None)
    if density is None or not jfif_density(data):
        return data
    return data[:_JFIF_DENSITY.start] + density + data[_JFIF_DENSITY.stop:]


def tiff_tags(page) -> tuple:
    """The kept tags of a TIFF page as tifffile ``extratags`` ``(code, dtype, count, value, True)``, and the
    resolution ``((x, y), unit)`` last when the file states a valid one (rationals with non-zero denominators)."""
    kept = tuple((t.code, t.dtype, None if t.dtype == 2 else t.count, _tag_value(t), True) for t in page.tags
                 if t.code in _TIFF_KEPT)
    tags = page.tags
    if all(code in tags and _rational(tags[code].value) for code in _TIFF_RESOLUTION[:2]):
        unit = tags[296].value if 296 in tags else 2
        kept += (("resolution", (tags[282].value, tags[283].value), int(unit)),)
    return kept


def _rational(value) -> bool:
    """True for a TIFF RATIONAL tifffile can write back: (numerator, denominator > 0)."""
    return isinstance(value, tuple) and len(value) == 2 and value[1] > 0 and value[0] >= 0


def _tag_value(tag):
    """A tag's value as tifffile writes it back: an ASCII tag's text as bytes (tifffile refuses a ``str`` beyond
    7-bit ASCII, as Photoshop's ``®`` in its ImageDescription), the orientation as a plain int."""
    if tag.dtype == 2:
        return tag.value.encode("utf-8", "surrogateescape") if isinstance(tag.value, str) else bytes(tag.value)
    return int(tag.value) if tag.code == 274 else tag.value


def tiff_write_args(metadata: tuple) -> dict:
    """tifffile ``write`` arguments that put :func:`tiff_tags` back."""
    extratags = [t for t in metadata if t[0] != "resolution"]
    args = {"extratags": extratags} if extratags else {}
    for t in metadata:
        if t[0] == "resolution":
            args.update(resolution=t[1], resolutionunit=t[2])
    return args


def fitting_icc(icc: bytes | None, channels: int) -> bytes | None:
    """``icc`` unless its data colour space (header bytes 16–19) is one an image of ``channels`` written channels
    cannot have: CMYK, or grey on colour (other profiles are copied as they came)."""
    space = (icc or b"")[16:20]
    if space in _ICC_NEVER_WRITTEN or (space == b"GRAY" and channels != 1):
        return None
    return icc


def full_resolution_pages(tif: tifffile.TiffFile) -> int:
    """How many full-resolution images a TIFF holds (a multi-page file, a stack: refused, as rvnoise reads one image
    per file and would drop the others); reduced-resolution pages (thumbnails, NewSubfileType bit 0) do not count."""
    return sum(1 for page in tif.pages if not int(getattr(page, "subfiletype", 0)) & 1)


def orientation(encoding) -> int:
    """The EXIF/TIFF orientation (274) of a file as read (:class:`..types.ImageEncoding`): 1 = stored upright, 2–8 a
    viewer turns or mirrors the stored pixels to show them (CIPA DC-008 §4.6.4); 1 when the file states none."""
    if encoding.fmt == "tiff":
        return tiff_orientation(encoding.metadata)
    found = exif_orientation_at(encoding.exif or b"")
    if found is None:
        return 1
    at, order = found
    value = int.from_bytes(encoding.exif[at:at + 2], order)
    return value if 1 <= value <= 8 else 1


def exif_orientation_at(exif: bytes) -> tuple[int, str] | None:
    """(offset of the orientation value, byte order) in an EXIF block — IFD0's tag 274; the block may start with
    JPEG's ``Exif\\0\\0`` header, as a WebP EXIF chunk or Pillow's may — or None when it states none."""
    start = 6 if exif.startswith(b"Exif\x00\x00") else 0
    tiff = exif[start:]
    if tiff[:4] not in (b"II*\x00", b"MM\x00*"):
        return None
    order = "little" if tiff[:2] == b"II" else "big"
    ifd = int.from_bytes(tiff[4:8], order)
    for k in range(int.from_bytes(tiff[ifd:ifd + 2], order)):
        entry = tiff[ifd + 2 + 12 * k:ifd + 14 + 12 * k]
        if len(entry) == 12 and int.from_bytes(entry[:2], order) == 274:
            return start + ifd + 2 + 12 * k + 8, order
    return None


def tiff_orientation(metadata: tuple) -> int:
    """The orientation (274) among a TIFF's kept tags (:func:`tiff_tags`); 1 when it states none or a bad value."""
    for tag in metadata:
        if tag[0] == 274:
            return int(tag[3]) if 1 <= int(tag[3]) <= 8 else 1
    return 1


_PNG_GAMMA_LINEAR = 100000                  # gAMA of 1.0 (the chunk stores 100 000 × the encoding's exponent)
#: H.273 (ITU-T H.273 Table 3) transfer characteristics rvnoise decodes as stated: PNG cICP, HEIF nclx
#: (``physics/transfers.py``; 1, 6, 14, 15 are one OETF: BT.709, BT.601, BT.2020 10- and 12-bit)
CICP_TRANSFERS = {1: "bt709", 4: "gamma22", 5: "gamma28", 6: "bt709", 8: "linear", 13: "srgb", 14: "bt709",
                  15: "bt709", 16: "pq", 18: "hlg"}
_CICP_UNSPECIFIED = 2
CICP_TRANSFER_NAMES = {1: "BT.709", 4: "gamma 2.2", 5: "gamma 2.8", 6: "BT.601", 7: "SMPTE 240M", 8: "linear",
                       9: "log 100:1", 10: "log 316:1", 11: "IEC 61966-2-4", 12: "BT.1361", 13: "sRGB",
                       14: "BT.2020 10-bit", 15: "BT.2020 12-bit", 16: "BT.2100 PQ", 17: "SMPTE ST 428",
                       18: "BT.2100 HLG"}


def stated_transfer(fmt: str, metadata: tuple, icc: bytes | None) -> str | None:
    """The transfer function of integer codes as the file states it: :data:`CICP_TRANSFERS` for a PNG ``cICP`` or
    HEIF ``nclx`` transfer in it (``bt709``, ``gamma22``, ``linear``, ``srgb``, ``pq``, …); ``linear`` for a PNG
    ``gAMA`` of 1.0 with no ``cICP``, ``iCCP`` or ``sRGB`` above it (PNG 3rd ed. §4.3's precedence); ``srgb``
    for any other statement (``sRGB``, ``gAMA``, another ``cICP``/``nclx`` transfer — :func:`unread_transfer` —,
    an ICC profile: read as sRGB, not colour-managed); None when a PNG or TIFF states none — the PNG spec leaves
    that to the reader ("choose a likely default … but allow the user to select a new one", PNG 1.2 §10.5):
    ``inputs.untagged_transfer``."""
    code = cicp_transfer(fmt, metadata)
    if code is not None:
        return CICP_TRANSFERS.get(code, "srgb")
    chunks = {c[4:8]: c[8:-4] for c in metadata} if fmt == "png" else {}
    if icc is not None or b"sRGB" in chunks or fmt in ("heif", "avif"):
        return "srgb"
    if b"gAMA" in chunks:
        return "linear" if int.from_bytes(chunks[b"gAMA"], "big") == _PNG_GAMMA_LINEAR else "srgb"
    return None


def cicp_transfer(fmt: str, metadata: tuple) -> int | None:
    """The H.273 transfer characteristics a PNG's ``cICP`` chunk or a HEIF's ``nclx`` (:mod:`.heif` settings)
    states, None without."""
    if fmt == "png":
        return next((c[9] for c in metadata if c[4:8] == b"cICP" and len(c) == 16), None)
    return dict(metadata).get("nclx", (None, None))[1] if fmt == "heif" else None


def unread_transfer(fmt: str, metadata: tuple) -> int | None:
    """The H.273 transfer a PNG ``cICP`` or HEIF ``nclx`` states that rvnoise does not decode (SMPTE 240M, log,
    IEC 61966-2-4, BT.1361, ST 428, reserved; :data:`CICP_TRANSFERS` are decoded, 2 is "unspecified"): its codes
    are read as sRGB, which a warning says; None otherwise."""
    code = cicp_transfer(fmt, metadata)
    return code if code not in (None, _CICP_UNSPECIFIED, *CICP_TRANSFERS) else None
