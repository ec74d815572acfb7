"""ROS bags in, ROS bags out: ROS 1 and ROS 2 (MCAP) bags built from sample_data/, augmented with one CNF per sensor."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from roadview_noise.bag_export import export_bag
from roadview_noise.bag_recipe import parse_bag_recipe
from roadview_noise.bag_runner import manifest_path, replay_bag, run_bag, run_record_path
from roadview_noise.errors import InputError, RecipeError
from roadview_noise.io import ros_messages as rm
from roadview_noise.io.atomic import TMP_SUFFIX
from roadview_noise.io.pointcloud import output_columns, read_pointcloud
from roadview_noise.io.rosbag import open_bag
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from roadview_noise.sampledata.bag import RECIPE_TOPICS, write_sample_bag

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"
CHAINS = {"camera": "CNF16", "lidar": "CNF20", "radar": "CNF25"}
UNTOUCHED = ("/camera/depth", "/diagnostics")


def bag_recipe(**extra):
    return parse_bag_recipe({"seed": 11, "topics": RECIPE_TOPICS, "chains": CHAINS,
                             "params": {"wind.camera": {"wind_speed_m_per_s": 3.0}}, **extra}, base_dir=ROOT)


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def bag(request, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp(request.param)
    path = folder / ("drive.bag" if request.param == "ros1" else "drive")
    write_sample_bag(SAMPLE, path, ros2=request.param == "ros2")
    return path


@pytest.fixture(scope="module")
def augmented(bag, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("out") / ("drive-rain.bag" if bag.suffix == ".bag" else "drive-rain")
    summary = run_bag(bag_recipe(), bag, out, workers=1, progress=False)
    assert (summary.done, summary.failed) == (12, 0), summary.failures
    return out


def messages(path: Path) -> list[tuple[str, str, int, bytes]]:
    with open_bag(path) as reader:
        return [(c.topic, c.msgtype, t, raw) for c, t, raw in reader.messages()]


def decoded(path: Path, topic: str) -> list:
    with open_bag(path) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]


def test_topics_counts_stamps_and_untouched_topics(bag, augmented):
    before, after = messages(bag), messages(augmented)
    assert [(t, m, r) for t, m, r, _ in before] == [(t, m, r) for t, m, r, _ in after]   # order and record times
    with open_bag(bag) as a, open_bag(augmented) as b:
        assert sorted((c.topic, c.msgtype, c.digest) for c in a.connections) == \
            sorted((c.topic, c.msgtype, c.digest) for c in b.connections)
    for (topic, _, _, raw_in), (_, _, _, raw_out) in zip(before, after):
        assert (raw_in == raw_out) == (topic in UNTOUCHED), topic
    for topic in RECIPE_TOPICS:
        assert [(m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) for m in decoded(bag, topic)] == \
            [(m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) for m in decoded(augmented, topic)]


def test_augmented_messages_decode_and_keep_their_format(bag, augmented):
    for old, new in zip(decoded(bag, "/camera/image/compressed"), decoded(augmented, "/camera/image/compressed")):
        assert new.format == old.format == "jpeg" and bytes(new.data[:2]) == b"\xff\xd8"
        a, b = (rm.image_to_frame(m, rm.COMPRESSED_IMAGE, None, source="t").linear_rgb for m in (old, new))
        assert a.shape == b.shape and np.abs(a - b).mean() > 1e-3            # rain changed the picture
    for old, new in zip(decoded(bag, "/camera/image_raw"), decoded(augmented, "/camera/image_raw")):
        assert (new.encoding, new.height, new.width, new.step) == (old.encoding, old.height, old.width, old.step)
        assert not np.array_equal(old.data, new.data)
    for topic, grid in (("/os_cloud_node/points", bag.suffix == ".bag"), ("/radar/points", False)):
        for old, new in zip(decoded(bag, topic), decoded(augmented, topic)):
            layout = [(f.name, f.offset, f.datatype, f.count) for f in old.fields]
            assert [(f.name, f.offset, f.datatype, f.count) for f in new.fields][:len(layout)] == layout
            assert [f.name for f in new.fields][len(layout):] == ["rv_effect"]
            assert new.fields[-1].offset == old.point_step and new.point_step == old.point_step + 1
            assert (new.height > 1) == grid and new.is_dense == old.is_dense
            if grid:
                assert (new.height, new.width) == (old.height, old.width)
            effect = rm.cloud_columns(new, source="t")[-1][2]
            assert effect.max() > 0                                         # some points changed by the weather


def test_manifest_has_one_line_per_augmented_message(bag, augmented):
    entries = [json.loads(line) for line in manifest_path(augmented).read_text().splitlines()]
    assert len(entries) == 12 and {e["status"] for e in entries} == {"ok"}
    out = {(t, r): raw for t, _, r, raw in messages(augmented)}
    for e in entries:
        assert e["key"] == f"{e['topic']}@{e['stamp_ns']}"
        assert hashlib.sha256(out[(e["topic"], e["record_time_ns"])]).hexdigest() == e["output_sha256"]
        assert [s["model"] for s in e["steps"]] == e["chain"] and e["sequence"] == e["topic"].strip("/")
    lidar = [e["steps"][0] for e in entries if e["topic"] == "/os_cloud_node/points"]
    assert lidar[0]["model"] == "alignment.lidar" and lidar[0]["state"]             # per-beam offsets: drawn once
    assert all(step["state"] == lidar[0]["state"] for step in lidar[1:])           # per topic (sensor instance)
    record = json.loads(run_record_path(augmented).read_text())
    assert record["counts"] == {"augmented": 12, "failed": 0, "messages": 18}
    assert record["topics"]["/radar/points"] == {"messages": 3, "ok": 3, "failed": 0}


def test_same_pixels_and_points_as_the_files(bag, augmented, tmp_path):
    """Export the bag, augment the tree with the same chains and seed: same payload as the augmented bag."""
    recipe = bag_recipe()
    tree = tmp_path / "tree"
    summary = export_bag(bag, tree, recipe=recipe)
    assert summary["topics"] == dict.fromkeys(RECIPE_TOPICS, 3)
    assert (tree / "camera/image/compressed/1700000000100000000_depth.exr").is_file()
    globs = {"/camera/image/compressed": ("camera", "*.jpg"), "/camera/image_raw": ("raw", "*.raw"),
             "/os_cloud_node/points": ("lidar", "*.pcd"), "/radar/points": ("radar", "*.pcd")}
    for topic, (modality, glob) in globs.items():
        spec = {**recipe.topics[topic].recipe.resolved_dict(), "inputs": {modality: f"{topic.strip('/')}/{glob}"}}
        out = tmp_path / topic.strip("/").replace("/", "_")
        s = run(parse_recipe(spec), tree, out, workers=1, progress=False)
        assert (s.done, s.failed) == (3, 0), s.failures
        files = sorted(out.glob(f"{topic.strip('/')}/{glob}"))
        for path, msg in zip(files, decoded(augmented, topic), strict=True):
            assert path.stem == f"{msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec:019d}"
            assert payload(path, modality) == payload_of(msg, modality), (topic, path.name)


def payload(path: Path, modality: str) -> str:
    if modality in ("camera", "raw"):
        return hashlib.sha256(path.read_bytes()).hexdigest()
    cloud = read_pointcloud(path, sensor=modality)
    columns, _ = output_columns(cloud, cloud.layout, effect="none")
    return hashlib.sha256(b"".join(n.encode() + c.tobytes() for n, _, c in columns)).hexdigest()


def payload_of(msg, modality: str) -> str:
    if modality == "camera":
        return hashlib.sha256(bytes(msg.data)).hexdigest()
    if modality == "raw":
        return hashlib.sha256(rm.image_pixels(msg, source="t").astype("<u2").tobytes()).hexdigest()
    columns = rm.cloud_columns(msg, source="t")
    return hashlib.sha256(b"".join(n.encode() + c.tobytes() for n, _, c in columns)).hexdigest()


def test_two_workers_write_the_same_bytes(bag, augmented, tmp_path):
    out = tmp_path / augmented.name
    run_bag(bag_recipe(), bag, out, workers=2, progress=False, max_in_flight_bytes=1 << 20)
    files = sorted(p for p in [augmented, *augmented.glob("*")] if p.is_file())
    for p in files:
        twin = out / p.name if augmented.is_dir() else out
        assert hashlib.sha256(p.read_bytes()).digest() == hashlib.sha256(twin.read_bytes()).digest(), p.name
    strip = [{k: v for k, v in e.items() if k not in ("seconds", "steps")}
             for e in map(json.loads, manifest_path(augmented).read_text().splitlines())]
    assert strip == [{k: v for k, v in e.items() if k not in ("seconds", "steps")}
                     for e in map(json.loads, manifest_path(out).read_text().splitlines())]


def test_messages_travel_inline_when_nothing_can_be_spooled(bag, augmented, tmp_path, monkeypatch):
    """Messages go to the workers through spool files (io/spool.py); without a usable temporary folder they go
    through the pipes, with the same bytes. A spool folder of a process that no longer exists is removed; the run's
    own is gone when it ends."""
    import subprocess
    import tempfile

    from roadview_noise.io import spool

    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = Path(tempfile.gettempdir()) / f"{spool.PREFIX}{dead.pid}-x"
    stale.mkdir()
    (stale / "0").write_bytes(b"left by a killed run")
    put, sent = spool.Spool.put, []
    monkeypatch.setattr(spool.Spool, "put", lambda self, data: sent.append(put(self, data)) or sent[-1])
    out = tmp_path / "spooled" / augmented.name
    run_bag(bag_recipe(), bag, out, workers=2, progress=False)
    first = len(sent)                                       # 12 messages and the depth messages of the cameras
    assert first > 12 and all(isinstance(x, spool.Spooled) for x in sent)
    assert not stale.exists() and not list(Path(tempfile.gettempdir()).glob(f"{spool.PREFIX}{os.getpid()}-*"))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "missing"))
    inline = tmp_path / "inline" / augmented.name
    run_bag(bag_recipe(), bag, inline, workers=2, progress=False)
    assert len(sent) == 2 * first and all(isinstance(x, bytes) for x in sent[first:])
    for a, b in ((out, inline), (augmented, out)):
        files = sorted(p.name for p in [a, *a.glob("*")] if p.is_file())
        for name in files:
            x, y = (a / name, b / name) if a.is_dir() else (a, b)
            assert x.read_bytes() == y.read_bytes(), name


def test_replay_reproduces_one_message(augmented, tmp_path):
    entry = json.loads(manifest_path(augmented).read_text().splitlines()[4])
    r = replay_bag(manifest_path(augmented), entry["key"], out_file=tmp_path / "msg.bin")
    assert r["match"] and r["got"] == entry["output_sha256"] and not r["input_changed"]
    assert hashlib.sha256((tmp_path / "msg.bin").read_bytes()).hexdigest() == entry["output_sha256"]
    with pytest.raises(RecipeError, match="did you mean"):
        replay_bag(manifest_path(augmented), entry["key"] + "1")


def test_cli_augment_validate_replay_export(bag, tmp_path):
    recipe = tmp_path / "r.yaml"
    recipe.write_text((ROOT / "recipes/bag-rehearse.yaml").read_text())
    cli = CliRunner()
    r = cli.invoke(app, ["validate", str(recipe)])
    assert r.exit_code == 0 and "/os_cloud_node/points (lidar) chain alignment.lidar → fog.lidar" in r.output
    out = tmp_path / ("o.bag" if bag.suffix == ".bag" else "o.mcap")
    r = cli.invoke(app, ["augment", "-r", str(recipe), str(bag), str(out), "-q", "-j", "1"])
    assert r.exit_code == 0, r.output
    assert "9 messages augmented, 0 failed" in r.output and out.is_file()
    key = json.loads(manifest_path(out).read_text().splitlines()[0])["key"]
    r = cli.invoke(app, ["replay", str(manifest_path(out)), "--key", key])
    assert r.exit_code == 0 and r.output.startswith("match:")
    r = cli.invoke(app, ["augment", "-r", str(recipe), str(bag), str(out), "-q"])
    assert r.exit_code == 2 and "--overwrite" in r.output
    r = cli.invoke(app, ["augment", "-r", str(recipe), str(bag), str(out), "-q", "--resume"])
    assert r.exit_code == 2 and "not supported for bags" in r.output
    wrong = tmp_path / ("o2" if bag.suffix == ".bag" else "o2.bag")
    r = cli.invoke(app, ["augment", "-r", str(recipe), str(bag), str(wrong), "-q"])
    assert r.exit_code == 2 and "no ROS 1 ↔ ROS 2 conversion" in r.output
    r = cli.invoke(app, ["export", str(bag), str(tmp_path / "tree")])
    assert r.exit_code == 0 and "/radar/points (3)" in r.output
    assert (tmp_path / "tree/radar/points/radar.yaml").is_file()                  # sensor told by its fields
    assert not list(tmp_path.glob(f"*{TMP_SUFFIX}*"))


# --- bad bags --------------------------------------------------------------------------------------------------------


def test_truncated_bag_fails_naming_the_bag(bag, tmp_path):
    src = bag if bag.is_file() else next(bag.glob("*.mcap"))
    cut = tmp_path / f"cut{src.suffix}"
    cut.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    out = tmp_path / ("o.bag" if cut.suffix == ".bag" else "o")
    with pytest.raises(InputError, match=f"{cut}: cannot read the bag, it is truncated or damaged"):
        run_bag(bag_recipe(), cut, out, workers=1, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == [cut.name]                  # nothing written


def test_unknown_message_type_on_a_mapped_topic(bag, tmp_path):
    recipe = parse_bag_recipe({"topics": {**RECIPE_TOPICS, "/diagnostics": {"sensor": "radar"}}, "chains": CHAINS})
    out = tmp_path / ("o.bag" if bag.suffix == ".bag" else "o")
    with pytest.raises(RecipeError, match=r"topic /diagnostics carries std_msgs/msg/String, which a radar topic "
                                          r"cannot read \(expected sensor_msgs/msg/PointCloud2\)") as exc:
        run_bag(recipe, bag, out, workers=1, progress=False)
    assert str(bag) in str(exc.value)
    assert not list(tmp_path.iterdir())


def test_cloud_without_xyz_is_recorded_and_copied_unchanged(tmp_path):
    """A radar PointCloud2 whose x field is called `px`: that message fails (named by bag, topic, stamp), is copied
    unchanged and is in the manifest; every other message is augmented."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    src = tmp_path / "in.bag"
    write_sample_bag(SAMPLE, src, frames=2)
    store = get_typestore(Stores.ROS1_NOETIC)
    bad = tmp_path / "bad.bag"
    with open_bag(src) as reader:
        writer = Writer(bad)
        writer.open()
        conns = {id(c): writer.add_connection(c.topic, c.msgtype, typestore=store) for c in reader.connections}
        for c, t, raw in reader.messages():
            if c.topic == "/radar/points" and t > 1_700_000_000_050_000_000:
                msg = reader.deserialize(raw, c.msgtype)
                msg.fields[0].name = "px"
                raw = bytes(store.serialize_ros1(msg, c.msgtype))
            writer.write(conns[id(c)], t, raw)
        writer.close()
    out = tmp_path / "out.bag"
    summary = run_bag(bag_recipe(), bad, out, workers=1, progress=False)
    assert (summary.done, summary.failed) == (7, 1)
    assert summary.failures[0] == (f"{bad}: /radar/points@1700000000100000000: no scalar 'x' field "
                                   "(fields: ['px', 'y', 'z', 'velocity', 'snr', 'power', 'rcs'])")
    failed = [json.loads(x) for x in manifest_path(out).read_text().splitlines() if '"failed"' in x]
    assert failed[0]["copied_unchanged"] is True and failed[0]["key"] == "/radar/points@1700000000100000000"
    before = {(t, r): raw for t, _, r, raw in messages(bad)}
    after = {(t, r): raw for t, _, r, raw in messages(out)}
    assert before.keys() == after.keys()
    assert after[("/radar/points", 1_700_000_000_109_000_000)] == before[("/radar/points", 1_700_000_000_109_000_000)]


def test_a_read_error_mid_bag_leaves_nothing(tmp_path):
    """A mapped message too short for its header stops the run before the output exists (no half-written bag)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    bad = tmp_path / "short.bag"
    src = tmp_path / "in.bag"
    write_sample_bag(SAMPLE, src, frames=1)
    with open_bag(src) as reader:
        writer = Writer(bad)
        writer.open()
        conns = {id(c): writer.add_connection(c.topic, c.msgtype, typestore=store) for c in reader.connections}
        for c, t, raw in reader.messages():
            writer.write(conns[id(c)], t, raw[:6] if c.topic == "/radar/points" else raw)
        writer.close()
    out = tmp_path / "out" / "o.bag"
    with pytest.raises(InputError, match=r"short.bag: /radar/points at record time 1700000000009000000: the message "
                                         r"is too short for a header"):
        run_bag(bag_recipe(), bad, out, workers=1, progress=False)
    assert not list(out.parent.iterdir())


def test_ros2_single_files_sqlite_and_folders(tmp_path):
    """A single .mcap in, a single .db3 out (SQLite storage), then that .db3 into a ROS 2 bag folder."""
    src = tmp_path / "drive"
    write_sample_bag(SAMPLE, src, ros2=True, frames=1)
    mcap = next(src.glob("*.mcap"))
    db3 = tmp_path / "rain.db3"
    assert run_bag(bag_recipe(), mcap, db3, workers=1, progress=False).done == 4
    assert db3.read_bytes()[:16] == b"SQLite format 3\x00"
    folder = tmp_path / "rain-again"
    run_bag(bag_recipe(), db3, folder, workers=1, progress=False)
    assert sorted(p.name for p in folder.iterdir()) == ["metadata.yaml", "rain-again.db3"]
    a, b, c = messages(mcap), messages(db3), messages(folder)
    assert [m[:3] for m in a] == [m[:3] for m in b] == [m[:3] for m in c]
    assert [m[3] == n[3] for m, n in zip(a, b)] == [m[0] in UNTOUCHED for m in a]
    keep = tmp_path / "results"
    keep.mkdir()
    (keep / "notes.txt").write_text("mine")
    with pytest.raises(RecipeError, match="is a folder that is not a ROS 2 bag"):
        run_bag(bag_recipe(), mcap, keep, workers=1, progress=False, overwrite=True)
    assert (keep / "notes.txt").read_text() == "mine"
    run_bag(bag_recipe(), mcap, folder, workers=1, progress=False, overwrite=True)     # replaces a bag folder
    assert sorted(p.name for p in folder.iterdir()) == ["metadata.yaml", "rain-again.mcap"]
    assert not [p for p in tmp_path.iterdir() if TMP_SUFFIX in p.name]


def test_ros1_chunk_compression_is_kept(tmp_path):
    src = tmp_path / "lz4.bag"
    write_sample_bag(SAMPLE, src, frames=1, ros1_compression="lz4")
    out = tmp_path / "out.bag"
    assert run_bag(bag_recipe(), src, out, workers=1, progress=False).done == 4
    assert b"compression=lz4" in out.read_bytes()[:300_000]                        # a chunk header field
    assert out.stat().st_size < 0.9 * sum(len(m[3]) for m in messages(out))
    assert [m[:3] for m in messages(src)] == [m[:3] for m in messages(out)]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_dying_worker_costs_its_message_only(tmp_path, workers):
    """A worker killed on one message (SIGKILL, as the out-of-memory killer does), as in a file run: that message is
    tried once more on a fresh worker, then recorded as failed ("worker died") and copied unchanged; every other
    message is augmented and written in order, the bag is complete, the exit status is 1. The test model is adopted
    by the workers (registry.plugin_models), as in file runs."""
    import injected_models
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from roadview_noise.registry import MODELS, register

    store = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "cam.bag"
    writer = Writer(bag)
    writer.open()
    cam, copy = (writer.add_connection(t, rm.IMAGE, typestore=store) for t in ("/cam", "/cam_unmapped"))
    for k in range(4):
        pixels = ((np.arange(48 * 64 * 3) * 7 + k) % 200).astype(np.uint8).reshape(48, 64, 3)
        pixels[0, 0] = 255 if k == 1 else 90                                          # the poison frame
        header = store.types["std_msgs/msg/Header"](seq=k, stamp=store.types["builtin_interfaces/msg/Time"](
            sec=k, nanosec=0), frame_id="cam")
        msg = store.types["sensor_msgs/msg/Image"](header=header, height=48, width=64, encoding="rgb8",
                                                   is_bigendian=0, step=192, data=pixels.ravel())
        raw = bytes(store.serialize_ros1(msg, rm.IMAGE))
        writer.write(cam, 10**9 * k + 1, raw)
        writer.write(copy, 10**9 * k + 2, raw)
    writer.close()
    trace = tmp_path / "trace.txt"
    recipe = tmp_path / "r.yaml"
    recipe.write_text(json.dumps({"topics": {"/cam": "camera"}, "chains": {"camera": [
        {"model": "test_crash.camera", "params": {"trace_path": str(trace)}}]}}))
    out = tmp_path / "out" / "o.bag"
    register(injected_models.CrashCamera)
    try:
        r = CliRunner().invoke(app, ["augment", "-r", str(recipe), str(bag), str(out), "-q", "-j", str(workers)])
    finally:
        MODELS.pop(injected_models.CrashCamera.id, None)
    assert r.exit_code == 1, r.output
    assert "Traceback" not in r.output and "3 messages augmented, 1 failed" in r.output, r.output
    assert trace.read_text().split().count("poison") == 2                     # tried twice, never a third time
    entries = [json.loads(x) for x in manifest_path(out).read_text().splitlines()]
    assert [(e["key"], e["status"]) for e in entries] == [
        (f"/cam@{k * 10**9}", "failed" if k == 1 else "ok") for k in range(4)]
    bad = entries[1]
    assert bad["error"].startswith(f"{bag}: /cam@1000000000: worker died: signal 9")
    assert bad["worker_deaths"] == 2 and bad["copied_unchanged"] is True
    before, after = messages(bag), messages(out)
    assert [m[:3] for m in before] == [m[:3] for m in after]                   # complete, in record order
    assert after[2] == before[2] and [m[3] for m in after[1::2]] == [m[3] for m in before[1::2]]   # copied
    assert [e.get("output_sha256") for e in entries] == [
        None if k == 1 else hashlib.sha256(after[2 * k][3]).hexdigest() for k in range(4)]
    assert json.loads(run_record_path(out).read_text())["counts"] == {"augmented": 3, "failed": 1, "messages": 8}
    assert not list(out.parent.glob(f"*{TMP_SUFFIX}*"))


def test_a_bad_profile_stops_the_run_before_anything_is_written(bag, tmp_path):
    topics = {**RECIPE_TOPICS, "/os_cloud_node/points": {"sensor": "lidar", "lidar_profile": "os1-12"}}
    recipe = parse_bag_recipe({"topics": topics, "chains": CHAINS}, source="r.yaml")
    with pytest.raises(RecipeError, match=r"^r.yaml: topics./os_cloud_node/points.lidar_profile: invalid lidar "
                                          r"profile: .*no LiDAR profile 'os1-12'"):
        run_bag(recipe, bag, tmp_path / ("o.bag" if bag.suffix == ".bag" else "o"), workers=1, progress=False)
    assert not list(tmp_path.iterdir())


def test_writeback_starts_every_so_many_bytes(tmp_path, monkeypatch):
    """The output bag's pages are handed to the kernel for writing as the run goes (io/writeback.py), so the fsync
    before the rename waits for little; without a file or the call it does nothing."""
    from roadview_noise.io import writeback

    calls = []
    monkeypatch.setattr(writeback, "_sync_file_range", lambda: lambda *a: calls.append(a))
    f = tmp_path / "bag"
    f.write_bytes(b"x" * 100)
    wb = writeback.Writeback(f, every_bytes=40)
    for _ in range(5):
        wb.wrote(20)
    assert [a[1:] for a in calls] == [(0, 0, writeback.SYNC_FILE_RANGE_WRITE)] * 2
    wb.close()
    assert wb.fd is None
    none = writeback.Writeback(None)
    none.wrote(1 << 30)
    assert none.fd is None and len(calls) == 2


def test_export_without_recipe_leaves_depth_topics_out_and_says_which(tmp_path):
    """A RealSense-style bag: its 16UC1 depth topic (REP 118's depth encoding, as realsense2_camera, Azure Kinect and
    OAK drivers publish it) was exported as a 16-bit grey picture, so augmenting the tree put fog on depth maps; a
    usb_cam ``yuv422`` topic was left out without a word. Both are now left out and named; mono16 stays a picture."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "rs.bag"
    topics = {"/camera/color/image_raw": ("rgb8", np.uint8, 3), "/camera/depth/image_rect_raw": ("16UC1", np.uint16, 1),
              "/ir/image_raw": ("mono16", np.uint16, 1), "/usb_cam/image_raw": ("yuv422", np.uint8, 2)}
    with Writer(bag) as writer:
        for topic, (encoding, dtype, channels) in topics.items():
            conn = writer.add_connection(topic, rm.IMAGE, typestore=store)
            pixels = np.full((8, 12, channels), 100, dtype)
            header = store.types["std_msgs/msg/Header"](seq=0, stamp=store.types["builtin_interfaces/msg/Time"](
                sec=1, nanosec=0), frame_id="cam")
            msg = store.types["sensor_msgs/msg/Image"](header=header, height=8, width=12, encoding=encoding,
                                                       is_bigendian=0, step=pixels.strides[0],
                                                       data=pixels.view(np.uint8).ravel())
            writer.write(conn, 10**9 + 1, store.serialize_ros1(msg, rm.IMAGE))
    summary = export_bag(bag, tmp_path / "tree")
    assert set(summary["topics"]) == {"/camera/color/image_raw", "/ir/image_raw"}
    assert not (tmp_path / "tree" / "camera" / "depth").exists()
    assert any(w.startswith("not exported: /camera/depth/image_rect_raw (16UC1: a depth image") and "depth_topic" in w
               for w in summary["warnings"])
    assert any(w.startswith("not exported: /usb_cam/image_raw (Image encoding 'yuv422'") for w in summary["warnings"])
