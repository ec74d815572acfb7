"""A chain step on a sweep that merges several sensors, each sensor on its own rays (Argoverse 2's two VLP-32C).

A sweep whose profile lists its sensors (``LidarProfile.sensors``: rings, pose and own profile of each, from the
log's calibration, :func:`io.pointcloud.with_sensor_poses`) is not one sensor's point list: its upper and lower
(upside-down) sensors fire their own grids from their own origins. So every step of a chain runs once per sensor
(:func:`apply_per_sensor`):

- split: each sensor's rows (its rings), positions taken into its frame (``q = Rᵀ (p + o − t)``, ``o`` the sweep
  profile's ``sensor_origin_m`` the chain's positions are about), rings less its first, its own profile: a single
  VLP-32C list, whose firing grid and empty rays the weather finds as for any list (:mod:`physics.firing_time`);
- randomness: each sensor draws from ``derive_rng(seed, key, step, model, sensor)`` (sequence state: ``(seed,
  "sequence", sequence_id, model, sensor)``), independent of the other's; the parameters drawn for the file are the
  sweep's (one weather for both);
- merge: rows back in the sweep's frame, rings and order — the input's rows in their order, a sensor's added weather
  returns (their fields copied from a return of the same firing, ring their cell's) inserted by their time
  (``offset_ns``) when the rows are in time order, else appended —; a row that came back where it was keeps the
  input's coordinates bit for bit; each sensor's profile as its step left it (a misalignment tilts its beams);
- record: drawn state per sensor, diagnostics summed over the sensors (counts) with each sensor's own under
  ``sensors``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .physics.firing_time import TIME_FIELD
from .physics.lidar_geometry import RING
from .provenance import KEPT, NEW
from .types import PointCloud, SensorMount


PER_SENSOR = ("firing_grid_columns",)      # integer diagnostics that are a sensor's property, not a count


def sensors_of(data) -> tuple[SensorMount, ...]:
    """The sensors of a merged LiDAR sweep (() for any other data)."""
    if not isinstance(data, PointCloud) or data.sensor != "lidar":
        return ()
    return getattr(data.profile, "sensors", ())


@dataclasses.dataclass(frozen=True, eq=False)
class Part:
    """One sensor's rows of a sweep: ``rows`` (indices into the sweep) and ``cloud``, in the sensor's frame."""

    mount: SensorMount
    rows: np.ndarray
    cloud: PointCloud


def _pose(mount: SensorMount, origin_m) -> tuple[np.ndarray, np.ndarray]:
    """(R, t − o): the sensor's rotation and its origin relative to the chain's origin ``o``."""
    return np.asarray(mount.rotation, dtype=np.float64), (np.asarray(mount.translation_m, dtype=np.float64)
                                                          - np.asarray(origin_m, dtype=np.float64))


def split(cloud: PointCloud, recorded: bool = True) -> list[Part]:
    """Each sensor's rows of ``cloud`` in its own frame with its own profile (module doc); its ``recorded`` cloud
    (the chain's input) split likewise when ``recorded``. Rows of rings no sensor holds are refused."""
    ring = np.asarray(cloud.fields[RING]).astype(np.int64)
    mounts = sensors_of(cloud)
    owner = np.full(len(ring), -1)
    for k, mount in enumerate(mounts):
        owner[(ring >= mount.first_ring) & (ring < mount.first_ring + mount.profile.channels)] = k
    if (owner < 0).any():
        from .errors import ModelError

        raise ModelError(f"rings {sorted(set(ring[owner < 0].tolist()))[:8]} belong to none of the sweep's sensors "
                         f"({', '.join(m.name for m in mounts)})")
    orig = (split(cloud.recorded, recorded=False) if recorded and cloud.recorded is not None
            and RING in cloud.recorded.fields else None)
    origin_m = cloud.profile.sensor_origin_m
    parts = []
    for k, mount in enumerate(mounts):
        rows = np.flatnonzero(owner == k)
        rotation, translation = _pose(mount, origin_m)
        take = {name: np.take(v, rows, axis=0) for name, v in cloud.fields.items()}
        take[RING] = (take[RING] - mount.first_ring).astype(take[RING].dtype)
        attributes = {name: np.take(v, rows, axis=0) for name, v in cloud.attributes.items()}
        if RING in attributes:
            attributes[RING] = (attributes[RING] - mount.first_ring).astype(attributes[RING].dtype)
        part = cloud.replace(positions_m=(np.take(cloud.positions_m, rows, axis=0) - translation) @ rotation,
                             fields=take, attributes=attributes, origin=None, effect=None, profile=mount.profile,
                             recorded=None if orig is None else orig[k].cloud)
        parts.append(Part(mount, rows, part))
    return parts


def merge(cloud: PointCloud, parts: list[Part], outputs: list[PointCloud]) -> PointCloud:
    """The step's output of the sweep ``cloud`` from each sensor's ``outputs`` (of the ``parts`` :func:`split` gave):
    rows in the sweep's frame, rings and order with step-relative ``origin`` and ``effect`` (module doc)."""
    positions, fields, attributes, origin, effect, mounts = [], [], [], [], [], []
    for part, out in zip(parts, outputs):
        rotation, translation = _pose(part.mount, cloud.profile.sensor_origin_m)
        local = np.arange(len(out)) if out.origin is None else out.origin
        kept = local >= 0
        source = np.where(kept, part.rows[np.maximum(local, 0)], NEW)
        q, before = out.positions_m, np.take(part.cloud.positions_m, np.maximum(local, 0), axis=0)
        p = q @ rotation.T + translation
        same = np.flatnonzero(kept & (q[:, 0] == before[:, 0]) & (q[:, 1] == before[:, 1]) & (q[:, 2] == before[:, 2]))
        p[same] = np.take(cloud.positions_m, source[same], axis=0)     # a row that did not move: the input's
        positions.append(p)
        f = dict(out.fields)
        f[RING] = (f[RING] + part.mount.first_ring).astype(f[RING].dtype)
        fields.append(f)
        a = dict(out.attributes)
        if RING in a:
            a[RING] = (a[RING] + part.mount.first_ring).astype(a[RING].dtype)
        attributes.append(a)
        origin.append(source)
        effect.append(np.full(len(out), KEPT) if out.effect is None else out.effect)
        mounts.append(dataclasses.replace(part.mount, profile=out.profile))
    source = np.concatenate(origin)
    order = _sweep_order(cloud, source, np.concatenate([f[TIME_FIELD] for f in fields])
                         if all(TIME_FIELD in f for f in fields) else None)

    def ordered(arrays):
        return np.take(np.concatenate(arrays), order, axis=0)

    stacked = {k: ordered([f[k] for f in fields]) for k in fields[0]}
    carried = {k: ordered([a[k] for a in attributes]) for k in attributes[0] if all(k in a for a in attributes)}
    profile = dataclasses.replace(cloud.profile, sensors=tuple(mounts))
    return cloud.replace(positions_m=ordered(positions), fields=stacked, attributes=carried,
                         origin=np.take(source, order), effect=ordered(effect), profile=profile)


def _sweep_order(cloud: PointCloud, source: np.ndarray, time: np.ndarray | None) -> np.ndarray:
    """The order of the merged rows: the input's rows (``source`` ≥ 0) in their order, each new row (NEW) after the
    last of them whose ``time`` is not later than its own when the input's times never decrease, else at the end
    (sensor by sensor, in their order). O(N) but for sorting the new rows."""
    old = np.flatnonzero(source >= 0)
    present = np.zeros(len(cloud), np.int64)
    present[source[old]] = 1
    rank = (np.cumsum(present) - 1)[source[old]]                # each input row's place among those kept
    new = np.flatnonzero(source < 0)
    at = np.empty(len(source), np.int64)
    if len(new):
        by_rank = np.empty(len(old), np.int64)
        by_rank[rank] = old
        times = None if time is None else time[by_rank]
        if times is not None and (np.diff(times) >= 0).all():
            after = np.searchsorted(times, time[new], side="right")     # input rows before each new row
            new = new[np.argsort(after, kind="stable")]
            after = np.sort(after)
        else:
            after = np.full(len(new), len(old))
        at[new] = after + np.arange(len(new))
        at[old] = rank + np.cumsum(np.bincount(after, minlength=len(old) + 1))[rank]     # new rows before each
    else:
        at[old] = rank
    order = np.empty(len(source), np.int64)
    order[at] = np.arange(len(source))
    return order


def apply_per_sensor(model, given: PointCloud, *, seed: int, key: str, step: int,
                     sequence_id: str) -> tuple[PointCloud, dict, dict, dict]:
    """One chain step on a merged sweep, sensor by sensor (module doc): (the merged output, the drawn sequence state
    and frame values per sensor, the diagnostics)."""
    from .compound import apply_step

    parts = split(given)
    outputs, states, drawn, diagnostics = [], {}, {}, {}
    for part in parts:
        name = part.mount.name
        out, state, values, diagnostics[name] = apply_step(model, part.cloud, part.cloud, seed=seed, key=key,
                                                           step=step, sequence_id=sequence_id, sensor=(name,))
        diagnostics[name] = {**diagnostics[name], "sensor_frame": f"{name} of {part.mount.source}"}
        outputs.append(out)
        if state:
            states[name] = state
        if values:
            drawn[name] = values
    return merge(given, parts, outputs), states, drawn, summed(diagnostics)


def summed(per_sensor: dict[str, dict]) -> dict:
    """Diagnostics of a step over the sensors: each integer count summed, a value every sensor reports alike kept,
    texts that differ joined (``up_lidar: …; down_lidar: …``), and each sensor's own under ``sensors``."""
    first, *others = per_sensor.values()
    out = {}
    for k, v in first.items():
        values = [v] + [d.get(k) for d in others]
        if k not in PER_SENSOR and all(isinstance(x, int) and not isinstance(x, bool) for x in values):
            out[k] = sum(values)
        elif all(x == v for x in values[1:]) and isinstance(v, (str, int, float, bool)):
            out[k] = v
        elif all(isinstance(x, str) for x in values):
            out[k] = "; ".join(f"{name}: {x}" for name, x in zip(per_sensor, values))
    out["sensors"] = per_sensor
    return out
