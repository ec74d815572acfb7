"""ROS bags laid out as real drivers write them, built in tmp_path with rosbags' writers.

Layouts (the drivers' declared PointCloud2 fields):
- ouster-ros ``original`` point (``ouster_ros::Point``): x y z float32 at 0/4/8, 4 padding bytes (PCL's
  ``PCL_ADD_POINT4D``, which holds 1.0f), intensity float32 @16, t uint32 @20, reflectivity uint16 @24, ring uint16 @26,
  ambient uint16 @28, range uint32 @32, point_step 48; organised beams × columns, ``is_dense`` false; a no-return
  pixel is x=y=z=0 with range 0 in drivers before 0.10, NaN x/y/z since (the maintainer in ouster-ros PR #406).
- velodyne_pointcloud ``PointXYZIRT`` as its PointCloud2Modifier packs it: x y z intensity float32, ring uint16 @16,
  time float32 @18, point_step 22; its organised cloud has **one row per firing** (width = lasers, height grows by
  one per firing) and NaN x/y/z/intensity where a laser saw nothing (``OrganizedCloudXYZIRT::addPoint``).
- Livox ``CustomMsg`` (livox_ros_driver2 with ``xfer_format: 1``) is not a PointCloud2.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from roadview_noise.bag_recipe import parse_bag_recipe
from roadview_noise.bag_runner import manifest_path, run_bag
from roadview_noise.errors import RecipeError
from roadview_noise.io import ros_messages as rm
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.io.rosbag import open_bag
from roadview_noise.provenance import Effect

ROOT = Path(__file__).resolve().parents[1]
GRID_PCD = ROOT / "sample_data/lidar/os1-128-grid/seq0/000000.pcd"      # 128 beams × 256 columns, zeros = no return
STAMP = 1_700_000_000_100_000_000
TOPIC = "/points"
PROFILE = {"base": "os1-128", "columns": 256}
OUSTER_ORIGINAL = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("t", 20, 6),
                   ("reflectivity", 24, 4), ("ring", 26, 4), ("ambient", 28, 4), ("range", 32, 6)]
VELODYNE_XYZIRT = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("ring", 16, 4), ("time", 18, 7)]


def store(ros2: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)


def header(types, ros2: bool, frame_id: str):
    time = types.types["builtin_interfaces/msg/Time"](sec=STAMP // 10 ** 9, nanosec=STAMP % 10 ** 9)
    return types.types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id, **({} if ros2 else {"seq": 7}))


def scan() -> tuple[dict[str, np.ndarray], tuple[int, int]]:
    """The sample OS1-128 grid as per-cell values (beam-major), no-return cells at the origin."""
    cloud = read_pointcloud(GRID_PCD)
    p = cloud.positions_m.astype(np.float32)
    r = np.linalg.norm(p, axis=1)
    values = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "intensity": cloud.fields["intensity"],
              "t": np.rint(cloud.fields["time_s"] * 1e9), "reflectivity": np.minimum(cloud.fields["intensity"], 255),
              "ring": cloud.fields["ring"], "ambient": np.full(len(p), 7), "range": np.rint(r * 1000),
              "time": cloud.fields["time_s"]}
    return values, cloud.grid_shape


def cloud2(types, ros2: bool, fields, step: int, values: dict, shape: tuple[int, int], *, big: bool = False,
           pad_one_at: int | None = None, dense: bool = False):
    order = ">" if big else "<"
    record = np.dtype({"names": [f"f{i}" for i in range(len(fields))], "offsets": [f[1] for f in fields],
                       "formats": [order + rm.POINTFIELD_TYPES[f[2]] for f in fields], "itemsize": step})
    points = np.zeros(shape[0] * shape[1], record)
    for i, (name, _, _) in enumerate(fields):
        points[f"f{i}"] = values[name]
    raw = points.view(np.uint8).reshape(len(points), step)
    if pad_one_at is not None:                              # PCL's 4th coordinate: 1.0f in the padding
        raw[:, pad_one_at:pad_one_at + 4] = np.frombuffer(np.array(1.0, order + "f4").tobytes(), np.uint8)
    pf = types.types["sensor_msgs/msg/PointField"]
    return types.types["sensor_msgs/msg/PointCloud2"](
        header=header(types, ros2, "os_sensor"), height=shape[0], width=shape[1],
        fields=[pf(name=n, offset=o, datatype=d, count=1) for n, o, d in fields], is_bigendian=big, point_step=step,
        row_step=shape[1] * step, data=raw.ravel(), is_dense=dense)


def write_bag(path: Path, ros2: bool, types, messages: list[tuple[str, str, object]], qos=()) -> None:
    """One message per (topic, msgtype, msg), in order, 10 ms apart."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) if ros2 else Writer1(path)
    writer.open()
    conns = {}
    for k, (topic, msgtype, msg) in enumerate(messages):
        if topic not in conns:
            extra = {"offered_qos_profiles": qos} if ros2 else {}
            conns[topic] = writer.add_connection(topic, msgtype, typestore=types, **extra)
        raw = types.serialize_cdr(msg, msgtype) if ros2 else types.serialize_ros1(msg, msgtype)
        writer.write(conns[topic], STAMP + k * 10_000_000, raw)
    writer.close()


def run(tmp_path: Path, name: str, ros2: bool, msg, chain="CNF20", profile=PROFILE) -> tuple[list, object]:
    """Augment a one-cloud bag: (output messages of TOPIC, manifest entry)."""
    types = store(ros2)
    src = tmp_path / (name if ros2 else f"{name}.bag")
    write_bag(src, ros2, types, [(TOPIC, rm.POINTCLOUD2, msg)])
    out = tmp_path / (f"{name}-out" if ros2 else f"{name}-out.bag")
    recipe = parse_bag_recipe({"seed": 5, "topics": {TOPIC: {"sensor": "lidar", "lidar_profile": profile}},
                               "chains": {"lidar": chain}}, base_dir=ROOT)
    summary = run_bag(recipe, src, out, workers=1, progress=False)
    entry = json.loads(manifest_path(out).read_text().splitlines()[0])
    assert (summary.done, summary.failed) == (1, 0), summary.failures
    with open_bag(out) as reader:
        got = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    return got, entry


def columns_of(msg) -> dict[str, np.ndarray]:
    return {name: values for name, _, values in rm.cloud_columns(msg, source="t")}


@pytest.mark.parametrize("ros2", [False, True])
def test_ouster_ros_no_returns_as_nan_are_empty_rays(tmp_path, ros2):
    """ouster-ros ≥ 0.10 writes a no-return pixel as NaN x/y/z: it used to fail the message ("NaN coordinates");
    now it is a no-return ray like the older drivers' zeros — the same weather returns fill the same cells — and a
    cell still empty after the chain is written back byte for byte (NaN). Every field, offset, the padding (1.0f),
    organised shape, is_dense, header and point_step + rv_effect survive."""
    types = store(ros2)
    values, shape = scan()
    empty = ~(values["x"] != 0) & ~(values["y"] != 0) & ~(values["z"] != 0)
    assert 1000 < empty.sum() < empty.size
    zeros = cloud2(types, ros2, OUSTER_ORIGINAL, 48, values, shape, pad_one_at=12)
    nan = {**values, **{a: np.where(empty, np.nan, values[a]) for a in "xyz"}}
    marked = cloud2(types, ros2, OUSTER_ORIGINAL, 48, nan, shape, pad_one_at=12)
    (out0,), _ = run(tmp_path, "zeros", ros2, zeros)
    (out1,), entry = run(tmp_path, "nan", ros2, marked)
    assert entry["status"] == "ok"
    for out, msg in ((out0, zeros), (out1, marked)):
        assert [(f.name, f.offset, f.datatype, f.count) for f in out.fields[:-1]] == \
               [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
        assert (out.fields[-1].name, out.fields[-1].offset, out.point_step) == ("rv_effect", 48, 49)
        assert (out.height, out.width, out.is_dense, out.is_bigendian) == (*shape, False, False)
        assert out.header.frame_id == "os_sensor" and out.header.stamp == msg.header.stamp
        raw = np.asarray(out.data, np.uint8).reshape(-1, 49)
        assert (raw[:, 12:16].view("<f4") == 1.0).all()                      # padding kept
    c0, c1 = columns_of(out0), columns_of(out1)
    still = np.isnan(c1["x"])
    np.testing.assert_array_equal(still, (c0["x"] == 0) & (c0["y"] == 0) & (c0["z"] == 0))
    for name in c0:
        np.testing.assert_array_equal(c1[name][~still], c0[name][~still], err_msg=name)
    filled = empty & ~still
    assert filled.sum() > 0 and (c1["rv_effect"][filled] == Effect.ADDED).all()    # weather on the empty rays
    new = (c1["rv_effect"] == Effect.MOVED) | (c1["rv_effect"] == Effect.ADDED)     # Ouster range (mm) follows
    xyz = np.stack([c1[a] for a in "xyz"], axis=1).astype(np.float64)
    np.testing.assert_allclose(c1["range"][new], np.linalg.norm(xyz[new], axis=1) * 1000, atol=1)   # float32 x y z
    np.testing.assert_array_equal(c1["range"][~new], np.rint(values["range"])[~new])
    raw_in = np.asarray(marked.data, np.uint8).reshape(-1, 48)
    np.testing.assert_array_equal(np.asarray(out1.data, np.uint8).reshape(-1, 49)[still, :48], raw_in[still])


@pytest.mark.parametrize("big, laser_order", [(False, "ring"), (True, "ring"), (False, "firing")])
def test_velodyne_organised_cloud_has_a_row_per_firing(tmp_path, big, laser_order):
    """velodyne_pointcloud's organised cloud stores a row per firing and a column per laser (ring = column), with
    NaN for no return; rslidar_sdk's (without send_by_rows) too, its lasers in firing order (ring constant down a
    column, not equal to it). It is read as the beams × azimuths grid it is (and written back in its own order): the
    result equals, cell for cell, the same scan stored beam-major with zeros; big-endian too."""
    types = store(True)
    values, (beams, columns) = scan()
    empty = ~(values["x"] != 0) & ~(values["y"] != 0) & ~(values["z"] != 0)
    reference = cloud2(types, True, VELODYNE_XYZIRT, 22, values, (beams, columns))
    lasers = np.arange(beams) if laser_order == "ring" else np.random.default_rng(2).permutation(beams)
    transposed = {k: np.asarray(v).reshape(beams, columns)[lasers].T.ravel() for k, v in values.items()}
    cell_empty = empty.reshape(beams, columns)[lasers].T.ravel()
    for k in ("x", "y", "z", "intensity"):
        transposed[k] = np.where(cell_empty, np.nan, transposed[k])
    firing_major = cloud2(types, True, VELODYNE_XYZIRT, 22, transposed, (columns, beams), big=big)
    (ref,), _ = run(tmp_path, "ref", True, reference)
    (out,), entry = run(tmp_path, "velodyne", True, firing_major)
    assert (out.height, out.width, out.point_step, out.is_bigendian) == (columns, beams, 23, big)
    assert "input_warnings" not in entry                        # NaN intensity of a no-return cell is no bad point
    c_ref, c_out = columns_of(ref), columns_of(out)
    still = np.isnan(c_out["x"])
    for name, v in c_ref.items():
        back = v.reshape(beams, columns)[lasers].T.ravel()
        np.testing.assert_array_equal(c_out[name][~still], back[~still], err_msg=name)
    assert still.sum() < cell_empty.sum() and (c_out["rv_effect"][cell_empty & ~still] == Effect.ADDED).all()
    assert np.isnan(c_out["intensity"][still]).all() and (c_out["ring"] == np.tile(lasers, columns)).all()


def test_a_cell_the_chain_empties_gets_the_drivers_nan():
    """A return removed from a NaN-marked grid becomes NaN x/y/z (not a point at the origin); a zero-marked grid
    keeps zeros."""
    types = store(True)
    values, shape = scan()
    empty = ~(values["x"] != 0)
    nan = {**values, **{a: np.where(empty, np.nan, values[a]) for a in "xyz"}}
    for marker, vals in (("nan", nan), ("zero", values)):
        msg = cloud2(types, True, OUSTER_ORIGINAL, 48, vals, shape)
        cloud = rm.cloud_to_pointcloud(msg, sensor="lidar", profile=None, field_map=None, source="t")
        assert cloud.grid_shape == shape and np.isfinite(cloud.positions_m).all()
        remove = ~empty & (np.arange(len(empty)) % 7 == 0)
        out = rm.pointcloud_to_cloud2(msg, cloud.drop(remove), effect="auto", source="t")
        x = columns_of(out)["x"]
        assert (np.isnan(x[remove]) if marker == "nan" else x[remove] == 0).all()
        assert (np.isnan(x[empty]) if marker == "nan" else x[empty] == 0).all()
        assert out.fields[-1].name == "rv_effect"


def test_ros2_qos_and_counts_survive(tmp_path):
    """Sensor-data QoS (best effort, volatile, keep last 5) of a driver's topic and of a copied topic are kept;
    the reopened output has the input's connections and message counts."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    types = store(True)
    values, shape = scan()
    qos = [Qos(QosHistory.KEEP_LAST, 5, QosReliability.BEST_EFFORT, QosDurability.VOLATILE, QosTime(0, 0),
               QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)]
    msg = cloud2(types, True, OUSTER_ORIGINAL, 48, values, shape)
    text = types.types["std_msgs/msg/String"](data="ok")
    src = tmp_path / "drive"
    write_bag(src, True, types, [(TOPIC, rm.POINTCLOUD2, msg), ("/diag", "std_msgs/msg/String", text),
                                 ("/diag", "std_msgs/msg/String", text)], qos=qos)
    out = tmp_path / "out"
    recipe = parse_bag_recipe({"seed": 5, "topics": {TOPIC: {"sensor": "lidar", "lidar_profile": PROFILE}},
                               "chains": {"lidar": "CNF20"}}, base_dir=ROOT)
    assert run_bag(recipe, src, out, workers=1, progress=False).done == 1
    with open_bag(src) as a, open_bag(out) as b:
        assert [(c.topic, c.msgtype, c.msgcount, c.ext.offered_qos_profiles) for c in a.connections] == \
               [(c.topic, c.msgtype, c.msgcount, c.ext.offered_qos_profiles) for c in b.connections]
        assert b.message_count == 3 and [t for _, t, _ in a.messages()] == [t for _, t, _ in b.messages()]


def _refused_topic(tmp_path, types, topic: str, msgtype: str, msg, sensor: str, chain: str, match: str) -> None:
    """A bag whose ``topic`` carries ``msg`` mapped as ``sensor`` is refused with ``match`` before anything is
    written."""
    src = tmp_path / "in.bag"
    write_bag(src, False, types, [(topic, msgtype, msg)])
    recipe = parse_bag_recipe({"seed": 5, "topics": {topic: {"sensor": sensor}}, "chains": {sensor: chain}},
                              base_dir=ROOT)
    out = tmp_path / "out.bag"
    with pytest.raises(RecipeError, match=match):
        run_bag(recipe, src, out, workers=1, progress=False)
    assert not out.exists()


def test_livox_custom_msg_is_refused_naming_topic_and_fix(tmp_path):
    """A Livox CustomMsg topic mapped as a LiDAR is refused before anything is written, saying what it is and how
    to record a PointCloud2 instead."""
    from rosbags.typesys import get_types_from_msg

    types = store(False)
    point = "uint32 offset_time\nfloat32 x\nfloat32 y\nfloat32 z\nuint8 reflectivity\nuint8 tag\nuint8 line\n"
    custom = ("std_msgs/Header header\nuint64 timebase\nuint32 point_num\nuint8 lidar_id\nuint8[3] rsvd\n"
              "CustomPoint[] points\n")
    types.register({**get_types_from_msg(point, "livox_ros_driver2/msg/CustomPoint"),
                    **get_types_from_msg(custom, "livox_ros_driver2/msg/CustomMsg")})
    cls = types.types["livox_ros_driver2/msg/CustomMsg"]
    msg = cls(header=header(types, False, "livox_frame"), timebase=STAMP, point_num=0, lidar_id=0,
              rsvd=np.zeros(3, np.uint8), points=[])
    _refused_topic(tmp_path, types, "/livox/lidar", "livox_ros_driver2/msg/CustomMsg", msg, "lidar", "CNF20",
                   r"/livox/lidar carries livox_ros_driver2/msg/CustomMsg.*xfer_format")


def test_radar_scan_is_refused_naming_topic_and_fix(tmp_path):
    """A radar_msgs RadarScan topic (TIER IV's ars408_driver) mapped as radar is refused before anything is written,
    saying what it holds and what to convert it to."""
    from rosbags.typesys import get_types_from_msg

    types = store(False)
    ret = "float32 range\nfloat32 azimuth\nfloat32 elevation\nfloat32 doppler_velocity\nfloat32 amplitude\n"
    scan_def = "std_msgs/Header header\nRadarReturn[] returns\n"
    types.register({**get_types_from_msg(ret, "radar_msgs/msg/RadarReturn"),
                    **get_types_from_msg(scan_def, "radar_msgs/msg/RadarScan")})
    r = types.types["radar_msgs/msg/RadarReturn"](range=12.0, azimuth=0.1, elevation=0.0, doppler_velocity=-3.0,
                                                  amplitude=10.0)
    msg = types.types["radar_msgs/msg/RadarScan"](header=header(types, False, "radar"), returns=[r])
    _refused_topic(tmp_path, types, "/radar/scan", "radar_msgs/msg/RadarScan", msg, "radar", "CNF25",
                   r"/radar/scan carries radar_msgs/msg/RadarScan.*doppler_velocity")


def test_export_of_a_nan_marked_velodyne_cloud_augments_like_the_bag(tmp_path):
    """`rvnoise export` writes the NaN-marked, firing-major cloud as the beam-major PCD grid with zeros for no
    return (the file path's convention); augmenting that PCD with the same chain and seed gives the bag's points
    (its NaN cells are the PCD's zero cells)."""
    from roadview_noise.bag_export import export_bag
    from roadview_noise.recipe import parse_recipe
    from roadview_noise.runner import run as run_files

    types = store(True)
    values, (beams, columns) = scan()
    empty = ~(values["x"] != 0) & ~(values["y"] != 0) & ~(values["z"] != 0)
    transposed = {k: np.asarray(v).reshape(beams, columns).T.ravel() for k, v in values.items()}
    cell_empty = empty.reshape(beams, columns).T.ravel()
    for k in ("x", "y", "z", "intensity"):
        transposed[k] = np.where(cell_empty, np.nan, transposed[k])
    (out,), _ = run(tmp_path, "velodyne", True, cloud2(types, True, VELODYNE_XYZIRT, 22, transposed,
                                                       (columns, beams)))
    recipe = parse_bag_recipe({"seed": 5, "topics": {TOPIC: {"sensor": "lidar", "lidar_profile": PROFILE}},
                               "chains": {"lidar": "CNF20"}}, base_dir=ROOT)
    tree = tmp_path / "tree"
    export_bag(tmp_path / "velodyne", tree, recipe=recipe)
    (pcd,) = sorted(tree.glob("points/*.pcd"))
    exported = read_pointcloud(pcd)
    assert exported.grid_shape == (beams, columns) and np.isfinite(exported.positions_m).all()
    spec = {**recipe.topics[TOPIC].recipe.resolved_dict(), "inputs": {"lidar": "points/*.pcd"}}
    s = run_files(parse_recipe(spec), tree, tmp_path / "files", workers=1, progress=False)
    assert (s.done, s.failed) == (1, 0), s.failures
    files = read_pointcloud(tmp_path / "files/points" / pcd.name)
    bag = {k: v.reshape(columns, beams).T.ravel() for k, v in columns_of(out).items()}
    still = np.isnan(bag["x"])
    np.testing.assert_array_equal(still, ~files.positions_m.any(axis=1))
    np.testing.assert_array_equal(bag["x"][~still], files.positions_m[~still, 0].astype(np.float32))
    np.testing.assert_array_equal(bag["rv_effect"], files.fields["rv_effect"])


@pytest.mark.parametrize("ros2", [False, True])
def test_unorganised_cloud_with_small_and_wide_types_and_repeated_names(tmp_path, ros2):
    """A point list (height 1, dense) with uint8 intensity, uint16 ring, float64 time stamps, an int8 tag and two
    padding fields both named ``_`` (as PCL names padding), aligned to 32 bytes: every field keeps its offset,
    datatype and — on every point that came from the input — its value; the weather's points are appended."""
    types = store(ros2)
    values, _ = scan()
    keep = (values["x"] != 0) | (values["y"] != 0) | (values["z"] != 0)
    n = int(keep.sum())
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("_", 12, 7), ("intensity", 16, 2), ("tag", 17, 1),
              ("ring", 18, 4), ("_", 20, 6), ("timestamp", 24, 8)]
    listed = {k: np.asarray(v)[keep] for k, v in values.items()}
    listed.update(intensity=np.minimum(np.rint(listed["intensity"]), 255), tag=np.arange(n) % 3 - 1, _=0,
                  timestamp=1.7e9 + np.arange(n) * 1e-6)     # unique: finds each kept point's input
    msg = cloud2(types, ros2, fields, 32, listed, (1, n), dense=True)
    (out,), entry = run(tmp_path, "list", ros2, msg, chain=[{"model": "fog.lidar", "params": {"visibility_m": 30}}])
    assert [(f.name, f.offset, f.datatype) for f in out.fields[:-1]] == [(a, b, c) for a, b, c in fields]
    assert (out.height, out.point_step, out.is_dense, out.fields[-1].name) == (1, 33, True, "rv_effect")
    got = np.asarray(out.data, np.uint8).reshape(-1, 33)
    cols = columns_of(out)
    kept = cols["rv_effect"] != Effect.ADDED
    assert kept.sum() <= n < len(got) and entry["status"] == "ok"
    inp = rm.cloud_columns(msg, source="t")
    by_time = {t: i for i, t in enumerate(listed["timestamp"])}
    src = np.array([by_time[t] for t in cols["timestamp"][kept]])
    for name, _, v in inp:
        if name not in ("x", "y", "z", "intensity"):
            np.testing.assert_array_equal(cols[name][kept], v[src], err_msg=name)
    assert cols["intensity"].dtype == np.uint8 and cols["tag"].dtype == np.int8
    assert got.shape[0] == out.width


NUSCENES_RADAR = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("dyn_prop", 12, 1), ("id", 13, 3), ("rcs", 15, 7),
                  ("vx", 19, 7), ("vy", 23, 7), ("vx_comp", 27, 7), ("vy_comp", 31, 7), ("is_quality_valid", 35, 1),
                  ("ambig_state", 36, 1), ("x_rms", 37, 1), ("y_rms", 38, 1), ("invalid_state", 39, 1),
                  ("pdh0", 40, 1), ("vx_rms", 41, 1), ("vy_rms", 42, 1)]      # nuScenes radar PCD, packed: 43 bytes
TI_MMWAVE = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("velocity", 20, 7)]   # PCL aligned: 32


@pytest.mark.parametrize("layout", ["ti_mmwave", "ars408"])
def test_radar_point_clouds_of_real_drivers(tmp_path, layout):
    """ti_mmwave_rospkg (x y z intensity velocity, intensity = SNR dB, mapped with field_map) and a Continental ARS
    408 cluster list in nuScenes' 18 fields go through CNF25; every field keeps its offset, type and the values of
    the points that stay, the effect code is appended."""
    rng = np.random.default_rng(3)
    n = 120
    r, az = rng.uniform(5, 80, n), rng.uniform(-0.8, 0.8, n)
    values = {"x": r * np.cos(az), "y": r * np.sin(az), "z": np.zeros(n) if layout == "ars408" else
              rng.uniform(-1, 1, n), "intensity": rng.uniform(8, 30, n), "velocity": rng.uniform(-10, 10, n),
              "dyn_prop": rng.integers(0, 7, n), "id": np.arange(n), "rcs": rng.uniform(-5, 20, n),
              "vx": rng.normal(0, 3, n), "vy": rng.normal(0, 1, n), "is_quality_valid": np.ones(n),
              "ambig_state": np.full(n, 3), "x_rms": np.full(n, 3), "y_rms": np.full(n, 4),
              "invalid_state": np.zeros(n), "pdh0": np.ones(n), "vx_rms": np.full(n, 5), "vy_rms": np.full(n, 6)}
    values.update(vx_comp=values["vx"] + 12.0 * np.cos(az) ** 2, vy_comp=values["vy"] + 12.0 * np.cos(az) * np.sin(az))
    fields, step = (TI_MMWAVE, 32) if layout == "ti_mmwave" else (NUSCENES_RADAR, 43)
    types = store(False)
    msg = cloud2(types, False, fields, step, values, (1, n), dense=True)
    src = tmp_path / "radar.bag"
    write_bag(src, False, types, [("/radar", rm.POINTCLOUD2, msg)])
    spec = ({"sensor": "radar", "field_map": {"intensity": "snr_db"}} if layout == "ti_mmwave" else
            {"sensor": "radar", "radar_profile": "ars408"})
    recipe = parse_bag_recipe({"seed": 5, "topics": {"/radar": spec}, "chains": {"radar": "CNF25"}}, base_dir=ROOT)
    out = tmp_path / "out.bag"
    summary = run_bag(recipe, src, out, workers=1, progress=False)
    assert (summary.done, summary.failed) == (1, 0), summary.failures
    with open_bag(out) as reader:
        (got,) = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    assert [(f.name, f.offset, f.datatype) for f in got.fields[:-1]] == fields
    assert (got.fields[-1].name, got.point_step) == ("rv_effect", step + 1)
    cols = columns_of(got)
    kept = (cols["rv_effect"] != Effect.ADDED) & np.isin(cols["x"], np.float32(values["x"]))
    src_index = np.searchsorted(np.float32(values["x"]), cols["x"][kept], sorter=np.argsort(np.float32(values["x"])))
    order = np.argsort(np.float32(values["x"]))[src_index]
    assert kept.sum() > n // 2
    for name, _, datatype in fields:
        if name not in ("x", "y", "z", "rcs", "intensity", "velocity", "vx", "vy", "vx_comp", "vy_comp"):
            np.testing.assert_array_equal(cols[name][kept], np.asarray(values[name])[order].astype(
                rm.POINTFIELD_TYPES[datatype]), err_msg=name)


def test_a_binned_camera_info_gives_the_sample_drive_camera_its_intrinsics(tmp_path):
    """The sample drive's 484×366 camera with the CameraInfo a driver binning the 1936×1464 Lucid 4×4 publishes
    next to it: the camera topic takes that K, scaled to its pixels (rain's depth conversion and geometry use it),
    no intrinsics are assumed; a stated profile wins over it."""
    from rosbags.rosbag1 import Writer

    from roadview_noise.sampledata.bag import RECIPE_TOPICS, write_sample_bag

    src = tmp_path / "in.bag"
    write_sample_bag(ROOT / "sample_data", src, frames=1)
    types = store(False)
    bag = tmp_path / "info.bag"
    with open_bag(src) as reader:
        writer = Writer(bag)
        writer.open()
        conns = {id(c): writer.add_connection(c.topic, c.msgtype, typestore=types) for c in reader.connections}
        info = writer.add_connection("/camera/camera_info", rm.CAMERA_INFO, typestore=types)
        for c, t, raw in reader.messages():
            writer.write(conns[id(c)], t, raw)
            if c.topic == "/camera/image/compressed":
                stamp = reader.deserialize(raw, c.msgtype).header.stamp          # the image's: sync by stamp
        msg = types.types[rm.CAMERA_INFO](
            header=types.types["std_msgs/msg/Header"](seq=1, stamp=stamp, frame_id="camera"), height=1464,
            width=1936, distortion_model="plumb_bob",
            D=np.zeros(5), K=np.array([1200.0, 0, 968, 0, 1200, 732, 0, 0, 1]), R=np.eye(3).ravel(),
            P=np.zeros(12), binning_x=4, binning_y=4,
            roi=types.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                 do_rectify=False))
        writer.write(info, STAMP, types.serialize_ros1(msg, rm.CAMERA_INFO))
        writer.close()
    topics = {"/camera/image/compressed": RECIPE_TOPICS["/camera/image/compressed"]}
    recipe = parse_bag_recipe({"seed": 5, "topics": topics, "chains": {"camera": "CNF16"}}, base_dir=ROOT)
    summary = run_bag(recipe, bag, tmp_path / "out.bag", workers=1, progress=False, echo=lambda _: None)
    assert (summary.done, summary.failed) == (1, 0), summary.failures
    assert not [w for w in summary.warnings if "CameraInfo" in w or "FOV" in w]
    (entry,) = [json.loads(line) for line in manifest_path(tmp_path / "out.bag").read_text().splitlines()]
    camera = entry["inputs"]["camera"]
    assert (camera["fx_px"], camera["fy_px"], camera["cx_px"], camera["cy_px"]) == (300.0, 300.0, 241.625, 182.625)
    assert camera["camera_info"]["binning"] == [4, 4] and camera["from"].startswith("CameraInfo /camera/camera_info")
    with_profile = {"/camera/image/compressed": {**topics["/camera/image/compressed"],
                                                 "camera_profile": "lucid_triton_028s"}}
    recipe = parse_bag_recipe({"seed": 5, "topics": with_profile, "chains": {"camera": "CNF16"}}, base_dir=ROOT)
    summary = run_bag(recipe, bag, tmp_path / "out2.bag", workers=1, progress=False, echo=lambda _: None)
    (entry,) = [json.loads(line) for line in manifest_path(tmp_path / "out2.bag").read_text().splitlines()]
    assert "camera_info" not in entry["inputs"]["camera"] and entry["inputs"]["camera"]["profile"] == \
        "lucid_triton_028s"


VLS_PCD = ROOT / "sample_data/lidar/vls-128/seq0/000000.pcd"
VELODYNE_PCL_ALIGNED = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("ring", 20, 4),
                        ("time", 24, 7)]                   # velodyne_ros::Point as LIO-style tools publish it: 32 bytes


@pytest.mark.parametrize("fields, step", [(VELODYNE_XYZIRT, 22), (VELODYNE_PCL_ALIGNED, 32)])
def test_velodyne_point_list_augments_like_its_pcd(tmp_path, fields, step):
    """A VLS-128 scan as velodyne_pointcloud's (unorganised) point list, packed (22 bytes) or PCL-aligned (32):
    the bag's output equals the exported PCD's, augmented by the file path with the same chain and seed — the
    firing grid measured from the list, weather on its empty rays."""
    from roadview_noise.bag_export import export_bag
    from roadview_noise.recipe import parse_recipe
    from roadview_noise.runner import run as run_files

    cloud = read_pointcloud(VLS_PCD)
    values = {"x": cloud.positions_m[:, 0], "y": cloud.positions_m[:, 1], "z": cloud.positions_m[:, 2],
              "intensity": cloud.fields["intensity"], "ring": cloud.fields["ring"], "time": cloud.fields["time_s"]}
    types = store(False)
    src = tmp_path / "vls.bag"
    write_bag(src, False, types, [(TOPIC, rm.POINTCLOUD2, cloud2(types, False, fields, step, values,
                                                                 (1, len(cloud)), dense=True))])
    recipe = parse_bag_recipe({"seed": 5, "topics": {TOPIC: {"sensor": "lidar", "lidar_profile": "vls-128"}},
                               "chains": {"lidar": "CNF20"}}, base_dir=ROOT)
    out = tmp_path / "out.bag"
    summary = run_bag(recipe, src, out, workers=1, progress=False)
    assert (summary.done, summary.failed) == (1, 0), summary.failures
    entry = json.loads(manifest_path(out).read_text())
    with open_bag(out) as reader:
        (got,) = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    tree = tmp_path / "tree"
    export_bag(src, tree, recipe=recipe)
    spec = {**recipe.topics[TOPIC].recipe.resolved_dict(), "inputs": {"lidar": "points/*.pcd"}}
    s = run_files(parse_recipe(spec), tree, tmp_path / "files", workers=1, progress=False)
    assert (s.done, s.failed) == (1, 0), s.failures
    (pcd,) = (tmp_path / "files/points").glob("*.pcd")
    files = read_pointcloud(pcd)
    cols = columns_of(got)
    assert len(cols["x"]) == len(files) > len(cloud) and "firing grid" in json.dumps(entry["steps"])
    np.testing.assert_array_equal(cols["x"], files.positions_m[:, 0].astype(np.float32))
    np.testing.assert_array_equal(cols["time"], files.fields["time_s"])
    np.testing.assert_array_equal(cols["rv_effect"], files.fields["rv_effect"])


def to_mm(z_m: np.ndarray) -> np.ndarray:
    """16-bit millimetres as a driver stores them: no measurement 0, beyond 65.535 m the largest value."""
    return np.rint(np.minimum(np.nan_to_num(z_m, nan=0.0, posinf=65.535), 65.535) * 1000).astype(np.uint16)


def compressed_depth_msg(types, z_m: np.ndarray, encoding: str, *, codec: str = " png", frame_id: str = "camera"):
    """A CompressedImage as compressed_depth_image_transport writes it (its documented ConfigHeader + 16-bit PNG);
    32FC1 quantised with its defaults (depth_max 10 m, depth_quantization 100)."""
    import struct

    import cv2

    if encoding == "16UC1":
        a = b = 0.0
        v = to_mm(z_m)
    else:
        a = 100.0 * 101.0
        b = 1.0 - a / 10.0
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(np.isfinite(z_m) & (z_m > 0), np.rint(a / z_m + b), 0).astype(np.uint16)
    ok, png = cv2.imencode(".png", v)
    assert ok
    data = np.frombuffer(struct.pack("<iff", 0, a, b) + png.tobytes(), np.uint8)
    return types.types["sensor_msgs/msg/CompressedImage"](header=header(types, True, frame_id),
                                                          format=f"{encoding}; compressedDepth{codec}", data=data)


def test_compressed_depth_decodes_to_metres():
    """16UC1 (mm, lossless) and 32FC1 (inverse-depth quantisation: z = A/(v − B)) compressedDepth images give the
    depth in metres with holes as NaN; RVL and a headerless payload are refused naming the problem."""
    from roadview_noise.errors import InputError

    types = store(True)
    z = np.linspace(0.5, 9.5, 48, dtype=np.float32).reshape(6, 8)
    z[0, :3] = np.nan
    got16 = rm.depth_image_m(compressed_depth_msg(types, z, "16UC1", codec=""), rm.COMPRESSED_IMAGE, source="t")
    np.testing.assert_allclose(got16, np.rint(z * 1000) / 1000, rtol=0, atol=1e-6)
    got32 = rm.depth_image_m(compressed_depth_msg(types, z, "32FC1"), rm.COMPRESSED_IMAGE, source="t")
    assert np.isnan(got32[0, :3]).all() and np.isnan(got16[0, :3]).all()
    np.testing.assert_allclose(got32, z, rtol=np.nanmax(z) / 10100 * 1.01)    # one quantisation step: z²/A
    with pytest.raises(InputError, match="codec 'rvl' is not supported"):
        rm.depth_image_m(compressed_depth_msg(types, z, "16UC1", codec=" rvl"), rm.COMPRESSED_IMAGE, source="t")
    bare = compressed_depth_msg(types, z, "16UC1")
    with pytest.raises(InputError, match="not a 12-byte header and a PNG"):
        rm.depth_image_m(type(bare)(header=bare.header, format=bare.format, data=bare.data[12:]),
                         rm.COMPRESSED_IMAGE, source="t")


def test_compressed_depth_topic_gives_the_same_camera_output_as_a_16uc1_image(tmp_path):
    """A camera chain that needs depth reads a compressedDepth topic: same pixels as with the same depth as a 16UC1
    Image topic (it used to be refused: "depth topic carries CompressedImage")."""
    from roadview_noise.sampledata.bag import RECIPE_TOPICS, write_sample_bag

    src = tmp_path / "in"
    write_sample_bag(ROOT / "sample_data", src, ros2=True, frames=1)
    types = store(True)
    outputs = []
    for kind in ("image", "compressed"):
        messages = []
        with open_bag(src) as reader:
            for c, _, raw in reader.messages():
                if c.topic == "/camera/image/compressed":
                    messages.append((c.topic, c.msgtype, reader.deserialize(raw, c.msgtype)))
                elif c.topic == "/camera/depth":
                    z = rm.depth_image_m(reader.deserialize(raw, c.msgtype), rm.IMAGE, source="t")
                    if kind == "image":
                        mm = to_mm(z).astype("<u2")
                        msg = types.types[rm.IMAGE](header=header(types, True, "camera"), height=mm.shape[0],
                                                    width=mm.shape[1], encoding="16UC1", is_bigendian=0,
                                                    step=mm.strides[0], data=mm.view(np.uint8).ravel())
                        messages.append((c.topic, rm.IMAGE, msg))
                    else:
                        messages.append((c.topic, rm.COMPRESSED_IMAGE, compressed_depth_msg(types, z, "16UC1")))
        for i, (topic, msgtype, msg) in enumerate(messages):      # the camera message's stamp on its depth
            if topic == "/camera/image/compressed":
                stamp = msg.header.stamp
        messages = [(t, m, type(x)(**{**{k: getattr(x, k) for k in x.__dataclass_fields__},
                                      "header": type(x.header)(stamp=stamp, frame_id="camera")}))
                    for t, m, x in messages]
        bag = tmp_path / kind
        write_bag(bag, True, types, messages)
        topics = {"/camera/image/compressed": RECIPE_TOPICS["/camera/image/compressed"]}
        recipe = parse_bag_recipe({"seed": 5, "topics": topics, "chains": {"camera": "CNF16"}}, base_dir=ROOT)
        out = tmp_path / f"{kind}-out"
        summary = run_bag(recipe, bag, out, workers=1, progress=False, echo=lambda _: None)
        assert (summary.done, summary.failed) == (1, 0), summary.failures
        entry = json.loads(manifest_path(out).read_text())
        assert entry["inputs"]["depth"]["encoding"] == ("16UC1" if kind == "image" else "16UC1; compressedDepth png")
        with open_bag(out) as reader:
            outputs.append([bytes(raw) for c, _, raw in reader.messages() if c.topic == "/camera/image/compressed"])
    assert outputs[0] == outputs[1]
    from roadview_noise.bag_export import export_bag

    assert set(export_bag(tmp_path / "compressed", tmp_path / "tree")["topics"]) == {"/camera/image/compressed"}


def test_an_empty_cloud_is_copied_and_counted_not_failed(tmp_path):
    """A radar frame without detections (width 0, as ti_mmwave and ARS 408 drivers publish them) is copied unchanged
    and counted as empty, not failed: the run exits 0 (it used to fail "the point cloud is empty (0 points)"); its
    entry says so in the words of a file run's empty cloud."""
    from typer.testing import CliRunner

    from cli.main import app
    from roadview_noise.bag_runner import run_record_path

    types = store(False)
    rng = np.random.default_rng(1)
    n = 40
    values = {"x": rng.uniform(5, 50, n), "y": rng.uniform(-5, 5, n), "z": np.zeros(n),
              "intensity": rng.uniform(8, 30, n), "velocity": rng.uniform(-5, 5, n)}
    empty = cloud2(types, False, TI_MMWAVE, 32, {k: v[:0] for k, v in values.items()}, (1, 0), dense=True)
    full = cloud2(types, False, TI_MMWAVE, 32, values, (1, n), dense=True)
    src = tmp_path / "radar.bag"
    write_bag(src, False, types, [("/radar", rm.POINTCLOUD2, empty), ("/radar", rm.POINTCLOUD2, full)])
    recipe = tmp_path / "r.yaml"
    recipe.write_text('seed: 5\ntopics:\n  /radar: {sensor: radar, field_map: {intensity: snr_db}}\n'
                      'chains: {radar: CNF25}\n')
    out = tmp_path / "out.bag"
    result = CliRunner().invoke(app, ["augment", "--recipe", str(recipe), str(src), str(out)])
    assert result.exit_code == 0, result.output
    assert "1 messages augmented, 0 failed (copied unchanged), 1 empty clouds (copied unchanged)" in result.output
    record = json.loads(run_record_path(out).read_text())
    assert record["counts"] == {"augmented": 1, "failed": 0, "messages": 2, "empty": 1}
    assert record["topics"]["/radar"] == {"messages": 2, "ok": 1, "failed": 0, "empty": 1}
    first = json.loads(manifest_path(out).read_text().splitlines()[0])
    # the vocabulary of a file run's empty cloud (test_empty_clouds.py): ok, copied unchanged, why, no steps
    assert (first["status"], first["copied_unchanged"], first["steps"], first["metrics"]) == ("ok", True, [], {})
    assert "0 points" in first["note"] and first["output_sha256"] == first["input_sha256"]
    assert "skipped" not in first and "seed_key" not in first
    with open_bag(src) as a, open_bag(out) as b:
        assert next(a.messages())[2] == next(b.messages())[2]


def test_real_ouster_scan_nan_marked_zero_marked_and_pcd_agree(tmp_path, shared_data):
    """The real OS1-128 range image (128 × 1024, 23 425 no-return cells) as ouster-ros messages — no-returns NaN
    (≥ 0.10) and zeros (older) — and as a PCD grid through the file path: CNF20 puts the same weather returns in
    the same empty cells and leaves the same points (real data: skipped when ../shared/data is absent)."""
    from roadview_noise.bag_export import export_bag
    from roadview_noise.recipe import parse_recipe
    from roadview_noise.runner import run as run_files

    grid = np.load(shared_data / "os1-128/scan0_grid.npz")
    xyz = grid["xyz_m"].reshape(-1, 3)
    empty = grid["range_mm"].ravel() == 0
    beams, columns = grid["range_mm"].shape
    values = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "intensity": grid["reflectivity"].ravel(),
              "t": np.tile(np.arange(columns) * 97656, beams), "reflectivity": grid["reflectivity"].ravel(),
              "ring": np.repeat(np.arange(beams), columns), "ambient": grid["near_ir"].ravel(),
              "range": grid["range_mm"].ravel()}
    types = store(True)
    nan = {**values, **{a: np.where(empty, np.nan, values[a]) for a in "xyz"}}
    (zero_out,), _ = run(tmp_path, "zeros", True, cloud2(types, True, OUSTER_ORIGINAL, 48, values, (beams, columns),
                                                         pad_one_at=12), profile="os1-128")
    (nan_out,), _ = run(tmp_path, "nan", True, cloud2(types, True, OUSTER_ORIGINAL, 48, nan, (beams, columns),
                                                      pad_one_at=12), profile="os1-128")
    recipe = parse_bag_recipe({"seed": 5, "topics": {TOPIC: {"sensor": "lidar", "lidar_profile": "os1-128"}},
                               "chains": {"lidar": "CNF20"}}, base_dir=ROOT)
    tree = tmp_path / "tree"
    export_stem = f"points/{STAMP:019d}.pcd"
    export_bag(tmp_path / "nan", tree, recipe=recipe)                  # the NaN-marked bag, as a user would
    spec = {**recipe.topics[TOPIC].recipe.resolved_dict(), "inputs": {"lidar": "points/*.pcd"}}
    s = run_files(parse_recipe(spec), tree, tmp_path / "files", workers=1, progress=False)
    assert (s.done, s.failed) == (1, 0), s.failures
    files = read_pointcloud(tmp_path / "files" / export_stem)
    c0, c1 = columns_of(zero_out), columns_of(nan_out)
    still = np.isnan(c1["x"])
    filled = empty & ~still
    assert empty.sum() == 23425 and filled.sum() > 0 and (c1["rv_effect"][filled] == Effect.ADDED).all()
    np.testing.assert_array_equal(still, ~files.positions_m.any(axis=1))
    for name in ("x", "y", "z"):
        np.testing.assert_array_equal(c1[name][~still], c0[name][~still])
        np.testing.assert_array_equal(c0[name], files.positions_m[:, "xyz".index(name)].astype(np.float32))
    np.testing.assert_array_equal(c1["rv_effect"], files.fields["rv_effect"])
