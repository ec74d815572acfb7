"""Image reader/writer: exact 8/16-bit round trips, RGB order, sRGB oracle, JPEG quality, truncated files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

from roadview_noise.errors import InputError
from roadview_noise.io.image import read_image, write_image
from roadview_noise.types import ImageEncoding


def _roundtrip(tmp_path, name, pixels_bgr):
    src, dst = tmp_path / name, tmp_path / ("out_" + name)
    assert cv2.imwrite(str(src), pixels_bgr)
    linear, enc, alpha = read_image(src)
    write_image(dst, linear, enc, alpha)
    return linear, enc, alpha, cv2.imread(str(dst), cv2.IMREAD_UNCHANGED)


def test_png8_every_code_roundtrips_exactly(tmp_path):
    rng = np.random.default_rng(1)
    bgr = np.stack([rng.permutation(256) for _ in range(3)], axis=-1).astype(np.uint8).reshape(16, 16, 3)
    linear, enc, alpha, back = _roundtrip(tmp_path, "a.png", bgr)
    assert enc == ImageEncoding(fmt="png", bit_depth=8, transfer="srgb", channels=3)
    assert alpha is None and linear.dtype == np.float32 and linear.shape == (16, 16, 3)
    np.testing.assert_array_equal(back, bgr)


def test_png16_random_roundtrips_exactly(tmp_path):
    bgr = np.random.default_rng(2).integers(0, 65536, (33, 47, 3), dtype=np.uint16)
    bgr[0, :3] = [[0, 0, 0], [65535, 65535, 65535], [1, 2, 3]]
    _, enc, _, back = _roundtrip(tmp_path, "b.png", bgr)
    assert enc.bit_depth == 16 and enc.transfer == "srgb"
    np.testing.assert_array_equal(back, bgr)


def test_rgb_order_and_srgb_oracle(tmp_path):
    bgr = np.zeros((1, 3, 3), np.uint8)
    bgr[0, 0] = (0, 0, 255)          # pure red in OpenCV's BGR order
    bgr[0, 1] = (128, 128, 128)
    bgr[0, 2] = (10, 10, 10)         # on the linear segment of the sRGB curve
    cv2.imwrite(str(tmp_path / "c.png"), bgr)
    linear, _, _ = read_image(tmp_path / "c.png")
    np.testing.assert_array_equal(linear[0, 0], [1.0, 0.0, 0.0])
    # IEC 61966-2-1: ((V + 0.055) / 1.055) ** 2.4 above 0.04045, V / 12.92 below
    np.testing.assert_allclose(linear[0, 1], ((128 / 255 + 0.055) / 1.055) ** 2.4, rtol=1e-6)
    np.testing.assert_allclose(linear[0, 2], 10 / 255 / 12.92, rtol=1e-6)


def test_grey_and_alpha(tmp_path):
    rng = np.random.default_rng(3)
    grey = rng.integers(0, 256, (9, 11), dtype=np.uint8)
    linear, enc, alpha, back = _roundtrip(tmp_path, "g.png", grey)
    assert enc.channels == 1 and alpha is None
    assert np.array_equal(linear[..., 0], linear[..., 2])
    np.testing.assert_array_equal(back, grey)

    bgra = rng.integers(0, 65536, (9, 11, 4), dtype=np.uint16)
    _, enc, alpha, back = _roundtrip(tmp_path, "rgba.png", bgra)
    assert enc.channels == 4 and enc.bit_depth == 16
    np.testing.assert_array_equal(alpha, bgra[..., 3])
    np.testing.assert_array_equal(back, bgra)


def test_tiff_16bit_and_float(tmp_path):
    rng = np.random.default_rng(4)
    u16 = rng.integers(0, 65536, (12, 10, 3), dtype=np.uint16)
    _, enc, _, back = _roundtrip(tmp_path, "t.tiff", u16)
    assert (enc.fmt, enc.bit_depth, enc.transfer) == ("tiff", 16, "srgb")
    np.testing.assert_array_equal(back, u16)

    f32 = (rng.random((12, 10, 3)) * 3).astype(np.float32)      # linear HDR values above 1 stay
    linear, enc, _, back = _roundtrip(tmp_path, "f.tif", f32)
    assert (enc.bit_depth, enc.transfer) == (32, "linear")
    np.testing.assert_array_equal(linear, f32[..., ::-1])
    np.testing.assert_array_equal(back, f32)


@pytest.mark.parametrize("quality", [40, 75, 92])
def test_jpeg_quality_is_recovered_and_kept(tmp_path, quality):
    y, x = np.mgrid[0:64, 0:96]
    bgr = np.stack([x * 2, y * 3, (x + y) % 256], axis=-1).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "j.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    linear, enc, _ = read_image(tmp_path / "j.jpg")
    assert enc.fmt == "jpeg" and enc.jpeg_quality == quality
    write_image(tmp_path / "out.jpg", linear, enc)
    assert read_image(tmp_path / "out.jpg")[1].jpeg_quality == quality
    first, second = cv2.imread(str(tmp_path / "j.jpg")), cv2.imread(str(tmp_path / "out.jpg"))
    assert np.abs(first.astype(int) - second).mean() < 2.0


def test_clip_and_round_once(tmp_path):
    linear = np.array([[[-0.5, 0.5, 7.0]]], np.float32)
    write_image(tmp_path / "o.png", linear, ImageEncoding())
    code = cv2.imread(str(tmp_path / "o.png"), cv2.IMREAD_UNCHANGED)[0, 0, ::-1]
    expected = round(255 * (1.055 * 0.5 ** (1 / 2.4) - 0.055))
    np.testing.assert_array_equal(code, [0, expected, 255])
    assert [p.name for p in tmp_path.iterdir()] == ["o.png"]        # no temporary left behind


def test_writer_refuses_nan_and_wrong_suffix(tmp_path):
    with pytest.raises(ValueError, match="NaN"):
        write_image(tmp_path / "n.png", np.full((2, 2, 3), np.nan, np.float32), ImageEncoding())
    with pytest.raises(ValueError, match="suffix"):
        write_image(tmp_path / "n.jpg", np.zeros((2, 2, 3), np.float32), ImageEncoding(fmt="png"))


def _cut(path, n_bytes):
    data = path.read_bytes()
    path.write_bytes(data[:n_bytes] if n_bytes >= 0 else data[:len(data) + n_bytes])


@pytest.mark.parametrize("name,cut,match", [
    ("cut.png", -12, "IEND"),
    ("cut.png", 200, "IEND"),
    ("cut.jpg", -2, "FF D9"),
    ("cut.jpg", 700, "FF D9"),
    ("cut.tiff", -40, "TIFF"),
    ("cut.tiff", 12, "TIFF"),
])
def test_truncated_files_raise(tmp_path, name, cut, match):
    path = tmp_path / name
    bgr = np.random.default_rng(5).integers(0, 256, (40, 40, 3), dtype=np.uint8)
    cv2.imwrite(str(path), bgr)
    _cut(path, cut)
    with pytest.raises(InputError, match=match) as err:
        read_image(path)
    assert name in str(err.value)


def test_truncated_tiff_with_leading_directory(tmp_path):
    """A TIFF whose directory precedes the pixel data (tifffile layout) still decodes after a cut; must raise."""
    import tifffile
    path = tmp_path / "lead.tif"
    tifffile.imwrite(path, np.random.default_rng(6).integers(0, 65536, (64, 64, 3), dtype=np.uint16),
                     photometric="rgb")
    _cut(path, -1000)
    with pytest.raises(InputError, match="truncated TIFF") as err:
        read_image(path)
    assert "lead.tif" in str(err.value)


def test_bad_inputs_raise(tmp_path):
    (tmp_path / "junk.png").write_bytes(b"not an image at all")
    (tmp_path / "img.bmp").write_bytes(b"BM")
    for name, match in [("junk.png", "not a PNG"), ("img.bmp", "unknown image suffix"), ("missing.png", "cannot read")]:
        with pytest.raises(InputError, match=match) as err:
            read_image(tmp_path / name)
        assert name in str(err.value)


# --- colour profiles and HDR -----------------------------------------------------------------------------------------


def _icc() -> bytes:
    """A real sRGB ICC profile (Pillow's littleCMS), 500+ bytes."""
    ImageCms = pytest.importorskip("PIL.ImageCms")
    return ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()


@pytest.mark.parametrize("name,dtype,channels", [("a.png", np.uint8, 3), ("b.png", np.uint16, 4),
                                                 ("c.jpg", np.uint8, 3), ("d.tiff", np.uint16, 4),
                                                 ("e.tif", np.uint8, 1)])
def test_icc_profile_bit_depth_and_alpha_are_kept(tmp_path, name, dtype, channels):
    """An ICC profile embedded by Pillow/tifffile is read, written back unchanged next to the same bit depth and
    alpha, and Pillow (an independent reader) finds it in our output."""
    from PIL import Image

    icc = _icc()
    rng = np.random.default_rng(5)
    full = np.iinfo(dtype).max
    codes = rng.integers(0, full + 1, (20, 30, channels) if channels > 1 else (20, 30), dtype=dtype)
    src = tmp_path / name
    if src.suffix == ".png" or src.suffix == ".jpg":
        ok, buf = cv2.imencode(src.suffix, codes, [cv2.IMWRITE_JPEG_QUALITY, 93] if src.suffix == ".jpg" else [])
        from roadview_noise.io.image import embed_icc_profile
        src.write_bytes(embed_icc_profile(buf.tobytes(), "jpeg" if src.suffix == ".jpg" else "png", icc))
    else:
        rgb = codes if channels == 1 else np.dstack([codes[..., 2::-1], codes[..., 3:]])
        tifffile.imwrite(src, rgb, photometric="rgb" if channels > 1 else "minisblack", iccprofile=icc,
                         extrasamples=("unassalpha",) if channels == 4 else None)
    assert Image.open(src).info.get("icc_profile") == icc                        # the input is valid
    linear, enc, alpha = read_image(src)
    assert enc.icc_profile == icc and enc.channels == channels and enc.bit_depth == 8 * np.dtype(dtype).itemsize
    out = tmp_path / f"out{src.suffix}"
    write_image(out, linear, enc, alpha=alpha)
    assert Image.open(out).info.get("icc_profile") == icc
    back = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert back.dtype == dtype and back.shape == codes.shape
    if src.suffix != ".jpg":
        np.testing.assert_array_equal(back, codes)
    else:
        assert read_image(out)[1].jpeg_quality == 93


def test_without_icc_nothing_is_added(tmp_path):
    cv2.imwrite(str(tmp_path / "p.png"), np.zeros((4, 4, 3), np.uint8))
    linear, enc, _ = read_image(tmp_path / "p.png")
    assert enc.icc_profile is None
    write_image(tmp_path / "o.png", linear, enc)
    assert b"iCCP" not in (tmp_path / "o.png").read_bytes()


@pytest.mark.parametrize("half", [True, False])
def test_exr_image_stays_linear_hdr(tmp_path, half):
    """An HDR EXR (values far above 1, half or float, with alpha) comes back linear and unclipped, same channel
    type; a grey (Y) EXR stays grey."""
    import OpenEXR

    dtype = np.float16 if half else np.float32
    rng = np.random.default_rng(6)
    rgba = (rng.random((16, 24, 4)) * [40.0, 3.0, 0.5, 1.0]).astype(dtype)
    def header():                                    # OpenEXR adds the data window to the mapping it is given
        return {"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage}

    with OpenEXR.File(header(), {c: rgba[..., k].copy() for k, c in enumerate("RGBA")}) as exr:
        exr.write(str(tmp_path / "hdr.exr"))
    linear, enc, alpha = read_image(tmp_path / "hdr.exr")
    assert (enc.fmt, enc.transfer, enc.bit_depth, enc.channels) == ("exr", "linear", 16 if half else 32, 4)
    np.testing.assert_array_equal(linear, rgba[..., :3].astype(np.float32))
    assert linear.max() > 30
    write_image(tmp_path / "out.exr", linear * 2, enc, alpha=alpha)
    with OpenEXR.File(str(tmp_path / "out.exr"), separate_channels=True) as exr:
        ch = exr.channels()
        assert {k: v.pixels.dtype for k, v in ch.items()} == {c: np.dtype(dtype) for c in "RGBA"}
        np.testing.assert_array_equal(ch["R"].pixels, (rgba[..., 0].astype(np.float32) * 2).astype(dtype))
        np.testing.assert_array_equal(ch["A"].pixels, rgba[..., 3])
    with OpenEXR.File(header(), {"Y": rgba[..., 0].copy()}) as exr:
        exr.write(str(tmp_path / "grey.exr"))
    linear, enc, _ = read_image(tmp_path / "grey.exr")
    assert enc.channels == 1 and np.array_equal(linear[..., 0], linear[..., 2])
    write_image(tmp_path / "grey_out.exr", linear, enc)
    with OpenEXR.File(str(tmp_path / "grey_out.exr"), separate_channels=True) as exr:
        np.testing.assert_allclose(exr.channels()["Y"].pixels, rgba[..., 0], rtol=1e-3)
    with OpenEXR.File(header(), {"Z": np.ones((4, 4), np.float32)}) as exr:
        exr.write(str(tmp_path / "depth.exr"))
    with pytest.raises(InputError, match="R, G, B"):
        read_image(tmp_path / "depth.exr")


@pytest.mark.parametrize("bits", [8, 16])
def test_colour_codes_reach_opencv_in_bgr_order_without_a_swap_copy(bits):
    from roadview_noise.io.image import bgr_order, codes_from_image
    from roadview_noise.physics import srgb

    linear = np.random.default_rng(21).random((9, 11, 3)).astype(np.float32)
    codes = codes_from_image(linear, ImageEncoding(bit_depth=bits))
    np.testing.assert_array_equal(codes, srgb.linear_to_code(linear, bits))          # RGB order for every reader
    stored = bgr_order(codes)
    assert stored.flags.c_contiguous and np.shares_memory(stored, codes)                # OpenCV gets the storage
    np.testing.assert_array_equal(stored, codes[..., ::-1])
    rgb = np.ascontiguousarray(codes)                                                  # plain RGB: swapped copy
    assert not np.shares_memory(bgr_order(rgb), rgb)
    np.testing.assert_array_equal(bgr_order(rgb), codes[..., ::-1])
    plain = codes_from_image(linear, ImageEncoding(bit_depth=bits), bgr=False)          # the PNG / TIFF writers'
    assert plain.flags.c_contiguous
    np.testing.assert_array_equal(plain, codes)


@pytest.mark.parametrize("where", [(100, 100, 1), (300, 5, 0), (10, 300, 2)])    # in a block, last row, last column
def test_a_nan_is_refused_from_the_metrics_luminance_blocks_and_the_edges(tmp_path, where):
    """With the metrics collecting, the writer finds NaN in the luminance blocks its encode kept (301 × 301: 2 × 2
    blocks, one row and one column outside them) instead of reading the frame again."""
    from roadview_noise import luminance

    linear = np.full((301, 301, 3), 0.5, np.float32)
    linear[where] = np.nan
    luminance.collect(True)
    try:
        luminance.want(linear)
        with pytest.raises(ValueError, match="1 NaN"):
            write_image(tmp_path / "x.png", linear, ImageEncoding())
        assert luminance.blocks_of(linear, 2) is not None                  # the check had the blocks to read
    finally:
        luminance.collect(False)
    assert not (tmp_path / "x.png").exists()


def test_a_nan_anywhere_is_refused_by_the_writer(tmp_path):
    linear = np.full((4, 5, 3), 0.5, np.float32)
    linear[3, 4, 2] = np.nan
    with pytest.raises(ValueError, match="1 NaN"):
        write_image(tmp_path / "x.png", linear, ImageEncoding())
    assert not (tmp_path / "x.png").exists()
