"""sRGB transfer function (IEC 61966-2-1) against published values and its own inverse."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.physics import srgb


def test_published_values():
    # IEC 61966-2-1: the segments meet at linear 0.0031308 / encoded 0.04045; sRGB 0.5 is linear 0.21404;
    # 18 % grey encodes to 0.46135 (code 118)
    assert srgb.encode(0.0031308) == pytest.approx(0.04045, abs=1e-6)
    assert srgb.decode(0.5) == pytest.approx(0.214041, abs=1e-6)
    assert srgb.encode(0.18) == pytest.approx(0.461356, abs=1e-6)
    assert srgb.linear_to_code(np.array([0.18]))[0] == 118
    np.testing.assert_allclose(srgb.encode(np.array([0.0, 1.0])), [0.0, 1.0], atol=1e-12)


def test_encode_decode_inverse():
    v = np.linspace(0, 1, 10001)
    np.testing.assert_allclose(srgb.decode(srgb.encode(v)), v, atol=1e-12)


@pytest.mark.parametrize("bits", [8, 16])
def test_every_code_round_trips(bits):
    codes = np.arange(2 ** bits).astype(np.uint8 if bits == 8 else np.uint16)
    linear = srgb.code_to_linear(codes, bits)
    assert linear.dtype == np.float32 and np.all(np.diff(linear) > 0)
    np.testing.assert_array_equal(srgb.linear_to_code(linear, bits), codes)


def test_fast_codes_match_float64_rounding():
    v = np.random.default_rng(3).uniform(-0.1, 1.1, 1_000_000)
    fast = srgb.linear_to_code(v).astype(int)
    exact = np.rint(255 * srgb.encode(np.clip(v, 0, 1))).astype(int)
    assert np.abs(fast - exact).max() <= 1
    assert np.mean(fast != exact) < 1e-4          # only values within float32 rounding of a code boundary


def test_clips_out_of_range():
    np.testing.assert_array_equal(srgb.linear_to_code(np.array([-3.0, 0.0, 1.0, 7.0])), [0, 0, 255, 255])


def test_rejects_wrong_width_or_dtype():
    with pytest.raises(ValueError):
        srgb.linear_to_code(np.zeros(3), bits=12)
    with pytest.raises(ValueError):
        srgb.code_to_linear(np.zeros(3, dtype=np.uint16), bits=8)


# --- table look-ups (issue 19): exact, strided, codes kept with an unchanged frame -----------------------------------


@pytest.mark.parametrize("bits", [8, 16])
def test_table_codes_are_the_exact_rounding_at_every_decision_level(bits):
    # the code steps at T_c = decode((c + ½)/M); float32 values at, just below and just above every T_c must land
    # on the side the float64 formula puts them (a code is monotone in v, so this covers every value)
    full = 2 ** bits - 1
    levels = srgb.decode((np.arange(full) + 0.5) / full)
    t32 = levels.astype(np.float32)
    v = np.concatenate([t32, np.nextafter(t32, np.float32(0)), np.nextafter(t32, np.float32(2))])
    expected = np.searchsorted(levels, v.astype(np.float64), side="right")
    np.testing.assert_array_equal(srgb.linear_to_code(v, bits).astype(np.int64), expected)
    u = np.random.default_rng(bits).random(200_000).astype(np.float32)
    assert np.abs(srgb.linear_to_code(u, bits) - full * srgb.encode(u.astype(np.float64))).max() <= 0.5 + 1e-9


def test_special_values():
    v = np.array([np.nan, -np.inf, -0.0, 0.0, np.inf, 1.0, np.nextafter(np.float32(1), np.float32(0))], np.float32)
    np.testing.assert_array_equal(srgb.linear_to_code(v), [0, 0, 0, 0, 255, 255, 255])


def test_strided_views_need_no_copy_and_give_the_same_codes():
    rgb = np.random.default_rng(5).random((7, 9, 3)).astype(np.float32)
    np.testing.assert_array_equal(srgb.linear_to_code(rgb[..., ::-1]), srgb.linear_to_code(rgb)[..., ::-1])
    bgr = srgb.linear_to_code(rgb)[..., ::-1]
    np.testing.assert_array_equal(srgb.code_to_linear(bgr), srgb.code_to_linear(np.ascontiguousarray(bgr)))
    np.testing.assert_array_equal(srgb.linear_to_code(rgb[:, 1]), srgb.linear_to_code(rgb)[:, 1])   # 2-D


def test_an_unchanged_frame_returns_its_own_codes_and_cannot_change():
    codes = np.random.default_rng(6).integers(0, 256, (5, 4, 3), dtype=np.uint8)
    linear = srgb.code_to_linear(codes)
    assert srgb.linear_to_code(linear) is codes and not linear.flags.writeable
    with pytest.raises(ValueError):
        linear *= 2                                   # read-only: the kept codes can never go stale
    changed = linear * np.float32(0.5)                # any change is a new array, converted for real
    assert srgb.attached_codes(changed, 8) is None
    np.testing.assert_array_equal(srgb.linear_to_code(changed), srgb.linear_to_code(changed.copy()))
    assert srgb.attached_codes(linear, 16) is None    # other bit depth: converted


# --- 8-bit direct table: every bucket, every pattern class; BGR in and out (issue 19) --------------------------------


def _reference_codes(v: np.ndarray, bits: int) -> np.ndarray:
    """The float64 definition: the number of decision levels at or below the clipped value; NaN → 0."""
    full = 2 ** bits - 1
    levels = srgb.decode((np.arange(full) + 0.5) / full)
    with np.errstate(invalid="ignore"):                   # signalling NaN payloads
        x = np.clip(np.nan_to_num(v.astype(np.float64), nan=0.0), 0.0, 1.0)
    return np.searchsorted(levels, x, side="right")


def test_8bit_codes_are_exact_for_every_float32():
    # the code is monotone in v and a bucket of the table holds at most one decision level, so checking the first
    # and last value of every bucket from 0 to +inf plus the values at and beside every level checks every float32
    table, levels = srgb.encode8_table()
    starts = np.arange((0x7F800000 >> 12) + 1, dtype=np.uint32) << np.uint32(12)
    ends = starts + np.uint32(4095)
    level_values = levels[:-1].view(np.float32)
    beside = np.concatenate([level_values, np.nextafter(level_values, np.float32(0)),
                             np.nextafter(level_values, np.float32(2))])
    for v in (starts[:-1].view(np.float32), ends[:-1].view(np.float32), beside):
        np.testing.assert_array_equal(srgb.linear_to_code(v).astype(np.int64), _reference_codes(v, 8))


@pytest.mark.parametrize("bits", [8, 16])
def test_codes_of_random_bit_patterns_negatives_infinities_and_nan(bits):
    patterns = np.random.default_rng(11).integers(0, 2 ** 32, 2_000_000, dtype=np.uint64).astype(np.uint32)
    patterns[:6] = [0x7F800000, 0x7F800001, 0x7F800FFF, 0x7F801000, 0xFF800000, 0x80000001]   # ±inf, NaN by +inf
    v = patterns.view(np.float32)                         # every sign, exponent, NaN payload
    np.testing.assert_array_equal(srgb.linear_to_code(v, bits).astype(np.int64), _reference_codes(v, bits))
    u = np.random.default_rng(12).random(2_000_000).astype(np.float32)
    np.testing.assert_array_equal(srgb.linear_to_code(u, bits).astype(np.int64), _reference_codes(u, bits))


@pytest.mark.parametrize("bits", [8, 16])
def test_bgr_codes_are_the_rgb_codes_reversed(bits):
    rgb = np.random.default_rng(13).uniform(-0.1, 1.1, (31, 17, 3)).astype(np.float32)
    bgr = srgb.linear_to_code(rgb, bits, bgr=True)
    assert bgr.flags.c_contiguous
    np.testing.assert_array_equal(bgr, srgb.linear_to_code(rgb, bits)[..., ::-1])
    with pytest.raises(ValueError, match="RGB"):
        srgb.linear_to_code(rgb[..., 0], bits, bgr=True)


def test_kept_codes_come_back_in_bgr_order_without_a_copy():
    bgr = np.random.default_rng(14).integers(0, 256, (6, 5, 3), dtype=np.uint8)   # as OpenCV decodes a file
    linear = srgb.code_to_linear(bgr[..., ::-1])
    np.testing.assert_array_equal(linear, srgb.code_to_linear(np.ascontiguousarray(bgr[..., ::-1])))
    assert np.shares_memory(srgb.linear_to_code(linear, bgr=True), bgr)
    np.testing.assert_array_equal(srgb.linear_to_code(linear, bgr=True), bgr)


@pytest.mark.parametrize("width", [1, 3, 5, 7, 333])
def test_8bit_decode_four_codes_per_load_matches_the_table_in_both_channel_orders(width):
    # odd widths: rows start at odd bytes and the frame's length is no multiple of 4 or 12 (the tails); the table
    # indexed by NumPy is the reference, RGB codes and OpenCV's BGR seen as RGB
    codes = np.random.default_rng(width).integers(0, 256, (9, width, 3), dtype=np.uint8)
    expected = srgb.decode_table(8)[codes]
    np.testing.assert_array_equal(srgb.code_to_linear(codes), expected)
    np.testing.assert_array_equal(srgb.code_to_linear(np.ascontiguousarray(codes[..., ::-1])[..., ::-1]), expected)
    np.testing.assert_array_equal(srgb.code_to_linear(codes[:, ::2]), expected[:, ::2])     # strided: plain kernel
    row = codes[4].reshape(-1)[1:]                                                           # starts at an odd byte
    np.testing.assert_array_equal(srgb.code_to_linear(row), srgb.decode_table(8)[row])
