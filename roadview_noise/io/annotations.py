"""Annotation files: per-point label sidecars, label images (masks), 2-D boxes and 3-D boxes — read into arrays and
written back in the same format, atomically. Geometry and bookkeeping live in :mod:`roadview_noise.annotations`.

Point-label sidecars (one value per point of the cloud, in point order):
- ``semantickitti``: ``.label``, uint32 little-endian, semantic class in the lower 16 bits, instance in the upper 16
  (SemanticKITTI, SemanticSTF, SemanticPOSS).
- ``nuscenes_lidarseg``: ``<sample_data token>_lidarseg.bin``, uint8 class index (nuScenes-lidarseg).
- ``nuscenes_panoptic``: ``<sample_data token>_panoptic.npz``, uint16 ``class · 1000 + instance`` under the key
  ``data`` (nuScenes-panoptic); written back the same way, deterministically (fixed zip time stamp).
- ``npy``: any 1-D (or N × k) NumPy array, dtype kept.

Polygon files: a JSON per image with ``objects`` and their ``polygon`` (Cityscapes ``*_gtFine_polygons.json``,
Mapillary Vistas v2 ``polygons/*.json``), every key kept.

Masks: PNG/TIFF label images of any integer dtype and channel count (Cityscapes ``*_labelIds.png`` 8-bit,
``*_instanceIds.png`` 16-bit, BDD100K's RGBA bitmasks), read and written without any colour conversion; a palette
PNG (Pascal VOC, Mapillary Vistas) as its indices, written back with its palette (:class:`Mask`); a ``.npy`` array
(labelme's ``SegmentationClassNpy``) as it is.

2-D boxes: Pascal VOC XML (``object/bndbox`` and ``part`` boxes, 1-based pixel indices, every other element kept),
KITTI ``label_2`` text (``type truncated occluded alpha left top right bottom h w l x y z ry [score]``,
pixels, within [0, W − 1]) and YOLO txt (``class cx cy w h`` or ``class x1 y1 x2 y2 …`` polygons, normalised to the
image size: 0 and 1 are the image edges, i.e. pixel positions −½ and W − ½ with pixel centres at integers).

3-D boxes: KITTI ``label_2`` + ``calib`` (camera-rectified frame, bottom-centre, ``rotation_y``), or boxes in the
sensor frame (x forward, y left, z up) as JSON (``[{"id", "class", "center_m": [x, y, z], "size_m": [length,
width, height], "yaw_rad"}]``, or that list under ``"boxes"``) or CSV (header ``id,class,x_m,y_m,z_m,length_m,
width_m,height_m,yaw_rad``; centre of the box, yaw about z from x).
"""

from __future__ import annotations

import base64
import csv
import io
import json
import os
import re
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from .atomic import write_bytes_atomic

POINT_LABEL_FORMATS = {"semantickitti": "<u4", "nuscenes_lidarseg": "|u1", "nuscenes_panoptic": None, "npy": None}
PANOPTIC_CLASS_SCALE = 1000            # nuScenes-panoptic: class · 1000 + instance
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)      # the time stamp written into an .npz: the bytes do not depend on the run
BOX_2D_FORMATS = ("kitti", "yolo", "voc")
BOX_3D_FORMATS = ("kitti", "json", "csv")
BOX_3D_LAYOUTS = {      # what a box file holds (a refusal names it)
    "kitti": "KITTI label_2 lines: type truncated occluded alpha left top right bottom h w l x y z rotation_y [score] "
             "(KITTI tracking's label_02: frame track_id first)",
    "json": '[{"id", "class", "center_m": [x, y, z], "size_m": [length, width, height], "yaw_rad"}] (or that list '
            'under "boxes") in the sensor frame; a segments.ai / View-of-Delft label JSON or nuScenes\' '
            'sample_annotation.json is another layout: give KITTI label_2 + calib files',
    "csv": "a header id,class,x_m,y_m,z_m,length_m,width_m,height_m,yaw_rad (sensor frame)"}
_PNG_GREY, _PNG_PALETTE = 0, 3                   # PNG colour types
_TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*")
_PALETTE_CHUNKS = (b"PLTE", b"tRNS", b"bKGD", b"hIST", b"sPLT")   # chunks whose content is palette indices/colours
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def _read(path: Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise InputError("annotation file declared in the recipe's inputs does not exist", file=str(path)) from None
    except OSError as exc:
        raise InputError(f"cannot read annotation file: {exc.strerror or exc}", file=str(path)) from None


# --- per-point labels ----------------------------------------------------------------------------------------------


def point_label_format(path: str | os.PathLike, fmt: str | None) -> str:
    """The sidecar format: given, else from the name (``.label``, ``_lidarseg.bin``, ``.npy``)."""
    if fmt is not None:
        return fmt
    name = Path(path).name.lower()
    for suffix, f in ((".label", "semantickitti"), ("_lidarseg.bin", "nuscenes_lidarseg"),
                      ("_panoptic.npz", "nuscenes_panoptic"), (".npy", "npy")):
        if name.endswith(suffix):
            return f
    raise InputError("cannot tell the point-label format from the name; give point_labels_format "
                     f"({' | '.join(POINT_LABEL_FORMATS)})", file=str(path))


def read_point_labels(path: str | os.PathLike, fmt: str) -> np.ndarray:
    data = _read(Path(path))
    if fmt == "npy":
        try:
            return np.load(io.BytesIO(data), allow_pickle=False)
        except ValueError as exc:
            raise InputError(f"not a NumPy .npy array ({exc})", file=str(path)) from None
    if fmt == "nuscenes_panoptic":
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                return npz["data"]
        except (ValueError, KeyError, OSError, zipfile.BadZipFile) as exc:
            raise InputError(f"not a nuScenes-panoptic .npz with a 'data' array ({exc})", file=str(path)) from None
    dtype = np.dtype(POINT_LABEL_FORMATS[fmt])
    if len(data) % dtype.itemsize:
        raise InputError(f"{len(data)} bytes is not a whole number of {dtype.itemsize}-byte {fmt} labels",
                         file=str(path))
    return np.frombuffer(data, dtype).astype(dtype.newbyteorder("="))


def write_point_labels(path: str | os.PathLike, labels: np.ndarray, fmt: str) -> None:
    if fmt == "npy":
        buf = io.BytesIO()
        np.save(buf, labels, allow_pickle=False)
        write_bytes_atomic(path, buf.getvalue())
    elif fmt == "nuscenes_panoptic":                # np.savez_compressed, with a fixed time stamp
        array, buf = io.BytesIO(), io.BytesIO()
        np.save(array, labels, allow_pickle=False)
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr(zipfile.ZipInfo("data.npy", _ZIP_TIME), array.getvalue(), zipfile.ZIP_DEFLATED)
        write_bytes_atomic(path, buf.getvalue())
    else:
        write_bytes_atomic(path, np.ascontiguousarray(labels, dtype=POINT_LABEL_FORMATS[fmt]).tobytes())


# --- masks ---------------------------------------------------------------------------------------------------------


@dataclass
class Mask:
    """A label image: its values (H × W or H × W × C, any integer dtype) and, for a palette PNG (Pascal VOC's
    ``SegmentationClass``, Mapillary Vistas' labels), the file's ``PLTE`` and ``tRNS`` chunks: the values are then
    the palette indices, the class ids those datasets' loaders read, and are written back with the same palette.
    ``bit_depth`` 1, 2 or 4: a PNG of that many bits per sample (a binary segmentation mask is 1-bit grey), or a
    1-bit TIFF, whose values are its levels (0 … 2^bit_depth − 1, not OpenCV's 0–255 scaling) and which is written
    back so; ``min_is_white``: a 1-bit TIFF storing white as 0 (PhotometricInterpretation 0, fax and scanner
    masks), whose levels are as readers show them (white 1, as Pillow's and OpenCV's) and stored inverted again."""

    values: np.ndarray
    palette_chunks: tuple[bytes, ...] = ()
    bit_depth: int = 0                                       # 0: as OpenCV writes the dtype (8 or 16 bits)
    min_is_white: bool = False

    @property
    def shape(self) -> tuple[int, ...]:
        return self.values.shape

    @property
    def max_level(self) -> int | None:
        """The highest value the file can hold (None: the dtype's)."""
        return 2 ** self.bit_depth - 1 if self.bit_depth else None


def read_mask(path: str | os.PathLike) -> Mask:
    data = _read(Path(path))
    if Path(path).suffix.lower() == ".npy":                # labelme's SegmentationClassNpy/, any integer dtype
        try:
            return Mask(np.load(io.BytesIO(data), allow_pickle=False))
        except ValueError as exc:
            raise InputError(f"not a NumPy .npy array ({exc})", file=str(path)) from None
    return read_mask_bytes(data, path)


def read_mask_bytes(data: bytes, path) -> Mask:
    """A PNG/TIFF label image's :class:`Mask` from its bytes (``path`` names it in errors)."""
    from .png import PNG_SIGNATURE                          # here: a LiDAR or radar worker never imports the codecs

    if data.startswith(PNG_SIGNATURE) and len(data) > 25 and data[25] == _PNG_PALETTE:
        return _palette_mask(data, path)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("not an image OpenCV can decode (masks are PNG/TIFF label images)", file=str(path))
    if data.startswith(PNG_SIGNATURE) and len(data) > 25 and data[25] == _PNG_GREY and data[24] < 8:
        return Mask(_levels(img, data[24]), bit_depth=data[24])
    if data[:4] in _TIFF_SIGNATURES and img.ndim == 2:
        bits, min_is_white = _tiff_bits(data)
        if bits == 1:
            return Mask(_levels(img, 1), bit_depth=1, min_is_white=min_is_white)
    return Mask(img)


def _tiff_bits(data: bytes) -> tuple[int, bool]:
    """A TIFF's bits per sample and whether it stores white as 0 (its first page's tags)."""
    import tifffile

    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        page = tif.pages[0]
        return page.bitspersample, page.photometric == tifffile.PHOTOMETRIC.MINISWHITE


def _levels(decoded: np.ndarray, bit_depth: int) -> np.ndarray:
    """The stored samples of a 1/2/4-bit PNG that OpenCV scaled to 0–255 (by 255, 85, 17)."""
    return decoded // (255 // (2 ** bit_depth - 1)) if bit_depth < 8 else decoded


def _palette_mask(data: bytes, path) -> Mask:
    """A palette PNG's indices and its PLTE/tRNS chunks, whole: decoded as the grey PNG of the same samples (OpenCV
    would give the palette's colours), its 1/2/4-bit levels (OpenCV scales them to 0–255) divided back."""
    from .image_metadata import png_chunk_spans

    chunks = tuple(data[pos:pos + 12 + n] for kind, pos, n in png_chunk_spans(data) if kind in (b"PLTE", b"tRNS"))
    grey = cv2.imdecode(np.frombuffer(_retyped_png(data, _PNG_GREY), np.uint8), cv2.IMREAD_UNCHANGED)
    if grey is None:
        raise InputError("cannot decode this palette PNG", file=str(path))
    bit_depth = data[24]
    return Mask(_levels(grey, bit_depth), chunks, bit_depth if bit_depth < 8 else 0)


def write_mask(path: str | os.PathLike, mask: Mask) -> None:
    suffix = Path(path).suffix or ".png"
    if suffix.lower() == ".npy":
        buf = io.BytesIO()
        np.save(buf, mask.values, allow_pickle=False)
        write_bytes_atomic(path, buf.getvalue())
        return
    if mask.bit_depth and suffix.lower() in (".tif", ".tiff"):
        data = bilevel_tiff(mask.values, mask.min_is_white)
    elif mask.bit_depth:
        data = packed_png(mask.values, mask.bit_depth)
    else:
        ok, buf = cv2.imencode(suffix, mask.values)
        if not ok:
            raise InputError(f"cannot encode a {mask.values.dtype} mask as {suffix}", file=str(path))
        data = buf.tobytes()
    if mask.palette_chunks:
        data = _as_palette_png(data, mask)
    write_bytes_atomic(path, data)


def packed_png(levels: np.ndarray, bit_depth: int) -> bytes:
    """A grey PNG of ``bit_depth`` (1, 2, 4) bits per sample: each row's samples packed from the high bit (PNG spec
    §7.2), filter type 0, one IDAT. ValueError names a level the depth cannot hold."""
    from .png import PNG_SIGNATURE, png_chunk

    top = int(levels.max(initial=0))
    if top >= 2 ** bit_depth:
        raise ValueError(f"value {top} does not fit a {bit_depth}-bit mask")
    h, w = levels.shape
    bits = (levels[..., None].astype(np.uint8) >> np.arange(bit_depth - 1, -1, -1, dtype=np.uint8)) & 1
    rows = np.packbits(bits.reshape(h, w * bit_depth), axis=1)          # each row padded to whole bytes
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()
    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([bit_depth, _PNG_GREY, 0, 0, 0])
    return PNG_SIGNATURE + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", zlib.compress(raw, 9)) + _PNG_END


def bilevel_tiff(levels: np.ndarray, min_is_white: bool = False) -> bytes:
    """A 1-bit TIFF (Deflate) of 0/1 levels, white = 1: stored as they are (MinIsBlack) or inverted (MinIsWhite).
    ValueError names a level that does not fit."""
    import tifffile

    top = int(levels.max(initial=0))
    if top > 1:
        raise ValueError(f"value {top} does not fit a 1-bit mask")
    buf = io.BytesIO()
    tifffile.imwrite(buf, (levels == 0) if min_is_white else levels.astype(bool), compression="zlib", metadata=None,
                     photometric="miniswhite" if min_is_white else "minisblack")
    return buf.getvalue()


def _as_palette_png(grey: bytes, mask: Mask) -> bytes:
    """A grey PNG of the indices made a palette PNG with the input's palette, extended with black entries up to the
    highest index (a warp's fill value)."""
    from .png import png_chunk

    chunks = list(mask.palette_chunks)
    entries = int.from_bytes(chunks[0][:4], "big") // 3 if chunks and chunks[0][4:8] == b"PLTE" else 0
    needed = int(mask.values.max(initial=0)) + 1
    if chunks and entries < needed:
        chunks[0] = png_chunk(b"PLTE", chunks[0][8:-4] + bytes(3 * (needed - entries)))
    return _retyped_png(grey, _PNG_PALETTE, tuple(chunks))


def _retyped_png(data: bytes, colour_type: int, chunks: tuple[bytes, ...] = ()) -> bytes:
    """PNG bytes with another colour type of the same pixel layout — grey and palette samples are both one value
    per pixel (PNG spec §11.2.2) —, the palette chunks dropped and ``chunks`` inserted after IHDR."""
    from .image_metadata import png_chunk_spans

    ihdr = bytearray(data[8:33])                            # length, "IHDR", 13-byte body, CRC
    ihdr[17] = colour_type
    ihdr[21:25] = zlib.crc32(bytes(ihdr[4:21])).to_bytes(4, "big")
    rest = b"".join(data[pos:pos + 12 + n] for kind, pos, n in png_chunk_spans(data)
                    if kind != b"IHDR" and kind not in _PALETTE_CHUNKS)
    return data[:8] + bytes(ihdr) + b"".join(chunks) + rest + _PNG_END


# --- polygon files ---------------------------------------------------------------------------------------------


LABELME_SHAPES = ("polygon", "rectangle", "circle", "line", "linestrip", "point", "points", "mask")   # moved


def read_polygons(path: str | os.PathLike) -> dict:
    """A per-image polygon JSON: Cityscapes (``*_gtFine_polygons.json``) and Mapillary Vistas v2 — ``objects``, each
    with a ``polygon`` of [x, y] pixel positions (pixel centres on integers) — or LabelMe — ``shapes``, each with
    ``points`` and a ``shape_type`` (polygon, rectangle, circle, line, linestrip, point, mask) —; every key kept."""
    try:
        data = json.loads(_read(Path(path)))
        key, points = ("shapes", "points") if isinstance(data, dict) and "shapes" in data else ("objects", "polygon")
        for k, obj in enumerate(data[key]):
            if np.asarray(obj[points], dtype=float).reshape(-1, 2).shape[0] != len(obj[points]):
                raise ValueError(f"{key}[{k}].{points} is not a list of [x, y] pairs")
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"not a Cityscapes-style polygon file (objects with [x, y] polygons) nor a LabelMe file "
                         f"(shapes with [x, y] points): {exc}", file=str(path)) from None
    return data


def write_polygons(path: str | os.PathLike, data: dict) -> None:
    write_bytes_atomic(path, json.dumps(data, ensure_ascii=False).encode("utf-8"))


def labelme_image_data(image: bytes | None) -> str | None:
    """LabelMe's ``imageData`` of an image file's bytes: base64 (labelme decodes it with Pillow, whatever the
    format); None (null: LabelMe then opens ``imagePath``) without bytes (an EXR output)."""
    return None if image is None else base64.b64encode(image).decode("ascii")


_IMAGE_DATA = re.compile(rb'"imageData"\s*:\s*"([A-Za-z0-9+/=\\\s]*)"')


def labelme_with_image(raw: bytes, image: bytes | None) -> bytes:
    """A LabelMe file's bytes with its ``imageData`` replaced by :func:`labelme_image_data` of ``image``, every other
    byte as read (the base64 string is swapped in place); a file whose ``imageData`` string is not found once as
    such is written again as compact JSON."""
    found = list(_IMAGE_DATA.finditer(raw))
    value = labelme_image_data(image)
    if len(found) != 1:
        return json.dumps({**json.loads(raw), "imageData": value}, ensure_ascii=False).encode("utf-8")
    return raw[:found[0].start(1) - 1] + json.dumps(value).encode("ascii") + raw[found[0].end(1) + 1:]


# --- 2-D boxes -----------------------------------------------------------------------------------------------------


@dataclass
class Boxes2D:
    """Lines of a 2-D box file: ``tokens`` per line and, per line, its points in pixels (x, y) as an (M, 2) array:
    KITTI and YOLO boxes as their 2 corners, YOLO polygons as their vertices."""

    fmt: str
    tokens: list
    points_px: list[np.ndarray]
    is_box: list[bool]
    document: bytes = b""          # Pascal VOC: the XML as read (tokens: (object, part or None) of each box)


VOC_BOX = ("xmin", "ymin", "xmax", "ymax")


def _voc_boxes(path, data: bytes, width: int, height: int) -> Boxes2D:
    """Pascal VOC XML: each ``object``'s ``bndbox`` and its ``part`` boxes (person layout), 1-based pixel indices
    (VOC devkit), as pixel positions (centres on integers: index − 1)."""
    from xml.etree import ElementTree

    try:
        root = ElementTree.fromstring(data)
        size = root.find("size")
        stated = (int(float(size.findtext("width"))), int(float(size.findtext("height")))) if size is not None \
            else (width, height)
        tokens, points = [], []
        for i, obj in enumerate(root.findall("object")):
            for j, box in [(None, obj.find("bndbox"))] + list(enumerate(b.find("bndbox") for b in obj.findall("part"))):
                if box is None:
                    raise ValueError(f"object {i + 1} has a part without a bndbox" if j is not None else
                                     f"object {i + 1} ({obj.findtext('name')}) has no bndbox")
                tokens.append((i, j))
                points.append(np.array([float(box.findtext(k)) for k in VOC_BOX]).reshape(2, 2) - 1.0)
    except (ElementTree.ParseError, ValueError, TypeError) as exc:
        raise InputError(f"not a Pascal VOC annotation (annotation/object/bndbox with xmin … ymax): {exc}",
                         file=str(path)) from None
    if stated != (width, height):
        raise InputError(f"its size is {stated[0]}×{stated[1]} px, the image {width}×{height}", file=str(path))
    return Boxes2D("voc", tokens, points, [True] * len(tokens), data)


def _write_voc(path, boxes: Boxes2D) -> None:
    """The VOC XML as read with each kept box's moved corners (integers when the input's were, else to 1/1000 px)
    and the objects and parts whose box left the image removed."""
    from xml.etree import ElementTree

    root = ElementTree.fromstring(boxes.document)
    objects = root.findall("object")
    moved = dict(zip(boxes.tokens, boxes.points_px))
    for i, obj in enumerate(objects):
        if (i, None) not in moved:
            root.remove(obj)
            continue
        for j, part in [(None, obj)] + list(enumerate(obj.findall("part"))):
            if (i, j) not in moved:
                obj.remove(part)
                continue
            box = part.find("bndbox")
            for k, v in zip(VOC_BOX, moved[(i, j)].ravel() + 1.0):
                whole = box.findtext(k).strip().lstrip("-").isdigit()
                box.find(k).text = str(int(round(v))) if whole else f"{v:.3f}"
    head = b'<?xml version="1.0" encoding="utf-8"?>\n' if boxes.document.lstrip().startswith(b"<?xml") else b""
    write_bytes_atomic(path, head + ElementTree.tostring(root, encoding="utf-8", xml_declaration=False))


def read_boxes_2d(path: str | os.PathLike, fmt: str, width: int, height: int) -> Boxes2D:
    if fmt == "voc":
        return _voc_boxes(path, _read(Path(path)), width, height)
    text = _read(Path(path)).decode("utf-8", errors="replace")
    tokens, points, is_box = [], [], []
    for i, line in enumerate(text.splitlines(), 1):
        words = line.split()
        if not words:
            continue
        try:
            if fmt == "kitti":
                if len(words) < 15:
                    raise ValueError(f"{len(words)} values, KITTI label_2 has 15 (16 with a score)")
                if _is_int(words[0]):
                    raise ValueError("a KITTI tracking label (frame track_id type …, one file per sequence): boxes_2d "
                                     "moves the boxes of per-image label_2 files; a sequence file's are not moved")
                left, top, right, bottom = map(float, words[4:8])
                pts, box = np.array([[left, top], [right, bottom]]), True
            else:
                values = np.array(words[1:], dtype=float)
                if len(values) < 4 or len(values) % 2:
                    raise ValueError(f"{len(words)} values; YOLO has class cx cy w h, or class and x y pairs")
                if len(values) == 4:
                    cx, cy, w, h = values
                    pts, box = np.array([[cx - w / 2, cy - h / 2], [cx + w / 2, cy + h / 2]]), True
                else:
                    pts, box = values.reshape(-1, 2), False
                pts = pts * [width, height] - 0.5               # pixel centres at integer coordinates (Warp)
        except ValueError as exc:
            raise InputError(f"line {i}: {exc}", file=str(path)) from None
        tokens.append(words)
        points.append(pts)
        is_box.append(box)
    return Boxes2D(fmt, tokens, points, is_box)


def write_boxes_2d(path: str | os.PathLike, boxes: Boxes2D, width: int, height: int) -> None:
    if boxes.fmt == "voc":
        return _write_voc(path, boxes)
    lines = []
    for words, pts, box in zip(boxes.tokens, boxes.points_px, boxes.is_box):
        if boxes.fmt == "kitti":
            words = words[:4] + [f"{v:.2f}" for v in pts.ravel()] + words[8:]
        else:
            p = (pts + 0.5) / [width, height]
            values = ([(p[0, 0] + p[1, 0]) / 2, (p[0, 1] + p[1, 1]) / 2, p[1, 0] - p[0, 0], p[1, 1] - p[0, 1]]
                      if box else p.ravel())
            words = words[:1] + [f"{v:.6f}" for v in values]
        lines.append(" ".join(words))
    write_bytes_atomic(path, ("\n".join(lines) + "\n" if lines else "").encode("utf-8"))


# --- 3-D boxes -----------------------------------------------------------------------------------------------------


@dataclass
class Boxes3D:
    """Boxes in the point cloud's frame: id, class, centre (m), size length × width × height (m, along the box's x,
    y, z), yaw about z (rad); ``to_box_frame`` (4 × 4) maps cloud coordinates into the frame the boxes are given in
    (identity for the sensor frame, rectified camera ← LiDAR for KITTI)."""

    ids: list[str]
    classes: list[str]
    center_m: np.ndarray
    size_m: np.ndarray
    yaw_rad: np.ndarray
    to_box_frame: np.ndarray
    up_axis: int = 2                 # 2: z up (sensor frame); 1: y down (KITTI camera: boxes stand on their base)


def read_boxes_3d(path: str | os.PathLike, fmt: str, calib_path: str | os.PathLike | None = None,
                  frame: str = "") -> Boxes3D:
    """The 3-D boxes of a scan; ``frame``: its file's stem, which picks a KITTI tracking label file's lines."""
    raw = _read(Path(path)).decode("utf-8", errors="replace")
    try:
        if fmt == "kitti":
            return _kitti_boxes(raw, calib_path, path, frame)
        rows = _json_rows(raw) if fmt == "json" else _csv_rows(raw)
        center = np.array([r[2] for r in rows], dtype=float).reshape(-1, 3)
        size = np.array([r[3] for r in rows], dtype=float).reshape(-1, 3)
        yaw = np.array([float(r[4]) for r in rows])
    except InputError:
        raise
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        what = f"no {exc.args[0]!r}" if isinstance(exc, KeyError) else repr(exc)
        raise InputError(f"bad {fmt} 3-D box file ({what}); expected {BOX_3D_LAYOUTS[fmt]}", file=str(path)) from None
    return Boxes3D([str(r[0]) for r in rows], [str(r[1]) for r in rows], center, size, yaw, np.eye(4))


def _json_rows(raw: str) -> list:
    data = json.loads(raw)
    boxes = data["boxes"] if isinstance(data, dict) else data
    return [(b.get("id", i), b.get("class", ""), b["center_m"], b["size_m"], b.get("yaw_rad", 0.0))
            for i, b in enumerate(boxes)]


def _csv_rows(raw: str) -> list:
    rows = []
    for i, r in enumerate(csv.DictReader(io.StringIO(raw))):
        rows.append((r.get("id") or i, r.get("class", ""), [r["x_m"], r["y_m"], r["z_m"]],
                     [r["length_m"], r["width_m"], r["height_m"]], r.get("yaw_rad") or 0.0))
    return rows


def _kitti_boxes(raw: str, calib_path, path, frame: str) -> Boxes3D:
    """KITTI object labels: ``h w l`` and bottom-centre ``x y z`` in the rectified camera frame (y down),
    ``rotation_y`` about its y axis; the calib's ``R0_rect · Tr_velo_to_cam`` maps LiDAR points into it. DontCare
    regions are skipped. A KITTI tracking label file (``label_02/0000.txt``: one per sequence, each line led by its
    ``frame`` and ``track_id``) gives the lines of the scan's frame (its file's stem, ``000042`` → 42), ids the
    track ids."""
    if calib_path is None:
        raise InputError("KITTI 3-D boxes need the calib file (annotations.calib)", file=str(path))
    calib = _kitti_calib(_read(Path(calib_path)).decode("utf-8", errors="replace"), calib_path)
    lines = [w for w in (line.split() for line in raw.splitlines()) if w]
    tracking = bool(lines) and _is_int(lines[0][0])
    if tracking:
        if not frame.isdigit():
            raise InputError(f"a KITTI tracking label file (frame, track_id, type, …) gives the boxes of frame "
                             f"numbers; the scan's name {frame!r} is none", file=str(path))
        lines = [w[1:] for w in lines if _is_int(w[0]) and int(w[0]) == int(frame)]
    ids, classes, center, size, yaw = [], [], [], [], []
    for i, w in enumerate(lines):
        ident, w = (w[0], w[1:]) if tracking else (str(i), w)
        if len(w) < 15 or w[0] == "DontCare":
            continue
        h, wd, ln, x, y, z, ry = map(float, w[8:15])
        ids.append(ident)
        classes.append(w[0])
        center.append([x, y - h / 2, z])
        size.append([ln, h, wd])                      # along the camera-frame box axes x (length), y, z (width)
        yaw.append(ry)
    return Boxes3D(ids, classes, np.array(center).reshape(-1, 3), np.array(size).reshape(-1, 3), np.array(yaw),
                   calib, up_axis=1)


def is_kitti_tracking(path: str | os.PathLike) -> bool:
    """Whether a KITTI label file is KITTI tracking's (``label_02/0000.txt``: one per sequence, each line led by
    ``frame track_id``) rather than a per-frame ``label_2`` file (led by the object's type)."""
    words = next((line.split() for line in _read(Path(path)).decode("utf-8", errors="replace").splitlines()
                  if line.strip()), [])
    return bool(words) and _is_int(words[0])


def _is_int(word: str) -> bool:
    return word.lstrip("-").isdigit()


def _kitti_calib(text: str, path) -> np.ndarray:
    """``R0_rect · Tr_velo_to_cam``: LiDAR → the rectified reference camera (camera 0) the labels are given in
    (:func:`~roadview_noise.depth.calibration.kitti_lidar_to_rectified`: also Waymo's KITTI-format
    ``Tr_velo_to_cam_0``)."""
    from ..depth.calibration import kitti_lidar_to_rectified, kitti_rows

    try:
        transforms = kitti_lidar_to_rectified(kitti_rows(text), 0, str(path))
    except (InputError, ValueError):
        transforms = None
    if transforms is None:
        raise InputError("KITTI calib needs R0_rect (9 values) and Tr_velo_to_cam (12 values; Tr_velo_to_cam_0 in "
                         "Waymo's KITTI format)", file=str(path))
    r0, tr = transforms
    return r0 @ tr
