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

The devkit reads exactly these 18 fields (``RadarPointCloud.nbr_dims() == 18``, asserted) and finds
``invalid_state`` as the 4th row from the end, so an extra ``rv_effect`` field would make it fail; such a file gets
its effect codes in the ``.rv_effect`` sidecar instead, as a fixed-layout ``.bin`` does (:func:`fixed_field_layout`).
"""

from __future__ import annotations

import numpy as np

from ..types import CloudLayout, PointCloud

NUSCENES_RADAR_FILE_FIELDS = tuple(("x y z dyn_prop id rcs vx vy vx_comp vy_comp is_quality_valid ambig_state x_rms "
                                    "y_rms invalid_state pdh0 vx_rms vy_rms").split())
NUSCENES_RADAR_FIELDS = ("dyn_prop", "id", "rcs_dbsm", "vx", "vy", "vx_comp", "vy_comp", "is_quality_valid",
                         "ambig_state", "x_rms", "y_rms", "invalid_state", "pdh0", "vx_rms", "vy_rms")
NUSCENES_ADDED_STATES = {"invalid_state": 0, "ambig_state": 3, "is_quality_valid": 1, "dyn_prop": 4}
NUSCENES_TYPICAL = ("pdh0", "x_rms", "y_rms", "vx_rms", "vy_rms")


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
    """A PCD whose readers expect exactly its fields (nuScenes radar): effect codes go to a sidecar."""
    return layout.fmt == "pcd" and tuple(name for _, name, _ in layout.fields) == NUSCENES_RADAR_FILE_FIELDS
