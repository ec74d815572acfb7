"""Apache Arrow Feather v2 (IPC file) point tables: Argoverse 2 LiDAR sweeps (``sensors/lidar/<ns>.feather``).

An Argoverse 2 sweep is one table, a row per return of its two stacked VLP-32C: ``x``, ``y``, ``z`` (halffloat,
metres, in the vehicle frame), ``intensity`` (uint8), ``laser_number`` (uint8, 0–31 the upper sensor, 32–63 the
lower), ``offset_ns`` (int32, the return's time after the sweep's stamp) and the pandas metadata of the writer
(av2 devkit ``av2.structures.sweep.Sweep.from_feather``; real sweeps of its test data checked: these six columns,
two record batches). Read with pyarrow (the ``arrow`` extra); written back with the table's schema — every column in
its order and Arrow type, the schema's metadata —, LZ4-compressed as Feather writes by default, so
``pyarrow.feather.read_table`` and the devkit read the output as they read the input. Columns of nested or
non-numeric type are refused, naming them.
"""

from __future__ import annotations

import io

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
