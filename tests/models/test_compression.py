"""compression.camera (models.md §2.7): JPEG of the 8-bit sRGB image."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.errors import ModelError
from roadview_noise.model import Stage
from roadview_noise.models.camera.compression import CHROMA_SUBSAMPLING, CompressionCamera
from roadview_noise.physics import srgb
from roadview_noise.profiles.camera import carla_pinhole
from roadview_noise.registry import load_all
from roadview_noise.types import CameraFrame, RawFrame

H, W = 240, 320


def natural_image(seed: int = 0) -> np.ndarray:
    """Linear RGB (H, W, 3) float32 with what photographs have: smooth shading, edges, colour, fine texture."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    img = np.stack([0.5 + 0.3 * np.sin(2 * np.pi * (x + 0.3 * y)), 0.4 + 0.3 * np.cos(3 * np.pi * y),
                    0.3 + 0.2 * np.sin(5 * x * y + 1)], axis=-1)
    cv2.rectangle(img, (40, 60), (140, 200), (0.9, 0.2, 0.1), -1)
    cv2.circle(img, (240, 110), 50, (0.1, 0.3, 0.8), -1)
    img = cv2.GaussianBlur(img, (0, 0), 1.5)                                     # optics: no step edges
    texture = cv2.GaussianBlur(rng.normal(0, 0.04, (H, W)), (0, 0), 1.0)[..., None]   # mostly luminance detail
    return np.clip((img + texture) ** 2.2, 0, 1).astype(np.float32)


def frame(linear=None, **kw) -> CameraFrame:
    linear = natural_image() if linear is None else linear
    return CameraFrame(linear, carla_pinhole(W, H), **kw)


def run(model: CompressionCamera, f: CameraFrame):
    return model.apply(f, state={}, drawn={}, rng=np.random.default_rng(0))


def psnr_db(a_linear: np.ndarray, b_linear: np.ndarray) -> float:
    """PSNR of the 8-bit sRGB renderings (independent of cv2.PSNR)."""
    a = srgb.linear_to_code(a_linear).astype(float)
    b = srgb.linear_to_code(b_linear).astype(float)
    return 10 * np.log10(255.0 ** 2 / np.mean((a - b) ** 2))


def test_registered_as_encoding_stage():
    assert load_all()["compression.camera"] is CompressionCamera
    assert CompressionCamera.stage == Stage.ENCODING and CompressionCamera.quality == 15


def test_shape_dtype_and_passthrough():
    depth = np.full((H, W), 12.0, dtype=np.float32)
    alpha = np.full((H, W), 200, dtype=np.uint8)
    f = frame(depth_m=depth, alpha=alpha)
    before = f.linear_rgb.copy()
    out, diag = run(CompressionCamera(), f)
    assert out.linear_rgb.shape == (H, W, 3) and out.linear_rgb.dtype == np.float32
    assert out.depth_m is depth and out.alpha is alpha and out.profile is f.profile
    np.testing.assert_array_equal(f.linear_rgb, before)                       # input untouched
    assert 0.0 <= out.linear_rgb.min() and out.linear_rgb.max() <= 1.0
    assert diag["bytes"] > 0 and diag["compression_ratio"] == pytest.approx(H * W * 3 / diag["bytes"])
    assert all(isinstance(v, (int, float, str)) for v in diag.values())


def test_output_is_an_8bit_srgb_image():
    """What comes back is exactly what a JPEG decoder writes: 8-bit sRGB codes, linearised."""
    out, _ = run(CompressionCamera(), frame())
    codes = srgb.linear_to_code(out.linear_rgb)
    np.testing.assert_array_equal(srgb.code_to_linear(codes), out.linear_rgb)


def test_quality_100_is_near_identity():
    f = frame()
    out, diag = run(CompressionCamera(quality=100), f)
    assert psnr_db(f.linear_rgb, out.linear_rgb) > 35.0
    assert diag["psnr_db"] == pytest.approx(psnr_db(f.linear_rgb, out.linear_rgb), abs=0.01)


def test_quality_15_degrades():
    f = frame()
    q15 = psnr_db(f.linear_rgb, run(CompressionCamera(quality=15), f)[0].linear_rgb)
    q100 = psnr_db(f.linear_rgb, run(CompressionCamera(quality=100), f)[0].linear_rgb)
    assert q15 < q100 - 10.0


def test_ratio_decreases_with_quality():
    f = frame()
    ratios = [run(CompressionCamera(quality=q), f)[1]["compression_ratio"] for q in (5, 15, 30, 50, 75, 90, 100)]
    assert all(a > b for a, b in zip(ratios, ratios[1:])), ratios


def test_smooth_content_compresses_more():
    """models.md §2.7: fog (low-pass) compresses more than snow (added high-frequency content) at equal Q."""
    base = natural_image()
    foggy = 0.6 * cv2.GaussianBlur(base, (0, 0), 4.0) + 0.3
    flakes = base.copy()
    flakes[np.random.default_rng(5).random((H, W)) < 0.02] = 1.0
    ratio = {name: run(CompressionCamera(), frame(img.astype(np.float32)))[1]["compression_ratio"]
             for name, img in (("fog", foggy), ("clear", base), ("snow", flakes))}
    assert ratio["fog"] > ratio["clear"] > ratio["snow"], ratio


def test_deterministic_and_seed_free():
    f = frame()
    a, _ = apply_models([CompressionCamera()], f, seed=1, key="a.png", sequence_id="s")
    b, _ = apply_models([CompressionCamera()], f, seed=2, key="b.png", sequence_id="t")
    np.testing.assert_array_equal(a.linear_rgb, b.linear_rgb)


def test_unclipped_input_is_clipped_before_coding():
    """Reference [BUG]: float arrays beyond full scale (fog) must be clipped, not wrapped."""
    img = natural_image()
    hot = img.copy()
    hot[:60] *= 4.0
    hot[-60:] -= 1.0
    a, _ = run(CompressionCamera(), frame(hot))
    b, _ = run(CompressionCamera(), frame(np.clip(hot, 0, 1)))
    np.testing.assert_array_equal(a.linear_rgb, b.linear_rgb)


def sof_sampling(bitstream: bytes) -> list[tuple[int, int]]:
    """(H, V) sampling factors of the components, read from the JPEG start-of-frame segment."""
    i = 2
    while True:
        marker, length = bitstream[i + 1], int.from_bytes(bitstream[i + 2:i + 4], "big")
        if 0xC0 <= marker <= 0xC2:
            n = bitstream[i + 9]
            comps = bitstream[i + 10:i + 10 + 3 * n]
            return [(comps[3 * k + 1] >> 4, comps[3 * k + 1] & 15) for k in range(n)]
        i += 2 + length


@pytest.mark.parametrize("name, luma", [("4:4:4", (1, 1)), ("4:2:2", (2, 1)), ("4:2:0", (2, 2)),
                                        ("4:4:0", (1, 2)), ("4:1:1", (4, 1))])
def test_chroma_subsampling_names_match_the_bitstream(name, luma):
    codes = srgb.linear_to_code(natural_image())
    ok, bitstream = cv2.imencode(".jpg", codes, [cv2.IMWRITE_JPEG_QUALITY, 15,
                                                 cv2.IMWRITE_JPEG_SAMPLING_FACTOR, CHROMA_SUBSAMPLING[name]])
    assert ok and sof_sampling(bitstream.tobytes()) == [luma, (1, 1), (1, 1)]


def test_default_subsampling_is_libjpeg_default():
    codes = srgb.linear_to_code(natural_image())
    ok, bitstream = cv2.imencode(".jpg", codes, [cv2.IMWRITE_JPEG_QUALITY, 15])
    assert ok and sof_sampling(bitstream.tobytes())[0] == (2, 2)
    assert CompressionCamera().chroma_subsampling == "4:2:0"


def test_full_chroma_keeps_colour_edges_better():
    f = frame()
    p420 = psnr_db(f.linear_rgb, run(CompressionCamera(quality=90), f)[0].linear_rgb)
    p444 = psnr_db(f.linear_rgb, run(CompressionCamera(quality=90, chroma_subsampling="4:4:4"), f)[0].linear_rgb)
    assert p444 > p420


def test_refuses_bayer_mosaic():
    raw = RawFrame(np.zeros((H, W), np.float32), "RGGB", 0.0, 4095.0, carla_pinhole(W, H))
    with pytest.raises(ModelError, match="Bayer"):
        run(CompressionCamera(), raw)


@pytest.mark.parametrize("kw", [{"quality": 0}, {"quality": 101}, {"quality": 15.5}, {"chroma_subsampling": "4:2:1"}])
def test_rejects_bad_parameters(kw):
    with pytest.raises(ModelError):
        CompressionCamera(**kw)


def test_codes_travel_with_the_frame_and_change_nothing():
    # a frame read from codes is coded from those codes, and the decoded codes go to the writer as they are: the
    # result is the one of the plain conversion, with no sRGB round trip (issue 19)
    codes = srgb.linear_to_code(natural_image(3))
    read = frame(srgb.code_to_linear(codes))
    plain = frame(srgb.code_to_linear(codes).copy())          # the same pixels without the kept codes
    out_kept, diag_kept = run(CompressionCamera(quality=30), read)
    out_plain, diag_plain = run(CompressionCamera(quality=30), plain)
    np.testing.assert_array_equal(out_kept.linear_rgb, out_plain.linear_rgb)
    assert diag_kept == diag_plain
    kept = srgb.attached_codes(out_kept.linear_rgb, 8)
    assert kept is not None
    np.testing.assert_array_equal(kept, srgb.linear_to_code(out_plain.linear_rgb.copy()))


def test_jpeg_output_holds_its_codes_and_decodes_only_when_read(tmp_path):
    # issue 19: the JPEG result is its decoded 8-bit codes; the linear values are computed only when a later step
    # reads them, and then they are exactly the codes' decoding; the writer stores the codes without decoding
    from roadview_noise.io.image import read_image, write_frame, write_image
    import dataclasses
    import pickle

    out, _ = run(CompressionCamera(quality=20), frame())
    codes = out.srgb8_codes()
    assert codes is not None and codes.dtype == np.uint8 and codes.shape == (H, W, 3) and out.shape == (H, W)
    assert "linear_rgb" not in vars(out)                                     # not decoded yet
    write_frame(tmp_path / "kept.png", out)
    assert "linear_rgb" not in vars(out)                                     # the writer did not decode it
    again = pickle.loads(pickle.dumps(out))                                  # to and from a worker
    np.testing.assert_array_equal(again.srgb8_codes(), codes)
    linear = out.linear_rgb                                                  # a later step reads it
    np.testing.assert_array_equal(linear, srgb.code_to_linear(np.ascontiguousarray(codes)))
    assert out.linear_rgb is linear and out.srgb8_codes() is codes
    write_image(tmp_path / "plain.png", linear.copy(), out.encoding)         # the same pixels, encoded afresh
    assert (tmp_path / "kept.png").read_bytes() == (tmp_path / "plain.png").read_bytes()
    np.testing.assert_array_equal(read_image(tmp_path / "kept.png")[0], linear)
    moved = dataclasses.replace(again, depth_m=np.ones((H, W), np.float32))  # other fields change: codes stay valid
    np.testing.assert_array_equal(moved.srgb8_codes(), codes)
    assert out.with_signal(linear * np.float32(0.5)).srgb8_codes() is None   # a changed image has none
    with pytest.raises(ValueError, match="uint8 codes"):
        frame().with_srgb8_codes(codes[:10])
