"""Recipes: YAML → validated pydantic model → resolved chain, parameter specs and sweep variants.

Unknown keys fail at load with the file, the path of the key and a did-you-mean. Parameter values are fixed or
explicit distributions (``{uniform: [lo, hi]}``, ``{choice: [a, b, ...]}``, ``{normal: [mean, sd]}``) drawn per
output file from ``derive_rng(seed, key, "params", step, model)``. A distribution must stay inside the parameter's
allowed range: uniform bounds and every choice are checked, and a normal is truncated at mean ± 4 sd
(:data:`NORMAL_TAIL_SD`; it changes 6·10⁻⁵ of the draws), so mean ± 4 sd must lie inside the range. Refusing rather
than clipping at the range: clipping would put a silent lump of probability on the bound (e.g. 2 % of the frames at
a rain rate of exactly 0), which the user never asked for; the refusal names the largest sd that fits.

A sweep's variants (the product of its value lists) are computed on demand (:class:`Variants`), so a large sweep
costs nothing at parse time.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_serializer, model_validator

from .annotations import AnnotationsSpec, NuscenesRule, ReplaceRule
from .compound import CNFS, cnf_chain, order_chain
from .errors import ModelError, RecipeError
from .input_checks import check_inputs
from .registry import get_model, known, suggest

SCHEMA = "rvnoise.recipe/1"
DISTRIBUTIONS = ("uniform", "choice", "normal")
NORMAL_TAIL_SD = 4.0

Globs = Union[str, list[str]]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class StepSpec(_Strict):
    model: str
    params: dict[str, Any] = Field(default_factory=dict)


class LidarDepthSpec(_Strict):
    """``depth_source: lidar`` (roadview_noise/depth/lidar.py)."""

    scan: str | None = None                        # paired scan, a pattern like `depth` (None: nuScenes tables)
    densify: Literal["nearest", "bilateral"] = "nearest"
    ground_plane: bool = True                      # flat ground below the lowest return where it fits the returns


class OnnxDepthSpec(_Strict):
    """``depth_source: onnx`` (roadview_noise/depth/monocular.py)."""

    model: str                                     # .onnx file; relative paths: the recipe's folder
    scale_m: float = Field(1.0, gt=0)              # metres per unit of the model's output
    kind: Literal["planar", "range"] = "planar"    # the output is planar z or range along the ray
    input: Literal["srgb", "linear"] = "srgb"
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    layout: Literal["nchw", "nhwc"] = "nchw"


class GroundPlaneSpec(_Strict):
    """``depth_source: ground_plane`` (roadview_noise/depth/ground_plane.py)."""

    camera_height_m: float | None = Field(None, gt=0)   # None: the calibration's, else the camera profile's
    pitch_deg: float | None = Field(None, gt=-90, lt=90)  # > 0 looks down; None: the calibration's, else 0
    sky_distance_m: float = Field(100.0, gt=0)           # at and above the horizon, and the farthest ground
    objects: bool = True              # vertical objects standing on the ground (depth/stixels.py); false: flat only


PHOTO_SUFFIXES_NOT_READ = ("jxl", "jp2", "bmp", "gif", "mpo")


def _photo_codec_missing(suffix: str) -> str | None:
    """Why photos of a glob's ``suffix`` cannot be read on this machine (HEIF/AVIF without the extra), else None."""
    from .io.heif import FORMATS, missing

    fmt = FORMATS.get(f".{suffix}")
    return missing(fmt) if fmt else None


class InputsSpec(_Strict):
    """Which files to read and how (globs relative to the input root). Sidecar patterns (``depth``,
    ``calibration``, ``lidar_depth.scan``) are relative to the image's folder: ``{stem}``, ``{name}``, ``{base}``
    (stem without its last ``_part``), ``{parent}`` (folder name), ``{parts[i]}`` (i-th folder from the root)."""

    camera: Globs | None = None
    raw: Globs | None = None
    # instead of every raw file's own black level (a DNG's wrong or missing BlackLevel): one value, or one per site
    # of the frame's 2×2 CFA, row by row from its top-left site (io/raw.py black_override)
    raw_black_level_dn: Annotated[float, Field(ge=0)] | tuple[Annotated[float, Field(ge=0)], ...] | None = None
    lidar: Globs | None = None
    radar: Globs | None = None
    exclude: list[str] = Field(default_factory=list)
    depth: str | ReplaceRule = "{stem}_depth.exr"   # sidecar pattern (fields: the docstring) or {replace: {a: b}}
    depth_kind: Literal["range", "planar"] = "range"
    depth_format: Literal["auto", "exr", "npy", "carla", "kitti", "cityscapes"] = "auto"
    depth_holes: Literal["fill", "sky", "error"] = "fill"
    depth_source: Literal["file", "lidar", "onnx", "ground_plane"] = "file"
    lidar_depth: LidarDepthSpec | None = None
    onnx_depth: OnnxDepthSpec | None = None
    ground_plane: GroundPlaneSpec = Field(default_factory=GroundPlaneSpec)
    calibration: str | NuscenesRule | None = None   # per-image: Cityscapes .json, KITTI .txt, rvnoise .yaml; or
                                                    # {nuscenes: v1.0-trainval} (the tables' folder under IN/)
    kitti_camera: int = Field(2, ge=0, le=4)   # the camera of a KITTI calibration the images are from (Waymo: 0–4)
    camera_fov_h_deg: float | None = Field(None, gt=0, lt=180)  # without a profile: square pixels, centred
    camera_profile: str | dict[str, Any] | None = None   # built-in, file ({dir} = the input file's folder), mapping
    # transfer function of PNG/TIFF codes whose file states none (no gAMA/sRGB/iCCP/cICP, no ICC): None = sRGB, and
    # 16-bit such files are counted in a warning (machine-vision cameras mostly write linear counts)
    untagged_transfer: Literal["srgb", "linear"] | None = None
    lidar_profile: str | dict[str, Any] | None = None
    radar_profile: str | dict[str, Any] | None = None
    intensity_unit: Literal["photons", "uint8", "unit"] | None = None
    intensity_full_scale: float | None = Field(default=None, gt=0)
    field_map: dict[str, str] = Field(default_factory=dict)  # file field name → canonical name
    bin_fields: tuple[str, ...] | None = None  # a LiDAR .bin's float32 columns when not KITTI's (x y z intensity) or
                                               # nuScenes' .pcd.bin (+ ring): e.g. Waymo's KITTI-format export
    radar_bin_fields: tuple[str, ...] | None = None  # a radar .bin's float32 columns when neither View-of-Delft's
                                                     # nor TJ4DRadSet's (Dual-Radar: 5); io/radar_formats.py
    sequence: Literal["folder", "file"] = "folder"           # sensor instance = input folder (default) or each file
    ego_velocity_m_per_s: tuple[float, float, float] | None = None  # sensor velocity, sensor frame (x fwd, y left)
    annotations: AnnotationsSpec = Field(default_factory=AnnotationsSpec)  # label sidecars, masks, boxes
    # a photo stored turned or mirrored (EXIF/TIFF orientation 2–8): processed upright, as displayed, and written
    # back as stored (roadview_noise/orientation.py); stored: the stored pixels as they are (the earlier behaviour)
    orientation: Literal["upright", "stored"] = "upright"

    @model_serializer(mode="wrap")
    def _dump(self, handler) -> dict[str, Any]:
        """The default ``orientation`` and an unset ``radar_bin_fields`` are left out, so run.json and the recipe's
        sha256 (resume) stay those of a recipe written before the keys existed."""
        d = handler(self)
        if self.orientation == "upright":
            d.pop("orientation", None)
        if self.radar_bin_fields is None:
            d.pop("radar_bin_fields", None)
        return d

    @model_validator(mode="after")
    def _raw_black_level(self) -> "InputsSpec":
        if isinstance(self.raw_black_level_dn, tuple) and len(self.raw_black_level_dn) not in (1, 4):
            raise ValueError(f"raw_black_level_dn has {len(self.raw_black_level_dn)} values: give one, or four (the "
                             "2×2 CFA sites row by row from the frame's top-left site)")
        return self

    @model_validator(mode="after")
    def _camera_suffixes(self) -> "InputsSpec":
        globs = [self.camera] if isinstance(self.camera, str) else self.camera or []
        for glob in globs:
            suffix = glob.rsplit(".", 1)[-1].lower() if "." in glob.rsplit("/", 1)[-1] else ""
            if suffix in PHOTO_SUFFIXES_NOT_READ:
                raise ValueError(f"camera: {glob!r} names .{suffix} files, which rvnoise does not read (camera "
                                 "images: .png .jpg .jpeg .tif .tiff .webp .heic .heif .hif .avif .exr); convert them "
                                 "to PNG or JPEG first")
            why = _photo_codec_missing(suffix)
            if why:
                raise ValueError(f"camera: {glob!r}: {why}")
        return self

    @model_validator(mode="after")
    def _cloud_suffixes(self) -> "InputsSpec":
        """A LiDAR/radar glob whose file suffix is spelled out (``*.npz``, ``*.feather``, ``*.h5``) and that the
        cloud reader would refuse on every file (:func:`io.pointcloud.cloud_format`) is refused here."""
        from .errors import InputError
        from .io.pointcloud import cloud_format

        for sensor in ("lidar", "radar"):
            globs = getattr(self, sensor)
            for glob in [globs] if isinstance(globs, str) else globs or []:
                name = glob.rsplit("/", 1)[-1]
                if "." not in name or any(c in name.rsplit(".", 1)[-1] for c in "*?["):
                    continue
                try:
                    cloud_format(name, sensor)
                except InputError as exc:
                    raise ValueError(f"{sensor}: {glob!r} names files rvnoise does not read: "
                                     f"{str(exc).removeprefix(f'{exc.file}: ')}") from None
        return self

    @model_validator(mode="after")
    def _depth_source_settings(self) -> "InputsSpec":
        for source, key in (("lidar", "lidar_depth"), ("onnx", "onnx_depth")):
            if self.depth_source == source and getattr(self, key) is None:
                raise ValueError(f"depth_source {source} needs `{key}:` (see the README, 'Which depth do I have?')")
        if isinstance(self.depth, str):
            check_pattern(self.depth)
        if isinstance(self.calibration, str):
            check_pattern(self.calibration)
        elif isinstance(self.calibration, NuscenesRule) and self.calibration.table != "lidarseg":
            raise ValueError("calibration: {nuscenes: …} reads the calibration tables; `table:` chooses the label "
                             "table of annotations.point_labels")
        if self.lidar_depth is not None:
            if self.lidar_depth.scan is not None:
                check_pattern(self.lidar_depth.scan)
            elif not isinstance(self.calibration, NuscenesRule):
                raise ValueError("lidar_depth needs `scan:` (a pattern of the paired scan); only "
                                 "`calibration: {nuscenes: …}` pairs the scan itself")
        return self


def check_pattern(pattern: str | None) -> None:
    """ValueError naming the field a sidecar pattern uses that does not exist."""
    if pattern is None:
        return
    try:
        pattern.format(stem="s", name="n", base="b", parent="p", parts=["p"] * 32)
    except (KeyError, IndexError, ValueError, AttributeError, TypeError) as exc:
        raise ValueError(f"pattern {pattern!r}: {exc!r}; its fields are {{stem}}, {{name}}, {{base}}, {{parent}}, "
                         f"{{parts[i]}}") from None


class OutputSpec(_Strict):
    format: Literal["same"] = "same"
    effect: Literal["auto", "none"] = "auto"       # the rv_effect code of clouds (io.pointcloud.write_pointcloud)
    jpeg_quality: int | None = Field(None, ge=1, le=100)  # JPEG outputs; None: the input's estimated quality
    metrics: bool = True                       # per-step and per-output metrics in the manifest (roadview_noise.metrics)


class RecipeSpec(_Strict):
    schema_: Literal["rvnoise.recipe/1"] = Field(SCHEMA, alias="schema")
    description: str = ""
    cnf: str | None = None
    sensor: Literal["camera", "lidar", "radar"] | None = None
    chain: list[StepSpec] | None = None
    order: Literal["physical", "as_written"] = "physical"
    params: dict[str, dict[str, Any]] = Field(default_factory=dict)
    sweep: dict[str, list[Any]] = Field(default_factory=dict)
    seed: int = 0
    inputs: InputsSpec = Field(default_factory=InputsSpec)
    output: OutputSpec = Field(default_factory=OutputSpec)

    @field_validator("sweep")
    @classmethod
    def _sweep_nonempty(cls, v: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for k, values in v.items():
            if not values:
                raise ValueError(f"sweep {k!r} lists no values")
        return v


# --- resolved form -------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Variant:
    """One output variant of a sweep: a file-name suffix and the parameter values it fixes."""

    suffix: str
    overrides: dict[str, dict[str, Any]]


class Variants(Sequence):
    """The variants of a sweep: the product of its axes (the last axis varies fastest, as ``itertools.product``),
    each built when it is asked for."""

    def __init__(self, axes: list[list[tuple[str, str, Any]]]):
        self.axes = axes
        self._len = math.prod(len(a) for a in axes)
        self._last: tuple[int, Variant] | None = None    # a file's steps ask for its variant several times

    def __len__(self) -> int:
        return self._len

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self._len))]
        if i < 0:
            i += self._len
        if not 0 <= i < self._len:
            raise IndexError(f"variant {i} of {self._len}")
        last = self._last                               # (one read: runs may share the recipe between threads)
        if last is not None and last[0] == i:
            return last[1]
        combo, rest = [], i
        for axis in reversed(self.axes):
            rest, k = divmod(rest, len(axis))
            combo.append(axis[k])
        combo.reverse()
        overrides: dict[str, dict[str, Any]] = {}
        for model_id, name, v in combo:
            overrides.setdefault(model_id, {})[name] = v
        variant = Variant("".join(f"__{name}-{_suffix_text(v)}" for _, name, v in combo), overrides)
        self._last = (i, variant)
        return variant

    def __eq__(self, other) -> bool:
        return isinstance(other, Variants) and self.axes == other.axes

    def __hash__(self) -> int:
        return hash(json.dumps(self.axes, default=str))


@dataclass(frozen=True)
class Recipe:
    """A validated recipe: models in physical order with their parameter specs, variants, inputs, seed."""

    spec: RecipeSpec
    source: str
    base_dir: Path
    model_ids: tuple[str, ...]
    step_params: tuple[dict[str, Any], ...]
    variants: Variants

    @property
    def sensor(self) -> str:
        return get_model(self.model_ids[0]).sensor

    @property
    def seed(self) -> int:
        return self.spec.seed

    def resolved_dict(self) -> dict[str, Any]:
        """The recipe as run: explicit chain and parameters (what run.json records and replay re-reads)."""
        d = self.spec.model_dump(mode="json", by_alias=True)
        d["chain"] = [{"model": m, "params": p} for m, p in zip(self.model_ids, self.step_params)]
        d["order"] = "as_written"
        d["cnf"] = None
        d["params"] = {}
        return d

    def sha256(self) -> str:
        return hashlib.sha256(json.dumps(self.resolved_dict(), sort_keys=True).encode()).hexdigest()

    def needs_depth(self) -> bool:
        return any(get_model(m).needs_depth for m in self.model_ids)


def _loc(loc: tuple) -> str:
    out = ""
    for p in loc:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def _allowed_keys(loc: tuple) -> list[str]:
    """Field names allowed at the parent of ``loc`` (for did-you-mean)."""
    model: Any = RecipeSpec
    for p in loc[:-1]:
        if isinstance(p, int) or model is None:
            continue
        fld = model.model_fields.get(p)
        if fld is None:
            model = None
            continue
        ann = fld.annotation
        args = getattr(ann, "__args__", ())
        candidates = [ann, *args, *(a for x in args for a in getattr(x, "__args__", ()))]
        model = next((c for c in candidates if isinstance(c, type) and issubclass(c, BaseModel)), None)
    if model is None:
        return []
    return [f.alias or n for n, f in model.model_fields.items()]


def _check_value(model_id: str, name: str, value: Any, key: str, source: str) -> None:
    cls = get_model(model_id)
    specs = {s.name: s for s in cls.param_specs()}
    if name not in specs:
        raise RecipeError(f"{model_id} has no parameter {name!r}{suggest(name, specs)}; it has: "
                          f"{', '.join(specs) or 'none'}", file=source, key=key)
    values: list[Any]
    if isinstance(value, dict):
        if len(value) != 1 or next(iter(value)) not in DISTRIBUTIONS:
            raise RecipeError(f"a distribution is one of {{uniform: [lo, hi]}}, {{choice: [...]}}, "
                              f"{{normal: [mean, sd]}}; got {value!r}", file=source, key=key)
        kind, args = next(iter(value.items()))
        if not isinstance(args, list) or not args or (kind != "choice" and len(args) != 2):
            raise RecipeError(f"{kind} needs a list{' of two numbers' if kind != 'choice' else ''}, got {args!r}",
                              file=source, key=key)
        if kind == "uniform" and not args[0] <= args[1]:
            raise RecipeError(f"uniform bounds must be [lo, hi] with lo ≤ hi, got {args}", file=source, key=key)
        if kind == "normal" and not args[1] >= 0:
            raise RecipeError(f"normal sd must be ≥ 0, got {args[1]}", file=source, key=key)
        if kind == "normal":
            _check_normal(specs[name], args[0], args[1], key, source)
        values = args if kind != "normal" else [args[0]]
    else:
        values = [value]
    for v in values:
        problem = specs[name].check(tuple(v) if isinstance(v, list) else v)
        if problem:
            raise RecipeError(problem, file=source, key=key)
        if specs[name].unit == "path" and isinstance(v, str) and not Path(v).is_file():   # read by every file's step
            raise RecipeError(f"no file {v!r} (a path relative to the folder rvnoise runs in, {str(Path.cwd())!r})",
                              file=source, key=key)


def _check_normal(spec, mean: float, sd: float, key: str, source: str) -> None:
    """mean ± NORMAL_TAIL_SD·sd must be allowed values (see module docstring)."""
    integer = type(spec.default) is int
    for v in (mean, mean - NORMAL_TAIL_SD * sd, mean + NORMAL_TAIL_SD * sd):
        problem = spec.check(round(v) if integer else v)
        if problem:
            bounds = [b for b in (spec.ge, spec.gt, spec.le, spec.lt) if b is not None]
            room = min((abs(mean - b) for b in bounds), default=0.0)
            raise RecipeError(f"normal [{mean}, {sd}] reaches {v:g} within ±{NORMAL_TAIL_SD:g} sd, outside the "
                              f"allowed range ({spec.range_text()}); draws are truncated at ±{NORMAL_TAIL_SD:g} sd, "
                              f"so use sd ≤ {room / NORMAL_TAIL_SD:g} for this mean, or a uniform",
                              file=source, key=key)


def draw_value(value: Any, rng, *, integer: bool = False) -> Any:
    """A fixed value as is, or one draw from an explicit distribution (integers for an integer parameter:
    uniform over the inclusive range, normal rounded; a normal is truncated at mean ± NORMAL_TAIL_SD·sd)."""
    if not isinstance(value, dict):
        return tuple(value) if isinstance(value, list) else value
    kind, args = next(iter(value.items()))
    if kind == "uniform":
        return int(rng.integers(args[0], args[1] + 1)) if integer else float(rng.uniform(args[0], args[1]))
    if kind == "normal":
        tail = NORMAL_TAIL_SD * args[1]
        v = min(max(rng.normal(args[0], args[1]), args[0] - tail), args[0] + tail)
        return int(round(v)) if integer else float(v)
    choice = args[int(rng.integers(len(args)))]
    return tuple(choice) if isinstance(choice, list) else choice


def _step_hint(model_id: str, ids: Sequence[str], *, cnf: bool) -> str:
    """What to tell a user whose ``params:`` name a model that is not a step: the step it misspells, or, for a real
    model, how to add it (a step is not suggested for a model that merely shares its sensor)."""
    if not known(model_id):
        return suggest(model_id, ids)
    return "; to add a model to a CNF, write its steps as `chain:`" if cnf else f"; add {model_id} to `chain:`"


def _suffix_text(v: Any) -> str:
    return str(v).replace("/", "_").replace(" ", "")


def parse_recipe(data: Any, *, source: str = "<recipe>", base_dir: Path | None = None) -> Recipe:
    """Validate a recipe mapping; raises RecipeError naming the file and key path."""
    if not isinstance(data, dict):
        raise RecipeError("a recipe is a YAML mapping", file=source)
    try:
        spec = RecipeSpec.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        key = _loc(err["loc"])
        if err["type"] == "extra_forbidden":
            name = str(err["loc"][-1])
            raise RecipeError(f"unknown key {name!r}{suggest(name, _allowed_keys(err['loc']))}",
                              file=source, key=key) from None
        got = err.get("input")
        hint = suggest(str(got), CNFS) if key == "cnf" else ""
        shown = f", got {got!r}{hint}" if isinstance(got, (str, int, float, bool)) else ""
        raise RecipeError(f"{err['msg']}{shown}", file=source, key=key) from None

    if (spec.cnf is None) == (spec.chain is None):
        raise RecipeError("give exactly one of `cnf:` or `chain:`", file=source)
    try:
        if spec.cnf is not None:
            ids = cnf_chain(spec.cnf, spec.sensor)
            ids = order_chain(ids, where="cnf")
            step_params = [dict(spec.params.get(m, {})) for m in ids]
            unknown = set(spec.params) - set(ids)
            if unknown:
                m = sorted(unknown)[0]
                raise RecipeError(f"{m!r} is not a step of {spec.cnf.upper()} ({', '.join(ids)})"
                                  f"{_step_hint(m, ids, cnf=True)}", key=f"params.{m}")
        else:
            if not spec.chain:
                raise RecipeError("the chain is empty", key="chain")
            ids = order_chain([s.model for s in spec.chain], as_written=spec.order == "as_written")
            step_params = [dict(s.params) for s in spec.chain]
            for m, p in spec.params.items():
                if m not in ids:
                    raise RecipeError(f"{m!r} is not in the chain{_step_hint(m, ids, cnf=False)}", key=f"params.{m}")
                step_params[ids.index(m)].update(p)
        if spec.sensor is not None and get_model(ids[0]).sensor != spec.sensor:
            raise RecipeError(f"the chain acts on {get_model(ids[0]).sensor}, not {spec.sensor}", key="sensor")
        spec.inputs.annotations.check_sensor(get_model(ids[0]).sensor)
    except RecipeError as e:
        raise RecipeError(e.message, file=source, key=e.key) from None
    except ModelError as e:
        raise RecipeError(str(e), file=source) from None

    for i, (m, params) in enumerate(zip(ids, step_params)):
        where = f"chain[{i}].params" if spec.chain is not None else f"params.{m}"
        for name, value in params.items():
            _check_value(m, name, value, f"{where}.{name}", source)
        fixed = {k: draw_value(v, None) for k, v in params.items() if not isinstance(v, dict)}
        try:
            get_model(m)(**fixed)
        except ModelError as e:
            raise RecipeError(str(e), file=source, key=where) from None

    axes = []
    for key, values in spec.sweep.items():
        model_id, _, name = key.rpartition(".")
        if model_id not in ids:
            raise RecipeError(f"sweep key must be MODEL.PARAM with a model of the chain{suggest(model_id, ids)}",
                              file=source, key=f"sweep.{key}")
        seen: dict[str, Any] = {}
        for v in values:
            _check_value(model_id, name, v, f"sweep.{key}", source)
            text = _suffix_text(v)
            if text in seen:
                raise RecipeError(f"values {seen[text]!r} and {v!r} give the same file-name suffix "
                                  f"'__{name}-{text}'", file=source, key=f"sweep.{key}")
            seen[text] = v
        axes.append([(model_id, name, v) for v in values])
    base_dir = base_dir or Path.cwd()
    check_inputs(spec.inputs, tuple(ids), source, base_dir)
    return Recipe(spec, source, base_dir, tuple(ids), tuple(step_params), Variants(axes))


def load_recipe(path: str | Path) -> Recipe:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise RecipeError(f"cannot read recipe ({e.strerror})", file=str(path)) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise RecipeError(f"not valid YAML: {e}", file=str(path)) from None
    return parse_recipe(data, source=str(path), base_dir=path.resolve().parent)
