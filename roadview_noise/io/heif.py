"""HEIF/HEIC and AVIF camera files (phones, recent datasets): decoded and encoded by Pillow with the optional extra
``heif`` (``pip install 'roadview_noise[heif]'``; ``make install`` installs it): pillow-heif (libheif, HEVC) for
``.heic``/``.heif``, Pillow's own AVIF plugin (libavif, Pillow ≥ 11.3 wheels) for ``.avif``.

- The file's primary image, 8-bit RGB, RGBA or grey (a 10/12-bit file is read at 8 bits, pillow-heif's and
  Pillow's default, and written so); other images a HEIF holds (a burst, depth or auxiliary images, thumbnails)
  are not kept.
- Orientation as for JPEG (:mod:`roadview_noise.orientation`): the pixels as stored with the EXIF orientation
  the file's ``irot``/``imir`` transforms state. Pillow's AVIF plugin reads them so; pillow-heif applies the
  transforms and sets the EXIF tag to 1 (``original_orientation`` in its info), so its pixels are turned back to
  the stored layout and the tag restored. Written back, the encoders turn the EXIF orientation into
  ``irot``/``imir`` again: a viewer shows the output turned like the input. A HEIF turned by ``irot``/``imir``
  without an EXIF orientation tag is read as displayed and written upright.
- Neither format records its encoder's quality and the libraries estimate none: the output is written at
  :data:`QUALITY` (libheif's default is 50, Pillow's AVIF 75), ``inputs.heif_quality`` in the manifest; the ICC
  profile and the EXIF block are copied as read, XMP is not.
"""

from __future__ import annotations

import io
from functools import lru_cache

import numpy as np

from ..errors import InputError

FORMATS = {".heic": "heif", ".heif": "heif", ".avif": "avif"}
QUALITY = 90                      # the output's encoder quality (0–100): the input's is not recorded
EXTRA = "pip install 'roadview_noise[heif]' (make install installs it)"
_PIL_FORMAT = {"heif": "HEIF", "avif": "AVIF"}
_MODES = {"RGB": "RGB", "RGBA": "RGBA", "L": "L", "LA": "RGBA", "P": "RGBA"}   # 16-bit grey: refused, not clipped


@lru_cache(maxsize=2)
def _image_module(fmt: str):
    """PIL.Image with the ``fmt`` codec registered; InputError naming the extra when it is not installed."""
    try:
        from PIL import Image, features
        if fmt == "heif":
            import pillow_heif

            pillow_heif.register_heif_opener()
            return Image
    except ImportError:
        raise InputError(f".{'heic' if fmt == 'heif' else fmt} photos need the optional extra heif: {EXTRA}") \
            from None
    if not features.check("avif"):
        raise InputError(f".avif photos need Pillow with AVIF support (Pillow ≥ 11.3 wheels): {EXTRA}")
    return Image


def missing(fmt: str) -> str | None:
    """Why ``fmt`` (heif | avif) files cannot be read here (the extra to install), None when they can."""
    try:
        _image_module(fmt)
    except InputError as exc:
        return str(exc)
    return None


def check_structure(data: bytes, fmt: str, path) -> None:
    """InputError naming the file when it is not an ISO base media file (no ``ftyp`` box first)."""
    if data[4:8] != b"ftyp":
        raise InputError(f"not a{'n AVIF' if fmt == 'avif' else ' HEIF'} file (no ftyp box)", file=str(path))


def decode(data: bytes, fmt: str, source) -> tuple[np.ndarray, bytes | None, bytes | None]:
    """``(codes, ICC profile, EXIF)`` of a HEIF or AVIF file's primary image: uint8 codes (H, W) grey or (H, W, C)
    RGB(A) as stored, with the EXIF orientation of the file's transforms (module docstring)."""
    from ..orientation import stored
    from .image_metadata import exif_orientation_at

    image_module = _image_module(fmt)
    try:
        with image_module.open(io.BytesIO(data), formats=[_PIL_FORMAT[fmt]]) as im:
            im.load()
            mode = _MODES.get(im.mode)
            if mode is None:
                raise InputError(f"a {fmt.upper()} image of mode {im.mode}: rvnoise reads 8-bit RGB, RGBA and grey",
                                 file=str(source))
            codes = np.asarray(im if im.mode == mode else im.convert(mode))
            icc, exif = im.info.get("icc_profile") or None, im.info.get("exif") or None
            turned = int(im.info.get("original_orientation") or 1)
    except InputError:
        raise
    except Exception as exc:                  # the decoders raise several types for a damaged or truncated file
        raise InputError(f"cannot decode this {fmt.upper()} file ({type(exc).__name__}: {exc})",
                         file=str(source)) from None
    if turned != 1 and exif is not None and exif_orientation_at(exif) is not None:
        codes, exif = stored(codes, turned), with_orientation(exif, turned)
    return np.ascontiguousarray(codes), icc, exif


def encode(codes: np.ndarray, fmt: str, icc: bytes | None, exif: bytes | None, name: str) -> bytes:
    """HEIF or AVIF bytes of uint8 codes (grey or RGB(A), RGB order) at :data:`QUALITY` with ``icc`` and ``exif``
    (its orientation becomes the file's ``irot``/``imir``)."""
    image_module = _image_module(fmt)
    buf = io.BytesIO()
    extra = {k: v for k, v in (("icc_profile", icc), ("exif", exif)) if v}
    try:
        image_module.fromarray(np.ascontiguousarray(codes)).save(buf, format=_PIL_FORMAT[fmt], quality=QUALITY,
                                                                 **extra)
    except (OSError, ValueError) as exc:
        raise OSError(f"{name}: cannot encode {fmt.upper()}: {exc}") from None
    return buf.getvalue()


def with_orientation(exif: bytes, value: int) -> bytes:
    """An EXIF block with its orientation (which it has) set to ``value``, every other byte as it was."""
    from .image_metadata import exif_orientation_at

    at, order = exif_orientation_at(exif)
    return exif[:at] + value.to_bytes(2, order) + exif[at + 2:]
