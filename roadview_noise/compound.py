"""Compound noise: chains of models ordered by stage (D3.5 Eq. 1–3) and the table of the 30 CNFs (Table 6).

A CNF is a named two-step chain per sensor; the stage of each model puts it before (Eq. 1), inside (Eq. 2,
MODIFIER) or after (Eq. 3) the weather. Model defaults are the D3.5 values for their sensor, so a CNF needs no
parameters of its own.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

from .errors import ModelError, RecipeError
from .model import Model, Scope, Stage
from .provenance import follow, step_input
from .registry import get_model, known
from .seeding import derive_rng
from .types import PointCloud, SensorData, sensor_kind

if TYPE_CHECKING:
    from .metrics import Deferred


@dataclass(frozen=True)
class Cnf:
    """One row of D3.5 Table 6: the model ids per sensor, in physical order."""

    factor: str
    weather: str
    method: str                                  # "Eq. 1" | "Eq. 2" | "Eq. 3"
    chains: dict[str, tuple[str, ...]]           # sensor → model ids


def _cnf_table() -> dict[str, Cnf]:
    weathers = ("rain", "fog", "snow")
    rows: list[tuple[str, str, dict[str, str]]] = [
        ("lens soiling (mud)", "Eq. 3", {"camera": "soiling.camera"}),
        ("windscreen distortion", "Eq. 3", {"camera": "windscreen.camera"}),
        ("motion blur", "Eq. 3", {"camera": "motion_blur.camera"}),
        ("lossy compression (JPEG)", "Eq. 3", {"camera": "compression.camera"}),
        ("low light", "Eq. 1", {"camera": "low_light.camera"}),
        ("wind", "Eq. 2", {"camera": "wind.camera"}),
        ("laser alignment error", "Eq. 1", {"lidar": "alignment.lidar"}),
        ("laser power variance", "Eq. 1", {"lidar": "power.lidar"}),
        ("occlusion / obstruction", "Eq. 3", {"lidar": "occlusion.lidar", "radar": "occlusion.radar"}),
        ("ray drop", "Eq. 1", {"lidar": "ray_drop.lidar"}),
    ]
    table = {}
    n = 0
    for factor, method, factor_models in rows:
        for weather in weathers:
            n += 1
            chains = {}
            for sensor, fm in factor_models.items():
                w = f"{weather}.{sensor}"
                chains[sensor] = (w, fm) if method == "Eq. 3" else (fm, w)
            table[f"CNF{n:02d}"] = Cnf(factor, weather, method, chains)
    return table


CNFS: dict[str, Cnf] = _cnf_table()


def cnf_chain(name: str, sensor: str | None = None) -> tuple[str, ...]:
    """Model ids of a CNF for ``sensor`` (may be omitted when the CNF has one sensor)."""
    key = name.upper()
    if key not in CNFS:
        from .registry import suggest
        raise RecipeError(f"unknown CNF {name!r}{suggest(key, CNFS)}; CNF01–CNF30 exist", key="cnf")
    chains = CNFS[key].chains
    if sensor is None:
        if len(chains) > 1:
            raise RecipeError(f"{key} exists for {', '.join(chains)}; say which with `sensor:`", key="sensor")
        return next(iter(chains.values()))
    if sensor not in chains:
        raise RecipeError(f"{key} has no {sensor} variant (has {', '.join(chains)})", key="sensor")
    return chains[sensor]


def order_chain(model_ids: Sequence[str], *, as_written: bool = False, where: str = "chain") -> tuple[str, ...]:
    """Validate a chain and return it in physical order.

    Refuses (``RecipeError``): unknown or unfinished models, mixed sensors, the same model twice, a modifier
    without a weather model after it, and — unless ``as_written`` — an order that contradicts the stages."""
    planned = {m for cnf in CNFS.values() for ids in cnf.chains.values() for m in ids}
    classes = []
    for i, mid in enumerate(model_ids):
        if mid in planned and not known(mid):
            raise RecipeError(f"model {mid!r} is not implemented yet (`rvnoise list` marks the CNFs that run)",
                              key=f"{where}[{i}].model")
        try:
            classes.append(get_model(mid))
        except ModelError as e:
            raise RecipeError(str(e), key=f"{where}[{i}].model") from None
    sensors = {c.sensor for c in classes}
    if len(sensors) > 1:
        raise RecipeError(f"a chain acts on one sensor, got models for {', '.join(sorted(sensors))}", key=where)
    if len(set(model_ids)) != len(model_ids):
        raise RecipeError("a model appears twice in the chain", key=where)
    ordered = sorted(range(len(classes)), key=lambda i: classes[i].stage)  # stable: equal stages keep order
    if not as_written and ordered != list(range(len(classes))):
        want = " → ".join(model_ids[i] for i in ordered)
        raise RecipeError(f"order contradicts the sensing chain (physical order: {want}); "
                          "reorder it, or say `order: as_written` to force it", key=where)
    for i, c in enumerate(classes):
        if c.stage == Stage.MODIFIER and not any(d.stage == Stage.MEDIUM for d in classes[i + 1:]):
            raise RecipeError(f"{c.id} modifies the weather model and needs one after it in the chain",
                              key=f"{where}[{i}]")
    return tuple(model_ids)


@dataclass
class StepRecord:
    """What the manifest keeps of one step."""

    model: str
    params: dict[str, Any]
    state: dict[str, Any] = field(default_factory=dict)
    drawn: dict[str, Any] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    metrics: dict[str, Any] = field(default_factory=dict)     # metrics.compare(step input, step output)

    def as_entry(self) -> dict[str, Any]:
        """The manifest's dict of this step: what ``dataclasses.asdict`` gives (a dataclass inside a value becomes a
        dict, containers are rebuilt) without its deep copy of every leaf value: the entry is encoded as it is and
        nothing changes the step's values later (the copy cost ≈ 0.1 ms per radar file, issue 19); the metrics are
        handed on as they are (the flat dict of JSON-ready values :func:`metrics.compare` returned)."""
        return {"model": self.model, "params": _plain(self.params), "state": _plain(self.state),
                "drawn": _plain(self.drawn), "diagnostics": _plain(self.diagnostics), "seconds": self.seconds,
                "metrics": self.metrics}


_LEAVES = (str, int, float, bool, type(None))
_LEAF_TYPES = frozenset(_LEAVES)


def _plain(value: Any) -> Any:
    """``value`` as ``dataclasses.asdict`` would convert it, its leaves not copied."""
    if isinstance(value, _LEAVES):
        return value
    if isinstance(value, dict):            # a leaf is taken as it is without a call (most of a step's values are)
        return {k: v if type(v) in _LEAF_TYPES else _plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, tuple):
        return tuple(_plain(v) for v in value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return value


def apply_step(model: Model, data: SensorData, given: SensorData, *, seed: int, key: str, step: int,
               sequence_id: str, sensor: tuple = ()) -> tuple[SensorData, dict, dict, dict]:
    """One model on one input: (output, sequence state, frame values, diagnostics). The state is drawn from
    ``derive_rng(seed, "sequence", sequence_id, model.id, *sensor)`` and ``data``, the frame's values and the model's
    own draws from ``derive_rng(seed, key, step, model.id, *sensor)``; ``given`` is what the model applies to
    (:func:`provenance.step_input` of ``data``); ``sensor``: a sensor's name in a sweep of several
    (:mod:`.sensor_rig`)."""
    state = {}
    if model.scope == Scope.SEQUENCE:
        state = model.draw_sequence(derive_rng(seed, "sequence", sequence_id, model.id, *sensor), data)
    rng = derive_rng(seed, key, step, model.id, *sensor) if model.uses_frame_rng else None
    drawn = model.draw(rng, data)
    out, diagnostics = model.apply(given, state=state, drawn=drawn, rng=rng)
    return out, state, drawn, diagnostics


def apply_models(models: Sequence[Model], data: SensorData, *, seed: int, key: str,
                 sequence_id: str, metrics: bool = True,
                 deferred: Deferred | None = None) -> tuple[SensorData, list[StepRecord]]:
    """Run instantiated models in order on one frame or cloud.

    Frame rng: ``derive_rng(seed, key, step_index, model.id)``; sequence (sensor-instance) rng:
    ``derive_rng(seed, "sequence", sequence_id, model.id)``. ``key`` identifies the output (input relpath plus
    sweep variant). The result carries its provenance relative to ``data`` (:mod:`roadview_noise.provenance`): each
    step gets a cloud with step-relative origin and effect, :func:`provenance.follow` composes them; a camera frame
    collects the warps of geometric steps. ``metrics``: record :func:`metrics.compare` of each step's
    input and output (models that write every position count its return geometry on the way:
    :mod:`~roadview_noise.physics.return_ranges`); with ``deferred`` (:class:`metrics.Deferred`), the last
    step's are filled in by its ``settle`` (each earlier step's when the next step has run: its JPEG encode may
    keep the frame's luminance). Each later step's cloud notes the chain's input as ``recorded`` (the sensor's own
    data), for the steps that calibrate the sensor on it. A ring-less cloud stored laser by laser (KITTI) first gets its rings
    and firing columns from that order (:func:`~roadview_noise.physics.laser_order.with_laser_order`); a sweep of several
    sensors runs each step sensor by sensor (:func:`sensor_rig.apply_per_sensor`)."""
    from .metrics import Deferred          # numba: only where a chain runs, not where recipes are checked
    from .physics import return_ranges
    from .sensor_rig import apply_per_sensor, sensors_of

    pending = deferred if deferred is not None else Deferred()
    return_ranges.collect(metrics)         # models note the return geometry of the clouds they write

    records = []
    if isinstance(data, PointCloud) and data.sensor == "lidar":     # imported by LiDAR workers only (≈ 7 ms)
        from .physics.laser_order import with_laser_order

        data = with_laser_order(data)
    recorded = data if isinstance(data, PointCloud) and data.recorded is None else None
    for i, model in enumerate(models):
        if model.sensor != sensor_kind(data):
            raise ModelError(f"acts on {model.sensor} data, got {sensor_kind(data)} data", model=model.id)
        t0 = time.perf_counter()
        given = step_input(data)
        if recorded is not None and given is not recorded and given.recorded is None:
            given = given.replace(recorded=recorded)
        if sensors_of(data):                    # a sweep of several sensors: each on its own rays (sensor_rig.py)
            out, state, drawn, diagnostics = apply_per_sensor(model, given, seed=seed, key=key, step=i,
                                                              sequence_id=sequence_id)
        else:
            out, state, drawn, diagnostics = apply_step(model, data, given, seed=seed, key=key, step=i,
                                                        sequence_id=sequence_id)
        before, data = data, follow(data, out, model, state=state, drawn=drawn, step=i)
        records.append(StepRecord(model.id, model.params(), state, drawn, diagnostics, time.perf_counter() - t0,
                                  pending.compare(before, data, out, linked=len(models) > 1) if metrics else {}))
        pending.settle(keep=data)
    if deferred is None:
        pending.settle()
    return data, records
