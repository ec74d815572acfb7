"""Sizes from file headers, read before any decoding: pixels of images, raw frames and depth maps, points of clouds.

A small file can declare a huge image (a PNG of 2 MB that inflates to 32000×24198 pixels) or cloud; the runner
compares these sizes with ``--max-pixels`` / ``--max-points`` before a reader allocates anything
(:func:`check_size`). Each function reads at most the header (PNG IHDR, JPEG SOF, TIFF/DNG IFDs, EXR data window,
``.npy`` header, PCD/PLY header lines, ``.bin`` file size).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

from ..errors import InputError

HEADER_BYTES = 1 << 16
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
BIN_POINT_BYTES = {"kitti_bin": 16, "nuscenes_bin": 20, "vod_bin": 28}


def _head(path: Path, n: int = HEADER_BYTES) -> bytes:
    with open(path, "rb") as fh:
        return fh.read(n)


def image_pixels(path: str | os.PathLike) -> tuple[int, int] | None:
    """(width, height) an image, raw frame or depth map declares, by suffix; None for a format without a header
    size (it is then bounded by the file size) or a header too damaged to tell (the reader reports it)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".png":
        return _png(_head(path, 33))
    if suffix in (".jpg", ".jpeg"):
        return _jpeg(path)
    if suffix in (".tif", ".tiff"):
        return _tiff(path)
    if suffix == ".webp":
        return _webp(_head(path, 30))
    if suffix == ".dng":
        return _dng(path)
    if suffix == ".exr":
        return _exr(path)
    if suffix == ".npy":
        return _npy(path)
    if suffix == ".raw":
        return (path.stat().st_size // 2, 1)                 # uint16 samples; the sidecar must match the size
    return None


def _png(head: bytes) -> tuple[int, int] | None:
    if len(head) < 24 or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])


def _webp(head: bytes) -> tuple[int, int] | None:
    """The canvas of an extended WebP (VP8X), or the size in a lossy (VP8 key frame) or lossless (VP8L) bitstream's
    header (WebP container specification; RFC 6386 §9.1)."""
    if len(head) < 30 or head[:4] != b"RIFF" or head[8:12] != b"WEBP":
        return None
    kind = head[12:16]
    if kind == b"VP8X":
        return int.from_bytes(head[24:27], "little") + 1, int.from_bytes(head[27:30], "little") + 1
    if kind == b"VP8 ":
        return int.from_bytes(head[26:28], "little") & 0x3FFF, int.from_bytes(head[28:30], "little") & 0x3FFF
    if kind == b"VP8L":
        bits = int.from_bytes(head[21:25], "little")
        return (bits & 0x3FFF) + 1, (bits >> 14 & 0x3FFF) + 1
    return None


def _jpeg(path: Path) -> tuple[int, int] | None:
    with open(path, "rb") as fh:
        if fh.read(2) != b"\xff\xd8":
            return None
        while True:
            marker = fh.read(2)
            if len(marker) < 2 or marker[0] != 0xFF:
                return None
            if marker[1] in (0xD8, 0x01) or 0xD0 <= marker[1] <= 0xD7:
                continue
            size = fh.read(2)
            if len(size) < 2:
                return None
            length = struct.unpack(">H", size)[0]
            if marker[1] in _SOF:
                seg = fh.read(5)
                if len(seg) < 5:
                    return None
                height, width = struct.unpack(">HH", seg[1:5])
                return width, height
            fh.seek(length - 2, os.SEEK_CUR)


def _tiff(path: Path) -> tuple[int, int] | None:
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            best = None
            for page in tif.pages:
                for p in (page, *(page.pages or ())):
                    w, h = int(p.imagewidth), int(p.imagelength)
                    if best is None or w * h > best[0] * best[1]:
                        best = (w, h)
            return best
    except Exception:                       # a damaged directory: the reader names the problem
        return None


def _dng(path: Path) -> tuple[int, int] | None:
    import rawpy

    raw = rawpy.RawPy()
    try:
        raw.open_file(str(path))             # header only: LibRaw's identify, no unpacking
        s = raw.sizes
        return int(s.raw_width), int(s.raw_height)
    except Exception:
        return _tiff(path)
    finally:
        raw.close()


def _exr(path: Path) -> tuple[int, int] | None:
    import OpenEXR

    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            (x0, y0), (x1, y1) = exr.header()["dataWindow"]
    except Exception:
        return None
    return int(x1) - int(x0) + 1, int(y1) - int(y0) + 1


def _npy(path: Path) -> tuple[int, int] | None:
    import numpy as np

    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, _ = read(fh)
    except Exception:                       # the reader names the problem
        return None
    n = 1
    for s in shape:
        n *= int(s)
    return (n, 1)


def cloud_points(path: str | os.PathLike, fmt: str, data: bytes | None = None, point_bytes: int | None = None
                 ) -> int | None:
    """Points a cloud declares: PCD ``POINTS`` (or WIDTH×HEIGHT), PLY ``element vertex``, ``.bin`` size / point
    size (``point_bytes``, the layout's row: :func:`.pointcloud.bin_point_bytes`; else the format's default row);
    None when the header is too damaged to tell (the reader reports it). ``data``: the file's bytes when the caller
    has read them (the runner: no second open of a small file), else its header is read here."""
    if fmt in BIN_POINT_BYTES:
        return (len(data) if data is not None else Path(path).stat().st_size) // (point_bytes or BIN_POINT_BYTES[fmt])
    head = _head(Path(path)) if data is None else data
    limit = min(len(head), HEADER_BYTES)
    end = head.find(b"DATA" if fmt == "pcd" else b"end_header", 0, limit)
    lines = head[: end if end >= 0 else limit].decode("ascii", errors="replace").splitlines()
    values: dict[str, list[str]] = {}
    for line in lines:
        words = line.split()
        if fmt == "pcd" and words:
            values[words[0].upper()] = words[1:]
        elif fmt == "ply" and len(words) == 3 and words[0] == "element" and words[1] == "vertex":
            values["POINTS"] = [words[2]]
    try:
        if "POINTS" in values:
            return int(values["POINTS"][0])
        return int(values["WIDTH"][0]) * int(values.get("HEIGHT", ["1"])[0])
    except (KeyError, ValueError, IndexError):
        return None


def check_size(path: str | os.PathLike, *, max_pixels: int | None = None, max_points: int | None = None,
               cloud_fmt: str | None = None, data: bytes | None = None, point_bytes: int | None = None) -> None:
    """Raise :class:`InputError` when the header declares more pixels or points than allowed (a cloud's header
    taken from ``data``, its bytes, when given; a ``.bin``'s row of ``point_bytes``: :func:`cloud_points`)."""
    try:
        if cloud_fmt is None and max_pixels is not None:
            size = image_pixels(path)
            if size is not None and size[0] * size[1] > max_pixels:
                what = f"{size[0]}×{size[1]} = " if size[1] > 1 else ""
                raise InputError(f"declares {what}{size[0] * size[1] / 1e6:.1f} megapixels, above the limit of "
                                 f"{max_pixels / 1e6:g} MP (--max-pixels; a decompression bomb or an unusually "
                                 "large frame: raise the limit to process it)", file=str(path))
        elif cloud_fmt is not None and max_points is not None:
            n = cloud_points(path, cloud_fmt, data, point_bytes)
            if n is not None and n > max_points:
                raise InputError(f"declares {n:,} points, above the limit of {max_points:,} (--max-points; raise "
                                 "the limit to process it)", file=str(path))
    except OSError as exc:
        raise InputError(f"cannot read the header: {exc.strerror or exc}", file=str(path)) from exc
