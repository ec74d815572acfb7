"""Camera intrinsics from a bag's sensor_msgs/CameraInfo topic (README "ROS bags", roadview_noise/bag_camera_info.py).

Bags are built in tmp_path with rosbags' writers: an ``rgb8`` Image topic ``/cam/image_raw`` (or a JPEG
CompressedImage ``/cam/image_raw/compressed``) and its ``/cam/camera_info``. The chain is the windscreen
distortion in normalised units, whose output depends on fx, fy, cx, cy and on nothing else of the camera, so an
equal output means the same K reached the model.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from roadview_noise.bag_camera_info import CameraInfoIndex
from roadview_noise.bag_recipe import parse_bag_recipe
from roadview_noise.bag_runner import manifest_path, replay_bag, run_bag
from roadview_noise.errors import RecipeError
from roadview_noise.io import ros_messages as rm
from roadview_noise.io.camera_info import (camera_info_intrinsics, camera_info_topic, default_matrix,
                                           distortion_shift_px)
from roadview_noise.io.rosbag import open_bag

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
W, H = 64, 48
K1 = (60.0, 58.0, 30.5, 22.0)                 # fx fy cx cy
K2 = (90.0, 90.0, 33.0, 25.0)
WINDSCREEN = [{"model": "windscreen.camera", "params": {"k1": 0.3, "coefficient_units": "normalised"}}]


def store(ros2: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)


def header(types, ros2: bool, stamp: int):
    time = types.types["builtin_interfaces/msg/Time"](sec=stamp // 10 ** 9, nanosec=stamp % 10 ** 9)
    return types.types["std_msgs/msg/Header"](stamp=time, frame_id="cam_optical", **({} if ros2 else {"seq": 1}))


def camera_info(types, ros2: bool, stamp: int, k=K1, size=(W, H), *, d=(0.0,) * 5, model="plumb_bob", p=None,
                binning=(0, 0), roi=(0, 0, 0, 0)):
    fx, fy, cx, cy = k
    kk = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], float)
    pp = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], float) if p is None else np.asarray(p, float)
    mats = {"D": np.asarray(d, float), "K": kk, "R": np.eye(3).ravel(), "P": pp}
    return types.types[rm.CAMERA_INFO](
        header=header(types, ros2, stamp), height=size[1], width=size[0], distortion_model=model,
        **{(n.lower() if ros2 else n): v for n, v in mats.items()}, binning_x=binning[0], binning_y=binning[1],
        roi=types.types["sensor_msgs/msg/RegionOfInterest"](x_offset=roi[0], y_offset=roi[1], width=roi[2],
                                                             height=roi[3], do_rectify=False))


def pixels(seed: int = 0, size=(W, H)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)


def image(types, ros2: bool, stamp: int, size=(W, H)):
    data = pixels(stamp % 97, size)
    return types.types[rm.IMAGE](header=header(types, ros2, stamp), height=size[1], width=size[0], encoding="rgb8",
                                 is_bigendian=False, step=size[0] * 3, data=data.ravel())


def compressed(types, ros2: bool, stamp: int):
    import cv2

    ok, jpg = cv2.imencode(".jpg", pixels(stamp % 97)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
    return types.types[rm.COMPRESSED_IMAGE](header=header(types, ros2, stamp), format="jpeg", data=jpg.ravel())


def write_bag(path: Path, ros2: bool, messages: list[tuple[str, str, object, int]]) -> Path:
    """Messages (topic, type, message, record time) in the order given."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    types = store(ros2)
    writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) if ros2 else Writer1(path)
    writer.open()
    conns = {}
    for topic, msgtype, msg, t in messages:
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=types)
        raw = types.serialize_cdr(msg, msgtype) if ros2 else types.serialize_ros1(msg, msgtype)
        writer.write(conns[topic], t, raw)
    writer.close()
    return path


def bag_path(tmp_path: Path, name: str, ros2: bool) -> Path:
    return tmp_path / (name if ros2 else f"{name}.bag")


def augment(tmp_path: Path, bag: Path, topics: dict, name: str = "out", chain=WINDSCREEN):
    recipe = parse_bag_recipe({"seed": 3, "topics": topics, "chains": {"camera": chain}}, base_dir=ROOT)
    out = tmp_path / (name if bag.suffix != ".bag" else f"{name}.bag")
    lines: list[str] = []
    summary = run_bag(recipe, bag, out, workers=1, progress=False, echo=lines.append)
    entries = [json.loads(line) for line in manifest_path(out).read_text().splitlines()]
    return summary, entries, out


def payloads(bag: Path, topic: str) -> list[bytes]:
    with open_bag(bag) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [bytes(reader.deserialize(raw, c.msgtype).data) for c, _, raw in reader.messages(connections=conns)]


def raw_messages(bag: Path) -> list[tuple[str, int, bytes]]:
    with open_bag(bag) as reader:
        return [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]


def profile_of(k, size=(W, H)) -> dict:
    fx, fy, cx, cy = k
    return {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "width_px": size[0], "height_px": size[1]}


# --- conventions and intrinsics --------------------------------------------------------------------------------------


def test_camera_info_topic_by_ros_convention():
    assert camera_info_topic("/cam/image_raw") == "/cam/camera_info"
    assert camera_info_topic("/cam/image_raw/compressed") == "/cam/camera_info"
    assert camera_info_topic("/cam/image_rect_color/compressed") == "/cam/camera_info"
    assert camera_info_topic("/front/image") == "/front/camera_info"
    assert camera_info_topic("/image_raw") == "/camera_info"
    assert default_matrix("/cam/image_rect_color/compressed") == "P"
    assert default_matrix("/cam/image_rect") == "P"
    assert default_matrix("/cam/image_raw/compressed") == "K"


@pytest.mark.parametrize("ros2", [False, True])
def test_binning_and_roi_map_pixel_centres(ros2):
    """A 3-D point projected with the full-resolution K, then cut to the ROI and binned (pixel centres at integer
    coordinates: a binned pixel covers b full pixels), lands where the CameraInfo's intrinsics project it."""
    types = store(ros2)
    k = (1000.0, 980.0, 959.5, 601.25)
    msg = camera_info(types, ros2, T0, k, (1920, 1200), binning=(2, 4), roi=(100, 48, 1600, 1000))
    got = camera_info_intrinsics(msg, source="t")
    assert (got.width_px, got.height_px) == (800, 250) and got.roi == (100, 48, 1600, 1000) and got.binning == (2, 4)
    rng = np.random.default_rng(1)
    xyz = rng.uniform([-2, -1, 4], [2, 1, 30], (50, 3))
    u_full = k[0] * xyz[:, 0] / xyz[:, 2] + k[2]
    v_full = k[1] * xyz[:, 1] / xyz[:, 2] + k[3]
    u_bin = (u_full - 100 - 0.5) / 2                  # ROI pixels 2i, 2i+1 → binned pixel i, centre at 2i + 0.5
    v_bin = (v_full - 48 - 1.5) / 4                   # ROI pixels 4i … 4i+3 → binned pixel i, centre at 4i + 1.5
    np.testing.assert_allclose(got.fx_px * xyz[:, 0] / xyz[:, 2] + got.cx_px, u_bin, atol=1e-9)
    np.testing.assert_allclose(got.fy_px * xyz[:, 1] / xyz[:, 2] + got.cy_px, v_bin, atol=1e-9)
    assert camera_info_intrinsics(camera_info(types, ros2, T0, (0.0, 0.0, 0.0, 0.0)), source="t") is None


def test_rectified_topics_take_p_and_refuse_a_roi():
    from roadview_noise.errors import InputError

    types = store(False)
    p = [500.0, 0, 320.0, 0, 0, 505.0, 240.0, 0, 0, 0, 1, 0]
    msg = camera_info(types, False, T0, (520.0, 520.0, 318.0, 242.0), (640, 480), p=p)
    assert camera_info_intrinsics(msg, matrix="P", source="t").intrinsics == (500.0, 505.0, 320.0, 240.0)
    assert camera_info_intrinsics(msg, matrix="K", source="t").intrinsics == (520.0, 520.0, 318.0, 242.0)
    with pytest.raises(InputError, match="rectified image with a roi"):
        camera_info_intrinsics(camera_info(types, False, T0, K1, (640, 480), p=p, roi=(8, 8, 320, 240)), matrix="P",
                               source="t")


def test_distortion_shift_against_the_radial_closed_form():
    """plumb_bob with k1 only: a border pixel at distorted normalised radius r_d comes from the ray at r with
    r (1 + k1 r²) = r_d; the shift is f·(r_d − r) at the farthest corner."""
    types = store(False)
    k1, f = -0.2, 50.0
    msg = camera_info(types, False, T0, (f, f, (W - 1) / 2, (H - 1) / 2), d=(k1, 0, 0, 0, 0))
    info = camera_info_intrinsics(msg, source="t")
    r_d = np.hypot((W - 1) / 2, (H - 1) / 2) / f
    roots = np.roots([k1, 0, 1, -r_d])
    r = min(x.real for x in roots if abs(x.imag) < 1e-12 and x.real > 0)
    assert distortion_shift_px(info) == pytest.approx(f * abs(r - r_d), rel=1e-3)
    assert distortion_shift_px(camera_info_intrinsics(camera_info(types, False, T0, K1, d=()), source="t")) is None


# --- through a bag run -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ros2", [False, True])
def test_k_from_camera_info_reaches_the_model(tmp_path, ros2):
    """The bag's CameraInfo K gives the output the same K stated as a profile gives; another K another output; the
    manifest says where the intrinsics came from; every other message (the CameraInfo) is copied byte for byte."""
    types = store(ros2)
    stamps = [T0, T0 + 100 * MS]
    messages = []
    for s in stamps:
        messages += [("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, ros2, s), s + 2 * MS),
                     ("/cam/image_raw", rm.IMAGE, image(types, ros2, s), s + 3 * MS)]
    bag = write_bag(bag_path(tmp_path, "in", ros2), ros2, messages)
    summary, entries, out = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera"}})
    assert (summary.done, summary.failed) == (2, 0), summary.failures
    assert not [w for w in summary.warnings if "FOV" in w or "assumed" in w]
    camera = entries[0]["inputs"]["camera"]
    assert camera["from"] == f"CameraInfo /cam/camera_info@{T0} (K)" and camera["profile"] == "camera_info"
    assert (camera["fx_px"], camera["fy_px"], camera["cx_px"], camera["cy_px"]) == K1
    assert camera["camera_info"]["topic"] == "/cam/camera_info" and camera["camera_info"]["stamp_ns"] == T0
    replayed = replay_bag(manifest_path(out), f"/cam/image_raw@{stamps[1]}")
    assert replayed["match"], replayed                         # replay pairs the same CameraInfo
    stated = {"/cam/image_raw": {"sensor": "camera", "camera_profile": profile_of(K1)}}
    _, stated_entries, stated_out = augment(tmp_path, bag, stated, "stated")
    assert stated_entries[0]["inputs"]["camera"]["from"].startswith("recipe topics./cam/image_raw.camera_profile")
    assert payloads(out, "/cam/image_raw") == payloads(stated_out, "/cam/image_raw")
    other = {"/cam/image_raw": {"sensor": "camera", "camera_profile": profile_of(K2)}}
    _, _, other_out = augment(tmp_path, bag, other, "other")
    assert payloads(out, "/cam/image_raw")[0] != payloads(other_out, "/cam/image_raw")[0]
    before, after = raw_messages(bag), raw_messages(out)
    assert [(t, r) for t, r, _ in before] == [(t, r) for t, r, _ in after]
    assert [raw for topic, _, raw in before if topic == "/cam/camera_info"] == \
        [raw for topic, _, raw in after if topic == "/cam/camera_info"]


@pytest.mark.parametrize("ros2", [False, True])
def test_latest_camera_info_at_or_before_the_header_stamp(tmp_path, ros2):
    """Re-calibration mid-bag: each image takes the latest CameraInfo stamped at or before it, by header stamp —
    the new calibration is recorded (received) before an older image and still not used for it; an image older than
    every CameraInfo takes the earliest, noted and warned."""
    types = store(ros2)
    s = [T0 + k * 100 * MS for k in range(5)]
    messages = [("/cam/image_raw", rm.IMAGE, image(types, ros2, s[0]), s[0] + 1 * MS),       # before any info
                ("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, ros2, s[1], K1), s[1]),
                ("/cam/image_raw", rm.IMAGE, image(types, ros2, s[1]), s[1] + 1 * MS),
                ("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, ros2, s[3], K2), s[2]),  # received early
                ("/cam/image_raw", rm.IMAGE, image(types, ros2, s[2]), s[2] + 5 * MS),
                ("/cam/image_raw", rm.IMAGE, image(types, ros2, s[3]), s[3] + 1 * MS),
                ("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, ros2, s[4], K2), s[4]),
                ("/cam/image_raw", rm.IMAGE, image(types, ros2, s[4]), s[4] + 1 * MS)]
    bag = write_bag(bag_path(tmp_path, "in", ros2), ros2, messages)
    summary, entries, _ = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera"}})
    assert (summary.done, summary.failed) == (5, 0), summary.failures
    used = [(e["stamp_ns"], e["inputs"]["camera"]["camera_info"]["stamp_ns"], e["inputs"]["camera"]["fx_px"])
            for e in entries]
    assert used == [(s[0], s[1], K1[0]), (s[1], s[1], K1[0]), (s[2], s[1], K1[0]), (s[3], s[3], K2[0]),
                    (s[4], s[4], K2[0])]
    assert entries[0]["inputs"]["camera"]["camera_info"]["after_image"] is True
    assert "after_image" not in entries[1]["inputs"]["camera"]["camera_info"]
    assert any("older than every CameraInfo" in w and "/cam/image_raw" in w for w in summary.warnings)
    with open_bag(bag) as reader:
        index = CameraInfoIndex.read(reader, {"/cam/image_raw": "/cam/camera_info"}, ros2, bag)
    assert index.stamps["/cam/camera_info"] == [s[1], s[3], s[4]] and len(index.payloads) == 2   # K2 kept once


@pytest.mark.parametrize("ros2", [False, True])
def test_binned_roi_camera_info_of_a_compressed_topic(tmp_path, ros2):
    """``/cam/image_raw/compressed`` pairs with ``/cam/camera_info``; a 4×-binned ROI of a 320×240 calibration
    describes the 64×48 JPEG, and its scaled K gives the output the same K stated as a profile gives."""
    types = store(ros2)
    k_full = (240.0, 236.0, 161.0, 118.5)
    info = camera_info(types, ros2, T0, k_full, (320, 240), binning=(4, 4), roi=(32, 24, 256, 192))
    bag = write_bag(bag_path(tmp_path, "in", ros2), ros2,
                    [("/cam/camera_info", rm.CAMERA_INFO, info, T0),
                     ("/cam/image_raw/compressed", rm.COMPRESSED_IMAGE, compressed(types, ros2, T0), T0 + MS)])
    summary, entries, out = augment(tmp_path, bag, {"/cam/image_raw/compressed": {"sensor": "camera"}})
    assert (summary.done, summary.failed) == (1, 0), summary.failures
    expected = (k_full[0] / 4, k_full[1] / 4, (k_full[2] - 32 + 0.5) / 4 - 0.5, (k_full[3] - 24 + 0.5) / 4 - 0.5)
    camera = entries[0]["inputs"]["camera"]
    assert (camera["fx_px"], camera["fy_px"], camera["cx_px"], camera["cy_px"]) == pytest.approx(expected)
    assert camera["camera_info"]["binning"] == [4, 4] and camera["camera_info"]["roi"] == [32, 24, 256, 192]
    stated = {"/cam/image_raw/compressed": {"sensor": "camera", "camera_profile": profile_of(expected)}}
    _, _, stated_out = augment(tmp_path, bag, stated, "stated")
    assert payloads(out, "/cam/image_raw/compressed") == payloads(stated_out, "/cam/image_raw/compressed")


@pytest.mark.parametrize("ros2", [False, True])
def test_camera_info_of_another_size_is_refused(tmp_path, ros2):
    """A CameraInfo for 640×480 next to a 64×48 image: the message fails naming both sizes and is copied
    unchanged; the run goes on."""
    types = store(ros2)
    bag = write_bag(bag_path(tmp_path, "in", ros2), ros2,
                    [("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, ros2, T0, K1, (640, 480)), T0),
                     ("/cam/image_raw", rm.IMAGE, image(types, ros2, T0), T0 + MS)])
    summary, entries, out = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera"}})
    assert (summary.done, summary.failed) == (0, 1)
    (entry,) = entries
    assert entry["copied_unchanged"] is True
    assert f"/cam/image_raw@{T0}: /cam/camera_info@{T0}: describes a 640×480 image (calibrated 640×480) but the " \
           "image is 64×48" in entry["error"] and "camera_info_topic" in entry["error"]
    assert raw_messages(out) == raw_messages(bag)


def test_explicit_profile_and_fov_win_and_are_not_combined_with_a_camera_info_topic(tmp_path):
    types = store(False)
    bag = write_bag(tmp_path / "in.bag", False,
                    [("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, False, T0, K1), T0),
                     ("/cam/image_raw", rm.IMAGE, image(types, False, T0), T0 + MS)])
    _, entries, _ = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera",
                                                               "camera_profile": profile_of(K2)}})
    camera = entries[0]["inputs"]["camera"]
    assert camera["fx_px"] == K2[0] and "camera_info" not in camera
    summary, entries, _ = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera", "camera_fov_h_deg": 70}},
                                  "fov")
    assert entries[0]["inputs"]["camera"]["from"].startswith("image size and horizontal FOV 70°")
    for key in ("camera_profile", "camera_fov_h_deg"):
        with pytest.raises(RecipeError, match=f"topics./cam/image_raw.{key}: give {key} or the intrinsics"):
            parse_bag_recipe({"topics": {"/cam/image_raw": {"sensor": "camera", key: profile_of(K1) if key ==
                                                            "camera_profile" else 70,
                                                            "camera_info_topic": "/cam/camera_info"}},
                              "chains": {"camera": WINDSCREEN}})


def test_camera_info_topic_key_and_checks(tmp_path):
    """``camera_info_topic`` pairs a CameraInfo outside the namespace; a stated one missing from the bag, or of
    another type, is refused before anything is written; a CameraInfo the image did not pair is named in the
    warning on assumed intrinsics."""
    types = store(False)
    bag = write_bag(tmp_path / "in.bag", False,
                    [("/calib/left", rm.CAMERA_INFO, camera_info(types, False, T0, K2), T0),
                     ("/cam/image_raw", rm.IMAGE, image(types, False, T0), T0 + MS)])
    summary, entries, _ = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera"}})
    assert entries[0]["inputs"]["camera"]["profile"].startswith("assumed_fov")
    (line,) = [w for w in summary.warnings if "CameraInfo" in w]
    assert "/calib/left were not paired with /cam/image_raw" in line and "camera_info_topic" in line
    summary, entries, _ = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera",
                                                                     "camera_info_topic": "/calib/left"}}, "keyed")
    assert entries[0]["inputs"]["camera"]["fx_px"] == K2[0] and not [w for w in summary.warnings if "CameraInfo" in w]
    for wrong, why in (("/calib/right", "is not in"), ("/cam/image_raw", f"carries {rm.IMAGE} in")):
        with pytest.raises(RecipeError, match=f"topics./cam/image_raw.camera_info_topic: camera_info_topic "
                                              f"'{wrong}' {why}"):
            augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera", "camera_info_topic": wrong}}, "bad")
    assert not (tmp_path / "bad.bag").exists()


def test_uncalibrated_and_distorted_camera_info_are_warned(tmp_path):
    """K all zero (an uncalibrated driver): intrinsics assumed, and the warning says why; a distorted image
    (plumb_bob D ≠ 0) is taken with its pinhole K, the manifest and the warning give the border shift."""
    types = store(False)
    zero = camera_info(types, False, T0, (0.0, 0.0, 0.0, 0.0))
    bag = write_bag(tmp_path / "in.bag", False,
                    [("/cam/camera_info", rm.CAMERA_INFO, zero, T0),
                     ("/cam/image_raw", rm.IMAGE, image(types, False, T0), T0 + MS)])
    summary, entries, _ = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera"}})
    assert entries[0]["inputs"]["camera"]["camera_info"]["uncalibrated"] is True
    assert any("uncalibrated (K[0] = 0)" in w for w in summary.warnings)
    distorted = camera_info(types, False, T0, K1, d=(-0.3, 0.1, 0.001, 0.0, 0.0))
    bag = write_bag(tmp_path / "distorted.bag", False,
                    [("/cam/camera_info", rm.CAMERA_INFO, distorted, T0),
                     ("/cam/image_raw", rm.IMAGE, image(types, False, T0), T0 + MS)])
    summary, entries, _ = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera"}}, "d")
    info = entries[0]["inputs"]["camera"]["camera_info"]
    assert info["distortion_model"] == "plumb_bob" and info["distortion"][:3] == [-0.3, 0.1, 0.001]
    assert info["distortion_shift_px"] > 0.5
    (line,) = [w for w in summary.warnings if "treated as pinhole" in w]
    assert f"/cam/image_raw {info['distortion_shift_px']:.1f} px" in line


def test_no_camera_info_is_read_when_the_chain_needs_no_geometry(tmp_path):
    """A chain without camera geometry or depth pairs nothing: a CameraInfo of another size does not fail it."""
    types = store(False)
    bag = write_bag(tmp_path / "in.bag", False,
                    [("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, False, T0, K1, (640, 480)), T0),
                     ("/cam/image_raw", rm.IMAGE, image(types, False, T0), T0 + MS)])
    summary, entries, _ = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera"}},
                                  chain=[{"model": "compression.camera", "params": {"quality": 30}}])
    assert (summary.done, summary.failed) == (1, 0) and "camera" not in entries[0].get("inputs", {})


def test_export_writes_the_camera_info_profile_and_warns_when_it_changes(tmp_path):
    """``rvnoise export`` writes camera.yaml from the CameraInfo (no recipe needed); augmenting the tree gives the
    bag's pixels; a re-calibration later in the bag is warned (camera.yaml holds the first message's)."""
    import yaml

    from roadview_noise.bag_export import export_bag
    from roadview_noise.recipe import parse_recipe
    from roadview_noise.runner import run

    types = store(False)
    s = [T0, T0 + 100 * MS]
    bag = write_bag(tmp_path / "in.bag", False,
                    [("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, False, s[0], K1), s[0]),
                     ("/cam/image_raw", rm.IMAGE, image(types, False, s[0]), s[0] + MS)])
    tree = tmp_path / "tree"
    summary = export_bag(bag, tree)
    assert summary["warnings"] == []
    sidecar = yaml.safe_load((tree / "cam/image_raw/camera.yaml").read_text())
    assert (sidecar["fx_px"], sidecar["fy_px"], sidecar["cx_px"], sidecar["cy_px"]) == K1
    _, _, out = augment(tmp_path, bag, {"/cam/image_raw": {"sensor": "camera"}})
    recipe = parse_recipe({"seed": 3, "chain": WINDSCREEN, "inputs": {"camera": "cam/image_raw/*.png"}})
    files = tmp_path / "files"
    done = run(recipe, tree, files, workers=1, progress=False)
    assert (done.done, done.failed) == (1, 0), done.failures
    from roadview_noise.io.image import decode_codes

    path = files / f"cam/image_raw/{s[0]:019d}.png"
    codes = decode_codes(path.read_bytes(), "png", source=path)
    assert codes.tobytes() == payloads(out, "/cam/image_raw")[0]
    bag2 = write_bag(tmp_path / "in2.bag", False,
                     [("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, False, s[0], K1), s[0]),
                      ("/cam/image_raw", rm.IMAGE, image(types, False, s[0]), s[0] + MS),
                      ("/cam/camera_info", rm.CAMERA_INFO, camera_info(types, False, s[1], K2), s[1]),
                      ("/cam/image_raw", rm.IMAGE, image(types, False, s[1]), s[1] + MS)])
    summary = export_bag(bag2, tmp_path / "tree2")
    (line,) = summary["warnings"]
    assert line.startswith("1 message(s) of /cam/image_raw have other intrinsics")
