"""Metrics of the manifest (roadview_noise.metrics) against hand-computed cases and scikit-image."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.metrics import (DEPTH_BIN_EDGES_M, Effect, compare, correspondence, metric_scale, psnr_db,
                                    rms_contrast_per_depth_bin, ssim, with_effect_codes)
from roadview_noise.physics.srgb import decode, encode
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.registry import get_model
from roadview_noise.types import CameraFrame, CameraProfile, PointCloud, RadarProfile, RawFrame

PROFILE = CameraProfile.from_fov("test", 64, 48, 90.0)


def frame_of_codes(codes: np.ndarray, depth_m: np.ndarray | None = None) -> CameraFrame:
    """A frame whose sRGB code values (0–1, exact multiples of 1/65535) are ``codes`` (grey, H×W)."""
    linear = decode(np.repeat(codes[..., None], 3, axis=2)).astype(np.float32)
    h, w = codes.shape
    return CameraFrame(linear, dataclasses.replace(PROFILE, width_px=w, height_px=h), depth_m=depth_m)


def code(k: int) -> float:
    return k / 65535


def two_levels(lo: float, hi: float, h=48, w=64) -> np.ndarray:
    img = np.full((h, w), lo)
    img[:, w // 2:] = hi
    return img


# --- camera ------------------------------------------------------------------------------------------------------


def test_identity_frame_psnr_inf_ssim_one():
    rng = np.random.default_rng(0)
    f = CameraFrame(rng.random((48, 64, 3), dtype=np.float32), PROFILE)
    m = compare(f, f)
    assert m["psnr_db"] == math.inf
    assert m["ssim"] == 1.0
    assert m["rms_contrast_in"] == m["rms_contrast_out"]
    assert m["edge_density_in"] == m["edge_density_out"]
    # a copy (another object, no cache hit) gives the same
    assert compare(f, dataclasses.replace(f, linear_rgb=f.linear_rgb.copy()))["psnr_db"] == math.inf


def test_rms_contrast_of_two_levels_and_a_contrast_change():
    lo, hi = code(10000), code(50000)
    before = frame_of_codes(two_levels(lo, hi))
    mid = (lo + hi) / 2
    after = frame_of_codes(two_levels(code(20000), code(40000)))          # contrast halved around the mean
    m = compare(before, after)
    assert m["rms_contrast_in"] == pytest.approx((hi - lo) / 2, abs=2e-6)      # σ of two equal halves
    assert m["rms_contrast_out"] == pytest.approx((hi - lo) / 4, abs=2e-6)
    assert m["mean_level_in"] == pytest.approx(mid, abs=2e-6)
    assert m["mean_level_out"] == pytest.approx(mid, abs=2e-6)


def test_psnr_of_a_uniform_offset():
    a = frame_of_codes(np.full((48, 64), code(30000)))
    b = frame_of_codes(np.full((48, 64), code(30000 + 655)))
    delta = 655 / 65535
    assert compare(a, b)["psnr_db"] == pytest.approx(-20 * math.log10(delta), abs=1e-3)
    assert psnr_db(np.zeros(4), np.full(4, 0.1)) == pytest.approx(20.0)


def test_edge_density_of_a_step_a_square_and_the_visibility_threshold():
    step = frame_of_codes(two_levels(0.0, code(51400)))
    assert compare(step, step)["edge_density_in"] == 2 * 48 / (48 * 64)       # the two columns beside the step
    square = np.zeros((48, 64))
    square[10:30, 20:40] = code(51400)
    assert compare(frame_of_codes(square), step)["edge_density_in"] == (22 * 22 - 18 * 18) / (48 * 64)
    lo = 20000
    visible = frame_of_codes(two_levels(code(lo), code(lo + 3277)))            # a 5.0 % step
    faint = frame_of_codes(two_levels(code(lo), code(lo + 3200)))              # a 4.9 % step
    assert compare(visible, faint)["edge_density_in"] == 2 * 48 / (48 * 64)
    assert compare(visible, faint)["edge_density_out"] == 0.0


def test_contrast_per_depth_bin():
    h, w = 48, 64
    codes = np.empty((h, w))
    codes[:24, ::2], codes[:24, 1::2] = code(10000), code(30000)   # near half: contrast 10000
    codes[24:, ::2], codes[24:, 1::2] = code(20000), code(24000)   # far half: contrast 2000
    depth = np.full((h, w), 5.0)
    depth[24:] = np.inf                                             # sky: the last bin
    m = compare(frame_of_codes(codes, depth), frame_of_codes(codes, depth))
    assert m["depth_bin_edges_m"] == list(DEPTH_BIN_EDGES_M)
    per_bin = m["rms_contrast_per_depth_bin_out"]
    assert per_bin[0] == pytest.approx(code(10000), abs=2e-6)
    assert per_bin[-1] == pytest.approx(code(2000), abs=2e-6)
    assert per_bin[1:-1] == [None, None, None]



@pytest.mark.parametrize("edges", [DEPTH_BIN_EDGES_M, (2.0, 30.0, 60.0)])
def test_contrast_per_depth_bin_is_the_std_of_each_bin(edges):
    """Each bin's RMS contrast is the standard deviation of its pixels (NumPy); pixels without depth (NaN,
    negative, below the first edge) count nowhere, the last bin takes everything from its lower edge up to inf."""
    rng = np.random.default_rng(7)
    grey = rng.random((90, 120), dtype=np.float32)
    depth = np.cumsum(rng.uniform(-3, 3.2, (90, 120)), axis=1).astype(np.float32)    # coherent, some negative
    depth[::7, ::5], depth[::11, 3::4] = np.nan, np.inf
    got = rms_contrast_per_depth_bin(grey, depth, edges)
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = (depth >= lo) & ((depth < hi) | (i == len(edges) - 2))
        expected = float(np.std(grey[sel].astype(np.float64))) if sel.sum() >= 64 else None
        assert got[i] == (None if expected is None else pytest.approx(expected, rel=1e-9, abs=1e-12))
    assert sum(v is not None for v in got) >= 2

def test_ssim_matches_scikit_image():
    skm = pytest.importorskip("skimage.metrics")
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:90, 0:120]
    a = (0.5 + 0.3 * np.sin(x / 7.0) * np.cos(y / 5.0)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1).astype(np.float32) * 0.8 + 0.1
    ref = skm.structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False)
    assert ssim(a, b) == pytest.approx(ref, abs=2e-4)
    assert ssim(a, a) == 1.0
    assert ssim(a[:8], a[:8]) is None                       # smaller than the 11×11 window


@pytest.mark.parametrize("f", [1, 2, 3, 7])
def test_luminance_area_is_the_area_resize_then_the_luminance_weights(f):
    """The one-pass reduction equals OpenCV's area resize then the Rec. 709 weights to float32 rounding, leaves
    out the rows/columns that do not fill a block, reads any memory layout alike and keeps the channel order."""
    import cv2

    from roadview_noise.luminance import LUMINANCE_WEIGHTS, luminance_area

    rng = np.random.default_rng(f)
    rgb = (rng.random((101, 157, 3), dtype=np.float32) * np.array([1.0, 0.3, 3.0], np.float32)).astype(np.float32)
    h, w = 101 // f, 157 // f
    ref = cv2.transform(cv2.resize(rgb[: h * f, : w * f], (w, h), interpolation=cv2.INTER_AREA),
                        np.array([LUMINANCE_WEIGHTS], np.float32))
    got = luminance_area(rgb, f)
    assert got.shape == (h, w) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=2e-6, atol=1e-7)
    view = np.ascontiguousarray(rgb[::-1, ::-1])[::-1, ::-1]           # the same pixels, negative strides
    np.testing.assert_array_equal(luminance_area(view, f), got)
    red = np.zeros((4 * f, 4 * f, 3), np.float32)
    red[..., 0] = 1.0
    np.testing.assert_allclose(luminance_area(red, f), LUMINANCE_WEIGHTS[0], rtol=1e-6)


@pytest.mark.parametrize("f", [1, 2, 7])
def test_codes_luminance_area_is_the_decoded_frames_bit_for_bit(f):
    """A JPEG output's summary reads its 8-bit codes (RGB, or OpenCV's BGR seen channel-reversed) and gives exactly
    the luminance of the decoded frame, without decoding it."""
    from roadview_noise.metrics import codes_luminance_area, luminance_area
    from roadview_noise.physics.srgb import code_to_linear

    rng = np.random.default_rng(f)
    bgr = rng.integers(0, 256, (101, 157, 3), dtype=np.uint8)
    for codes in (bgr[..., ::-1], np.ascontiguousarray(bgr[..., ::-1])):
        np.testing.assert_array_equal(codes_luminance_area(codes, f), luminance_area(code_to_linear(codes), f))


def test_a_jpeg_outputs_metrics_never_decode_it():
    """Metrics of a frame that holds its codes (compression.camera's output) leave it undecoded and equal the
    metrics of the same frame decoded."""
    from roadview_noise.metrics import compare
    from roadview_noise.physics.srgb import code_to_linear

    rng = np.random.default_rng(3)
    before = CameraFrame(rng.random((96, 128, 3), dtype=np.float32), PROFILE.resized(128, 96))
    codes = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    after = before.with_srgb8_codes(codes)
    got = compare(before, after)
    assert after.undecoded_srgb8_codes() is codes
    decoded = dataclasses.replace(before, linear_rgb=code_to_linear(codes))
    assert got == compare(before, decoded)


def test_one_pass_grey_statistics_equal_opencv_sobel_and_numpy():
    """The summary's single pass counts the edges of :func:`edge_density` (OpenCV's Sobel, replicated borders) —
    on levels that put many gradients exactly at the threshold; a count may differ only by gradients within
    float32 rounding of it — and gives NumPy's mean, standard deviation and per-bin sums."""
    import cv2

    from roadview_noise.metrics import _edge_limit, _grey_statistics, edge_density

    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:63, 0:97]
    grey = (0.5 + 0.15 * np.sin(x / 4.0) * np.cos(y / 5.0) + rng.normal(0, 0.003, x.shape)).astype(np.float32)
    grey[45:] = (rng.integers(0, 2, (18, 97)) * 0.05 + 0.4).astype(np.float32)   # steps of exactly 5 %
    bins = rng.integers(-1, 5, grey.shape).astype(np.int8)
    for img in (grey, grey[:1], grey[:, :1], np.ascontiguousarray(grey.T)):
        total, squares, edges, _ = _grey_statistics(img, _edge_limit(), np.zeros((0, 0), np.int8), 5)
        gx, gy = (cv2.Sobel(img, cv2.CV_32F, dx, 1 - dx, borderType=cv2.BORDER_REPLICATE) for dx in (1, 0))
        ties = np.count_nonzero(np.abs(gx * gx + gy * gy - _edge_limit()) <= 1e-5 * _edge_limit())
        assert abs(edges - round(edge_density(img) * img.size)) <= ties
        assert total == pytest.approx(float(np.sum(img, dtype=np.float64)), rel=1e-12)
        assert squares == pytest.approx(float(np.sum(img.astype(np.float64) ** 2)), rel=1e-12)
    assert 0.2 < edge_density(grey) < 0.8
    n, total, squares = _grey_statistics(grey, _edge_limit(), bins, 5)[3]
    g = grey.astype(np.float64)
    for b in range(5):
        assert n[b] == np.count_nonzero(bins == b)
        assert total[b] == pytest.approx(g[bins == b].sum(), rel=1e-12)
        assert squares[b] == pytest.approx((g[bins == b] ** 2).sum(), rel=1e-12)


def test_ssim_equals_equation_13_in_float64():
    """The compiled SSIM mean equals Wang et al.'s Eq. 13 evaluated in float64 from the same Gaussian window."""
    import cv2

    rng = np.random.default_rng(4)
    a = rng.random((70, 90), dtype=np.float32)
    b = np.clip(a * 0.7 + rng.normal(0.1, 0.05, a.shape), 0, 1).astype(np.float32)

    def blur(x):
        return cv2.GaussianBlur(x, (11, 11), 1.5)[5:-5, 5:-5]

    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    mu_a, mu_b = blur(a64), blur(b64)
    var_a, var_b, cov = blur(a64 * a64) - mu_a ** 2, blur(b64 * b64) - mu_b ** 2, blur(a64 * b64) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ref = np.mean((2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2)))
    assert ssim(a, b) == pytest.approx(ref, rel=1e-5)


def test_ssim_matches_a_scipy_reference():
    """The compiled SSIM (float32 separable window, its own summation order) against an independent float64
    reference: scipy's 2-D correlation with the 11×11 Gaussian window (σ = 1.5, normalised), Eq. 13, mean over the
    windows inside the image; on a smooth image with noise, a contrast change and flat regions (variances ≈ 0)."""
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(5)
    y, x = np.mgrid[0:83, 0:117]
    a = np.clip(0.5 + 0.3 * np.sin(x / 6.0) * np.cos(y / 4.0) + rng.normal(0, 0.03, x.shape), 0, 1)
    a[:30, :40] = 0.25                                           # a flat patch: SSIM's variances ≈ 0 there
    a = a.astype(np.float32)
    b = np.clip(0.6 * a + 0.2 + rng.normal(0, 0.02, a.shape), 0, 1).astype(np.float32)
    t = np.arange(-5, 6)
    g = np.exp(-t * t / (2 * 1.5 ** 2))
    window = np.outer(g, g) / np.outer(g, g).sum()

    def local_mean(v):
        return ndimage.correlate(v, window, mode="constant")[5:-5, 5:-5]

    def reference(p, q):
        p, q = p.astype(np.float64), q.astype(np.float64)
        mu_p, mu_q = local_mean(p), local_mean(q)
        var_p, var_q = local_mean(p * p) - mu_p ** 2, local_mean(q * q) - mu_q ** 2
        cov = local_mean(p * q) - mu_p * mu_q
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        return np.mean((2 * mu_p * mu_q + c1) * (2 * cov + c2) / ((mu_p ** 2 + mu_q ** 2 + c1) * (var_p + var_q + c2)))

    for p, q in ((a, b), (b, a), (a, np.clip(a + 0.01, 0, 1).astype(np.float32))):
        assert ssim(p, q) == pytest.approx(reference(p, q), abs=2e-6)
    assert ssim(b, b) == 1.0


def test_metric_scale_leaves_at_most_65536_pixels():
    assert metric_scale(1464, 1936) == 7                                       # 209 × 276
    assert metric_scale(366, 484) == 2                                         # 183 × 242
    assert metric_scale(256, 256) == 1 and metric_scale(257, 256) == 2
    for h, w in ((1080, 1920), (2048, 2448), (720, 1280), (64, 5000)):
        f = metric_scale(h, w)
        assert (h // f) * (w // f) <= 65536 < (h // (f - 1)) * (w // (f - 1)) if f > 1 else h * w <= 65536
    rng = np.random.default_rng(1)
    f = CameraFrame(rng.random((1464, 1936, 3), dtype=np.float32) * 0.5, PROFILE.resized(1936, 1464))
    m = compare(f, f)
    assert m["metric_scale"] == 7 and m["psnr_db"] == math.inf
    # the box filter averages pixel noise away: the reduced image has far less contrast than single pixels
    assert m["rms_contrast_in"] < 0.05


def test_raw_grey_is_the_mean_signal_of_each_cfa_cell():
    """Reducing the DN before the affine signal conversion gives the grey image of the definition: the mean signal
    of each 2×2 CFA cell (then sRGB-encoded)."""
    rng = np.random.default_rng(5)
    dn = rng.integers(64, 4000, (49, 67)).astype(np.float32)                 # odd: the last row/column is left out
    raw = RawFrame(dn, "RGGB", 64.0, 4095.0, PROFILE)
    cells = raw.signal()[:48, :66].reshape(24, 2, 33, 2).mean(axis=(1, 3))
    grey = np.round(encode(np.clip(cells, 0, 1)) * 65535) / 65535
    assert compare(raw, raw)["mean_level_in"] == pytest.approx(float(np.mean(grey)), abs=2e-6)


def test_raw_frame_metrics():
    rng = np.random.default_rng(2)
    dn = rng.integers(64, 4000, (48, 64)).astype(np.float32)
    raw = RawFrame(dn, "RGGB", 64.0, 4095.0, PROFILE)
    m = compare(raw, raw)
    assert m["psnr_db"] == math.inf and m["ssim"] == 1.0 and m["metric_scale"] == 1   # on 24×32 CFA cells
    darker = dataclasses.replace(raw, dn=(dn - 64) * 0.5 + 64)
    assert compare(raw, darker)["mean_level_out"] < m["mean_level_in"]


# --- point clouds ------------------------------------------------------------------------------------------------


def lidar_list(n=100, seed=0) -> PointCloud:
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    r = rng.uniform(1, 95, n)
    return PointCloud(direction * r[:, None], {"intensity": rng.uniform(10, 100, n).astype(np.float32)}, "lidar",
                      profile=os1_128())


def test_identity_cloud_nothing_removed():
    c = lidar_list()
    m = compare(c, c)
    assert (m["points_in"], m["points_out"], m["kept"]) == (100, 100, 100)
    assert m["removed"] == m["added"] == m["moved"] == m["attenuated"] == 0
    assert m["mean_intensity_change"] == 0.0
    assert m["max_range_m_in"] == m["max_range_m_out"] == pytest.approx(c.ranges_m.max())
    assert sum(m["points_per_10m_in"]) == 100
    assert m["points_per_10m_in"] == np.bincount((c.ranges_m // 10).astype(int)).tolist()


def test_value_change_is_taken_in_float64():
    """float32 intensities 1 and 1e-8: their difference in float32 would round to 1 exactly."""
    c = lidar_list(n=1)
    before = PointCloud(c.positions_m, {"intensity": np.array([1e-8], np.float32)}, "lidar", profile=c.profile)
    after = PointCloud(c.positions_m, {"intensity": np.array([1.0], np.float32)}, "lidar", profile=c.profile)
    expected = float(np.float64(np.float32(1.0)) - np.float64(np.float32(1e-8)))
    assert expected != 1.0
    assert compare(before, after)["mean_intensity_change"] == expected


def test_known_drop_mask_moves_and_additions_give_exact_counts():
    c = lidar_list()
    drop = np.zeros(100, bool)
    drop[[3, 17, 40, 41, 99]] = True
    label = np.zeros(100, np.uint8)
    label[[5, 6]] = Effect.MOVED
    label[[7, 8, 9]] = Effect.ATTENUATED
    pos = c.positions_m.copy()
    pos[[5, 6]] *= 0.25                                           # moved along their rays
    intensity = c.fields["intensity"].copy()
    intensity[[7, 8, 9]] -= 6.0
    after = PointCloud(pos, {"intensity": intensity}, "lidar", profile=c.profile).select(~drop)
    after = after.concat(np.array([[1.0, 2.0, 0.5], [3.0, 0.0, 0.1]]), {"intensity": np.full(2, 5, np.float32)})
    after = with_effect_codes(after, np.concatenate([label[~drop], np.full(2, Effect.ADDED)]))
    m = compare(c, after)
    assert m["removed"] == 5 and m["moved"] == 2 and m["attenuated"] == 3 and m["added"] == 2
    assert m["kept"] == 100 - 5 - 2 - 3 and m["points_out"] == 97
    assert m["mean_intensity_change"] == pytest.approx(-6.0 * 3 / (100 - 5 - 2))
    index, moved = correspondence(c, after)
    assert np.array_equal(index < 0, drop)
    assert np.flatnonzero(moved).tolist() == [5, 6]


def test_drop_on_a_grid_and_per_object_counts():
    c = lidar_list(64)
    ids = np.repeat([1, 2, 0, 7], 16).astype(np.int32)
    grid = dataclasses.replace(c.with_fields(object_id=ids), grid_shape=(4, 16))
    drop = np.zeros(64, bool)
    drop[[0, 1, 2, 20, 40]] = True                                # object 1 loses 3, object 2 loses 1, none: 1
    after = grid.drop(drop)
    m = compare(grid, after)
    assert m["removed"] == 5 and m["points_out"] == 59 and m["kept"] == 59
    assert m["objects"] == {"1": [16, 13], "2": [16, 15], "7": [16, 16]}


def test_a_step_that_keeps_the_positions_array_is_summarised_anew():
    """Intensity models hand the positions array on unchanged; the geometry is kept for it, the intensities and
    effect codes are counted again, and another array (even equal in value) is summarised afresh."""
    c = lidar_list()
    brighter = with_effect_codes(c.with_fields(intensity=c.fields["intensity"] * 2), np.full(100, Effect.ATTENUATED))
    assert brighter.positions_m is c.positions_m
    m = compare(c, brighter)
    assert (m["points_in"], m["points_out"], m["attenuated"], m["kept"]) == (100, 100, 100, 0)
    assert m["mean_intensity_out"] == pytest.approx(2 * m["mean_intensity_in"])
    assert m["mean_intensity_change"] == pytest.approx(m["mean_intensity_in"])
    pos = c.positions_m.copy()
    pos[:10] = 0.0                                                # ten rays without a return
    fewer = dataclasses.replace(c, positions_m=pos)
    m = compare(brighter, fewer)
    assert (m["points_in"], m["points_out"]) == (100, 90)
    assert sum(m["points_per_10m_out"]) == 90


def test_clouds_without_intensity_or_codes():
    c = lidar_list()
    bare = PointCloud(c.positions_m, {}, "lidar", profile=c.profile)
    m = compare(bare, bare.select(np.arange(100) % 4 != 0))
    assert m["removed"] == 25 and m["mean_intensity_change"] is None and m["mean_intensity_in"] is None


def test_alignment_shift_without_removal_keeps_correspondence():
    c = lidar_list()
    shifted = dataclasses.replace(c, positions_m=c.positions_m + 0.01)
    index, moved = correspondence(c, shifted)
    assert np.array_equal(index, np.arange(100)) and not moved.any()
    assert compare(c, shifted)["removed"] == 0


def test_alignment_then_removal_composes_the_steps():
    c0 = lidar_list()
    c1 = dataclasses.replace(c0, positions_m=c0.positions_m * 1.001)            # every point moved: no exact match
    keep = np.ones(100, bool)
    keep[[10, 50]] = False
    label = np.zeros(100, np.uint8)
    label[[20, 21]] = Effect.ATTENUATED
    label[30] = Effect.MOVED
    pos = c1.positions_m.copy()
    pos[30] *= 0.5
    c2 = c1.with_fields(intensity=c1.fields["intensity"] - 4 * (label == Effect.ATTENUATED))
    c2 = with_effect_codes(dataclasses.replace(c2, positions_m=pos).select(keep), label[keep])
    compare(c0, c1), compare(c1, c2)                                            # the steps, as apply_models does
    index, moved = correspondence(c0, c2)
    assert np.array_equal(index < 0, ~keep) and np.flatnonzero(moved).tolist() == [30]
    m = compare(c0, c2)
    assert m["removed"] == 2 and m["moved"] == 1 and m["attenuated"] == 2
    assert m["mean_intensity_change"] == pytest.approx(-8 / 97, rel=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_three_step_chain_against_its_construction(seed):
    """Alignment (every point shifted, none removed) → weather (random removals, moves along the ray,
    attenuations, additions) → an intensity step that keeps the positions array: each step's counts and the
    chain's correspondence and mean intensity change equal what the construction says, point by point."""
    rng = np.random.default_rng(seed)
    n = 300
    c0 = lidar_list(n, seed=seed)
    c1 = dataclasses.replace(c0, positions_m=c0.positions_m * 1.001)
    keep = rng.random(n) > 0.2
    label = np.where(rng.random(n) < 0.1, Effect.MOVED, np.where(rng.random(n) < 0.3, Effect.ATTENUATED,
                                                                 Effect.KEPT)).astype(np.uint8)
    pos = c1.positions_m.copy()
    pos[label == Effect.MOVED] *= 0.5
    intensity = c1.fields["intensity"] - 3 * (label == Effect.ATTENUATED)
    c2 = dataclasses.replace(c1, positions_m=pos).with_fields(intensity=intensity.astype(np.float32)).select(keep)
    added = rng.uniform(2, 20, (5, 3))
    c2 = c2.concat(added, {"intensity": np.full(5, 7, np.float32)})
    c2 = with_effect_codes(c2, np.concatenate([label[keep], np.full(5, Effect.ADDED, np.uint8)]))
    c3 = c2.with_fields(intensity=c2.fields["intensity"] * 0.5)
    assert c3.positions_m is c2.positions_m
    steps = [compare(c0, c1), compare(c1, c2), compare(c2, c3)]             # as apply_models does
    moves, attenuations = keep & (label == Effect.MOVED), keep & (label == Effect.ATTENUATED)
    assert steps[0]["removed"] == 0 and steps[0]["mean_intensity_change"] == 0.0
    assert steps[1]["removed"] == n - keep.sum() and steps[1]["added"] == 5
    assert steps[1]["moved"] == moves.sum() and steps[1]["attenuated"] == attenuations.sum()
    assert steps[1]["mean_intensity_change"] == pytest.approx(-3 * attenuations.sum() / (keep.sum() - moves.sum()))
    expected_index = np.where(keep, np.cumsum(keep) - 1, -1)
    index, moved = correspondence(c0, c3)
    assert np.array_equal(index, expected_index) and np.array_equal(moved, moves)
    in_place = keep & ~moves
    final = c3.fields["intensity"][expected_index[in_place]].astype(np.float64)
    m = compare(c0, c3)
    assert m["mean_intensity_change"] == pytest.approx(np.mean(final - c0.fields["intensity"][in_place]), rel=1e-6)
    assert m["points_out"] == keep.sum() + 5 and m["removed"] == n - keep.sum()
    r = np.linalg.norm(c3.positions_m, axis=1)
    assert m["max_range_m_out"] == pytest.approx(r.max())
    assert m["points_per_10m_out"][: int(r.max() // 10) + 1] == np.bincount((r // 10).astype(int)).tolist()


def test_radar_snr_change_in_db():
    rng = np.random.default_rng(4)
    pos = rng.uniform(5, 80, (50, 3))
    snr = rng.uniform(10, 30, 50).astype(np.float32)
    before = PointCloud(pos, {"snr_db": snr}, "radar", profile=RadarProfile("r"))
    label = np.full(50, Effect.ATTENUATED, np.uint8)
    after = PointCloud(pos, {"snr_db": snr - 3.0}, "radar", profile=before.profile).select(snr > 12)
    m = compare(before, with_effect_codes(after, label[snr > 12]))
    assert m["mean_snr_change_db"] == pytest.approx(-3.0, abs=1e-5)
    assert m["removed"] == int(np.count_nonzero(snr <= 12))
    assert "mean_intensity_change" not in m


# --- the hook in apply_models -----------------------------------------------------------------------------------


def test_apply_models_records_step_metrics():
    c = lidar_list(400)
    models = [get_model("fog.lidar")(visibility_m=30.0)]
    out, records = apply_models(models, c, seed=1, key="k", sequence_id="s")
    m = records[0].metrics
    assert m == compare(c, out) and m["points_in"] == 400
    assert m["removed"] + m["moved"] + m["attenuated"] + m["kept"] == 400
    _, off = apply_models(models, c, seed=1, key="k", sequence_id="s", metrics=False)
    assert off[0].metrics == {}


def test_a_step_records_manifest_dict_is_its_asdict_with_the_metrics_handed_on():
    c = lidar_list(400)
    _, records = apply_models([get_model("fog.lidar")(visibility_m=30.0)], c, seed=1, key="k", sequence_id="s")
    entry, copied = records[0].as_entry(), dataclasses.asdict(records[0])
    assert entry == copied and list(entry) == list(copied) and entry["metrics"]["points_in"] == 400
    assert entry["metrics"] is records[0].metrics


def _fresh(cloud: PointCloud) -> PointCloud:
    """The same cloud in new arrays (nothing of it summarised yet)."""
    return dataclasses.replace(cloud, positions_m=cloud.positions_m.copy(), recorded=None,
                               fields={k: v.copy() for k, v in cloud.fields.items()},
                               effect=None if cloud.effect is None else cloud.effect.copy())


@pytest.mark.parametrize("chain", [("power.lidar", "fog.lidar"), ("fog.lidar", "rain.lidar")])
def test_a_chain_summarises_its_input_once_and_its_metrics_equal_a_fresh_computation(monkeypatch, chain):
    """The runner's whole-chain compare of the input it holds reuses the first step's summary of it (one cloud
    pass per step, although later steps' clouds note the input as ``recorded``), with the same metrics as clouds
    that were never summarised; the input's needs no cloud pass when a model noted its return geometry (the laser
    power its intensity sum too; after the weather step's counting only the sum is taken, by a loop of its own)."""
    import roadview_noise.metrics as metrics_module

    passes = []
    real_pass = metrics_module._cloud_pass
    monkeypatch.setattr(metrics_module, "_cloud_pass", lambda *a, **k: passes.append(1) or real_pass(*a, **k))
    c = lidar_list(400, seed=3)
    kwargs = {"power.lidar": {}, "fog.lidar": {"visibility_m": 30.0}, "rain.lidar": {"rain_rate_mm_per_h": 20.0}}
    models = [get_model(m)(**kwargs[m]) for m in chain]
    out, records = apply_models(models, c, seed=2, key="k", sequence_id="s")
    whole = compare(c, out)
    assert len(passes) == 2
    assert whole == compare(_fresh(c), _fresh(out))
    assert whole["points_in"] == records[0].metrics["points_in"] == 400


def test_steps_sharing_a_depth_map_give_the_contrast_of_a_fresh_one():
    rng = np.random.default_rng(5)
    depth = rng.uniform(0, 120, (40, 60)).astype(np.float32)
    depth[::9, ::7] = np.inf
    frames = [frame_of_codes(rng.integers(0, 65536, (40, 60)) / 65535, depth) for _ in range(3)]
    shared = [compare(frames[0], frames[1]), compare(frames[1], frames[2])]
    alone = [compare(*(dataclasses.replace(f, depth_m=depth.copy()) for f in pair))
             for pair in ((frames[0], frames[1]), (frames[1], frames[2]))]
    assert shared == alone
    assert shared[0]["rms_contrast_per_depth_bin_out"] != shared[1]["rms_contrast_per_depth_bin_out"]
