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

TJ4DRadSet (``training/velodyne/*.bin``, Oculii Eagle 4D radar; github.com/TJRadarLab/TJ4DRadSet) stores each frame
as N×8 float32 ``x y z V_r Range Power Alpha Beta`` — the same ``.bin`` suffix and folder as View-of-Delft's N×7,
and N×8×4 bytes is also a whole number of VoD points when N is a multiple of 7 (6 of the 41 sample frames), so the
layout is told from the data (:func:`radar_bin_format`): the dataset's README names the columns, and its 41 sample
frames (108 222 detections) show ``Range`` = ``|p|`` (within 3.1e-5 m), ``Alpha`` = ``−atan2(y, x)`` and ``Beta``
= ``−atan2(z, x)`` in degrees (within 1.4e-5°): columns that restate the position, recomputed on writing where a
point no longer matches them (added, moved or turned: :func:`tj4d_derived`). ``V_r`` is the raw range rate,
positive receding (the README's "relative radial velocity"; a stationary world, car at about 17 m/s, gives
−17 m/s ahead and −9 m/s at 57°), read as ``v_r_m_per_s``; ``Power`` is "in dB scale and represents the signal to
noise ratio of the detection" (README), read as ``snr_db``. No RCS: the weather models add no clutter
(``clutter_skipped``).

A ``.bin`` read as View-of-Delft's must also behave as one (:func:`check_vod_columns`). A radar ``.bin`` in neither
layout (Dual-Radar's Arbe Phoenix and ARS548 RDI clouds are N×5 float32, named ``x y z
intensity dopple`` in its devkit's dataset configs, units not documented) is read with the recipe's
``inputs.radar_bin_fields`` (format ``radar_bin``); without it, a size that fits neither layout is refused naming
both.

ars548_ros (github.com/robotics-upo/ars548_ros, the open ROS driver of the Continental ARS 548 RDI) publishes its
detections as ``PointCloudDetection`` with the fields ``x y z v r RCS azimuth elevation`` (float32, RCS int8;
src/ars548_driver.cpp, detection_list.h): ``v`` the sensor's f_RangeRate ("Detection Radial Velocity", m/s; a
rate of range, so positive receding — by its name, not checked on recordings), ``r`` its f_Range (m), ``RCS``
s_RCS (int8; dBsm, Continental's unit, not stated by the driver), azimuth and elevation in radians, x y z computed
from them. In this layout ``v`` is read as ``v_r_m_per_s`` and ``r`` restates the position
(:data:`RESTATING`: an added clutter point gets its own |p|, not 0); azimuth and elevation follow
io/derived_fields.py.

Oculii Eagle clouds recorded in ROS (NTU4DRadLM, as read by github.com/zhuge2333/4DRadarSLAM's ``EaglePointXYZIVRAB``:
float32 ``x y z snr_db doppler range alpha beta``) are pointed to ``oculii-eagle`` when no profile is stated;
``doppler`` and ``snr_db`` are read by their names, ``range`` follows io/derived_fields.py; the sign of ``doppler``
and the convention of ``alpha``/``beta`` were not checked on recordings (none at hand).

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
TJ4D_COLUMNS = ("x", "y", "z", "V_r", "Range", "Power", "Alpha", "Beta")
TJ4D_FIELD_MAP = {"V_r": "v_r_m_per_s", "Power": "snr_db"}
ARS548_ROS_FIELDS = ("x", "y", "z", "v", "r", "RCS", "azimuth", "elevation")      # ars548_ros PointCloudDetection
ARS548_ROS_FIELD_MAP = {"v": "v_r_m_per_s"}
EAGLE_ROS_FIELDS = ("x", "y", "z", "snr_db", "doppler", "range", "alpha", "beta")   # Oculii Eagle PointCloud2
RADARSCENES_FIELDS = ("timestamp", "sensor_id", "range_sc", "azimuth_sc", "rcs", "vr", "vr_compensated", "x_cc",
                      "y_cc", "x_seq", "y_seq", "uuid", "track_id", "label_id")


class RadarProfileWarning(UserWarning):
    """A radar file in a known dataset's layout read with the default profile (printed once; in the manifest)."""


def dataset_profile(cloud: PointCloud) -> tuple[str, str] | None:
    """(dataset, built-in profile) whose file layout ``cloud`` was read in — a View-of-Delft ``.bin``: vod, a
    nuScenes ``RADAR_*`` PCD: ars408, an Astyx ``X Y Z V_r Mag`` table: astyx-6455, a TJ4DRadSet ``.bin``:
    oculii-eagle, an ars548_ros detection cloud: ars548, an Oculii Eagle PointCloud2: oculii-eagle — or None."""
    layout = cloud.layout
    names = tuple(name for _, name, _ in layout.fields) if layout is not None else ()
    if layout is not None and layout.fmt == "vod_bin":
        return "View-of-Delft", "vod"
    if is_nuscenes_radar(cloud):
        return "nuScenes (Continental ARS 408-21)", "ars408"
    if layout is not None and layout.fmt == "txt" and names == ASTYX_COLUMNS:
        return "Astyx HiRes2019", "astyx-6455"
    if layout is not None and layout.fmt == "tj4d_bin":
        return "TJ4DRadSet (Oculii Eagle)", "oculii-eagle"
    if names == ARS548_ROS_FIELDS:
        return "ars548_ros (Continental ARS 548 RDI)", "ars548"
    if names == EAGLE_ROS_FIELDS:
        return "Oculii Eagle PointCloud2", "oculii-eagle"
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
    merged = _completed(field_map, ASTYX_FIELD_MAP)
    return merged, tuple(f for f, c in ASTYX_NEGATED.items() if merged.get(f) == c)


def layout_field_map(names: tuple[str, ...], field_map: Mapping[str, str] | None) -> Mapping[str, str] | None:
    """The field map of a radar cloud stored with the fields ``names``: the recipe's, completed with the dataset's
    or driver's own for a layout it names (TJ4DRadSet's ``.bin``, ars548_ros' PointCloudDetection)."""
    own = {TJ4D_COLUMNS: TJ4D_FIELD_MAP, ARS548_ROS_FIELDS: ARS548_ROS_FIELD_MAP}.get(tuple(names))
    return field_map if own is None else _completed(field_map, own)


def _completed(field_map: Mapping[str, str] | None, dataset: Mapping[str, str]) -> dict[str, str]:
    """The recipe's ``field_map`` with a dataset's own names for the fields and targets it leaves free."""
    given = dict(field_map or {})
    taken = set(given.values())
    return {**{f: c for f, c in dataset.items() if f not in given and c not in taken}, **given}


def radar_bin_format(data: bytes, columns: tuple[str, ...] | None, path) -> str:
    """The layout of a radar ``.bin`` (module docstring): ``radar_bin`` when the recipe names its ``columns``, else
    ``tj4d_bin`` when its size fits 8 float32 columns and every point's Range and Alpha restate its position,
    ``vod_bin`` when it fits 7; :class:`InputError` otherwise."""
    if columns is not None:
        return "radar_bin"
    if is_tj4d_bin(data):
        return "tj4d_bin"
    if len(data) % 28 == 0:
        return "vod_bin"
    raise InputError(f"size {len(data)} bytes fits neither View-of-Delft's radar .bin (7 float32 columns: x y z RCS "
                     "v_r v_r_compensated time) nor TJ4DRadSet's (8: x y z V_r Range Power Alpha Beta, Range = |p|); "
                     "name its float32 columns in the recipe, inputs.radar_bin_fields (x, y, z first; Dual-Radar's "
                     "are 5: README, Radar inputs)", file=str(path))


def is_tj4d_bin(data: bytes | memoryview) -> bool:
    """The bytes hold TJ4DRadSet's N×8 float32 layout: every point's Range and Alpha restate its position (the first
    64 points first: a LiDAR ``.bin`` is told apart without a pass over the file)."""
    n = len(data) // 32
    if not n or len(data) % 32:
        return False
    table = np.frombuffer(data, "<f4", count=8 * n).reshape(n, 8)
    rules = RESTATING[TJ4D_COLUMNS]
    return all(np.all(_restated(rows[:, i], rules[name], rows[:, :3]))
               for rows in (table[:64], table) for i, name in ((4, "Range"), (6, "Alpha")))


def check_vod_columns(cloud: PointCloud, path) -> None:
    """Refuse a ``.bin`` read as View-of-Delft's whose ``v_r_compensated − v_r`` follows no sensor velocity (RMS
    above physics/radar_frame.EGO_FIT_MAX_RMS_M_PER_S): the columns are another layout's — a Dual-Radar N×5 frame of
    7k points fits the 28-byte VoD point too. View-of-Delft's 3 example frames fit within 0.01 m/s; a Dual-Radar-like
    frame read so, 24 m/s."""
    from ..physics.radar_frame import EGO_FIT_MAX_RMS_M_PER_S, ego_velocity_from_data

    _, rms = ego_velocity_from_data(cloud, planar=False)
    if rms > EGO_FIT_MAX_RMS_M_PER_S:
        raise InputError(f"read as View-of-Delft's radar .bin (x y z RCS v_r v_r_compensated time) its columns do not "
                         f"behave as VoD's: v_r_compensated − v_r fits no sensor velocity (RMS {rms:.3g} m/s, above "
                         f"{EGO_FIT_MAX_RMS_M_PER_S}); if it holds another layout (Dual-Radar's 5 columns), name its "
                         "float32 columns in inputs.radar_bin_fields", file=str(path))


def _range_m(p: np.ndarray) -> np.ndarray:
    return np.linalg.norm(p, axis=1)


def _minus_deg(axis: int):
    """−atan2(p_axis, x) in degrees: TJ4DRadSet's Alpha (axis 1) and Beta (axis 2)."""
    return lambda p: -np.degrees(np.arctan2(p[:, axis], p[:, 0]))


# columns of a layout (its file field names) that restate a point's position: (value of positions, tolerance in the
# column's unit — TJ4DRadSet's 16–70× the largest difference on its 41 sample frames; ars548_ros' r: float32 ranges)
RESTATING = {TJ4D_COLUMNS: {"Range": (_range_m, 5e-4), "Alpha": (_minus_deg(1), 1e-3),
                            "Beta": (_minus_deg(2), 1e-3)},
             ARS548_ROS_FIELDS: {"r": (_range_m, 1e-3)}}


def _restated(values: np.ndarray, rule, positions: np.ndarray) -> np.ndarray:
    """Which stored ``values`` restate their point's position under ``rule`` (an entry of :data:`RESTATING`)."""
    value, tolerance = rule
    return np.abs(values - value(np.asarray(positions, dtype=np.float64))) <= tolerance


def restated_column(values: np.ndarray, file_name: str, cloud: PointCloud) -> np.ndarray | None:
    """A column of ``cloud``'s layout that restates the position (:data:`RESTATING`: TJ4DRadSet's Range, Alpha,
    Beta; ars548_ros' r), recomputed for the points whose stored value no longer does (added, moved or turned by the
    chain), every other value as read; None for any other column."""
    names = tuple(name for _, name, _ in cloud.layout.fields) if cloud.layout is not None else ()
    rule = RESTATING.get(names, {}).get(file_name)
    if rule is None:
        return None
    stale = ~_restated(np.asarray(values, dtype=np.float64), rule, cloud.positions_m)
    if not stale.any():
        return values
    out = np.array(values, dtype=np.float64)
    out[stale] = rule[0](np.asarray(cloud.positions_m[stale], dtype=np.float64))
    return out


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
