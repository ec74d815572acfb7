"""Image reader/writer: exact 8/16-bit round trips, RGB order, sRGB oracle, JPEG quality, truncated files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

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
