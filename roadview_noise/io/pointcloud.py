"""LiDAR and 4D-radar point-cloud readers/writers.

Formats (by suffix, or ``fmt``):
- ``pcd``: PCD v0.7 ``ascii`` | ``binary`` | ``binary_compressed``, any fields (COUNT > 1 kept as (N, COUNT) arrays).
  Parsed here (vectorised header → NumPy structured dtype) rather than with open3d's tensor reader, which keeps
  dtypes but not the field order (it stores attributes in a hash map) and renames x/y/z, normals and colours.
  ``binary_compressed`` uses the LZF codec below. An organised cloud (HEIGHT > 1) sets ``grid_shape``.
- ``ply``: CARLA LiDAR PLY (x, y, z, I) or any PLY whose only non-empty element is ``vertex`` with scalar
  properties; ``ascii`` | ``binary_little_endian`` | ``binary_big_endian``, kept in ``layout.pcd_data``.
- ``kitti_bin`` (``.bin``): N×4 float32 x, y, z, intensity.
- ``nuscenes_bin`` (``.pcd.bin``): N×5 float32 x, y, z, intensity, ring.
- ``vod_bin`` (``.bin`` with ``sensor="radar"``): View-of-Delft N×7 float32 x, y, z, RCS, v_r, v_r_compensated, time;
  ``tj4d_bin``: TJ4DRadSet N×8 float32 x, y, z, V_r, Range, Power, Alpha, Beta (told apart by the data:
  io/radar_formats.radar_bin_format); ``radar_bin``: the float32 columns a recipe names (``radar_bin_fields``).
- ``txt`` (``.txt`` with ``sensor="radar"``): a text table, a header line naming the columns and one point per line
  (Astyx HiRes2019 radar, io/radar_formats.py), float64; written back row for row (io/text_table.py).
- ``feather`` (``.feather``): an Arrow table, a row per point (Argoverse 2's LiDAR sweeps, io/feather.py); positions
  about the profile's ``sensor_origin_m`` (Argoverse 2 stores the vehicle frame), put back when written; each
  sensor's pose from the log's calibration when it is beside the sweep (:func:`with_sensor_poses`).

File fields get canonical names (types.CloudLayout) through :data:`ALIASES` (first alias present wins; a recipe's
``field_map`` {file name: canonical} overrides); every other field (a user's ``label`` too) keeps its file name and
is carried through. The chain's effect code is written as its own field ``rv_effect`` (:func:`write_pointcloud`).
Radar radial velocity is passed through as stored, without a sign change; rvnoise reads it as range rate, positive
when the target recedes (models.md §0.4), so a dataset with the opposite sign needs its field negated beforehand.
Writers put every field back in file order and dtype; integer fields are rounded and clipped there, once.
Not kept: PCD VIEWPOINT/VERSION (written as identity / 0.7) and PLY comments.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..errors import EmptyCloudError, InputError
from ..physics.compiled import jit
from ..types import CloudLayout, LidarProfile, PointCloud, RadarProfile
from .atomic import write_bytes_atomic
from .derived_fields import with_derived
from .feather import CALIBRATION, calibration_path, feather_bytes, read_feather, read_sensor_poses
from . import text_table
from .radar_formats import TJ4D_COLUMNS, check_vod_columns, fixed_field_layout, is_tj4d_bin, layout_field_map, \
    radar_bin_format, text_table_fields

FORMATS = ("pcd", "ply", "kitti_bin", "nuscenes_bin", "vod_bin", "tj4d_bin", "radar_bin", "txt", "feather")

# canonical name ← file names in priority order (the first one present in the file wins)
ALIASES: dict[str, tuple[str, ...]] = {
    "x": ("x",), "y": ("y",), "z": ("z",),
    "intensity": ("intensity", "signal", "i", "I", "reflectivity"),
    "ring": ("ring", "channel", "laser_id", "laser_number"),
    "time_s": ("time_s", "time"),          # seconds (Velodyne ROS convention); Ouster `t` (ns) keeps its name
    "rcs_dbsm": ("rcs_dbsm", "rcs", "RCS"),
    "v_r_m_per_s": ("v_r_m_per_s", "v_r", "vr", "velocity", "doppler"),
    "v_r_comp_m_per_s": ("v_r_comp_m_per_s", "v_r_compensated", "vr_compensated"),   # vr…: RadarScenes' names
    "snr_db": ("snr_db", "snr"),
    "power_db": ("power_db", "power"),
}

BIN_FIELDS = {
    "kitti_bin": ("x", "y", "z", "intensity"),
    "nuscenes_bin": ("x", "y", "z", "intensity", "ring"),
    "vod_bin": ("x", "y", "z", "RCS", "v_r", "v_r_compensated", "time"),
    "tj4d_bin": TJ4D_COLUMNS,
}
EFFECT_FIELD = "rv_effect"              # the weather-effect code (provenance.Effect), uint8
EFFECT_DTYPE = "|u1"

_PCD_TYPE = {"F": "f", "U": "u", "I": "i"}
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_NAME = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint", "f4": "float",
             "f8": "double"}
_PLY_ENDIAN = {"ascii": "<", "binary_little_endian": "<", "binary_big_endian": ">"}

Column = tuple[str, str, np.ndarray]          # (file name, file dtype string, values (N,) or (N, COUNT))


# --- public API ---------------------------------------------------------------------------------------------------


def cloud_format(path: str | os.PathLike, sensor: str = "lidar") -> str:
    """Format id from the file name: ``.pcd``, ``.ply``, ``.pcd.bin`` (nuScenes), ``.bin`` (KITTI, or View-of-Delft
    for radar), ``.txt`` (radar: a text table such as Astyx's)."""
    name = os.path.basename(os.fspath(path).rstrip("/" + os.sep)).lower()   # Path(path).name, without pathlib's
    if name.endswith(".pcd.bin"):                                             # parse (≈ 3 µs; 3 calls per file)
        return "nuscenes_bin"
    if name.endswith(".bin"):
        return "vod_bin" if sensor == "radar" else "kitti_bin"
    if name.endswith(".pcd"):
        return "pcd"
    if name.endswith(".ply"):
        return "ply"
    if name.endswith(".txt") and sensor == "radar":
        return "txt"
    if name.endswith(".feather") and sensor == "lidar":
        return "feather"
    if name.endswith((".h5", ".hdf5")):
        raise InputError("HDF5 is not read: a RadarScenes radar_data.h5 holds a whole sequence (every scan of its 4 "
                         "sensors, indexed by scenes.json), and rvnoise augments one frame per file; write each "
                         "scan as a PCD with roadview_noise.io.radar_formats.radarscenes_scan (README: Radar inputs)",
                         file=str(path))
    why = next((w for ends, w in NOT_READ.items() if name.endswith(ends)), "")
    raise InputError(f"unknown point-cloud suffix {Path(path).suffix!r}; expected .pcd, .ply, .bin, .pcd.bin or "
                     ".feather (LiDAR)"
                     + (" (.txt: radar only)" if name.endswith(".txt") else "") + (f"; {why}" if why else ""),
                     file=str(path))


NOT_READ = {      # point-cloud containers users bring that are not read, and the way to what is (the refusal says it)
    (".pcap", ".pcapng"): "a packet capture holds a sensor's raw UDP packets, many scans each: decode it into one "
                          "PCD per scan with the sensor's SDK (ouster-sdk, velodyne_decoder, the Hesai SDK), or give "
                          "rvnoise the bag its ROS driver recorded (README: ROS bags)",
    (".osf",): "an Ouster OSF file holds a whole recording: save its scans as PCD files with ouster-sdk, or give "
               "rvnoise the bag ouster-ros recorded (README: ROS bags)",
    (".bag", ".mcap", ".db3"): "a ROS bag is augmented as a whole: rvnoise augment --recipe R.yaml drive.bag "
                               "out/drive.bag (README: ROS bags)",
    (".las", ".laz", ".e57"): "a survey/mapping format (often an accumulated map, no firing grid): convert it to PCD "
                              "or PLY (PDAL, CloudCompare) and give the weather models empty_rays: ignore",
    (".npy", ".npz"): "NumPy arrays (A2D2's .npz: points, reflectance, … per key) are not read: write the scan as a "
                      "float32 .bin (x y z first) and name its columns in the recipe, inputs.bin_fields (README: "
                      "LiDAR inputs)",
    (".parquet", ".csv"): "a table is not read: convert it to PCD, its columns the PCD's fields (or to Feather, "
                          "read for LiDAR)",
    (".pkl", ".pkl.gz", ".pickle"): "a pickle is not read (loading one runs code the file names): PandaSet's "
                                    "lidar/NN.pkl.gz is a pandas DataFrame x y z i t d of both its sensors in world "
                                    "coordinates; move one sensor's points (d) into its frame with lidar/poses.json "
                                    "and write them as a PCD or Feather table",
    (".tfrecord",): "a Waymo Open Dataset TFRecord holds a whole segment as range images: export its frames with "
                    "the dataset's tools (mmdetection3d's KITTI-format .bin: 6 float32 columns, read with "
                    "inputs.bin_fields, README: LiDAR inputs)"}


def read_pointcloud(path: str | os.PathLike, *, sensor: str = "lidar",
                    profile: LidarProfile | RadarProfile | None = None, field_map: Mapping[str, str] | None = None,
                    fmt: str | None = None, bin_fields: Sequence[str] | None = None,
                    data: bytes | None = None) -> PointCloud:
    """Read a cloud: float64 positions, fields under canonical names in their file dtype, and the layout to write
    it back with (see module docstring). ``bin_fields``: the float32 columns of a LiDAR ``.bin``/``.pcd.bin`` that
    is not in its fixed layout (Waymo's KITTI-format export: x y z intensity elongation timestamp); x, y, z first.
    For a radar ``.bin``, ``bin_fields`` names its columns when it is neither View-of-Delft's nor TJ4DRadSet's
    (io/radar_formats.py). ``data``: the file's bytes when the caller has read them (the runner, for their sha256),
    else read here.
    """
    if sensor not in ("lidar", "radar"):
        raise ValueError(f"sensor must be 'lidar' or 'radar', got {sensor!r}")
    path = Path(path)
    fmt = fmt or cloud_format(path, sensor)
    if fmt not in FORMATS:
        raise ValueError(f"unknown point-cloud format {fmt!r}; expected one of {FORMATS}")
    try:
        data = path.read_bytes() if data is None else data
    except OSError as exc:
        raise InputError(f"cannot read point cloud: {exc.strerror or exc}", file=str(path)) from exc
    if not data:                       # no header either: a failed copy, not a frame without points
        raise InputError("the file is empty (0 bytes)", file=str(path))
    grid_shape, table, lasers, schema = None, None, None, None
    if fmt == "feather":
        columns, schema = read_feather(data, path)
        mode = "lz4"
    elif fmt == "pcd":
        columns, mode, grid_shape = _read_pcd(data, path)
        columns, grid_shape, lasers = _as_beam_rows(columns, grid_shape, field_map, path)
    elif fmt == "ply":
        columns, mode = _read_ply(data, path)
    elif fmt == "txt":
        columns, mode, table, field_map = _read_txt(data, field_map, path)
    else:
        if fmt == "vod_bin":
            fmt = radar_bin_format(data, None if bin_fields is None else tuple(bin_fields), path)
        elif fmt == "kitti_bin" and bin_fields is None and is_tj4d_bin(data):
            raise InputError("a TJ4DRadSet 4D-radar .bin (8 float32 columns x y z V_r Range Power Alpha Beta, Range = "
                             "|p|) read as a LiDAR scan: read it as radar (the recipe's inputs.radar glob, e.g. "
                             "'training/velodyne/*.bin'; rvnoise preview --sensor radar)", file=str(path))
        columns, mode = _read_bin(data, _bin_names(fmt, bin_fields, path), path, fmt), "binary"
    cloud = cloud_from_columns(columns, fmt=fmt, mode=mode, grid_shape=grid_shape, sensor=sensor, profile=profile,
                               field_map=field_map, source=path, text=table, lasers_by_ring=lasers)
    if fmt == "vod_bin":
        check_vod_columns(cloud, path)
    return cloud if schema is None else about_sensor(cloud, schema, profile, path)


def firing_row_columns(ring: np.ndarray) -> tuple[int, ...] | None:
    """For an organised cloud's (height, width) ``ring`` field: the stored column of each beam, lowest ring first,
    when the cloud stores a row per firing and a column per laser (Velodyne's organised clouds, rslidar_sdk's unless
    ``send_by_rows``: a ring constant down each column, not along each row); else None (rows are beams)."""
    h, w = ring.shape
    if w < 2 or (ring[:, 0] != ring[0, 0]).any():             # (rows are beams: told from one column, O(h))
        return None
    if not (ring == ring[:1]).all() or (ring == ring[:, :1]).all():
        return None
    return tuple(int(c) for c in np.argsort(ring[0], kind="stable"))


def beam_row_order(height: int, width: int, lasers_by_ring: tuple[int, ...]) -> np.ndarray:
    """The stored index of each cell of the beams × firings grid of a cloud stored a row per firing
    (:func:`firing_row_columns`)."""
    return np.arange(height * width).reshape(height, width)[:, list(lasers_by_ring)].T.ravel()


def _as_beam_rows(columns: list[Column], grid_shape, field_map, path):
    """``columns`` in beams × firings order when an organised PCD stores a row per firing (a Velodyne organised cloud
    saved by pcl_ros), with the grid's shape and the layout's ``lasers_by_ring``; else as read."""
    if grid_shape is None:
        return columns, grid_shape, None
    keys = _canonical_keys([c[0] for c in columns], field_map, path)
    if "ring" not in keys or columns[keys.index("ring")][2].ndim != 1:
        return columns, grid_shape, None
    lasers = firing_row_columns(columns[keys.index("ring")][2].reshape(grid_shape))
    if lasers is None:
        return columns, grid_shape, None
    order = beam_row_order(*grid_shape, lasers)
    return [(name, dt, values[order]) for name, dt, values in columns], grid_shape[::-1], lasers


def cloud_from_columns(columns: list[Column], *, fmt: str, mode: str, grid_shape: tuple[int, int] | None,
                       sensor: str, profile: LidarProfile | RadarProfile | None,
                       field_map: Mapping[str, str] | None, source, text=None,
                       lasers_by_ring: tuple[int, ...] | None = None) -> PointCloud:
    """A cloud from stored columns (file name, dtype string, values) in storage order: canonical names, float64
    positions, the layout to store it back with (``text``: a text table's, io/text_table.py); :class:`InputError`
    (naming ``source``) for an empty cloud, missing or non-scalar x/y/z and non-finite coordinates."""
    if sensor == "radar":
        field_map = layout_field_map(tuple(c[0] for c in columns), field_map)
    keys = _canonical_keys([c[0] for c in columns], field_map, source)
    n = len(columns[0][2])
    if n == 0:
        raise EmptyCloudError("the point cloud is empty (0 points)", file=str(source))
    where = {k: i for i, k in enumerate(keys)}
    for axis in "xyz":
        if axis not in where or columns[where[axis]][2].ndim != 1:
            raise InputError(f"no scalar {axis!r} field (fields: {[c[0] for c in columns]})", file=str(source))
    positions = np.empty((n, 3))
    for i, axis in enumerate("xyz"):               # one pass each from the stored (possibly strided) column
        positions[:, i] = columns[where[axis]][2]
    empty = _non_finite_rows(positions)
    if empty.all() and grid_shape is None:
        raise EmptyCloudError(f"every point ({n}) has NaN or infinite coordinates: an empty frame's marker (as "
                              "nuScenes writes a radar sweep without detections)", file=str(source))
    if empty.any() and grid_shape is None:
        raise InputError(f"{int(np.count_nonzero(empty))} of {n} points have NaN or infinite coordinates "
                         "(only an organised cloud, HEIGHT > 1, may mark its no-return cells so)", file=str(source))
    if empty.any():
        positions[empty] = 0.0
        columns = [(name, dt, _cleared(values, empty)) for name, dt, values in columns]
    fields = {k: _native(col) for k, (_, _, col) in zip(keys, columns) if k not in ("x", "y", "z")}
    layout = CloudLayout(fmt=fmt, fields=tuple((k, name, dt) for k, (name, dt, _) in zip(keys, columns)),
                         pcd_data=mode, no_return="nan" if empty.any() else "zero", text=text,
                         lasers_by_ring=lasers_by_ring)
    return PointCloud(positions_m=positions, fields=fields, sensor=sensor, profile=profile, layout=layout,
                      grid_shape=grid_shape)


def about_sensor(cloud: PointCloud, schema, profile, path) -> PointCloud:
    """A Feather table's cloud with its Arrow ``schema`` in the layout and its positions about the profile's
    ``sensor_origin_m``. An Argoverse 2 sweep (``laser_number`` and ``offset_ns`` columns: the vehicle frame, its
    origin on the ground 1.35 m behind the sensors and 1.6 m below them) read with a profile that states no origin
    is refused: ranges, rays and the points weather moves along them would be the vehicle origin's."""
    origin = tuple(float(v) for v in getattr(profile, "sensor_origin_m", (0.0, 0.0, 0.0)))
    names = {name for _, name, _ in cloud.layout.fields}
    if profile is not None and not any(origin) and {"laser_number", "offset_ns"} <= names:
        raise InputError(f"an Argoverse 2 sweep (columns {sorted(names)}) is in the vehicle frame, not the sensor's: "
                         f"give lidar_profile: av2-vlp32c (its sensors' origin in that frame), not "
                         f"{getattr(profile, 'name', profile)!r}", file=str(path))
    layout = dataclasses.replace(cloud.layout, schema=schema, origin_m=origin)
    profile = with_sensor_poses(profile, names, path)
    return dataclasses.replace(cloud, positions_m=cloud.positions_m - np.asarray(origin), layout=layout,
                               profile=profile)


def with_sensor_poses(profile, names: set, path):
    """An Argoverse 2 sweep's profile (``storage_order: merged``) with each sensor's pose and own profile
    (``LidarProfile.sensors``) when its log's ``calibration/egovehicle_SE3_sensor.feather`` is beside it
    (:func:`io.feather.calibration_path`), so the weather acts on each sensor's rays (:mod:`sensor_rig`); else, or for
    another table, ``profile`` unchanged."""
    if not isinstance(profile, LidarProfile) or profile.sensors or not {"laser_number", "offset_ns"} <= names:
        return profile
    from ..physics.firing_grid import MERGED_SENSORS
    from ..profiles.lidar import AV2_SENSORS, av2_mounts

    calibration = calibration_path(path)
    if profile.storage_order != MERGED_SENSORS or not calibration.is_file():
        return profile

    source = f"{calibration.parent.parent.name}/{CALIBRATION.as_posix()}"
    return dataclasses.replace(profile, sensors=av2_mounts(read_sensor_poses(calibration, AV2_SENSORS), source))


def _non_finite_rows(positions: np.ndarray) -> np.ndarray:
    """Rows of ``positions`` (N, 3) with a NaN or infinite coordinate. A finite total means every coordinate is finite
    (one pass; NumPy's reductions along a row of 3 are ≈ 15× slower than along the columns)."""
    with np.errstate(invalid="ignore", over="ignore"):        # (inf − inf, an overflow: not the input's fault)
        total = positions.sum()
    if np.isfinite(total):
        return np.zeros(len(positions), bool)
    return ~(np.isfinite(positions[:, 0]) & np.isfinite(positions[:, 1]) & np.isfinite(positions[:, 2]))


def _cleared(values: np.ndarray, empty: np.ndarray) -> np.ndarray:
    """A column with the no-return cells ``empty`` of an organised cloud that marks them with non-finite x/y/z
    (PCL, ouster-ros ≥ 0.10, velodyne_pointcloud) as rvnoise's grid has them: non-finite values 0, others kept."""
    if values.dtype.kind != "f" or np.isfinite(values[empty]).all():
        return values
    values = values.copy()
    cells = values[empty]
    values[empty] = np.where(np.isfinite(cells), cells, 0)
    return values


def write_pointcloud(path: str | os.PathLike, cloud: PointCloud, *, effect: str = "auto") -> list[Path]:
    """Write ``cloud`` in the format, field order and dtypes of ``cloud.layout`` (a default layout from the suffix
    when it has none), atomically; returns the files written.

    ``effect="auto"``: the cloud's effect codes (``cloud.effect``, provenance.Effect, when a step reported them) are
    appended as a uint8 field ``rv_effect`` (PCD/PLY; ``rv_effect_2``, … if the input already has a field of that
    name: an input field is never overwritten) or written to the sidecar :func:`effect_sidecar_path` (fixed-layout
    ``.bin``, nuScenes radar PCD: io/radar_formats.py); ``"none"``: not written. Fields outside the layout, or
    layout fields missing from the cloud, are refused."""
    if effect not in ("auto", "none"):
        raise ValueError(f"effect must be 'auto' or 'none', got {effect!r}")
    layout = cloud.layout or default_layout(path, cloud)
    family = _family(layout.fmt)
    name = os.path.basename(os.fspath(path))
    if _family(cloud_format(path, cloud.sensor)) != family:
        raise ValueError(f"{name}: suffix does not match the cloud's layout format {layout.fmt!r}")
    columns, added = output_columns(cloud, layout, effect=effect, name=name)
    sidecar = family in ("bin", "feather") or fixed_field_layout(layout)
    if added is not None and not sidecar:
        columns.append(added)
    if layout.fmt == "pcd":
        grid = cloud.grid_shape
        if layout.lasers_by_ring is not None and grid is not None and len(layout.lasers_by_ring) == grid[0]:
            order, grid = beam_row_order(grid[1], grid[0], layout.lasers_by_ring), grid[::-1]   # back a row per firing
            columns = [(name, dt, _stored_at(values, order)) for name, dt, values in columns]
        data = _pcd_bytes(columns, layout.pcd_data, grid)
    elif layout.fmt == "ply":
        data = _ply_bytes(columns, layout.pcd_data)
    elif layout.fmt == "feather":
        data = feather_bytes(columns, layout.schema)
    elif layout.fmt == "txt":
        data = text_table.table_bytes(columns, layout.text or text_table.new_table(tuple(c[0] for c in columns)),
                                      cloud.origin)
    else:
        table = np.empty((len(columns[0][2]), len(columns)), "<f4")
        for i, (_, _, values) in enumerate(columns):
            table[:, i] = values
        data = _frozen(table)
    write_bytes_atomic(path, data)
    written = [Path(path)]
    if added is not None and sidecar:
        written.append(effect_sidecar_path(path))
        write_bytes_atomic(written[-1], added[2].tobytes())
    return written


def _stored_at(values: np.ndarray, order: np.ndarray) -> np.ndarray:
    stored = np.empty_like(values)
    stored[order] = values
    return stored


def output_columns(cloud: PointCloud, layout: CloudLayout, *, effect: str = "auto",
                   name: str = "cloud") -> tuple[list[Column], Column | None]:
    """What a writer stores (see :func:`write_pointcloud`): the layout's fields in order and file dtype, and the
    ``rv_effect`` column to append (None without effect codes or with ``effect="none"``); ``name`` identifies the
    cloud in errors."""
    keys = [k for k, _, _ in layout.fields]
    extra = sorted(set(cloud.fields) - set(keys))
    missing = [k for k in keys if k not in ("x", "y", "z") and k not in cloud.fields]
    if extra or missing:
        raise ValueError(f"{name}: cloud fields do not match the {layout.fmt} layout "
                         f"(not in layout: {extra}; missing from cloud: {missing})")
    positions = cloud.positions_m + np.asarray(layout.origin_m) if any(layout.origin_m) else cloud.positions_m
    if layout.no_return == "nan" and cloud.grid_shape is not None:     # no-return cells as the input marked them
        no_return = (positions[:, 0] == 0) & (positions[:, 1] == 0) & (positions[:, 2] == 0)     # (by column: fast)
        positions = np.where(no_return[:, None], np.nan, positions) if no_return.any() else positions
    columns: list[Column] = []
    for key, file_name, dt in layout.fields:
        values = positions[:, "xyz".index(key)] if key in ("x", "y", "z") else cloud.fields[key]
        columns.append((file_name, dt, _cast(with_derived(values, file_name, dt, cloud), dt, key)))
    if effect == "none" or cloud.effect is None:
        return columns, None
    field = effect_field_name([file_name for _, file_name, _ in layout.fields])
    return columns, (field, EFFECT_DTYPE, _cast(cloud.effect, EFFECT_DTYPE, EFFECT_FIELD))


def _family(fmt: str) -> str:
    """``pcd`` | ``ply`` | ``txt`` | ``feather`` | ``bin``: the formats a file suffix can tell apart."""
    return fmt if fmt in ("pcd", "ply", "txt", "feather") else "bin"


def effect_sidecar_path(path: str | os.PathLike) -> Path:
    """``<file name>.rv_effect`` next to a ``.bin``/``.pcd.bin`` cloud (``000001.bin.rv_effect``): N uint8 effect
    codes (provenance.Effect). The full name keeps ``x.bin`` and ``x.pcd.bin`` apart and never collides with a
    SemanticKITTI ``.label``."""
    path = Path(path)
    return path.with_name(path.name + "." + EFFECT_FIELD)


def effect_field_name(file_fields: list[str]) -> str:
    """``rv_effect``, or ``rv_effect_2``, ``rv_effect_3`` … when the file already has a field of that name."""
    name, k = EFFECT_FIELD, 1
    while name in file_fields:
        k += 1
        name = f"{EFFECT_FIELD}_{k}"
    return name


def default_layout(path: str | os.PathLike, cloud: PointCloud) -> CloudLayout:
    """Layout for a cloud built in memory: the fixed ``.bin`` layouts, float64 x, y, z and the cloud's fields for a
    text table, or float32 x, y, z followed by the cloud's fields in their dtypes for PCD (binary) and PLY (binary
    little-endian)."""
    fmt = cloud_format(path, cloud.sensor)
    if fmt in BIN_FIELDS:
        names = BIN_FIELDS[fmt]
        keys = _canonical_keys(list(names), None, path)
        return CloudLayout(fmt, tuple((k, n, "<f4") for k, n in zip(keys, names)))
    if fmt == "txt":
        names = ("x", "y", "z", *cloud.fields)
        return CloudLayout(fmt, tuple((k, k, "<f8") for k in names), "ascii", text=text_table.new_table(names))
    fields = [(a, a, "<f4") for a in "xyz"]
    fields += [(k, k, _dtype_str(np.asarray(v).dtype, np.asarray(v).shape[1:])) for k, v in cloud.fields.items()]
    return CloudLayout(fmt, tuple(fields), "binary" if fmt == "pcd" else "binary_little_endian")


# --- field names and dtypes ---------------------------------------------------------------------------------------


def _canonical_keys(names: list[str], field_map: Mapping[str, str] | None, path) -> list[str]:
    """In-memory key of each file field: ``field_map`` first, then :data:`ALIASES`, else the file name
    (repeated file names such as PCL's ``_`` padding become ``_#2``, ``_#3`` …)."""
    field_map = dict(field_map or {})
    unknown = [f for f in field_map if f not in names]
    if unknown:
        raise InputError(f"field_map names fields {unknown} that the file does not have (fields: {names})",
                         file=str(path))
    targets = list(field_map.values())
    if len(set(targets)) != len(targets):
        raise InputError(f"field_map maps several fields to one name: {field_map}", file=str(path))
    keys: list[str | None] = [field_map.get(n) for n in names]
    taken = set(targets)
    for canonical, aliases in ALIASES.items():
        if canonical in taken:
            continue
        hit = next((i for a in aliases for i, n in enumerate(names) if n == a and keys[i] is None), None)
        if hit is not None:
            keys[hit] = canonical
            taken.add(canonical)
    for i, name in enumerate(names):
        if keys[i] is not None:
            continue
        key, k = name, 1
        if key in taken and names.count(name) == 1:
            raise InputError(f"field {name!r} clashes with the field mapped to {name!r}; map it to another name in "
                             "field_map", file=str(path))
        while key in taken:
            k += 1
            key = f"{name}#{k}"
        keys[i] = key
        taken.add(key)
    return keys


def _dtype_str(base: np.dtype, shape: tuple[int, ...] = ()) -> str:
    """Layout dtype string: ``<f4``, ``|u1`` …, or ``(3,)<f4`` for a field with COUNT 3."""
    if shape:
        return f"({','.join(map(str, shape))},){base.str}"
    return base.str


def _native(col: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(col, dtype=col.dtype.newbyteorder("="))


def _cast(values: np.ndarray, dt: str, key: str) -> np.ndarray:
    """Values in the file dtype: floats cast, integers rounded and clipped to the type's range."""
    target = np.dtype(dt)
    base, shape = (target.subdtype if target.subdtype else (target, ()))
    values = np.asarray(values)
    if values.shape[1:] != shape:
        raise ValueError(f"field {key!r} has per-point shape {values.shape[1:]}, the file field has {shape}")
    if base.kind in "iu" and values.dtype.kind not in "iu":
        if np.isnan(values).any():
            raise ValueError(f"field {key!r} has NaN values but is stored as {base.name}")
        info = np.iinfo(base)
        values = np.clip(np.rint(values), info.min, info.max)
    elif base.kind in "iu" and not np.can_cast(values.dtype, base):
        info = np.iinfo(base)
        values = np.clip(values, info.min, info.max)
    return np.ascontiguousarray(values, dtype=base)


# --- PCD ----------------------------------------------------------------------------------------------------------


def _read_pcd(data: bytes, path) -> tuple[list[Column], str, tuple[int, int] | None]:
    header, start = _pcd_header(data, path)
    names, types = header["FIELDS"], header["TYPE"]
    try:
        sizes = [int(s) for s in header["SIZE"]]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        width, height = int(header["WIDTH"][0]), int(header.get("HEIGHT", ["1"])[0])
        n = int(header.get("POINTS", [width * height])[0])
    except (ValueError, IndexError) as exc:
        raise InputError(f"bad number in the PCD header ({exc})", file=str(path)) from exc
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise InputError(f"PCD header has {len(names)} FIELDS, {len(sizes)} SIZE, {len(types)} TYPE and "
                         f"{len(counts)} COUNT entries", file=str(path))
    try:
        bases = [np.dtype(f"<{_PCD_TYPE[t]}{s}") for t, s in zip(types, sizes)]
    except (KeyError, TypeError) as exc:
        raise InputError(f"unsupported PCD TYPE/SIZE in {list(zip(types, sizes))}", file=str(path)) from exc
    if n != width * height:
        raise InputError(f"PCD header WIDTH×HEIGHT = {width}×{height} does not match POINTS {n}", file=str(path))
    mode = header["DATA"][0].lower()
    dtypes = [np.dtype((b, (c,))) if c > 1 else b for b, c in zip(bases, counts)]
    record = np.dtype([(f"f{i}", d) for i, d in enumerate(dtypes)])
    body = memoryview(data)[start:]
    if mode == "binary":
        if len(body) < n * record.itemsize:
            raise InputError(f"truncated PCD: header says {n} points × {record.itemsize} bytes = "
                             f"{n * record.itemsize} bytes of data, the file has {len(body)}", file=str(path))
        _check_trailing(body, n * record.itemsize, record.itemsize, n, "PCD", path)
        arr = np.frombuffer(body, record, count=n)
        values = [arr[f"f{i}"] for i in range(len(names))]
    elif mode == "binary_compressed":
        values = _pcd_decompress(body, n, dtypes, record.itemsize, path)
    elif mode == "ascii":
        values = _parse_ascii(bytes(body), n, dtypes, path)
    else:
        raise InputError(f"unknown PCD DATA mode {mode!r} (ascii | binary | binary_compressed)", file=str(path))
    columns = [(name, _dtype_str(b, (c,) if c > 1 else ()), v)     # views: cloud_from_columns copies what it keeps
               for name, b, c, v in zip(names, bases, counts, values)]
    return columns, mode, ((height, width) if height > 1 else None)


def _check_trailing(body, used: int, itemsize: int, n: int, kind: str, path, *, sized: bool = False) -> None:
    """Refuse data after the declared points (the header's point count is smaller than the data): a whole point
    more, or anything but whitespace. ``sized``: the data state their own size (binary_compressed), so NUL or
    whitespace padding of any length is no point (PCL 1.x left some KiB of NULs after its own test clouds' data)."""
    extra = len(body) - used
    if (extra >= itemsize and not sized) or (extra > 0 and bytes(body[used:]).strip(b" \t\r\n\0")):
        raise InputError(f"{kind} header declares {n} points ({used} bytes of data) but the file holds {extra} "
                         "bytes more; the point count does not match the data (the rest would be dropped "
                         "silently)", file=str(path))


def _pcd_header(data: bytes, path) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while pos < len(data):
        end = data.find(b"\n", pos)
        end = len(data) if end < 0 else end
        try:
            line = data[pos:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise InputError("not a PCD file (binary bytes before the DATA line)", file=str(path)) from None
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            missing = [k for k in ("FIELDS", "SIZE", "TYPE", "WIDTH") if k not in header]
            if missing or not vals:
                raise InputError(f"PCD header lacks {missing or ['DATA mode']}", file=str(path))
            return header, pos
    raise InputError("not a PCD file (no DATA line in the header)", file=str(path))


def _pcd_decompress(body: memoryview, n: int, dtypes: list[np.dtype], itemsize: int, path) -> list[np.ndarray]:
    """binary_compressed: uint32 compressed size, uint32 raw size, LZF data of the columns one after another."""
    if len(body) < 8:
        raise InputError("truncated PCD: binary_compressed data has no size words", file=str(path))
    csize, usize = (int(v) for v in np.frombuffer(body[:8], "<u4"))
    if usize != n * itemsize:
        raise InputError(f"PCD binary_compressed raw size {usize} ≠ POINTS {n} × {itemsize} bytes", file=str(path))
    if len(body) < 8 + csize:
        raise InputError(f"truncated PCD: {csize} compressed bytes announced, {len(body) - 8} present", file=str(path))
    _check_trailing(body, 8 + csize, itemsize, n, "PCD", path, sized=True)
    raw, produced = _lzf_decompress(np.frombuffer(body[8:8 + csize], np.uint8), usize)
    if produced != usize:
        raise InputError("corrupt PCD: the LZF-compressed data do not decode to the announced size", file=str(path))
    out, offset = [], 0
    for dt in dtypes:
        out.append(np.frombuffer(raw, dt, count=n, offset=offset))
        offset += n * dt.itemsize
    return out


def _parse_ascii(text: bytes, n: int, dtypes: list[np.dtype], path) -> list[np.ndarray]:
    """Whitespace-separated values, one point per line (PCD ascii, PLY ascii)."""
    widths = [int(np.prod(d.shape)) if d.shape else 1 for d in dtypes]
    tokens = text.split()
    total = n * sum(widths)
    if len(tokens) < total:
        raise InputError(f"truncated ascii data: header says {n} points × {sum(widths)} values, the file has "
                         f"{len(tokens)} values", file=str(path))
    if len(tokens) > total:
        raise InputError(f"the header declares {n} points × {sum(widths)} values but the file holds "
                         f"{len(tokens)} values; the point count does not match the data (the rest would be "
                         "dropped silently)", file=str(path))
    table = np.array(tokens[:total]).reshape(n, sum(widths))
    out, col = [], 0
    for dt, w in zip(dtypes, widths):
        base = dt.base
        try:
            vals = table[:, col:col + w].astype(base)
        except (ValueError, OverflowError):
            bad = next((t for t in table[:, col:col + w].ravel() if not _fits(t, base)), b"?")
            raise InputError(f"bad ascii value {bad.decode('ascii', 'replace')!r} in column {col + 1}: not a "
                             f"{base.name} number", file=str(path)) from None
        out.append(vals if w > 1 else vals[:, 0])
        col += w
    return out


def _fits(token: bytes, base: np.dtype) -> bool:
    try:
        np.array([token]).astype(base)
        return True
    except (ValueError, OverflowError):
        return False


def _ascii_bytes(columns: list[Column]) -> bytes:
    parts = []
    for _, dt, col in columns:
        base = np.dtype(dt).base
        fmt = {"f4": "%.9g", "f8": "%.17g"}.get(f"{base.kind}{base.itemsize}", "%d")
        flat = col.reshape(len(col), -1)
        parts += [np.char.mod(fmt, flat[:, j]) for j in range(flat.shape[1])]
    return ("\n".join(map(" ".join, zip(*parts))) + "\n").encode("ascii")


def _pcd_bytes(columns: list[Column], mode: str, grid_shape: tuple[int, int] | None) -> bytes | memoryview:
    n = len(columns[0][2])
    height, width = grid_shape if grid_shape and grid_shape[0] * grid_shape[1] == n else (1, n)
    bases = [np.dtype(dt).base for _, dt, _ in columns]
    counts = [int(np.prod(np.dtype(dt).shape)) if np.dtype(dt).shape else 1 for _, dt, _ in columns]
    kinds = {"f": "F", "u": "U", "i": "I"}
    if any(b.kind not in kinds for b in bases):
        raise ValueError(f"PCD cannot store dtypes {[b.str for b in bases]}")
    header = "\n".join([
        "# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7",
        "FIELDS " + " ".join(name for name, _, _ in columns),
        "SIZE " + " ".join(str(b.itemsize) for b in bases),
        "TYPE " + " ".join(kinds[b.kind] for b in bases),
        "COUNT " + " ".join(map(str, counts)),
        f"WIDTH {width}", f"HEIGHT {height}", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", f"DATA {mode}", ""])
    if mode == "ascii":
        body = _ascii_bytes(columns)
    elif mode == "binary":
        return _records(header.encode("ascii"), columns, "<")
    elif mode == "binary_compressed":
        raw = np.frombuffer(b"".join(c.astype(b.newbyteorder("<")).tobytes() for (_, _, c), b in zip(columns, bases)),
                            np.uint8)
        packed = _lzf_compress(raw)
        body = np.array([len(packed), len(raw)], "<u4").tobytes() + packed.tobytes()
    else:
        raise ValueError(f"unknown PCD DATA mode {mode!r}")
    return header.encode("ascii") + body


def _records(header: bytes, columns: list[Column], order: str) -> memoryview:
    """``header`` followed by the columns as packed records in byte order ``order``, built in one buffer (no copy
    into ``bytes``; :func:`_frozen`)."""
    record = np.dtype([(f"f{i}", np.dtype(dt).newbyteorder(order)) for i, (_, dt, _) in enumerate(columns)])
    buf = np.empty(len(header) + len(columns[0][2]) * record.itemsize, np.uint8)
    buf[:len(header)] = np.frombuffer(header, np.uint8)
    arr = buf[len(header):].view(record)
    for i, (_, _, col) in enumerate(columns):
        arr[f"f{i}"] = col
    return _frozen(buf)


def _frozen(arr: np.ndarray) -> memoryview:
    """The bytes of a C-contiguous array nobody else holds, read-only: written as they are, and hashed from memory
    for the manifest (io/atomic.write_bytes_atomic)."""
    flat = arr.reshape(-1).view(np.uint8)
    flat.flags.writeable = False
    return memoryview(flat)


# --- PLY ----------------------------------------------------------------------------------------------------------


def _read_ply(data: bytes, path) -> tuple[list[Column], str]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file (no 'ply' magic or no end_header)", file=str(path))
    start = data.find(b"\n", end) + 1
    mode, elements = None, []                  # elements: [name, count, [(property name, type)]]
    for line in data[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            mode = words[1] if len(words) > 1 else None
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property" and elements and len(words) >= 3:
            if words[1] == "list":
                raise InputError(f"PLY list property {words[-1]!r} is not supported (point clouds only)",
                                 file=str(path))
            if words[1] not in _PLY_TYPES:
                raise InputError(f"unknown PLY property type {words[1]!r}", file=str(path))
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise InputError(f"bad PLY header line {line!r}", file=str(path))
    if mode not in _PLY_ENDIAN:
        raise InputError(f"unknown PLY format {mode!r}", file=str(path))
    if not elements or elements[0][0] != "vertex" or any(e[1] for e in elements[1:]):
        raise InputError(f"expected one non-empty 'vertex' element first, got {[(e[0], e[1]) for e in elements]}",
                         file=str(path))
    _, n, props = elements[0]
    dtypes = [np.dtype(_PLY_ENDIAN[mode] + t) for _, t in props]
    if mode == "ascii":
        values = _parse_ascii(data[start:], n, dtypes, path)
    else:
        record = np.dtype([(f"f{i}", d) for i, d in enumerate(dtypes)])
        if len(data) - start < n * record.itemsize:
            raise InputError(f"truncated PLY: header says {n} vertices × {record.itemsize} bytes, the file has "
                             f"{len(data) - start} bytes of data", file=str(path))
        _check_trailing(memoryview(data)[start:], n * record.itemsize, record.itemsize, n, "PLY", path)
        arr = np.frombuffer(data, record, count=n, offset=start)
        values = [arr[f"f{i}"] for i in range(len(props))]
    return [(name, d.str, v) for (name, _), d, v in zip(props, dtypes, values)], mode


def _ply_bytes(columns: list[Column], mode: str) -> bytes | memoryview:
    if mode not in _PLY_ENDIAN:
        raise ValueError(f"unknown PLY format {mode!r}")
    n = len(columns[0][2])
    props = []
    for name, dt, _ in columns:
        base = np.dtype(dt)
        if base.shape or f"{base.kind}{base.itemsize}" not in _PLY_NAME:
            raise ValueError(f"PLY cannot store field {name!r} of dtype {dt}")
        props.append(f"property {_PLY_NAME[f'{base.kind}{base.itemsize}']} {name}")
    header = "\n".join(["ply", f"format {mode} 1.0", f"element vertex {n}", *props, "end_header", ""])
    if mode == "ascii":
        return header.encode("ascii") + _ascii_bytes(columns)
    return _records(header.encode("ascii"), columns, _PLY_ENDIAN[mode])


# --- text tables ---------------------------------------------------------------------------------------------------


def _read_txt(data: bytes, field_map: Mapping[str, str] | None, path):
    """Columns, mode, :class:`~.text_table.TextTable` and field map (Astyx's completed, io/radar_formats.py) of a
    text table."""
    columns, table = text_table.parse(data, path, negate=lambda names: text_table_fields(names, field_map)[1])
    return columns, "ascii", table, text_table_fields(table.names, field_map)[0]


# --- fixed-layout .bin ---------------------------------------------------------------------------------------------


def bin_point_bytes(fmt: str, bin_fields: Sequence[str] | None, data: bytes | None) -> int | None:
    """Bytes a point of a ``.bin`` of format ``fmt`` (:func:`cloud_format`) takes as :func:`read_pointcloud` reads
    it: 4 per float32 column of the recipe's ``bin_fields`` (``radar_bin_fields`` for radar), TJ4DRadSet's 8
    columns for a radar ``.bin`` whose ``data`` (its bytes, when read) are that layout, else the format's columns;
    None for a format that is no ``.bin``."""
    if fmt not in BIN_FIELDS:
        return None
    if bin_fields is not None:
        return 4 * len(bin_fields)
    if fmt == "vod_bin" and data is not None and is_tj4d_bin(data):
        return 4 * len(BIN_FIELDS["tj4d_bin"])
    return 4 * len(BIN_FIELDS[fmt])


def _bin_names(fmt: str, bin_fields: Sequence[str] | None, path) -> tuple[str, ...]:
    """The columns of a ``.bin``: the format's fixed ones, or the recipe's ``bin_fields`` (x, y, z first)."""
    if bin_fields is None or fmt in ("vod_bin", "tj4d_bin"):
        return BIN_FIELDS[fmt]
    names = tuple(bin_fields)
    if names[:3] != ("x", "y", "z") or len(set(names)) != len(names):
        key = "radar_bin_fields" if fmt == "radar_bin" else "bin_fields"
        raise InputError(f"inputs.{key} {list(names)} must start with x, y, z and name each column once",
                         file=str(path))
    return names


def _read_bin(data: bytes, names: tuple[str, ...], path, fmt: str) -> list[Column]:
    point = 4 * len(names)
    lidar = fmt in ("kitti_bin", "nuscenes_bin")           # (the hints name LiDAR layouts and inputs.bin_fields)
    if len(data) % point:
        raise InputError(f"size {len(data)} bytes is not a multiple of the {point}-byte point "
                         f"({', '.join(names)} as float32)" + (_other_columns(data, names) if lidar else ""),
                         file=str(path))
    table = np.frombuffer(data, "<f4").reshape(-1, len(names))
    # (every column first: one contiguous pass, 10× faster than x/y/z's strided one, which only a larger value needs;
    # non-finite coordinates: refused by cloud_from_columns)
    if fmt in ("kitti_bin", "nuscenes_bin", "radar_bin") and _farthest_m(table) > MAX_COORDINATE_M \
            and (top := _farthest_m(table[:, :3])) > MAX_COORDINATE_M:
        raise InputError(f"not N×{len(names)} float32 ({', '.join(names)}): coordinates reach {top:.3g} m"
                         + (_other_columns(data, names) if lidar else ""), file=str(path))
    return [(name, "<f4", table[:, i]) for i, name in enumerate(names)]      # views: see _read_pcd


def _farthest_m(xyz: np.ndarray) -> float:
    """The largest finite |coordinate| (0 for none): from the extremes (no temporary array) when they are finite."""
    if not len(xyz):
        return 0.0
    low, high = float(xyz.min()), float(xyz.max())
    if np.isfinite(low) and np.isfinite(high):
        return max(high, -low, 0.0)
    return float(np.max(np.abs(np.nan_to_num(xyz, nan=0.0, posinf=0.0, neginf=0.0)), initial=0.0))


MAX_COORDINATE_M = 1.0e4     # farther than any LiDAR sees: a .bin read with the wrong column count


def _plausible(table: np.ndarray) -> bool:
    xyz = table[:, :3]
    return bool(len(xyz) and np.isfinite(xyz).all() and np.abs(xyz).max(initial=0.0) <= MAX_COORDINATE_M)


def _other_columns(data: bytes, names: tuple[str, ...]) -> str:
    """What a LiDAR ``.bin`` that does not fit its fixed layout fits instead: its points may have another number of
    float32 columns (Waymo's KITTI-format export: 6, x y z intensity elongation timestamp; Lyft and nuScenes: 5),
    which a byte count divisible by both does not reveal."""
    floats = np.frombuffer(data[:len(data) - len(data) % 4], "<f4")
    fits = [k for k in range(3, 9) if k != len(names) and len(floats) % k == 0 and _plausible(floats.reshape(-1, k))]
    if not fits:
        return "; no other column count gives plausible coordinates either"
    return (f"; read as {' or '.join(map(str, fits))} float32 columns it is plausible (Waymo's KITTI-format export "
            f"has 6: x, y, z, intensity, elongation, timestamp; nuScenes and Lyft 5, named .pcd.bin): name its "
            f"columns with inputs.bin_fields (e.g. [x, y, z, intensity, elongation, timestamp])")


# --- LZF (liblzf stream format, as used by PCD binary_compressed) ---------------------------------------------------
# A control byte c < 32 is followed by c + 1 literal bytes; otherwise it is a back-reference of length
# (c >> 5) + 2 (length field 7: plus the next byte) to distance ((c & 31) << 8) + next byte + 1 behind the output.


@jit(inline="always")
def _lzf_literals(src, start, end, dst, op):            # pragma: no cover - compiled
    """Copy ``src[start:end]`` to ``dst`` at ``op`` as literal runs of at most 32 bytes; returns the new ``op``."""
    while start < end:
        k = min(32, end - start)
        dst[op] = k - 1
        dst[op + 1:op + 1 + k] = src[start:start + k]
        op += k + 1
        start += k
    return op


@jit
def _lzf_compress(src: np.ndarray) -> np.ndarray:            # pragma: no cover - compiled
    """Greedy LZF with a 16 k-entry hash of 3-byte prefixes (liblzf's scheme); any LZF decoder reads the output."""
    n = src.size
    dst = np.empty(n + n // 32 + 16, np.uint8)
    table = np.full(1 << 14, -1, np.int64)
    ip = 0
    op = 0
    lit = 0
    while ip + 2 < n:
        h = (np.uint32(src[ip]) << 16) | (np.uint32(src[ip + 1]) << 8) | np.uint32(src[ip + 2])
        h = ((h * np.uint32(2654435761)) & np.uint32(0xFFFFFFFF)) >> np.uint32(18)
        ref = table[h]
        table[h] = ip
        off = ip - ref - 1
        if ref >= 0 and off < 8192 and src[ref] == src[ip] and src[ref + 1] == src[ip + 1] \
                and src[ref + 2] == src[ip + 2]:
            op = _lzf_literals(src, lit, ip, dst, op)
            limit = min(264, n - ip)
            length = 3
            while length < limit and src[ref + length] == src[ip + length]:
                length += 1
            code = length - 2
            if code < 7:
                dst[op] = (code << 5) | (off >> 8)
                op += 1
            else:
                dst[op] = (7 << 5) | (off >> 8)
                dst[op + 1] = code - 7
                op += 2
            dst[op] = off & 255
            op += 1
            ip += length
            lit = ip
        else:
            ip += 1
    op = _lzf_literals(src, lit, n, dst, op)
    return dst[:op]


@jit
def _lzf_decompress(src: np.ndarray, size: int) -> tuple[np.ndarray, int]:   # pragma: no cover - compiled
    """Decoded bytes and their count; the count is −1 when the stream is corrupt or overruns ``size``."""
    dst = np.zeros(size, np.uint8)
    n = src.size
    ip = 0
    op = 0
    while ip < n:
        c = np.int64(src[ip])
        ip += 1
        if c < 32:
            length = c + 1
            if ip + length > n or op + length > size:
                return dst, -1
            dst[op:op + length] = src[ip:ip + length]
            ip += length
            op += length
        else:
            length = c >> 5
            if length == 7:
                if ip >= n:
                    return dst, -1
                length += np.int64(src[ip])
                ip += 1
            if ip >= n:
                return dst, -1
            ref = op - ((c & 31) << 8) - np.int64(src[ip]) - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > size:
                return dst, -1
            for k in range(length):                  # byte by byte: the source may overlap the output
                dst[op + k] = dst[ref + k]
            op += length
    return dst, op
