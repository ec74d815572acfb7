"""A sample drive as a ROS bag, built from a sample-data tree (``rvnoise sample-data``) with ``rosbags``' writer.

Topics, one message per frame (header stamps 0.1 s apart from ``START_STAMP_NS``; record times a few ms later,
interleaved like a real recording):

- ``/camera/image/compressed`` CompressedImage (``jpeg``, quality 90) of ``camera/seq0/NNNNNN.png``;
- ``/camera/depth`` Image ``32FC1``: planar depth z (m, REP 118) of ``NNNNNN_depth.exr`` (sky: +inf);
- ``/camera/image_raw`` Image ``bayer_rggb16`` of ``raw/seq0/NNNNNN.dng`` (12-bit DN, black 64, white 4095);
- ``/os_cloud_node/points`` PointCloud2 in the Ouster driver's layout: ``x y z`` float32, 4 padding bytes,
  ``intensity`` float32 at 16, ``t`` uint32 (ns) at 20, ``ring`` uint16 at 24, ``point_step`` 32 — the organised
  128 × columns grid (``os1-128-grid``) for ROS 1, the list of returns (``os1-128``) for ROS 2;
- ``/radar/points`` PointCloud2 float32 ``x y z velocity snr power rcs`` (REHEARSE layout; power = snr − 90 dB);
- ``/diagnostics`` std_msgs/String, a topic rvnoise does not map (copied through).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..io.depth import read_depth
from ..io.pointcloud import read_pointcloud
from ..io.raw import read_raw
from ..profiles.camera import load_camera_profile
from ..units import ray_factor

START_STAMP_NS = 1_700_000_000_000_000_000
FRAME_NS = 100_000_000
TOPIC_DELAY_NS = {"/camera/image/compressed": 3_000_000, "/camera/depth": 4_000_000, "/camera/image_raw": 5_000_000,
                  "/os_cloud_node/points": 7_000_000, "/radar/points": 9_000_000, "/diagnostics": 11_000_000}
RECIPE_TOPICS = {
    "/camera/image/compressed": {"sensor": "camera", "depth_topic": "/camera/depth"},
    "/camera/image_raw": {"sensor": "camera", "depth_topic": "/camera/depth", "black_level_dn": 64,
                          "white_level_dn": 4095},
    "/os_cloud_node/points": {"sensor": "lidar", "lidar_profile": {"base": "os1-128", "columns": 256}},
    "/radar/points": {"sensor": "radar", "radar_profile": {"base": "generic-77ghz", "snr_threshold_db": 10.0}},
}
OUSTER_FIELDS = (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("t", 20, 6), ("ring", 24, 4))
OUSTER_POINT_STEP = 32
RADAR_FIELDS = ("x", "y", "z", "velocity", "snr", "power", "rcs")


def write_sample_bag(sample_root: Path, out: Path, *, ros2: bool = False, frames: int | None = None,
                     repeat: int = 1, ros1_compression: str | None = None) -> dict[str, int]:
    """Write the sample drive under ``sample_root`` as a ROS 1 bag (``out`` = ``*.bag``; chunks compressed with
    ``ros1_compression`` ``lz4``/``bz2``) or a ROS 2 MCAP bag folder (``ros2``); ``repeat`` cycles the frames to
    make a longer drive. Returns the message count per topic."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    names = sorted(p.stem for p in (sample_root / "camera/seq0").glob("[0-9]*.png"))[:frames]
    profile = load_camera_profile(str(sample_root / "camera/seq0/camera.yaml"))
    writer = Writer2(out, version=9, storage_plugin=StoragePlugin.MCAP) if ros2 else Writer1(out)
    if ros1_compression:
        writer.set_compression(Writer1.CompressionFormat[ros1_compression.upper()])
    writer.open()
    types = {"/camera/image/compressed": "sensor_msgs/msg/CompressedImage", "/camera/depth": "sensor_msgs/msg/Image",
             "/camera/image_raw": "sensor_msgs/msg/Image", "/os_cloud_node/points": "sensor_msgs/msg/PointCloud2",
             "/radar/points": "sensor_msgs/msg/PointCloud2", "/diagnostics": "std_msgs/msg/String"}
    conns = {t: writer.add_connection(t, m, typestore=store) for t, m in types.items()}
    counts = dict.fromkeys(types, 0)
    serialize = store.serialize_cdr if ros2 else store.serialize_ros1
    lidar_dir = sample_root / ("lidar/os1-128/seq0" if ros2 else "lidar/os1-128-grid/seq0")
    messages = []
    for k in range(len(names) * repeat):
        name = names[k % len(names)]
        stamp = START_STAMP_NS + k * FRAME_NS
        header = _header(store, stamp, ros2)
        payloads = {
            "/camera/image/compressed": _compressed(store, header("camera"), sample_root / f"camera/seq0/{name}.png"),
            "/camera/depth": _depth(store, header("camera"), sample_root / f"camera/seq0/{name}_depth.exr", profile),
            "/camera/image_raw": _bayer(store, header("camera"), sample_root / f"raw/seq0/{name}.dng"),
            "/os_cloud_node/points": _ouster(store, header("os_sensor"), lidar_dir / f"{name}.pcd"),
            "/radar/points": _radar(store, header("radar"), sample_root / f"radar/seq0/{name}.pcd"),
            "/diagnostics": store.types["std_msgs/msg/String"](data=f"frame {k} ok"),
        }
        for topic, msg in payloads.items():
            messages.append((stamp + TOPIC_DELAY_NS[topic], topic, msg))
    for t, topic, msg in sorted(messages, key=lambda m: m[0]):
        writer.write(conns[topic], t, serialize(msg, types[topic]))
        counts[topic] += 1
    writer.close()
    return counts


def _header(store, stamp_ns: int, ros2: bool):
    def make(frame_id: str):
        time = store.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000,
                                                          nanosec=stamp_ns % 1_000_000_000)
        extra = {} if ros2 else {"seq": stamp_ns // 10 ** 8 % 2 ** 32}
        return store.types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id, **extra)
    return make


def _compressed(store, header, png: Path):
    ok, buf = cv2.imencode(".jpg", cv2.imread(str(png), cv2.IMREAD_UNCHANGED), [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return store.types["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=buf.ravel())


def _image(store, header, pixels: np.ndarray, encoding: str):
    pixels = np.ascontiguousarray(pixels)
    h, w = pixels.shape[:2]
    return store.types["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                                                step=pixels.strides[0], data=pixels.view(np.uint8).ravel())


def _depth(store, header, exr: Path, profile):
    range_m = read_depth(exr)
    planar = range_m / ray_factor(profile.width_px, profile.height_px, profile.fx_px, profile.fy_px, profile.cx_px,
                                  profile.cy_px)
    return _image(store, header, planar.astype("<f4"), "32FC1")


def _bayer(store, header, dng: Path):
    dn, pattern, *_ = read_raw(dng)
    return _image(store, header, dn.astype("<u2"), f"bayer_{pattern.lower()}16")


def _cloud(store, header, columns: list[tuple[str, int, int, np.ndarray]], step: int, grid: tuple[int, int] | None):
    from ..io.ros_messages import POINTFIELD_TYPES

    n = len(columns[0][3])
    record = np.dtype({"names": [c[0] for c in columns], "offsets": [c[1] for c in columns],
                       "formats": ["<" + POINTFIELD_TYPES[c[2]] for c in columns], "itemsize": step})
    points = np.zeros(n, record)
    for name, _, _, values in columns:
        points[name] = values
    h, w = grid or (1, n)
    field = store.types["sensor_msgs/msg/PointField"]
    return store.types["sensor_msgs/msg/PointCloud2"](
        header=header, height=h, width=w, fields=[field(name=c[0], offset=c[1], datatype=c[2], count=1)
                                                  for c in columns],
        is_bigendian=False, point_step=step, row_step=w * step, data=points.view(np.uint8).ravel(), is_dense=True)


def _ouster(store, header, pcd: Path):
    cloud = read_pointcloud(pcd)
    values = {"x": cloud.positions_m[:, 0], "y": cloud.positions_m[:, 1], "z": cloud.positions_m[:, 2],
              "intensity": cloud.fields["intensity"], "t": np.rint(cloud.fields["time_s"] * 1e9),
              "ring": cloud.fields["ring"]}
    return _cloud(store, header, [(n, o, d, values[n]) for n, o, d in OUSTER_FIELDS], OUSTER_POINT_STEP,
                  cloud.grid_shape)


def _radar(store, header, pcd: Path):
    cloud = read_pointcloud(pcd, sensor="radar")
    values = {"x": cloud.positions_m[:, 0], "y": cloud.positions_m[:, 1], "z": cloud.positions_m[:, 2],
              "velocity": cloud.fields["v_r_m_per_s"], "snr": cloud.fields["snr_db"],
              "power": cloud.fields["snr_db"] - 90.0, "rcs": cloud.fields["rcs_dbsm"]}
    return _cloud(store, header, [(n, 4 * i, 7, values[n]) for i, n in enumerate(RADAR_FIELDS)], 28, None)
