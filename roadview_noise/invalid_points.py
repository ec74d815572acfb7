"""Points with invalid values are removed before the chain, and counted.

A NaN or infinite value in a field the models read (intensity, radar velocity, RCS, …) used to be dropped by some
models as if the weather had removed the point (``fog.lidar`` counted them as attenuated) and to pass through others
with a numpy RuntimeWarning. Such points are invalid returns: the runner removes them once, before the first model
(a grid keeps its shape: the cell becomes a no-return), and the manifest entry counts them per field under
``input_warnings`` (``dropped_nonfinite_<field>``). Fields the models do not read (a dataset's own extra columns)
are carried through as they are. Coordinates are never screened here: a cloud with non-finite coordinates is
refused by the reader.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .types import PointCloud, SensorData

SCREENED_FIELDS = ("intensity", "time_s", "rcs_dbsm", "v_r_m_per_s", "v_r_comp_m_per_s", "snr_db", "power_db")


def drop_invalid_points(data: SensorData, *, file: str | None = None) -> tuple[SensorData, dict[str, int]]:
    """``(data without the invalid points, {"dropped_nonfinite_<field>": count})``; frames pass unchanged."""
    if not isinstance(data, PointCloud):
        return data, {}
    bad = np.zeros(len(data), bool)
    counts = {}
    for name in SCREENED_FIELDS:
        values = data.fields.get(name)
        if values is None or values.dtype.kind != "f":
            continue
        finite = np.isfinite(values)
        if finite.all():                                 # the usual field: no row reduction, no count
            continue
        invalid = ~finite.reshape(len(values), -1).all(axis=1)
        n = int(np.count_nonzero(invalid))
        if n:
            counts[f"dropped_nonfinite_{name}"] = n
            bad |= invalid
    if not counts:
        return data, {}
    if data.grid_shape is None and bad.all():
        fields = ", ".join(k.removeprefix("dropped_nonfinite_") for k in counts)
        raise InputError(f"all {len(data)} points have NaN or infinite values (in {fields}); nothing left to "
                         "process", file=file)
    return data.drop(bad), counts
