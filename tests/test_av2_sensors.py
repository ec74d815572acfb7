"""Argoverse 2 sweeps, each of the two VLP-32C on its own rays (sensor_rig.py, physics/firing_time.py).

Synthetic logs with the real layout: ``<log>/sensors/lidar/<ns>.feather`` (x, y, z halffloat in the vehicle frame,
intensity u8, laser_number u8 — 0–31 the upper sensor, 32–63 the lower one, upside down and tilted —, offset_ns
i32, rows in time order) and, or not, ``<log>/calibration/egovehicle_SE3_sensor.feather`` (sensor_name, qw, qx, qy,
qz, tx_m, ty_m, tz_m; the poses of the av2 devkit's test log 7fab2350). Each sensor fires its 32 lasers every
55.296 µs, 2.304 µs apart, its head turning at 50 Hz (360 columns a turn: a small grid), clockwise in the upper
sensor's frame, counter-clockwise in the lower one's (as in the real sweeps); its upper lasers see nothing over half
the turn (sky)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from roadview_noise.io.feather import quaternion_matrix
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.manifest import read_manifest
from roadview_noise.profiles.lidar import av2_sensor, load_lidar_profile
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run

pa = pytest.importorskip("pyarrow")
import pyarrow.feather  # noqa: E402

POSES = {"up_lidar": (0.99999, 0.0, 0.0, -0.00508, 1.35018, 0.0, 1.64042),       # qw qx qy qz tx ty tz (real log)
         "down_lidar": (-0.00054, -0.99492, 0.10067, -0.00014, 1.34676, 0.00457, 1.5255)}
CYCLE_NS = 55296
COLUMNS = 360
SPIN = {"up_lidar": -1, "down_lidar": 1}           # the head's turn in the sensor's frame (real sweeps: −10, +10 Hz)
SLOT_NS = 2304 * (np.arange(32) // 2)              # two lasers a firing, 16 firings a cycle
JITTER_DEG = 0.6                                   # standard deviation: 0.4 column median, as on the real sweeps


def sensor_rays(name: str, seed: int):
    """One sensor's fired rays: laser, firing time (ns), direction in its frame (unit), range (0: no return), and the
    direction its return is stored at (azimuth jittered by ``JITTER_DEG``, as ego-motion compensation leaves real
    sweeps: 0.09° median off a uniform turn)."""
    rng = np.random.default_rng(seed)
    profile = av2_sensor(name)
    elevation = np.deg2rad(profile.beam_elevation_deg)
    offset = np.deg2rad(profile.beam_azimuth_offset_deg)
    laser = np.tile(np.arange(32), COLUMNS)
    cycle = np.repeat(np.arange(COLUMNS), 32)
    t_ns = 3_000_000 * (name == "down_lidar") + cycle * CYCLE_NS + SLOT_NS[laser] + 1000
    head = 0.7 + SPIN[name] * 2 * np.pi * t_ns * 1e-9 / (COLUMNS * CYCLE_NS * 1e-9)
    azimuth = head - offset[laser]
    range_m = rng.uniform(4, 60, len(laser))
    sky = (elevation[laser] > np.deg2rad(2)) & (np.cos(azimuth) > 0)         # nothing up there, half the turn
    range_m[sky | (rng.random(len(laser)) < 0.05)] = 0.0
    seen = azimuth + rng.normal(0.0, np.deg2rad(JITTER_DEG), len(laser))    # ego-motion compensated returns
    return laser, t_ns, _unit(elevation[laser], azimuth), range_m, _unit(elevation[laser], seen)


def _unit(elevation, azimuth):
    return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], 1)


def av2_log(root, with_calibration: bool = True, seed: int = 0, stamp: str = "315966265259836000") -> dict:
    """A log with one sweep (and the calibration); returns the sweep's columns and each sensor's fired rays."""
    lidar = root / "sensors" / "lidar"
    lidar.mkdir(parents=True)
    rows, rays = [], {}
    for k, name in enumerate(POSES):
        qw, qx, qy, qz, *t = POSES[name]
        laser, t_ns, _, range_m, seen = rays[name] = sensor_rays(name, seed + k)
        hit = range_m > 0
        p = (seen[hit] * range_m[hit, None]) @ quaternion_matrix(qw, qx, qy, qz).T + t
        rows.append((p, laser[hit] + 32 * k, t_ns[hit]))
    p, laser, t_ns = (np.concatenate(c) for c in zip(*rows))
    order = np.argsort(t_ns, kind="stable")
    rng = np.random.default_rng(seed)
    cols = {"x": p[order, 0].astype(np.float16), "y": p[order, 1].astype(np.float16),
            "z": p[order, 2].astype(np.float16), "intensity": rng.integers(0, 256, len(order)).astype(np.uint8),
            "laser_number": laser[order].astype(np.uint8), "offset_ns": t_ns[order].astype(np.int32)}
    meta = {b"pandas": json.dumps({"index_columns": [], "columns": [{"name": k} for k in cols]}).encode()}
    pyarrow.feather.write_feather(pa.table(cols).replace_schema_metadata(meta), str(lidar / f"{stamp}.feather"),
                                  chunksize=len(order) // 2 + 1)
    if with_calibration:
        (root / "calibration").mkdir()
        names = ["ring_front_center", *POSES]
        table = {"sensor_name": names}
        for i, c in enumerate(("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")):
            table[c] = [1.0 if c == "qw" else 0.0] + [POSES[n][i] for n in POSES]
        pyarrow.feather.write_feather(pa.table(table), str(root / "calibration" / "egovehicle_SE3_sensor.feather"))
    return {"cols": cols, "rays": rays, "path": lidar / f"{stamp}.feather"}


def augment(tmp_path, chain, inputs="in", out="out", seed=3):
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": seed, "chain": chain,
                           "inputs": {"lidar": "*/sensors/lidar/*.feather", "lidar_profile": "av2-vlp32c"}},
                          base_dir=tmp_path)
    assert run(recipe, tmp_path / inputs, tmp_path / out, workers=1, progress=False,
               echo=lambda *_: None).failed == 0
    written = tmp_path / out / "log" / "sensors" / "lidar" / "315966265259836000.feather"
    table = pyarrow.feather.read_table(str(written))
    effect = np.frombuffer((written.parent / (written.name + ".rv_effect")).read_bytes(), np.uint8)
    entry, = read_manifest(tmp_path / out / "manifest.jsonl")
    return table, effect, entry


FOG = [{"model": "fog.lidar", "params": {"visibility_m": 30.0}}]


def test_calibration_beside_the_log_gives_each_sensor_its_pose_and_profile(tmp_path):
    """The poses of the log's calibration file (vehicle ← sensor), laser_number 0–31 / 32–63, each sensor's own
    32-beam profile with the firing cycle; without the file the sweep keeps the merged profile."""
    log = av2_log(tmp_path / "log")
    cloud = read_pointcloud(log["path"], profile=load_lidar_profile("av2-vlp32c"))
    up, down = cloud.profile.sensors
    assert (up.name, up.first_ring, down.name, down.first_ring) == ("up_lidar", 0, "down_lidar", 32)
    assert down.translation_m == POSES["down_lidar"][4:] and up.profile.channels == 32
    rotation = np.asarray(down.rotation)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-4)
    assert rotation[2, 2] < -0.97                   # upside down: its z axis points down
    assert up.profile.firing_cycle_s == pytest.approx(55.296e-6) and up.source == "log/calibration/" \
        "egovehicle_SE3_sensor.feather"
    bare = av2_log(tmp_path / "bare", with_calibration=False)
    assert read_pointcloud(bare["path"], profile=load_lidar_profile("av2-vlp32c")).profile.sensors == ()


def test_fog_returns_on_each_sensors_empty_rays(tmp_path):
    """Fog 30 m: each sensor's rays that saw nothing get weather returns (every one of them, as on the real sweeps),
    on their laser's direction in their sensor's frame at their firing (within 0.2°: halffloat's steps at 1.3 m from
    the sensor; 0.05° median; a column is 1° wide) — the
    added rows' laser_number and offset_ns are those of the cell's laser and firing (±1 cycle); every input row keeps
    its place, the rows the fog left alone their bytes; the table its schema; the rows stay in time order. The
    returns' azimuths jitter by 0.6° (a column is 1°; real sweeps: 0.09° median, their column 0.2°). Before: no
    weather return on an empty ray (two sensors in one frame: no firing grid)."""
    log = av2_log(tmp_path / "in" / "log")
    table, effect, entry = augment(tmp_path, FOG)
    cols = log["cols"]
    src = pyarrow.feather.read_table(str(log["path"]))
    assert table.schema.equals(src.schema, check_metadata=True)
    got = {k: table.column(k).to_numpy() for k in table.column_names}
    assert (np.diff(got["offset_ns"]) >= 0).all()
    old, added = effect != 3, effect == 3
    assert old.sum() == len(cols["x"])
    same = effect[old] <= 1
    for k in ("x", "y", "z", "laser_number", "offset_ns"):
        np.testing.assert_array_equal(got[k][old], cols[k]) if k in ("laser_number", "offset_ns") else \
            np.testing.assert_array_equal(got[k][old][same], cols[k][same])
    diagnostics = entry["steps"][0]["diagnostics"]
    for k, name in enumerate(("up_lidar", "down_lidar")):
        laser, t_ns, d, range_m, _ = log["rays"][name]
        empty = range_m == 0
        mine = added & (got["laser_number"] // 32 == k)
        per = diagnostics["sensors"][name]
        assert per["added"] == mine.sum() == empty.sum() == per["empty_rays"]
        assert per["firing_grid_columns"] == COLUMNS and "firing times (offset_ns)" in per["empty_rays_source"]
        qw, qx, qy, qz, *t = POSES[name]
        p = np.stack([got[a][mine].astype(np.float64) for a in "xyz"], 1)
        q = (p - t) @ quaternion_matrix(qw, qx, qy, qz)
        q /= np.linalg.norm(q, axis=1)[:, None]
        cell = np.flatnonzero(empty)
        lasers = got["laser_number"][mine].astype(int) - 32 * k
        # each added return: the empty cell of its laser whose direction is nearest; one cell each
        best = np.array([cell[laser[cell] == b][np.argmax(d[cell[laser[cell] == b]] @ u)] for b, u in zip(lasers, q)])
        angle = np.degrees(np.arccos(np.clip((d[best] * q).sum(1), -1, 1)))
        assert angle.max() < 0.2 and np.median(angle) < 0.05 and len(np.unique(best)) == len(best)
        assert np.abs(got["offset_ns"][mine].astype(np.int64) - t_ns[best]).max() <= CYCLE_NS
    assert diagnostics["added"] == added.sum()


def test_each_sensor_draws_its_own_randomness(tmp_path):
    """Rain (random drops): the same run twice gives the same bytes; changing the lower sensor's intensities leaves
    the upper sensor's output rows as they were (its draws derive from (seed, file, step, model, sensor)), and the
    two sensors' drops differ."""
    first = av2_log(tmp_path / "in" / "log")
    chain = [{"model": "rain.lidar", "params": {"rain_rate_mm_per_h": 50.0}}]
    a, ea, _ = augment(tmp_path, chain, out="a")
    b, eb, _ = augment(tmp_path, chain, out="b")
    assert a.equals(b) and np.array_equal(ea, eb)
    cols = dict(first["cols"])
    lower = cols["laser_number"] >= 32
    cols["intensity"] = np.where(lower, 255 - cols["intensity"], cols["intensity"]).astype(np.uint8)
    src = pyarrow.feather.read_table(str(first["path"]))
    pyarrow.feather.write_feather(pa.table(cols).replace_schema_metadata(src.schema.metadata), str(first["path"]))
    c, ec, _ = augment(tmp_path, chain, out="c")

    def upper(table, effect):
        keep = table.column("laser_number").to_numpy() < 32
        return {k: table.column(k).to_numpy()[keep] for k in table.column_names}, effect[keep]

    (ua, uea), (uc, uec) = upper(a, ea), upper(c, ec)
    assert np.array_equal(uea, uec) and all(np.array_equal(ua[k], uc[k]) for k in ua)
    assert (ea == 2).sum() > 20 and not np.array_equal(ea[a.column("laser_number").to_numpy() >= 32], ec[
        c.column("laser_number").to_numpy() >= 32])


def test_without_calibration_the_sweep_keeps_its_returns_only_and_says_why(tmp_path):
    """No calibration file beside the log: positions about the fixed origin, weather on the returns only, the
    manifest naming the missing file."""
    log = av2_log(tmp_path / "in" / "log", with_calibration=False)
    table, effect, entry = augment(tmp_path, FOG)
    assert table.num_rows == len(log["cols"]["x"]) and not (effect == 3).any()
    diagnostics = entry["steps"][0]["diagnostics"]
    assert diagnostics["empty_rays"] == 0 and "egovehicle_SE3_sensor.feather" in diagnostics["empty_rays_source"]
    assert "sensors" not in diagnostics


def test_a_broken_calibration_file_names_itself(tmp_path):
    """A calibration table without the lower sensor's pose: the sweep fails with an error naming the file."""
    from roadview_noise.errors import InputError

    log = av2_log(tmp_path / "log")
    cal = tmp_path / "log" / "calibration" / "egovehicle_SE3_sensor.feather"
    table = pyarrow.feather.read_table(str(cal))
    pyarrow.feather.write_feather(table.slice(0, 2), str(cal))
    with pytest.raises(InputError, match="no pose of \\['down_lidar'\\]") as e:
        read_pointcloud(log["path"], profile=load_lidar_profile("av2-vlp32c"))
    assert "egovehicle_SE3_sensor.feather" in str(e.value)
