"""Motion blur kernels (models.md §2.6): D3.5's radial blur in closed form against its iterated definition and the
b·r·√n oracle; the physical flow blur against the box lengths of forward motion and yaw."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from roadview_noise.physics.motion_blur import flow_blur, zoom_blur, zoom_blur_taps


def impulse(h, w, row, col):
    img = np.zeros((h, w, 1), np.float32)
    img[row, col] = 1.0
    return img


def spread(out, axis):
    """Mean and standard deviation of the output mass along an axis (0 rows, 1 columns)."""
    m = out[..., 0].sum(axis=1 - axis)
    x = np.arange(m.size)
    mean = (m * x).sum() / m.sum()
    return mean, math.sqrt((m * (x - mean) ** 2).sum() / m.sum())


def test_taps_are_the_binomial_expansion():
    scales, weights = zoom_blur_taps(0.002, 7)
    np.testing.assert_allclose(weights * 128, [1, 7, 21, 35, 35, 21, 7, 1])
    np.testing.assert_allclose(scales[[0, -1]], [0.998 ** 7, 1.002 ** 7])


@pytest.mark.parametrize("r_px", [300, 1000])
def test_radial_sd_is_b_r_sqrt_n(r_px):
    b, n = 0.002, 7
    h, w, cx, cy = 31, 2401, 1200, 15
    out = zoom_blur(impulse(h, w, cy, cx + r_px), (cx, cy), b, n)
    mean, sd = spread(out, axis=1)
    assert sd == pytest.approx(b * r_px * math.sqrt(n), rel=0.10)      # 5.3 px at 1000 px
    assert out[..., 0].sum() == pytest.approx(1.0, rel=0.02)
    assert spread(out, axis=0)[1] < 0.5                                # along the radius only


def test_closed_form_equals_d35_iterations():
    """D3.5: n times J ← ½ J(c + (1+b)(p − c)) + ½ J(c + (1−b)(p − c)), bilinear, here with reflect borders."""
    rng = np.random.default_rng(0)
    h, w = 240, 320
    img = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 16)  # smooth: interpolation ≈ exact
    c = (170.0, 101.0)
    b, n = 0.01, 5
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    j = img.copy()
    for _ in range(n):
        taps = [cv2.remap(j, (c[0] + s * (u - c[0])).astype(np.float32), (c[1] + s * (v - c[1])).astype(np.float32),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101) for s in (1 + b, 1 - b)]
        j = 0.5 * taps[0] + 0.5 * taps[1]
    out = zoom_blur(img[..., None], c, b, n)[..., 0]
    inner = (slice(20, -20), slice(20, -20))
    assert np.abs(out - j)[inner].max() < 0.01 * img.std()


def test_centre_and_constant_image_unchanged():
    rng = np.random.default_rng(1)
    img = rng.random((101, 151, 3)).astype(np.float32)
    out = zoom_blur(img, (75.0, 50.0), 0.002, 7)
    np.testing.assert_allclose(out[50, 75], img[50, 75], rtol=1e-6)
    flat = np.full((101, 151, 3), 0.37, np.float32)
    np.testing.assert_allclose(zoom_blur(flat, (75.0, 50.0), 0.01, 7), flat, rtol=1e-6)   # borders included


def test_physical_forward_motion_is_a_radial_box():
    f, r_px, v, t, z = 1000.0, 800, 20.0, 0.01, 10.0
    h, w, cx, cy = 31, 2001, 1000, 15
    stats = np.zeros(2)
    out = flow_blur(impulse(h, w, cy, cx + r_px), None, scene_depth_m=z, intrinsics=(f, f, cx, cy),
                    velocity_m_per_s=(0.0, 0.0, v), yaw_rate_rad_per_s=0.0, exposure_time_s=t, stats=stats)
    length = r_px * v * t / z                                           # 16 px, centred on the mid-exposure
    mean, sd = spread(out, axis=1)
    assert sd == pytest.approx(length / math.sqrt(12), rel=0.10)
    assert mean == pytest.approx(cx + r_px, abs=0.5)
    assert stats[1] == pytest.approx((w - 1 - cx) * v * t / z, rel=0.05)


def test_physical_yaw_blurs_horizontally_and_sky_only_by_yaw():
    f, omega, t = 1000.0, math.radians(30.0), 0.01                    # 5.2 px at the centre
    h, w, cx, cy = 41, 201, 100, 20
    img = impulse(h, w, cy, cx)
    out = flow_blur(img, np.full((h, w), np.inf, np.float32), scene_depth_m=0.0, intrinsics=(f, f, cx, cy),
                    velocity_m_per_s=(0.0, 0.0, 30.0), yaw_rate_rad_per_s=omega, exposure_time_s=t)
    assert spread(out, axis=1)[1] == pytest.approx(f * omega * t / math.sqrt(12), rel=0.10)
    assert spread(out, axis=0)[1] < 0.3
    still = flow_blur(img, np.full((h, w), np.inf, np.float32), scene_depth_m=0.0, intrinsics=(f, f, cx, cy),
                      velocity_m_per_s=(0.0, 0.0, 30.0), yaw_rate_rad_per_s=0.0, exposure_time_s=t)
    np.testing.assert_array_equal(still, img)                           # sky: no translation flow


def test_sublattice_geometry_matches_the_full_grid():
    """A plane given as one 2×2 phase (stride 2) samples the same image positions as the full grid."""
    rng = np.random.default_rng(3)
    full = cv2.GaussianBlur(rng.random((120, 160)).astype(np.float32), (0, 0), 8)[..., None]
    c = (81.0, 57.0)
    ref = zoom_blur(full, c, 0.01, 7)
    sub = zoom_blur(np.ascontiguousarray(full[1::2, 0::2]), c, 0.01, 7, stride=2, offset=(0, 1))
    inner = (slice(10, -10), slice(10, -10))
    assert np.abs(sub - ref[1::2, 0::2])[inner].max() < 0.02 * full.std()
