"""Camera photos keep their EXIF (orientation), JPEG chroma subsampling and progressive mode through a write-back,
as real dataset photos (nuScenes/Waymo JPEGs, phone pictures with an orientation tag) come."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from roadview_noise.io.image import read_image, write_image


def _photo(w=96, h=64) -> Image.Image:
    y, x = np.mgrid[0:h, 0:w]
    rgb = np.stack([x * 255 // w, y * 255 // h, (x + y) * 255 // (w + h)], axis=2).astype(np.uint8)
    return Image.fromarray(rgb)


def _roundtrip(src, dst):
    linear, enc, alpha = read_image(src)
    write_image(dst, linear * np.float32(0.8), enc, alpha)        # a photometric model changed the pixels
    return linear, enc


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_exif_orientation_and_tags_are_kept_and_pixels_not_rotated(tmp_path, suffix):
    exif = Image.Exif()
    exif[0x0112] = 6                                   # orientation: rotate 90° CW to display
    exif[0x010F] = "RoadCam"                           # make
    src, dst = tmp_path / f"in{suffix}", tmp_path / f"out{suffix}"
    _photo().save(src, exif=exif.tobytes(), **({"quality": 90} if suffix == ".jpg" else {}))
    linear, enc = _roundtrip(src, dst)
    assert linear.shape[:2] == (64, 96)                # stored grid, not the displayed one
    assert enc.exif is not None
    out = Image.open(dst)
    assert out.size == (96, 64)
    tags = dict(out.getexif())
    assert tags.get(0x0112) == 6 and tags.get(0x010F) == "RoadCam"


def test_no_exif_adds_none(tmp_path):
    src, dst = tmp_path / "in.jpg", tmp_path / "out.jpg"
    _photo().save(src, quality=90)
    _, enc = _roundtrip(src, dst)
    assert enc.exif is None and dict(Image.open(dst).getexif()) == {}


@pytest.mark.parametrize("subsampling,layer", [(0, (1, 1, 1)), (1, (2, 1, 1)), (2, (2, 2, 1))])
@pytest.mark.parametrize("progressive", [False, True])
def test_jpeg_chroma_subsampling_and_progressive_are_kept(tmp_path, subsampling, layer, progressive):
    src, dst = tmp_path / "in.jpg", tmp_path / "out.jpg"
    _photo().save(src, quality=95, subsampling=subsampling, progressive=progressive)
    assert Image.open(src).layer[0][1:3] == layer[:2]
    _roundtrip(src, dst)
    out = Image.open(dst)
    assert out.layer[0][1:3] == layer[:2]               # luma H, V sampling; chroma stays 1 × 1
    assert [c[1:3] for c in out.layer[1:]] == [(1, 1), (1, 1)]
    assert bool(out.info.get("progressive")) == progressive


def test_grey_and_cmyk_jpeg(tmp_path):
    """Grey stays one channel; CMYK is decoded to RGB (OpenCV) and written as an RGB JPEG."""
    photo = _photo()
    photo.convert("L").save(tmp_path / "g.jpg", quality=90)
    photo.convert("CMYK").save(tmp_path / "c.jpg", quality=90)
    _roundtrip(tmp_path / "g.jpg", tmp_path / "g_out.jpg")
    assert Image.open(tmp_path / "g_out.jpg").mode == "L"
    linear, enc = _roundtrip(tmp_path / "c.jpg", tmp_path / "c_out.jpg")
    assert enc.channels == 3 and Image.open(tmp_path / "c_out.jpg").mode == "RGB"
    ref = np.asarray(Image.open(tmp_path / "c.jpg").convert("RGB"), dtype=float)
    got = np.asarray(Image.open(tmp_path / "c_out.jpg").convert("RGB"), dtype=float) / 0.8 ** (1 / 2.2)
    assert np.abs(got - ref)[ref < 200].mean() < 6     # colours, not inverted CMYK
