"""``rvnoise export BAG OUT/``: the sensor topics of a bag as an input tree that ``rvnoise augment`` reads.

One folder per topic (the topic name without its leading slash), one file per message named by its header stamp
(``<19-digit stamp ns>[_k]``, the k-th repeat of a stamp): the message's seed key (bag_runner), so augmenting the
tree and augmenting the bag with the same chains and seed give the same pixels and points.

- CompressedImage: its JPEG/PNG bytes as they are (``.jpg``/``.png``); Image: a lossless ``.png`` of its code values
  (8/16 bit, grey, colour, alpha); Bayer Image: plain ``.raw`` + ``<stem>.yaml`` (CFA pattern, levels);
- the aligned depth message of a camera topic (recipe ``depth_topic``): ``<stem>_depth.exr``, range along the ray
  with its holes as NaN (the tree's run treats them by ``inputs.depth_holes`` as the bag's run does);
- PointCloud2: binary ``.pcd`` with the message's fields in offset order, names and types (padding dropped;
  organised clouds keep WIDTH × HEIGHT);
- per topic folder the resolved profile as a complete sidecar: ``camera.yaml`` (the topic's profile fitted to the
  image size, else the intrinsics of its CameraInfo (:mod:`roadview_noise.bag_camera_info`) at its first message —
  a warning counts the messages whose CameraInfo states others —, else the pinhole assumed from
  ``camera_fov_h_deg``),
  ``lidar.yaml`` (with the recipe's intensity scale) or ``radar.yaml``.

With a recipe, its mapped topics are exported with their profiles (its chains are not run); without one, every
image topic with a camera encoding and every PointCloud2 (radar when it has a velocity/Doppler, SNR or RCS field,
else LiDAR), with default profiles; the image topics left out (depth images: ``32FC1``, ``16UC1``,
``compressedDepth``; encodings not read) are named in a warning.
"""

from __future__ import annotations

import dataclasses
import pickle
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .bag_recipe import BagRecipe, parse_bag_recipe
from .bag_runner import (BagContext, MessageJob, TopicImage, _context, _deserialize, depth_syncs, export_stem,
                         export_suffix, plan_bag, sensor_data, stamped_messages)
from .camera_inputs import camera_geometry
from .errors import InputError, RecipeError
from .io import ros_messages as rm
from .io.atomic import write_bytes_atomic
from .io.depth import write_depth_exr
from .io.image import encode_codes
from .io.pointcloud import ALIASES, write_pointcloud
from .io.raw import write_plain_raw
from .io.rosbag import bag_kind, open_bag
from .types import ImageEncoding, RawFrame

RADAR_FIELDS = {a for k in ("v_r_m_per_s", "snr_db", "rcs_dbsm") for a in ALIASES[k]}
PROFILE_SIDECARS = {"camera": "camera.yaml", "lidar": "lidar.yaml", "radar": "radar.yaml"}


def export_bag(bag: Path, out_dir: Path, *, recipe: BagRecipe | None = None, overwrite: bool = False) -> dict:
    """Write the tree (module docstring); returns ``{"files": n, "topics": {topic: messages}, "warnings": [...]}``."""
    bag, out_dir = Path(bag), Path(out_dir)
    if bag_kind(bag) is None:
        raise RecipeError(f"input {str(bag)!r} is not a ROS bag (.bag, .mcap, .db3, or a ROS 2 bag folder)")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise RecipeError(f"{str(out_dir)!r} is not empty; use --overwrite to write over its files")
    summary: dict[str, Any] = {"files": 0, "topics": {}, "warnings": []}
    written: dict[str, Any] = {}                     # topic → the profile of its sidecar
    differing: dict[str, int] = {}                   # topic → messages whose camera geometry differs from it
    with ExitStack() as stack:
        reader = stack.enter_context(open_bag(bag))
        is2 = bag_kind(bag) == "ros2"
        if recipe is None:
            recipe, skipped = sensor_topics(reader)
            summary["warnings"] += [f"not exported: {topic} ({why})" for topic, why in skipped.items()]
        plan = plan_bag(recipe, reader, bag, every_camera=True)
        ctx = BagContext(str(bag), is2, dict(reader.typestore.fielddefs), recipe, bag.resolve().parent)
        _, typestore = _context(pickle.dumps(ctx))
        syncs = depth_syncs(stack, bag, plan, is2)
        mapped = [c for c in reader.connections if id(c) in plan.mapped]
        for conn, t, raw, stamp, repeat in stamped_messages(reader, plan.mapped, is2, bag, connections=mapped):
            topic = plan.mapped[id(conn)]
            job = MessageJob(conn.topic, conn.msgtype, stamp, repeat, t, raw,
                             syncs[topic.spec.depth_topic].take(stamp, t) if topic.spec.depth_topic else None,
                             plan.camera_info.at(conn.topic, stamp))
            source = f"{bag}: {job.key}"
            msg = _deserialize(typestore, is2, raw, conn.msgtype, source)
            data = sensor_data(ctx, topic, msg, conn.msgtype, source)
            path = out_dir / (export_stem(conn.topic, stamp, repeat) + export_suffix(msg, conn.msgtype))
            summary["files"] += write_message_file(path, msg, conn.msgtype, data)
            profile = data.profile
            if topic.sensor == "camera":
                origin = TopicImage(ctx, typestore, topic, job, source)
                geometry = camera_geometry(origin, topic.recipe, data.shape[1], data.shape[0])
                profile = geometry.profile
                if job.depth is not None:
                    depth, _, _ = origin.depth(topic.recipe, geometry)
                    write_depth_exr(path.with_name(path.name.split(".")[0] + "_depth.exr"), depth)
                    summary["files"] += 1
            if conn.topic not in written:
                write_profile(path.parent / PROFILE_SIDECARS[topic.sensor], profile)
                written[conn.topic] = profile
                summary["files"] += 1
            elif profile != written[conn.topic]:
                differing[conn.topic] = differing.get(conn.topic, 0) + 1
            summary["topics"][conn.topic] = summary["topics"].get(conn.topic, 0) + 1
    for name, n in differing.items():
        summary["warnings"].append(f"{n} message(s) of {name} have other intrinsics (their CameraInfo changed) than "
                                   f"its camera.yaml, which holds the first message's: augmenting the tree uses "
                                   "those for every image of the folder")
    return summary


def sensor_topics(reader: Any) -> tuple[BagRecipe, dict[str, str]]:
    """A topics-only recipe of every camera image and PointCloud2 topic (sensor of a cloud from its first message's
    fields), and the image topics left out with the reason: depth images — ``32FC1``, ``16UC1`` (REP 118's
    encodings: RealSense, Azure Kinect and OAK depth topics; a 16-bit grey picture is ``mono16``),
    ``compressedDepth`` — and encodings rvnoise does not read."""
    topics: dict[str, dict] = {}
    skipped: dict[str, str] = {}
    for conn in reader.connections:
        if conn.msgtype == rm.IMAGE:
            encoding = _first(reader, conn).encoding
            if encoding in rm.DEPTH_ENCODINGS and encoding != "mono16":
                skipped[conn.topic] = f"{encoding}: a depth image (REP 118); give it as a camera topic's depth_topic"
                continue
            if encoding not in rm.CAMERA_ENCODINGS:
                skipped[conn.topic] = f"Image encoding {encoding!r} is not read (supported: " \
                                      f"{', '.join(rm.CAMERA_ENCODINGS)})"
                continue
        if conn.msgtype == rm.COMPRESSED_IMAGE and "compresseddepth" in _first(reader, conn).format.lower():
            skipped[conn.topic] = "a compressedDepth image; give it as a camera topic's depth_topic"
            continue
        if conn.msgtype in rm.SENSOR_TYPES["camera"]:
            topics.setdefault(conn.topic, {"sensor": "camera"})
        elif conn.msgtype == rm.POINTCLOUD2:
            names = {f.name for f in _first(reader, conn).fields}
            topics.setdefault(conn.topic, {"sensor": "radar" if names & RADAR_FIELDS else "lidar"})
    if not topics:
        raise InputError("the bag has no camera Image, CompressedImage or PointCloud2 topic to export")
    return parse_bag_recipe({"topics": topics}, source="<export>", chains_required=False), skipped


def _first(reader: Any, conn: Any) -> Any:
    _, _, raw = next(reader.messages(connections=[conn]))
    return reader.deserialize(raw, conn.msgtype)


def write_message_file(path: Path, msg: Any, msgtype: str, data) -> int:
    """Write one message's file (and a raw frame's sidecar); returns the number of files written."""
    if msgtype == rm.COMPRESSED_IMAGE:
        write_bytes_atomic(path, bytes(msg.data))
    elif isinstance(data, RawFrame):
        write_plain_raw(path, rm.image_pixels(msg, source=str(path)).astype("uint16"), data.cfa_pattern,
                        data.black_level_dn, data.white_level_dn)
        return 2
    elif msgtype == rm.IMAGE:
        layout = rm.pixel_layout(msg.encoding, source=str(path))
        pixels = rm.image_pixels(msg, source=str(path))
        encoding = ImageEncoding(fmt="png", bit_depth=8 * pixels.dtype.itemsize, channels=layout.channels)
        write_bytes_atomic(path, encode_codes(rm.rgb_codes(pixels, layout), encoding, name=str(path)))
    else:
        write_pointcloud(path, data)
    return 1


def write_profile(path: Path, profile) -> None:
    """A complete profile sidecar: every field, so the file path resolves the very profile the bag path used."""
    fields = {k: _plain(v) for k, v in dataclasses.asdict(profile).items()}
    write_bytes_atomic(path, yaml.safe_dump(fields, sort_keys=False).encode())


def _plain(value: Any) -> Any:
    """YAML-safe value: NumPy scalars as Python numbers, tuples as lists."""
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value.item() if isinstance(value, np.generic) else value
