"""Where camera rain/snow particles streak: image motion per image position (models.md §2.2, §2.9).

A particle at pixel ``p = (u, v)`` and planar depth Z moving with ``v_rel = (v_x, v_y, v_z)`` (optical frame)
moves in the image at ``w(p)/Z`` px/s, ``w(p) = (f_x v_x − (u − c_x) v_z, f_y v_y − (v − c_y) v_z)``: the
derivative of ``u = f_x X/Z + c_x``; the exposure's end points ``P ∓ v_rel T/2`` give exactly ``w T / Z`` times
``1/(1 − (v_z T / 2Z)²)``. Without a ``v_z`` (no ego motion, no head wind) w is the same everywhere; with one it
vanishes at the focus of expansion and grows in proportion to the distance from it, so that far particles near
the focus of expansion stay points (unresolved) even at speed while the same particles near the border streak.

:func:`motion_bands` cuts the image into bands of the motion along the streak's major axis,
``max(|w_x|, |w_y|)`` (the splat's extent), for a reference fall speed (the number-weighted median class's): per
band and size class an upper bound of the streak length times Z (the band's upper edge, plus ``½|v_z|`` for a
particle anywhere in its pixel and ``f_y |v_t,i − v_t,ref|`` for its own fall speed, times T and the second-order
factor) gives the depth up to which a particle is drawn one by one there
(:func:`particles.resolved_depth_limits`), and the band's mean major-axis motion the variance of the per-pixel
draw beyond it (:func:`particles.unresolved_field`). Pixels whose band would reach ``min_extent · d_max`` are in a
last band where every visible particle is drawn one by one."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..types import CameraProfile
from .compiled import jit

MOTION_BANDS = 16             # bands of |w| below min_extent · d_max (each 1/16 of it wide)
VARIANCE_STRIDE_PX = 8        # pixel grid on which each band's mean major-axis motion is taken


class MotionBands(NamedTuple):
    """The image cut into bands of motion (see module docstring); band ``MOTION_BANDS`` is the last (every
    particle explicit). ``band`` (H, W) uint8 per pixel; per band and class (px·m, ×Z⁻¹ = px): ``bound`` an upper
    bound of the streak's motion anywhere in the band (inf in the last band), ``major`` the mean motion along the
    streak's major axis; ``rows`` (bands, H) the number of pixels of each band per image row; ``pixel`` the
    float32 constants of :func:`pixel_band` (f_x v_x, f_y v_y of the reference, c_x, c_y, v_z, 1/band width)."""

    band: np.ndarray
    bound: np.ndarray
    major: np.ndarray
    rows: np.ndarray
    pixel: np.ndarray


def motion_bands(profile: CameraProfile, exposure_s: float, v_rel: np.ndarray, number: np.ndarray,
                 d_min_m: float, d_max_m: float, min_extent_px: float) -> MotionBands | None:
    """:class:`MotionBands` for the per-class relative velocities ``v_rel`` ((classes, 3), optical frame, the
    fall speed in ``v_y``) and number densities ``number``, or None when the motion is the same over the whole
    image (``v_z = 0``) or every visible particle is drawn one by one (``min_extent_px = 0``)."""
    vz = float(v_rel[0, 2])
    if vz == 0.0 or min_extent_px <= 0.0:
        return None
    h, w = profile.height_px, profile.width_px
    cumulative = np.cumsum(number)
    ref = int(np.searchsorted(cumulative, 0.5 * cumulative[-1]))         # the number-weighted median class
    ax, ay = profile.fx_px * float(v_rel[ref, 0]), profile.fy_px * float(v_rel[ref, 1])
    width = min_extent_px * d_max_m / (MOTION_BANDS * exposure_s)        # px·m/s per band
    pixel = np.array([ax, ay, profile.cx_px, profile.cy_px, vz, 1.0 / width], np.float32)
    band = np.empty((h, w), np.uint8)
    _band_map_kernel(pixel, band)
    wx = pixel[0] - (np.arange(w, dtype=np.float32) - pixel[2]) * pixel[4]
    wy = pixel[1] - (np.arange(h, dtype=np.float32) - pixel[3]) * pixel[4]
    # the band's upper edge, plus the class's fall speed off the reference's, times T and the 2nd-order factor
    offset = profile.fy_px * np.abs(v_rel[:, 1] - v_rel[ref, 1])
    ratio = (0.5 * vz * exposure_s / d_min_m) ** 2                     # < 1 unless the nearest ones pass the lens
    second_order = 1.0 / (1.0 - ratio) if ratio < 1.0 else math.inf
    edge = width * np.arange(1, MOTION_BANDS + 1) + 0.5 * abs(vz)
    bound = np.full((MOTION_BANDS + 1, number.size), np.inf)
    bound[:-1] = exposure_s * second_order * (edge[:, None] + offset[None, :])
    # mean |w| along the major axis per band and class, on a grid of pixels (the band's bound where it has none)
    s = VARIANCE_STRIDE_PX
    sx, sy = np.abs(wx[s // 2::s]).astype(float), wy[s // 2::s].astype(float)
    grid_band = band[s // 2::s, s // 2::s].ravel()
    gx = np.broadcast_to(sx[None, :], (sy.size, sx.size)).ravel()
    gy = np.broadcast_to(sy[:, None], (sy.size, sx.size)).ravel()
    dy = profile.fy_px * (v_rel[:, 1] - v_rel[ref, 1])
    major = bound.copy()
    for b in range(MOTION_BANDS):
        on = grid_band == b
        if on.any():
            major[b] = exposure_s * np.maximum(gx[on][:, None], np.abs(gy[on][:, None] + dy[None, :])).mean(axis=0)
    per_row = np.bincount((band + np.arange(0, h * (MOTION_BANDS + 1), MOTION_BANDS + 1, dtype=np.int32)[:, None])
                          .ravel(), minlength=h * (MOTION_BANDS + 1)).reshape(h, MOTION_BANDS + 1).T.copy()
    for a in (band, bound, major, per_row, pixel):
        a.flags.writeable = False
    return MotionBands(band, bound, major, per_row, pixel)


@jit(error_model="numpy")
def pixel_band(pixel, row, col):                                             # pragma: no cover - compiled
    """The band of the pixel (row, col): ``|w|`` along the major axis (``pixel``: :class:`MotionBands`' constants)
    in band widths, the last band beyond."""
    ax, ay, cx, cy, vz, per_width = pixel
    wx = ax - (np.float32(col) - cx) * vz
    wy = ay - (np.float32(row) - cy) * vz
    return np.uint8(min(max(abs(wx), abs(wy)) * per_width, np.float32(MOTION_BANDS)))


@jit(error_model="numpy")
def _band_map_kernel(pixel, band):                                           # pragma: no cover - compiled
    """:func:`pixel_band` of every pixel into ``band`` (H, W)."""
    for row in range(band.shape[0]):
        for col in range(band.shape[1]):
            band[row, col] = pixel_band(pixel, row, col)


def band_volume(profile: CameraProfile, rows: np.ndarray, z_m: np.ndarray, bottom: np.ndarray) -> np.ndarray:
    """(bands, Z) volume (m³) of each band's part of the image frustum between the first and each planar depth of
    ``z_m`` (increasing), above the ground plane at the camera height: the rows whose centre is above ``bottom``, the
    ground's row at each Z (:func:`particles.bottom_row_px`, as :func:`particles.above_ground_volume_table`;
    trapezoids)."""
    cumulative = np.concatenate([np.zeros((rows.shape[0], 1)), np.cumsum(rows, axis=1)], axis=1)   # rows < r
    edge = np.arange(rows.shape[1] + 1, dtype=float)
    pixels = np.stack([np.interp(bottom + 0.5, edge, c) for c in cumulative])                      # (bands, Z)
    area = pixels * z_m ** 2 / (profile.fx_px * profile.fy_px)
    return np.concatenate([np.zeros((rows.shape[0], 1)),
                           np.cumsum(0.5 * (area[:, 1:] + area[:, :-1]) * np.diff(z_m), axis=1)], axis=1)
