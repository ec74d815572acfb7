"""Apache Arrow Feather v2 (IPC file) point tables: Argoverse 2 LiDAR sweeps (``sensors/lidar/<ns>.feather``).

An Argoverse 2 sweep is one table, a row per return of its two stacked VLP-32C: ``x``, ``y``, ``z`` (halffloat,
metres, in the vehicle frame), ``intensity`` (uint8), ``laser_number`` (uint8, 0–31 the upper sensor, 32–63 the
lower), ``offset_ns`` (int32, the return's time after the sweep's stamp) and the pandas metadata of the writer
(av2 devkit ``av2.structures.sweep.Sweep.from_feather``; real sweeps of its test data checked: these six columns,
two record batches). Read with pyarrow (the ``arrow`` extra); written back with the table's schema — every column in
its order and Arrow type, the schema's metadata —, LZ4-compressed as Feather writes by default, so
``pyarrow.feather.read_table`` and the devkit read the output as they read the input. Columns of nested or
non-numeric type are refused, naming them.

The sweep's two sensors have their own frames: the log's ``calibration/egovehicle_SE3_sensor.feather`` (three levels
above the sweep: ``<log>/sensors/lidar/<ns>.feather``) holds each sensor's pose in the vehicle frame, a row per sensor
(``sensor_name`` string; ``qw``, ``qx``, ``qy``, ``qz``: unit quaternion, scalar first; ``tx_m``, ``ty_m``, ``tz_m``),
``p_vehicle = R(q) p_sensor + t`` (av2 devkit ``read_ego_SE3_sensor``, ``quat_to_mat``): :func:`read_sensor_poses`.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..errors import InputError

Column = tuple[str, str, np.ndarray]


def _pyarrow(path):
    try:
        import pyarrow
        import pyarrow.feather  # noqa: F401  (the submodule the calls below use)
    except ImportError:
        raise InputError("reading a .feather table needs pyarrow: pip install 'roadview_noise[arrow]'",
                         file=str(path)) from None
    return pyarrow


def read_feather(data: bytes, path) -> tuple[list[Column], object]:
    """The table's columns (file name, NumPy dtype string, values) in storage order and its Arrow schema."""
    pa = _pyarrow(path)
    try:
        table = pa.feather.read_table(io.BytesIO(data), memory_map=False)
    except (pa.ArrowInvalid, pa.ArrowException, OSError) as exc:
        raise InputError(f"not a readable Feather/Arrow table: {exc}", file=str(path)) from None
    columns = []
    for field, column in zip(table.schema, table.columns):
        if not (pa.types.is_integer(field.type) or pa.types.is_floating(field.type)):
            raise InputError(f"column {field.name!r} is of Arrow type {field.type}: only numeric per-point "
                             f"columns are read", file=str(path))
        if column.null_count:
            raise InputError(f"column {field.name!r} has {column.null_count} null values", file=str(path))
        values = column.to_numpy()
        columns.append((field.name, values.dtype.str, values))
    return columns, table.schema


def feather_bytes(columns: list[Column], schema) -> bytes:
    """The Feather v2 file of ``columns`` (in the file dtypes of :func:`read_feather`) under ``schema`` (None: a
    cloud built in memory, its columns' types)."""
    pa = _pyarrow("")
    if schema is None:
        schema = pa.schema([(name, pa.from_numpy_dtype(np.dtype(dt))) for name, dt, _ in columns])
    arrays = [pa.array(values, type=field.type) for field, (_, _, values) in zip(schema, columns)]
    sink = io.BytesIO()
    pa.feather.write_feather(pa.Table.from_arrays(arrays, schema=schema), sink)
    return sink.getvalue()


CALIBRATION = Path("calibration", "egovehicle_SE3_sensor.feather")     # relative to the log (av2 devkit)
_POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")


def calibration_path(sweep) -> Path:
    """Where the log of an Argoverse 2 sweep ``<log>/sensors/lidar/<ns>.feather`` keeps its sensors' poses."""
    return Path(sweep).parent.parent.parent / CALIBRATION


def read_sensor_poses(path, names: tuple[str, ...]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per sensor of ``names``: (3×3 rotation, translation m), sensor → vehicle frame, from an Argoverse 2
    ``egovehicle_SE3_sensor.feather`` (module doc); :class:`InputError` naming the file for an unreadable table,
    missing columns or sensors, or a quaternion that is not of unit norm (±1 %)."""
    pa = _pyarrow(path)
    try:
        table = pa.feather.read_table(str(path), memory_map=False)
    except (pa.ArrowInvalid, pa.ArrowException, OSError) as exc:
        raise InputError(f"not a readable Feather/Arrow table: {exc}", file=str(path)) from None
    missing = [c for c in ("sensor_name", *_POSE_COLUMNS) if c not in table.schema.names]
    if missing:
        raise InputError(f"sensor poses without columns {missing}", file=str(path))
    rows = {name: i for i, name in enumerate(table.column("sensor_name").to_pylist())}
    absent = [n for n in names if n not in rows]
    if absent:
        raise InputError(f"no pose of {absent} (sensors: {sorted(map(str, rows))})", file=str(path))
    values = np.stack([table.column(c).to_numpy(zero_copy_only=False).astype(np.float64) for c in _POSE_COLUMNS], 1)
    poses = {}
    for name in names:
        w, x, y, z, *t = values[rows[name]]
        norm = w * w + x * x + y * y + z * z
        if not abs(norm - 1.0) < 0.02:
            raise InputError(f"the pose of {name} has a quaternion of squared norm {norm:.4g}, not 1", file=str(path))
        poses[name] = (quaternion_matrix(w, x, y, z), np.array(t))
    return poses


def quaternion_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    """The rotation matrix of the quaternion w + xi + yj + zk (normalised; Hamilton convention, scalar first)."""
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
