"""8-bit BGR codes of linear frames (``srgb.linear_to_code(..., bgr=True)``: JPEG compression after a weather step,
the 8-bit writer), which read the float32 values two at a time: every channel, pixel count and memory offset gives
the exact codes in reversed channel order."""

import numpy as np
import pytest

from roadview_noise.physics import srgb


def _reference_bgr(v: np.ndarray) -> np.ndarray:
    """Exact 8-bit codes (float64 decision levels, NaN → 0, clipped), channel order reversed."""
    levels = srgb.decode((np.arange(255) + 0.5) / 255)
    with np.errstate(invalid="ignore"):
        x = np.clip(np.nan_to_num(v.astype(np.float64), nan=0.0), 0.0, 1.0)
    return np.searchsorted(levels, x, side="right")[..., ::-1]


def _pixels(values: np.ndarray, width: int) -> np.ndarray:
    """``values`` as an (H, width, 3) frame, the last pixel row padded with zeros."""
    n = -(-values.size // (3 * width)) * 3 * width
    return np.concatenate([values, np.zeros(n - values.size, np.float32)]).reshape(-1, width, 3)


def test_every_bucket_edge_and_decision_level_in_every_channel():
    table, levels = srgb.encode8_table()
    starts = np.arange((0x7F800000 >> 12) + 1, dtype=np.uint32) << np.uint32(12)
    level_values = levels[:-1].view(np.float32)
    values = np.concatenate([starts.view(np.float32), (starts[:-1] + np.uint32(4095)).view(np.float32),
                             level_values, np.nextafter(level_values, np.float32(0)),
                             np.nextafter(level_values, np.float32(2))])
    for shift in range(3):                                # each value once in R, G and B
        frame = _pixels(np.roll(values, shift), 7)        # 7 pixels a row: pairs of floats straddle pixels
        np.testing.assert_array_equal(srgb.linear_to_code(frame, bgr=True), _reference_bgr(frame))


@pytest.mark.parametrize("shape", [(1, 1), (1, 2), (1, 3), (3, 5), (4, 4), (17, 31)])
@pytest.mark.parametrize("offset", [0, 1])
def test_random_bit_patterns_any_pixel_count_and_alignment(shape, offset):
    n = shape[0] * shape[1] * 3
    bits = np.random.default_rng(n + offset).integers(0, 2 ** 32, n + offset, dtype=np.uint64).astype(np.uint32)
    bits[offset:offset + 4] = [0x7F800000, 0x7FC00000, 0xFF800000, 0x3F800000][:min(4, n)]   # +inf, NaN, −inf, 1
    frame = bits.view(np.float32)[offset:].reshape(*shape, 3)    # offset 1: the uint64 reads are not 8-byte aligned
    got = srgb.linear_to_code(frame, bgr=True)
    assert got.flags.c_contiguous and got.dtype == np.uint8
    np.testing.assert_array_equal(got, _reference_bgr(frame))
