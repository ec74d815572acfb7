"""HEIF/HEIC and AVIF camera files (phones, recent datasets, Sony/Canon ``.HIF``): decoded and encoded with the
optional extra ``heif`` (``pip install 'roadview_noise[heif]'``; ``make install`` installs it): pillow-heif
(libheif: libde265, x265) for ``.heic``/``.heif``/``.hif``, Pillow's own AVIF plugin (libavif, Pillow ≥ 11.3
wheels) for ``.avif``.

- The file's primary image, RGB, RGBA or grey; other images a HEIF holds (a burst, depth or auxiliary images,
  thumbnails) are not kept.
- Bit depth. A HEIF is decoded at its own depth, 8, 10 or 12 bits (pillow-heif ``convert_hdr_to_8bit=False,
  hdr_to_16bit=False``: codes 0 … 2ᵇ − 1, grey too). 10/12-bit codes are scaled to 16 bits, round(c · 65535 /
  (2ᵇ − 1)), and go through the chain as a 16-bit PNG's (the sRGB tables are 8- and 16-bit); the writer scales
  them back and encodes at the file's depth. The scaling moves a code by at most ½ · (2ᵇ − 1) / 65535 < 1/100 of a
  code, so an unchanged image gets its own codes back before the encoder. pillow-heif's own 16-bit form (codes
  shifted left, 1023 → 65472) would read white as 0.9990 of full scale. Pillow's AVIF plugin decodes and encodes
  8 bits only: a 10/12-bit AVIF (the depth its ``av1C`` box states) is read and written at 8 bits, and
  :func:`notes` says so (manifest and a run's warning), never silently.
- Kept from the input: the chroma subsampling (HEIF: libheif's ``chroma``; AVIF: ``av1C``), a HEIF's ``nclx``
  colour description (primaries, transfer, matrix, range: a BT.2100 HLG file stays tagged HLG; its transfer decodes
  the codes as :func:`.image_metadata.stated_transfer` says: BT.709, gamma, PQ, HLG, linear or sRGB), the ICC
  profile, the EXIF block and the XMP packet.
- Orientation as for JPEG (:mod:`roadview_noise.orientation`): the pixels as stored with the EXIF orientation
  the file's ``irot``/``imir`` transforms state. Pillow's AVIF plugin reads them so; libheif applies the
  transforms, and pillow-heif's ``set_orientation`` sets the EXIF tag to 1 and drops an XMP ``tiff:Orientation``
  as the plugin does, so the pixels are turned back to the stored layout and the tag restored. Written back, the
  encoders turn the EXIF orientation into ``irot``/``imir`` again: a viewer shows the output turned like the
  input. A HEIF turned by ``irot``/``imir`` without an EXIF orientation tag is read as displayed and written
  upright.
- Neither format records its encoder's quality and the libraries estimate none: the output is written at
  :data:`QUALITY` (libheif's default is 50, Pillow's AVIF 75), ``inputs.heif_quality`` in the manifest.

The file's settings travel in :attr:`..types.ImageEncoding.metadata` as ``(name, value)`` pairs: ``bit_depth``,
``chroma``, ``nclx`` (4 ints) and ``xmp``.
"""

from __future__ import annotations

import io
from functools import lru_cache

import numpy as np

from ..errors import InputError

FORMATS = {".heic": "heif", ".heif": "heif", ".hif": "heif", ".avif": "avif"}   # .hif: Sony, Canon
QUALITY = 90                      # the output's encoder quality (0–100): the input's is not recorded
EXTRA = "pip install 'roadview_noise[heif]' (make install installs it)"
AVIF_BITS = 8                     # what Pillow's AVIF plugin decodes and encodes
_CHANNELS = {"L": None, "I": None, "RGB": None, "RGBA": None, "LA": [0, 0, 0, 1]}   # pillow-heif mode → channels
_PIL_MODES = {"RGB": "RGB", "RGBA": "RGBA", "L": "L", "LA": "RGBA", "P": "RGBA"}    # Pillow's AVIF modes
_NCLX = ("color_primaries", "transfer_characteristics", "matrix_coefficients", "full_range_flag")
_AVIF_CHROMA = {(1, 1): 420, (1, 0): 422, (0, 0): 444}        # av1C (subsampling x, y) → chroma
_SUBSAMPLING = {420: "4:2:0", 422: "4:2:2", 444: "4:4:4"}


@lru_cache(maxsize=2)
def _codec(fmt: str):
    """pillow_heif (``heif``) or PIL.Image with its AVIF plugin (``avif``); InputError naming the extra when it is
    not installed."""
    try:
        from PIL import Image, features
        if fmt == "heif":
            import pillow_heif

            return pillow_heif
    except ImportError:
        raise InputError(f".{'heic' if fmt == 'heif' else fmt} photos need the optional extra heif: {EXTRA}") \
            from None
    if not features.check("avif"):
        raise InputError(f".avif photos need Pillow with AVIF support (Pillow ≥ 11.3 wheels): {EXTRA}")
    return Image


def missing(fmt: str) -> str | None:
    """Why ``fmt`` (heif | avif) files cannot be read here (the extra to install), None when they can."""
    try:
        _codec(fmt)
    except InputError as exc:
        return str(exc)
    return None


def check_structure(data: bytes, fmt: str, path) -> None:
    """InputError naming the file when it is not an ISO base media file (no ``ftyp`` box first)."""
    if data[4:8] != b"ftyp":
        raise InputError(f"not a{'n AVIF' if fmt == 'avif' else ' HEIF'} file (no ftyp box)", file=str(path))


def decode(data: bytes, fmt: str, source) -> tuple[np.ndarray, bytes | None, bytes | None, tuple]:
    """``(codes, ICC profile, EXIF, settings)`` of a HEIF or AVIF file's primary image: uint8 codes, or uint16 on
    16 bits for a 10/12-bit HEIF, (H, W) grey or (H, W, C) RGB(A) as stored, with the EXIF orientation of the
    file's transforms; ``settings``: the ``(name, value)`` pairs the writer keeps (module docstring)."""
    from ..orientation import stored
    from .image_metadata import exif_orientation_at

    codec = _codec(fmt)
    try:
        codes, info, settings = (_decode_heif if fmt == "heif" else _decode_avif)(codec, data, source)
    except InputError:
        raise
    except Exception as exc:                  # the decoders raise several types for a damaged or truncated file
        raise InputError(f"cannot decode this {fmt.upper()} file ({type(exc).__name__}: {exc})",
                         file=str(source)) from None
    icc, exif, turned = info.get("icc_profile") or None, info.get("exif") or None, info["turned"]
    if turned != 1 and exif is not None and exif_orientation_at(exif) is not None:
        codes, exif = stored(codes, turned), with_orientation(exif, turned)
    xmp = info.get("xmp") or None
    return np.ascontiguousarray(codes), icc, exif, settings + ((("xmp", bytes(xmp)),) if xmp else ())


def _decode_heif(pillow_heif, data: bytes, source) -> tuple[np.ndarray, dict, tuple]:
    """Codes (16-bit scale above 8 bits), info and settings of a HEIF by pillow-heif at the file's depth."""
    heif_file = pillow_heif.open_heif(io.BytesIO(data), convert_hdr_to_8bit=False, hdr_to_16bit=False)
    info = dict(heif_file.info)
    info["turned"] = pillow_heif.set_orientation(info) or 1
    base, bits = heif_file.mode.split(";")[0], int(info.get("bit_depth") or 8)
    if base not in _CHANNELS or bits not in (8, 10, 12):
        raise InputError(f"a {bits}-bit HEIF image of mode {heif_file.mode}: rvnoise reads 8-, 10- and 12-bit RGB, "
                         "RGBA and grey (alpha not premultiplied)", file=str(source))
    codes = np.asarray(heif_file)
    if _CHANNELS[base] is not None:
        codes = codes[..., _CHANNELS[base]]
    if bits > 8:
        codes = rescaled(codes, 2 ** bits - 1, 65535)
    settings = (("bit_depth", bits),) + ((("chroma", int(info["chroma"])),) if info.get("chroma") else ())
    nclx = info.get("nclx_profile")
    return codes, info, settings + ((("nclx", tuple(int(nclx[k]) for k in _NCLX)),) if nclx else ())


def _decode_avif(image_module, data: bytes, source) -> tuple[np.ndarray, dict, tuple]:
    """8-bit codes, info and settings of an AVIF by Pillow; the file's depth and chroma from its ``av1C``."""
    with image_module.open(io.BytesIO(data), formats=["AVIF"]) as im:
        im.load()
        mode = _PIL_MODES.get(im.mode)
        if mode is None:
            raise InputError(f"an AVIF image of mode {im.mode}: rvnoise reads RGB, RGBA and grey", file=str(source))
        codes = np.asarray(im if im.mode == mode else im.convert(mode))
        info = dict(im.info, turned=int(im.info.get("original_orientation") or 1))
    bits, chroma = av1_layout(data)
    return codes, info, (("bit_depth", bits),) + ((("chroma", chroma),) if chroma else ())


def rescaled(codes: np.ndarray, full: int, to_full: int) -> np.ndarray:
    """Integer codes on the scale 0 … ``full`` as uint16 codes on 0 … ``to_full``, rounded to nearest (exact
    integer arithmetic: both scales are odd, so no value falls on a half)."""
    wide = codes.astype(np.uint32)
    return ((wide * np.uint32(to_full) + np.uint32(full // 2)) // np.uint32(full)).astype(np.uint16)


def written_bits(fmt: str, settings: dict) -> int:
    """Bits per sample the writer encodes: a HEIF's own depth, 8 for AVIF (Pillow's plugin)."""
    return int(settings.get("bit_depth", 8)) if fmt == "heif" else AVIF_BITS


def encode(codes: np.ndarray, fmt: str, icc: bytes | None, exif: bytes | None, settings: tuple, name: str) -> bytes:
    """HEIF or AVIF bytes of codes (grey or RGB(A), RGB order; uint16 on 16 bits for a 10/12-bit HEIF) at
    :data:`QUALITY` with the file's ``settings`` (:func:`decode`), ``icc`` and ``exif`` (its orientation becomes
    the file's ``irot``/``imir``)."""
    codec, kept = _codec(fmt), dict(settings)
    buf = io.BytesIO()
    extra = {k: v for k, v in (("icc_profile", icc), ("exif", exif), ("xmp", kept.get("xmp"))) if v}
    try:
        if fmt == "avif":
            if codes.dtype != np.uint8:
                raise ValueError(f"Pillow's AVIF plugin encodes {AVIF_BITS}-bit codes, got {codes.dtype}")
            if "chroma" in kept and codes.ndim == 3:
                extra["subsampling"] = _SUBSAMPLING[kept["chroma"]]
            codec.fromarray(np.ascontiguousarray(codes)).save(buf, format="AVIF", quality=QUALITY, **extra)
        else:
            _encode_heif(codec, codes, written_bits(fmt, kept), kept, extra, buf)
    except (OSError, ValueError, RuntimeError) as exc:
        raise OSError(f"{name}: cannot encode {fmt.upper()}: {exc}") from None
    return buf.getvalue()


def _encode_heif(pillow_heif, codes: np.ndarray, bits: int, kept: dict, extra: dict, buf) -> None:
    """Write ``codes`` as a ``bits``-bit HEIF (x265) into ``buf`` with the kept chroma and nclx and ``extra``."""
    if (codes.dtype == np.uint8) != (bits == 8) or bits not in (8, 10, 12):
        raise ValueError(f"{codes.dtype} codes cannot be written as a {bits}-bit HEIF (x265 codes 8, 10 or 12 bits)")
    if bits > 8:
        codes = rescaled(codes, 65535, 2 ** bits - 1)
    mode = {2: "L", 3: "RGB", 4: "RGBA"}[codes.ndim if codes.ndim == 2 else codes.shape[2]]
    if "chroma" in kept and codes.ndim == 3:
        extra["chroma"] = kept["chroma"]
    if "nclx" in kept:
        extra.update(zip(_NCLX, kept["nclx"]))
    h, w = codes.shape[:2]
    pillow_heif.from_bytes(mode + (f";{bits}" if bits > 8 else ""), (w, h), np.ascontiguousarray(codes).tobytes()
                           ).save(buf, quality=QUALITY, **extra)


def notes(encoding) -> tuple[dict, list[str]]:
    """The manifest's ``inputs`` notes of a HEIF or AVIF frame (quality, bit depth and chroma written) and its
    warnings: ``avif_8bit`` when a 10/12-bit AVIF is written at 8 bits (the transfer: ``camera_inputs``)."""
    kept = dict(encoding.metadata)
    bits, written = int(kept.get("bit_depth", 8)), written_bits(encoding.fmt, kept)
    out = {"heif_quality": {"value": QUALITY, "from": "rvnoise's default (the file records no quality)"},
           "heif_bit_depth": {"value": written, "file": bits,
                              "from": "the file" if written == bits else "Pillow's AVIF plugin codes 8 bits"}}
    if "chroma" in kept and encoding.channels != 1:
        out["heif_chroma"] = {"value": _SUBSAMPLING[kept["chroma"]], "from": "the file"}
    return out, ["avif_8bit"] if written < bits else []


def av1_layout(data: bytes) -> tuple[int, int | None]:
    """(bits per sample, chroma 420 | 422 | 444, None for grey) of an AVIF's primary image from its ``av1C``
    property (AV1-ISOBMFF §2.3.3: ``high_bitdepth``, ``twelve_bit``, ``monochrome``, ``chroma_subsampling_x/y``),
    found through the ``pitm`` and ``ipma`` boxes of its ``meta`` (ISO/IEC 14496-12 §8.11, 23008-12 §9.3);
    (8, None) when the boxes are not found (Pillow then refuses the file)."""
    meta = _child(data, 0, len(data), b"meta")
    if meta is None:
        return 8, None
    start, end = meta[0] + 4, meta[1]                        # a full box: version and flags first
    pitm, iprp = _child(data, start, end, b"pitm"), _child(data, start, end, b"iprp")
    ipco = _child(data, *iprp, b"ipco") if iprp else None
    ipma = _child(data, *iprp, b"ipma") if iprp else None
    if not (pitm and ipco and ipma):
        return 8, None
    wide = data[pitm[0]] != 0                                 # pitm version 1: 32-bit item IDs
    primary = int.from_bytes(data[pitm[0] + 4:pitm[0] + (8 if wide else 6)], "big")
    properties = list(_boxes(data, *ipco))
    for index in _associations(data, ipma, primary):
        if 0 < index <= len(properties) and properties[index - 1][0] == b"av1C":
            b = data[properties[index - 1][1][0] + 2]
            bits = 12 if b & 0x60 == 0x60 else 10 if b & 0x40 else 8
            return bits, None if b & 0x10 else _AVIF_CHROMA.get(((b >> 3) & 1, (b >> 2) & 1))
    return 8, None


def _associations(data: bytes, ipma: tuple[int, int], item: int) -> list[int]:
    """The 1-based ``ipco`` indices ``ipma`` associates with ``item``."""
    pos, end = ipma
    version, flags = data[pos], data[pos + 3]
    count, pos = int.from_bytes(data[pos + 4:pos + 8], "big"), pos + 8
    id_size, index_size = (4 if version >= 1 else 2), (2 if flags & 1 else 1)
    for _ in range(count):
        item_id = int.from_bytes(data[pos:pos + id_size], "big")
        n, pos = data[pos + id_size], pos + id_size + 1
        raw = [int.from_bytes(data[pos + k * index_size:pos + (k + 1) * index_size], "big") for k in range(n)]
        pos += n * index_size
        if item_id == item:
            return [r & (0x7FFF if index_size == 2 else 0x7F) for r in raw]
        if pos > end:
            break
    return []


def _boxes(data: bytes, start: int, end: int):
    """``(type, (body start, body end))`` of the ISO BMFF boxes between ``start`` and ``end``."""
    pos = start
    while pos + 8 <= end:
        size, kind, head = int.from_bytes(data[pos:pos + 4], "big"), data[pos + 4:pos + 8], 8
        if size == 1:
            size, head = int.from_bytes(data[pos + 8:pos + 16], "big"), 16
        elif size == 0:
            size = end - pos
        if size < head or pos + size > end:
            return
        yield kind, (pos + head, pos + size)
        pos += size


def _child(data: bytes, start: int, end: int, kind: bytes) -> tuple[int, int] | None:
    """The body span of the first box ``kind`` between ``start`` and ``end``, or None."""
    return next((span for k, span in _boxes(data, start, end) if k == kind), None)


def with_orientation(exif: bytes, value: int) -> bytes:
    """An EXIF block with its orientation (which it has) set to ``value``, every other byte as it was."""
    from .image_metadata import exif_orientation_at

    at, order = exif_orientation_at(exif)
    return exif[:at] + value.to_bytes(2, order) + exif[at + 2:]
