"""What a DNG's TIFF directories say about its raw image, read (with tifffile) before LibRaw decodes it.

LibRaw (rawpy) decodes the mosaic, applies the LinearizationTable and finds the visible area. It does not report,
or reports wrongly, what this module reads from the tags (DNG specification 1.7, chapters 4–6):

- which IFD holds the raw image: full-resolution (NewSubFileType 0) CFA or LinearRaw data, in IFD0 or in a SubIFD
  behind a preview (as cameras and Adobe DNG Converter write it); the largest if there are several, as LibRaw;
- what rvnoise cannot use, refused in words: linear (demosaiced) DNGs, CFA repeat patterns other than 2×2 (X-Trans
  is 6×6), BigTIFF files (LibRaw cannot read them), floating-point data (HDR merges: not one exposure's digital
  numbers, and LibRaw rescales them to 14-bit integers, out of step with their black level tags), compressions
  LibRaw cannot decode for integer data (deflate, JPEG XL), image data with tiles or strips missing or empty (sample
  files whose pixels a metadata tool stripped: LibRaw would decode zeros);
- the ActiveArea at any origin (LibRaw's visible area starts at an even row and column): CFAPattern and the
  BlackLevel repeat pattern have their origin at its top-left site;
- the black level over the active area: ``BlackLevel`` per position of its ``BlackLevelRepeatDim`` pattern plus the
  per-column ``BlackLevelDeltaH`` and per-row ``BlackLevelDeltaV`` (LibRaw averages the deltas away and reads only
  the first value of a repeat pattern larger than 2×2), exact for RATIONAL values;
- the tags that still hold when the written image is the whole active area (default crop, opcode lists 2 and 3,
  user crop, scale): see :func:`template_tags`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import tifffile

from ..errors import InputError

CFA, LINEAR_RAW = 32803, 34892                       # PhotometricInterpretation of raw data
DECODABLE = {1: "uncompressed", 7: "lossless JPEG", 34892: "lossy JPEG"}      # integer CFA data, by LibRaw
# IFD0 camera, colour-profile and rendering tags copied from the input: Make, Model, Orientation, DateTime,
# Copyright, UniqueCameraModel, LocalizedCameraModel, ColorMatrix1/2, CameraCalibration1/2, AnalogBalance,
# AsShotNeutral, AsShotWhiteXY, BaselineExposure, BaselineSharpness, LinearResponseLimit, CameraSerialNumber,
# LensInfo, ShadowScale, CalibrationIlluminant1/2, CameraCalibrationSignature, ProfileCalibrationSignature,
# AsShotProfileName, ProfileName, ProfileHueSatMapDims, ProfileHueSatMapData1/2, ProfileToneCurve,
# ProfileEmbedPolicy, ProfileCopyright, ForwardMatrix1/2, ProfileLookTableDims/Data, ProfileHueSatMapEncoding,
# ProfileLookTableEncoding, BaselineExposureOffset, DefaultBlackRender.
# Not copied: EXIF/GPS/XMP and maker-note IFDs, previews and thumbnails (they would show the unaugmented scene),
# BaselineNoise and NoiseProfile (they describe the input's noise, which the models changed), OpcodeList1 and the
# LinearizationTable (the written samples are already linear and cropped to the active area).
IFD0_TAGS = (271, 272, 274, 306, 33432, 50708, 50709, 50721, 50722, 50723, 50724, 50727, 50728, 50729, 50730, 50732,
             50734, 50735, 50736, 50739, 50778, 50779, 50931, 50932, 50934, 50936, 50937, 50938, 50939, 50940, 50941,
             50942, 50964, 50965, 50981, 50982, 51107, 51108, 51109, 51110)
# raw-IFD tags in active-area coordinates: DefaultScale, DefaultCropOrigin, DefaultCropSize, BayerGreenSplit,
# AntiAliasStrength, BestQualityScale, OpcodeList2, OpcodeList3, DefaultUserCrop
RAW_IFD_TAGS = (50718, 50719, 50720, 50733, 50738, 50780, 51009, 51022, 51125)
OPCODE_LISTS = (51009, 51022)                         # need a DNG 1.3 reader


@dataclass(frozen=True)
class DngLayout:
    """The raw IFD's facts that LibRaw does not give (module docstring)."""

    active_hw: tuple[int, int]          # rows, columns of the active area (the whole raw image without ActiveArea)
    black_mean_dn: float | None         # mean black level over the active area; None: no black-level tag
    black_spread_dn: float              # max − min of the black level over the active area
    black_source: str                   # the tags it comes from, for messages
    active_origin: tuple[int, int] = (0, 0)      # top, left of the active area in the raw image (any parity)
    raw_hw: tuple[int, int] | None = None        # rows, columns of the raw IFD's image
    orientation: int = 1                         # IFD0's Orientation (274), 1–8: how the raw image is displayed


def inspect(tif: tifffile.TiffFile, path: str | os.PathLike) -> DngLayout:
    """The layout of the raw image of an open DNG; :class:`InputError` for what rvnoise cannot use."""
    if tif.is_bigtiff:
        raise InputError("BigTIFF DNG: LibRaw reads only classic TIFF DNGs (as the DNG specification defines them)",
                         file=str(path))
    ifd = raw_ifd(tif, path)
    h, w = int(ifd.imagelength), int(ifd.imagewidth)
    if h == 0 or w == 0:
        raise InputError(f"its raw image is {w}×{h} px", file=str(path))
    if ifd.photometric == LINEAR_RAW:
        raise InputError(f"linear DNG: its raw image is already demosaiced (LinearRaw, {ifd.samplesperpixel} samples "
                         "per pixel); rvnoise's raw models need a Bayer mosaic, so render it to RGB (PNG/TIFF) and "
                         "use a camera recipe", file=str(path))
    dim, pattern = ifd.tags.get(33421), ifd.tags.get(33422)
    if dim is None or pattern is None:
        raise InputError("its raw IFD lacks CFARepeatPatternDim or CFAPattern: the Bayer layout is not stated",
                         file=str(path))
    if tuple(dim.value) != (2, 2):
        rows, cols = dim.value
        raise InputError(f"CFA repeat pattern {rows}×{cols} (X-Trans or another non-Bayer mosaic): rvnoise reads 2×2 "
                         "Bayer mosaics only", file=str(path))
    _check_compression(ifd, path)
    _check_chunks(ifd, h, w, path)
    top, left, bottom, right = _ints(ifd.tags.get(50829), (0, 0, h, w))           # ActiveArea
    turn = tif.pages[0].tags.get(274)                                               # Orientation (DNG: IFD0)
    return DngLayout((bottom - top, right - left), *_black(ifd.tags, bottom - top, right - left, path), (top, left),
                     (h, w), int(turn.value) if turn is not None and 1 <= int(turn.value) <= 8 else 1)


def raw_ifd(tif: tifffile.TiffFile, path: str | os.PathLike):
    """The largest full-resolution (NewSubFileType 0) CFA or LinearRaw IFD among the IFDs and their SubIFDs."""
    found = [p for page in tif.pages for p in (page, *(page.pages or ()))
             if int(p.subfiletype) == 0 and p.photometric in (CFA, LINEAR_RAW)]
    if not found:
        raise InputError("the DNG holds no raw image: none of its IFDs or SubIFDs has full-resolution CFA or "
                         "LinearRaw data (only previews?)", file=str(path))
    return max(found, key=lambda p: int(p.imagelength) * int(p.imagewidth))


def template_tags(path: str | os.PathLike, written_hw: tuple[int, int]) -> list[tuple]:
    """tifffile ``extratags`` copying the input DNG's :data:`IFD0_TAGS`, and its :data:`RAW_IFD_TAGS` when the
    written image is its whole active area (their coordinates then still hold); else those are dropped."""
    try:
        with tifffile.TiffFile(path) as tif:
            first = tif.pages[0].tags
            tags = [_copy(code, tag, tif) for code in IFD0_TAGS if (tag := first.get(code)) is not None]
            layout = inspect(tif, path)
            if layout.active_hw == tuple(written_hw):
                raw = raw_ifd(tif, path).tags
                tags += [_copy(code, tag, tif) for code in RAW_IFD_TAGS if (tag := raw.get(code)) is not None]
            return tags
    except (OSError, tifffile.TiffFileError, IndexError) as exc:
        raise InputError(f"cannot read DNG metadata: {exc}", file=str(path)) from exc


def _copy(code: int, tag, tif: tifffile.TiffFile) -> tuple:
    """A tag as tifffile writes it: its bytes as stored for opcode lists (big-endian by the DNG spec whatever the
    file's byte order), enums such as Orientation as their integer."""
    if code in OPCODE_LISTS:
        tif.filehandle.seek(tag.valueoffset)
        return code, 7, tag.count, tif.filehandle.read(tag.count), True
    value = tag.value
    return code, int(tag.dtype), tag.count, int(value) if isinstance(value, int) else value, True


def _check_compression(ifd, path) -> None:
    if int(ifd.sampleformat) == 3:
        raise InputError(f"floating-point DNG ({ifd.bitspersample}-bit float samples, e.g. an HDR merge): its values "
                         "are not one exposure's digital numbers, which rvnoise's sensor models need", file=str(path))
    comp = int(ifd.compression)
    if comp not in DECODABLE:
        try:
            name = tifffile.COMPRESSION(comp).name
        except ValueError:
            name = "unknown"
        raise InputError(f"its raw image uses compression {comp} ({name}), which LibRaw cannot decode for integer "
                         "data; readable: " + ", ".join(f"{c} {n}" for c, n in DECODABLE.items())
                         + " (Adobe DNG Converter rewrites a file as lossless JPEG)", file=str(path))


def _check_chunks(ifd, h: int, w: int, path) -> None:
    """Every tile or strip of the raw image present and non-empty."""
    if ifd.is_tiled:
        kind, need = "tiles", math.ceil(w / ifd.tilewidth) * math.ceil(h / ifd.tilelength)
    else:
        kind, need = "strips", math.ceil(h / min(int(ifd.rowsperstrip) or h, h))
    if int(ifd.planarconfig) == 2:
        need *= int(ifd.samplesperpixel)
    have = len(ifd.dataoffsets)
    empty = sum(1 for c in ifd.databytecounts if c == 0)
    if have < need or empty:
        raise InputError(f"incomplete raw image: {w}×{h} px need {need} {kind}, the file holds {have}"
                         + (f" ({empty} empty)" if empty else "")
                         + "; was its image data stripped (as in metadata tools' sample files)?", file=str(path))


def _black(tags, h: int, w: int, path) -> tuple[float | None, float, str]:
    """(mean, spread, source) of the black level over the h×w active area (BlackLevel, its repeat pattern and the
    per-column/per-row deltas)."""
    level, delta_h, delta_v = tags.get(50714), tags.get(50715), tags.get(50716)
    if level is None and delta_h is None and delta_v is None:
        return None, 0.0, "no black-level tag"
    rows, cols = _ints(tags.get(50713), (1, 1))
    black = _reals(level, path) if level is not None else np.zeros(1)
    if black.size == 1:
        black = np.full(rows * cols, black[0])
    if black.size != rows * cols:
        raise InputError(f"BlackLevel has {black.size} values but BlackLevelRepeatDim {rows}×{cols} needs "
                         f"{rows * cols}", file=str(path))
    pattern = black.reshape(rows, cols)
    dh = _reals(delta_h, path) if delta_h is not None else np.zeros(w)
    dv = _reals(delta_v, path) if delta_v is not None else np.zeros(h)
    hi = max(pattern[i, j] + dv[i::rows].max() + dh[j::cols].max()
             for i in range(min(rows, dv.size)) for j in range(min(cols, dh.size)))
    lo = min(pattern[i, j] + dv[i::rows].min() + dh[j::cols].min()
             for i in range(min(rows, dv.size)) for j in range(min(cols, dh.size)))
    source = f"BlackLevel {rows}×{cols}" + (" + BlackLevelDeltaH" if delta_h is not None else "") \
        + (" + BlackLevelDeltaV" if delta_v is not None else "")
    return float(pattern.mean() + dh.mean() + dv.mean()), float(hi - lo), source


def _reals(tag, path) -> np.ndarray:
    """A numeric tag's values as floats (RATIONAL/SRATIONAL as numerator/denominator)."""
    value = np.atleast_1d(np.asarray(tag.value, dtype=float))
    if int(tag.dtype) in (5, 10):
        pairs = value.reshape(-1, 2)
        if (pairs[:, 1] == 0).any():
            raise InputError(f"tag {tag.name} has a zero denominator", file=str(path))
        return pairs[:, 0] / pairs[:, 1]
    return value


def _ints(tag, default: tuple) -> tuple:
    return default if tag is None else tuple(int(v) for v in np.atleast_1d(tag.value))
