"""sensor_msgs ↔ frames and clouds: every Image encoding, padded rows, big-endian data, PointCloud2 layouts."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from roadview_noise.errors import InputError
from roadview_noise.io import ros_messages as rm
from roadview_noise.io.image import decode_image, embed_icc_profile, icc_profile
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.provenance import ATTENUATED, REMOVED
from roadview_noise.types import CameraFrame, RawFrame

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
PROFILE = lucid_triton_028s().resized(40, 30)
RNG = np.random.default_rng(5)
RGB16 = RNG.integers(0, 65536, (30, 40, 3), dtype=np.uint16)
RGB8 = (RGB16 >> 8).astype(np.uint8)


def header():
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=3, nanosec=4), frame_id="cam")


def image(pixels: np.ndarray, encoding: str, *, pad: int = 0, big: bool = False):
    pixels = np.ascontiguousarray(pixels, dtype=pixels.dtype.newbyteorder(">" if big else "<"))
    h, w = pixels.shape[:2]
    rows = pixels.reshape(h, -1).view(np.uint8)
    data = np.concatenate([rows, np.full((h, pad), 7, np.uint8)], axis=1).ravel()
    return T["sensor_msgs/msg/Image"](header=header(), height=h, width=w, encoding=encoding, is_bigendian=int(big),
                                      step=rows.shape[1] + pad, data=data)


@pytest.mark.parametrize("encoding, pixels", [
    ("rgb8", RGB8), ("bgr8", RGB8[..., ::-1]), ("rgba8", np.dstack([RGB8, RGB8[..., 0]])),
    ("bgra8", np.dstack([RGB8[..., ::-1], RGB8[..., 0]])), ("8UC3", RGB8[..., ::-1]),
    ("rgb16", RGB16), ("bgr16", RGB16[..., ::-1])])
def test_colour_encodings_give_the_same_frame(encoding, pixels):
    rgb = RGB8 if "8" in encoding else RGB16
    ok, png = cv2.imencode(".png", rgb[..., ::-1])                                # the same picture as a PNG file
    reference, _, _ = decode_image(png.tobytes(), "png", source="t")
    for pad, big in ((0, False), (5, False), (3, True)):
        msg = image(pixels, encoding, pad=pad, big=big)
        frame = rm.image_to_frame(msg, rm.IMAGE, PROFILE, source="t")
        assert isinstance(frame, CameraFrame)
        np.testing.assert_array_equal(frame.linear_rgb, reference)
        assert (frame.alpha is not None) == encoding.endswith("a8")
        back = rm.frame_to_image(msg, rm.IMAGE, frame, source="t")                 # unchanged frame: same pixels
        assert back.encoding == encoding and back.is_bigendian == big and back.header == msg.header
        np.testing.assert_array_equal(rm.image_pixels(back, source="t"), pixels)


@pytest.mark.parametrize("encoding, dtype", [("mono8", np.uint8), ("8UC1", np.uint8), ("mono16", np.uint16),
                                             ("16UC1", np.uint16)])
def test_grey_encodings_are_like_a_grey_png(encoding, dtype):
    grey = RGB16[..., 1] if dtype == np.uint16 else RGB8[..., 1]
    msg = image(grey, encoding)
    frame = rm.image_to_frame(msg, rm.IMAGE, PROFILE, source="t")
    ok, png = cv2.imencode(".png", grey)
    linear, encoding_png, _ = decode_image(png.tobytes(), "png", source="t")
    np.testing.assert_array_equal(frame.linear_rgb, linear)
    assert frame.encoding == encoding_png
    np.testing.assert_array_equal(rm.image_pixels(rm.frame_to_image(msg, rm.IMAGE, frame, source="t"),
                                                  source="t"), grey)


def test_untagged_transfer_linear_reads_image_codes_as_linear():
    """inputs.untagged_transfer reaches bag images: a mono16 machine-vision Image (or a PNG CompressedImage without
    colour chunks) read as linear counts (code / 65 535), written back to the same codes."""
    grey = RGB16[..., 1]
    msg = image(grey, "mono16")
    frame = rm.image_to_frame(msg, rm.IMAGE, PROFILE, source="t", untagged_transfer="linear")
    np.testing.assert_allclose(frame.linear_rgb[..., 0], grey / 65535.0, rtol=1e-6)
    assert frame.encoding.transfer == "linear"
    srgb = rm.image_to_frame(msg, rm.IMAGE, PROFILE, source="t")
    assert srgb.encoding.transfer == "srgb" and not np.allclose(srgb.linear_rgb, frame.linear_rgb)
    np.testing.assert_array_equal(rm.image_pixels(rm.frame_to_image(msg, rm.IMAGE, frame, source="t"),
                                                  source="t"), grey)
    ok, png = cv2.imencode(".png", grey)
    compressed = T["sensor_msgs/msg/CompressedImage"](header=header(), format="png", data=png.ravel())
    packed = rm.image_to_frame(compressed, rm.COMPRESSED_IMAGE, PROFILE, source="t", untagged_transfer="linear")
    np.testing.assert_array_equal(packed.linear_rgb, frame.linear_rgb)


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_bayer_is_a_raw_frame(bits, pattern):
    dn = RGB16[..., 0] if bits == 16 else RGB8[..., 0]
    msg = image(dn, f"bayer_{pattern.lower()}{bits}", pad=2)
    frame = rm.image_to_frame(msg, rm.IMAGE, PROFILE, source="t")
    assert isinstance(frame, RawFrame) and frame.cfa_pattern == pattern
    assert (frame.black_level_dn, frame.white_level_dn) == (0.0, 2.0 ** bits - 1)
    np.testing.assert_array_equal(frame.dn, dn.astype(np.float32))
    levels = rm.image_to_frame(msg, rm.IMAGE, PROFILE, source="t", black_level_dn=64, white_level_dn=200)
    assert (levels.black_level_dn, levels.white_level_dn) == (64.0, 200.0)
    brighter = dataclasses.replace(frame, dn=frame.dn * 4.0)                       # clipped to the sample type
    out = rm.image_pixels(rm.frame_to_image(msg, rm.IMAGE, brighter, source="t"), source="t")
    np.testing.assert_array_equal(out, np.minimum(dn.astype(np.int64) * 4, 2 ** bits - 1))


@pytest.mark.parametrize("fmt, ext", [("png", ".png"), ("bgr8; jpeg compressed bgr8", ".jpg"), ("jpeg", ".jpg")])
def test_compressed_image_keeps_its_format(fmt, ext):
    ok, buf = cv2.imencode(ext, RGB8[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 80] if ext == ".jpg" else [])
    msg = T["sensor_msgs/msg/CompressedImage"](header=header(), format=fmt, data=buf.ravel())
    frame = rm.image_to_frame(msg, rm.COMPRESSED_IMAGE, PROFILE, source="t")
    assert frame.encoding.fmt == ("png" if ext == ".png" else "jpeg")
    if ext == ".jpg":
        assert frame.encoding.jpeg_quality == 80
    back = rm.frame_to_image(msg, rm.COMPRESSED_IMAGE, frame, source="t")
    assert back.format == fmt and back.header == msg.header
    if ext == ".png":
        np.testing.assert_array_equal(cv2.imdecode(np.asarray(back.data), cv2.IMREAD_UNCHANGED),
                                      RGB8[..., ::-1])                              # lossless: same pixels


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_compressed_image_keeps_its_icc_profile_and_alpha(ext):
    icc = bytes(range(256)) * 3                                            # opaque to us: copied unchanged
    pixels = np.dstack([RGB8[..., ::-1], RGB8[..., 0]]) if ext == ".png" else RGB8[..., ::-1]
    ok, buf = cv2.imencode(ext, pixels)
    data = embed_icc_profile(buf.tobytes(), "png" if ext == ".png" else "jpeg", icc)
    msg = T["sensor_msgs/msg/CompressedImage"](header=header(), format=ext[1:], data=np.frombuffer(data, np.uint8))
    frame = rm.image_to_frame(msg, rm.COMPRESSED_IMAGE, PROFILE, source="t")
    assert frame.encoding.icc_profile == icc and (frame.alpha is not None) == (ext == ".png")
    back = bytes(rm.frame_to_image(msg, rm.COMPRESSED_IMAGE, frame, source="t").data)
    assert icc_profile(back, frame.encoding.fmt) == icc
    if ext == ".png":                                                       # lossless: the same pixels, alpha too
        np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(back, np.uint8), cv2.IMREAD_UNCHANGED), pixels)


def test_unsupported_images_name_the_message():
    with pytest.raises(InputError, match=r"^bag: /cam@3: Image encoding 'yuv422' is not supported"):
        rm.image_to_frame(image(RGB8[..., :2], "yuv422"), rm.IMAGE, PROFILE, source="bag: /cam@3")
    depth = T["sensor_msgs/msg/CompressedImage"](header=header(), format="16UC1; compressedDepth png",
                                                 data=np.zeros(4, np.uint8))
    with pytest.raises(InputError, match="compressed depth image"):
        rm.image_to_frame(depth, rm.COMPRESSED_IMAGE, PROFILE, source="t")
    short = image(RGB8, "rgb8")
    short = dataclasses.replace(short, data=short.data[:100])
    with pytest.raises(InputError, match="needs 3600 bytes, the message has 100"):
        rm.image_to_frame(short, rm.IMAGE, PROFILE, source="t")


def test_depth_images_rep118():
    """No measurement (0, NaN, −inf: too close) is a hole (NaN); +inf (nothing within range) stays."""
    z = np.array([[1.5, 0.0, np.nan], [-np.inf, np.inf, 20.0]], np.float32)
    np.testing.assert_array_equal(rm.depth_image_m(image(z, "32FC1"), rm.IMAGE, source="t"),
                                  [[1.5, np.nan, np.nan], [np.nan, np.inf, 20.0]])
    mm = np.array([[1500, 0], [65535, 20]], np.uint16)
    np.testing.assert_allclose(rm.depth_image_m(image(mm, "16UC1", big=True), rm.IMAGE, source="t"),
                               [[1.5, np.nan], [65.535, 0.02]], rtol=1e-6)
    with pytest.raises(InputError, match="not supported here"):
        rm.depth_image_m(image(RGB8, "rgb8"), rm.IMAGE, source="t")


# --- PointCloud2 -----------------------------------------------------------------------------------------------------

FIELDS = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 16, 7, 1), ("t", 20, 6, 1),
          ("ring", 24, 4, 1), ("normal", 28, 7, 3)]        # 4 padding bytes after z, a COUNT-3 field, step 48


def cloud2(n: int, *, big: bool = False, grid: tuple[int, int] | None = None, row_pad: int = 0):
    order = ">" if big else "<"
    record = np.dtype({"names": [f[0] for f in FIELDS], "offsets": [f[1] for f in FIELDS],
                       "formats": [np.dtype((order + rm.POINTFIELD_TYPES[f[2]], (f[3],))) if f[3] > 1
                                   else order + rm.POINTFIELD_TYPES[f[2]] for f in FIELDS], "itemsize": 48})
    points = np.zeros(n, record)
    for name in ("x", "y", "z"):
        points[name] = RNG.uniform(-20, 20, n)
    points["intensity"] = RNG.uniform(0, 500, n)
    points["t"] = np.arange(n) * 1000
    points["ring"] = np.arange(n) % 128
    points["normal"] = RNG.normal(size=(n, 3))
    h, w = grid or (1, n)
    rows = points.view(np.uint8).reshape(h, w * 48)
    data = np.concatenate([rows, np.zeros((h, row_pad), np.uint8)], axis=1).ravel()
    pf = T["sensor_msgs/msg/PointField"]
    return T["sensor_msgs/msg/PointCloud2"](
        header=header(), height=h, width=w, fields=[pf(name=a, offset=b, datatype=c, count=d) for a, b, c, d in FIELDS],
        is_bigendian=big, point_step=48, row_step=w * 48 + row_pad, data=data, is_dense=True), points


@pytest.mark.parametrize("big", [False, True])
def test_pointcloud2_fields_and_identity(big):
    msg, points = cloud2(50, big=big)
    cloud = rm.cloud_to_pointcloud(msg, sensor="lidar", profile=None, field_map=None, source="t")
    assert [k for k, _, _ in cloud.layout.fields] == ["x", "y", "z", "intensity", "t", "ring", "normal"]
    assert [d for _, _, d in cloud.layout.fields] == ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "(3,)<f4"]
    np.testing.assert_array_equal(cloud.positions_m[:, 0], points["x"].astype(np.float64))
    np.testing.assert_array_equal(cloud.fields["normal"], points["normal"])
    assert cloud.fields["ring"].dtype == np.uint16 and cloud.grid_shape is None
    back = rm.pointcloud_to_cloud2(msg, cloud, effect="auto", source="t")
    assert bytes(back.data) == bytes(msg.data) and back.point_step == 48 and back.fields == msg.fields


def test_pointcloud2_effect_appended_and_points_dropped():
    msg, _ = cloud2(50)
    cloud = rm.cloud_to_pointcloud(msg, sensor="lidar", profile=None, field_map=None, source="t")
    marked = dataclasses.replace(cloud, effect=np.full(50, ATTENUATED)).select(np.arange(50) % 2 == 0)
    out = rm.pointcloud_to_cloud2(msg, marked, effect="auto", source="t")
    assert (out.height, out.width, out.point_step, out.row_step) == (1, 25, 49, 25 * 49)
    assert (out.fields[-1].name, out.fields[-1].offset, out.fields[-1].datatype) == ("rv_effect", 48, 2)
    columns = rm.cloud_columns(out, source="t")
    np.testing.assert_array_equal(columns[-1][2], np.full(25, ATTENUATED))
    np.testing.assert_array_equal(columns[3][2], cloud.fields["intensity"][::2])
    none = rm.pointcloud_to_cloud2(msg, marked, effect="none", source="t")
    assert none.point_step == 48 and len(none.fields) == len(msg.fields)
    again = rm.cloud_to_pointcloud(out, sensor="lidar", profile=None, field_map=None, source="t")   # a second run
    twice = rm.pointcloud_to_cloud2(out, dataclasses.replace(again, effect=np.full(25, ATTENUATED)), effect="auto",
                                    source="t")
    assert [(f.name, f.offset) for f in twice.fields[-2:]] == [("rv_effect", 48), ("rv_effect_2", 49)]


def test_organised_cloud_is_a_grid_and_keeps_its_shape():
    msg, points = cloud2(4 * 6, grid=(4, 6), row_pad=8)
    cloud = rm.cloud_to_pointcloud(msg, sensor="lidar", profile=None, field_map=None, source="t")
    assert cloud.grid_shape == (4, 6)
    np.testing.assert_array_equal(cloud.fields["t"], points["t"])                 # row padding skipped
    dropped = cloud.drop(np.arange(24) < 5)
    out = rm.pointcloud_to_cloud2(msg, dropped, effect="auto", source="t")
    assert (out.height, out.width, out.row_step) == (4, 6, 6 * 49)
    columns = rm.cloud_columns(out, source="t")
    assert not columns[0][2][:5].any() and (columns[-1][2][:5] == REMOVED).all() and not columns[-1][2][5:].any()


def test_bad_pointclouds_name_the_message():
    msg, _ = cloud2(5)
    no_x = dataclasses.replace(msg, fields=msg.fields[1:])
    with pytest.raises(InputError, match=r"^bag: /p@3: no scalar 'x' field"):
        rm.cloud_to_pointcloud(no_x, sensor="lidar", profile=None, field_map=None, source="bag: /p@3")
    short = dataclasses.replace(msg, data=msg.data[:100])
    with pytest.raises(InputError, match="needs 240 bytes, the message has 100"):
        rm.cloud_columns(short, source="t")
    pf = T["sensor_msgs/msg/PointField"]
    odd = dataclasses.replace(msg, fields=[pf(name="x", offset=0, datatype=9, count=1)])
    with pytest.raises(InputError, match="unknown datatype 9"):
        rm.cloud_columns(odd, source="t")
    beyond = dataclasses.replace(msg, fields=[*msg.fields, pf(name="w", offset=46, datatype=7, count=1)])
    with pytest.raises(InputError, match="beyond point_step 48"):
        rm.cloud_columns(beyond, source="t")


@pytest.mark.parametrize("ext,fmt", [(".jpg", ""), (".png", "jpeg"), (".jpg", "rgb8; png compressed rgb8")])
def test_compressed_image_codec_from_its_bytes(ext, fmt):
    """A publisher that leaves ``format`` empty or names another codec than it wrote (a PNG labelled ``jpeg``):
    the message failed ("neither JPEG nor PNG", "not a JPEG file"); the data's signature decides now, and the
    image is written back in the codec it came in, ``format`` unchanged."""
    ok, buf = cv2.imencode(ext, RGB8[..., ::-1])
    msg = T["sensor_msgs/msg/CompressedImage"](header=header(), format=fmt, data=buf.ravel())
    frame = rm.image_to_frame(msg, rm.COMPRESSED_IMAGE, PROFILE, source="t")
    assert frame.encoding.fmt == ("jpeg" if ext == ".jpg" else "png")
    back = rm.frame_to_image(msg, rm.COMPRESSED_IMAGE, frame, source="t")
    assert back.format == fmt and bytes(back.data[:2]) == buf.tobytes()[:2]
