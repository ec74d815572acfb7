"""Particle renderer of camera rain/snow (models.md §2.2, §2.3, §2.9): size classes vs closed forms, Poisson
sampling, streak geometry and photometry, occlusion, far-field veil."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import gamma as gamma_fn
from scipy.special import gammainc

from roadview_noise.physics import particles as P
from roadview_noise.physics.dsd import (BRANDES_SNOW_GAMMA, exponential_number_density, geometric_extinction_per_m,
                                        gunn_marshall, liquid_water_content_g_per_m3, marshall_palmer, snowfall)
from roadview_noise.physics.fall_speed import snow_power_law_m_per_s
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.types import CameraProfile, Conditions

LUCID = lucid_triton_028s()


# --- size distributions ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("rate", [10.0, 20.0, 50.0, 83.0])
def test_marshall_palmer_number_density_and_lwc_vs_closed_form(rate):
    classes = P.rain_classes(rate)
    n0, lam = marshall_palmer(rate)
    assert classes.number_per_m3 == pytest.approx(exponential_number_density(n0, lam, 0.5, 6.0), rel=0.01)
    assert classes.liquid_water_g_per_m3() == pytest.approx(liquid_water_content_g_per_m3(n0, lam, 0.5, 6.0),
                                                            rel=0.01)
    assert classes.extinction_per_m() == pytest.approx(geometric_extinction_per_m(n0, lam, 0.5, 6.0, q_ext=1.0),
                                                       rel=0.01)
    assert len(classes.number) == 55 and classes.edges_mm[0] == 0.5 and classes.edges_mm[-1] == 6.0


def test_marshall_palmer_50_mm_per_h_values():
    """Λ(50) = 1.8030 mm⁻¹ (models.md §8); 0.5–6 mm drops: 1971 m⁻³ (exact integral), extinction 4.0e-3 m⁻¹ with
    Q = 2 (§2.2), so 2.0e-3 m⁻¹ for the imaging (shadow) extinction."""
    assert marshall_palmer(50.0)[1] == pytest.approx(1.8030, rel=1e-4)
    classes = P.rain_classes(50.0)
    assert classes.number_per_m3 == pytest.approx(8000 / 1.8030 * (math.exp(-0.5 * 1.8030) - math.exp(-6 * 1.8030)),
                                                  rel=1e-3)
    assert classes.extinction_per_m(q_ext=2.0) == pytest.approx(4.0e-3, rel=0.01)


def test_brandes_snow_vs_incomplete_gamma():
    n0, mu, lam = BRANDES_SNOW_GAMMA[3.03]
    a = mu + 1
    closed = n0 * gamma_fn(a) / lam ** a * (gammainc(a, 20 * lam) - gammainc(a, 0.1 * lam))
    assert P.snow_classes(3.03, "brandes").number_per_m3 == pytest.approx(closed, rel=0.01)


def test_gunn_marshall_snow_vs_closed_form():
    """The camera's flakes are the LiDAR's snowfall (one DSD): flakes of 0.1–20 mm geometric diameter are the melted
    diameters between the size law's inverses of the bounds; their shadow area is the LiDAR's extinction / Q_ext."""
    snow = snowfall(3.03)
    lo, hi = (float(snow.size.melted_mm(d)) for d in (0.1, 20.0))
    classes = P.snow_classes(3.03, "gunn_marshall")
    assert snow.lam_per_mm == gunn_marshall(3.03)[1]
    assert classes.number_per_m3 == pytest.approx(exponential_number_density(snow.n0_per_m3_mm, snow.lam_per_mm,
                                                                             lo, hi), rel=0.01)
    assert classes.extinction_per_m(q_ext=2.0) == pytest.approx(snow.extinction_per_m(), rel=0.01)


def test_terminal_speeds_follow_the_cited_laws():
    assert float(P.rain_fall_speed_m_per_s(2.0)) == pytest.approx(6.014, rel=1e-3)     # Atlas & Ulbrich, §8
    assert float(P.rain_fall_speed_m_per_s(1.0)) == pytest.approx(3.778, rel=1e-6)
    assert float(snow_power_law_m_per_s(1.0)) == pytest.approx(0.8)                    # a D^b, §2.3 [PROP]


# --- sampling ------------------------------------------------------------------------------------------------------

def _small_profile() -> CameraProfile:
    return LUCID.resized(242, 183)


def test_poisson_counts_are_unbiased_and_diameters_follow_the_dsd():
    prof = _small_profile()
    classes = P.rain_classes(5.0)
    limits = np.full(len(classes.number), 3.0)
    counts, diameters = [], []
    for seed in range(200):
        parts, expected = P.sample_particles(np.random.default_rng(seed), prof, classes, limits, 0.5, 30.0,
                                             P.rain_fall_speed_m_per_s)
        counts.append(parts.z.size)
        diameters.append(parts.d_mm)
    sd = math.sqrt(expected / len(counts))
    assert abs(np.mean(counts) - expected) < 4 * sd                  # no floor bias (models.md §2.2 [PROP])
    d = np.concatenate(diameters)
    lam = marshall_palmer(5.0)[1]
    # mean of the exponential truncated to [0.5, 6] mm
    lo, hi = 0.5, 6.0
    mean = lo + 1 / lam - (hi - lo) * math.exp(-lam * (hi - lo)) / (1 - math.exp(-lam * (hi - lo)))
    assert abs(d.mean() - mean) < 4 * d.std() / math.sqrt(d.size)
    assert d.min() >= 0.5 and d.max() <= 6.0


def test_positions_fill_the_above_ground_frustum_uniformly():
    prof = _small_profile()
    classes = P.rain_classes(10.0)
    limits = np.full(len(classes.number), 8.0)
    parts, expected = P.sample_particles(np.random.default_rng(3), prof, classes, limits, 0.5, 30.0,
                                         P.rain_fall_speed_m_per_s)
    z_grid, vol, _ = P.above_ground_volume_table(prof, 0.5, 30.0)
    assert expected == pytest.approx(classes.number_per_m3 * np.interp(8.0, z_grid, vol), rel=1e-6)
    # planar depths: fraction nearer than 4 m equals the volume fraction
    frac = np.interp(4.0, z_grid, vol) / np.interp(8.0, z_grid, vol)
    n = parts.z.size
    assert abs(np.mean(parts.z < 4.0) - frac) < 4 * math.sqrt(frac * (1 - frac) / n)
    assert parts.z.min() >= 0.5 - 1e-4 and parts.z.max() <= 8.0 + 1e-3
    # all in the image and above the ground (optical Y is down, ground at +h)
    u = prof.fx_px * parts.x / parts.z + prof.cx_px
    v = prof.fy_px * parts.y / parts.z + prof.cy_px
    assert np.all((u >= -0.5 - 1e-3) & (u <= prof.width_px - 0.5 + 1e-3) & (v >= -0.5 - 1e-3))
    assert np.all(parts.y <= prof.height_above_ground_m + 1e-5)
    # uniform across the image width (pixel centres at integers: the image spans −½ … W − ½)
    assert abs(np.mean(u < (prof.width_px - 1) / 2) - 0.5) < 4 * math.sqrt(0.25 / n)


# --- streak geometry and photometry ------------------------------------------------------------------------------

def _one(x=0.0, y=0.0, z=5.0, d_mm=2.0, v=None) -> P.Particles:
    v = float(P.rain_fall_speed_m_per_s(d_mm)) if v is None else v
    return P.Particles(*(np.array([c], dtype=np.float32) for c in (x, y, z, d_mm, v)))


def _moments(cov: np.ndarray):
    """Mass, axial length estimate sqrt(12·var) along the principal axis, and its angle from vertical (deg)."""
    v, u = np.mgrid[0:cov.shape[0], 0:cov.shape[1]]
    m = cov.sum()
    cu, cv = (cov * u).sum() / m, (cov * v).sum() / m
    suu = (cov * (u - cu) ** 2).sum() / m
    svv = (cov * (v - cv) ** 2).sum() / m
    suv = (cov * (u - cu) * (v - cv)).sum() / m
    lam_max = 0.5 * (suu + svv) + math.sqrt(0.25 * (suu - svv) ** 2 + suv ** 2)
    angle = 0.5 * math.degrees(math.atan2(2 * suv, svv - suu))
    return m, math.sqrt(12 * lam_max), angle


def _render(prof, parts, conditions=Conditions(), depth=None, exposure=0.005):
    depth = np.full((prof.height_px, prof.width_px), np.inf, np.float32) if depth is None else depth
    return P.render_coverage(prof, parts, conditions, exposure, depth, 0.5)


def test_streak_length_is_speed_times_exposure_times_focal_over_depth():
    """A 2 mm drop at 5 m on the optical axis: L = v T f / Z = 6.84 px (Lucid K, square pixels). The rendered
    streak (a uniform segment lengthened by the footprint) has sqrt(12·var) = L + footprint along its axis."""
    parts = _one(z=5.0)
    u0, v0, _, u1, v1, _ = P.streak_endpoints(LUCID, parts, Conditions(), 0.005)
    expected = 6.0145 * 0.005 * LUCID.fy_px / 5.0
    assert float(np.hypot(u1 - u0, v1 - v0)[0]) == pytest.approx(expected, rel=1e-3)
    cov, n_visible = _render(LUCID, parts)
    mass, length, angle = _moments(cov)
    footprint = math.hypot(2e-3 * LUCID.fx_px / 5.0, float(P.defocus_px(LUCID, 5.0)))
    assert abs(length - footprint - expected) < 1.0
    assert abs(angle) < 0.5 and n_visible == 1


def test_lucid_streak_oracle_of_models_md():
    """models.md §2.2/§8: L = vT/p_v + D/p_v = 7.876 px for D = 2 mm at 5 m with the reference's 61.6° vertical
    FoV (f_y = 1227.9 px). Our formulation gives the same motion length plus the drop's own image; it differs in
    photometry (exact coverage instead of τ/T = 0.2019 per touched pixel) and adds the defocus disk."""
    prof = CameraProfile.from_fov("lucid_ref", 1936, 1464, 80.8, 61.6)
    parts = _one(z=5.0)
    u0, v0, _, u1, v1, _ = P.streak_endpoints(prof, parts, Conditions(), 0.005)
    assert float(abs(v1 - v0)[0] + 2e-3 * prof.fy_px / 5.0) == pytest.approx(7.876, abs=0.01)


def test_crosswind_tilts_the_streak_by_atan_u_over_vt():
    """§2.9 oracle: 3 m/s crosswind, 2 mm drop (v_t = 6.014 m/s): 26.5° from vertical at the image centre; the
    wind blowing towards the left (+y) moves the drop to the image left (−u) as it falls (+v)."""
    wind = Conditions(wind_velocity_m_per_s=(0.0, 3.0, 0.0))
    parts = _one(z=2.0)
    u0, v0, _, u1, v1, _ = P.streak_endpoints(LUCID, parts, wind, 0.005)
    geometric = math.degrees(math.atan2(float(u0[0] - u1[0]), float(v1[0] - v0[0])))
    assert geometric == pytest.approx(26.5, abs=0.05)
    _, _, angle = _moments(_render(LUCID, parts, wind)[0])
    assert -angle == pytest.approx(26.5, abs=1.0)


def test_along_axis_wind_does_not_tilt_at_the_centre():
    parts = _one(z=4.0)
    u0, _, _, u1, _, _ = P.streak_endpoints(LUCID, parts, Conditions(wind_velocity_m_per_s=(5.0, 0.0, 0.0)), 0.005)
    assert abs(float(u1[0] - u0[0])) < 1e-4


def test_coverage_is_the_particle_image_area_and_at_most_one():
    """Σ α over the pixels = (π/4) D² f_x f_y k / Z² (exposure-fraction photometry conserves the image area); a
    drop that does not move in the image covers its pixels for at most the whole exposure (τ ≤ T)."""
    for z, x in ((5.0, 0.0), (3.0, 1.5), (1.0, 0.2)):
        parts = _one(x=x, z=z)
        cov, _ = _render(LUCID, parts)
        k = math.hypot(x, z) / z
        area = math.pi / 4 * (2e-3) ** 2 * LUCID.fx_px * LUCID.fy_px * k / z ** 2
        assert cov.sum() == pytest.approx(area, rel=0.01)
    still = _one(z=3.0, d_mm=5.0, v=0.0)                 # 1.9 px drop, no motion
    cov, _ = _render(LUCID, still)
    assert 0.3 < cov.max() <= 1.0


def test_occlusion_compares_metres_with_metres():
    prof = LUCID
    depth = np.full((prof.height_px, prof.width_px), np.inf, np.float32)
    depth[:, : prof.width_px // 2 + 200] = 4.0                 # wall at 4 m over the image centre
    behind, _ = _render(prof, _one(z=6.0), depth=depth)
    front, n_front = _render(prof, _one(z=3.0), depth=depth)
    assert behind.sum() == 0.0
    assert front.sum() > 0 and n_front == 1


def test_defocus_disk_oracle():
    """models.md §2.2 [PROP]: f²/(N d p) = 2.54 px at 1.5 m and 7.6 px at 0.5 m for the Lucid lens."""
    assert float(P.defocus_px(LUCID, 1.5)) == pytest.approx(2.54, abs=0.01)
    assert float(P.defocus_px(LUCID, 0.5)) == pytest.approx(7.62, abs=0.02)
    focused = CameraProfile.from_fov("f", 1936, 1464, 80.8, focus_distance_m=5.0)
    assert float(P.defocus_px(focused, 5.0)) == 0.0


def test_near_blurred_drop_keeps_its_area_on_a_coarse_buffer():
    parts = _one(z=0.6, d_mm=3.0)
    assert P.footprint_level(np.atleast_1d(np.hypot(3e-3 * LUCID.fx_px / 0.6, P.defocus_px(LUCID, 0.6))))[0] >= 2
    cov, _ = _render(LUCID, parts)
    area = math.pi / 4 * (3e-3) ** 2 * LUCID.fx_px * LUCID.fy_px / 0.6 ** 2
    assert cov.sum() == pytest.approx(area, rel=0.02)
    assert cov.max() < 0.5                                   # spread over the defocus disk


# --- explicit / veil split ---------------------------------------------------------------------------------------

def test_explicit_limits_follow_the_opacity_threshold():
    classes = P.rain_classes(50.0)
    limits = P.explicit_depth_limits(LUCID, 0.005, classes, P.rain_fall_speed_m_per_s, Conditions(), 0.5, 30.0,
                                     0.02)
    assert np.all((limits >= 0.5) & (limits <= 30.0))
    assert np.all(np.diff(limits[limits > 0.5]) >= 0)            # bigger drops are seen farther
    d = classes.rms_d_mm
    big = limits > 0.5
    alpha = P.peak_opacity(LUCID, 0.005, d[big], P.rain_fall_speed_m_per_s(d[big]), limits[big])
    assert np.all(alpha >= 0.02)
    lower = P.explicit_depth_limits(LUCID, 0.005, classes, P.rain_fall_speed_m_per_s, Conditions(), 0.5, 30.0,
                                    0.01)
    assert np.all(lower >= limits)


def test_veil_plus_explicit_particles_is_the_whole_medium():
    """Mean conservation: along any ray, explicit particles cover on average Σ σ_i (Z_i − d_min) and the veil
    adds H; together the full extinction σ·d (Q = 1), whatever the threshold."""
    classes = P.rain_classes(50.0)
    limits = P.explicit_depth_limits(LUCID, 0.005, classes, P.rain_fall_speed_m_per_s, Conditions(), 0.5, 30.0,
                                     0.02)
    z, h = P.veil_optical_depth_table(classes, limits, 0.5, 30.0)
    sigma_i = classes.shadow_area_m2
    explicit = np.clip(z[:, None] - 0.5, 0, None)
    explicit = np.minimum(explicit, np.maximum(limits - 0.5, 0)[None, :]) @ sigma_i
    np.testing.assert_allclose(h + explicit, classes.extinction_per_m() * z, rtol=1e-9, atol=1e-12)


def test_rendered_mean_coverage_matches_the_explicit_share_of_extinction():
    """Mean opacity of rendered particles = σ_explicit × path length (image area ∝ k/Z², volume ∝ Z² dZ)."""
    prof = _small_profile()
    classes = P.rain_classes(10.0)
    limits = np.full(len(classes.number), 6.0)
    parts, _ = P.sample_particles(np.random.default_rng(0), prof, classes, limits, 0.5, 30.0,
                                  P.rain_fall_speed_m_per_s)
    cov, _ = _render(prof, parts)
    region = (slice(5, prof.height_px // 3), slice(5, -5))      # away from the border, above the horizon
    k = P.ray_factor(prof.width_px, prof.height_px, prof.fx_px, prof.fy_px, prof.cx_px, prof.cy_px)[region]
    expected = k.mean() * classes.extinction_per_m() * (6.0 - 0.5)
    assert cov[region].mean() == pytest.approx(expected, rel=0.05)


def test_veil_transmission():
    prof = _small_profile()
    classes = P.rain_classes(50.0)
    limits = np.full(len(classes.number), 10.0)
    table = P.veil_optical_depth_table(classes, limits, 0.5, 30.0)
    sigma = classes.extinction_per_m()
    cy, cx = int(prof.cy_px), int(prof.cx_px)
    depth = np.full((prof.height_px, prof.width_px), 200.0, np.float32)
    depth[0, 0] = np.inf
    depth[1, 0] = 0.0
    t = P.veil_transmission(prof, depth, table, sigma, 30.0)
    k = P.ray_factor(prof.width_px, prof.height_px, prof.fx_px, prof.fy_px, prof.cx_px, prof.cy_px)
    h30 = sigma * 30.0 - classes.shadow_area_m2.sum() * (10.0 - 0.5)
    assert t[cy, cx] == pytest.approx(math.exp(-(k[cy, cx] * h30 + sigma * (200.0 - 30.0 * k[cy, cx]))), rel=1e-4)
    assert t[0, 0] < 1e-30 and t[1, 0] == pytest.approx(1.0)


# --- compiled kernels against NumPy oracles ------------------------------------------------------------------------

def _splat_reference(streaks: P.Streaks, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NumPy oracle of :func:`P.splat_streaks`: every sample of every streak at once (np.repeat), np.add.at."""
    h, w = depth.shape
    top = int(streaks.level.max())
    offsets = P.level_offsets(h, w, top)
    pyramid = np.zeros(offsets[-1], np.float32)
    n = streaks.count.astype(np.int64)
    p = np.repeat(np.arange(n.size), n)                                   # particle of each sample
    j = np.arange(p.size) - np.repeat(np.cumsum(n) - n, n)                # sample number along its streak
    s = P.Streaks(*(a[p] for a in streaks))
    half = np.float32(0.5)
    c = (s.first + j).astype(np.float32)
    seg_lo, seg_hi = np.maximum(s.lo, c - half), np.minimum(s.hi, c + half)
    weight = s.density * np.maximum(seg_hi - seg_lo, np.float32(0))
    b = s.b0 + (half * (seg_lo + seg_hi) - s.a0) * s.slope
    frac = b - np.floor(b)
    bi = np.floor(b).astype(np.int64)
    nearest = bi + (frac >= half)
    scale = 1 << s.level.astype(np.int64)
    rows, cols = -(-h // scale), -(-w // scale)
    n_minor = np.where(s.vertical, cols, rows)
    ci = s.first + j
    row, col = np.where(s.vertical, ci, nearest), np.where(s.vertical, nearest, ci)
    # depth at the pixel nearest the cell centre; the last cells repeat the last cell that has one
    depth_row = np.minimum(row, (h - scale // 2 - 1) // scale) * scale + scale // 2
    depth_col = np.minimum(col, (w - scale // 2 - 1) // scale) * scale + scale // 2
    inside = (nearest >= 0) & (nearest < n_minor)
    in_front = inside & (depth[np.clip(depth_row, 0, h - 1), np.clip(depth_col, 0, w - 1)] > s.range_m)
    visible = np.zeros(n.size, bool)
    visible[p[j == 0]] = in_front[j == 0]
    for cell_b, wb, ok in ((bi, weight * (np.float32(1) - frac), bi >= 0), (bi + 1, weight * frac, bi + 1 < n_minor)):
        cell = offsets[s.level] + np.where(s.vertical, ci * cols + cell_b, cell_b * cols + ci)
        np.add.at(pyramid, cell[in_front & ok], wb[in_front & ok])
    return pyramid, visible


@pytest.mark.parametrize("rain, wind", [(True, (0.0, 10.0, 0.0)), (False, (0.0, -6.0, 0.0)), (True, (0.0, 0.0, 0.0))])
def test_splat_kernel_matches_the_numpy_oracle(rain, wind):
    """Near particles (footprint levels 0–2) with vertical and horizontal streaks, crossing the image edges and
    cut by a wall at 1.2 m; ego motion 8 m/s forward."""
    classes = P.rain_classes(50.0) if rain else P.snow_classes(3.03, "gunn_marshall")
    speed = P.rain_fall_speed_m_per_s if rain else snow_power_law_m_per_s
    parts, _ = P.sample_particles(np.random.default_rng(11), LUCID, classes, np.full(len(classes.number), 1.6),
                                  0.5, 30.0, speed)
    conditions = Conditions(wind_velocity_m_per_s=wind, ego_velocity_m_per_s=(8.0, 0.0, 0.0))
    streaks = P.streak_geometry(LUCID, parts, conditions, 0.005, 0.5)
    assert set(np.unique(streaks.level[streaks.count > 0])) >= {0, 1, 2}
    assert streaks.vertical.any() and (rain or not streaks.vertical.all())
    depth = np.full((LUCID.height_px, LUCID.width_px), np.inf, np.float32)
    depth[600:, 900:] = 1.2
    expected, visible_expected = _splat_reference(streaks, depth)
    pyramid = np.zeros_like(expected)
    visible = np.zeros(parts.z.size, bool)
    P.splat_streaks(pyramid, P.level_offsets(*depth.shape, int(streaks.level.max())), depth, *streaks, visible)
    np.testing.assert_array_equal(visible, visible_expected)
    np.testing.assert_allclose(pyramid, expected, rtol=1e-5, atol=1e-7)
    assert 0 < visible.sum() < visible.size


@pytest.mark.parametrize("h, w", [(1464, 1936), (183, 242), (7, 5), (1, 1), (2, 3)])
def test_add_upsampled_is_opencv_bilinear(h, w):
    import cv2
    rng = np.random.default_rng(h * w)
    coarse = rng.random((-(-h // 2), -(-w // 2)), dtype=np.float32)
    fine = rng.random((h, w), dtype=np.float32)
    up = cv2.resize(coarse, (2 * coarse.shape[1], 2 * coarse.shape[0]), interpolation=cv2.INTER_LINEAR)[:h, :w]
    expected = fine + up
    P.add_upsampled(fine, coarse)
    np.testing.assert_allclose(fine, expected, rtol=1e-6, atol=1e-7)


def test_veil_kernel_matches_the_numpy_oracle():
    """``τ = k·H(nearest bin of min(d/k, d_max)) + σ·max(d − k d_max, 0)``, t = exp(−min(τ, 80)); bins may flip
    only at rounding ties."""
    classes = P.rain_classes(50.0)
    table = P.veil_optical_depth_table(classes, np.full(len(classes.number), 7.0), 0.5, 30.0)
    sigma = classes.extinction_per_m()
    rng = np.random.default_rng(5)
    depth = (rng.random((LUCID.height_px, LUCID.width_px)) * 80).astype(np.float32)
    depth[::7, ::3] = np.inf
    depth[::11, ::5] = 0.0
    k = P.ray_factor(LUCID.width_px, LUCID.height_px, LUCID.fx_px, LUCID.fy_px, LUCID.cx_px, LUCID.cy_px)
    z = np.minimum(depth / k, np.float32(30.0))
    bins = np.floor(z * np.float32((P.VEIL_LUT_SIZE - 1) / 30.0) + np.float32(0.5)).astype(int)
    with np.errstate(invalid="ignore"):
        tau = k * table[1][bins] + sigma * np.maximum(depth - k * np.float32(30.0), 0)
    expected = np.exp(-np.minimum(tau, 80.0))
    t = P.veil_transmission(LUCID, depth, table, sigma, 30.0)
    bin_step = k.max() * np.abs(np.diff(table[1])).max()
    assert np.abs(t - expected).max() <= bin_step
    assert np.mean(np.abs(t - expected) > 1e-6) < 1e-4
    assert t[7, 3] < 1e-30 and t[11, 5] == 1.0                             # sky, and the camera itself


def test_streak_beside_the_image_leaves_no_trace():
    """A vertical streak 4.3 px left of the image (every sample's nearest column is outside) adds nothing; a
    clip of the column before the inside test once put 70 % of it into column 0."""
    z = 5.0
    parts = _one(x=(-4.3 - LUCID.cx_px) * z / LUCID.fx_px, z=z)
    cov, n_visible = _render(LUCID, parts)
    assert cov.sum() == 0.0 and n_visible == 0
    inside = _one(x=(0.7 - LUCID.cx_px) * z / LUCID.fx_px, z=z)             # the same streak at column 0.7
    k = math.hypot(float(inside.x[0]), z) / z
    assert _render(LUCID, inside)[0].sum() == pytest.approx(
        math.pi / 4 * (2e-3) ** 2 * LUCID.fx_px * LUCID.fy_px * k / z ** 2, rel=0.01)


def test_coverage_does_not_depend_on_the_particle_order():
    """The rasteriser visits particles in raster order of pixel blocks (cache locality); any order gives the same
    opacity up to float rounding."""
    classes = P.rain_classes(50.0)
    parts, _ = P.sample_particles(np.random.default_rng(2), LUCID, classes, np.full(len(classes.number), 3.0), 0.5,
                                  30.0, P.rain_fall_speed_m_per_s)
    order = _raster_order(LUCID, parts)
    assert np.array_equal(np.sort(order), np.arange(parts.z.size))
    depth = np.full((LUCID.height_px, LUCID.width_px), np.inf, np.float32)
    depth[:, :700] = 2.0
    cov, n_visible = _render(LUCID, parts, depth=depth)
    shuffled = parts.take(np.random.default_rng(3).permutation(parts.z.size))
    cov2, n_visible2 = _render(LUCID, shuffled, depth=depth)
    assert n_visible2 == n_visible
    np.testing.assert_allclose(cov2, cov, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("rain, wind", [(True, (0.0, 10.0, 0.0)), (False, (0.0, -6.0, 0.0))])
def test_banded_renderer_is_the_sorted_splat_exactly(rain, wind):
    """The renderer distributes the particles into bands of blocks and sorts each band in cache: the same visiting
    order, so the same float sums, as the whole raster sort followed by streak_geometry and splat_streaks — and
    streak_geometry's compiled float32 pass equals the NumPy expressions operation by operation."""
    classes = P.rain_classes(50.0) if rain else P.snow_classes(3.03, "gunn_marshall")
    speed = P.rain_fall_speed_m_per_s if rain else snow_power_law_m_per_s
    parts, _ = P.sample_particles(np.random.default_rng(5), LUCID, classes, np.full(len(classes.number), 6.0),
                                  0.5, 30.0, speed)
    conditions = Conditions(wind_velocity_m_per_s=wind, ego_velocity_m_per_s=(8.0, 0.0, 0.0))
    depth = np.full((LUCID.height_px, LUCID.width_px), np.inf, np.float32)
    depth[600:, 900:] = 1.2
    ordered = parts.take(_raster_order(LUCID, parts))
    streaks = P.streak_geometry(LUCID, ordered, conditions, 0.005, 0.5)
    for got, want in zip(streaks, _numpy_streak_geometry(LUCID, ordered, conditions, 0.005, 0.5)):
        np.testing.assert_array_equal(got, want)
    offsets = P.level_offsets(*depth.shape, P.MAX_LEVEL)
    expected, visible = np.zeros(offsets[-1], np.float32), np.zeros(parts.z.size, bool)
    P.splat_streaks(expected, offsets, depth, *streaks, visible)
    pyramid = np.zeros_like(expected)
    top, n_visible = P._render_streaks(*P.particle_columns(parts), P.block_keys(LUCID, parts),
                                       *P._streak_constants(LUCID, conditions, 0.005, 0.5), pyramid, offsets, depth)
    assert pyramid.tobytes() == expected.tobytes() and n_visible == visible.sum() > 0
    assert top == streaks.level[streaks.count > 0].max()
    assert parts.z.size > 20_000 and len(np.unique(P.block_keys(LUCID, parts) >> 8)) > 100


def _raster_order(profile, particles) -> np.ndarray:
    """The renderer's visiting order as one whole sort: a stable sort of the particles' block numbers."""
    return np.argsort(P.block_keys(profile, particles), kind="stable")


def _numpy_streak_geometry(profile, particles, conditions, exposure_s, d_min_m) -> P.Streaks:
    """The NumPy formulation of the streak geometry (the renderer's until issue 19), as the oracle."""
    h, w = profile.height_px, profile.width_px
    u0, v0, z0, u1, v1, z1 = P.streak_endpoints(profile, particles, conditions, exposure_s)
    z = particles.z
    r = np.sqrt(particles.x ** 2 + particles.y ** 2 + z * z)
    mass = np.float32(math.pi / 4 * 1e-6 * profile.fx_px * profile.fy_px) * particles.d_mm ** 2 * r / (z * z * z)
    d_px = particles.d_mm * np.float32(1e-3 * P.focal_px(profile)) / z
    c_px = P.defocus_px(profile, z)
    footprint = np.sqrt(d_px * d_px + c_px * c_px)
    level = P.footprint_level(footprint)
    inv = (0.5 ** np.arange(P.MAX_LEVEL + 1)).astype(np.float32)[level]
    du, dv = u1 - u0, v1 - v0
    vertical = np.abs(dv) >= np.abs(du)
    a0, b0 = u0 + vertical * (v0 - u0), v0 + vertical * (u0 - v0)
    da, db = du + vertical * (dv - du), dv + vertical * (du - dv)
    offset = np.float32(0.5) * inv - np.float32(0.5)
    a0, b0, da, db = a0 * inv + offset, b0 * inv + offset, da * inv, db * inv
    slope = db / (da + (da == 0))
    half = np.float32(0.5) * footprint * inv
    a_lo = np.minimum(a0, a0 + da)
    b0 = b0 + slope * (a_lo - half - a0)
    a0, a1 = a_lo - half, a_lo + np.abs(da) + half
    density = mass * inv * inv / (a1 - a0)
    n_major = np.ceil((np.float32(w) + vertical * np.float32(h - w)) * inv)
    lo, hi = np.maximum(a0, np.float32(-0.5)), np.minimum(a1, n_major - np.float32(0.5))
    first = np.floor(lo + np.float32(0.5))
    count = (np.minimum(np.floor(hi + np.float32(0.5)), n_major - 1) - first + 1).astype(np.int32)
    count[(hi <= lo) | (np.minimum(z0, z1) <= np.float32(0.5 * d_min_m))] = 0
    return P.Streaks(level, vertical, a0, lo, hi, first.astype(np.int32), count, b0, slope, density, r)


def test_footprint_level_bounds_reproduce_footprint_level():
    bounds = P.footprint_level_bounds()
    f = np.concatenate([np.geomspace(0.01, 200.0, 200_001).astype(np.float32),
                        *(np.nextafter(b, np.float32([-np.inf, np.inf])).astype(np.float32) for b in bounds), bounds])
    np.testing.assert_array_equal((f[:, None] >= bounds).sum(axis=1), P.footprint_level(f))
