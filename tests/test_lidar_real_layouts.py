"""Real LiDAR dataset layouts, built synthetically: the HDL-32E of nuScenes (its no-return placeholders), the ring
field of another sensor read with the default profile, and fixed-layout .bin files with another column count
(Waymo's 6-column KITTI-format export, Lyft's 5 columns)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roadview_noise.errors import InputError
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.physics.firing_grid import firing_grid
from roadview_noise.physics.lidar_intensity import IntensityWarning, chain_intensity_scale, resolve_profile
from roadview_noise.physics.lidar_rays import cloud_rays
from roadview_noise.profiles.lidar import default_profile, hdl_32e, load_lidar_profile
from roadview_noise.types import PointCloud


def test_hdl_32e_datasheet_values():
    """32 beams −30.67°…+10.67° in 4/3° steps, ring 0 the lowest (the Velodyne driver's and nuScenes' ring), 8-bit
    calibrated reflectivity (white = 100), 100 m, a 1 m minimum range; K reproduces the faintest reading at 75 m
    of a real nuScenes scan (22): ρ = I/100 at the threshold, K = 100 R² / I within 3 %."""
    p = load_lidar_profile("hdl-32e")
    elev = np.asarray(p.beam_elevation_deg)
    assert p.channels == 32 and elev[0] == pytest.approx(-30.67) and elev[-1] == pytest.approx(10.67)
    assert np.allclose(np.diff(elev), 4 / 3, atol=0.0101)                  # rounded to 0.01° as in the manual
    assert (p.intensity_unit, p.intensity_full_scale, p.intensity_kind) == ("uint8", 255.0, "reflectivity")
    assert (p.reflectivity_white_reading, p.max_range_m, p.min_range_m, p.wavelength_m) == (100.0, 100.0, 1.0, 905e-9)
    assert p.sensor_constant == pytest.approx(100 * 75.0 ** 2 / 22, rel=0.03)


def nuscenes_like(fill: float = 0.7, columns: int = 1085, seed: int = 0) -> tuple[PointCloud, np.ndarray]:
    """A nuScenes LIDAR_TOP-style scan: every firing of 32 rings × ``columns`` stored, column by column; a return
    2–80 m away (uint8 reflectivity, ring field) or, for a no-return, the point at the ego vehicle's displacement
    since the sweep started (up to 0.9 m at 18 m/s, 20 Hz), as the ego-motion compensation leaves a zero range.
    Returns the cloud and the no-return mask."""
    rng = np.random.default_rng(seed)
    profile = hdl_32e()
    c = np.arange(columns)
    az = 0.4 - 2 * np.pi * c / columns
    el = np.deg2rad(np.asarray(profile.beam_elevation_deg))
    ring = np.tile(np.arange(32), columns)
    col = np.repeat(c, 32)
    r = rng.uniform(2, 80, len(ring))
    pos = r[:, None] * np.stack([np.cos(el[ring]) * np.cos(az[col]), np.cos(el[ring]) * np.sin(az[col]),
                                 np.sin(el[ring])], 1)
    empty = rng.random(len(ring)) > fill
    ego = np.stack([0.9 * col / columns, 0.01 * np.ones(len(col)), np.zeros(len(col))], 1)
    pos[empty] = ego[empty]
    fields = {"intensity": np.rint(rng.uniform(5, 60, len(ring))).astype(np.float32),
              "ring": ring.astype(np.float32)}
    return PointCloud(pos, fields, "lidar", profile), empty


def test_nuscenes_no_return_placeholders_are_empty_rays():
    """nuScenes stores no-returns as points within 1 m (the HDL-32E's minimum range): they are no-return rays, so the
    list's firing grid is found and every one of them is an empty ray that fog or snow can return on. Read as
    returns (min_range_m 0, the behaviour before), their azimuths break the grid: no empty ray at all."""
    cloud, empty = nuscenes_like()
    rays = cloud_rays(cloud, "fog.lidar")
    assert rays.listed is not None, rays.empty_source
    assert rays.listed.columns == 1085 and len(rays.listed.ring) == np.count_nonzero(empty)
    assert not rays.has_target[:len(cloud)][empty].any() and rays.has_target[:len(cloud)][~empty].all()
    before = dataclasses.replace(cloud, profile=dataclasses.replace(cloud.profile, min_range_m=0.0))
    assert cloud_rays(before, "fog.lidar").listed is None


def test_weather_on_a_placeholder_ray_takes_its_row():
    """A weather return on the ray of a nuScenes no-return placeholder is written in the placeholder's row (ADDED,
    its origin and ring kept), not appended next to it: one point per ray, and the rows (and a lidarseg label file
    carried by them: nuScenes' class 0 "noise" on the weather returns) stay those of the input — every empty ray of
    this scan has its placeholder, so nothing is appended. Placeholders that got no weather keep their bytes. Before: the placeholder stayed and the weather
    return was appended, two points on one ray."""
    from roadview_noise.annotations import carry_values
    from roadview_noise.compound import apply_models
    from roadview_noise.registry import get_model

    cloud, empty = nuscenes_like(fill=0.6, columns=400)
    out, records = apply_models([get_model("fog.lidar")(visibility_m=30.0)], cloud, seed=1, key="k",
                                sequence_id="s", metrics=False)
    n = len(cloud)
    effect = np.asarray(out.effect)
    hosted = empty & (effect[:n] == 3)
    added = records[0].diagnostics["added"]
    assert len(out) == n and added == np.count_nonzero(hosted) > 1000       # every firing stored: none appended
    assert out.origin is None                                            # output row i is input row i
    np.testing.assert_array_equal(out.fields["ring"], cloud.fields["ring"])
    r = np.linalg.norm(out.positions_m, axis=1)
    assert (r[hosted] > 1.0).all() and (r[empty & ~hosted] < 1.0).all()
    np.testing.assert_array_equal(out.positions_m[empty & ~hosted], cloud.positions_m[empty & ~hosted])
    # the hosted return lies on its placeholder's ray: its ring's elevation, its firing's azimuth
    el = np.deg2rad(np.asarray(cloud.profile.beam_elevation_deg))[cloud.fields["ring"].astype(int)]
    p = out.positions_m[hosted]
    assert np.abs(np.arcsin(p[:, 2] / r[hosted]) - el[hosted]).max() < 1e-3
    az_firing = 0.4 - 2 * np.pi * (np.flatnonzero(hosted) // 32) / 400
    assert np.abs(np.angle(np.exp(1j * (np.arctan2(p[:, 1], p[:, 0]) - az_firing)))).max() < 0.3 * 2 * np.pi / 400
    labels = np.arange(n, dtype=np.uint8) % 31 + 1                      # lidarseg: one class per input row
    carried = carry_values(labels, out, 0)
    new = (effect[:n] == 2) | hosted                                     # moved to a droplet, or on a placeholder
    assert (carried[new] == 0).all() and np.array_equal(carried[~new], labels[~new])


def nuscenes_sweep(columns: int = 400, overlap: int = 3, jitter: float = 0.15, seed: int = 2) -> PointCloud:
    """A nuScenes LIDAR_TOP sweep as the real one stores it (mmdetection3d's demo: 1 084 firings a ring on 1 081
    measured columns): a few firings more than a turn (the sweep overlaps its start), returns' azimuths jittering
    by up to 0.6 column (``jitter`` of them; a column between beams in 14 % of the real firings), no-return
    placeholders at the ego displacement, among them every ring's first two and last two firings."""
    rng = np.random.default_rng(seed)
    firings = columns + overlap
    el = np.deg2rad(np.asarray(hdl_32e().beam_elevation_deg))
    ring = np.tile(np.arange(32), firings)
    col = np.repeat(np.arange(firings), 32)
    wobble = np.where(rng.random(len(ring)) < jitter, rng.uniform(-0.6, 0.6, len(ring)), 0.0)
    az = 0.4 - 2 * np.pi * (col + wobble) / columns
    r = rng.uniform(2, 80, len(ring))
    pos = r[:, None] * np.stack([np.cos(el[ring]) * np.cos(az), np.cos(el[ring]) * np.sin(az), np.sin(el[ring])], 1)
    empty = (rng.random(len(ring)) > 0.7) | (col < 2) | (col >= firings - 2)
    pos[empty] = np.stack([0.9 * col / firings, 0.01 * np.ones(len(col)), np.zeros(len(col))], 1)[empty]
    fields = {"intensity": np.rint(rng.uniform(5, 60, len(ring))).astype(np.float32),
              "ring": ring.astype(np.float32)}
    return PointCloud(pos, fields, "lidar", hdl_32e())


def test_every_placeholder_of_a_whole_sweep_takes_its_weather_return():
    """A sweep that stores every firing (each ring ≥ 98 % of the grid's columns): its empty rays are its no-return
    placeholders, one ray each — those at a ring's ends (placed one column per firing on from the ring's first or
    last return, around the turn) and those whose rounded cell a jittered return or another placeholder took
    included —, and an empty cell without a placeholder (a return's jitter left it) is no ray. So under fog every
    placeholder's row holds its weather return and nothing is appended: the output keeps the input's rows, and a
    lidarseg file its labels. Before (round 21): the real nuScenes demo scan appended 914 returns and kept 238
    placeholders; here every ring's four end placeholders stayed and their rays' returns were appended."""
    from roadview_noise.annotations import carry_values
    from roadview_noise.compound import apply_models
    from roadview_noise.registry import get_model

    cloud = nuscenes_sweep()
    n = len(cloud)
    empty = np.linalg.norm(cloud.positions_m, axis=1) < 1.0
    rays = cloud_rays(cloud, "fog.lidar")
    assert rays.listed.columns == 400
    np.testing.assert_array_equal(np.sort(rays.listed.host), np.flatnonzero(empty))
    out, records = apply_models([get_model("fog.lidar")(visibility_m=30.0)], cloud, seed=1, key="k",
                                sequence_id="s", metrics=False)
    assert len(out) == n and records[0].diagnostics["added"] == np.count_nonzero(empty)
    assert (np.asarray(out.effect)[empty] == 3).all() and (np.linalg.norm(out.positions_m[empty], axis=1) > 1).all()
    np.testing.assert_array_equal(out.fields["ring"], cloud.fields["ring"])
    # a ring end's return lies on its own firing's azimuth (the sweep's last firings overlap its first columns)
    col = np.arange(n) // 32
    p = out.positions_m
    az_firing = 0.4 - 2 * np.pi * col / 400
    off = np.abs(np.angle(np.exp(1j * (np.arctan2(p[:, 1], p[:, 0]) - az_firing))))
    assert off[empty].max() < 1.6 * 2 * np.pi / 400 and np.median(off[empty]) < 0.5 * 2 * np.pi / 400
    labels = np.arange(n, dtype=np.uint8) % 31 + 1
    carried = carry_values(labels, out, 0)
    assert len(carried) == n and (carried[empty] == 0).all()


def test_a_list_storing_part_of_its_firings_keeps_its_other_empty_rays():
    """A list in firing order that stores only some of its no-returns (a third of the placeholders dropped: rings
    store under 98 % of the columns): each stored placeholder still takes its ray's weather return, and the empty
    cells no placeholder lies on are rays the list did not store, their returns appended."""
    from roadview_noise.compound import apply_models
    from roadview_noise.registry import get_model

    cloud = nuscenes_sweep(overlap=0)
    near = np.linalg.norm(cloud.positions_m, axis=1) < 1.0
    drop = near & (np.random.default_rng(5).random(len(cloud)) < 0.35)
    part = cloud.select(np.flatnonzero(~drop))
    empty = np.linalg.norm(part.positions_m, axis=1) < 1.0
    out, records = apply_models([get_model("fog.lidar")(visibility_m=30.0)], part, seed=1, key="k",
                                sequence_id="s", metrics=False)
    n = len(part)
    appended = len(out) - n
    assert (np.asarray(out.effect)[:n][empty] == 3).all()
    assert records[0].diagnostics["added"] == np.count_nonzero(empty) + appended
    assert 0.8 * np.count_nonzero(drop) < appended < 1.2 * np.count_nonzero(drop)


def test_placeholders_of_a_list_not_stored_firing_by_firing_host_nothing():
    """A list whose rows are shuffled (rings do not rise within a firing): no placeholder can be placed in a firing,
    so weather returns are appended (the placeholders keep their rows), as before."""
    from roadview_noise.compound import apply_models
    from roadview_noise.registry import get_model

    cloud, empty = nuscenes_like(fill=0.6, columns=400)
    order = np.random.default_rng(3).permutation(len(cloud))
    shuffled = cloud.select(order)
    out, records = apply_models([get_model("fog.lidar")(visibility_m=30.0)], shuffled, seed=1, key="k",
                                sequence_id="s", metrics=False)
    n = len(cloud)
    added = records[0].diagnostics["added"]
    assert added > 1000 and len(out) == n + added - records[0].diagnostics["removed"]
    np.testing.assert_array_equal(np.asarray(out.effect)[-added:], 3)


def test_ring_field_of_a_smaller_sensor_is_pointed_out():
    """A nuScenes scan read with the default OS1-128 (nothing stated): its rings 0–31 index the OS1's top 32 beams;
    the warning says so and names hdl-32e. A ring field spanning the profile's beams adds nothing."""
    cloud, _ = nuscenes_like()
    pos, intensity = cloud.positions_m, cloud.fields["intensity"]
    scale = resolve_profile(default_profile(), intensity, pos, "fog.lidar", cloud.fields["ring"])
    assert "ring field counts 32 beams (0…31) but profile 'os1-128' has 128" in scale.warning
    assert "lidar_profile hdl-32e" in scale.warning
    full = np.arange(len(pos)) % 128
    assert "ring field" not in resolve_profile(default_profile(), intensity, pos, "fog.lidar", full).warning
    with pytest.warns(IntensityWarning, match="hdl-32e"):
        cloud_rays(dataclasses.replace(cloud, profile=default_profile()), "fog.lidar")


def test_ring_field_of_an_ouster_cloud_points_to_its_metadata():
    """An OS-2-32 cloud as ouster-ros writes it (ring 0–31 and an ``ambient`` field) read with the default OS1-128:
    the hint names the unit's metadata JSON, not hdl-32e (a Velodyne of as many beams); without Ouster's fields it
    still names hdl-32e."""
    cloud, _ = nuscenes_like()
    ambient = np.zeros(len(cloud.positions_m), np.uint16)
    ouster = dataclasses.replace(cloud, profile=default_profile(), fields={**cloud.fields, "ambient": ambient})
    scale = chain_intensity_scale(ouster, "fog.lidar")
    assert "ring field counts 32 beams" in scale.warning and "Ouster metadata" in scale.warning
    assert "give lidar_profile hdl-32e" not in scale.warning and "lidar_profile FILE.json" in scale.warning
    plain = chain_intensity_scale(dataclasses.replace(cloud, profile=default_profile()), "fog.lidar")
    assert "lidar_profile hdl-32e" in plain.warning and "Ouster metadata" not in plain.warning


def test_elevations_of_a_smaller_sensor_without_ring_are_pointed_out():
    """An HDL-32E point list without a ring field (hdl_graph_slam's test scans: 32 beams −30.67° … +10.67°, 8-bit
    intensities) read with the default OS1-128 (±22°): the warning says its returns lie below the profile's beams and
    names hdl-32e (before: nothing, and fog filled a 128 × 2157 grid, 214 872 points added to 64 056 returns; with
    hdl-32e 32 × 2159 and 6 072). A cloud within the profile's beams, or a stated profile, adds nothing."""
    cloud, empty = nuscenes_like()
    pos, intensity = cloud.positions_m[~empty], cloud.fields["intensity"][~empty]
    warning = resolve_profile(default_profile(), intensity, pos, "fog.lidar").warning
    assert "returns span elevations -30.7° … +10.7° but profile 'os1-128''s beams" in warning
    assert warning.endswith("give lidar_profile hdl-32e")
    inside = pos * np.array([1.0, 1.0, 0.5])                            # within ±22°
    assert "elevations" not in resolve_profile(default_profile(), intensity, inside, "fog.lidar").warning
    assert resolve_profile(hdl_32e(), intensity, pos, "fog.lidar").warning is None


def test_bin_with_another_column_count_is_refused(tmp_path):
    """Waymo's KITTI-format velodyne .bin has 6 float32 columns (x y z intensity elongation timestamp): with an even
    point count its size is a multiple of KITTI's 16-byte point, and it used to be read as garbage (timestamps as
    coordinates of 1.5e15 m). Now refused, naming the column count that fits; Lyft's 5 columns likewise."""
    rng = np.random.default_rng(1)
    n = 800
    xyz = rng.uniform(-70, 70, (n, 3))
    waymo = np.column_stack([xyz, rng.uniform(0, 1, n), rng.uniform(0, 1.5, n), np.full(n, 1.55e15)])
    path = tmp_path / "0000000.bin"
    waymo.astype("<f4").tofile(path)
    with pytest.raises(InputError, match=r"reach 1\.55e\+15 m; read as 6 float32 columns it is plausible") as e:
        read_pointcloud(path)
    assert "0000000.bin" in str(e.value)
    lyft = tmp_path / "lyft.bin"
    np.column_stack([xyz[:5], np.full(5, 100.0), np.ones(5)]).astype("<f4").tofile(lyft)
    with pytest.raises(InputError, match="read as 5 float32 columns it is plausible"):
        read_pointcloud(lyft)
    kitti = tmp_path / "kitti.bin"
    np.column_stack([xyz, rng.uniform(0, 1, n)]).astype("<f4").tofile(kitti)
    assert len(read_pointcloud(kitti)) == n


def test_bin_fields_read_and_write_back_another_column_layout(tmp_path):
    """``inputs.bin_fields`` names a .bin's columns (Waymo's KITTI-format export): read, run and written back in
    the same 6 columns, the unchanged points byte for byte, the effect codes in the sidecar."""
    from roadview_noise.compound import apply_models
    from roadview_noise.io.pointcloud import effect_sidecar_path, write_pointcloud
    from roadview_noise.profiles.lidar import kitti_hdl64
    from roadview_noise.registry import get_model

    rng = np.random.default_rng(2)
    n = 4000
    az, el = rng.uniform(-np.pi, np.pi, n), np.deg2rad(rng.uniform(-24, 2, n))
    r = rng.uniform(3, 60, n)
    xyz = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
    reflectance = np.round(rng.uniform(0.05, 1, n), 2)                       # in 0.01 steps, as the profile stores
    table = np.column_stack([xyz, reflectance, rng.uniform(0, 1.5, n), np.full(n, 1.55e15)]).astype("<f4")
    path = tmp_path / "0000000.bin"
    table.tofile(path)
    names = ("x", "y", "z", "intensity", "elongation", "timestamp")
    cloud = read_pointcloud(path, profile=kitti_hdl64(), bin_fields=names)
    assert len(cloud) == n and set(cloud.fields) == {"intensity", "elongation", "timestamp"}
    write_pointcloud(tmp_path / "same.bin", cloud)
    assert (tmp_path / "same.bin").read_bytes() == path.read_bytes()
    out, _ = apply_models([get_model("rain.lidar")(rain_rate_mm_per_h=20)], cloud, seed=1, key="k", sequence_id="s")
    written = write_pointcloud(tmp_path / "out.bin", out)
    back = np.fromfile(tmp_path / "out.bin", "<f4").reshape(-1, 6)
    assert effect_sidecar_path(tmp_path / "out.bin") in written and len(back) == len(out)
    kept = np.flatnonzero(out.effect == 0)
    origin = np.arange(len(out)) if out.origin is None else np.asarray(out.origin)
    assert 0 < len(kept) < len(out)
    np.testing.assert_array_equal(back[kept], table[origin[kept]])
    with pytest.raises(InputError, match="must start with x, y, z"):
        read_pointcloud(path, bin_fields=("intensity", "x", "y", "z", "e", "t"))


def test_camera_fov_crop_is_reported_and_not_filled():
    """A scan cropped to the camera's field of view (KITTI's x ≥ 2.9 m): no empty ray in the cropped-away
    azimuths, and the manifest's source line says how many columns were out of view."""
    cloud, empty = nuscenes_like()
    keep = (cloud.positions_m[:, 0] >= 2.9) & ~empty
    cropped = dataclasses.replace(cloud.drop(~keep), profile=cloud.profile)
    grid = firing_grid(cropped, cropped.profile)
    assert not isinstance(grid, str), grid
    direction = grid.directions(np.arange(len(grid.ring)))
    assert len(grid.ring) > 0 and np.all(direction[:, 0] > 0)           # nothing behind the sensor
    out = int(grid.describe().split("; ")[-1].split(" of ")[0])
    assert 0.5 * 1085 < out < 0.8 * 1085 and "out of view (a crop" in grid.describe()


def nebula_pcd(path, n: int = 400, seed: int = 0) -> np.ndarray:
    """A PCD as nebula (TIER IV's Hesai/Velodyne/Robosense driver, Autoware's ``PointXYZIRCAEDT``) writes it, e.g.
    its VLP-16 test scan: x y z float32, intensity uint8, return_type uint8, channel uint16, azimuth, elevation
    (rad; azimuth clockwise from +x in [0, 2π)), distance (m) float32, time_stamp uint32. Returns its records."""
    rng = np.random.default_rng(seed)
    az, el = rng.uniform(0, 2 * np.pi, n), np.deg2rad(rng.integers(-15, 16, n) // 2 * 2.0)
    r = rng.uniform(2, 80, n)
    rec = np.zeros(n, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"), ("return_type", "u1"),
                       ("channel", "<u2"), ("azimuth", "<f4"), ("elevation", "<f4"), ("distance", "<f4"),
                       ("time_stamp", "<u4")])
    rec["x"], rec["y"], rec["z"] = r * np.cos(el) * np.cos(az), -r * np.cos(el) * np.sin(az), r * np.sin(el)
    rec["intensity"], rec["return_type"] = rng.integers(0, 120, n), 6
    rec["channel"], rec["azimuth"], rec["elevation"], rec["distance"] = (el / np.deg2rad(2) + 7.5) // 1, az, el, r
    rec["time_stamp"] = rng.integers(0, 100_000, n)
    names = rec.dtype.names
    head = ("VERSION 0.7\nFIELDS " + " ".join(names) + "\nSIZE 4 4 4 1 1 2 4 4 4 4\nTYPE F F F U U U F F F U\n"
            f"COUNT {' '.join('1' * len(names))}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
            "DATA binary\n")
    path.write_bytes(head.encode() + rec.tobytes())
    return rec


def test_nebula_distance_and_angles_follow_moved_and_added_points(tmp_path):
    """A point moved along its ray to a particle gets ``distance`` = |p| (its azimuth and elevation stay: same ray);
    a point added elsewhere gets the distance and the azimuth/elevation of its position in the file's own
    convention (clockwise azimuth in [0, 2π)). Before: both kept the values of the point their other fields came
    from (a real nebula VLP-16 scan under fog 30 m: distance up to 13 m off, elevation up to 32°)."""
    from roadview_noise.io.pointcloud import write_pointcloud
    from roadview_noise.provenance import Effect

    rec = nebula_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd")
    pos = cloud.positions_m.copy()
    pos[:10] *= 0.25                                                        # moved along the ray
    effect = np.where(np.arange(len(pos)) < 10, Effect.MOVED, Effect.ATTENUATED).astype(np.uint8)
    added = np.array([[3.0, 4.0, 0.5], [-6.0, -2.0, -1.0]])
    out = cloud.replace(positions_m=pos, effect=effect).concat(
        added, {k: v[:2] for k, v in cloud.fields.items()})                   # fields copied from other points
    write_pointcloud(tmp_path / "out.pcd", out)
    stored = np.dtype(rec.dtype.descr + [("rv_effect", "u1")])
    got = np.frombuffer((tmp_path / "out.pcd").read_bytes()[-(len(rec) + 2) * stored.itemsize:], stored)
    r = np.linalg.norm(np.concatenate([pos, added]), axis=1)
    np.testing.assert_allclose(got["distance"][:10], r[:10], rtol=1e-6)
    np.testing.assert_array_equal(got["distance"][10:-2], rec["distance"][10:])       # recorded points kept
    for name in ("azimuth", "elevation", "channel", "time_stamp"):
        np.testing.assert_array_equal(got[name][:-2], rec[name], err_msg=name)
    np.testing.assert_allclose(got["distance"][-2:], r[-2:], rtol=1e-6)
    np.testing.assert_allclose(got["azimuth"][-2:], np.mod(-np.arctan2(added[:, 1], added[:, 0]), 2 * np.pi),
                               atol=1e-6)
    np.testing.assert_allclose(got["elevation"][-2:], np.arcsin(added[:, 2] / r[-2:]), atol=1e-6)


def test_angles_without_a_convention_are_kept(tmp_path):
    """Azimuths that are not a function of the position (here shuffled) are copied as before, not invented."""
    from roadview_noise.io.derived_fields import with_derived
    from roadview_noise.provenance import Effect

    rec = nebula_pcd(tmp_path / "in.pcd")
    cloud = read_pointcloud(tmp_path / "in.pcd")
    out = cloud.replace(effect=np.full(len(rec), Effect.KEPT, np.uint8)).concat(np.ones((1, 3)), {})
    shuffled = np.append(np.random.default_rng(1).permutation(rec["azimuth"]), 0.5)
    np.testing.assert_array_equal(with_derived(shuffled, "azimuth", "<f4", out), shuffled)
    assert with_derived(shuffled, "azimuth", "<f4", out)[-1] == 0.5
    aligned = np.append(rec["azimuth"].astype(np.float64), 0.0)
    assert with_derived(aligned, "azimuth", "<f4", out)[-1] == pytest.approx(7 * np.pi / 4)


@pytest.mark.parametrize("sensor", ["lidar", "radar"])
def test_inline_profile_with_lists_is_read(tmp_path, sensor):
    """A recipe's inline profile may hold lists (a VLP-16's 16 beam elevations, no built-in profile has them):
    before, every file failed with "internal error TypeError: unhashable type: 'list'" (the profile cache key)."""
    import yaml
    from typer.testing import CliRunner

    from roadview_noise.cli.main import app
    from roadview_noise.manifest import read_manifest

    (tmp_path / "in" / sensor).mkdir(parents=True)
    nebula_pcd(tmp_path / "in" / sensor / "000000.pcd")
    beams = [-15.0 + 2 * k for k in range(16)]
    profile = ({"lidar_profile": {"base": "hdl-32e", "beam_elevation_deg": beams, "beam_azimuth_offset_deg":
                                  [0.0] * 16, "columns": 1800}} if sensor == "lidar" else
               {"radar_profile": {"base": "vod", "fov_azimuth_deg": 100.0}, "field_map": {"intensity": "snr_db"}})
    chain = [{"model": f"fog.{sensor}", "params": {"visibility_m": 30}}]
    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump({"schema": "rvnoise.recipe/1", "chain": chain, "seed": 1,
                                      "inputs": {sensor: f"{sensor}/*.pcd", **profile}}))
    r = CliRunner().invoke(app, ["augment", str(tmp_path / "in"), str(tmp_path / "out"), "--recipe", str(recipe),
                                 "--quiet"])
    entry, = read_manifest(tmp_path / "out" / "manifest.jsonl")
    assert r.exit_code == 0 and entry["status"] == "ok", r.output + str(entry.get("error"))
