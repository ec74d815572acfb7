"""HEIF/HEIC and AVIF photos (roadview_noise/io/heif.py), on tiny files pillow-heif and Pillow write here: read as
stored with the EXIF orientation their transforms state (as JPEG), written back in the same format with the ICC
profile and EXIF as read; a run records the quality written; without the extra, the refusal names it."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

pillow_heif = pytest.importorskip("pillow_heif")
from PIL import Image, ImageCms, features  # noqa: E402

from roadview_noise.errors import InputError, RecipeError  # noqa: E402
from roadview_noise.io import heif  # noqa: E402
from roadview_noise.io.image import read_image, write_image  # noqa: E402
from roadview_noise.io.image_metadata import orientation  # noqa: E402
from roadview_noise.recipe import parse_recipe  # noqa: E402
from roadview_noise.runner import run  # noqa: E402

pillow_heif.register_heif_opener()
FORMATS = [("heic", "HEIF"), pytest.param("avif", "AVIF", marks=pytest.mark.skipif(
    not features.check("avif"), reason="this Pillow has no AVIF support"))]
H, W = 48, 64
SRGB_ICC = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()


def _photo(channels: int = 3) -> np.ndarray:
    """A smooth 8-bit picture with a white block at the top left of the stored pixels (where a turn moves it)."""
    v, u = np.mgrid[0:H, 0:W]
    rgb = np.stack([u * 3, v * 4, (u + v) * 2], axis=-1).astype(np.uint8)
    rgb[:8, :16] = 255
    if channels == 4:
        return np.dstack([rgb, np.where(u < W // 2, 255, 90).astype(np.uint8)])
    return rgb


def _file(fmt: str, pixels: np.ndarray, turn: int = 1) -> bytes:
    exif = Image.Exif()
    exif[271], exif[274] = "rvnoise test", turn
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format=fmt, quality=95, exif=exif.tobytes(), icc_profile=SRGB_ICC)
    return buf.getvalue()


@pytest.mark.parametrize("suffix,fmt", FORMATS)
@pytest.mark.parametrize("channels", [3, 4])
def test_round_trip_keeps_format_pixels_alpha_icc_and_exif(tmp_path, suffix, fmt, channels):
    path = tmp_path / f"a.{suffix}"
    path.write_bytes(_file(fmt, _photo(channels)))
    linear, encoding, alpha = read_image(path)
    assert linear.shape == (H, W, 3) and encoding.fmt == heif.FORMATS[f".{suffix}"]
    assert encoding.channels == channels and (alpha is None) == (channels == 3)
    assert encoding.icc_profile == SRGB_ICC and b"rvnoise test" in encoding.exif
    out = tmp_path / f"out.{suffix}"
    write_image(out, linear, encoding, alpha)
    data = out.read_bytes()
    assert data[4:8] == b"ftyp"
    with Image.open(io.BytesIO(data)) as im:
        assert im.format == fmt and im.size == (W, H) and im.info["icc_profile"] == SRGB_ICC
    again, encoding2, alpha2 = read_image(out)
    assert encoding2.exif == encoding.exif and encoding2.channels == channels
    codes = lambda x: np.round(np.clip(x, 0, 1) ** (1 / 2.2) * 255)      # noqa: E731  close enough to sRGB here
    assert np.abs(codes(again) - codes(linear)).mean() < 3                 # lossy at heif.QUALITY
    if channels == 4:
        assert np.abs(alpha2.astype(int) - alpha.astype(int)).max() <= 3


@pytest.mark.parametrize("suffix,fmt", FORMATS)
def test_a_turned_photo_is_read_as_stored_with_its_orientation_like_a_jpeg(tmp_path, suffix, fmt):
    """pillow-heif turns a HEIF by its irot/imir and sets the EXIF tag to 1; Pillow's AVIF plugin keeps the stored
    pixels with the tag. Both are read as stored with orientation 6 and written so: a viewer shows the output
    turned like the input."""
    path = tmp_path / f"a.{suffix}"
    path.write_bytes(_file(fmt, _photo(), turn=6))
    linear, encoding, _ = read_image(path)
    assert orientation(encoding) == 6 and linear.shape == (H, W, 3)
    assert linear[:8, :16].min() > 0.9 and linear[-8:, -16:].max() < 0.9   # the white block where it was stored
    out = tmp_path / f"out.{suffix}"
    write_image(out, linear, encoding)
    with Image.open(path) as a, Image.open(out) as b:
        assert a.size == b.size                                            # displayed alike (turned or not)
    assert orientation(read_image(out)[1]) == 6


@pytest.mark.parametrize("suffix,fmt", FORMATS)
def test_a_run_processes_it_upright_and_records_the_quality_written(tmp_path, suffix, fmt):
    src = tmp_path / "in/phone"
    src.mkdir(parents=True)
    (src / f"IMG_0001.{suffix}").write_bytes(_file(fmt, _photo(), turn=6))
    recipe = parse_recipe({"chain": [{"model": "rain.camera"}], "seed": 3,
                           "inputs": {"camera": f"**/*.{suffix}", "depth_source": "ground_plane"}})
    summary = run(recipe, tmp_path / "in", tmp_path / "out", progress=False, echo=lambda *_: None, workers=1)
    assert summary.failed == 0 and summary.done == 1
    entry = json.loads((tmp_path / "out/manifest.jsonl").read_text().splitlines()[0])
    assert entry["inputs"]["orientation"] == {"exif": 6, "processed": "upright"}
    assert entry["inputs"]["heif_quality"]["value"] == heif.QUALITY
    with Image.open(tmp_path / f"out/phone/IMG_0001.{suffix}") as im:
        assert im.format == fmt


def test_without_the_extra_the_refusal_names_it(tmp_path, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "pillow_heif", None)      # import pillow_heif fails
    heif._image_module.cache_clear()
    try:
        path = tmp_path / "a.heic"
        path.write_bytes(_file("HEIF", _photo()))
        with pytest.raises(InputError, match=r"optional extra heif: pip install 'roadview_noise\[heif\]'"):
            read_image(path)
        with pytest.raises(RecipeError, match=r"roadview_noise\[heif\]"):
            parse_recipe({"chain": [{"model": "compression.camera"}], "inputs": {"camera": "phone/**/*.HEIC"}})
    finally:
        heif._image_module.cache_clear()


def test_not_a_heif_file_is_refused_by_name(tmp_path):
    path = tmp_path / "a.heic"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(40))
    with pytest.raises(InputError, match="not a HEIF file"):
        read_image(path)
    path.write_bytes(_file("HEIF", _photo())[:300])
    with pytest.raises(InputError, match="cannot decode this HEIF file"):
        read_image(path)


def test_a_16_bit_grey_heif_is_refused_not_clipped(tmp_path):
    """pillow-heif reads a 16-bit grey HEIF as mode I;16, which Pillow's convert would clip to 255: refused."""
    buf = io.BytesIO()
    Image.fromarray((np.arange(64 * 64, dtype=np.uint16).reshape(64, 64) * 16)).save(buf, format="HEIF", quality=-1)
    path = tmp_path / "grey16.heic"
    path.write_bytes(buf.getvalue())
    with pytest.raises(InputError, match="mode I;16: rvnoise reads 8-bit"):
        read_image(path)
