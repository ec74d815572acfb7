"""Unresolved camera rain/snow particles drawn per pixel (physics/particles.py: resolved_depth_limits,
unresolved_field, transmit_through_particles): the per-pixel compound-Poisson opacity has the mean and variance of
the explicit particles it replaces, the mean image does not change, and the split is where streaks drop below a
pixel."""

from __future__ import annotations

import numpy as np
import pytest

from roadview_noise.physics import particles as P
from roadview_noise.physics.streak_motion import MOTION_BANDS
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.registry import get_model
from roadview_noise.types import Conditions

LUCID = lucid_triton_028s()
SNOW = get_model("snow.camera")()
WALL_M = 12.0


def _split(prof, model=SNOW, conditions=Conditions(), min_extent_px=1.0):
    classes = model.size_classes()
    far = P.explicit_depth_limits(prof, 0.005, classes, model.fall_speed, conditions, 0.5, 30.0, 0.02)
    near = P.resolved_depth_limits(prof, 0.005, classes, model.fall_speed, conditions, 0.5, 30.0, far,
                                   min_extent_px)
    return classes, near, far


def _scene_depth(prof):
    """Sky on the left half, a wall at 12 m (planar) on the right."""
    h, w = prof.height_px, prof.width_px
    k = P.ray_factor(w, h, prof.fx_px, prof.fy_px, prof.cx_px, prof.cy_px)
    depth = np.full((h, w), np.inf, np.float32)
    depth[:, w // 2:] = WALL_M * k[:, w // 2:]
    return depth, k


def test_resolved_limits_split_where_streaks_drop_below_the_extent():
    classes, near, far = _split(LUCID)
    assert np.all((near >= 0.5) & (near <= far))
    assert np.any(near < far)                                     # snow at 3 mm/h: most flakes unresolved
    _, all_explicit, _ = _split(LUCID, min_extent_px=0.0)
    np.testing.assert_array_equal(all_explicit, far)
    _, coarser, _ = _split(LUCID, min_extent_px=2.0)
    assert np.all(coarser <= near)
    # at the split, a flake's streak (fall during 5 ms + footprint) still spans ≥ 1 px; 10 % farther it does not
    split = (near > 0.5) & (near < far)
    d = classes.rms_d_mm[split]
    f = P.focal_px(LUCID)

    def extent(z):
        return (0.005 * SNOW.fall_speed(d) * LUCID.fy_px / z
                + np.hypot(d * 1e-3 * f / z, P.defocus_px(LUCID, z)))
    assert np.all(extent(near[split]) >= 1.0)
    assert np.all(extent(1.1 * near[split]) < 1.0)
    # ego motion lengthens streaks towards the image corners: more particles stay explicit
    _, moving, _ = _split(LUCID, conditions=Conditions(ego_velocity_m_per_s=(10.0, 0.0, 0.0)))
    assert np.all(moving >= near) and np.any(moving > near)


def test_quantised_counts_keep_the_mean_exactly_and_the_variance():
    classes, near, far = _split(LUCID)
    field = P.unresolved_field(LUCID, 0.005, classes, SNOW.fall_speed, Conditions(), 0.5, near, far, 30.0)
    p_at_least = (P.UNIFORM_CODES - field.cuts[:, :-1]) / P.UNIFORM_CODES           # P(N ≥ n), n = 1 … top
    mean_n = p_at_least.sum(axis=1)
    second = ((2 * np.arange(1, p_at_least.shape[1] + 1) - 1) * p_at_least).sum(axis=1)   # E[N²]
    on = field.mean > 0
    np.testing.assert_allclose(field.mark[on] * mean_n[on], field.mean[on], rtol=1e-6)
    variance = field.mark ** 2 * (second - mean_n ** 2)
    fine = p_at_least[:, 0] >= 1 / 256                       # 16-bit uniforms: P(N ≥ 1) to ± ½ code
    np.testing.assert_allclose(variance[fine], field.variance[fine], rtol=0.01)
    np.testing.assert_allclose(variance, field.variance, rtol=0, atol=1e-3 * field.variance.max())
    # the mean is the veil's optical depth of the same particles (Q = 1): Σ σ_i |[near_i, far_i] ∩ [0, z]|
    z = np.linspace(0.0, 30.0, P.VEIL_LUT_SIZE)
    _, h_near = P.veil_optical_depth_table(classes, near, 0.5, 30.0)
    _, h_far = P.veil_optical_depth_table(classes, far, 0.5, 30.0)
    np.testing.assert_allclose(field.mean, h_near - h_far, rtol=1e-9, atol=1e-12)
    assert z[-1] == 30.0


def _explicit_unresolved(prof, classes, near, far, seed):
    """The explicit renderer's particles between near and far (sampled up to far, the nearer ones dropped)."""
    parts, _ = P.sample_particles(np.random.default_rng(seed), prof, classes, far, 0.5, 30.0, SNOW.fall_speed)
    cls = np.searchsorted(classes.edges_mm, parts.d_mm, side="right") - 1
    return parts.take(np.flatnonzero(parts.z > near[np.clip(cls, 0, len(near) - 1)]))


@pytest.mark.parametrize("profile", [LUCID.resized(484, 366), LUCID.resized(968, 732)])
def test_per_pixel_draw_has_the_mean_and_variance_of_the_explicit_particles(profile):
    """Same particles (between the resolved and the visibility limits) drawn one by one by the streak renderer
    and per pixel by the compound-Poisson field, several seeds: per depth region (sky: all of them; a wall at
    12 m: those in front of it), the mean and the variance of the opacity per unit ray factor agree, and both
    agree with the field's closed-form moments."""
    classes, near, far = _split(profile)
    field = P.unresolved_field(profile, 0.005, classes, SNOW.fall_speed, Conditions(), 0.5, near, far, 30.0)
    depth, k = _scene_depth(profile)
    h, w = depth.shape
    rows = slice(4, int(profile.cy_px) - 4)                   # above the horizon, away from the borders
    regions = {"sky": (rows, slice(4, w // 2 - 4)), "wall": (rows, slice(w // 2 + 4, w - 4))}
    bins = {"sky": P.VEIL_LUT_SIZE - 1, "wall": round(WALL_M * (P.VEIL_LUT_SIZE - 1) / 30.0)}
    explicit, drawn = {r: [] for r in regions}, {r: [] for r in regions}
    for seed in range(6):
        cov_e, _ = P.render_coverage(profile, _explicit_unresolved(profile, classes, near, far, seed), Conditions(),
                                     0.005, depth, 0.5)
        t = np.ones((h, w), np.float32)
        mean = P.transmit_through_particles(t, np.zeros((h, w), np.float32), profile, depth, field, 30.0,
                                            np.random.default_rng(seed))
        cov_s = 1 - t
        assert mean == pytest.approx(cov_s.mean(), rel=1e-5)
        for r, sl in regions.items():
            explicit[r].append((cov_e / k)[sl].ravel())
            drawn[r].append((cov_s / k)[sl].ravel())
    for r in regions:
        e, s = np.concatenate(explicit[r]), np.concatenate(drawn[r])
        b = bins[r]
        assert e.max() < 1 and s.max() < 1                      # no clipping in the comparison
        assert e.mean() == pytest.approx(field.mean[b], rel=0.03)
        assert s.mean() == pytest.approx(field.mean[b], rel=0.03)
        assert e.var() == pytest.approx(field.variance[b], rel=0.08)
        assert s.var() == pytest.approx(field.variance[b], rel=0.05)


EGO = Conditions(ego_velocity_m_per_s=(10.0, 0.0, 0.0))


def _keys(parts):
    """One uint64 per particle (its float32 z and x bits) to find the same particles in two draws."""
    return (parts.z.view(np.uint32).astype(np.uint64) << np.uint64(32)) | parts.x.view(np.uint32).astype(np.uint64)


def _band_split(prof, conditions, seed):
    """The motion bands' field and split, the visible particles of one draw (sampled up to the visibility limits)
    and which of them the bands keep explicit (the same draw restricted by the bands' limits)."""
    classes = SNOW.size_classes()
    limits = P.explicit_depth_limits(prof, 0.005, classes, SNOW.fall_speed, conditions, 0.5, 30.0, 0.02)
    _, field, split = P.band_tables(prof, 0.005, classes, SNOW.fall_speed, conditions, 0.5, 30.0, limits, 1.0)
    every, _ = P.sample_particles(np.random.default_rng(seed), prof, classes, limits, 0.5, 30.0, SNOW.fall_speed)
    kept, _ = P.sample_particles(np.random.default_rng(seed), prof, classes, limits, 0.5, 30.0, SNOW.fall_speed,
                                 P.band_split(prof, classes, split.bands, split.limits, limits, 0.5, 30.0))
    explicit = np.isin(_keys(every), _keys(kept))
    assert explicit.sum() == kept.z.size                      # the kept ones are a selection of the same draw
    return field, split, every, explicit


@pytest.mark.parametrize("conditions", [EGO, Conditions(ego_velocity_m_per_s=(5.0, 0.0, 0.0)),
                                        Conditions(wind_velocity_m_per_s=(-3.0, 1.0, 0.0))],
                         ids=["ego 10 m/s", "ego 5 m/s", "head and cross wind"])
def test_motion_bands_draw_per_pixel_only_particles_shorter_than_a_pixel(conditions):
    """With ego motion (or head wind) the streak length depends on the image position: near the focus of expansion
    far particles stay points. Every particle the bands leave to the per-pixel draw spans < 1 px along its
    streak's major axis (exact exposure end points plus footprint; up to the split's grid), their number is the
    field's expected count, and without v_z there are no bands (the image-wide split of the calm case)."""
    field, split, every, explicit = _band_split(LUCID, conditions, 0)
    u0, v0, _, u1, v1, _ = P.streak_endpoints(LUCID, every, conditions, 0.005)
    extent = np.maximum(np.abs(u1 - u0), np.abs(v1 - v0)) + np.hypot(
        every.d_mm * 1e-3 * P.focal_px(LUCID) / every.z, P.defocus_px(LUCID, every.z))
    dropped = ~explicit
    assert dropped.sum() > 0.05 * every.z.size
    # < 1 px up to the split's depth grid (1.6 % steps) and the diameters inside a 0.1 mm class, as the calm
    # split (1.020 px at most and 0.6 % of its per-pixel particles ≥ 1 px on this frame)
    assert extent[dropped].max() < 1.025 and np.mean(extent[dropped] >= 1.0) < 0.01
    assert dropped.sum() == pytest.approx(field.expected, rel=0.01)
    assert field.band is split.bands.band and field.mean.size == P.VEIL_LUT_SIZE * split.limits.shape[0]
    assert P.band_tables(LUCID, 0.005, SNOW.size_classes(), SNOW.fall_speed,
                         Conditions(wind_velocity_m_per_s=(0.0, 3.0, 0.0)), 0.5, 30.0, split.limits[-1], 1.0) is None


def test_frames_use_the_bands_where_they_cost_less():
    """The per-pixel draw of the whole frame and a band test per sampled particle against the particles the bands
    leave to it (COST_* figures): at 5 m/s of ego speed on the Lucid frame 0.41 M of 1.23 M visible flakes leave,
    and the bands are used; at 10 m/s 0.12 M, and the frame keeps the image-wide split (as without bands)."""
    classes = SNOW.size_classes()

    def tables(speed):
        return P.particle_tables(LUCID, 0.005, classes, SNOW.fall_speed,
                                 Conditions(ego_velocity_m_per_s=(speed, 0.0, 0.0)), 0.5, 30.0, 0.02, 1.0)
    slow, fast = tables(5.0), tables(10.0)
    assert slow.split is not None and slow.unresolved.band is slow.split.bands.band
    assert slow.unresolved.expected > 0.3 * (slow.unresolved.expected + slow.split.expected.sum())
    assert fast.split is None and (fast.unresolved is None or fast.unresolved.band is None)


@pytest.mark.parametrize("profile", [LUCID.resized(484, 366), LUCID.resized(968, 732)])
def test_per_pixel_draw_under_ego_motion_has_the_moments_of_the_explicit_particles(profile):
    """The particles the motion bands leave to the per-pixel draw (ego 10 m/s), drawn one by one by the streak
    renderer and per pixel by the field, several seeds: in the sky near the focus of expansion (slow bands) and
    farther out, in front of a wall at 12 m near it, the mean and the second moment of the opacity per unit ray factor
    agree with each other and with the field's per-band moments."""
    depth, k = _scene_depth(profile)
    h, w = depth.shape
    field, split, _, _ = _band_split(profile, EGO, 0)
    band = split.bands.band
    rows = np.arange(h)[:, None] < int(profile.cy_px) - 4
    inner = np.zeros((h, w), bool)
    inner[4:-4, 4:-4] = True
    sky, wall = inner & rows & (np.arange(w) < w // 2 - 4), inner & rows & (np.arange(w) >= w // 2 + 4)
    slow, fast = band < 6, (band >= 6) & (band < MOTION_BANDS)
    # (in the fast bands no particle in front of the wall is unresolved)
    regions = {"sky slow": sky & slow, "sky fast": sky & fast, "wall slow": wall & slow}
    cell = band.astype(int) * P.VEIL_LUT_SIZE + np.where(np.isinf(depth), P.VEIL_LUT_SIZE - 1,
                                                          round(WALL_M * (P.VEIL_LUT_SIZE - 1) / 30.0))
    explicit, drawn = {r: [] for r in regions}, {r: [] for r in regions}
    for seed in range(6):
        _, _, every, kept = _band_split(profile, EGO, seed)
        cov_e, _ = P.render_coverage(profile, every.take(np.flatnonzero(~kept)), EGO, 0.005, depth, 0.5)
        t = np.ones((h, w), np.float32)
        P.transmit_through_particles(t, np.zeros((h, w), np.float32), profile, depth, field, 30.0,
                                     np.random.default_rng(seed))
        for r, sel in regions.items():
            explicit[r].append((cov_e / k)[sel])
            drawn[r].append(((1 - t) / k)[sel])
    for r, sel in regions.items():
        assert sel.sum() > 2000, r
        e, s = np.concatenate(explicit[r]), np.concatenate(drawn[r])
        mean, var = field.mean[cell[sel]], field.variance[cell[sel]]
        second = (var + mean ** 2).mean()                          # E[X²] over the region's mixture of bands
        assert e.max() < 1 and s.max() < 1 and mean.mean() > 0
        assert e.mean() == pytest.approx(mean.mean(), rel=0.03), r
        assert s.mean() == pytest.approx(mean.mean(), rel=0.03), r
        assert (e ** 2).mean() == pytest.approx(second, rel=0.08), r
        assert (s ** 2).mean() == pytest.approx(second, rel=0.05), r
