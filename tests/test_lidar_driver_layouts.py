"""Clouds as ROS drivers and their users lay them out, built synthetically: ouster-ros' organised
``ouster_ros::Point`` clouds (``x y z intensity t reflectivity ring ambient range``, NaN or zero x/y/z for no-return
cells) saved by PCL with its ``_`` padding fields (COUNT > 1); velodyne_pointcloud's organised clouds (a row per
firing); VLP-16 lists with and without ``ring`` read with the default profile; radar PCDs with RadarScenes' velocity
names."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.io.pointcloud import read_pointcloud, write_pointcloud
from roadview_noise.profiles.lidar import load_lidar_profile
from roadview_noise.physics.firing_grid import FiringGridWarning, firing_grid
from roadview_noise.registry import get_model
from roadview_noise.types import PointCloud

OUSTER_POINT = np.dtype({"names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
                         "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
                         "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32], "itemsize": 48})
PCL_HEADER = ("VERSION 0.7\nFIELDS x y z _ intensity t reflectivity ring ambient _ range _\n"
              "SIZE 4 4 4 1 4 4 2 2 2 1 4 1\nTYPE F F F U F U U U U U U U\nCOUNT 1 1 1 4 1 1 1 1 1 2 1 12\n"
              "WIDTH {w}\nHEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")


def ouster_ros_pcd(path, beams: int = 16, columns: int = 256, no_return: float = np.nan, seed: int = 0):
    """An organised ouster-ros cloud (a row per beam, staggered columns) saved as PCL saves it; ~30 % no-return
    cells (range 0, x/y/z ``no_return``). Returns the stored records."""
    rng = np.random.default_rng(seed)
    el = np.deg2rad(np.linspace(16.6, -16.6, beams))[:, None]
    az = -2 * np.pi * np.arange(columns)[None, :] / columns
    r = rng.uniform(3, 60, (beams, columns))
    hit = rng.random((beams, columns)) > 0.3
    rec = np.zeros((beams, columns), OUSTER_POINT)
    for name, v in zip("xyz", (np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0 * az)):
        rec[name] = np.where(hit, r * v, no_return)
    rec["intensity"] = np.where(hit, rng.uniform(2, 40, hit.shape), 0)          # signal photons: faint returns
    rec["t"] = np.arange(columns)[None, :] * 97_656                            # ns since the scan began
    rec["reflectivity"] = np.where(hit, rng.integers(1, 100, hit.shape), 0)
    rec["ring"] = np.arange(beams)[:, None]
    rec["range"] = np.where(hit, np.rint(r * 1000), 0)
    path.write_bytes(PCL_HEADER.format(w=columns, h=beams, n=rec.size).encode() + rec.tobytes())
    return rec


def test_organised_cloud_with_pcl_padding_fields_loses_returns_to_rain(tmp_path):
    """Returns rain removes from an organised cloud are emptied in every field, PCL's multi-byte ``_`` padding
    (COUNT 4, read as an N × 4 field) included. Before: every such ouster-ros PCD failed rain or snow with
    ``internal error ValueError: operands could not be broadcast together with shapes (N,) () (N,4)``."""
    rec = ouster_ros_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd")
    cloud = cloud.replace(profile=load_lidar_profile("os1-128"))
    out, records = apply_models([get_model("rain.lidar")(rain_rate_mm_per_h=50.0)], cloud, seed=1, key="k",
                                sequence_id="s", metrics=False)
    assert records[0].diagnostics["removed"] > 0 and out.grid_shape == rec.shape
    write_pointcloud(tmp_path / "out.pcd", out)
    back = read_pointcloud(tmp_path / "out.pcd")
    assert back.grid_shape == rec.shape
    np.testing.assert_array_equal(back.fields["ring"], rec["ring"].ravel())


def test_empty_cells_of_another_sensors_grid_take_its_beams_directions(tmp_path):
    """A 16-beam organised cloud (±16.6°) read with the default OS1-128 profile (128 beams, warned): fog's returns
    on its no-return cells lie on the cloud's own beams, measured from its returns (elevation and column azimuth
    within 0.01°). Before: on the profile's first 16 beams (+22° … +17°, up to 33° off; a real OS-0-32 ouster-ros
    cloud's fog points up to 56° off)."""
    rec = ouster_ros_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd").replace(profile=load_lidar_profile("os1-128"))
    out, records = apply_models([get_model("fog.lidar")(visibility_m=30.0)], cloud, seed=1, key="k",
                                sequence_id="s", metrics=False)
    empty = np.isnan(rec["x"]).ravel()
    filled = empty & out.positions_m.any(axis=1)
    assert filled.sum() > 0.5 * empty.sum()
    p = out.positions_m[filled]
    beams, columns = rec.shape
    el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    cell = np.flatnonzero(filled)
    want_el = np.linspace(16.6, -16.6, beams)[cell // columns]
    want_az = -360.0 * (cell % columns) / columns
    np.testing.assert_allclose(el, want_el, atol=0.01)
    np.testing.assert_allclose((az - want_az + 180) % 360 - 180, 0, atol=0.01)


def velodyne_list(beams: int, low_deg: float, high_deg: float, columns: int = 1800, seed: int = 0,
                  ring: bool = False) -> PointCloud:
    """A spinning LiDAR's ``x y z intensity`` point list (pcl::PointXYZI; ``ring``: with velodyne_pointcloud's
    ``ring`` field, 0 the lowest beam): ``beams`` evenly spread
    from ``low_deg`` to ``high_deg``, a return on 90 % of the firings, 1.5–50 m away (log-uniform: near returns,
    whose elevations the profile's beam-origin offsets turn, spread over the profile's finer beams as a real list's do)."""
    rng = np.random.default_rng(seed)
    el = np.deg2rad(np.linspace(low_deg, high_deg, beams))
    ring_of, col = np.divmod(np.arange(beams * columns), columns)
    az = -2 * np.pi * col / columns
    r = np.exp(rng.uniform(np.log(1.5), np.log(50), len(ring_of)))
    e = el[ring_of]
    pos = r[:, None] * np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)], 1)
    keep = rng.random(len(ring_of)) < 0.9
    fields = {"intensity": rng.integers(1, 100, keep.sum()).astype(np.float32)}
    if ring:
        fields["ring"] = ring_of[keep].astype(np.uint16)
    return PointCloud(pos[keep], fields, "lidar", load_lidar_profile("os1-128"))


def test_list_of_a_sensor_with_fewer_beams_is_warned():
    """A 16-beam list (±15°, a VLP-16's ``x y z intensity`` as PCL tools save it) read with the OS1-128 profile fills
    a few % of its 128-beam firing grid: a FiringGridWarning says the sensor has fewer beams (a real VLP-16 list:
    10 % of its 84 returning beams filled, fog 30 m turned its 14 868 points into 188 122 without a word). A
    128-beam list is not warned, nor one under open sky whose lowest beam alone returns."""
    with pytest.warns(FiringGridWarning, match=r"fill \d+% of the 128x1800 firing grid .*fewer beams"):
        grid = firing_grid(velodyne_list(16, -15, 15), load_lidar_profile("os1-128"))
    assert grid.columns == 1800
    with warnings.catch_warnings():
        warnings.simplefilter("error", FiringGridWarning)
        full = velodyne_list(128, -21, 21, columns=1024)
        firing_grid(full, load_lidar_profile("os1-128"))
        p = full.positions_m
        ground = full.select(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])) < np.deg2rad(-20.9))
        assert len(firing_grid(ground, load_lidar_profile("os1-128")).ring) > 100 * len(ground)


XYZIRT = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"], "offsets": [0, 4, 8, 12, 16, 18],
                   "itemsize": 22})


def velodyne_organised_pcd(path, firings: int = 600, seed: int = 0) -> np.ndarray:
    """velodyne_pointcloud's organised PointXYZIRT cloud as pcl_ros saves it: a row per firing, a column per laser
    (in the VLP-16's firing order, ring = elevation rank), NaN x/y/z for no return, ``time`` s since the scan."""
    rng = np.random.default_rng(seed)
    ring_of_laser = np.array([0, 8, 1, 9, 2, 10, 3, 11, 4, 12, 5, 13, 6, 14, 7, 15])
    el = np.deg2rad(-15 + 2 * ring_of_laser)[None, :]
    az = (-2 * np.pi * np.arange(firings) / firings)[:, None]
    r = rng.uniform(3, 60, (firings, 16))
    hit = rng.random((firings, 16)) > 0.4
    rec = np.zeros((firings, 16), XYZIRT)
    for name, v in zip("xyz", (np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0 * az)):
        rec[name] = np.where(hit, r * v, np.nan)
    rec["intensity"] = np.where(hit, rng.integers(1, 100, hit.shape), 0)
    rec["ring"] = ring_of_laser[None, :]
    rec["time"] = (np.arange(firings) * 0.1 / firings)[:, None]
    path.write_bytes(f"VERSION 0.7\nFIELDS x y z intensity ring time\nSIZE 4 4 4 4 2 4\nTYPE F F F F U F\n"
                     f"COUNT 1 1 1 1 1 1\nWIDTH 16\nHEIGHT {firings}\nVIEWPOINT 0 0 0 1 0 0 0\n"
                     f"POINTS {rec.size}\nDATA binary\n".encode() + rec.tobytes())
    return rec


def test_velodyne_organised_pcd_is_read_as_beams_by_firings(tmp_path):
    """A PCD stored a row per firing (ring constant down each column) is read as the 16 × firings grid, rows in ring
    order, and written back a row per firing; fog's returns on its no-return cells lie on their firing's azimuth.
    Before: read as a 600 × 16 grid of 600 "beams", fog points were put at random azimuths (real VLP-16 scan: median
    103° off their firing's)."""
    rec = velodyne_organised_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd")
    assert cloud.grid_shape == (16, 600)
    assert (np.asarray(cloud.fields["ring"]).reshape(16, 600) == np.arange(16)[:, None]).all()
    write_pointcloud(tmp_path / "back.pcd", cloud, effect="none")
    back = (tmp_path / "back.pcd").read_bytes()
    assert b"WIDTH 16\nHEIGHT 600\n" in back and back.endswith(rec.tobytes())
    out, _ = apply_models([get_model("fog.lidar")(visibility_m=30.0)], cloud.replace(profile=load_lidar_profile(
        {"base": "hdl-32e", "beam_elevation_deg": list(range(-15, 16, 2)), "beam_azimuth_offset_deg": [0] * 16,
         "columns": 600})), seed=1, key="k", sequence_id="s", metrics=False)
    write_pointcloud(tmp_path / "out.pcd", out)
    got = read_pointcloud(tmp_path / "out.pcd")
    stored = np.frombuffer((tmp_path / "out.pcd").read_bytes()[-rec.size * 23:],
                           np.dtype(XYZIRT.descr + [("rv_effect", "u1")])).reshape(rec.shape)
    filled = np.isnan(rec["x"]) & np.isfinite(stored["x"])
    assert filled.sum() > 0.5 * np.isnan(rec["x"]).sum() and got.grid_shape == (16, 600)
    az = np.arctan2(stored["y"], stored["x"])[filled]
    firing = (-2 * np.pi * np.arange(600) / 600)[np.nonzero(filled)[0]]
    assert np.abs(np.angle(np.exp(1j * (az - firing)))).max() < np.deg2rad(0.5)


def test_empty_rays_of_a_list_with_another_sensors_rings_lie_on_its_beams():
    """A 16-beam list with velodyne_pointcloud's ``ring`` field (0…15, warned: "its rings index other beams") read
    with the default OS1-128: fog's returns on its empty rays get each ring's elevation measured from its returns
    (within 0.05°), not the profile's first 16 beams' (+22° … +17°: before, up to 36° off; a real VLP-16 list under
    fog 30 m: 26.7° off, median)."""
    cloud = velodyne_list(16, -15, 15, ring=True)
    out, _ = apply_models([get_model("fog.lidar")(visibility_m=30.0)], cloud, seed=1, key="k", sequence_id="s",
                          metrics=False)
    added = out.origin < 0
    assert added.sum() > 1000
    p = out.positions_m[added]
    el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    np.testing.assert_allclose(el, np.linspace(-15, 15, 16)[np.asarray(out.fields["ring"])[added]], atol=0.05)


def test_radar_cloud_with_radarscenes_velocity_names_is_read_with_its_doppler(tmp_path):
    """A radar PCD naming its radial velocities as RadarScenes does (``vr``, ``vr_compensated``: the ``radar_data``
    columns, kept by many ARS 408 exports) is read with its Doppler and the ego velocity fitted from it; before, both
    were ignored in silence (every cell at Doppler 0, ego velocity 0, clutter given another detection's ``vr``)."""
    from roadview_noise.physics.radar_frame import ego_velocity_from_data

    rng = np.random.default_rng(0)
    n, az = 80, rng.uniform(-0.8, 0.8, 80)
    r = rng.uniform(2, 80, n)
    rec = np.zeros(n, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rcs", "<f4"), ("vr", "<f4"),
                       ("vr_compensated", "<f4")])
    rec["x"], rec["y"], rec["rcs"] = r * np.cos(az), r * np.sin(az), rng.uniform(-10, 30, n)
    rec["vr"] = rng.uniform(-12, 2, n)
    rec["vr_compensated"] = rec["vr"] + 8 * rec["x"] / r                      # ego 8 m/s along x
    (tmp_path / "r.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y z rcs vr vr_compensated\nSIZE 4 4 4 4 4 4\n"
                                     b"TYPE F F F F F F\nCOUNT 1 1 1 1 1 1\nWIDTH 80\nHEIGHT 1\nPOINTS 80\n"
                                     b"DATA binary\n" + rec.tobytes())
    cloud = read_pointcloud(tmp_path / "r.pcd", sensor="radar")
    np.testing.assert_array_equal(cloud.fields["v_r_m_per_s"], rec["vr"])
    ego, rms = ego_velocity_from_data(cloud, planar=True)
    np.testing.assert_allclose(ego[:2], [8, 0], atol=1e-3)


def test_ouster_ros_intensity_is_stated_signal_by_its_fields(tmp_path):
    """ouster-ros' cloud (``intensity`` next to ``reflectivity`` and ``ambient``) carries the signal photons in its
    intensity: with an Ouster signal profile whose packet profile leaves the channel open (the default, a metadata
    JSON of a LEGACY or RNG19 unit) the unit is stated by the fields — no "unit not stated" warning; before, the data
    decided (here: fractional photons, refused). A cloud with Ouster's ``ambient`` but no second strength field is
    still read from the data."""
    from roadview_noise.physics.lidar_intensity import chain_intensity_scale
    from roadview_noise.profiles.lidar import default_profile

    ouster_ros_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd").replace(profile=default_profile())
    scale = chain_intensity_scale(cloud, "fog.lidar")
    assert scale.warning is None and "stated by the cloud's fields (ouster-ros" in scale.note
    assert scale.profile.intensity_kind == "signal" and scale.profile.intensity_unit == "photons"
    fields = {k: v for k, v in cloud.fields.items() if k != "reflectivity"}
    with pytest.raises(Exception, match="fractions"):
        chain_intensity_scale(cloud.replace(fields=fields), "fog.lidar")


def test_ouster_ros_1_cloud_with_noise_field_is_stated_signal(tmp_path):
    """ouster_ros 1.x (ouster_example) names the ambient channel ``noise`` (``x y z intensity t reflectivity ring
    noise range``, a list saved as PCD, ring u8): its intensity is the signal too, stated by the fields (before: the
    data decided, here fractional photons, refused; and its weather returns kept the hidden object's reflectivity)."""
    from roadview_noise.physics.lidar_intensity import chain_intensity_scale
    from roadview_noise.profiles.lidar import default_profile

    rec = ouster_ros_pcd(tmp_path / "in.pcd")
    path = tmp_path / "old.pcd"
    path.write_bytes((tmp_path / "in.pcd").read_bytes().replace(b"ring ambient", b"ring noise", 1))
    cloud = read_pointcloud(path).replace(profile=default_profile())
    assert "noise" in cloud.fields
    scale = chain_intensity_scale(cloud, "fog.lidar")
    assert scale.warning is None and "stated by the cloud's fields (ouster-ros" in scale.note
    out, _ = apply_models([get_model("fog.lidar")(visibility_m=30.0)], cloud.replace(
        profile=load_lidar_profile("os1-128")), seed=1, key="k", sequence_id="s", metrics=False)
    write_pointcloud(tmp_path / "out.pcd", out)                # weather returns' reflectivity: written (derived)
    back = read_pointcloud(tmp_path / "out.pcd")
    moved = np.asarray(back.fields["rv_effect"]) == 2
    assert moved.sum() > 100 and (back.fields["reflectivity"][moved] != rec.ravel()["reflectivity"][moved]).mean() > 0.5


def _written(tmp_path, cloud, model: str, name: str = "out.pcd", **params):
    """(the chain's output, that output written as a PCD and read back, its ``rv_effect`` codes)."""
    out, _ = apply_models([get_model(model)(**params)], cloud, seed=1, key="k", sequence_id="s", metrics=False)
    write_pointcloud(tmp_path / name, out)
    back = read_pointcloud(tmp_path / name)
    return out, back, np.asarray(back.fields["rv_effect"])


def test_range_saved_as_float_follows_moved_points(tmp_path):
    """An Ouster list converted by a tool that stores every field as float (``FIELDS x y z intensity t reflectivity
    ring ambient range``, ``TYPE F F F F F U U U F``: range in millimetres as float, as found in public Ouster PCDs):
    a point moved to a fog droplet gets its own range in the unit the recorded points follow (mm), not the range of
    the object behind the fog, which it kept before (only a uint32 ``range`` was updated); in fog that moved every
    point, millimetres because the values exceed 1 000."""
    rec = ouster_ros_pcd(tmp_path / "grid.pcd").ravel()
    hit = rec["range"] > 0
    header = ("VERSION 0.7\nFIELDS x y z intensity t reflectivity ring ambient range\nSIZE 4 4 4 4 4 2 1 2 4\n"
              "TYPE F F F F F U U U F\nCOUNT 1 1 1 1 1 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
              "POINTS {n}\nDATA binary\n")
    listed = np.zeros(np.count_nonzero(hit), np.dtype([(k, t) for k, t in zip(
        ("x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"),
        ("<f4", "<f4", "<f4", "<f4", "<f4", "<u2", "u1", "<u2", "<f4"))]))
    for k in listed.dtype.names:
        listed[k] = rec[k][hit]
    (tmp_path / "list.pcd").write_bytes(header.format(n=len(listed)).encode() + listed.tobytes())
    cloud = read_pointcloud(tmp_path / "list.pcd").replace(profile=load_lidar_profile("os1-128"))
    out, back, effect = _written(tmp_path, cloud, "fog.lidar", visibility_m=100.0)
    new = (effect == 2) | (effect == 3)
    assert np.count_nonzero(effect == 2) > 100
    np.testing.assert_allclose(back.fields["range"][new], np.linalg.norm(back.positions_m[new], axis=1) * 1000,
                               rtol=1e-6)
    kept = ~new                                                  # the input's returns keep their recorded range
    assert np.count_nonzero(kept) > 100
    np.testing.assert_array_equal(back.fields["range"][kept], listed["range"][out.origin[kept]])
    _, back, effect = _written(tmp_path, cloud, "fog.lidar", "dense.pcd", visibility_m=30.0)
    assert (effect >= 2).all()                                   # every point moved: no recorded one to fit on
    np.testing.assert_allclose(back.fields["range"], np.linalg.norm(back.positions_m, axis=1) * 1000, rtol=1e-6)


def test_weather_returns_get_their_own_reflectivity(tmp_path):
    """ouster-ros' ``reflectivity`` of a fog return (a point moved to a droplet or added on an empty ray) is the
    reading its own return gives in the 8-bit reflectivity channel (W·S·R²/K of its signal S at its range R, W =
    100, K the profile's; a faint one reads 1), not the reflectivity of the object behind the fog, which it kept
    before. Returns that are the input's keep theirs (attenuated ones: next test)."""
    rec = ouster_ros_pcd(tmp_path / "in.pcd").ravel()
    cloud = read_pointcloud(tmp_path / "in.pcd").replace(profile=load_lidar_profile("os1-128"))
    _, back, effect = _written(tmp_path, cloud, "fog.lidar", visibility_m=30.0)
    new = (effect == 2) | (effect == 3)                                       # MOVED, ADDED
    assert np.count_nonzero(effect == 2) > 100 and np.count_nonzero(effect == 3) > 100
    r = np.linalg.norm(back.positions_m[new], axis=1)
    want = np.maximum(np.rint(100.0 * back.fields["intensity"][new] * r ** 2 / 65535.0), 1)
    np.testing.assert_array_equal(back.fields["reflectivity"][new], np.minimum(want, 255))
    assert back.fields["reflectivity"].dtype == np.uint16
    kept = (effect == 0) | (effect == 1)
    np.testing.assert_array_equal(back.fields["reflectivity"][kept], rec["reflectivity"][kept])
    assert not np.array_equal(back.fields["reflectivity"][effect == 2], rec["reflectivity"][effect == 2])


@pytest.mark.parametrize("model, params", [("rain.lidar", {"rain_rate_mm_per_h": 10.0}),
                                           ("fog.lidar", {"visibility_m": 100.0})])
def test_attenuated_returns_reflectivity_follows_their_signal(tmp_path, model, params):
    """ouster-ros' ``reflectivity`` of a return the weather attenuated: the sensor computes its calibrated
    reflectivity from the signal photons it measured, scaled by range (Ouster FW manual, "Calibrated
    Reflectivity"), so at its unchanged range the reading falls with the signal: its recorded reading times
    I_out / I_in, rounded, at least 1 — the unit's own calibration kept. Before: its recorded reading, as if the
    sensor had seen it in clear air. Returns kept (a change below one photon) keep theirs."""
    rec = ouster_ros_pcd(tmp_path / "in.pcd").ravel()
    cloud = read_pointcloud(tmp_path / "in.pcd").replace(profile=load_lidar_profile("os1-128"))
    _, back, effect = _written(tmp_path, cloud, model, **params)
    attenuated = effect == 1
    assert np.count_nonzero(attenuated) > 300
    ratio = back.fields["intensity"][attenuated].astype(float) / rec["intensity"][attenuated]
    want = np.maximum(np.rint(rec["reflectivity"][attenuated] * ratio), 1)
    np.testing.assert_array_equal(back.fields["reflectivity"][attenuated], want)
    assert (want < rec["reflectivity"][attenuated]).mean() > 0.5
    np.testing.assert_array_equal(back.fields["reflectivity"][effect == 0], rec["reflectivity"][effect == 0])


@pytest.mark.parametrize("model, params", [("power.lidar", {}),
                                           ("occlusion.lidar", {"seed_probability": 0.05, "opacity": 0.6})])
def test_reflectivity_follows_the_signal_other_steps_change(tmp_path, model, params):
    """The same rule for the other steps that change a return's signal in place: laser power variance and partial
    soiling. Every return whose stored signal changed reads ρ · I_out / I_in (at least 1); the others keep theirs."""
    rec = ouster_ros_pcd(tmp_path / "in.pcd").ravel()
    cloud = read_pointcloud(tmp_path / "in.pcd").replace(profile=load_lidar_profile("os1-128"))
    out, _ = apply_models([get_model(model)(**params)], cloud, seed=1, key="k", sequence_id="s", metrics=False)
    same_row = np.asarray(out.fields["intensity"]) != 0
    changed = same_row & (np.asarray(out.fields["intensity"]) != rec["intensity"]) & (rec["intensity"] > 0)
    assert np.count_nonzero(changed) > 50
    ratio = out.fields["intensity"][changed].astype(float) / rec["intensity"][changed]
    want = np.maximum(np.rint(rec["reflectivity"][changed] * ratio), 1)
    np.testing.assert_array_equal(out.fields["reflectivity"][changed], np.minimum(want, 255))
    unchanged = same_row & (np.asarray(out.fields["intensity"]) == rec["intensity"])
    np.testing.assert_array_equal(out.fields["reflectivity"][unchanged], rec["reflectivity"][unchanged])
