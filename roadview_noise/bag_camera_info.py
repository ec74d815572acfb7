"""A bag's ``sensor_msgs/CameraInfo`` topics as the camera profile of its camera topics (README "ROS bags").

Pairing: a camera topic without ``camera_profile`` or ``camera_fov_h_deg`` takes the CameraInfo of its
``camera_info_topic`` (recipe) or, by ROS convention, of ``<namespace>/camera_info``
(:func:`io.camera_info.camera_info_topic`); a stated profile wins. Pairs are made only where a step of the chain
uses camera geometry or the chain needs depth (``rvnoise export``: always, for the ``camera.yaml`` it writes).

Sync by header stamp: every CameraInfo message of the paired topics is read once before the run
(:class:`CameraInfoIndex`: their stamps, and each distinct content once — a driver republishes the same
calibration with every frame), and an image takes the latest CameraInfo whose stamp is at or before its own
(drivers stamp both alike), or the earliest one when the bag has none that early (the recording began between an
image and its CameraInfo; noted and warned). Its width × height, binned and cut to its ROI, must be the image's:
else the message fails, copied unchanged, naming both sizes.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InputError, RecipeError
from .io.camera_info import CAMERA_INFO, camera_info_intrinsics, camera_info_topic, default_matrix
from .io.rosbag import header_stamp_ns


def paired_topics(recipe: Any, by_topic: dict[str, list], bag: Path, *, every_camera: bool = False
                  ) -> dict[str, str]:
    """Camera topic → its CameraInfo topic (module docstring); RecipeError when a stated ``camera_info_topic`` is
    not in the bag or carries another type."""
    from .camera_inputs import needs_camera_geometry

    pairs = {}
    for name, topic in recipe.topics.items():
        spec = topic.spec
        if topic.sensor != "camera" or spec.camera_profile is not None or spec.camera_fov_h_deg is not None:
            continue
        if not (every_camera or needs_camera_geometry(topic.recipe) or topic.recipe.needs_depth()):
            continue
        info = spec.camera_info_topic or camera_info_topic(name)
        conns = by_topic.get(info, [])
        types = {c.msgtype for c in conns}
        if spec.camera_info_topic is not None and types != {CAMERA_INFO}:
            why = "is not in" if not conns else f"carries {', '.join(sorted(types - {CAMERA_INFO}))} in"
            raise RecipeError(f"camera_info_topic {info!r} {why} {str(bag)!r} (expected {CAMERA_INFO})",
                              file=recipe.source, key=f"topics.{name}.camera_info_topic")
        if types == {CAMERA_INFO}:
            pairs[name] = info
    return pairs


@dataclass
class CameraInfoIndex:
    """The CameraInfo messages of the paired topics by header stamp (module docstring)."""

    topic_of: dict[str, str]                                   # camera topic → CameraInfo topic
    stamps: dict[str, list[int]] = field(default_factory=dict)      # CameraInfo topic → sorted stamps
    content: dict[str, list[int]] = field(default_factory=dict)     # … → index in ``payloads`` per stamp
    payloads: list[bytes] = field(default_factory=list)

    @classmethod
    def read(cls, reader: Any, topic_of: dict[str, str], is2: bool, bag: Path) -> "CameraInfoIndex":
        """Read every message of the paired CameraInfo topics (a message repeated with another stamp is kept once;
        of two with one stamp, the later recorded)."""
        index = cls(topic_of)
        conns = [c for c in reader.connections if c.topic in set(topic_of.values())]
        if not conns:
            return index
        known: dict[bytes, int] = {}
        by_stamp: dict[str, dict[int, int]] = {}
        messages = reader.messages(connections=conns)
        while True:
            try:
                item = next(messages, None)
            except Exception as e:  # rosbags raises several types for a damaged chunk or page
                raise InputError(f"cannot read the bag's {CAMERA_INFO} messages ({type(e).__name__}: {e})",
                                 file=str(bag)) from None
            if item is None:
                break
            conn, _, raw = item
            try:
                stamp = header_stamp_ns(raw, is2)
            except Exception:
                raise InputError(f"{conn.topic}: a CameraInfo message too short for a header", file=str(bag)) from None
            key = raw[:4] + raw[12:] if is2 else raw[12:]          # without the stamp (and ROS 1's seq)
            if key not in known:
                known[key] = len(index.payloads)
                index.payloads.append(raw)
            by_stamp.setdefault(conn.topic, {})[stamp] = known[key]
        for topic, versions in by_stamp.items():
            index.stamps[topic] = sorted(versions)
            index.content[topic] = [versions[s] for s in index.stamps[topic]]
        return index

    def at(self, camera_topic: str, stamp_ns: int) -> tuple[str, int, bytes, bool] | None:
        """``(CameraInfo topic, its stamp, raw message, stamp after the image's)`` for an image of ``camera_topic``
        stamped ``stamp_ns``; None when the topic is not paired or its CameraInfo topic has no message."""
        topic = self.topic_of.get(camera_topic)
        stamps = self.stamps.get(topic) if topic else None
        if not stamps:
            return None
        i = bisect.bisect_right(stamps, stamp_ns) - 1
        after = i < 0
        i = max(i, 0)
        return topic, stamps[i], self.payloads[self.content[topic][i]], after


@dataclass(frozen=True)
class StatedIntrinsics:
    """What an image's CameraInfo states (``intrinsics`` None: an uncalibrated camera) and the manifest's notes."""

    intrinsics: tuple[float, float, float, float] | None
    name: str
    source: str
    notes: dict[str, Any]
    warnings: list[str]


def stated_intrinsics(msg: Any, info: tuple[str, int, bytes, bool], camera_topic: str, matrix: str | None,
                      width_px: int, height_px: int, *, source: str) -> StatedIntrinsics:
    """The intrinsics a deserialised CameraInfo ``msg`` (``info`` as :meth:`CameraInfoIndex.at` gave it) states for
    an image of ``width_px`` × ``height_px``; InputError when it describes an image of another size."""
    topic, stamp, _, after = info
    matrix = matrix or default_matrix(camera_topic)
    note: dict[str, Any] = {"topic": topic, "stamp_ns": stamp}
    if after:
        note["after_image"] = True
    got = camera_info_intrinsics(msg, matrix=matrix, source=source)
    if got is None:
        return StatedIntrinsics(None, "", "", {"camera_info": {**note, "uncalibrated": True}}, [])
    if (got.width_px, got.height_px) != (width_px, height_px):
        how = f"calibrated {got.calibrated_size[0]}×{got.calibrated_size[1]}"
        how += f", binning {got.binning[0]}×{got.binning[1]}" if got.binning != (1, 1) else ""
        how += f", roi {got.roi[2]}×{got.roi[3]} at ({got.roi[0]}, {got.roi[1]})" if got.roi else ""
        raise InputError(f"describes a {got.width_px}×{got.height_px} image ({how}) but the image is "
                         f"{width_px}×{height_px}: not this stream's calibration; name the right one with "
                         "camera_info_topic or state a camera_profile", file=source)
    note.update(got.notes())
    warnings = ["camera_info_after_image"] if after else []
    if (note.get("distortion_shift_px") or 0) >= 0.5:
        warnings.append("camera_info_distorted")
    return StatedIntrinsics(got.intrinsics, "camera_info", f"CameraInfo {topic}@{stamp} ({matrix})",
                            {"camera_info": note}, warnings)


class CameraInfoWarnings:
    """One run-level line per kind of CameraInfo warning over the manifest entries (folded one at a time)."""

    def __init__(self, unpaired: list[str]):
        self.unpaired = unpaired                       # CameraInfo topics of the bag no camera topic took
        self.assumed: set[str] = set()
        self.after: set[str] = set()
        self.uncalibrated: set[str] = set()
        self.distorted: dict[str, float] = {}

    def add(self, entry: dict) -> None:
        inputs = entry.get("inputs") or {}
        kinds = inputs.get("warnings", ())
        info = (inputs.get("camera") or {}).get("camera_info") or {}
        topic = entry["topic"]
        if "intrinsics_from_fov" in kinds:
            (self.uncalibrated if info.get("uncalibrated") else self.assumed).add(topic)
        if "camera_info_after_image" in kinds:
            self.after.add(topic)
        if "camera_info_distorted" in kinds:
            self.distorted[topic] = max(self.distorted.get(topic, 0.0), info["distortion_shift_px"])

    def lines(self) -> list[str]:
        out = []
        if self.assumed and self.unpaired:
            out.append(f"the bag's {CAMERA_INFO} topic(s) {', '.join(self.unpaired)} were not paired with "
                       f"{', '.join(sorted(self.assumed))}, whose intrinsics were assumed: a camera topic takes "
                       "<its namespace>/camera_info; name another with the topic's camera_info_topic")
        if self.uncalibrated:
            out.append(f"the CameraInfo of {', '.join(sorted(self.uncalibrated))} is uncalibrated (K[0] = 0): "
                       "intrinsics assumed from a FOV; state a camera_profile")
        if self.after:
            out.append(f"images of {', '.join(sorted(self.after))} are older than every CameraInfo of their topic: "
                       "they took the earliest one (the manifest's inputs.camera.camera_info.after_image)")
        if self.distorted:
            worst = ", ".join(f"{t} {px:.1f} px" for t, px in sorted(self.distorted.items()))
            out.append(f"distorted images (CameraInfo D) treated as pinhole K, off at the image border by up to "
                       f"{worst}: the camera models have no lens distortion; a rectified topic (image_rect, its "
                       "CameraInfo's P) is exact")
        return out
