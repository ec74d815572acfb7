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


@pytest.mark.parametrize("dpi,mode", [((300, 300), "L"), ((72, 144), "RGB")])
def test_jpeg_jfif_density_is_kept(tmp_path, dpi, mode):
    """A JPEG's JFIF density (the dpi viewers show; hopper.jpg of Pillow's tests: 96 dpi) was written as OpenCV's
    1:1 aspect ratio (no dpi); a file without JFIF gets none added."""
    src, dst = tmp_path / "in.jpg", tmp_path / "out.jpg"
    _photo().convert(mode).save(src, quality=90, dpi=dpi)
    _roundtrip(src, dst)
    assert tuple(round(v) for v in Image.open(dst).info["dpi"]) == dpi
    stripped = tmp_path / "bare.jpg"                  # no APP0 at all: SOI, then the rest of the file
    data = src.read_bytes()
    stripped.write_bytes(data[:2] + data[4 + int.from_bytes(data[4:6], "big"):])
    _roundtrip(stripped, dst)
    assert "dpi" not in Image.open(dst).info or Image.open(dst).info["dpi"] == (1, 1)


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


# --- round 19 (rc35): what real camera files carry besides EXIF ------------------------------------------------------


def test_jpeg_with_data_after_its_end_is_read(tmp_path):
    """Phones append data after the end-of-image marker (Samsung's SEFH trailer, a Motion Photo's MP4): the image
    is whole and was refused as truncated; a file cut inside its scan still is."""
    src = tmp_path / "in.jpg"
    _photo().save(src, quality=90)
    data = src.read_bytes()
    (tmp_path / "trailer.jpg").write_bytes(data + b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 4 + b"SEFT")
    np.testing.assert_array_equal(read_image(tmp_path / "trailer.jpg")[0], read_image(src)[0])
    (tmp_path / "cut.jpg").write_bytes(data[:len(data) // 2] + b"SEFT")
    from roadview_noise.errors import InputError
    with pytest.raises(InputError, match="cut.jpg.*FF D9"):
        read_image(tmp_path / "cut.jpg")


def _segment(marker: int, payload: bytes) -> bytes:
    return bytes([0xFF, marker]) + (len(payload) + 2).to_bytes(2, "big") + payload


def test_jpeg_xmp_iptc_and_comment_segments_are_kept_and_mpf_is_not(tmp_path):
    """A camera JPEG's XMP (APP1, as Pillow's xmp_test.jpg: provenance, ratings, the orientation too), IPTC (APP13
    Photoshop 3.0) and comment (COM) come out byte for byte, in their order, after the EXIF (round 22; before: all
    dropped); an MPF segment (APP2: offsets of the images a phone appends after the end, which are not written) is
    not copied."""
    src, dst = tmp_path / "in.jpg", tmp_path / "out.jpg"
    exif = Image.Exif()
    exif[274] = 1
    _photo().save(src, quality=90, exif=exif.tobytes())
    data = src.read_bytes()
    kept = [_segment(0xE1, b"http://ns.adobe.com/xap/1.0/\x00<x:xmpmeta xmlns:x='adobe:ns:meta/'/>"),
            _segment(0xED, b"Photoshop 3.0\x008BIM\x04\x04\x00\x00\x00\x00\x00\x05\x1c\x02\x00\x00\x02"),
            _segment(0xFE, b"recorded by the test rig")]
    mpf = _segment(0xE2, b"MPF\x00MM\x00*\x00\x00\x00\x08")
    at = data.index(b"\xff\xdb")                                     # before the first quantisation table
    src.write_bytes(data[:at] + kept[0] + mpf + b"".join(kept[1:]) + data[at:])
    _roundtrip(src, dst)
    out = dst.read_bytes()
    positions = [out.find(k) for k in kept]
    assert -1 not in positions and positions == sorted(positions) and mpf not in out
    with Image.open(src) as read_in, Image.open(dst) as written:
        assert written.info["exif"] == read_in.info["exif"] and written.info["xmp"] == read_in.info["xmp"]
        assert written.info["comment"] == b"recorded by the test rig"


def test_png_text_colour_and_imagemagick_exif_chunks_are_kept(tmp_path):
    """ImageMagick keeps a PNG's EXIF (orientation included) in a ``Raw profile type exif`` text chunk and Adobe
    the XMP in iTXt; gAMA, cHRM, sRGB and pHYs say how to show it: all were dropped on write-back."""
    from PIL import PngImagePlugin
    info = PngImagePlugin.PngInfo()
    info.add_text("Raw profile type exif", "\nexif\n      26\n4578696600004d4d002a00000008000101120003000000010006")
    info.add_itxt("XML:com.adobe.xmp", '<x:xmpmeta><tiff:Orientation>6</tiff:Orientation></x:xmpmeta>')
    info.add(b"gAMA", (45455).to_bytes(4, "big"))
    info.add(b"sRGB", b"\x00")
    src, dst = tmp_path / "in.png", tmp_path / "out.png"
    _photo().save(src, pnginfo=info, dpi=(300, 300))
    _roundtrip(src, dst)
    out = Image.open(dst)
    assert out.text["Raw profile type exif"] == Image.open(src).text["Raw profile type exif"]
    assert "Orientation>6" in out.text["XML:com.adobe.xmp"]
    assert out.info["gamma"] == pytest.approx(0.45455) and round(out.info["dpi"][0]) == 300
    assert "srgb" in out.info
    out.load()                                          # every chunk well formed (CRCs checked)


def test_tiff_orientation_resolution_and_description_are_kept(tmp_path):
    """A TIFF's orientation tag was dropped on write-back (the output displays turned otherwise than the input),
    with its resolution, make/model and description (non-ASCII text included, as Photoshop writes it)."""
    import tifffile
    src, dst = tmp_path / "in.tif", tmp_path / "out.tif"
    codes = np.asarray(_photo())
    tifffile.imwrite(src, codes, photometric="rgb", resolution=(300, 300), resolutionunit=2, metadata=None,
                     extratags=[(274, "H", 1, 6, True), (271, "s", 0, "RoadCam", True),
                                (270, 2, None, "caf\xc3\xa9 \xc2\xae".encode("latin-1"), True)])
    _roundtrip(src, dst)
    with tifffile.TiffFile(dst) as tif:
        tags = tif.pages[0].tags
        assert tags[274].value == 6 and tags[271].value == "RoadCam"
        assert tags[282].value == (300, 1) and tags[296].value == 2
        assert "caf" in tags[270].value
    with tifffile.TiffFile(src, mode="r+") as tif:      # a resolution of 0/0 (tifffile cannot write it): left out
        tif.pages[0].tags[282].overwrite((0, 0))
    _roundtrip(src, dst)
    with tifffile.TiffFile(dst) as tif:
        assert tif.pages[0].tags[274].value == 6 and tif.pages[0].tags[282].value == (1, 1)


def test_geotiff_tags_are_kept(tmp_path):
    """A georeferenced TIFF (imageio's test_images/geotiff.tif layout: ModelPixelScale, ModelTiepoint, GeoKeyDirectory,
    GeoAsciiParams) keeps its georeference through a write-back (round 22; before: the four tags were dropped)."""
    import tifffile

    geo = [(33550, "d", 3, (32.8, 32.8, 0.0), True), (33922, "d", 6, (0.0, 0.0, 0.0, 681480.0, 1913050.0, 0.0), True),
           (34735, "H", 8, (1, 0, 2, 1, 1024, 0, 1, 1), True), (34737, "s", 0, "NAD27 in Feet|", True)]
    src, dst = tmp_path / "in.tif", tmp_path / "out.tif"
    tifffile.imwrite(src, np.asarray(_photo()), photometric="rgb", extratags=geo, metadata=None)
    _roundtrip(src, dst)
    with tifffile.TiffFile(src) as read_in, tifffile.TiffFile(dst) as written:
        for code, *_ in geo:
            assert written.pages[0].tags[code].value == read_in.pages[0].tags[code].value


def test_multi_page_tiff_is_refused_naming_its_pages(tmp_path):
    """Only the first page was read and written: the others were lost without a word."""
    import tifffile
    from roadview_noise.errors import InputError
    path = tmp_path / "stack.tif"
    with tifffile.TiffWriter(path) as tif:
        for k in range(3):
            tif.write(np.full((8, 8), 40 * k, np.uint8), photometric="minisblack", metadata=None)
    with pytest.raises(InputError, match="stack.tif.*3 pages"):
        read_image(path)
    one = tmp_path / "thumb.tif"                        # a full image and its reduced-resolution thumbnail: one image
    with tifffile.TiffWriter(one) as tif:
        tif.write(np.zeros((8, 8), np.uint8), photometric="minisblack", metadata=None)
        tif.write(np.zeros((2, 2), np.uint8), photometric="minisblack", metadata=None, subfiletype=1)
    assert read_image(one)[0].shape == (8, 8, 3)


@pytest.mark.parametrize("space,mode,kept", [(b"GRAY", "LA", False), (b"GRAY", "L", True), (b"RGB ", "L", True),
                                             (b"RGB ", "RGB", True), (b"CMYK", "RGB", False)])
def test_icc_profile_of_another_colour_space_than_the_output_is_dropped(tmp_path, space, mode, kept):
    """A grey + alpha PNG is written as RGBA: its grey profile does not describe RGB and was copied onto it; a CMYK
    profile (a CMYK JPEG decoded to RGB) likewise. A profile the input could have is kept."""
    ImageCms = pytest.importorskip("PIL.ImageCms")
    icc = bytearray(ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
    icc[16:20] = space
    src, dst = tmp_path / "in.png", tmp_path / "out.png"
    _photo().convert(mode).save(src, icc_profile=bytes(icc))
    _, enc = _roundtrip(src, dst)
    assert (enc.icc_profile == bytes(icc)) == kept
    assert (Image.open(dst).info.get("icc_profile") == bytes(icc)) == kept


def test_a_png_icc_chunk_that_does_not_inflate_is_no_profile(tmp_path):
    """Pillow's icc_profile_none.png: an iCCP chunk whose stream has no zlib header. Reading it raised an internal
    zlib error (the image failed); now the image reads as sRGB without a profile, as Pillow reads it, and its
    output has none."""
    import zlib

    from roadview_noise.io.png import png_chunk

    src, dst = tmp_path / "in.png", tmp_path / "out.png"
    _photo().save(src)
    data = src.read_bytes()
    deflate = zlib.compressobj(wbits=-15)                            # a raw deflate stream: no zlib header
    body = b"ICC Profile\x00\x00" + deflate.compress(bytes(300)) + deflate.flush()
    src.write_bytes(data[:33] + png_chunk(b"iCCP", body) + data[33:])
    linear, enc = _roundtrip(src, dst)
    assert enc.icc_profile is None and linear.shape == (64, 96, 3)
    with Image.open(src) as read_in, Image.open(dst) as written:
        assert read_in.info.get("icc_profile") is None and written.info.get("icc_profile") is None


def test_a_tiff_opencv_cannot_decode_is_refused_naming_why(tmp_path):
    """2/4-bit grey TIFFs (Pillow's hopper_gray_4bpp.tif) were refused as "corrupt or unsupported variant"; the
    error now names the layout (and a missing PhotometricInterpretation tag, Pillow's 10ct_32bit_128.tiff)."""
    import tifffile

    from roadview_noise.errors import InputError

    codes = (np.arange(48 * 64).reshape(48, 64) % 4).astype(np.uint8)
    tifffile.imwrite(tmp_path / "four.tif", codes, photometric="minisblack")
    with tifffile.TiffFile(tmp_path / "four.tif", mode="r+b") as tif:
        tif.pages[0].tags[258].overwrite(4)                      # BitsPerSample 4 (tifffile cannot pack them here)
    with pytest.raises(InputError, match="4-bit unsigned samples: rvnoise reads 8- and 16-bit"):
        read_image(tmp_path / "four.tif")


@pytest.mark.parametrize("extra,dtype", [("unassalpha", np.uint8), ("assocalpha", np.uint8),
                                         ("unassalpha", np.uint16), ("assocalpha", np.uint16)])
@pytest.mark.parametrize("turn", [1, 6])
def test_a_tiff_alpha_keeps_its_colours_and_kind(tmp_path, extra, dtype, turn):
    """An RGBA TIFF read and written back unchanged keeps its samples and its ExtraSamples kind. OpenCV multiplied
    8-bit colours by an unassociated alpha (100 at alpha 128 came out 50) and an associated alpha was written as
    unassociated; read as stored, also with an orientation tag."""
    import tifffile

    full = np.iinfo(dtype).max
    rgba = np.zeros((30, 40, 4), dtype)
    rgba[..., 0], rgba[..., 1], rgba[..., 2] = full // 5 * 2, full // 5, full // 10
    rgba[..., 3] = np.linspace(0, full, 40).astype(dtype)
    rgba[5, 7] = [full, 0, 0, full]                               # a marker the orientation must not move
    src, dst = tmp_path / "in.tif", tmp_path / "out.tif"
    tifffile.imwrite(src, rgba, photometric="rgb", extrasamples=[extra], extratags=[(274, "H", 1, turn, True)])
    linear, enc, alpha = read_image(src)
    write_image(dst, linear, enc, alpha)
    with tifffile.TiffFile(dst) as tif:
        assert tif.pages[0].extrasamples[0].name.lower() == extra
        np.testing.assert_array_equal(tif.pages[0].asarray(), rgba)


def test_an_lzw_rgba_tiff_tifffile_cannot_decode_is_unpremultiplied(tmp_path):
    """Without imagecodecs tifffile decodes no LZW: such an RGBA TIFF (Pillow's tiff_16bit_RGBa.tiff; Pillow's own
    RGBA files, ExtraSamples 2) is OpenCV's, whose 8-bit colours under alpha a are divided back to within
    255 / (2a) codes (they came out multiplied by a / 255: 100 at alpha 128 written 50)."""
    rgba = np.zeros((30, 40, 4), np.uint8)
    rgba[..., 0], rgba[..., 1], rgba[..., 2] = 100, 200, 30
    rgba[..., 3] = np.linspace(8, 255, 40).astype(np.uint8)
    src, dst = tmp_path / "in.tif", tmp_path / "out.tif"
    Image.fromarray(rgba, "RGBA").save(src, compression="tiff_lzw")
    linear, enc, alpha = read_image(src)
    write_image(dst, linear, enc, alpha)
    with Image.open(dst) as out:
        written = np.asarray(out)
    np.testing.assert_array_equal(written[..., 3], rgba[..., 3])
    tolerance = np.ceil(255 / (2 * rgba[..., 3:].astype(float)))
    assert np.all(np.abs(written[..., :3].astype(int) - rgba[..., :3]) <= tolerance)
    assert np.array_equal(written[:, -1, :3], rgba[:, -1, :3])               # full alpha: exact


def test_a_12_bit_jpeg_is_refused_saying_so(tmp_path):
    """OpenCV decodes 8-bit JPEGs only: a 12-bit one (libjpeg-turbo's monkey12.jpg; medical and some industrial
    cameras) failed as "corrupt or unsupported variant"."""
    from roadview_noise.errors import InputError
    src = tmp_path / "in.jpg"
    _photo().save(src, quality=90)
    data = bytearray(src.read_bytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 4] = 12                                  # sample precision of the start-of-frame segment
    (tmp_path / "p12.jpg").write_bytes(bytes(data))
    with pytest.raises(InputError, match="p12.jpg.*a 12-bit JPEG"):
        read_image(tmp_path / "p12.jpg")


def test_palette_and_cmyk_tiff_are_read_in_colour_as_rgb(tmp_path):
    """OpenCV reads a palette TIFF as the grey levels of its colours (green (0, 128, 0) came out as grey 75) and a
    CMYK TIFF with an opaque alpha plane it adds (written back as RGBA); both are RGB now, as palette PNGs and CMYK
    JPEGs are."""
    import tifffile
    index = (np.arange(12 * 10) % 4).astype(np.uint8).reshape(12, 10)
    colormap = np.zeros((3, 256), np.uint16)
    colormap[:, :4] = np.array([[0, 255, 0, 10], [128, 0, 0, 20], [0, 0, 255, 30]]) * 257
    tifffile.imwrite(tmp_path / "pal.tif", index, photometric="palette", colormap=colormap)
    linear, enc, alpha = read_image(tmp_path / "pal.tif")
    assert enc.channels == 3 and alpha is None
    from roadview_noise.physics import srgb
    np.testing.assert_array_equal(srgb.linear_to_code(linear, 8),
                                  np.asarray(Image.open(tmp_path / "pal.tif").convert("RGB")))
    cmyk = np.asarray(_photo().convert("CMYK"))
    tifffile.imwrite(tmp_path / "cmyk.tif", cmyk, photometric="separated")
    _, enc = _roundtrip(tmp_path / "cmyk.tif", tmp_path / "cmyk_out.tif")
    assert enc.channels == 3 and Image.open(tmp_path / "cmyk_out.tif").mode == "RGB"


@pytest.mark.parametrize("bits", [8, 16])
def test_grey_png_transparency_becomes_an_alpha_plane(tmp_path, bits):
    """A grey PNG whose tRNS chunk makes one level transparent (PngSuite's ftbbn0g*, Pillow's l_trns.png) was read
    opaque by OpenCV and written without it; its transparency is now an alpha plane (RGBA out, as grey + alpha)."""
    grey = (np.arange(20 * 30) % 7 * 30).astype(np.uint8 if bits == 8 else np.uint16).reshape(20, 30)
    src, dst = tmp_path / "in.png", tmp_path / "out.png"
    Image.fromarray(grey).save(src, transparency=60)
    _, enc = _roundtrip(src, dst)
    assert enc.channels == 4
    alpha = np.asarray(Image.open(dst))[..., 3]
    np.testing.assert_array_equal(alpha == 0, grey == 60)
