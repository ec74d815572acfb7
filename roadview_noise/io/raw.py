"""Raw Bayer frames: DNG (read with rawpy/LibRaw, written with tifffile) and plain ``.raw`` + YAML sidecar.

Digital numbers are returned as LibRaw decodes them (uint16, the whole ActiveArea whatever the parity of its
origin, LinearizationTable applied), with the 2×2 CFA pattern of the active area's top-left site and the black/white
levels the file states (the black level from the DNG tags, :mod:`.dng_layout`) or the recipe's
``inputs.raw_black_level_dn``. ``RawFrame`` has one black level: black levels that differ by more than
``MAX_BLACK_SPREAD_DN`` over the frame (per CFA position, per row or column) are refused rather than averaged, since
averaging would bias the darker sites; within the tolerance their mean is used.

Plain raw sidecar ``<stem>.yaml``: ``width``, ``height``, ``dtype`` (uint16), ``byte_order`` (little | big),
``cfa_pattern`` (RGGB | BGGR | GRBG | GBRG), ``black_level_dn``, ``white_level_dn``.
"""

from __future__ import annotations

import os
import warnings
from fractions import Fraction
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import rawpy
import tifffile
import yaml

from ..errors import InputError
from ..types import CFA_PATTERNS, RawEncoding
from . import dng_layout
from .atomic import atomic_path, write_bytes_atomic

MAX_BLACK_SPREAD_DN = 1.0
UNTAGGED_BLACK_HINT = 0.01     # no black-level tag and the darkest sample above this fraction of white: warn


class BlackLevelWarning(UserWarning):
    """A DNG states no black level and its data suggest one above the DNG default 0 (the manifest records it)."""
MIN_DNG_SIDE_PX = 22            # LibRaw rejects raw images narrower or lower than this
SIDECAR_KEYS = ("width", "height", "dtype", "byte_order", "cfa_pattern", "black_level_dn", "white_level_dn")
_BYTE_ORDERS = {"little": "<", "big": ">"}

RawParts = tuple[np.ndarray, str, float, float]
BlackOverride = float | Sequence[float] | None


def read_raw(path: str | os.PathLike, black_level_dn: BlackOverride = None
             ) -> tuple[np.ndarray, str, float, float, RawEncoding]:
    """``.dng`` or ``.raw`` (+ sidecar) by suffix: (dn uint16 (H, W), cfa_pattern, black, white, encoding).
    ``black_level_dn``: the black level to use instead of the file's (:func:`black_override`)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".dng":
        parts, layout = _read_dng(path, black_level_dn)
        return (*parts, RawEncoding(fmt="dng", orientation=layout.orientation))
    if suffix == ".raw":
        meta = _read_sidecar(Path(path))
        dn, pattern, black, white = read_plain_raw(path, meta)
        if black_level_dn is not None:
            black = black_override(black_level_dn, white, path)
        return dn, pattern, black, white, RawEncoding(fmt="raw", sidecar=tuple(meta.items()))
    raise InputError(f"unknown raw suffix {Path(path).suffix!r}; expected .dng or .raw", file=str(path))


def black_override(black_level_dn: float | Sequence[float], white_level_dn: float, path) -> float:
    """The one black level (DN) of a recipe's ``inputs.raw_black_level_dn`` for a file whose white level is
    ``white_level_dn``: one value, or one per site of the frame's 2×2 CFA (row by row from its top-left site, as
    the DNG BlackLevel with BlackLevelRepeatDim 2×2), whose mean is used when they differ by at most
    ``MAX_BLACK_SPREAD_DN`` (else refused, as for the file's own tags)."""
    levels = np.atleast_1d(np.asarray(black_level_dn, dtype=float))
    if np.ptp(levels) > MAX_BLACK_SPREAD_DN:
        raise InputError(f"inputs.raw_black_level_dn {levels.tolist()} differs by more than {MAX_BLACK_SPREAD_DN} DN "
                         "between CFA sites; rvnoise needs one black level", file=str(path))
    black = float(levels.mean())
    if not 0 <= black < white_level_dn:
        raise InputError(f"inputs.raw_black_level_dn {black:g} is not below the white level {white_level_dn:g}",
                         file=str(path))
    return black


def write_raw(path: str | os.PathLike, dn: np.ndarray, cfa_pattern: str, black_level_dn: float,
              white_level_dn: float, encoding: RawEncoding, *, template: str | os.PathLike | None = None) -> None:
    """Write in ``encoding.fmt`` (dng | raw); the inverse of :func:`read_raw`. ``template``: the input DNG whose
    camera metadata :func:`write_dng` copies."""
    if encoding.fmt == "dng":
        write_dng(path, dn, cfa_pattern, black_level_dn, white_level_dn, template=template)
    elif encoding.fmt == "raw":
        write_plain_raw(path, dn, cfa_pattern, black_level_dn, white_level_dn, dict(encoding.sidecar))
    else:
        raise ValueError(f"unknown raw format {encoding.fmt!r}")


def read_dng(path: str | os.PathLike, black_level_dn: BlackOverride = None) -> RawParts:
    """Bayer DNG via rawpy: the whole ActiveArea, CFA pattern of its top-left site, black and white level (DN);
    ``black_level_dn`` instead of the file's black-level tags when given (:func:`black_override`). The TIFF
    structure is checked first (:func:`check_dng_structure`), so a truncated file or one rvnoise cannot use is
    named as such."""
    return _read_dng(path, black_level_dn)[0]


def _read_dng(path, black_level_dn: BlackOverride) -> tuple[RawParts, dng_layout.DngLayout]:
    """:func:`read_dng`'s parts and the file's layout (its orientation: :class:`.dng_layout.DngLayout`)."""
    layout = check_dng_structure(path)
    try:
        with rawpy.imread(str(path)) as raw:
            if raw.raw_pattern is None or raw.raw_pattern.shape != (2, 2):
                raise InputError("not a 2×2 Bayer CFA raw (linear DNG, X-Trans or other mosaic)", file=str(path))
            dn, colours = _active_area(raw, layout)
            letters = raw.color_desc.decode("ascii")
            pattern = "".join(letters[c] for c in colours.ravel())
            blacks = np.asarray(raw.black_level_per_channel, dtype=float)
            white = float(raw.white_level)
    except rawpy.LibRawError as exc:
        raise InputError(_LIBRAW_WORDS.get(type(exc).__name__, "LibRaw cannot read this DNG"), file=str(path)) \
            from exc
    if pattern not in CFA_PATTERNS:
        raise InputError(f"CFA pattern {pattern!r} is not one of {CFA_PATTERNS}", file=str(path))
    if black_level_dn is not None:
        return (dn, pattern, black_override(black_level_dn, white, path), white), layout
    if layout.black_spread_dn > MAX_BLACK_SPREAD_DN:
        raise InputError(f"the black level varies by {layout.black_spread_dn:g} DN over the frame "
                         f"({layout.black_source}), more than {MAX_BLACK_SPREAD_DN} DN; rvnoise needs one black level",
                         file=str(path))
    if layout.black_mean_dn is not None:
        return (dn, pattern, layout.black_mean_dn, white), layout
    if np.ptp(blacks) > MAX_BLACK_SPREAD_DN:         # no black tag: LibRaw's estimate (e.g. from masked areas)
        raise InputError(f"per-channel black levels {blacks.tolist()} differ by more than {MAX_BLACK_SPREAD_DN} DN; "
                         "rvnoise needs one black level", file=str(path))
    black, darkest = float(blacks.mean()), int(dn.min()) if dn.size else 0
    if darkest - black > UNTAGGED_BLACK_HINT * white:
        warnings.warn(BlackLevelWarning(
            "a DNG without a BlackLevel tag is read with black 0 DN (the DNG default), but none of its samples is "
            f"below {UNTAGGED_BLACK_HINT:.0%} of white: the sensor's black is likely higher (e.g. PiDNG files of "
            "Raspberry Pi cameras), and noise and weather radiances would then ride on that offset; if so, add the "
            "tag (e.g. with exiftool) or set the recipe's inputs.raw_black_level_dn"))
    return (dn, pattern, black, white), layout


def _active_area(raw, layout: dng_layout.DngLayout) -> tuple[np.ndarray, np.ndarray]:
    """The samples of the whole ActiveArea (uint16) and the colour indices of its top-left 2×2 sites. LibRaw's
    visible area starts at an even row and column (one row or column of an odd origin lost) and its colour map
    keeps the CFAPattern's phase at the ActiveArea's origin, as the DNG specification puts it; the full raw image
    is cropped here instead. A raw image whose size is not the IFD's (LibRaw cropped it itself) stays LibRaw's
    visible area."""
    top, left = layout.active_origin
    if raw.raw_image.shape != layout.raw_hw:
        return np.array(raw.raw_image_visible, dtype=np.uint16), raw.raw_colors_visible[:2, :2]
    rows, cols = layout.active_hw
    return (np.array(raw.raw_image[top:top + rows, left:left + cols], dtype=np.uint16),
            raw.raw_colors[top:top + 2, left:left + 2])


_LIBRAW_WORDS = {
    "LibRawIOError": "truncated or unreadable DNG: LibRaw reached the end of the file or could not read it",
    "LibRawFileUnsupportedError": "not a DNG LibRaw can read (corrupt header or an unsupported variant)",
    "LibRawDataError": "corrupt DNG: LibRaw could not decode its image data",
    "LibRawRequestForNonexistentImageError": "the DNG holds no raw image",
    "LibRawTooBigError": "the DNG declares an image too large to decode",
}


def dng_orientation(path: str | os.PathLike) -> int:
    """A DNG's IFD0 Orientation (1–8; 1 when absent, invalid or the file unreadable): IFD0 only, no pixels read."""
    try:
        with tifffile.TiffFile(path) as tif:
            tag = tif.pages[0].tags.get(274)
            return int(tag.value) if tag is not None and 1 <= int(tag.value) <= 8 else 1
    except Exception:                              # tifffile raises many types for a damaged directory
        return 1


def check_dng_structure(path: str | os.PathLike) -> dng_layout.DngLayout:
    """The raw image's layout (:func:`.dng_layout.inspect`); :class:`InputError` for a file that is not
    TIFF-structured, whose image data (of any IFD or sub-IFD) ends beyond the end of the file, or that rvnoise
    cannot use."""
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise InputError(f"cannot read the DNG: {exc.strerror or exc}", file=str(path)) from None
    try:
        with tifffile.TiffFile(path) as tif:
            end = 0
            for page in tif.pages:
                for p in (page, *(page.pages or ())):
                    end = max(end, max((o + c for o, c in zip(p.dataoffsets, p.databytecounts)), default=0))
            if end > size:
                raise InputError(f"truncated DNG: its image data ends at byte {end}, the file has {size} bytes",
                                 file=str(path))
            return dng_layout.inspect(tif, path)
    except InputError:
        raise
    except Exception as exc:                       # tifffile raises many types for a damaged directory
        raise InputError(f"corrupt or truncated DNG: its TIFF directory cannot be read ({exc})", file=str(path)) \
            from None


def write_dng(path: str | os.PathLike, dn_uint16: np.ndarray, cfa_pattern: str, black_level_dn: float,
              white_level_dn: float, *, template: str | os.PathLike | None = None) -> None:
    """Uncompressed single-IFD DNG 1.4 (CFA photometric 32803, 16 bits) that LibRaw reads back with the same pattern,
    white level and values, and tifffile with the same black level (a fractional black, the mean of per-site levels,
    is written as a RATIONAL; LibRaw reads its integer part). Colour tags are neutral (identity ColorMatrix1, D65,
    unit AsShotNeutral) unless ``template`` (the input DNG) is given: its AsShotNeutral if it has one, its camera,
    colour-profile and rendering tags are copied, and its default crop and opcode lists 2/3 when the frame is its
    whole active area
    (:func:`.dng_layout.template_tags`, which also lists what is dropped: previews, EXIF, noise profile), so raw
    converters render the output like the input. Values are rounded and clipped to 0…65535 (not to the white level:
    the file keeps what the models produced). Both sides must be at least ``MIN_DNG_SIDE_PX``, or LibRaw cannot read
    the file back."""
    dn = _to_uint16(dn_uint16)
    if min(dn.shape) < MIN_DNG_SIDE_PX:
        raise ValueError(f"DNG of {dn.shape[1]}×{dn.shape[0]} px: LibRaw reads only frames of at least "
                         f"{MIN_DNG_SIDE_PX} px per side")
    _check_pattern(cfa_pattern)
    white = _integral_level(white_level_dn, "white")
    cfa = bytes("RGB".index(c) for c in cfa_pattern)
    identity = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)   # 3×3 SRATIONAL numerator/denominator pairs
    tags = [
        (33421, "H", 2, (2, 2), True),                  # CFARepeatPatternDim
        (33422, "B", 4, cfa, True),                     # CFAPattern (0 R, 1 G, 2 B)
        (50706, "B", 4, (1, 4, 0, 0), True),            # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),            # DNGBackwardVersion
        (50708, "s", 0, "rvnoise", True),               # UniqueCameraModel
        (50710, "B", 3, (0, 1, 2), True),               # CFAPlaneColor
        (50711, "H", 1, 1, True),                       # CFALayout: rectangular
        (50713, "H", 2, (1, 1), True),                  # BlackLevelRepeatDim
        _black_tag(black_level_dn),                     # BlackLevel
        (50717, "I", 1, white, True),                   # WhiteLevel
        (50721, "2i", 9, identity, True),               # ColorMatrix1
        (50728, "2I", 3, (1, 1, 1, 1, 1, 1), True),     # AsShotNeutral
        (50778, "H", 1, 21, True),                      # CalibrationIlluminant1: D65
    ]
    if template is not None:
        copied = dng_layout.template_tags(template, dn.shape)
        if any(c[0] in dng_layout.OPCODE_LISTS for c in copied):
            copied.append((50707, "B", 4, (1, 3, 0, 0), True))     # opcode lists need a DNG 1.3 reader
        # the input's white balance or none (a raw converter's default), never a made-up neutral one
        tags = [t for t in tags if t[0] not in {c[0] for c in copied} | {50728}] + copied
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, dn, photometric=32803, extratags=tags, metadata=None, subfiletype=0)


def _black_tag(black_level_dn: float) -> tuple:
    """BlackLevel as a LONG, or as the nearest RATIONAL with a denominator ≤ 2¹⁶ when it is fractional."""
    if not 0 <= black_level_dn <= 65535:
        raise ValueError(f"DNG black level must be 0…65535 DN, got {black_level_dn}")
    if black_level_dn == round(black_level_dn):
        return 50714, "I", 1, int(round(black_level_dn)), True
    q = Fraction(black_level_dn).limit_denominator(1 << 16)
    return 50714, "2I", 1, (q.numerator, q.denominator), True


def read_plain_raw(path: str | os.PathLike, meta: dict | None = None) -> RawParts:
    """``.raw`` samples described by the sidecar ``<stem>.yaml`` (see module docstring; ``meta``: it, already
    read)."""
    path = Path(path)
    meta = _read_sidecar(path) if meta is None else meta
    dtype = np.dtype(meta["dtype"]).newbyteorder(_BYTE_ORDERS[meta["byte_order"]])
    h, w = meta["height"], meta["width"]
    size = path.stat().st_size if path.is_file() else None
    if size is None:
        raise InputError("raw file does not exist", file=str(path))
    if size != h * w * dtype.itemsize:
        raise InputError(f"file has {size} bytes but the sidecar describes {w}×{h} {meta['dtype']} = "
                         f"{h * w * dtype.itemsize} bytes", file=str(path))
    dn = np.fromfile(path, dtype=dtype).reshape(h, w).astype(np.uint16)
    return dn, meta["cfa_pattern"], float(meta["black_level_dn"]), float(meta["white_level_dn"])


def write_plain_raw(path: str | os.PathLike, dn: np.ndarray, cfa_pattern: str, black_level_dn: float,
                    white_level_dn: float, like: dict | None = None) -> None:
    """uint16 ``.raw`` plus its YAML sidecar, each written atomically (sidecar last): little-endian, or like the
    input's sidecar ``like`` — its byte order, key order, other keys (a user's time stamps, exposure) and the form
    of unchanged numbers (``64`` stays ``64``, not ``64.0``)."""
    dn16 = _to_uint16(dn)
    _check_pattern(cfa_pattern)
    path = Path(path)
    like = like or {}
    meta = {**like, "width": int(dn16.shape[1]), "height": int(dn16.shape[0]), "dtype": "uint16",
            "byte_order": like.get("byte_order", "little"), "cfa_pattern": cfa_pattern}
    for key, value in (("black_level_dn", black_level_dn), ("white_level_dn", white_level_dn)):
        meta[key] = like[key] if key in like and like[key] == value else float(value)
    write_bytes_atomic(path, dn16.astype(_BYTE_ORDERS[meta["byte_order"]] + "u2").tobytes())
    write_bytes_atomic(sidecar_path(path), yaml.safe_dump(meta, sort_keys=False).encode())


def sidecar_path(path: str | os.PathLike) -> Path:
    return Path(path).with_suffix(".yaml")


def _read_sidecar(path: Path) -> dict:
    side = sidecar_path(path)
    try:
        meta = yaml.safe_load(side.read_text())
    except FileNotFoundError:
        raise InputError(f"plain raw needs the sidecar {side.name} (width, height, dtype, byte_order, cfa_pattern, "
                         "black_level_dn, white_level_dn)", file=str(path)) from None
    except (OSError, yaml.YAMLError) as exc:
        raise InputError(f"cannot read sidecar {side.name}: {exc}", file=str(path)) from exc
    if not isinstance(meta, dict):
        raise InputError(f"sidecar {side.name} is not a mapping", file=str(path))
    missing = [k for k in SIDECAR_KEYS if k not in meta]
    if missing:
        raise InputError(f"sidecar {side.name} lacks {missing}", file=str(path))
    problems = []
    if meta["dtype"] != "uint16":
        problems.append(f"dtype {meta['dtype']!r} (only uint16)")
    if meta["byte_order"] not in _BYTE_ORDERS:
        problems.append(f"byte_order {meta['byte_order']!r} (little | big)")
    if meta["cfa_pattern"] not in CFA_PATTERNS:
        problems.append(f"cfa_pattern {meta['cfa_pattern']!r} (one of {CFA_PATTERNS})")
    for k in ("width", "height"):
        if not isinstance(meta[k], int) or meta[k] <= 0:
            problems.append(f"{k} {meta[k]!r} (a positive integer)")
    for k in ("black_level_dn", "white_level_dn"):
        if not isinstance(meta[k], (int, float)):
            problems.append(f"{k} {meta[k]!r} (a number)")
    if not problems and not meta["black_level_dn"] < meta["white_level_dn"]:
        problems.append("black_level_dn must be below white_level_dn")
    if problems:
        raise InputError(f"sidecar {side.name} has invalid " + "; ".join(problems), file=str(path))
    return meta


def _to_uint16(dn: np.ndarray) -> np.ndarray:
    dn = np.asarray(dn)
    if dn.ndim != 2:
        raise ValueError(f"raw frame must be 2-D (H, W), got shape {dn.shape}")
    if dn.dtype == np.uint16:
        return dn
    if np.isnan(dn).any():
        raise ValueError("raw frame contains NaN digital numbers")
    return np.clip(np.rint(dn), 0, 65535).astype(np.uint16)


def _check_pattern(pattern: str) -> None:
    if pattern not in CFA_PATTERNS:
        raise ValueError(f"unknown CFA pattern {pattern!r}; expected one of {CFA_PATTERNS}")


def _integral_level(value: float, what: str) -> int:
    if value != round(value) or not 0 <= value <= 65535:
        raise ValueError(f"DNG {what} level must be an integer 0…65535 DN, got {value}")
    return int(round(value))
