"""Bag recipes: which topics of a ROS bag are which sensor instances (with their profiles), and one chain per sensor.

A bag recipe is a recipe (``recipe.py``) with a ``topics:`` mapping; each mapped topic is one sensor instance.
Chains for several sensors at once:

- ``chains: {camera: CNF16, lidar: CNF20, radar: [{model: rain.radar}, ...]}`` — per sensor a CNF name or a list of
  steps (as ``chain:``), or
- ``cnf: CNF25`` (no ``sensor:``) — the CNF's chain for every sensor the topics map (an error when it has none for
  one of them), or a single-sensor ``cnf:`` + ``sensor:`` / ``chain:`` when every topic is that sensor.

``params:`` go to the chain holding the model; ``order:``, ``seed:``, ``output:`` apply to all chains. ``inputs:``
and ``sweep:`` are file-tree keys and refused (inputs are given per topic; one run writes one bag). Unmapped topics
are copied through unchanged.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError

from .errors import ModelError, RecipeError
from .recipe import (GroundPlaneSpec, InputsSpec, OnnxDepthSpec, Recipe, RecipeSpec, Variant, _loc, _Strict,
                     parse_recipe)
from .registry import get_model, suggest

SENSORS = ("camera", "lidar", "radar")
BAG_KEYS = ("topics", "chains")
_PER_SENSOR = {"camera": ("camera_profile", "camera_fov_h_deg", "camera_info_topic", "camera_info_matrix",
                          "depth_source", "depth_topic", "depth_kind", "depth_holes", "onnx_depth", "ground_plane",
                          "black_level_dn", "white_level_dn"),
               "lidar": ("lidar_profile", "intensity_unit", "intensity_full_scale", "field_map"),
               "radar": ("radar_profile", "field_map")}


class TopicSpec(_Strict):
    """One mapped topic: its sensor, profile and how to read it (see README "ROS bags")."""

    sensor: Literal["camera", "lidar", "radar"]
    camera_profile: str | dict[str, Any] | None = None
    camera_fov_h_deg: float | None = Field(None, gt=0, lt=180)  # without a profile: square pixels, centred
    camera_info_topic: str | None = None                       # default: <namespace>/camera_info (bag_camera_info)
    camera_info_matrix: Literal["K", "P"] | None = None        # default: P for image_rect*, else K
    lidar_profile: str | dict[str, Any] | None = None
    radar_profile: str | dict[str, Any] | None = None
    depth_source: Literal["topic", "onnx", "ground_plane"] = "topic"   # topic: depth_topic (the file source's role)
    depth_topic: str | None = None                             # aligned depth Image (same header stamp)
    depth_kind: Literal["planar", "range"] = "planar"          # REP 118 depth images are planar z
    depth_holes: Literal["fill", "sky", "error"] = "fill"      # as inputs.depth_holes
    onnx_depth: OnnxDepthSpec | None = None
    ground_plane: GroundPlaneSpec = Field(default_factory=GroundPlaneSpec)
    black_level_dn: float | None = None                        # Bayer Image levels (default 0 … 2^bits − 1)
    white_level_dn: float | None = Field(default=None, gt=0)
    intensity_unit: Literal["photons", "uint8", "unit"] | None = None
    intensity_full_scale: float | None = Field(default=None, gt=0)
    field_map: dict[str, str] = Field(default_factory=dict)
    ego_velocity_m_per_s: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class BagTopic:
    """A mapped topic: its spec, the sensor instance id shared by its messages, and its chain with its inputs."""

    name: str
    spec: TopicSpec
    recipe: Recipe

    @property
    def sensor(self) -> str:
        return self.spec.sensor

    @property
    def sequence_id(self) -> str:
        return topic_folder(self.name)


@dataclass(frozen=True)
class BagRecipe:
    source: str
    base_dir: Path
    chains: dict[str, Recipe]            # sensor → chain
    topics: dict[str, BagTopic]

    @property
    def seed(self) -> int:
        return next(iter(self.chains.values())).seed

    def resolved_dict(self) -> dict[str, Any]:
        """The recipe as run: explicit steps per sensor with their parameters (what replay re-reads)."""
        first = next(iter(self.chains.values())).resolved_dict()
        d = {k: first[k] for k in ("schema", "description", "seed", "output")}
        d["order"] = "as_written"
        d["chains"] = {s: r.resolved_dict()["chain"] for s, r in self.chains.items()}
        d["topics"] = {t: bt.spec.model_dump(mode="json", exclude_defaults=True) for t, bt in self.topics.items()}
        return d

    def sha256(self) -> str:
        return hashlib.sha256(json.dumps(self.resolved_dict(), sort_keys=True).encode()).hexdigest()


def topic_folder(topic: str) -> str:
    """A topic's folder in an exported tree, and its sensor-instance id: the name without its leading slash."""
    return topic.strip("/")


def is_bag_recipe(data: Any) -> bool:
    return isinstance(data, dict) and "topics" in data


def parse_bag_recipe(data: Any, *, source: str = "<recipe>", base_dir: Path | None = None,
                     chains_required: bool = True) -> BagRecipe:
    """Validate a bag recipe; RecipeError names the file and the key path. Without ``chains_required`` a recipe
    may give topics only (``rvnoise export``): their chains are then empty."""
    if not is_bag_recipe(data):
        raise RecipeError("a bag recipe maps topics to sensors under `topics:`", file=source)
    rest = {k: v for k, v in data.items() if k not in BAG_KEYS}
    for key, why in (("inputs", "inputs are given per topic under `topics:`"),
                     ("sweep", "a run writes one bag; run once per value instead")):
        if key in rest:
            raise RecipeError(f"not allowed in a bag recipe: {why}", file=source, key=key)
    topic_specs = _topic_specs(data["topics"], source)
    sensors = sorted({t.sensor for t in topic_specs.values()}, key=SENSORS.index)
    if chains_required or any(k in data for k in ("chains", "cnf", "chain")):
        chains = _chains(data.get("chains"), rest, sensors, source, base_dir)
    else:
        try:
            spec = RecipeSpec.model_validate({k: v for k, v in rest.items() if k != "params"})
        except ValidationError as e:
            raise RecipeError(e.errors()[0]["msg"], file=source, key=_loc(e.errors()[0]["loc"])) from None
        chains = {s: Recipe(spec, source, base_dir or Path.cwd(), (), (), (Variant("", {}),)) for s in sensors}
    topics = {}
    for name, spec in topic_specs.items():
        chain = chains[spec.sensor]
        recipe = dataclasses.replace(chain, spec=chain.spec.model_copy(update={"inputs": _inputs(spec, name, source)}))
        if spec.sensor == "camera" and spec.depth_source == "topic" and spec.depth_topic is None and \
                recipe.needs_depth():
            needing = ", ".join(m for m in recipe.model_ids if get_model(m).needs_depth)
            raise RecipeError(f"the camera chain needs depth ({needing}): give depth_topic (an aligned depth Image), "
                              "or depth_source: onnx (with onnx_depth) or ground_plane", file=source,
                              key=f"topics.{name}")
        topics[name] = BagTopic(name, spec, recipe)
    return BagRecipe(source, base_dir or Path.cwd(), chains, topics)


def _inputs(spec: TopicSpec, name: str, source: str) -> InputsSpec:
    """A topic's settings as the ``inputs`` of its chain (the depth topic plays the role of the ``file`` depth
    source)."""
    keys = ("camera_profile", "camera_fov_h_deg", "depth_kind", "depth_holes", "onnx_depth", "ground_plane",
            "lidar_profile", "radar_profile", "intensity_unit", "intensity_full_scale", "field_map",
            "ego_velocity_m_per_s")
    values = {k: getattr(spec, k) for k in keys if getattr(spec, k) is not None}
    values["depth_source"] = "file" if spec.depth_source == "topic" else spec.depth_source
    try:
        return InputsSpec.model_validate(values)
    except ValidationError as e:
        raise RecipeError(e.errors()[0]["msg"].removeprefix("Value error, "), file=source,
                          key=f"topics.{name}") from None


def load_bag_recipe(path: str | Path) -> BagRecipe:
    path = Path(path)
    return parse_bag_recipe(read_recipe_yaml(path), source=str(path), base_dir=path.resolve().parent)


def read_recipe_yaml(path: Path) -> Any:
    try:
        return yaml.safe_load(path.read_text())
    except OSError as e:
        raise RecipeError(f"cannot read recipe ({e.strerror})", file=str(path)) from None
    except yaml.YAMLError as e:
        raise RecipeError(f"not valid YAML: {e}", file=str(path)) from None


def _topic_specs(raw: Any, source: str) -> dict[str, TopicSpec]:
    if not isinstance(raw, dict) or not raw:
        raise RecipeError("`topics:` maps topic names to {sensor: camera|lidar|radar, ...}", file=source,
                          key="topics")
    specs = {}
    for name, value in raw.items():
        key = f"topics.{name}"
        if not isinstance(name, str) or not name.startswith("/"):
            raise RecipeError(f"topic names start with '/', got {name!r}", file=source, key=key)
        try:
            spec = TopicSpec.model_validate(value if isinstance(value, dict) else {"sensor": value})
        except ValidationError as e:
            err = e.errors()[0]
            where = f"{key}.{_loc(err['loc'])}" if err["loc"] else key
            if err["type"] == "extra_forbidden":
                bad = str(err["loc"][-1])
                raise RecipeError(f"unknown key {bad!r}{suggest(bad, list(TopicSpec.model_fields))}", file=source,
                                  key=where) from None
            raise RecipeError(err["msg"], file=source, key=where) from None
        foreign = [k for s, keys in _PER_SENSOR.items() if s != spec.sensor for k in keys
                   if k in spec.model_fields_set and k not in _PER_SENSOR[spec.sensor]]
        if foreign:
            raise RecipeError(f"{foreign[0]!r} is not a key of a {spec.sensor} topic", file=source,
                              key=f"{key}.{foreign[0]}")
        specs[name] = spec
    for name, spec in specs.items():
        if spec.camera_info_topic is not None and not spec.camera_info_topic.startswith("/"):
            raise RecipeError(f"topic names start with '/', got {spec.camera_info_topic!r}", file=source,
                              key=f"topics.{name}.camera_info_topic")
        stated = [k for k in ("camera_profile", "camera_fov_h_deg") if getattr(spec, k) is not None]
        if stated and (spec.camera_info_topic or spec.camera_info_matrix):
            raise RecipeError(f"give {stated[0]} or the intrinsics of a CameraInfo topic, not both (a stated "
                              "profile wins over the bag's CameraInfo)", file=source, key=f"topics.{name}.{stated[0]}")
        if spec.depth_topic is not None and spec.depth_topic in specs:
            raise RecipeError(f"depth topic {spec.depth_topic!r} is itself mapped to a sensor", file=source,
                              key=f"topics.{name}.depth_topic")
    return specs


def _chains(chains: Any, rest: dict, sensors: list[str], source: str, base_dir: Path | None) -> dict[str, Recipe]:
    """One Recipe per mapped sensor (module docstring), each validated by :func:`parse_recipe`."""
    single = [k for k in ("cnf", "chain", "sensor") if k in rest]
    if chains is not None:
        if single:
            raise RecipeError(f"give `chains:` or `{single[0]}:`, not both", file=source, key=single[0])
        if not isinstance(chains, dict) or not chains:
            raise RecipeError("`chains:` maps sensors to a CNF name or a list of steps", file=source, key="chains")
        for sensor in chains:
            if sensor not in SENSORS:
                raise RecipeError(f"unknown sensor {sensor!r}{suggest(str(sensor), SENSORS)}", file=source,
                                  key=f"chains.{sensor}")
            if sensor not in sensors:
                raise RecipeError(f"no topic maps to {sensor}", file=source, key=f"chains.{sensor}")
        per_sensor = {s: ({"cnf": v, "sensor": s} if isinstance(v, str) else {"chain": v}) for s, v in chains.items()}
    elif "cnf" in rest and "sensor" not in rest:
        per_sensor = {s: {"cnf": rest["cnf"], "sensor": s} for s in sensors}
    elif single:
        per_sensor = {s: {k: rest[k] for k in single} for s in sensors}
    else:
        raise RecipeError("give `chains:` (a CNF or steps per sensor) or `cnf:`", file=source)
    missing = [s for s in sensors if s not in per_sensor]
    if missing:
        raise RecipeError(f"topics map to {missing[0]} but `chains:` has no {missing[0]} chain", file=source,
                          key="chains")
    params = rest.get("params") or {}
    owner = {}
    for model_id in params:
        try:
            owner[model_id] = get_model(model_id).sensor
        except ModelError as e:
            raise RecipeError(str(e), file=source, key=f"params.{model_id}") from None
    common = {k: v for k, v in rest.items() if k not in ("cnf", "chain", "sensor", "params")}
    out = {}
    for sensor, chain in per_sensor.items():
        sub = {**common, **chain, "params": {m: p for m, p in params.items() if owner[m] == sensor}}
        try:
            out[sensor] = parse_recipe(sub, source=source, base_dir=base_dir)
        except RecipeError as e:
            key = _chain_key(e.key, sensor, chains is not None)
            key = "cnf" if key == "sensor" and "sensor" not in rest else key
            raise RecipeError(e.message, file=source, key=key) from None
        if out[sensor].sensor != sensor:
            raise RecipeError(f"topics map to {sensor} but the chain acts on {out[sensor].sensor}; give `chains:` "
                              "per sensor", file=source, key="chains" if chains is not None else single[0])
    unused = [m for m, s in owner.items() if s not in out]
    if unused:
        raise RecipeError(f"{unused[0]!r} acts on {owner[unused[0]]}, which no topic maps", file=source,
                          key=f"params.{unused[0]}")
    return out


def _chain_key(key: str | None, sensor: str, per_sensor: bool) -> str | None:
    """The key path of an error inside one sensor's chain, as written in the bag recipe."""
    if not per_sensor or key is None:
        return key
    if key.startswith("chain"):
        return f"chains.{sensor}{key[len('chain'):]}"
    return f"chains.{sensor}" if key in ("cnf", "sensor") else key

