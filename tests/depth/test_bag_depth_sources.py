"""Depth of bag camera topics through the same code as files: an aligned depth topic with holes (``depth_holes``),
a monocular ONNX model and the ground-plane prior; each checked against the file path on the exported tree."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from roadview_noise.bag_export import export_bag
from roadview_noise.bag_recipe import parse_bag_recipe
from roadview_noise.bag_runner import manifest_path, run_bag
from roadview_noise.io import ros_messages as rm
from roadview_noise.io.rosbag import open_bag
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from roadview_noise.sampledata.bag import write_sample_bag

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_data"
CAMERA = "/camera/image/compressed"
HOLE = (slice(100, 140), slice(200, 260))                  # 40 × 60 pixels without a depth measurement


def bag_with_depth_holes(folder: Path) -> Path:
    """The one-frame sample bag (ROS 1) whose depth message has a block of zeros (REP 118: no measurement)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    src, bag = folder / "src.bag", folder / "holes.bag"
    write_sample_bag(SAMPLE, src, frames=1)
    store = get_typestore(Stores.ROS1_NOETIC)
    with open_bag(src) as reader:
        writer = Writer(bag)
        writer.open()
        conns = {id(c): writer.add_connection(c.topic, c.msgtype, typestore=store) for c in reader.connections}
        for c, t, raw in reader.messages():
            if c.topic == "/camera/depth":
                msg = reader.deserialize(raw, c.msgtype)
                z = rm.image_pixels(msg, allowed=("32FC1",), source="t").copy()
                z[HOLE] = 0.0
                raw = bytes(store.serialize_ros1(type(msg)(**{**msg.__dict__, "data": z.view(np.uint8).ravel()}),
                                                 c.msgtype))
            writer.write(conns[id(c)], t, raw)
        writer.close()
    return bag


def camera_recipe(topic: dict, **extra):
    return parse_bag_recipe({"seed": 5, "topics": {CAMERA: {"sensor": "camera", **topic}},
                             "chains": {"camera": [{"model": "fog.camera", "params": {"visibility_m": 40.0}}]},
                             **extra}, base_dir=ROOT)


def bag_jpeg(out_bag: Path) -> bytes:
    with open_bag(out_bag) as reader:
        conn = next(c for c in reader.connections if c.topic == CAMERA)
        _, _, raw = next(reader.messages(connections=[conn]))
        return bytes(reader.deserialize(raw, conn.msgtype).data)


def file_jpeg(recipe, bag: Path, tmp_path: Path, inputs: dict) -> tuple[bytes, dict]:
    """Export the bag and augment the tree with the topic's chain and seed and the same depth settings."""
    tree, out = tmp_path / "tree", tmp_path / "files"
    export_bag(bag, tree, recipe=recipe)
    spec = {**recipe.topics[CAMERA].recipe.resolved_dict(), "inputs": {"camera": "camera/image/compressed/*.jpg",
                                                                         **inputs}}
    summary = run(parse_recipe(spec, base_dir=ROOT), tree, out, workers=1, progress=False, echo=lambda _: None)
    assert (summary.done, summary.failed) == (1, 0), summary.failures
    entry = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
    return (out / entry["output"]).read_bytes(), entry


def test_depth_topic_holes_are_filled_like_a_file_sidecar(tmp_path):
    bag = bag_with_depth_holes(tmp_path)
    recipe = camera_recipe({"depth_topic": "/camera/depth", "depth_holes": "fill"})
    lines: list[str] = []
    summary = run_bag(recipe, bag, tmp_path / "out.bag", workers=1, progress=False, echo=lines.append)
    assert (summary.done, summary.failed) == (1, 0), summary.failures
    entry = json.loads(manifest_path(tmp_path / "out.bag").read_text().splitlines()[0])
    depth = entry["inputs"]["depth"]
    assert (depth["source"], depth["topic"], depth["kind"]) == ("topic", "/camera/depth", "planar")
    assert depth["holes"] == depth["filled"] == 40 * 60 and depth["policy"] == "fill"
    assert any("depth holes filled" in line for line in lines)
    assert set(entry["metrics"]) and all("metrics" in s for s in entry["steps"])    # as a file's manifest line
    jpeg, file_entry = file_jpeg(recipe, bag, tmp_path, {"depth_holes": "fill"})
    assert file_entry["inputs"]["depth"]["holes"] == 40 * 60
    assert bag_jpeg(tmp_path / "out.bag") == jpeg                                  # the same picture, byte for byte


def test_depth_topic_holes_with_policy_error_fail_that_message(tmp_path):
    bag = bag_with_depth_holes(tmp_path)
    summary = run_bag(camera_recipe({"depth_topic": "/camera/depth", "depth_holes": "error"}), bag,
                      tmp_path / "out.bag", workers=1, progress=False, echo=lambda _: None)
    assert (summary.done, summary.failed) == (0, 1)
    assert summary.failures[0].startswith(f"{bag}: {CAMERA}@1700000000000000000: /camera/depth@1700000000000000000: "
                                          "depth has 2400 holes")
    entry = json.loads(manifest_path(tmp_path / "out.bag").read_text().splitlines()[0])
    assert entry["copied_unchanged"] is True
    with open_bag(bag) as a, open_bag(tmp_path / "out.bag") as b:
        assert [raw for _, _, raw in a.messages()] == [raw for _, _, raw in b.messages()]


@pytest.mark.parametrize("source", ["onnx", "ground_plane"])
def test_depth_sources_without_a_depth_topic(tmp_path, tiny_depth_model, source):
    """A camera topic without depth messages: a monocular model or the flat-road prior, as for photos."""
    settings: dict = {"depth_source": source, "camera_fov_h_deg": 70.0}
    if source == "onnx":
        pytest.importorskip("onnxruntime")
        model = tiny_depth_model(tmp_path / "depth.onnx", weights=(0.0, 0.0, 0.0), bias=12.0)
        settings["onnx_depth"] = {"model": str(model)}
    else:
        settings["ground_plane"] = {"camera_height_m": 1.4, "sky_distance_m": 80.0}
    bag = tmp_path / "drive.bag"
    write_sample_bag(SAMPLE, bag, frames=1)
    recipe = camera_recipe(settings)
    lines: list[str] = []
    summary = run_bag(recipe, bag, tmp_path / "out.bag", workers=1, progress=False, echo=lines.append)
    assert (summary.done, summary.failed) == (1, 0), summary.failures
    entry = json.loads(manifest_path(tmp_path / "out.bag").read_text().splitlines()[0])
    assert entry["inputs"]["depth"]["source"] == source
    assert entry["inputs"]["camera"]["fov_h_deg"] == pytest.approx(70.0)
    assert any("FOV of 70°" in line for line in lines)                            # intrinsics assumed: said once
    jpeg, _ = file_jpeg(recipe, bag, tmp_path, {k: v for k, v in settings.items() if k != "camera_fov_h_deg"})
    assert bag_jpeg(tmp_path / "out.bag") == jpeg
