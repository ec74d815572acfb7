"""Vertical objects standing on the flat ground (depth/stixels.py) on scenes ray-cast here: a textured road, a box
standing on it facing the camera, a blue sky — the range of every pixel known exactly."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from roadview_noise.depth.ground_plane import ground_plane_range
from roadview_noise.depth.stixels import object_range

HEIGHT_M = 1.5
SKY_M = 100.0
BOX = {"z_m": 12.0, "left_m": -2.0, "right_m": 1.0, "top_m": 2.5}      # its face: the plane 12 m ahead, level frame


def _scene(width_px: int, height_px: int, f_px: float, pitch_deg: float, box: bool = True, seed: int = 0):
    """(srgb, range_m, what) of the scene seen by a camera HEIGHT_M above the road pitched down by pitch_deg;
    what: 0 sky, 1 road, 2 box face."""
    cx, cy = (width_px - 1) / 2, (height_px - 1) / 2
    th = math.radians(pitch_deg)
    x = (np.arange(width_px) - cx) / f_px
    y = (np.arange(height_px) - cy) / f_px
    down = (y * math.cos(th) + math.sin(th))[:, None] * np.ones((1, width_px))
    fwd = (math.cos(th) - y * math.sin(th))[:, None] * np.ones((1, width_px))
    side = np.broadcast_to(x[None, :], down.shape)
    norm = np.sqrt(1 + x[None, :] ** 2 + y[:, None] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_road = np.where(down > 0, HEIGHT_M / down, np.inf)               # along the ray (x, y, 1)
        t_box = np.where(fwd > 0, BOX["z_m"] / fwd, np.inf)
    hit_x, hit_up = t_box * side, HEIGHT_M - t_box * down                  # lateral, height above the road
    on_box = box & (hit_x >= BOX["left_m"]) & (hit_x <= BOX["right_m"]) & (hit_up >= 0) & (hit_up <= BOX["top_m"])
    t_box = np.where(on_box, t_box, np.inf)
    what = np.where(t_box < t_road, 2, np.where(np.isfinite(t_road), 1, 0))
    range_m = np.where(what == 2, t_box, np.where(what == 1, t_road, np.inf)) * norm
    rng = np.random.default_rng(seed)
    grain = rng.normal(0.0, 0.02, down.shape)                              # asphalt grain
    srgb = np.empty(down.shape + (3,), np.float32)
    srgb[what == 1] = (0.35 + grain[what == 1])[:, None] * [1.0, 1.0, 0.98]
    srgb[what == 2] = (np.array([0.7, 0.25, 0.2]) + 0.3 * grain[what == 2][:, None])
    srgb[what == 0] = [0.55, 0.7, 0.95]
    return np.clip(srgb, 0, 1), range_m, what


def _contact_bounds(what: np.ndarray, f_px: float, pitch_deg: float) -> tuple[float, float]:
    """The box face's horizontal distance as the flat ground gives it one pixel row above and below the face's
    lowest row (the contact row's precision)."""
    height_px = what.shape[0]
    rows = np.flatnonzero((what == 2).any(axis=1))
    th = math.radians(pitch_deg)
    out = []
    for r in (rows.max() - 1, rows.max() + 1):
        y = (r - (height_px - 1) / 2) / f_px
        out.append(HEIGHT_M * (math.cos(th) - y * math.sin(th)) / (y * math.cos(th) + math.sin(th)))
    return min(out), max(out)


def _inner(face: np.ndarray, margin_px: int = 2) -> np.ndarray:
    """The face without its outermost columns: the 5×5 majority vote on the road look rounds the box's bottom
    corners by up to 2 px (at the working resolution)."""
    cols = np.flatnonzero(face.any(axis=0))
    inner = face.copy()
    inner[:, : cols.min() + margin_px] = False
    inner[:, cols.max() + 1 - margin_px:] = False
    return inner


@pytest.mark.parametrize("pitch_deg", [0.0, 2.0])
def test_box_face_at_its_contact_distance_within_a_pixel_row(pitch_deg):
    w, h, f = 480, 300, 360.0
    srgb, truth, what = _scene(w, h, f, pitch_deg)
    depth, notes = object_range(srgb, (f, f, (w - 1) / 2, (h - 1) / 2), camera_height_m=HEIGHT_M,
                                pitch_rad=math.radians(pitch_deg), sky_distance_m=SKY_M)
    face = what == 2
    lo, hi = _contact_bounds(what, f, pitch_deg)
    inner = _inner(face)
    ratio = depth[inner] / truth[inner]                        # range ∝ the horizontal distance along a pixel ray
    assert lo / BOX["z_m"] - 1e-4 <= ratio.min() and ratio.max() <= hi / BOX["z_m"] + 1e-4
    assert hi / lo < 1.05                                      # ± a row is < 5 % of the distance here
    horizon_row = (h - 1) / 2 - f * math.tan(math.radians(pitch_deg))
    above = face & (np.arange(h)[:, None] < horizon_row)
    assert above.sum() > 1000                                  # the face reaches above the horizon …
    flat = ground_plane_range((f, f, (w - 1) / 2, (h - 1) / 2), w, h, camera_height_m=HEIGHT_M,
                              pitch_rad=math.radians(pitch_deg), sky_distance_m=SKY_M)
    assert (flat[above] == SKY_M).all()                        # … where the flat prior puts it at sky distance
    assert notes["objects"] is True and notes["object_columns"] > 0


def test_road_stays_the_flat_ground_and_sky_stays_far():
    w, h, f = 480, 300, 360.0
    srgb, truth, what = _scene(w, h, f, 0.0)
    k = (f, f, (w - 1) / 2, (h - 1) / 2)
    depth, notes = object_range(srgb, k, camera_height_m=HEIGHT_M, sky_distance_m=SKY_M)
    flat = ground_plane_range(k, w, h, camera_height_m=HEIGHT_M, sky_distance_m=SKY_M)
    road = (what == 1) & (truth < 60.0)
    below_box = road & ((what == 2).cumsum(axis=0) > 0)       # road in the box's columns, below it
    assert below_box.sum() > 1000
    np.testing.assert_array_equal(depth[road], flat[road])
    assert (depth[what == 0] == SKY_M).all()
    assert notes["sky_fraction"] == pytest.approx((what == 0).mean(), abs=0.01)


def test_no_objects_gives_the_flat_prior():
    w, h, f = 480, 300, 360.0
    srgb, truth, what = _scene(w, h, f, 0.0, box=False)
    k = (f, f, (w - 1) / 2, (h - 1) / 2)
    depth, _ = object_range(srgb, k, camera_height_m=HEIGHT_M, sky_distance_m=SKY_M)
    np.testing.assert_array_equal(depth, ground_plane_range(k, w, h, camera_height_m=HEIGHT_M, sky_distance_m=SKY_M))


def test_large_frames_are_exact_to_the_reduction_factor():
    """1600 × 900 (nuScenes' size) is worked on at half resolution: the contact row is exact to 2 rows."""
    w, h, f = 1600, 900, 1266.0
    srgb, truth, what = _scene(w, h, f, 0.0)
    depth, notes = object_range(srgb, (f, f, (w - 1) / 2, (h - 1) / 2), camera_height_m=HEIGHT_M)
    face = what == 2
    bottom = np.flatnonzero(face.any(axis=1)).max()
    y = (np.array([bottom - 2, bottom + 2]) - (h - 1) / 2) / f
    lo, hi = sorted(HEIGHT_M / y)
    ratio = depth[_inner(face, 4)] / truth[_inner(face, 4)]
    assert lo / BOX["z_m"] - 1e-4 <= ratio.min() and ratio.max() <= hi / BOX["z_m"] + 1e-4
    near_face = cv2.dilate(face.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)   # the 2-px blocks
    assert (depth[(what == 0) & ~near_face] == SKY_M).all()


def test_deterministic_and_input_untouched():
    srgb, _, _ = _scene(320, 200, 240.0, 1.0, seed=3)
    before = srgb.copy()
    k = (240.0, 240.0, 159.5, 99.5)
    a, notes_a = object_range(srgb, k, camera_height_m=HEIGHT_M, pitch_rad=math.radians(1.0))
    b, notes_b = object_range(srgb.copy(), k, camera_height_m=HEIGHT_M, pitch_rad=math.radians(1.0))
    assert a.tobytes() == b.tobytes() and notes_a == notes_b
    np.testing.assert_array_equal(srgb, before)


def test_no_road_in_view_keeps_the_flat_prior():
    """A camera looking up (the ego lane 4–15 m ahead out of view): nothing is learnt, the flat prior stays."""
    srgb, _, _ = _scene(320, 200, 240.0, -30.0)
    k = (240.0, 240.0, 159.5, 99.5)
    depth, notes = object_range(srgb, k, camera_height_m=HEIGHT_M, pitch_rad=math.radians(-30.0))
    assert notes["road_seed_pixels"] == 0
    np.testing.assert_array_equal(depth, ground_plane_range(k, 320, 200, camera_height_m=HEIGHT_M,
                                                            pitch_rad=math.radians(-30.0)))


def test_bad_geometry_is_refused():
    with pytest.raises(ValueError, match="camera_height_m"):
        object_range(np.zeros((10, 10, 3), np.float32), (10.0, 10.0, 5.0, 5.0), camera_height_m=0.0)
