"""Falling rain drops and snowflakes seen by a camera (models.md §2.2, §2.3, §2.9; Garg & Nayar 2007).

One renderer serves rain and snow; they differ only in size distribution, fall speed and particle radiance.

Geometry. Particles are a marked Poisson process in the camera frustum above the ground plane (models.md §2.2
[PROP]): per 0.1 mm size class i a Poisson count with mean ``n_i · V_i`` (no floor bias), the planar depth Z by
inverse CDF of the slab volume (∝ Z² until the ground enters the image) on ``[d_min, Z_i]``, then a uniform image
position above the ground (flat ground at the camera height, optical axis horizontal) — exactly a uniform volume
density. The sampled point is the particle's position at mid-exposure; it moves with the relative velocity
``v_rel = v_particle + wind − ego`` (§2.9: its horizontal velocity equals the steady wind, because its
relaxation time ``v_t/g`` is much shorter than its fall), so the streak joins the projections (intrinsics K) of
``P ∓ v_rel T/2``. With no wind and no ego motion this is §2.2's vertical streak of length ``v T f / Z``.

Photometry. A pixel's opacity is the fraction of the exposure during which the particle covers it, weighted by
the covered fraction of the pixel: ``α = (1/T) ∫ a(t) dt``. This is §2.2's ``τ/T`` (τ = time the drop covers
the pixel) generalised to partial coverage: ``α ≤ 1`` (τ ≤ T), and the opacity summed over the pixels is exactly
the particle's image area ``(π/4) D² f_x f_y k / Z²`` (k = range/Z). §2.2 counts a pixel as covered whenever the
drop touches it, which over-states a sub-pixel drop's opacity by ``(1 + D_px)/D_px``. The footprint is the
particle's image (``D f/Z``) blurred by the defocus disk ``c = f²|Z − Z_f| / (N Z (Z_f − f) p)`` (§2.2 [PROP];
focus at infinity: ``f²/(N Z p)``), which spreads near particles and lowers their opacity.

Rasterisation (geometry vectorised in NumPy, the per-pixel accumulation in the numba kernel
:func:`splat_streaks`, one pass over the particles). A streak is a segment of uniform line density lengthened by
its footprint, integrated exactly over the pixels it crosses along its major axis and split linearly between the
two nearest pixels across it (Wu-style anti-aliasing). Particles whose footprint
exceeds ~2.7 px go to a buffer at scale s = 2, 4, … px (chosen so that the 2-tap split plus bilinear upsampling
has the second moment of the footprint disk across the streak), upsampled and added. Each pixel sample is tested
against the scene range at its nearest pixel (metres against metres), so streaks are cut at occluding edges.
Overlapping streaks are summed and clipped to 1 (§2.2).

Hybrid far field (models.md §2.2 [PROP]). A particle is explicit only where it can be seen one by one: the
expected peak pixel opacity of its streak must reach ``min_opacity`` (small far drops are invisible individually
but numerous — 3.5·10⁷ in the 0.5–30 m frustum of the Lucid camera at 50 mm/h, 1.5·10⁴ of them explicit). All others — fainter particles, those nearer than ``d_min`` and all beyond
``d_max`` — form a homogeneous veil with the same particles' extinction ``σ = Σ n_i (π/4) D_i²``: the geometric
shadow, Q = 1, because a camera pixel collects the forward diffraction lobe (λ/D < 1 mrad for millimetre
particles), the "extinction paradox" of Bohren & Huffman §4.4; this also makes the veil the exact mean of the
explicit particles it replaces. The veil's path radiance is the particles' radiance S (Koschmieder with A = S),
so the mean image does not depend on ``min_opacity``; only the texture of the sub-threshold particles is lost.

Unresolved particles. Of the visible ones, those whose streak (motion + footprint) spans less than
``min_extent_px`` (1 px: a point, whose only trace is the opacity it adds to one or two pixels) are not drawn one
by one but per pixel: their summed opacity in a pixel is a compound-Poisson sum whose mean (the same optical depth
as the veil's) and variance follow in closed form from the size classes, the depth slabs and the splat's pixel
shares (:func:`unresolved_field`); each pixel draws a Poisson count with both moments matched. Snow at 3.03 mm/h
on the Lucid frame: 0.26 M particles drawn one by one instead of 1.2 M, 0.97 M unresolved. Under ego motion (or
head wind) the streak length depends on the image position — far particles near the focus of expansion stay
points — so the split is made per band of image motion (:mod:`.streak_motion`, :func:`band_tables`) where that
costs less than the image-wide split (``COST_*``): at 5 m/s 0.41 M of the 1.23 M visible flakes are unresolved.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import lru_cache
from typing import Callable, NamedTuple

import cv2
import numpy as np
from scipy.special import pdtr, pdtrc

from ..profiles.camera import fit_to_image
from ..table_cache import disk_cached
from ..types import CameraProfile, Conditions
from ..units import ray_factor
from .cfa import SiteLayout
from .dsd import BRANDES_SNOW_GAMMA, gamma_dsd, marshall_palmer, snowfall
from .fall_speed import atlas_ulbrich_m_per_s
from .compiled import jit
from .photometry import blend_operands, capped, frame_depth_m
from .sensor_noise import uniform_bits
from .streak_motion import MotionBands, band_volume, motion_bands, pixel_band

IMAGING_Q_EXT = 1.0           # geometric shadow (see module docstring)
CLASS_WIDTH_MM = 0.1
FINE_STEP_MM = 0.005
QUANTILES_PER_CLASS = 32
DEPTH_QUANTILES = 4096
RAIN_DIAMETER_RANGE_MM = (0.5, 6.0)
SNOW_DIAMETER_RANGE_MM = (0.1, 20.0)      # flake (geometric) diameters, as the LiDAR's snowfall
SNOW_DSDS = ("gunn_marshall", "sekhon_srivastava", "brandes")
# disk diameters with the second moment, across a streak, of the 2-tap linear split (1.63 px) and of the split at
# scale s followed by bilinear upsampling (2.31 s px)
BILINEAR_DISK_PX = 4.0 / math.sqrt(6.0)
DISK_PER_SCALE_PX = 4.0 / math.sqrt(3.0)
MAX_LEVEL = 5
VEIL_LUT_SIZE = 256           # depth bins of the veil table (≤ 256: the kernel indexes them with uint8)


# --- size classes ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class SizeClasses:
    """A particle size distribution cut into 0.1 mm classes.

    Per m³ of air: ``number`` per class, ``shadow_area_m2`` = Σ (π/4) D² per class, ``volume_m3`` = Σ (π/6) D³.
    ``quantiles_mm`` (classes × 33): the diameters at cumulative fractions 0, 1/32, …, 1 within each class, for
    inverse-CDF sampling by table lookup (np.interp costs ~75 ns per particle)."""

    edges_mm: np.ndarray
    number: np.ndarray
    shadow_area_m2: np.ndarray
    volume_m3: np.ndarray
    quantiles_mm: np.ndarray

    @property
    def rms_d_mm(self) -> np.ndarray:
        lo, hi = self.edges_mm[:-1], self.edges_mm[1:]
        return np.where(self.number > 0, np.sqrt(self.shadow_area_m2 / np.maximum(self.number, 1e-300) * 4e6 /
                                                 math.pi), 0.5 * (lo + hi))

    @property
    def number_per_m3(self) -> float:
        return float(self.number.sum())

    def extinction_per_m(self, q_ext: float = IMAGING_Q_EXT) -> float:
        return q_ext * float(self.shadow_area_m2.sum())

    def liquid_water_g_per_m3(self) -> float:
        """Mass of liquid-equivalent spheres (ρ_w = 10⁶ g/m³)."""
        return 1e6 * float(self.volume_m3.sum())

    def sample_diameters_mm(self, cls: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Inverse CDF within each particle's class (``u`` uniform in [0, 1)), float32."""
        q = self.quantiles_mm.shape[1] - 1
        base = np.arange(self.quantiles_mm.shape[0], dtype=np.int64) * (q + 1)
        return lerp_table(self.quantiles_mm.ravel(), base, np.full(base.size, q, np.float32), cls, u, q)


def lerp_table(table: np.ndarray, base: np.ndarray, scale: np.ndarray, cls: np.ndarray, u: np.ndarray,
               n: int) -> np.ndarray:
    """Linear interpolation in equally spaced tables, float32: ``table[base[c] + t]`` at ``t = u · scale[c]`` in
    [0, n], c = ``cls`` of each value (one compiled pass)."""
    out = np.empty(np.shape(u), np.float32)
    _lerp_kernel(table, base, np.asarray(scale, np.float32), cls, np.asarray(u, np.float32), n, out)
    return out


@jit(error_model="numpy")
def _lerp_kernel(table, base, scale, cls, u, n, out):                        # pragma: no cover - compiled
    for i in range(u.size):
        c = cls[i]
        t = u[i] * scale[c]
        j = min(np.int32(t), n - 1)
        frac = t - np.float32(j)
        lo = table[base[c] + j]
        out[i] = lo + frac * (table[base[c] + j + 1] - lo)


def size_classes(n_of_d: Callable[[np.ndarray], np.ndarray], d_min_mm: float, d_max_mm: float) -> SizeClasses:
    """Integrate ``N(D)`` (m⁻³ mm⁻¹, D in mm) over 0.1 mm classes with the trapezoid rule on a 5 µm grid."""
    n_fine = round((d_max_mm - d_min_mm) / FINE_STEP_MM)
    d = np.linspace(d_min_mm, d_max_mm, n_fine + 1)
    n = np.asarray(n_of_d(d), dtype=float)

    def cumulative(y):
        return np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(d))])

    per_class = round(CLASS_WIDTH_MM / FINE_STEP_MM)
    idx = np.arange(0, n_fine + 1, per_class)
    if idx[-1] != n_fine:
        idx = np.append(idx, n_fine)
    c0, c2, c3 = cumulative(n), cumulative(d ** 2 * n), cumulative(d ** 3 * n)
    frac = np.linspace(0.0, 1.0, QUANTILES_PER_CLASS + 1)
    targets = c0[idx[:-1], None] + frac[None, :] * np.diff(c0[idx])[:, None]
    quantiles = np.interp(targets, c0, d)
    # classes without particles (underflow): the class edges
    empty = np.diff(c0[idx]) <= 0
    quantiles[empty] = d[idx[:-1]][empty, None] + frac[None, :] * np.diff(d[idx])[empty, None]
    return SizeClasses(edges_mm=d[idx], number=np.diff(c0[idx]),
                       shadow_area_m2=math.pi / 4 * np.diff(c2[idx]) * 1e-6,
                       volume_m3=math.pi / 6 * np.diff(c3[idx]) * 1e-9,
                       quantiles_mm=quantiles.astype(np.float32))


@lru_cache(maxsize=32)
def rain_classes(rain_rate_mm_per_h: float) -> SizeClasses:
    """Marshall–Palmer (1948) drops 0.5–6 mm (models.md §2.2)."""
    n0, lam = marshall_palmer(rain_rate_mm_per_h)
    return size_classes(lambda d: n0 * np.exp(-lam * d), *RAIN_DIAMETER_RANGE_MM)


@lru_cache(maxsize=32)
def snow_classes(snowfall_rate_mm_per_h: float, dsd: str, habit: str = "dry_aggregates") -> SizeClasses:
    """Snowflakes of 0.1–10 mm geometric diameter (models.md §2.3 and its correction): the LiDAR's snowfall
    (:func:`dsd.snowfall`: Gunn–Marshall / Sekhon–Srivastava slope in melted diameter, flakes from the habit's
    density–size law, N0 from the mass flux), or the Brandes et al. (2007) measured gamma fits in flake diameter
    (3.03, 2.70, 2.59 mm/h only)."""
    if dsd == "brandes":
        if snowfall_rate_mm_per_h not in BRANDES_SNOW_GAMMA:
            raise ValueError(f"the Brandes table has only {sorted(BRANDES_SNOW_GAMMA)} mm/h")
        n0, mu, lam = BRANDES_SNOW_GAMMA[snowfall_rate_mm_per_h]
        return size_classes(lambda d: gamma_dsd(d, n0, mu, lam), *SNOW_DIAMETER_RANGE_MM)
    return size_classes(snowfall(snowfall_rate_mm_per_h, dsd, habit).flake_density, *SNOW_DIAMETER_RANGE_MM)


def rain_fall_speed_m_per_s(d_mm):
    """Atlas & Ulbrich (1977), the law of models.md §2.2 (valid 0.5–5 mm; few drops are larger)."""
    return atlas_ulbrich_m_per_s(d_mm)


# --- camera geometry --------------------------------------------------------------------------------------------

def sensor_to_optical(v_xyz) -> np.ndarray:
    """Vehicle/sensor frame (x forward, y left, z up) → camera optical frame (X right, Y down, Z forward)."""
    x, y, z = (float(c) for c in v_xyz)
    return np.array([-y, -z, x])


def relative_velocity_optical(conditions: Conditions, fall_speed_m_per_s) -> np.ndarray:
    """``v_rel = (wind − ego) + (0, 0, −v_t)`` in the optical frame, (N, 3) for N fall speeds (models.md §2.9)."""
    base = sensor_to_optical(np.subtract(conditions.wind_velocity_m_per_s, conditions.ego_velocity_m_per_s))
    v = np.repeat(base[None, :], np.size(fall_speed_m_per_s), axis=0)
    v[:, 1] = v[:, 1] + np.ravel(fall_speed_m_per_s)          # falling = +Y (down) in the optical frame
    return v


def focal_px(profile: CameraProfile) -> float:
    return math.sqrt(profile.fx_px * profile.fy_px)


def defocus_px(profile: CameraProfile, z_m) -> np.ndarray:
    """Circle-of-confusion diameter in pixels at planar distance Z (thin lens, models.md §2.2 [PROP])."""
    f, n, p, zf = profile.focal_length_m, profile.f_number, profile.pixel_pitch_m, profile.focus_distance_m
    z = np.asarray(z_m, dtype=np.float32)
    if math.isinf(zf):
        return np.float32(f * f / (n * p)) / z
    return np.float32(f * f / (n * (zf - f) * p)) * np.abs(z - np.float32(zf)) / z


@lru_cache(maxsize=8)
def above_ground_volume_table(profile: CameraProfile, d_min_m: float, d_max_m: float) -> tuple[np.ndarray, ...]:
    """``(Z grid, V(Z), Z quantiles)``: volume (m³) of the image frustum between planar depths d_min and Z above
    the ground plane at the camera height (rows below ``c_y + h f_y / Z`` are under the ground), and ``Z³`` at 4097
    equally spaced fractions of the whole volume (inverse CDF for sampling by table lookup; Z³ is linear in the
    volume until the ground enters the image, so the lookup is exact there)."""
    z = np.geomspace(d_min_m, d_max_m, 8192)
    rows = bottom_row_px(profile, z) + 0.5
    area = profile.width_px * z * z * rows / (profile.fx_px * profile.fy_px)
    vol = np.concatenate([[0.0], np.cumsum(0.5 * (area[1:] + area[:-1]) * np.diff(z))])
    quantiles = (np.interp(np.linspace(0.0, vol[-1], DEPTH_QUANTILES + 1), vol, z) ** 3).astype(np.float32)
    for a in (z, vol, quantiles):
        a.flags.writeable = False
    return z, vol, quantiles


def bottom_row_px(profile: CameraProfile, z_m):
    """Lowest image row (pixel-centre coordinate, bottom edge at H − ½) still above the ground at planar depth Z."""
    return np.minimum(profile.height_px - 0.5, profile.cy_px + profile.height_above_ground_m * profile.fy_px / z_m)


def peak_opacity(profile: CameraProfile, exposure_s: float, d_mm, lateral_speed_m_per_s, z_m) -> np.ndarray:
    """Expected largest pixel opacity of a particle's rendered streak: its image area times the share of the
    brightest pixel. Along the streak (motion plus footprint, ℓ px) that share is ``1/ℓ`` for long streaks and
    ``1 − ℓ/4`` for short ones (a box of length ℓ < 1 at a random sub-pixel offset); across it, the two-pixel
    split gives ¾ on average, and a footprint spread on a coarse buffer (scale ≈ footprint/2.31) ¾ of 1/scale."""
    f = focal_px(profile)
    z = np.asarray(z_m, dtype=float)
    d_px = np.asarray(d_mm) * 1e-3 * f / z
    fp = np.hypot(d_px, defocus_px(profile, z))
    along = np.asarray(lateral_speed_m_per_s) * exposure_s * f / z + fp
    share_along = np.where(along <= 2.0, 1.0 - along / 4.0, 1.0 / np.maximum(along, 2.0))
    share_across = np.minimum(0.75, 0.75 * DISK_PER_SCALE_PX / np.maximum(fp, 1e-9))
    return np.minimum(1.0, math.pi / 4 * d_px ** 2 * share_along * share_across)


def explicit_depth_limits(profile: CameraProfile, exposure_s: float, classes: SizeClasses, fall_speed,
                          conditions: Conditions, d_min_m: float, d_max_m: float, min_opacity: float) -> np.ndarray:
    """Per class, the planar depth up to which particles are rendered explicitly: the farthest Z in
    ``[d_min, d_max]`` where the peak opacity still reaches ``min_opacity`` (image-plane speed from the lateral
    components of v_rel, a lower bound, so the test errs towards explicit particles)."""
    d = classes.rms_d_mm
    v = relative_velocity_optical(conditions, fall_speed(d))
    lateral = np.hypot(v[:, 0], v[:, 1])
    z = np.geomspace(d_min_m, d_max_m, 256)
    visible = peak_opacity(profile, exposure_s, d[:, None], lateral[:, None], z[None, :]) >= min_opacity
    last = np.where(visible.any(axis=1), z.size - 1 - np.argmax(visible[:, ::-1], axis=1), -1)
    limits = np.where(last >= 0, z[np.maximum(last, 0)], d_min_m)
    return np.where(classes.number > 0, limits, d_min_m)


def resolved_depth_limits(profile: CameraProfile, exposure_s: float, classes: SizeClasses, fall_speed,
                          conditions: Conditions, d_min_m: float, d_max_m: float, limits_m: np.ndarray,
                          min_extent_px: float, motion_px_m: np.ndarray | None = None) -> np.ndarray:
    """Per class, the planar depth up to which particles are drawn one by one (at most ``limits_m``, the
    :func:`explicit_depth_limits`): the farthest Z on the same grid where the streak still spans ``min_extent_px``
    pixels (motion during the exposure plus footprint). Beyond it a particle is an unresolved point whose only
    trace is the opacity it adds to one or two pixels: :func:`unresolved_field` draws those per pixel. The motion
    is bounded from above (lateral speed at the longer focal length plus the radial part of v_rel at the image
    corner), so the test errs towards explicit particles; or ``motion_px_m`` ((bands, classes), px·m) gives the
    bounds per band of the image (:func:`streak_motion.motion_bands`), and the limits are per band and class."""
    d = classes.rms_d_mm
    if motion_px_m is None:
        v = relative_velocity_optical(conditions, fall_speed(d))
        corner_px = math.hypot(max(profile.cx_px, profile.width_px - profile.cx_px),
                               max(profile.cy_px, profile.height_px - profile.cy_px))
        motion = exposure_s * (max(profile.fx_px, profile.fy_px) * np.hypot(v[:, 0], v[:, 1]) +
                               np.abs(v[:, 2]) * corner_px)                                    # px·m
    else:
        motion = motion_px_m
    z = np.geomspace(d_min_m, d_max_m, 256)
    footprint = np.hypot(d[:, None] * 1e-3 * focal_px(profile) / z[None, :], defocus_px(profile, z)[None, :])
    resolved = motion[..., :, None] / z + footprint >= min_extent_px
    last = np.where(resolved.any(axis=-1), z.size - 1 - np.argmax(resolved[..., ::-1], axis=-1), -1)
    return np.minimum(np.where(last >= 0, z[np.maximum(last, 0)], d_min_m), limits_m)


# --- sampling --------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Particles:
    """Mid-exposure particles in the optical frame (m, float32), diameters (mm) and fall speeds (m/s)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    d_mm: np.ndarray
    fall_speed_m_per_s: np.ndarray

    def take(self, index: np.ndarray) -> "Particles":
        """The particles at ``index`` (a selection or an order)."""
        return Particles(*(getattr(self, f.name)[index] for f in fields(self)))


def sample_particles(rng: np.random.Generator, profile: CameraProfile, classes: SizeClasses,
                     z_limits_m: np.ndarray, d_min_m: float, d_max_m: float, fall_speed,
                     split: BandSplit | None = None) -> tuple[Particles, float]:
    """Marked Poisson process in the above-ground frustum slabs ``[d_min, Z_i]`` of each class: per-class Poisson
    counts, Z by inverse CDF of the slab volume (∝ Z² until the ground enters the image), then a uniform image
    position above the ground. Returns (particles, expected count). With a :class:`BandSplit` (made for these
    ``z_limits_m``), only the particles up to the limit of the band of their mid-exposure pixel are kept (the same
    process restricted to those slabs)."""
    z_grid, vol, z3_quantiles = above_ground_volume_table(profile, d_min_m, d_max_m)
    v_lim = np.interp(np.clip(z_limits_m, d_min_m, d_max_m), z_grid, vol)
    lam = classes.number * v_lim
    counts = rng.poisson(lam)
    cls = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
    u = rng.random((4, cls.size), dtype=np.float32)
    q = (v_lim * (DEPTH_QUANTILES / vol[-1])).astype(np.float32)         # class slab in quantile units
    z = np.exp(np.log(lerp_table(z3_quantiles, np.zeros(q.size, np.int64), q, cls, u[1], DEPTH_QUANTILES))
               * np.float32(1 / 3))                                                   # ∛
    if split is not None:
        cls, u, z = _keep_in_bands(profile, split, cls, u, z)
        lam = split.expected
    d = classes.sample_diameters_mm(cls, u[0])
    # image column uniform, row uniform above the ground (bottom_row_px), back-projected at Z; float32 as NumPy
    # evaluates col = u·W − ½, row = u·(min(H − ½, c_y + h f_y / Z) + ½) − ½, x = (col − c_x) Z / f_x
    # (y alike)
    camera = np.array([profile.width_px, profile.height_px - 0.5, profile.cy_px,
                       profile.height_above_ground_m * profile.fy_px, profile.cx_px, profile.fx_px, profile.fy_px],
                      np.float32)
    x, y = np.empty_like(z), np.empty_like(z)
    _position_kernel(u[2], u[3], z, camera, x, y)
    return Particles(x, y, z, d, np.asarray(fall_speed(d), dtype=np.float32)), float(lam.sum())


def _keep_in_bands(profile: CameraProfile, split: BandSplit, cls, u, z):
    """:func:`sample_particles`' draws (classes, uniforms, Z) of the particles inside their band's limits, in place
    (views of the first ones)."""
    camera = np.array([profile.width_px, profile.height_px - 0.5, profile.cy_px,
                       profile.height_above_ground_m * profile.fy_px], np.float32)
    n = _band_keep_kernel(u, z, cls, camera, profile.width_px, profile.height_px, split.bands.pixel,
                          split.threshold)
    return cls[:n], u[:, :n], z[:n]


@jit(error_model="numpy")
def _band_keep_kernel(u, z, cls, camera, w, h, pixel, threshold):              # pragma: no cover - compiled
    """Moves the particles whose Z is within the limit of their class in the band of their mid-exposure pixel
    (:func:`_position_kernel`'s column and row) to the front, in order; returns their number."""
    width, bottom, cy, ground = camera
    half = np.float32(0.5)
    u_d, u_col, u_row = u[0], u[2], u[3]
    kept = 0
    for i in range(z.size):                   # branch-free: every particle is written, the kept ones stay
        zi, ci, col_u, row_u = z[i], cls[i], u_col[i], u_row[i]
        lowest = cy + ground / zi
        col = min(np.int32(col_u * width), np.int32(w - 1))
        row = min(np.int32(row_u * ((bottom if bottom <= lowest else lowest) + half)), np.int32(h - 1))
        cls[kept], z[kept], u_d[kept], u_col[kept], u_row[kept] = ci, zi, u_d[i], col_u, row_u
        kept += np.int64(zi <= threshold[pixel_band(pixel, row, col), ci])
    return kept


@jit(error_model="numpy")
def _position_kernel(u_col, u_row, z, camera, x, y):                          # pragma: no cover - compiled
    width, bottom, cy, ground, cx, fx, fy = camera
    half = np.float32(0.5)
    for i in range(z.size):
        zi = z[i]
        col = u_col[i] * width - half
        lowest = cy + ground / zi
        row = u_row[i] * ((bottom if bottom <= lowest else lowest) + half) - half
        x[i] = (col - cx) * zi / fx
        y[i] = (row - cy) * zi / fy


# --- rasterisation ---------------------------------------------------------------------------------------------

def streak_endpoints(profile: CameraProfile, particles: Particles, conditions: Conditions, exposure_s: float):
    """Image positions and planar depths at the start and end of the exposure, ``P ∓ v_rel T/2``:
    ``(u0, v0, z0, u1, v1, z1)``."""
    half_t = np.float32(exposure_s / 2)
    hx, hy_base, hz = (np.float32(c) * half_t for c in relative_velocity_optical(conditions, 0.0)[0])
    hy = hy_base + particles.fall_speed_m_per_s * half_t
    fx, fy, cx, cy = (np.float32(c) for c in (profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px))
    p = particles
    z0, z1 = p.z - hz, p.z + hz
    return (fx * (p.x - hx) / z0 + cx, fy * (p.y - hy) / z0 + cy, z0,
            fx * (p.x + hx) / z1 + cx, fy * (p.y + hy) / z1 + cy, z1)


class Streaks(NamedTuple):
    """Streaks on the grids of their footprint levels, one entry per particle (float32 unless noted).

    The major axis (a) is the one along which the streak moves most (v when ``vertical``), b the other; ``lo``,
    ``hi`` are the streak's ends along a clipped to the grid, ``first`` (int32) and ``count`` (int32, 0 = not drawn)
    the pixels it crosses along a; the centre line is ``b = b0 + (a − a0)·slope``; ``density`` the opacity per
    unit length along a (per full-resolution pixel); ``range_m`` the particle's range at mid-exposure."""

    level: np.ndarray
    vertical: np.ndarray
    a0: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    first: np.ndarray
    count: np.ndarray
    b0: np.ndarray
    slope: np.ndarray
    density: np.ndarray
    range_m: np.ndarray


def streak_geometry(profile: CameraProfile, particles: Particles, conditions: Conditions, exposure_s: float,
                    d_min_m: float) -> Streaks:
    """Each particle's streak: the segment between its exposure end points (:func:`streak_endpoints`) with
    uniform line density (total = the particle's image area), lengthened by its footprint, on the grid of its
    footprint level."""
    return _streaks_of_columns(profile, particle_columns(particles), conditions, exposure_s, d_min_m)


PARTICLE_COLUMNS = ("x", "y", "z", "d_mm", "fall_speed_m_per_s")     # the rows of :func:`particle_columns`


def particle_columns(particles: Particles) -> np.ndarray:
    """The particles as (5, N) float32 (:data:`PARTICLE_COLUMNS`)."""
    return np.stack([getattr(particles, name) for name in PARTICLE_COLUMNS]).astype(np.float32, copy=False)


def _streaks_of_columns(profile: CameraProfile, columns: np.ndarray, conditions: Conditions, exposure_s: float,
                        d_min_m: float) -> Streaks:
    """:func:`streak_geometry` of particles given as :func:`particle_columns`: one compiled, vectorised pass, float32
    operation by operation as the NumPy expressions of the formulas (tests/physics/test_particles.py keeps them as
    the oracle)."""
    n = columns.shape[1]
    out = Streaks(np.empty(n, np.int8), np.empty(n, bool), *(np.empty(n, np.float32) for _ in range(3)),
                  np.empty(n, np.int32), np.empty(n, np.int32), *(np.empty(n, np.float32) for _ in range(4)))
    _streak_geometry_kernel(*columns, *_streak_constants(profile, conditions, exposure_s, d_min_m), *out)
    return out


def _streak_constants(profile: CameraProfile, conditions: Conditions, exposure_s: float, d_min_m: float) -> tuple:
    """The arguments of :func:`_streak_geometry_kernel` after the particles: float32 camera and motion constants,
    whether the focus is finite, the image size and :func:`footprint_level_bounds`."""
    half_t = np.float32(exposure_s / 2)
    hx, hy, hz = (np.float32(c) * half_t for c in relative_velocity_optical(conditions, 0.0)[0])
    zf = profile.focus_distance_m
    f, fn, pitch = profile.focal_length_m, profile.f_number, profile.pixel_pitch_m
    k_defocus = f * f / (fn * pitch) if math.isinf(zf) else f * f / (fn * (zf - f) * pitch)    # defocus_px
    camera = np.array([profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px, hx, hy, hz, half_t,
                       math.pi / 4 * 1e-6 * profile.fx_px * profile.fy_px, 1e-3 * focal_px(profile), k_defocus,
                       0.0 if math.isinf(zf) else zf, 0.5 * d_min_m], dtype=np.float32)
    return camera, not math.isinf(zf), profile.width_px, profile.height_px, footprint_level_bounds()


@jit(error_model="numpy")
def _streak_geometry_kernel(x, y, z, d_mm, fall_speed, camera, finite_focus, w, h, bounds,
                            level, vertical, a0, lo, hi, first, count, b0, slope, density, range_m):
    """:func:`streak_geometry` of particle i into entry i of the outputs; branch-free (selects), so that LLVM
    vectorises it (5× faster than a table look-up of the level scale or min/max calls allow)."""  # pragma: no cover
    fx, fy, cx, cy, hx, hy_base, hz, half_t, k_mass, k_dpx, k_defocus, zf, z_cross = camera
    b_1, b_2, b_3, b_4, b_5 = bounds
    one, half, zero = np.float32(1), np.float32(0.5), np.float32(0)
    w32, hw32 = np.float32(w), np.float32(h - w)
    for i in range(z.size):
        xp, yp, zp, dp = x[i], y[i], z[i], d_mm[i]
        # exposure end points P ∓ v_rel T/2 (streak_endpoints)
        hy = hy_base + fall_speed[i] * half_t
        z0, z1 = zp - hz, zp + hz
        u0, v0 = fx * (xp - hx) / z0 + cx, fy * (yp - hy) / z0 + cy
        u1, v1 = fx * (xp + hx) / z1 + cx, fy * (yp + hy) / z1 + cy
        r = np.sqrt(xp * xp + yp * yp + zp * zp)
        mass = k_mass * (dp * dp) * r / (zp * zp * zp)
        d_px = dp * k_dpx / zp
        c_px = k_defocus * abs(zp - zf) / zp if finite_focus else k_defocus / zp
        footprint = np.sqrt(d_px * d_px + c_px * c_px)
        lv = (np.int32(footprint >= b_1) + np.int32(footprint >= b_2) + np.int32(footprint >= b_3) +
              np.int32(footprint >= b_4) + np.int32(footprint >= b_5))
        inv = one / np.float32(np.int32(1) << lv)                     # 2^-level, exact
        du, dv = u1 - u0, v1 - v0
        vert = abs(dv) >= abs(du)
        vf = one if vert else zero
        pa0, pb0 = u0 + vf * (v0 - u0), v0 + vf * (u0 - v0)
        da, db = du + vf * (dv - du), dv + vf * (du - dv)
        offset = half * inv - half
        pa0, pb0, da, db = pa0 * inv + offset, pb0 * inv + offset, da * inv, db * inv
        sl = db / (da + (one if da == zero else zero))
        hf = half * footprint * inv
        a_lo = pa0 if pa0 <= pa0 + da else pa0 + da
        pb0 = pb0 + sl * (a_lo - hf - pa0)
        pa0, pa1 = a_lo - hf, a_lo + abs(da) + hf
        n_major = np.ceil((w32 + vf * hw32) * inv)
        plo = pa0 if pa0 >= -half else -half
        phi = pa1 if pa1 <= n_major - half else n_major - half
        pfirst = np.floor(plo + half)
        last = np.floor(phi + half)
        pcount = (last if last <= n_major - one else n_major - one) - pfirst + one
        crossing = (z0 if z0 <= z1 else z1) <= z_cross
        level[i], vertical[i], a0[i], lo[i], hi[i] = lv, vert, pa0, plo, phi
        first[i] = np.int32(pfirst)
        count[i] = 0 if phi <= plo or crossing else np.int32(pcount)
        b0[i], slope[i], density[i], range_m[i] = pb0, sl, mass * inv * inv / (pa1 - pa0), r


@lru_cache(maxsize=1)
def footprint_level_bounds() -> np.ndarray:
    """The smallest float32 footprints (px) of levels 1 … MAX_LEVEL under :func:`footprint_level`, found by
    scanning its NumPy evaluation around each nominal step (``DISK_PER_SCALE_PX·2^(l−½)``, and the level-1 gate),
    so the compiled rasteriser assigns exactly its levels."""
    nominal = [math.sqrt(BILINEAR_DISK_PX * 2 * DISK_PER_SCALE_PX)] + [DISK_PER_SCALE_PX * 2 ** (lv - 0.5)
                                                                       for lv in range(2, MAX_LEVEL + 1)]
    bounds = []
    for lv, x in enumerate(nominal, start=1):
        bits = np.arange(-4096, 4097, dtype=np.int64) + int(np.float32(x).view(np.int32))
        f = bits.astype(np.int32).view(np.float32)
        step = np.flatnonzero(np.diff(footprint_level(f) >= lv))
        if step.size != 1 or footprint_level(f[:1])[0] >= lv or footprint_level(f[-1:])[0] < lv:
            raise AssertionError(f"footprint level {lv}: no single step near {x} px")
        bounds.append(f[step[0] + 1])
    out = np.array(bounds, np.float32)
    out.flags.writeable = False
    return out


def block_keys(profile: CameraProfile, particles: Particles) -> np.ndarray:
    """The number (uint16) of the 8 × 8 px or coarser block (≤ 2¹⁶ blocks, raster order) holding each particle's
    mid-exposure image."""
    h, w = profile.height_px, profile.width_px
    shift = 3                                         # 8 px
    while -(-h >> shift) * -(-w >> shift) > 1 << 16:
        shift += 1
    camera = np.array([profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px], np.float32)
    key = np.empty(particles.z.size, np.uint16)
    _block_keys_kernel(particles.x, particles.y, particles.z, camera, w, h, shift, key)
    return key


@jit(error_model="numpy")
def _block_keys_kernel(x, y, z, camera, w, h, shift, key):                    # pragma: no cover - compiled
    fx, fy, cx, cy = camera
    blocks_per_row = (w + (1 << shift) - 1) >> shift
    for p in range(z.size):
        col = min(max(fx * x[p] / z[p] + cx, np.float32(0)), np.float32(w - 1))
        row = min(max(fy * y[p] / z[p] + cy, np.float32(0)), np.float32(h - 1))
        key[p] = (np.int32(row) >> shift) * blocks_per_row + (np.int32(col) >> shift)


@jit(error_model="numpy")
def _render_streaks(x, y, z, d_mm, fall_speed, key, camera, finite_focus, w, h, bounds, pyramid, offsets,
                    depth_m):                                          # pragma: no cover - compiled
    """:func:`splat_streaks` of the :func:`streak_geometry` of the particles in raster order of their blocks
    (``key``: :func:`block_keys`; visited so, the reads of the depth map and the writes to the grids stay in
    cache), without the sorted particle and streak arrays: the particles are first distributed by
    the key's high byte (a band of blocks: one streaming pass), then each band is sorted by the low byte, given
    its streaks and splatted while it is in cache. The same order, so the same sums, as the whole sort. Returns
    the highest level drawn and the number of visible particles."""
    n = z.size
    start = np.zeros(257, np.int64)
    for p in range(n):
        start[(key[p] >> 8) + 1] += 1
    for b in range(256):
        start[b + 1] += start[b]
    fill = start[:256].copy()
    banded, low_byte = np.empty((n, 5), np.float32), np.empty(n, np.uint8)   # rows: 256 write streams
    for p in range(n):
        b = key[p] >> 8
        j = fill[b]
        fill[b] = j + 1
        low_byte[j] = key[p] & 255
        banded[j, 0], banded[j, 1], banded[j, 2], banded[j, 3], banded[j, 4] = \
            x[p], y[p], z[p], d_mm[p], fall_speed[p]
    size = 0                        # the largest band; not np.max, which imports numba.np.arraymath (see warmup)
    for b in range(256):
        size = max(size, start[b + 1] - start[b])
    cols = np.empty((5, size), np.float32)
    level, vertical = np.empty(size, np.int8), np.empty(size, np.bool_)
    first, count = np.empty(size, np.int32), np.empty(size, np.int32)
    a0, lo, hi, b0, slope, density, range_m = (np.empty(size, np.float32), np.empty(size, np.float32),
                                                np.empty(size, np.float32), np.empty(size, np.float32),
                                                np.empty(size, np.float32), np.empty(size, np.float32),
                                                np.empty(size, np.float32))
    visible = np.empty(size, np.bool_)
    top, n_visible = 0, 0
    low_start = np.empty(257, np.int64)
    for b in range(256):
        m = start[b + 1] - start[b]
        if m == 0:
            continue
        low_start[:] = 0
        for i in range(start[b], start[b + 1]):
            low_start[low_byte[i] + 1] += 1
        for k in range(256):
            low_start[k + 1] += low_start[k]
        for i in range(start[b], start[b + 1]):
            j = low_start[low_byte[i]]
            low_start[low_byte[i]] = j + 1
            for c in range(5):
                cols[c, j] = banded[i, c]
        _streak_geometry_kernel(cols[0, :m], cols[1, :m], cols[2, :m], cols[3, :m], cols[4, :m], camera,
                                finite_focus, w, h, bounds, level[:m], vertical[:m], a0[:m], lo[:m], hi[:m],
                                first[:m], count[:m], b0[:m], slope[:m], density[:m], range_m[:m])
        visible[:m] = False
        splat_streaks(pyramid, offsets, depth_m, level[:m], vertical[:m], a0[:m], lo[:m], hi[:m], first[:m],
                      count[:m], b0[:m], slope[:m], density[:m], range_m[:m], visible[:m])
        for i in range(m):
            if count[i] > 0:
                top = max(top, level[i])
                n_visible += visible[i]
    return top, n_visible


def level_offsets(height: int, width: int, top_level: int) -> np.ndarray:
    """Start of each level's (⌈H/2^l⌉, ⌈W/2^l⌉) grid in one flat buffer, levels 0 … top_level, and the end."""
    sizes = [-(-height // (1 << lv)) * -(-width // (1 << lv)) for lv in range(top_level + 1)]
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)


@jit(error_model="numpy")
def splat_streaks(pyramid, offsets, depth_m, level, vertical, a0, lo, hi, first, count, b0, slope, density,
                  range_m, visible):                                   # pragma: no cover - compiled
    """Add every streak to its level's grid in ``pyramid`` (flat, :func:`level_offsets`) and set ``visible``
    (the first sample of the streak is in front of the scene).

    Per pixel crossed along the major axis: the exact length of the segment inside it times the density, split
    linearly between the two nearest cells across (Wu-style anti-aliasing); nothing where the cell nearest the
    sample is outside the grid or the scene there (the pixel nearest the cell centre) is nearer than the particle
    (metres against metres)."""
    h, w = depth_m.shape
    half_px = np.float32(0.5)
    # per level: grid rows and columns, and the last ones with a pixel at their centre
    n_levels = offsets.size - 1
    rows, cols = np.empty(n_levels, np.int64), np.empty(n_levels, np.int64)
    last_row, last_col = np.empty(n_levels, np.int64), np.empty(n_levels, np.int64)
    for lv in range(n_levels):
        scale = 1 << lv
        rows[lv], cols[lv] = (h + scale - 1) // scale, (w + scale - 1) // scale
        last_row[lv], last_col[lv] = (h - scale // 2 - 1) // scale, (w - scale // 2 - 1) // scale
    flat = depth_m.ravel()
    for p in range(level.size):
        n = count[p]
        if n == 0:
            continue
        # per particle: its level's grid and the strides along the streak's major and minor axes, in the grid and
        # (per grid cell, at its centre pixel) in the depth map
        lv, vert = level[p], vertical[p]
        scale = 1 << lv
        base, n_cols = offsets[lv], cols[lv]
        n_minor = n_cols if vert else rows[lv]
        s_major, s_minor = (n_cols, 1) if vert else (1, n_cols)
        last_major, last_minor = (last_row[lv], last_col[lv]) if vert else (last_col[lv], last_row[lv])
        d_major, d_minor = (w * scale, scale) if vert else (scale, w * scale)
        d_centre = (scale // 2) * (w + 1)
        f0, lo_p, hi_p, a0_p, b0_p, sl, dens, r = first[p], lo[p], hi[p], a0[p], b0[p], slope[p], density[p], \
            range_m[p]
        for j in range(n):
            ci = f0 + j
            c = np.float32(ci)
            seg_lo = max(lo_p, c - half_px)
            seg_hi = min(hi_p, c + half_px)
            weight = dens * max(seg_hi - seg_lo, np.float32(0))
            b = b0_p + (half_px * (seg_lo + seg_hi) - a0_p) * sl
            b_floor = np.floor(b)
            frac = b - b_floor
            bi = int(b_floor)
            nearest = bi + 1 if frac >= half_px else bi
            in_front = (0 <= nearest < n_minor and
                        flat[min(ci, last_major) * d_major + min(nearest, last_minor) * d_minor + d_centre] > r)
            if j == 0:
                visible[p] = in_front
            if not in_front:
                continue
            cell = base + ci * s_major + bi * s_minor
            if bi >= 0:
                pyramid[cell] += weight * (np.float32(1) - frac)
            if bi + 1 < n_minor:
                pyramid[cell + s_minor] += weight * frac


def render_coverage(profile: CameraProfile, particles: Particles, conditions: Conditions, exposure_s: float,
                    depth_m: np.ndarray, d_min_m: float) -> tuple[np.ndarray, int]:
    """Per-pixel opacity (H, W) float32 of all explicit particles, clipped to 1; and the number of particles in
    the image and in front of the scene at the first pixel of their streak.

    Each streak is a segment of uniform line density (total = the particle's image area), lengthened by its
    footprint, integrated exactly over the pixels it crosses along its major axis and split linearly between
    the two nearest pixels across it (Wu-style anti-aliasing), on the grid of its footprint level. A pixel
    gets nothing where the scene is nearer than the particle (metres against metres)."""
    h, w = profile.height_px, profile.width_px
    if particles.z.size == 0:
        return np.zeros((h, w), dtype=np.float32), 0
    offsets = level_offsets(h, w, MAX_LEVEL)
    pyramid = np.zeros(offsets[-1], dtype=np.float32)
    top, n_visible = _render_streaks(*(np.asarray(getattr(particles, name), np.float32) for name in PARTICLE_COLUMNS),
                                     block_keys(profile, particles),
                                     *_streak_constants(profile, conditions, exposure_s, d_min_m), pyramid, offsets,
                                     np.ascontiguousarray(depth_m, dtype=np.float32))
    # collapse the pyramid (grids hold opacity per full-resolution pixel): each level is upsampled ×2 into the
    # next finer one, the last one clipped on the way
    grids = [pyramid[offsets[lv]:offsets[lv + 1]].reshape(-(-h // (1 << lv)), -(-w // (1 << lv)))
             for lv in range(top + 1)]
    for lv in range(top - 1, -1, -1):
        add_upsampled(grids[lv], grids[lv + 1], lv == 0)
    return grids[0] if top else capped(grids[0], 1.0, out=grids[0]), int(n_visible)


@jit(error_model="numpy")
def add_upsampled(fine, coarse, clip=False):                          # pragma: no cover - compiled
    """``fine += ×2 upsampling of coarse`` (⌈h/2⌉ × ⌈w/2⌉), bilinear as OpenCV's INTER_LINEAR: fine pixel x
    samples the coarse grid at (x + ½)/2 − ½, i.e. ¼ and ¾ of its two nearest cells, edge cells replicated;
    the sums clipped to 1 with ``clip``."""
    hc, wc = coarse.shape
    q, tq = np.float32(0.25), np.float32(0.75)
    row = np.empty(wc + 2, np.float32)            # vertical blend of two coarse rows, padded by one cell each side
    wide = np.empty(2 * wc, np.float32)           # ... upsampled along the row (separate loops vectorise)
    for y in range(fine.shape[0]):
        near = y // 2
        far = min(max(near - 1 if y % 2 == 0 else near + 1, 0), hc - 1)
        for i in range(wc):
            row[i + 1] = tq * coarse[near, i] + q * coarse[far, i]
        row[0], row[wc + 1] = row[1], row[wc]
        for i in range(wc):
            wide[2 * i] = q * row[i] + tq * row[i + 1]
            wide[2 * i + 1] = tq * row[i + 1] + q * row[i + 2]
        f = fine[y]
        if clip:
            for x in range(f.size):
                f[x] = min(f[x] + wide[x], np.float32(1))
        else:
            for x in range(f.size):
                f[x] += wide[x]


def footprint_level(footprint_px: np.ndarray) -> np.ndarray:
    """Buffer scale 2^level whose splat kernel best matches a footprint disk (nearest in log diameter)."""
    coarse = np.clip(np.round(np.log2(np.maximum(footprint_px, 1e-6) / DISK_PER_SCALE_PX)), 1, MAX_LEVEL)
    return (coarse * (footprint_px >= math.sqrt(BILINEAR_DISK_PX * 2 * DISK_PER_SCALE_PX))).astype(np.int8)


# --- far-field veil --------------------------------------------------------------------------------------------

def veil_optical_depth_table(classes: SizeClasses, z_limits_m: np.ndarray, d_min_m: float,
                             d_max_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(Z grid (256,), H(Z))``: optical depth of the non-explicit particles from the camera to planar depth Z
    along the optical axis, for Z in [0, d_max]; beyond d_max it grows with the full extinction."""
    z = np.linspace(0.0, d_max_m, VEIL_LUT_SIZE)
    sigma_i = IMAGING_Q_EXT * classes.shadow_area_m2
    # class i is veil for Z < d_min and for Z > its explicit limit
    lo = np.minimum(z[:, None], d_min_m)
    hi = np.maximum(z[:, None] - np.maximum(z_limits_m, d_min_m)[None, :], 0.0)
    return z, (lo + hi) @ sigma_i


def veil_transmission(profile: CameraProfile, depth_m: np.ndarray, table: tuple[np.ndarray, np.ndarray],
                      sigma_per_m: float, d_max_m: float, bins: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel transmission (H, W) float32 of the veil to the scene point at range ``d`` (inf → 0):
    ``τ = k·H(min(d/k, d_max)) + σ·max(d − k d_max, 0)`` with k the ray factor (range/planar depth), H at the
    nearest of the table's depth bins (< 12 cm); that bin is also written into ``bins`` ((H, W) uint8) if given,
    for :func:`transmit_through_particles`."""
    k = ray_factor(profile.width_px, profile.height_px, profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px)
    depth_m = np.ascontiguousarray(depth_m, dtype=np.float32)
    neg_tau = np.empty_like(depth_m)
    _veil_neg_optical_depth(depth_m, k, -np.asarray(table[1], dtype=np.float32),
                            np.float32((VEIL_LUT_SIZE - 1) / d_max_m), np.float32(d_max_m), np.float32(sigma_per_m),
                            neg_tau, np.empty((0, 0), np.uint8) if bins is None else bins)
    return cv2.exp(neg_tau, dst=neg_tau)


@jit(error_model="numpy")
def _veil_neg_optical_depth(depth_m, k, neg_h, bins_per_m, d_max_m, sigma, out, bins):  # pragma: no cover
    """``−τ`` of :func:`veil_transmission` per pixel, floored at −80 (t > 2e-35 leaves no trace in float32, and
    exp of −inf takes a slow path), and the nearest bins into ``bins`` unless it is empty. Two loops per row: the
    first vectorises (divisions), the second is the table lookup."""
    keep = bins.size > 0
    row_bins = np.empty(depth_m.shape[1], np.uint8)
    for y in range(depth_m.shape[0]):
        d, k_row, row = depth_m[y], k[y], out[y]
        nearest_bin = bins[y] if keep else row_bins
        for x in range(row.size):
            nearest_bin[x] = np.uint8(min(d[x] / k_row[x], d_max_m) * bins_per_m + np.float32(0.5))
            far = max(d[x] - k_row[x] * d_max_m, np.float32(0))
            row[x] = sigma * far if sigma > 0 else np.float32(0)           # σ·inf would be nan for σ = 0
        for x in range(row.size):
            row[x] = max(k_row[x] * neg_h[nearest_bin[x]] - row[x], np.float32(-80))


# --- unresolved particles: compound-Poisson opacity per pixel ----------------------------------------------------

UNRESOLVED_CELLS = 256          # depth cells of the variance quadrature (midpoint rule, 1.6 % wide)
UNRESOLVED_TAIL = 2.0 ** -24    # Poisson tail left out of the count tables (its mean is kept by the mark)
UNIFORM_CODES = 1 << 16         # 16-bit uniforms (sensor_noise.uniform_bits)
BUCKET_SHIFT = 8                # count look-up per bin and high byte of the uniform (unresolved_field.buckets)


class UnresolvedField(NamedTuple):
    """Per planar-depth bin b of the veil table (the scene, or the ground, nearest along the pixel's ray): a pixel
    draws ``N`` = the number of ``cuts[b]`` ≤ its 16-bit uniform and gains the opacity ``N · mark[b] · k`` (k the
    ray factor). ``mean``/``variance`` per unit k / k² are the moments matched; ``expected`` the number of
    particles in the image above the ground. ``buckets`` (flat, bin × the uniform's high byte, uint8): N for every
    uniform of the bucket, or +128 where a cut falls inside it (then N counts on from there; also where N could
    exceed 127). ``band`` (H, W) uint8 or None: with motion bands (:func:`streak_motion.motion_bands`) the tables
    hold one veil table of bins per band, and a pixel of band β reads bin ``β·VEIL_LUT_SIZE + b``."""

    cuts: np.ndarray
    mark: np.ndarray
    mean: np.ndarray
    variance: np.ndarray
    expected: float
    buckets: np.ndarray
    band: np.ndarray | None = None


def unresolved_field(profile: CameraProfile, exposure_s: float, classes: SizeClasses, fall_speed,
                     conditions: Conditions, d_min_m: float, near_m: np.ndarray, far_m: np.ndarray,
                     d_max_m: float, bands: MotionBands | None = None) -> UnresolvedField | None:
    """The particles of class i between planar depths ``near_m[i]`` and ``far_m[i]`` (unresolved points, see
    :func:`resolved_depth_limits`) as one compound-Poisson opacity per pixel, or None if there are none.

    Their opacity summed over a pixel whose ray meets the scene at planar depth z is a compound-Poisson sum: a
    pixel's frustum holds ``n_i Z²/(f_x f_y) dZ`` particles per depth step, each of opacity (image area)
    ``m = (π/4) D² f_x f_y k / Z²`` spread by :func:`splat_streaks` over a streak of ℓ px along its major axis
    (motion + footprint) and two pixels across. Hence (Campbell's theorem) the mean ``k Σ_i σ_i |[near_i, far_i] ∩
    [0, z]|`` — the same optical depth as the veil's, so the mean image is unchanged — and the variance
    ``k² Σ_i ∫ σ_i m_i(Z) s(ℓ_i(Z)) dZ``, with ``s(ℓ) = ⅔ (1 − ℓ/3)`` (ℓ ≤ 1) or ``⅔ (ℓ − ⅓)/ℓ²`` the mean of
    Σ (pixel share)² of a box of length ℓ at a uniform offset (⅔: the two-pixel split across). A pixel draws a
    Poisson count of rate mean²/variance, each adding variance/mean: both moments matched per pixel (quantised to
    16-bit uniforms; the mark is set so that the mean stays exact). What is not kept: the correlation between the
    one to three pixels a single particle touches, and the spread of the individual opacities. The streak length
    is the lateral motion's; with ``bands`` (:func:`streak_motion.motion_bands`: motion that depends on the image
    position), ``near_m`` is (bands, classes), the streak length the band's mean, and the tables are per band (band
    b's bins at ``b·VEIL_LUT_SIZE + bin``; ``band`` the per-pixel map)."""
    if bands is None:
        moments = [_unresolved_moments(profile, exposure_s, classes, fall_speed, conditions, near_m, far_m, d_max_m)]
    else:
        moments = [_unresolved_moments(profile, exposure_s, classes, fall_speed, conditions, near_m[b], far_m,
                                       d_max_m, bands.major[b]) for b in range(near_m.shape[0])]
    if all(m is None for m in moments):
        return None
    empty = np.zeros(VEIL_LUT_SIZE)
    mean = np.concatenate([empty if m is None else m[0] for m in moments])
    variance = np.concatenate([empty if m is None else m[1] for m in moments])
    rate = np.divide(mean ** 2, variance, out=np.zeros_like(mean), where=variance > 0)
    counts = np.arange(int(rate.max() + 12 * math.sqrt(rate.max())) + 32)
    top = int(np.argmax(pdtrc(counts, rate.max()) < UNRESOLVED_TAIL)) + 1      # P(N ≥ top) < the tail
    cdf = pdtr(counts[:top], rate[:, None])
    cuts = np.empty((mean.size, top + 1), np.int32)
    cuts[:, :top] = np.rint(cdf * UNIFORM_CODES)
    cuts[:, 0] = np.where(mean > 0, np.minimum(cuts[:, 0], UNIFORM_CODES - 1), UNIFORM_CODES)   # never lose the mean
    cuts[:, top] = UNIFORM_CODES                                                 # stops the count
    counted = (UNIFORM_CODES - cuts[:, :top]).sum(axis=1) / UNIFORM_CODES        # E[N] of the quantised draw
    mark = np.divide(mean, counted, out=np.zeros_like(mean), where=counted > 0).astype(np.float32)
    field = (far_m > near_m) & (classes.number > 0)
    if bands is None:
        z_grid, vol, _ = above_ground_volume_table(profile, d_min_m, d_max_m)
        near, far = near_m[field], far_m[field]
        expected = float(classes.number[field] @ (np.interp(far, z_grid, vol) - np.interp(near, z_grid, vol)))
    else:
        z_grid, volume = _band_volume_table(profile, bands, d_min_m, d_max_m)
        expected = float(sum(classes.number @ np.where(field[b], np.interp(far_m, z_grid, volume[b]) -
                                                       np.interp(near_m[b], z_grid, volume[b]), 0.0)
                             for b in range(near_m.shape[0])))
    return UnresolvedField(cuts, mark, mean, variance, expected, count_buckets(cuts),
                           None if bands is None else bands.band)


def _unresolved_moments(profile: CameraProfile, exposure_s: float, classes: SizeClasses, fall_speed,
                        conditions: Conditions, near_m: np.ndarray, far_m: np.ndarray, d_max_m: float,
                        major_px_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`unresolved_field`'s mean and variance per unit ray factor at each veil-table bin, or None if no class
    has particles between ``near_m`` and ``far_m``; the motion along the streak (px·m) is ``major_px_m`` per class
    if given, else the lateral motion's."""
    field = (far_m > near_m) & (classes.number > 0)
    if not field.any():
        return None
    near, far = near_m[field], far_m[field]
    sigma = IMAGING_Q_EXT * classes.shadow_area_m2[field]
    d = classes.rms_d_mm[field]
    # variance: midpoint rule on geometric cells, each class over the part of the cell inside [near_i, far_i]
    edges = np.geomspace(near.min(), far.max(), UNRESOLVED_CELLS + 1)
    mid = np.sqrt(edges[1:] * edges[:-1])
    inside = np.clip(np.minimum(edges[1:, None], far) - np.maximum(edges[:-1, None], near), 0.0, None)
    if major_px_m is None:
        v = relative_velocity_optical(conditions, fall_speed(d))
        motion = exposure_s * np.maximum(np.abs(v[:, 0]) * profile.fx_px, np.abs(v[:, 1]) * profile.fy_px)
    else:
        motion = major_px_m[field]
    length = motion / mid[:, None] + np.hypot(d * 1e-3 * focal_px(profile) / mid[:, None],
                                              defocus_px(profile, mid)[:, None])
    share2 = np.where(length <= 1.0, 1.0 - length / 3.0, (length - 1.0 / 3.0) / length ** 2) * (2.0 / 3.0)
    mass = math.pi / 4 * (d * 1e-3) ** 2 * profile.fx_px * profile.fy_px / mid[:, None] ** 2
    cumulative = np.concatenate([[0.0], np.cumsum((inside * sigma * mass * share2).sum(axis=1))])
    # per veil-table bin (the kernel's nearest bin of min(scene, ground, d_max))
    z = np.linspace(0.0, d_max_m, VEIL_LUT_SIZE)
    return np.clip(z[:, None] - near, 0.0, far - near) @ sigma, np.interp(z, edges, cumulative)


def count_buckets(cuts: np.ndarray) -> np.ndarray:
    """:class:`UnresolvedField`'s ``buckets`` of the (bins, counts) ``cuts`` table."""
    start = np.arange(0, UNIFORM_CODES, 1 << BUCKET_SHIFT)
    # the number of cuts ≤ u per row: one search in the rows laid end to end (each row's cuts are sorted)
    offset = (np.arange(cuts.shape[0], dtype=np.int64) * 2 * UNIFORM_CODES)[:, None]
    flat = (cuts + offset).ravel()

    def at_most(u):
        return np.searchsorted(flat, (u[None, :] + offset).ravel(), side="right").reshape(offset.size, -1) - \
            np.arange(cuts.shape[0])[:, None] * cuts.shape[1]
    at_start, at_end = at_most(start), at_most(start + (1 << BUCKET_SHIFT) - 1)
    walk = (at_end != at_start) | (at_start > 127)
    return (np.minimum(at_start, 127) + 128 * walk).astype(np.uint8).ravel()


def transmit_through_particles(t: np.ndarray, coverage: np.ndarray, profile: CameraProfile, depth_m: np.ndarray,
                               field: UnresolvedField | None, d_max_m: float, rng: np.random.Generator,
                               bins: np.ndarray | None = None) -> float:
    """``t ← t·(1 − M)`` in place per pixel, M the opacity of the explicit streaks (``coverage``) plus, with a
    ``field``, the :func:`unresolved_field` draw (particles up to the scene's planar depth, or to the ground's below
    the horizon: none are under the ground; at the nearest bin of the veil table), clipped to 1 (written back into
    ``coverage``). Returns the mean M over the image. ``bins``: the scene's veil-table bins from
    :func:`veil_transmission` (the nearer of those and the ground's is the bin: the same, as rounding is
    monotonic), else computed here."""
    return _transmit(t, coverage, profile, depth_m, field, d_max_m, rng, bins, None)


def blend_through_particles(layout: SiteLayout, signal: np.ndarray, values, t: np.ndarray, coverage: np.ndarray,
                            profile: CameraProfile, depth_m: np.ndarray, field: UnresolvedField | None,
                            d_max_m: float, rng: np.random.Generator, bins: np.ndarray | None = None
                            ) -> tuple[np.ndarray, float]:
    """:func:`~roadview_noise.physics.photometry.composite` ``(layout, signal, t·(1 − M), values)`` with the
    t·(1 − M) of :func:`transmit_through_particles` (same arguments; ``t`` is left as it is), in the same pass
    and with the same float32 operations: the blended signal and the mean M."""
    rows_values, rows = blend_operands(layout, signal, values)
    out = np.empty_like(rows)
    mean = _transmit(t, coverage, profile, depth_m, field, d_max_m, rng, bins, (rows_values, rows, out))
    return out.reshape(np.shape(signal)), mean


def _transmit(t, coverage, profile, depth_m, field, d_max_m, rng, bins, blend) -> float:
    """The pass of both: ``blend`` None or (S per value of a row, signal rows, output rows); the mean M."""
    h, w = coverage.shape
    k = ray_factor(profile.width_px, profile.height_px, profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px)
    below = np.arange(h) - profile.cy_px
    with np.errstate(divide="ignore"):
        ground = np.where(below > 0, profile.height_above_ground_m * profile.fy_px / below, np.inf)
    no_band = np.zeros((0, 0), np.uint8)
    if field is None:                                  # nothing drawn: no tables, no uniforms
        cuts, buckets, mark, bits, band = (np.zeros((0, 0), np.int32), np.zeros(0, np.uint8),
                                           np.zeros(0, np.float32), np.zeros(0, np.uint16), no_band)
    else:
        cuts, buckets, mark, bits = field.cuts, field.buckets, field.mark, uniform_bits(rng, h * w)
        band = no_band if field.band is None else field.band
    if blend is None:                                  # t·(1 − M) back into t
        blend = np.zeros((1, 1), np.float32), np.zeros((0, 0), np.float32), np.zeros((0, 0), np.float32)
    total = _transmit_kernel(t, coverage, np.ascontiguousarray(depth_m, dtype=np.float32), k,
                             np.empty((0, 0), np.uint8) if bins is None else bins,
                             np.minimum(ground, d_max_m).astype(np.float32),
                             np.float32((VEIL_LUT_SIZE - 1) / d_max_m), cuts, buckets, mark, bits, band,
                             field is not None, *blend)
    return total / coverage.size


@jit(inline="always")
def _count(b, u, cuts, buckets):                                         # pragma: no cover - compiled
    """N of :class:`UnresolvedField` for a pixel of (banded) bin ``b`` and 16-bit uniform ``u``: its bucket's
    count, counted on through ``cuts[b]`` where the bucket says so (rare)."""
    c = buckets[(b << (16 - BUCKET_SHIFT)) | (u >> BUCKET_SHIFT)]
    n = np.int32(c & 127)
    if c >= 128:
        while u >= cuts[b, n]:
            n += 1
    return n


@jit(error_model="numpy")
def _transmit_kernel(t, coverage, depth_m, k, scene_bins, ground_z, bins_per_m, cuts, buckets, mark, bits, band,
                     draw, values, signal, out):                              # pragma: no cover - compiled
    """Per row: the bins (vectorised; the nearer of ``scene_bins`` and the ground's if given; in the table of the
    pixel's ``band`` unless it is empty), then one loop over the pixels: the count (:func:`_count`), M back into
    ``coverage`` and either t·(1 − M) back into ``t`` (``signal`` empty) or the blend of ``composite`` into ``out``
    (:func:`~roadview_noise.physics.photometry.blend_operands`: rows of W·3 RGB values or W mosaic sites);
    returns Σ M. (The count inside the blend's loop, not in loops of its own that fill a row of counts: one pass
    less per row, docs/performance.md round 24.)"""
    one, half, zero = np.float32(1), np.float32(0.5), np.float32(0)
    w = depth_m.shape[1]
    blend, rgb = signal.size > 0, signal.shape[1] == 3 * w
    bins = np.zeros(w, np.int32)                                         # of the pixel's band's table
    a0, a1, a2 = (values[0, 0], values[0, 1], values[0, 2]) if rgb else (one, one, one)   # S (R, G, B) on RGB rows
    total = 0.0                                                                  # Σ M
    for y in range(depth_m.shape[0]):
        d, k_row, cov, t_row = depth_m[y], k[y], coverage[y], t[y]
        u_row = bits[y * w:(y + 1) * w]
        if draw:
            limit = ground_z[y]
            if scene_bins.size > 0:
                ground_bin, scene_row = np.uint8(limit * bins_per_m + half), scene_bins[y]
                for x in range(w):
                    bins[x] = min(scene_row[x], ground_bin)
            else:
                for x in range(w):
                    bins[x] = np.uint8(min(d[x] / k_row[x], limit) * bins_per_m + half)
            if band.size > 0:
                band_row = band[y]
                for x in range(w):
                    bins[x] += np.int32(band_row[x]) * VEIL_LUT_SIZE
        if not blend:
            for x in range(w):
                added = np.float32(_count(bins[x], np.int32(u_row[x]), cuts, buckets)) * mark[bins[x]] if draw \
                    else zero
                m = min(cov[x] + added * k_row[x], one)
                cov[x] = m
                t_row[x] *= one - m
        elif rgb:                                  # the three values of a pixel with its t·(1 − M)
            s_row, o_row = signal[y], out[y]
            for x in range(w):
                added = np.float32(_count(bins[x], np.int32(u_row[x]), cuts, buckets)) * mark[bins[x]] if draw \
                    else zero
                m = min(cov[x] + added * k_row[x], one)
                cov[x] = m
                tm = t_row[x] * (one - m)
                o_row[3 * x] = a0 + tm * (s_row[3 * x] - a0)
                o_row[3 * x + 1] = a1 + tm * (s_row[3 * x + 1] - a1)
                o_row[3 * x + 2] = a2 + tm * (s_row[3 * x + 2] - a2)
        else:
            a_row, s_row, o_row = values[y % values.shape[0]], signal[y], out[y]
            for x in range(w):
                added = np.float32(_count(bins[x], np.int32(u_row[x]), cuts, buckets)) * mark[bins[x]] if draw \
                    else zero
                m = min(cov[x] + added * k_row[x], one)
                cov[x] = m
                tm = t_row[x] * (one - m)
                o_row[x] = a_row[x] + tm * (s_row[x] - a_row[x])
        total += _row_sum(cov)
    return total


@jit(error_model="numpy", fastmath=True)
def _row_sum(a):                                                              # pragma: no cover - compiled
    """Σ a (float64; in any order: vectorised)."""
    total = 0.0
    for i in range(a.size):
        total += np.float64(a[i])
    return total


# --- one frame -------------------------------------------------------------------------------------------------

class ParticleTables(NamedTuple):
    """What :func:`render_precipitation` derives from the camera, the medium and the conditions alone: per class
    the depth limits of the visible (:func:`explicit_depth_limits`) and of the resolved particles
    (:func:`resolved_depth_limits`), the :func:`unresolved_field` between them, the
    :func:`veil_optical_depth_table` of the rest (read-only arrays); ``split``, where the streak length depends on
    the image position (:func:`streak_motion.motion_bands`: ego motion, head wind), the :class:`BandSplit` of the
    resolved limits per band (``resolved`` is then their largest per class), else None."""

    limits: np.ndarray
    resolved: np.ndarray
    unresolved: UnresolvedField | None
    veil: tuple[np.ndarray, np.ndarray]
    split: BandSplit | None = None


class BandSplit(NamedTuple):
    """The particles :func:`sample_particles` keeps in each band of :class:`MotionBands`: per band and class the
    resolved depth ``limits`` (m), the float32 ``threshold`` the sampled Z is compared with (inf where the band
    keeps the whole sampled slab: Z may pass its limit by float32 rounding), and per class the ``expected`` number
    kept (volume of each band's slab above the ground)."""

    bands: MotionBands
    limits: np.ndarray
    threshold: np.ndarray
    expected: np.ndarray


def band_split(profile: CameraProfile, classes: SizeClasses, bands: MotionBands, limits_m: np.ndarray,
               z_limits_m: np.ndarray, d_min_m: float, d_max_m: float) -> BandSplit:
    """:class:`BandSplit` of the (bands, classes) ``limits_m`` for particles sampled up to ``z_limits_m``."""
    slab = np.clip(z_limits_m, d_min_m, d_max_m)
    limits = np.minimum(np.clip(limits_m, d_min_m, d_max_m), slab)
    threshold = np.where(limits >= slab, np.inf, limits).astype(np.float32)
    z_grid, volume = _band_volume_table(profile, bands, d_min_m, d_max_m)
    expected = classes.number * sum(np.interp(limits[b], z_grid, volume[b]) for b in range(limits.shape[0]))
    for a in (limits, threshold, expected):
        a.flags.writeable = False
    return BandSplit(bands, limits, threshold, expected)


def _band_volume_table(profile: CameraProfile, bands: MotionBands, d_min_m: float, d_max_m: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``(Z grid, V)``: 1024 planar depths from d_min to d_max and each band's frustum volume above the ground up to
    them (:func:`streak_motion.band_volume`)."""
    z_grid = np.geomspace(d_min_m, d_max_m, 1024)
    return z_grid, band_volume(profile, bands.rows, z_grid, bottom_row_px(profile, z_grid))


# thread CPU per frame (ns; issue 19 round 10, the 2-core VM): a particle drawn one by one (sampled, sorted,
# splatted), a sampled particle's band test, a pixel's per-pixel draw (its uniform and count); motion bands are
# used only where the particles they leave to the per-pixel draw save more than the bands cost
COST_EXPLICIT_NS, COST_BAND_TEST_NS, COST_DRAW_NS = 48.0, 6.0, 2.0


@disk_cached(maxsize=8)                # a worker's first frame reads them (the table cache) instead of building them
def particle_tables(profile: CameraProfile, exposure_s: float, classes: SizeClasses, fall_speed,
                    conditions: Conditions, d_min_m: float, d_max_m: float, min_opacity: float,
                    min_extent_px: float) -> ParticleTables:
    """:class:`ParticleTables`, built once per camera, medium and conditions (≈ 5 ms for snow's 199 classes;
    ≈ 0.1 s more with motion bands), kept on disk (:mod:`roadview_noise.table_cache`): the image-wide split, or
    the :func:`band_tables` where they are cheaper by the ``COST_*`` figures."""
    limits = explicit_depth_limits(profile, exposure_s, classes, fall_speed, conditions, d_min_m, d_max_m,
                                   min_opacity)
    resolved = resolved_depth_limits(profile, exposure_s, classes, fall_speed, conditions, d_min_m, d_max_m,
                                     limits, min_extent_px)
    field = unresolved_field(profile, exposure_s, classes, fall_speed, conditions, d_min_m, resolved, limits,
                             d_max_m)
    split = None
    banded = band_tables(profile, exposure_s, classes, fall_speed, conditions, d_min_m, d_max_m, limits,
                         min_extent_px)
    if banded is not None:
        z_grid, vol, _ = above_ground_volume_table(profile, d_min_m, d_max_m)
        pixels = profile.width_px * profile.height_px
        cost = COST_EXPLICIT_NS * float(classes.number @ np.interp(resolved, z_grid, vol)) + \
            (0.0 if field is None else COST_DRAW_NS * pixels)
        cost_banded = COST_EXPLICIT_NS * float(banded[2].expected.sum()) + COST_DRAW_NS * pixels + \
            COST_BAND_TEST_NS * float(classes.number @ np.interp(banded[0], z_grid, vol))
        if cost_banded < cost:
            resolved, field, split = banded
    out = ParticleTables(limits, resolved, field, veil_optical_depth_table(classes, limits, d_min_m, d_max_m), split)
    for a in (limits, resolved, *out.veil, *(a for a in (field or ()) if isinstance(a, np.ndarray))):
        a.flags.writeable = False
    return out


def band_tables(profile: CameraProfile, exposure_s: float, classes: SizeClasses, fall_speed, conditions: Conditions,
                d_min_m: float, d_max_m: float, limits_m: np.ndarray, min_extent_px: float
                ) -> tuple[np.ndarray, UnresolvedField | None, BandSplit] | None:
    """With :func:`streak_motion.motion_bands` (None without): the resolved limits per class (the largest of the
    bands'), the :func:`unresolved_field` per band and the :class:`BandSplit` of the particles to sample."""
    bands = motion_bands(profile, exposure_s, relative_velocity_optical(conditions, fall_speed(classes.rms_d_mm)),
                         classes.number, d_min_m, d_max_m, min_extent_px)
    if bands is None:
        return None
    per_band = resolved_depth_limits(profile, exposure_s, classes, fall_speed, conditions, d_min_m, d_max_m,
                                     limits_m, min_extent_px, bands.bound)
    resolved = per_band[bands.rows.sum(axis=1) > 0].max(axis=0)
    field = unresolved_field(profile, exposure_s, classes, fall_speed, conditions, d_min_m, per_band, limits_m,
                             d_max_m, bands)
    return resolved, field, band_split(profile, classes, bands, per_band, resolved, d_min_m, d_max_m)


def render_precipitation(frame, model_id: str, *, classes: SizeClasses, fall_speed, radiance, exposure_s: float,
                         d_min_m: float, d_max_m: float, min_opacity: float, min_extent_px: float,
                         rng: np.random.Generator):
    """Rain or snow on a camera or raw frame: explicit streaks in front of the scene, veil behind them.

    ``radiance(layout, signal, depth, depth_valid) -> (3,)`` gives the particles' radiance S (R, G, B) from the
    frame (``depth_valid``: ``frame.depth_valid``, :class:`~roadview_noise.physics.photometry.FrameSample`).
    Per site: ``I' = S + (1 − M)·t·(I − S)`` with M the streak opacity and t the veil transmission."""
    depth = frame_depth_m(frame, model_id)
    h, w = depth.shape
    profile = fit_to_image(frame.profile, w, h)
    layout = SiteLayout.of(frame)
    signal = frame.signal()
    s = np.asarray(radiance(layout, signal, depth, frame.depth_valid), dtype=float)
    tables = particle_tables(profile, exposure_s, classes, fall_speed, frame.conditions, d_min_m, d_max_m,
                             min_opacity, min_extent_px)
    particles, expected = sample_particles(rng, profile, classes, tables.resolved, d_min_m, d_max_m, fall_speed,
                                           tables.split)
    coverage, n_visible = render_coverage(profile, particles, frame.conditions, exposure_s, depth, d_min_m)
    sigma = classes.extinction_per_m()
    bins = np.empty((h, w), np.uint8)
    t = veil_transmission(profile, depth, tables.veil, sigma, d_max_m, bins)
    out, mean_coverage = blend_through_particles(layout, signal, s, t, coverage, profile, depth, tables.unresolved,
                                                 d_max_m, rng, bins)
    return frame.with_signal(out), {
        "particles_expected": expected,
        "particles_drawn": int(particles.z.size),
        "particles_visible": n_visible,
        "particles_unresolved_expected": 0.0 if tables.unresolved is None else tables.unresolved.expected,
        "mean_streak_opacity": mean_coverage,
        "veil_extinction_per_m": sigma,
        "particle_radiance": [float(v) for v in s],
        "exposure_time_s": float(exposure_s),
    }
