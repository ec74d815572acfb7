"""Brown–Conrady pull map and its Newton forward map (models.md §2.5) against OpenCV's camera model and the D3.5
pull-radius oracle."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roadview_noise.physics.brown_conrady import COEFFICIENTS, BrownConrady

D35 = (1e-7,) + (0.0,) * 11


def reference(width=1936, height=1464, coefficients=D35):
    """D3.5 pixel units: f = 1 px, centre the image centre."""
    return BrownConrady(coefficients, ((width - 1) / 2, (height - 1) / 2), (1.0, 1.0))


@pytest.mark.parametrize("r_px, pulled_px", [(500, 512.5), (1000, 1100.0)])
def test_d35_pull_radius(r_px, pulled_px):
    d = reference()
    for angle in np.linspace(0, 2 * np.pi, 7):
        xd, yd = d.distort(np.array([r_px * np.cos(angle)]), np.array([r_px * np.sin(angle)]))
        assert np.hypot(xd, yd)[0] == pytest.approx(pulled_px, rel=1e-12)


def test_corner_factor_and_fixed_centre():
    xd, yd = reference().distort(np.array([968.0]), np.array([732.0]))   # image corner, r = 1213.6 px
    assert np.hypot(xd, yd)[0] / np.hypot(968.0, 732.0) == pytest.approx(1.1473, abs=1e-4)
    odd = reference(101, 77).pull_map(77, 101)                  # odd size: the centre is a pixel
    assert (odd.map_x[38, 50], odd.map_y[38, 50]) == (50.0, 38.0)
    assert odd.shape == (77, 101)


def test_matches_opencv_projectpoints_with_tangential_and_prism():
    """Every term of the model against cv2.projectPoints (OpenCV's k1,k2,p1,p2,k3,k4,k5,k6,s1..s4 order)."""
    coeffs = dict(k1=-0.21, k2=0.05, k3=-0.004, k4=0.03, k5=-0.01, k6=0.002, p1=0.0012, p2=-0.0008,
                  s1=0.0015, s2=-0.0004, s3=-0.001, s4=0.0003)
    fx, fy, cx, cy = 1137.4, 1150.2, 960.3, 725.8
    d = BrownConrady(tuple(coeffs[k] for k in COEFFICIENTS), (cx, cy), (fx, fy))
    h, w = 1464, 1936
    warp = d.pull_map(h, w)
    rng = np.random.default_rng(0)
    u, v = rng.integers(0, w, 500), rng.integers(0, h, 500)
    obj = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(500)], axis=1)
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    dist = np.array([coeffs[n] for n in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")])
    img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), k, dist)
    np.testing.assert_allclose(warp.map_x[v, u], img[:, 0, 0], atol=2e-3)   # float32 maps
    np.testing.assert_allclose(warp.map_y[v, u], img[:, 0, 1], atol=2e-3)


@settings(max_examples=40, deadline=None)
@given(k1=st.floats(-0.3, 0.5), p1=st.floats(-0.01, 0.01), p2=st.floats(-0.01, 0.01),
       s1=st.floats(-0.01, 0.01), s3=st.floats(-0.01, 0.01))
def test_forward_inverts_the_pull_map(k1, p1, p2, s1, s3):
    """Sources of output pixels map back to those pixels (forward ∘ pull = identity, far below the 0.05 px
    acceptance); input points no output pixel sees (beyond the largest pull radius of negative k1) get NaN."""
    c = (k1,) + (0.0,) * 5 + (p1, p2, s1, 0.0, s3, 0.0)
    d = BrownConrady(c, (640.0, 360.0), (900.0, 900.0))
    rng = np.random.default_rng(1)
    p = np.stack([rng.uniform(0, 1280, 300), rng.uniform(0, 720, 300)], axis=1)
    q = np.stack(d.distort((p[:, 0] - 640) / 900, (p[:, 1] - 360) / 900), axis=1) * 900 + (640, 360)
    assert np.abs(d.pull_map(721, 1281).forward(q) - p).max() < 1e-4
    if k1 < -0.1 and max(abs(p1), abs(p2), abs(s1), abs(s3)) < 1e-3:
        r_max = 2 / 3 / np.sqrt(-3 * k1) * 900                 # largest radius the radial pull reaches
        unseen = np.array([[640 + 1.05 * r_max, 360.0]])
        assert np.isnan(d.undistort_px(unseen)).all()
        assert d.pull_map(721, 1281).forward(unseen)[0, 0] > 1281     # annotations: beyond the right edge


def test_d35_round_trip_through_the_sampled_map():
    """Distort/undistort round trip through the float32 map itself (what annotations see): < 0.05 px."""
    h, w = 1464, 1936
    warp = reference(w, h).pull_map(h, w)
    rng = np.random.default_rng(2)
    out_px = np.stack([rng.uniform(0, w - 1, 400), rng.uniform(0, h - 1, 400)], axis=1)
    src = np.stack([cv2.remap(m, out_px[:, :1].astype(np.float32), out_px[:, 1:].astype(np.float32),
                              cv2.INTER_LINEAR)[:, 0] for m in (warp.map_x, warp.map_y)], axis=1)
    assert np.abs(warp.forward(src) - out_px).max() < 0.05


def test_coefficient_count_checked():
    with pytest.raises(ValueError, match="12 coefficients"):
        BrownConrady((1e-7,), (0.0, 0.0), (1.0, 1.0))


def test_points_beyond_the_fold_go_to_the_image_edge():
    """k1 = −0.3 (normalised) never pulls from beyond r = 2/(3√0.9) = 0.70: such input points have no output
    position (NaN from the physics), and the annotation forward map sends them outside the image."""
    d = BrownConrady((-0.3,) + (0.0,) * 11, (640.0, 360.0), (900.0, 900.0))
    unseen = np.array([[640 + 0.75 * 900, 360.0], [640.0, 360 - 0.72 * 900]])
    assert np.isnan(d.undistort_px(unseen)).all()
    out = d.pull_map(721, 1281).forward(unseen)
    assert out[0, 0] > 1281 and out[1, 1] < 0 and np.isfinite(out).all()
