"""Ring (beam index) recovery from elevation with a sensor's beam table (models.md §3.0)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roadview_noise.errors import InputError
from roadview_noise.physics.lidar_geometry import recover_ring, ring_index, velodyne_to_xyz
from roadview_noise.profiles.lidar import from_ouster_metadata, os1_128, uniform, vls_128
from roadview_noise.types import PointCloud


def real_scan(shared_data):
    d = shared_data / "os1-128"
    xyz = np.fromfile(d / "scan0.bin", dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    return xyz, np.fromfile(d / "scan0_ring.u16", dtype=np.uint16)


def test_os1_128_ring_recovery_on_a_real_scan(shared_data):
    """The unit's beam table with its 36.18 mm z offset and 15.806 mm beam-origin offset recovers the ring of
    every point of a real scan (measured: 100.0 % of 107 647)."""
    xyz, ring = real_scan(shared_data)
    assert np.mean(recover_ring(xyz, os1_128()) == ring) >= 0.995


def test_sensor_metadata_gives_the_same_rings(shared_data):
    xyz, ring = real_scan(shared_data)
    profile = from_ouster_metadata(shared_data / "os1-128" / "beam_intrinsics.json")
    assert np.mean(recover_ring(xyz, profile) == ring) >= 0.995


def test_generic_tables_are_much_worse(shared_data):
    """Measured on the same scan: the nominal uniform ±22.5° table gets 17.0 % right, a uniform table spanning the
    real beams 45.2 %, and the real table without the origin offsets 47.0 % — a generic profile is not enough."""
    xyz, ring = real_scan(shared_data)
    real = os1_128()
    figures = {
        "uniform ±22.5°": uniform("nominal", 128, 22.5, -22.5),
        "uniform over the real span": uniform("span", 128, max(real.beam_elevation_deg),
                                              min(real.beam_elevation_deg)),
        "real table, no offsets": dataclasses.replace(real, sensor_z_offset_m=0.0, beam_origin_offset_m=0.0),
    }
    for name, profile in figures.items():
        assert np.mean(recover_ring(xyz, profile) == ring) < 0.5, name


def test_vls_128_table_recovers_noise_free_rings():
    """Synthetic VLS-128 scan (D3.5 Eq. 4 with the per-laser table, laser ids not in elevation order): exact as long
    as the elevation error stays below half the smallest beam spacing (0.11° / 2)."""
    profile = vls_128()
    rng = np.random.default_rng(0)
    ring = np.repeat(np.arange(128), 50)
    alpha = rng.uniform(-np.pi, np.pi, ring.size) + np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring]
    omega = np.deg2rad(np.asarray(profile.beam_elevation_deg)[ring] + rng.uniform(-0.05, 0.05, ring.size))
    xyz = velodyne_to_xyz(rng.uniform(1, 200, ring.size), alpha, omega)
    np.testing.assert_array_equal(recover_ring(xyz, profile), ring)


def test_ring_field_takes_priority():
    profile = vls_128()
    xyz = velodyne_to_xyz(np.full(3, 10.0), np.zeros(3), np.deg2rad([15.0, 0.1, -25.0]))
    cloud = PointCloud(xyz, {"ring": np.array([7, 8, 9], dtype=np.uint16)}, "lidar", profile)
    np.testing.assert_array_equal(ring_index(cloud), [7, 8, 9])
    np.testing.assert_array_equal(ring_index(dataclasses.replace(cloud, fields={})), [59, 12, 36])


def test_ring_field_outside_the_table_is_refused():
    cloud = PointCloud(np.ones((2, 3)), {"ring": np.array([3, 64], dtype=np.uint16)}, "lidar", uniform("u", 64, 2, -24))
    with pytest.raises(InputError, match="64 beams"):
        ring_index(cloud)


def test_recipe_intensity_scale_keeps_the_physics():
    """Re-expressing stored intensities in another unit rescales what is tied to them, nothing else."""
    from roadview_noise.profiles.lidar import with_intensity_scale

    p = os1_128()
    q = with_intensity_scale(p, "uint8", None)
    assert q.intensity_full_scale == 255.0
    ratio = 255.0 / p.intensity_full_scale
    k_p = p.sensor_constant if p.sensor_constant is not None else p.intensity_full_scale
    k_q = q.sensor_constant if q.sensor_constant is not None else q.intensity_full_scale
    assert k_q == pytest.approx(k_p * ratio)
    assert q.detection_threshold / k_q == pytest.approx(p.detection_threshold / k_p)   # same detection range


def test_camera_profile_mapping_over_a_base(tmp_path):
    """A mapping overrides fields of a base profile; a new size alone resamples the base optics."""
    from roadview_noise.profiles.camera import load_camera_profile, lucid_triton_028s

    base = lucid_triton_028s()
    p = load_camera_profile({"exposure_time_s": 0.01})
    assert p.exposure_time_s == 0.01 and p.fx_px == base.fx_px
    half = load_camera_profile({"width_px": 968, "height_px": 732})
    assert half.fx_px == pytest.approx(base.fx_px / 2) and half.cx_px == pytest.approx((968 - 1) / 2)
    (tmp_path / "cam.yaml").write_text("base: lucid_triton_028s\nK: [[1000, 0, 960], [0, 1000, 540], [0, 0, 1]]\n"
                                       "width_px: 1920\nheight_px: 1080\n")
    k = load_camera_profile(str(tmp_path / "cam.yaml"))
    assert (k.name, k.fx_px, k.cy_px, k.f_number) == ("cam", 1000.0, 540.0, base.f_number)
    with pytest.raises(InputError, match="focal_mm"):
        load_camera_profile({"focal_mm": 6})
