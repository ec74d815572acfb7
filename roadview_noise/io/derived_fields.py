"""Per-point fields that restate a point's position, kept true to the position written.

Ouster's ``range`` (uint32, millimetres; ouster-ros' and ouster-sdk's clouds) is the distance the sensor measured.
A point the chain moved along its ray to a weather particle (:class:`~roadview_noise.provenance.Effect` MOVED) or
added on an empty ray (ADDED) gets ``rint(|p| · 1000)``: the distance from the cloud's origin, which differs from
the sensor's own by its beam-origin offset (−12 … +14 mm on a real OS1-128 scan); before, such a point kept the
range of the object behind the particle (median 12.8 m off under fog 30 m) or of the empty cell (0). Every other
point keeps the value it was recorded with. Fields of other names or types are not touched.
"""

from __future__ import annotations

import numpy as np

from ..types import PointCloud

RANGE_MM_FIELDS = (("range", "<u4"),)          # (file field name, stored dtype) of a range in millimetres


def with_derived(values: np.ndarray, file_name: str, dt: str, cloud: PointCloud) -> np.ndarray:
    """``values`` of the stored field ``file_name`` with the points the chain moved or added brought up to date."""
    if (file_name, dt) not in RANGE_MM_FIELDS or cloud.effect is None:
        return values
    from ..provenance import Effect

    new = (cloud.effect == Effect.MOVED) | (cloud.effect == Effect.ADDED)
    if not new.any():
        return values
    out = np.array(values, dtype=np.float64)
    out[new] = np.rint(np.linalg.norm(cloud.positions_m[new], axis=1) * 1000.0)
    return out
