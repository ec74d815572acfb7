"""Point provenance: which input point every output point descends from, what the chain did to it, and what the
chain knows about it — so that per-point annotations (labels, sidecars) follow every model with one gather.

A :class:`~roadview_noise.types.PointCloud` carries, besides the ``fields`` a writer puts in the file:

- ``origin``: int64 (N,), index of the point it descends from (:data:`NEW` = −1: a point without one, e.g. a weather
  return on an empty ray of a point list or a radar clutter point). ``None`` is the identity (point i descends from
  point i). A return moved along its ray to a particle (MOVED), and a grid cell that gained a weather return
  (ADDED), keep the origin of their ray: its sensor fields (ring, time stamp) and attributes are theirs, while the
  effect code says they show a particle, not the input's object.
- ``effect``: uint8 (N,), an :class:`Effect` code; ``None``: no step has reported effects (every point KEPT).
- ``attributes``: per-point arrays the chain knows but does not write (a ``ring`` recovered by an earlier step, a
  firing-grid cell …), so later steps use them instead of re-deriving them from coordinates an earlier step moved.

Inside a model, ``origin`` and ``effect`` are relative to the cloud the model received: :func:`compound.apply_models
<roadview_noise.compound.apply_models>` hands every step a cloud with ``origin = effect = None`` and composes the
step's result with what came before (:func:`follow`), so after the chain ``origin`` indexes the chain's *input* and
``effect`` sums up every step. ``attributes`` are not reset: they travel through every step.

What a model does: nothing, if it keeps its points (same N, same order) or uses :meth:`PointCloud.select`,
:meth:`~PointCloud.drop` and :meth:`~PointCloud.concat` (they keep ``fields``, ``origin``, ``effect`` and
``attributes`` aligned: select gathers, drop deletes from a list or zeroes a grid cell (REMOVED), concat appends
NEW points marked ADDED). A model that builds its output otherwise (``physics.lidar_output.assemble``) sets ``origin``
and ``effect`` itself and gathers ``attributes`` by the same index as its fields. A model that marks effects on
points it keeps calls :func:`mark`.
"""

from __future__ import annotations

import dataclasses
from enum import IntEnum

import cv2
import numpy as np

from .types import CameraFrame, PointCloud, RawFrame

NEW = -1                                 # origin of a point that descends from no input point
MADE_BY_STEP = "made_by_step"            # attribute set by the chain: step that made a point new (see follow)


class Effect(IntEnum):
    """What the chain did to a point: the ``rv_effect`` field (uint8) of written clouds.

    Codes compose over a chain by severity (:func:`combine`): a point attenuated by one step and kept by the next
    stays ATTENUATED; MOVED and ADDED mark points that show a weather particle or clutter, not the input's object,
    so annotations give them the weather class (:mod:`roadview_noise.annotations`)."""

    KEPT = 0          # the input's return, intensity changed by less than half a resolution step of the file
    ATTENUATED = 1    # the input's return in place, intensity/SNR reduced
    MOVED = 2         # the ray's return moved along it to a weather particle (soft-target return): a new point
    ADDED = 3         # a new point: weather return on an empty ray, radar clutter
    REMOVED = 4       # a full grid's cell whose return was lost (zeroed; in a point list removal is absence)


KEPT, ATTENUATED, MOVED, ADDED, REMOVED = (np.uint8(e) for e in Effect)


def is_new(effect: np.ndarray) -> np.ndarray:
    """Points that show a particle or clutter, not the input's object: MOVED or ADDED."""
    return (effect - MOVED) <= (ADDED - MOVED)          # uint8 wrap-around: one subtraction, one comparison


def combine(before: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Effect of a step on a point that already had ``before``: a step that makes the point new (MOVED, ADDED) sets
    it; otherwise the more severe code stays (KEPT < ATTENUATED < MOVED < ADDED < REMOVED)."""
    return np.where(is_new(step), step, np.maximum(before, step))


def mark(cloud: PointCloud, mask: np.ndarray, effect: Effect) -> PointCloud:
    """The cloud with ``effect`` combined into the masked points' codes (other points keep theirs)."""
    if cloud.effect is None:                            # every code KEPT, and combine(KEPT, e) = e
        return cloud.replace(effect=np.where(mask, np.uint8(effect), KEPT))
    out = cloud.effect.copy()
    idx = np.flatnonzero(mask)                          # unmasked points keep theirs: combine(c, KEPT) = c
    out[idx] = combine(out[idx], np.full(len(idx), np.uint8(effect)))
    return cloud.replace(effect=out)


def gather(values: np.ndarray, origin: np.ndarray, fill=0) -> np.ndarray:
    """``values[origin]`` with ``fill`` where origin is NEW."""
    out = np.asarray(values)[np.maximum(origin, 0)]
    new = origin < 0
    if new.any():
        out[new] = fill
    return out


def identity(n: int) -> np.ndarray:
    return np.arange(n, dtype=np.int64)


def step_input(cloud: PointCloud) -> PointCloud:
    """The cloud a chain step receives: origin and effect reset to the identity (step-relative), the chain's own
    :data:`MADE_BY_STEP` bookkeeping left out; attributes kept. Frames pass unchanged."""
    if not isinstance(cloud, PointCloud) or (cloud.origin is None and cloud.effect is None
                                             and MADE_BY_STEP not in cloud.attributes):
        return cloud
    attributes = {k: v for k, v in cloud.attributes.items() if k != MADE_BY_STEP}
    return cloud.replace(origin=None, effect=None, attributes=attributes)


def follow(before, after, model, *, state: dict, drawn: dict, step: int):
    """What the chain adds to a step's output: for clouds the composed point provenance (:func:`follow_points`),
    for camera frames the step's :class:`~roadview_noise.physics.warp.Warp` (``Model.warp``) appended to
    ``warps``, so masks and boxes move with the image, and the file's alpha plane resampled through it (beyond the
    input's border it takes the nearest edge's alpha: a uniform plane, CARLA's, stays as it was)."""
    if isinstance(after, (CameraFrame, RawFrame)):
        warp = model.warp(before, state=state, drawn=drawn)
        if warp is None:
            return after
        alpha = getattr(after, "alpha", None)
        moved = {} if alpha is None else {"alpha": warp.apply(alpha, border=cv2.BORDER_REPLICATE)}
        return dataclasses.replace(after, warps=(*after.warps, warp), **moved)
    return follow_points(before, after, step, model.id)


def follow_points(before: PointCloud, after: PointCloud, step: int, model_id: str = "") -> PointCloud:
    """Compose the step-relative provenance of ``after`` (a step's output) with ``before`` (its input, relative to
    the chain input): ``origin = before.origin[after.origin]`` (NEW stays NEW), effects by :func:`combine`, and
    :data:`MADE_BY_STEP`: the step that made each new point new (meaningful where ``effect`` is MOVED/ADDED; a
    constant view while only one step has made new points)."""
    from .errors import ModelError

    o_step, e_step = after.origin, after.effect
    if o_step is None and len(after) != len(before):
        raise ModelError(f"returned {len(after)} points for {len(before)} without saying where they come from "
                         "(PointCloud.origin; use select/drop/concat)", model=model_id)
    o_prev, e_prev = before.origin, before.effect
    if o_step is None:
        origin = o_prev
    elif o_prev is None:
        origin = o_step
    else:
        origin = gather(o_prev, o_step, NEW)
    if e_prev is not None and o_step is not None:
        e_prev = gather(e_prev, o_step, KEPT)
    effect = e_prev if e_step is None else (e_step if e_prev is None else combine(e_prev, e_step))

    made_prev = before.attributes.get(MADE_BY_STEP)
    if made_prev is not None and o_step is not None:
        made_prev = gather(made_prev, o_step, -1)
    made = made_prev
    new = None if e_step is None else is_new(e_step)
    if new is not None and new.any():
        made = (np.broadcast_to(np.int16(step), (len(after),)) if made_prev is None
                else np.where(new, np.int16(step), made_prev).astype(np.int16))
    if origin is o_step and effect is e_step and made is None:
        return after                                   # nothing to compose (a step on a cloud without provenance)
    attributes = dict(after.attributes)
    if made is not None:
        attributes[MADE_BY_STEP] = made
    return after.replace(origin=origin, effect=effect, attributes=attributes)
