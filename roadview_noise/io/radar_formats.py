"""Radar dataset layouts the readers meet, and what their sensors write into the status fields of a detection.

nuScenes ``RADAR_*`` PCDs (Continental ARS 408-21 cluster list; nuScenes devkit
``RadarPointCloud.from_file``): binary PCD, FIELDS x y z dyn_prop id rcs vx vy vx_comp vy_comp is_quality_valid
ambig_state x_rms y_rms invalid_state pdh0 vx_rms vy_rms, SIZE 4 4 4 1 2 4 4 4 4 4 1 1 1 1 1 1 1 1, TYPE F F F I I
F F F F F I I I I I I I I; z = 0 (2-D radar), ``rcs`` in dBsm, velocities Cartesian (physics/radar_frame.py). The
devkit drops, by default, every point whose ``invalid_state`` is not 0 (valid), whose ``dyn_prop`` is 7 (stopped)
or whose ``ambig_state`` is not 3 (unambiguous). A detection the models add (precipitation clutter) is therefore
written as one the sensor declared valid and unambiguous, so that a user's default loader keeps it:
``invalid_state`` 0, ``ambig_state`` 3, ``is_quality_valid`` 1, ``dyn_prop`` 4 (unknown: the sensor's
moving/stationary classification of a clutter cluster is not modelled), ``id`` continuing the frame's cluster ids,
and the frame's most frequent ``pdh0``, ``x_rms``, ``y_rms``, ``vx_rms``, ``vy_rms`` (the sensor's typical quality
codes). Without these, added points would have ``ambig_state`` 0 (invalid) and vanish on loading.

Astyx HiRes2019 ``radar_6455/*.txt`` (Astyx 6455 HiRes, 3-D: elevation measured): a blank line, the header
``X Y Z V_r Mag``, one detection per line printed with ``%.18g`` (io/text_table.py; checked on frames of the public
copy github.com/under-the-radar/radar_dataset_astyx). X, Y, Z in metres (sensor frame, x forward). The dataset paper
(Meyer & Kuschk, EuRAD 2019) does not define the columns further; what the files show:

- ``V_r`` is the radial velocity in 0.0812 m/s steps within ±5.1968 m/s (64 steps: it aliases; unambiguous
  interval 10.39 m/s) with the sign **positive approaching** — the opposite of rvnoise's range rate (models.md
  §0.4): on 7 frames recorded while driving, a stationary world fits ``V_r = +v_ego cos(angle)`` (wrapped) for
  47–76 % of the detections within 0.15 m/s and ``−v_ego cos`` for 7–25 % (two slow frames fit both alike). It
  is read negated into ``v_r_m_per_s`` and negated back on writing (exact).
- ``Mag`` is a received level in dB of unknown reference (relative power): 0.5 dB steps, 45 … 87.5, and the same
  floor 45.0 at every range in every frame checked — a fixed detection threshold on the level itself, not on an
  RCS (whose threshold would rise as 40 log10 r). It maps to ``power_db`` (``power_unit: relative``), whose
  per-frame threshold estimate, the frame's weakest detection (models/radar/detection.py), is then that 45.
  There is no RCS, so the weather models add no clutter (``clutter_skipped`` in the manifest).

The file is read as this layout only when its header is exactly ``X Y Z V_r Mag``; a recipe's ``field_map`` wins
over these names (mapping ``V_r`` elsewhere also drops the negation). Effect codes go to the ``.rv_effect``
sidecar (an extra column would break loaders that read five columns).

RadarScenes (``sequence_N/radar_data.h5``; radar-scenes.com, devkit github.com/oleschum/radar_scenes) is **not
read**: one file holds a whole sequence — the table ``radar_data`` with every scan of the 4 sensors (fields
timestamp, sensor_id, range_sc, azimuth_sc, rcs, vr, vr_compensated, x_cc, y_cc, x_seq, y_seq, uuid, track_id,
label_id), the table ``odometry``, and ``scenes.json`` indexing each scan's rows (``radar_indices``). Augmenting it
in place needs a many-frames-per-file task (as ROS bags have), rewritten ``radar_indices``, and car and world
coordinates (x_cc … y_seq) and uuids for added detections; rvnoise's tasks are one frame per file. Instead,
:func:`radarscenes_scan` turns one scan's rows into a 2-D radar cloud in its sensor's frame to write as a PCD
(README, "Radar inputs").

The devkit reads exactly these 18 fields (``RadarPointCloud.nbr_dims() == 18``, asserted) and finds
``invalid_state`` as the 4th row from the end, so an extra ``rv_effect`` field would make it fail; such a file gets
its effect codes in the ``.rv_effect`` sidecar instead, as a fixed-layout ``.bin`` does (:func:`fixed_field_layout`).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..errors import InputError
from ..types import CloudLayout, PointCloud

NUSCENES_RADAR_FILE_FIELDS = tuple(("x y z dyn_prop id rcs vx vy vx_comp vy_comp is_quality_valid ambig_state x_rms "
                                    "y_rms invalid_state pdh0 vx_rms vy_rms").split())
NUSCENES_RADAR_FIELDS = ("dyn_prop", "id", "rcs_dbsm", "vx", "vy", "vx_comp", "vy_comp", "is_quality_valid",
                         "ambig_state", "x_rms", "y_rms", "invalid_state", "pdh0", "vx_rms", "vy_rms")
NUSCENES_ADDED_STATES = {"invalid_state": 0, "ambig_state": 3, "is_quality_valid": 1, "dyn_prop": 4}
NUSCENES_TYPICAL = ("pdh0", "x_rms", "y_rms", "vx_rms", "vy_rms")
ASTYX_COLUMNS = ("X", "Y", "Z", "V_r", "Mag")
ASTYX_FIELD_MAP = {"X": "x", "Y": "y", "Z": "z", "V_r": "v_r_m_per_s", "Mag": "power_db"}
ASTYX_NEGATED = {"V_r": "v_r_m_per_s"}       # stored positive approaching (module docstring)
RADARSCENES_FIELDS = ("timestamp", "sensor_id", "range_sc", "azimuth_sc", "rcs", "vr", "vr_compensated", "x_cc",
                      "y_cc", "x_seq", "y_seq", "uuid", "track_id", "label_id")


class RadarProfileWarning(UserWarning):
    """A radar file in a known dataset's layout read with the default profile (printed once; in the manifest)."""


def dataset_profile(cloud: PointCloud) -> tuple[str, str] | None:
    """(dataset, built-in profile) whose file layout ``cloud`` was read in — a View-of-Delft ``.bin``: vod, a
    nuScenes ``RADAR_*`` PCD: ars408, an Astyx ``X Y Z V_r Mag`` table: astyx-6455 — or None."""
    layout = cloud.layout
    names = tuple(name for _, name, _ in layout.fields) if layout is not None else ()
    if layout is not None and layout.fmt == "vod_bin":
        return "View-of-Delft", "vod"
    if is_nuscenes_radar(cloud):
        return "nuScenes (Continental ARS 408-21)", "ars408"
    if layout is not None and layout.fmt == "txt" and names == ASTYX_COLUMNS:
        return "Astyx HiRes2019", "astyx-6455"
    return None


def is_nuscenes_radar(cloud: PointCloud) -> bool:
    """The cloud has every field of a nuScenes radar PCD (canonical names: ``rcs`` → ``rcs_dbsm``)."""
    return all(f in cloud.fields for f in NUSCENES_RADAR_FIELDS)


def added_detection_fields(cloud: PointCloud, n: int) -> dict[str, np.ndarray]:
    """Status fields for ``n`` detections added to ``cloud`` (module docstring); {} for other layouts."""
    if not is_nuscenes_radar(cloud) or not len(cloud):
        return {}
    out = {k: np.full(n, v) for k, v in NUSCENES_ADDED_STATES.items()}
    for name in NUSCENES_TYPICAL:
        values, counts = np.unique(cloud.fields[name], return_counts=True)
        out[name] = np.full(n, values[np.argmax(counts)])
    ids = cloud.fields["id"]
    out["id"] = np.minimum(int(ids.max()) + 1 + np.arange(n), np.iinfo(ids.dtype).max)
    return {k: v.astype(cloud.fields[k].dtype) for k, v in out.items()}


def fixed_field_layout(layout: CloudLayout) -> bool:
    """A file whose readers expect exactly its fields (nuScenes radar PCD, text tables such as Astyx's): effect
    codes go to a sidecar."""
    if layout.fmt == "txt":
        return True
    return layout.fmt == "pcd" and tuple(name for _, name, _ in layout.fields) == NUSCENES_RADAR_FILE_FIELDS


def text_table_fields(names: tuple[str, ...], field_map: Mapping[str, str] | None
                      ) -> tuple[dict[str, str] | None, tuple[str, ...]]:
    """The field map of a text table's columns ``names`` (the recipe's, completed with Astyx's for an Astyx
    header) and the columns stored with the opposite sign of their field."""
    if names != ASTYX_COLUMNS:
        return field_map, ()
    given = dict(field_map or {})
    taken = set(given.values())
    merged = {**{f: c for f, c in ASTYX_FIELD_MAP.items() if f not in given and c not in taken}, **given}
    return merged, tuple(f for f, c in ASTYX_NEGATED.items() if merged.get(f) == c)


def radarscenes_scan(rows: np.ndarray, first_row: int = 0) -> PointCloud:
    """One RadarScenes scan — the ``radar_data`` rows ``first_row …`` of one ``scenes.json`` entry — as a 2-D radar
    cloud in its sensor's frame: ``x, y = range_sc (cos, sin) azimuth_sc``, z = 0; ``rcs`` → ``rcs_dbsm`` (dBsm),
    ``vr`` → ``v_r_m_per_s``, ``vr_compensated`` → ``v_r_comp_m_per_s`` (as stored); ``label_id``, ``sensor_id``,
    ``timestamp`` (µs) kept in their dtypes, and ``row``, the detection's row in ``radar_data``, to join uuid,
    track_id and the car/world coordinates back (an added detection has 0 there and rv_effect ADDED)."""
    missing = [f for f in RADARSCENES_FIELDS if f not in (rows.dtype.names or ())]
    if missing:
        raise InputError(f"not RadarScenes radar_data rows: no fields {missing}", file="radar_data")
    if len(rows) and (np.any(rows["timestamp"] != rows["timestamp"][0]) or
                      np.any(rows["sensor_id"] != rows["sensor_id"][0])):
        raise InputError("the rows hold more than one scan (timestamps or sensor ids differ): give one "
                         "scenes.json entry's radar_indices", file="radar_data")
    r, az = rows["range_sc"].astype(np.float64), rows["azimuth_sc"].astype(np.float64)
    positions = np.stack([r * np.cos(az), r * np.sin(az), np.zeros_like(r)], axis=1)
    fields = {"rcs_dbsm": rows["rcs"], "v_r_m_per_s": rows["vr"], "v_r_comp_m_per_s": rows["vr_compensated"],
              "label_id": rows["label_id"], "sensor_id": rows["sensor_id"], "timestamp": rows["timestamp"],
              "row": first_row + np.arange(len(rows), dtype=np.int64)}
    return PointCloud(positions, {k: np.ascontiguousarray(v) for k, v in fields.items()}, "radar")
