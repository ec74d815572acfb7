"""ROS sensor messages ↔ rvnoise frames and clouds: ``sensor_msgs`` CompressedImage, Image and PointCloud2.

Messages are the deserialised objects of ``rosbags`` (ROS 1 and ROS 2 alike); everything but the payload — header
(stamp, frame_id), ``format``, ``encoding``, ``is_bigendian``, ``is_dense``, the field layout — is carried over
unchanged by the writers here, which return a new message of the same class.

- CompressedImage: the ``data`` bytes are a JPEG or PNG file (told by its signature, else by ``format``, e.g.
  ``jpeg``, ``bgr8; jpeg compressed bgr8``, ``png``), decoded and re-encoded exactly like image files
  (:func:`..io.image.decode_image` / :func:`..io.image.encode_image`, JPEG quality estimated from the input).
- Image: ``rgb8 bgr8 rgba8 bgra8 rgb16 bgr16 rgba16 bgra16 mono8 mono16 8UC1 8UC3 16UC1 16UC3`` are sRGB code values
  like an 8/16-bit PNG (``8UC3``/``16UC3`` in OpenCV's BGR order; ``16UC1`` is a 16-bit grey image on a camera
  topic): :class:`CameraFrame`. ``bayer_{rggb,bggr,gbrg,grbg}{8,16}`` are CFA digital numbers: :class:`RawFrame` with
  black level 0 and white level 2^bits − 1 unless the topic states its levels. Rows may be padded (``step``).
- Depth (aligned depth topic, REP 118): Image ``32FC1`` (m) or ``16UC1``/``mono16`` (mm), or a ``compressedDepth``
  CompressedImage (PNG codec); 0, NaN and −inf (no measurement, too close) are holes (NaN, for the recipe's
  ``depth_holes``), +inf (nothing within range) stays.
- PointCloud2: fields (any of the eight PointField datatypes, ``count`` ≥ 1, any offsets, padding, big-endian)
  are read in offset order and named like file fields (:func:`..io.pointcloud.cloud_from_columns`); an organised
  cloud (height > 1) is a full grid (``grid_shape``, beams × azimuths: a cloud stored a row per firing, Velodyne's,
  is read transposed, :class:`GridCells`) whose cells with NaN x/y/z (the driver's no-return marker) are no-return
  cells. Written back with every input field at its offset and datatype (a point from the input starts from its
  bytes: padding kept), then the field :func:`..io.pointcloud.output_columns` adds (the weather-effect code
  ``rv_effect``, uint8) appended after the input's ``point_step``; an organised cloud keeps height × width, its
  order and its no-return marker when the point count is unchanged.
"""

from __future__ import annotations

import dataclasses
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from ..types import CFA_PATTERNS, CameraFrame, CameraProfile, CloudLayout, PointCloud, RawEncoding, RawFrame
from . import image as image_io
from .png import PNG_SIGNATURE
from .pointcloud import Column, _canonical_keys, beam_row_order, cloud_from_columns, firing_row_columns, \
    output_columns

COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"             # a camera topic's intrinsics: io/camera_info.py
SENSOR_TYPES = {"camera": (COMPRESSED_IMAGE, IMAGE), "lidar": (POINTCLOUD2,), "radar": (POINTCLOUD2,)}

# PointField datatype → NumPy base type (sensor_msgs/PointField constants INT8 … FLOAT64)
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_POINTFIELD_CODE = {v: k for k, v in POINTFIELD_TYPES.items()}


@dataclass(frozen=True)
class PixelLayout:
    """How an Image encoding stores pixels: sample type, channels, channel order (``rgb``, ``bgr``, ``grey``) or the
    CFA pattern of a Bayer mosaic."""

    dtype: str                  # u1 | u2 | f4
    channels: int
    order: str                  # rgb | bgr | grey | bayer
    cfa_pattern: str | None = None


def _pixel_layouts() -> dict[str, PixelLayout]:
    table = {"mono8": PixelLayout("u1", 1, "grey"), "mono16": PixelLayout("u2", 1, "grey"),
             "8UC1": PixelLayout("u1", 1, "grey"), "16UC1": PixelLayout("u2", 1, "grey"),
             "8UC3": PixelLayout("u1", 3, "bgr"), "16UC3": PixelLayout("u2", 3, "bgr"),
             "32FC1": PixelLayout("f4", 1, "grey")}
    for bits, dt in ((8, "u1"), (16, "u2")):
        for order in ("rgb", "bgr"):
            table[f"{order}{bits}"] = PixelLayout(dt, 3, order)
            table[f"{order}a{bits}"] = PixelLayout(dt, 4, order)
        for pattern in CFA_PATTERNS:
            table[f"bayer_{pattern.lower()}{bits}"] = PixelLayout(dt, 1, "bayer", pattern)
    return table


PIXEL_LAYOUTS = _pixel_layouts()
CAMERA_ENCODINGS = tuple(k for k, v in PIXEL_LAYOUTS.items() if v.dtype != "f4")
DEPTH_ENCODINGS = ("32FC1", "16UC1", "mono16")


def type_hint(msgtype: str) -> str:
    """What to do about a message type rvnoise does not read, where a common driver writes it ('' otherwise)."""
    if msgtype.startswith("livox_ros_driver") and msgtype.endswith("/CustomMsg"):
        return ("; a Livox CustomMsg is the driver's own point list, not a PointCloud2: record with "
                "livox_ros_driver2's xfer_format 0 (PointCloud2) or convert the topic first")
    if msgtype in ("radar_msgs/msg/RadarScan", "radar_msgs/RadarScan"):
        return ("; a radar_msgs RadarScan (TIER IV's ars408_driver, Autoware) lists returns as range, azimuth, "
                "elevation, doppler_velocity, amplitude, not a PointCloud2: convert the topic to PointCloud2 (x y z "
                "from range and angles, v_r = doppler_velocity, amplitude named for its unit, rcs or snr) first")
    return ""


def compressed_format(msg: Any, *, source: str) -> str:
    """``jpeg`` | ``png`` of a CompressedImage: its data's signature, else its ``format`` string (publishers that
    leave ``format`` empty or name another codec than they wrote); ``compressedDepth`` is refused."""
    fmt = msg.format
    text = fmt.lower()
    if "compresseddepth" in text:
        raise InputError(f"CompressedImage format {fmt!r} is a compressed depth image, not a camera image",
                         file=source)
    head = np.asarray(msg.data[:8], np.uint8).tobytes()
    if head.startswith(b"\xff\xd8\xff"):
        return "jpeg"
    if head == PNG_SIGNATURE:
        return "png"
    if "jpeg" in text or "jpg" in text:
        return "jpeg"
    if "png" in text:
        return "png"
    raise InputError(f"CompressedImage format {fmt!r} is neither JPEG nor PNG", file=source)


def pixel_layout(encoding: str, *, allowed: tuple[str, ...] = CAMERA_ENCODINGS, source: str) -> PixelLayout:
    if encoding not in allowed:
        raise InputError(f"Image encoding {encoding!r} is not supported here (supported: {', '.join(allowed)})",
                         file=source)
    return PIXEL_LAYOUTS[encoding]


def image_pixels(msg: Any, *, allowed: tuple[str, ...] = CAMERA_ENCODINGS, source: str) -> np.ndarray:
    """The pixels of an Image message as stored (H, W) or (H, W, C), native byte order, padding removed."""
    layout = pixel_layout(msg.encoding, allowed=allowed, source=source)
    dtype = np.dtype(layout.dtype).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * layout.channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if h == 0 or w == 0 or step < row or len(data) < step * (h - 1) + row:
        raise InputError(f"Image {msg.encoding} {w}×{h} with step {step} needs {step * h} bytes, the message has "
                         f"{len(data)}", file=source)
    rows = data[:h * row] if step == row else np.ascontiguousarray(
        np.lib.stride_tricks.as_strided(data, (h, row), (step, 1)))
    pixels = rows.view(dtype).reshape((h, w) if layout.channels == 1 else
                                                              (h, w, layout.channels))
    return pixels.astype(dtype.newbyteorder("="), copy=False)


def rgb_codes(pixels: np.ndarray, layout: PixelLayout) -> np.ndarray:
    """An Image's colour pixels in RGB(A) order (grey as it is) — and back: swapping R and B is its own inverse."""
    if layout.order != "bgr":
        return pixels
    return pixels[..., [2, 1, 0, 3]] if layout.channels == 4 else pixels[..., ::-1]


def image_to_frame(msg: Any, msgtype: str, profile: CameraProfile | None, *, source: str,
                   black_level_dn: float | None = None, white_level_dn: float | None = None,
                   untagged_transfer: str = "srgb") -> CameraFrame | RawFrame:
    """A camera or raw frame from a CompressedImage or Image message with ``profile`` (fitted to the image size, or
    None until :func:`roadview_noise.camera_inputs.with_camera_inputs` resolves it). Levels of a Bayer mosaic
    default to 0 and the full scale of its sample type. ``untagged_transfer`` (``srgb`` or ``linear``: the recipe's
    ``inputs.untagged_transfer``) is the transfer function of codes that state none: every Image message (``mono16``
    of a machine-vision camera: usually linear) and a compressed PNG without colour chunks."""
    if msgtype == COMPRESSED_IMAGE:
        fmt = compressed_format(msg, source=source)
        linear, encoding, alpha = image_io.decode_image(np.asarray(msg.data, np.uint8).tobytes(), fmt, source=source,
                                                        untagged_transfer=untagged_transfer)
        return CameraFrame(linear, profile, encoding=encoding, alpha=alpha)
    layout = pixel_layout(msg.encoding, source=source)
    pixels = image_pixels(msg, source=source)
    if layout.order == "bayer":
        black = 0.0 if black_level_dn is None else float(black_level_dn)
        white = float(np.iinfo(pixels.dtype).max) if white_level_dn is None else float(white_level_dn)
        return RawFrame(pixels.astype(np.float32), layout.cfa_pattern, black, white, profile,
                        encoding=RawEncoding(fmt="raw", bits_per_sample=8 * pixels.dtype.itemsize))
    linear, encoding, alpha = image_io.image_from_codes(rgb_codes(pixels, layout), "png", source=source,
                                                        transfer=untagged_transfer)
    return CameraFrame(linear, profile, encoding=encoding, alpha=alpha)


def frame_to_image(msg: Any, msgtype: str, frame: CameraFrame | RawFrame, *, source: str) -> Any:
    """``msg`` with the frame as its payload, in the message's own format or encoding (JPEG quality of the input)."""
    if msgtype == COMPRESSED_IMAGE:
        data = image_io.encode_image(frame.linear_rgb, frame.encoding, frame.alpha, name=source)
        return dataclasses.replace(msg, data=np.frombuffer(data, np.uint8))
    layout = PIXEL_LAYOUTS[msg.encoding]
    if isinstance(frame, RawFrame):
        info = np.iinfo(np.dtype(layout.dtype))
        rounded = np.rint(frame.dn)
        pixels = np.clip(rounded, info.min, info.max, out=rounded).astype(layout.dtype)
    else:
        pixels = rgb_codes(image_io.codes_from_image(frame.linear_rgb, frame.encoding, frame.alpha, name=source),
                           layout)
    pixels = np.ascontiguousarray(pixels, dtype=pixels.dtype.newbyteorder(">" if msg.is_bigendian else "<"))
    h, w = pixels.shape[:2]
    return dataclasses.replace(msg, height=h, width=w, step=pixels.strides[0],
                               data=pixels.reshape(-1).view(np.uint8))


def depth_image_m(msg: Any, msgtype: str, *, source: str) -> np.ndarray:
    """Depth (m, float32) of a depth Image (REP 118): ``32FC1`` metres or 16-bit millimetres, or of a
    ``compressedDepth`` CompressedImage (:func:`compressed_depth`); no measurement (0, NaN, −inf) → NaN (a hole)."""
    if msgtype == COMPRESSED_IMAGE:
        z = compressed_depth(msg, source=source)
    elif msgtype == IMAGE:
        pixels = image_pixels(msg, allowed=DEPTH_ENCODINGS, source=source)
        z = pixels.astype(np.float32) * np.float32(1.0 if pixels.dtype.kind == "f" else 1e-3)
    else:
        raise InputError(f"a depth topic must carry sensor_msgs/Image ({', '.join(DEPTH_ENCODINGS)}) or a "
                         f"compressedDepth CompressedImage, not {msgtype}", file=source)
    z[~(z > 0)] = np.nan
    return z


def compressed_depth(msg: Any, *, source: str) -> np.ndarray:
    """Depth (m, float32; NaN where none) of a CompressedImage of ROS' compressed_depth_image_transport: ``format``
    ``16UC1; compressedDepth png`` (or without the codec, older publishers) or ``32FC1; compressedDepth png``; the data
    are a 12-byte ConfigHeader (int32 format, float32 depthQuantA, depthQuantB; little-endian) then a 16-bit PNG:
    millimetres for 16UC1, quantised inverse depth for 32FC1, z = A / (v − B) with v = 0 no measurement."""
    import cv2

    encoding, _, rest = msg.format.partition(";")
    encoding, codec = encoding.strip(), rest.strip().removeprefix("compressedDepth").strip() or "png"
    if "compressedDepth" not in msg.format or encoding not in ("16UC1", "32FC1"):
        raise InputError(f"CompressedImage format {msg.format!r} is not a 16UC1 or 32FC1 compressedDepth image",
                         file=source)
    if codec != "png":
        raise InputError(f"compressedDepth codec {codec!r} is not supported (png is)", file=source)
    data = np.asarray(msg.data, np.uint8).tobytes()
    if len(data) < 20 or data[12:20] != b"\x89PNG\r\n\x1a\n":
        raise InputError(f"compressedDepth data ({len(data)} bytes) is not a 12-byte header and a PNG", file=source)
    _, quant_a, quant_b = struct.unpack_from("<iff", data)
    v = cv2.imdecode(np.frombuffer(data, np.uint8, offset=12), cv2.IMREAD_UNCHANGED)
    if v is None or v.dtype != np.uint16 or v.ndim != 2:
        raise InputError("compressedDepth PNG is not a 16-bit single-channel image", file=source)
    if encoding == "16UC1":
        return v.astype(np.float32) * np.float32(1e-3)
    with np.errstate(divide="ignore"):
        z = np.float32(quant_a) / (v.astype(np.float32) - np.float32(quant_b))
    z[v == 0] = np.nan
    return z


# --- PointCloud2 ----------------------------------------------------------------------------------------------------


def cloud_columns(msg: Any, *, source: str, stored: np.ndarray | None = None) -> list[Column]:
    """Per-point fields of a PointCloud2 in offset order as (name, little-endian dtype string, native values);
    ``stored``: its :func:`point_bytes` if already read."""
    order = ">" if msg.is_bigendian else "<"
    fields = sorted(msg.fields, key=lambda f: f.offset)
    if not fields:
        raise InputError("PointCloud2 has no fields", file=source)
    formats, offsets, end = [], [], 0
    for f in fields:
        base = POINTFIELD_TYPES.get(int(f.datatype))
        if base is None:
            raise InputError(f"PointCloud2 field {f.name!r} has unknown datatype {f.datatype}", file=source)
        count = max(int(f.count), 1)
        if f.offset < end:
            raise InputError(f"PointCloud2 field {f.name!r} at offset {f.offset} overlaps the previous field",
                             file=source)
        formats.append(np.dtype((order + base, (count,))) if count > 1 else np.dtype(order + base))
        offsets.append(int(f.offset))
        end = int(f.offset) + formats[-1].itemsize
    step = int(msg.point_step)
    if end > step:
        raise InputError(f"PointCloud2 fields end at byte {end}, beyond point_step {step}", file=source)
    record = np.dtype({"names": [f"f{i}" for i in range(len(fields))], "formats": formats, "offsets": offsets,
                       "itemsize": step})
    points = (point_bytes(msg, source=source) if stored is None else stored).reshape(-1).view(record)
    columns = []
    for i, (f, fmt) in enumerate(zip(fields, formats)):
        base, shape = (fmt.subdtype if fmt.subdtype else (fmt, ()))
        values = points[f"f{i}"]
        dt = ("(" + ",".join(map(str, shape)) + ",)" if shape else "") + base.newbyteorder("<").str
        columns.append((f.name, dt, np.ascontiguousarray(values, dtype=values.dtype.newbyteorder("="))))
    return columns


def point_bytes(msg: Any, *, source: str) -> np.ndarray:
    """The points of a PointCloud2 as stored, row padding removed: (height·width, point_step) uint8."""
    step, h, w = int(msg.point_step), int(msg.height), int(msg.width)
    data = np.asarray(msg.data, np.uint8)
    row_step = int(msg.row_step)
    if h * w and (row_step < w * step or len(data) < row_step * (h - 1) + w * step):
        raise InputError(f"PointCloud2 of {h}×{w} points × {step} bytes (row_step {row_step}) needs "
                         f"{row_step * h} bytes, the message has {len(data)}", file=source)
    if h * w and row_step != w * step:
        data = np.lib.stride_tricks.as_strided(data, (h, w * step), (row_step, 1))
    return np.ascontiguousarray(data[:h * w * step] if data.ndim == 1 else data).reshape(h * w, step)


@dataclass(frozen=True)
class GridCells:
    """How an organised PointCloud2 (height > 1) is rvnoise's grid of beams × azimuths (``shape``, None for a point
    list): ``order`` the message index of each grid cell when the message stores the transpose (Velodyne's organised
    clouds, rslidar_sdk's unless ``send_by_rows``: a row per firing, a column per laser — told by a ``ring`` field
    constant down each column; grid rows sorted by ring), else None;
    ``empty`` per grid cell: x, y or z not finite, the driver's no-return marker (ouster-ros since 0.10, Velodyne
    organised clouds), read as a no-return cell (position zero) and written back as it was."""

    shape: tuple[int, int] | None
    order: np.ndarray | None
    empty: np.ndarray


def grid_cells(msg: Any, columns: list[Column], keys: list[str]) -> GridCells:
    """:class:`GridCells` of a message whose per-point ``columns`` (storage order) have canonical ``keys``."""
    h, w = int(msg.height), int(msg.width)
    where = {k: i for i, k in enumerate(keys)}
    if h <= 1:
        return GridCells(None, None, np.zeros(h * w, bool))
    shape, order = (h, w), None
    ring = columns[where["ring"]][2] if "ring" in where and columns[where["ring"]][2].ndim == 1 else None
    lasers = None if ring is None else firing_row_columns(ring.reshape(h, w))
    if lasers is not None:                                                       # one ring per column
        shape, order = (w, h), beam_row_order(h, w, lasers)                      # grid rows in ring order
    empty = np.zeros(h * w, bool)
    for axis in "xyz":
        if axis in where and columns[where[axis]][2].ndim == 1 and columns[where[axis]][2].dtype.kind == "f":
            empty |= ~np.isfinite(columns[where[axis]][2])
    return GridCells(shape, order, empty if order is None else empty[order])


def cloud_to_pointcloud(msg: Any, *, sensor: str, profile, field_map: dict[str, str] | None,
                        source: str) -> PointCloud:
    """A cloud from a PointCloud2 (see module docstring); InputError names ``source``."""
    columns = cloud_columns(msg, source=source)
    keys = _canonical_keys([c[0] for c in columns], field_map, source)
    grid = grid_cells(msg, columns, keys)
    if grid.order is not None:
        columns = [(name, dt, values[grid.order]) for name, dt, values in columns]
    return cloud_from_columns(columns, fmt="pcd", mode="binary", grid_shape=grid.shape, sensor=sensor,
                              profile=profile, field_map=field_map, source=source)


def pointcloud_to_cloud2(msg: Any, cloud: PointCloud, *, effect: str, source: str) -> Any:
    """``msg`` carrying ``cloud``: the input fields at their offsets and datatypes, added fields appended. A point
    that descends from an input point starts from its bytes (padding kept); a no-return cell of the input that is
    still one is written back byte for byte (NaN marker included), and a cell the chain emptied gets NaN x/y/z when
    the input marks no-returns so (``CloudLayout.no_return``, :func:`..io.pointcloud.output_columns`)."""
    layout = cloud.layout or CloudLayout("pcd", ())
    columns, added = output_columns(cloud, layout, effect=effect, name=source)
    fields = sorted(msg.fields, key=lambda f: f.offset)
    point_field = type(fields[0])
    out_fields = list(msg.fields)
    offsets = [int(f.offset) for f in fields]
    step_in = step = int(msg.point_step)
    if added is not None:
        base = np.dtype(added[1])
        out_fields.append(point_field(name=added[0], offset=step, datatype=_POINTFIELD_CODE[base.str[1:]], count=1))
        offsets.append(step)
        step += base.itemsize
        columns.append(added)
    order = ">" if msg.is_bigendian else "<"
    record = np.dtype({"names": [f"f{i}" for i in range(len(columns))],
                       "formats": [np.dtype(dt).newbyteorder(order) for _, dt, _ in columns],
                       "offsets": offsets, "itemsize": step})
    n = len(cloud)
    keys = [k for k, _, _ in layout.fields]
    source_bytes = point_bytes(msg, source=source)
    msg_columns = cloud_columns(msg, source=source, stored=source_bytes) if int(msg.height) > 1 else []
    grid = grid_cells(msg, msg_columns, keys)
    to_msg = np.arange(len(source_bytes)) if grid.order is None else grid.order   # message index of a cloud index
    cells = grid.shape is not None and cloud.grid_shape == grid.shape and n == len(source_bytes)
    points = np.zeros(n, record)
    raw = points.view(np.uint8).reshape(n, step)
    origin = None if cloud.origin is None else np.asarray(cloud.origin)
    if origin is not None and len(origin) == len(source_bytes) and (origin == np.arange(len(origin))).all():
        origin = None                                                  # a grid's cells: the identity
    if origin is None and grid.order is None and n == len(source_bytes):
        raw[:, :step_in] = source_bytes
    else:
        origin = np.arange(n) if origin is None else origin
        from_input = origin >= 0
        raw[from_input, :step_in] = np.take(source_bytes, to_msg[origin[from_input]], axis=0)
    for i, (_, _, values) in enumerate(columns):
        points[f"f{i}"] = values
    if cells and grid.empty.any():             # (cells the chain emptied have NaN x/y/z: output_columns)
        still = ~cloud.positions_m.any(axis=1) & grid.empty
        raw[still, :step_in] = np.take(source_bytes, to_msg[still], axis=0)
    if cells and grid.order is not None:
        stored = np.empty_like(points)
        stored[grid.order] = points
        points, (h, w) = stored, (int(msg.height), int(msg.width))
    else:
        h, w = cloud.grid_shape if cloud.grid_shape and cloud.grid_shape[0] * cloud.grid_shape[1] == n else (1, n)
    return dataclasses.replace(msg, height=h, width=w, fields=out_fields, point_step=step, row_step=w * step,
                               data=points.view(np.uint8))
