"""Synthetic sample drive (roadview_noise.sampledata): geometry, formats, radar equation, determinism, and the
committed sample_data/ registry. A tiny set is regenerated in a temporary directory."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import rawpy

from roadview_noise.io.depth import read_depth
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.io.raw import read_dng
from roadview_noise.physics import srgb
from roadview_noise.profiles.camera import load_camera_profile
from roadview_noise.physics.lidar_geometry import recover_ring
from roadview_noise.profiles.lidar import load_lidar_profile, os1_128, vls_128
from roadview_noise.profiles.radar import load_radar_profile
from roadview_noise.sampledata import rig
from roadview_noise.sampledata.generate import generate
from roadview_noise.physics.lidar_intensity import received_signal, sensor_constant
from roadview_noise.sampledata.scene import FACADE_Y_M, FACADES, MAT, MATERIALS, GLASS, build_scene

ROOT = Path(__file__).resolve().parents[1]
TINY = {"frames": 2, "seed": 3, "camera_size": (242, 183), "lidar_columns": 128}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("sample") / "data"
    return out, generate(out, **TINY)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _check_registry(root: Path) -> None:
    listed = {}
    for line in (root / "SHA256SUMS").read_text().splitlines():
        digest, rel = line.split("  ", 1)
        listed[rel] = digest
    present = {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()} - {"SHA256SUMS"}
    assert present == set(listed), f"unlisted: {present - set(listed)}, missing: {set(listed) - present}"
    bad = [rel for rel, digest in listed.items() if _sha256(root / rel) != digest]
    assert not bad, f"sha256 mismatch: {bad}"


def test_summary_and_layout(tiny):
    out, summary = tiny
    s = "seq0"
    expected = {f"camera/{s}/camera.yaml", f"raw/{s}/camera.yaml", f"radar/{s}/radar.yaml", "README.md"}
    for k in range(TINY["frames"]):
        n = f"{k:06d}"
        expected |= {f"camera/{s}/{n}.png", f"camera/{s}/{n}_depth.exr", f"raw/{s}/{n}.dng", f"raw/{s}/{n}_depth.exr",
                     f"lidar/os1-128/{s}/{n}.pcd", f"lidar/os1-128-kitti/{s}/{n}.bin",
                     f"lidar/os1-128-grid/{s}/{n}.pcd", f"lidar/vls-128/{s}/{n}.pcd", f"radar/{s}/{n}.pcd"}
    assert expected <= set(summary["files"])
    assert summary["seconds"] > 0 and summary["bytes"] == sum((out / f).stat().st_size for f in summary["files"])
    _check_registry(out)


def _segment_hits_box(origin, ends, lo, hi) -> np.ndarray:
    """Slab test: does the segment origin → ends[i] pass through the axis-aligned box [lo, hi]?"""
    d = ends - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - origin) / d, (hi - origin) / d
    near = np.nanmax(np.minimum(t0, t1), axis=1)
    far = np.nanmin(np.maximum(t0, t1), axis=1)
    return (near <= far) & (far >= 0) & (near <= 1)


def test_depth_is_range_to_known_facade(tiny):
    """Pixels whose ray meets a left building's facade (plane y = 14 m) with no other object's bounding box in the
    way (and above the 0.15 m pavement) have depth = the analytic ray–plane distance within 1 cm; sky is inf."""
    out, _ = tiny
    scene = build_scene(TINY["seed"])
    prof = load_camera_profile(str(out / "camera/seq0/camera.yaml"))
    assert (prof.width_px, prof.height_px) == TINY["camera_size"]
    u, v = np.meshgrid(np.arange(prof.width_px), np.arange(prof.height_px))
    d = np.stack([np.ones(u.shape), -(u - prof.cx_px) / prof.fx_px, -(v - prof.cy_px) / prof.fy_px], axis=-1)
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)
    for k in range(TINY["frames"]):
        time_s = scene.frame_time_s(k)
        depth = read_depth(out / f"camera/seq0/{k:06d}_depth.exr").reshape(-1)
        origin = scene.ego_position_m(time_s) + [*rig.CAMERA_MOUNT_XY_M, prof.height_above_ground_m]
        with np.errstate(divide="ignore"):
            t = np.where(d[:, 1] > 0, (FACADE_Y_M - origin[1]) / d[:, 1], np.inf)
        p = origin + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        on = np.zeros(len(t), dtype=bool)
        for b in scene.buildings:
            if b.side > 0:
                on |= (p[:, 0] > b.x0_m + 0.05) & (p[:, 0] < b.x1_m - 0.05) & (p[:, 2] > 0.2) & (
                    p[:, 2] < b.height_m - 0.05)
        on &= np.isfinite(t)
        for obj in scene.objects:
            if obj.kind not in ("building", "road"):
                verts = obj.vertices_at(time_s)
                on[on] &= ~_segment_hits_box(origin, p[on], verts.min(axis=0), verts.max(axis=0))
        assert on.sum() > 1000
        np.testing.assert_allclose(depth[on], t[on], atol=0.01)
        assert np.isinf(depth.reshape(u.shape)[0, int(prof.cx_px)])       # straight up the street: sky
        assert np.isfinite(depth.reshape(u.shape)[-1]).all()              # bottom row: road


def test_raw_dng_pattern_levels_and_values(tiny):
    out, _ = tiny
    path = out / "raw/seq0/000000.dng"
    with rawpy.imread(str(path)) as raw:
        pattern = "".join(raw.color_desc.decode()[i] for i in raw.raw_pattern.ravel())
        assert pattern == "RGGB"
        assert list(raw.black_level_per_channel) == [rig.RAW_BLACK_DN] * 4
        assert raw.white_level == rig.RAW_WHITE_DN
        assert raw.raw_image_visible.dtype == np.uint16
    dn, pattern, black, white = read_dng(path)
    assert (pattern, black, white) == ("RGGB", 64, 4095) and dn.max() <= 4095
    # the mosaic is the PNG frame sampled at each site's colour: same 8-bit sRGB code within one step
    png = cv2.imread(str(out / "camera/seq0/000000.png"), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(int)
    code = srgb.linear_to_code((dn.astype(np.float32) - black) / (white - black)).astype(int)
    for (r0, c0), ch in (((0, 0), 0), ((0, 1), 1), ((1, 0), 1), ((1, 1), 2)):
        assert np.abs(code[r0::2, c0::2] - png[r0::2, c0::2, ch]).max() <= 1


@pytest.mark.parametrize("folder, profile", [("os1-128", os1_128()), ("os1-128-grid", os1_128()),
                                             ("vls-128", vls_128())])
def test_lidar_ring_recovered_from_elevation(tiny, folder, profile):
    out, _ = tiny
    for k in range(TINY["frames"]):
        cloud = read_pointcloud(out / f"lidar/{folder}/seq0/{k:06d}.pcd", profile=profile)
        ret = np.any(cloud.positions_m != 0, axis=1)
        assert ret.sum() > 1000
        ring = cloud.fields["ring"][ret]
        assert (recover_ring(cloud.positions_m[ret], profile) == ring).mean() >= 0.999
        assert np.unique(ring).size > 100                              # most beams see something
        i = cloud.fields["intensity"][ret]
        s = received_signal(i, np.linalg.norm(cloud.positions_m[ret], axis=1), profile)   # VLS: no beam-origin offset
        assert s.min() >= profile.detection_threshold * (1 - 1e-5) and i.max() <= profile.intensity_full_scale
        t = cloud.fields.get("time_s", cloud.fields.get("time"))[ret]          # float32 s (alias "time")
        assert 0 <= t.min() and t.max() < 0.1


def test_lidar_grid_kitti_and_list_agree(tiny):
    out, _ = tiny
    prof = load_lidar_profile(str(out / "lidar/os1-128-grid/seq0/lidar.yaml"))
    assert prof.columns == TINY["lidar_columns"] and prof.channels == 128
    grid = read_pointcloud(out / "lidar/os1-128-grid/seq0/000000.pcd", profile=prof)
    lst = read_pointcloud(out / "lidar/os1-128/seq0/000000.pcd", profile=prof)
    kitti = read_pointcloud(out / "lidar/os1-128-kitti/seq0/000000.bin", profile=prof)
    assert grid.grid_shape == (128, TINY["lidar_columns"]) and lst.grid_shape is None
    ret = np.any(grid.positions_m != 0, axis=1)
    assert 0.3 < ret.mean() < 0.99
    np.testing.assert_array_equal(grid.positions_m[ret], lst.positions_m)
    np.testing.assert_array_equal(kitti.positions_m, lst.positions_m)
    np.testing.assert_array_equal(kitti.fields["intensity"], lst.fields["intensity"])
    time_s = grid.fields.get("time_s", grid.fields.get("time"))
    assert (grid.fields["intensity"][~ret] == 0).all() and (time_s[~ret] == 0).all()
    np.testing.assert_array_equal(grid.fields["ring"], np.repeat(np.arange(128), TINY["lidar_columns"]))


@pytest.mark.parametrize("folder, profile", [("os1-128", os1_128()), ("vls-128", vls_128())])
def test_lidar_intensity_follows_lambertian_lidar_equation(tiny, folder, profile):
    """On the left facade plane: the received signal ``K ρ cos θ / R²`` recovered from the stored intensity (OS1
    photons as is, VLS calibrated reflectivity) gives one of the facade or glass reflectivities (I rounded); the VLS
    stores ``110 ρ cos θ`` (diffuse white reads 110, VLS-128 manual)."""
    out, _ = tiny
    scene = build_scene(TINY["seed"])
    cloud = read_pointcloud(out / f"lidar/{folder}/seq0/000000.pcd", profile=profile)
    prof = profile
    sensor = scene.ego_position_m(0.0) + rig.LIDAR_MOUNT_M
    p = cloud.positions_m
    on = (np.abs(p[:, 1] + sensor[1] - FACADE_Y_M) < 1e-3) & (p[:, 2] + sensor[2] > 0.5)
    i = cloud.fields["intensity"].astype(float)
    on &= i >= 50
    assert on.sum() > 50
    # beam origin: offset from the axis along the encoder direction; distance travelled R from there
    az = np.arctan2(p[on, 1], p[on, 0])
    origin = np.stack([prof.beam_origin_offset_m * np.cos(az), prof.beam_origin_offset_m * np.sin(az),
                       np.full(on.sum(), prof.sensor_z_offset_m)], axis=1)
    ray = p[on] - origin
    r = np.linalg.norm(ray, axis=1)
    cos = np.abs(ray[:, 1]) / r
    rho = received_signal(i[on], r, prof) * r**2 / (sensor_constant(prof) * cos)
    table = np.array([MATERIALS[MAT[f]].nir_reflectivity for f in FACADES] + [GLASS.nir_reflectivity])
    err = np.min(np.abs(rho[:, None] / table[None, :] - 1), axis=1)
    assert np.quantile(err, 0.99) < 0.02 + 0.5 / 50
    if folder == "vls-128":                         # the reading itself, without the conversion layer
        np.testing.assert_allclose(rho, i[on] / (110.0 * cos), rtol=1e-9)


def test_radar_snr_falls_as_inverse_fourth_power(tiny):
    out, _ = tiny
    prof = load_radar_profile(str(out / "radar/seq0/radar.yaml"))
    assert prof.snr_threshold_db == 10.0
    r, x = [], []
    for k in range(TINY["frames"]):
        c = read_pointcloud(out / f"radar/seq0/{k:06d}.pcd", sensor="radar")
        assert {"v_r_m_per_s", "rcs_dbsm", "snr_db"} <= set(c.fields)
        r.append(c.ranges_m)
        x.append(c.fields["snr_db"].astype(float) - c.fields["rcs_dbsm"])
        assert c.fields["snr_db"].min() >= prof.snr_threshold_db
    r, x = np.concatenate(r), np.concatenate(x)
    assert len(r) > 30 and r.max() / r.min() > 3
    slope, intercept = np.polyfit(10 * np.log10(r), x, 1)
    assert slope == pytest.approx(-4.0, abs=0.01)
    assert intercept + slope * 10 * np.log10(50.0) + 10.0 == pytest.approx(20.0, abs=0.05)   # 10 dBsm at 50 m


def test_radar_radial_velocity_of_static_scene(tiny):
    """Static targets approach at the ego speed times the cosine of the angle to the direction of travel."""
    out, _ = tiny
    c = read_pointcloud(out / "radar/seq0/000001.pcd", sensor="radar")
    u = c.positions_m / c.ranges_m[:, None]
    expected = -build_scene(TINY["seed"]).ego_velocity_m_per_s[0] * u[:, 0]
    static = np.abs(c.fields["v_r_m_per_s"] - expected) < 1e-3
    assert static.mean() > 0.5                                     # buildings, poles, parked cars
    assert (~static).sum() >= 1                                    # moving road users


def test_generation_is_deterministic_for_a_seed(tiny, tmp_path):
    out, _ = tiny
    again = generate(tmp_path / "again", **TINY)
    assert (tmp_path / "again" / "SHA256SUMS").read_text() == (out / "SHA256SUMS").read_text()
    assert again["files"] == tiny[1]["files"]
    other = generate(tmp_path / "other", **{**TINY, "frames": 1, "seed": TINY["seed"] + 1})
    assert _sha256(tmp_path / "other/camera/seq0/000000.png") != _sha256(out / "camera/seq0/000000.png")
    assert other["frames"] == 1


def test_committed_sample_data_matches_registry():
    root = ROOT / "sample_data"
    if not (root / "SHA256SUMS").is_file():
        pytest.fail("sample_data/SHA256SUMS is missing: regenerate with python -m roadview_noise.sampledata.generate")
    _check_registry(root)
