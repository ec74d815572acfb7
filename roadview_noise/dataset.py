"""The input tree: which files a recipe processes (sorted samples with sidecars and sequence ids), how each is read
into a frame or cloud, and how the result is written back in the input's own format.

Workers receive :class:`Sample` keys, never arrays; all reading and writing happens here and in ``io/``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import posixpath
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Callable, Iterable, Iterator

from .annotations import Annotated, label_image_reason, sidecar_files
from .annotations import write as write_annotations
from .errors import InputError
from .io.atomic import recorded_writes
from .recipe import InputsSpec, Recipe
from .types import CameraFrame, Conditions, LidarProfile, RawFrame, SensorData
from .walk import Matcher, WalkFailure, walk

DEFAULT_GLOBS = {
    "camera": ["**/*.png", "**/*.jpg", "**/*.jpeg", "**/*.tif", "**/*.tiff", "**/*.webp", "**/*.heic", "**/*.heif",
               "**/*.hif", "**/*.avif"],
    "raw": ["**/*.dng", "**/*.raw"],
    "lidar": ["**/*.pcd", "**/*.bin", "**/*.ply"],
    "radar": ["**/*.pcd", "**/*.bin"],
}
MODALITIES = {"camera": ("camera", "raw"), "lidar": ("lidar",), "radar": ("radar",)}
COMPOUND_SUFFIXES = (".pcd.bin",)
# nuScenes' file names: <log>__<channel>__<µs timestamp>, every log of a channel in one folder (samples/CAM_FRONT)
NUSCENES_NAME = re.compile(r"(n\d{3}-\d{4}(?:-\d\d){5}[+-]\d{4}__[A-Z0-9_]+)__\d+\.")


@dataclass(frozen=True)
class Sample:
    """One input file: POSIX path relative to the input root, modality, sensor instance, sidecar paths."""

    relpath: str
    modality: str                 # camera | raw | lidar | radar
    sequence_id: str
    depth_relpath: str | None = None


def split_suffix(relpath: str) -> tuple[str, str]:
    """(path without its suffix, suffix) as ``PurePosixPath``'s ``with_suffix("")`` and ``suffix`` give them;
    on a normalised path with a plain suffix by string operations (pathlib parses the path: ≈ 10 µs of the
    main process per planned output, issue 19)."""
    for s in COMPOUND_SUFFIXES:
        if relpath.lower().endswith(s):
            return relpath[: -len(s)], relpath[-len(s):]
    name = relpath.rpartition("/")[2]
    dot = name.rfind(".")
    if 0 < dot < len(name) - 1 and not relpath.startswith("./") and "//" not in relpath and "/./" not in relpath:
        cut = len(relpath) - len(name) + dot
        return relpath[:cut], relpath[cut:]
    p = PurePosixPath(relpath)
    return str(p.with_suffix("")), p.suffix


def sequence_id(relpath: str, mode: str) -> str:
    """The sensor instance (sequence) of an input (``inputs.sequence``): the file itself for ``file``; for
    ``folder`` its folder, and within it, for nuScenes' names, its log and channel (nuScenes keeps every recording
    of a channel in one folder, so the folder alone would give all its logs one lens soiling and one set of beam
    offsets, and every channel of a flattened folder the same)."""
    if mode == "file":
        return relpath
    folder, _, name = relpath.rpartition("/")
    nuscenes = NUSCENES_NAME.match(name)
    return f"{folder}/{nuscenes.group(1)}" if nuscenes and folder else nuscenes.group(1) if nuscenes else folder or "."


def output_relpath(relpath: str, suffix: str) -> str:
    """The output path of an input for a sweep variant: ``000001.png`` → ``000001__visibility_m-30.png``."""
    stem, ext = split_suffix(relpath)
    return f"{stem}{suffix}{ext}"


def depth_relpath_for(relpath: str, pattern) -> str:
    """The sidecar of an input file for a pattern relative to its folder (``recipe.InputsSpec`` fields), or for a
    ``{replace: {old: new}}`` rule on its path under the input root (KITTI's depth_selection names the depth of
    ``image/…_sync_image_0000000005_image_02.png`` ``velodyne_raw/…_sync_velodyne_raw_0000000005_image_02.png``),
    as a normalised POSIX path relative to the input root (``..`` allowed)."""
    if not isinstance(pattern, str):
        return posixpath.normpath(pattern.applied(relpath))
    p = PurePosixPath(relpath)
    stem, _ = split_suffix(p.name)
    base = stem.rpartition("_")[0] or stem
    try:
        name = pattern.format(stem=stem, name=p.name, base=base, parent=p.parent.name, parts=list(p.parent.parts))
    except IndexError:
        raise InputError(f"pattern {pattern!r} names a folder level the file does not have (it is in "
                         f"{str(p.parent)!r})", file=relpath) from None
    return posixpath.normpath(str(p.parent / name))


def _globs(inputs: InputsSpec, modality: str, explicit: bool) -> list[str]:
    value = getattr(inputs, modality)
    if value is None:
        return [] if explicit else DEFAULT_GLOBS[modality]
    return [value] if isinstance(value, str) else list(value)


def matcher(recipe: Recipe) -> Matcher:
    """The recipe's input globs per modality (in order: the first modality that matches a path wins)."""
    inputs = recipe.spec.inputs
    modalities = MODALITIES[recipe.sensor]
    explicit = any(getattr(inputs, m) is not None for m in modalities)
    return Matcher([(m, p) for m in modalities for p in _globs(inputs, m, explicit)], inputs.exclude)


class _Sidecars:
    """Which matched files are a sidecar of a matched input (they are then not inputs themselves): a file is one
    when ``of(input)`` names it for some matched input. When every sidecar lies in its input's folder (``local``),
    this is decided folder by folder during the walk; otherwise the sidecars of every matched input are collected by
    one walk of the tree first."""

    def __init__(self, of: Callable[[str], Iterable[str | None]], local: bool, match: Matcher, in_root: Path):
        self.of, self.match = of, match
        self._folder: tuple[str, set[str | None]] | None = None
        self._everywhere: set[str | None] | None = None
        if not local:
            self._everywhere = {s for item in walk(in_root, match) if not isinstance(item, WalkFailure)
                                for s in of(item[0])}

    def __call__(self, rel: str, siblings: list[str]) -> bool:
        if self._everywhere is not None:
            return rel in self._everywhere
        folder = str(PurePosixPath(rel).parent)
        if self._folder is None or self._folder[0] != folder:
            prefix = "" if folder == "." else folder + "/"
            self._folder = (folder, {s for n in siblings if self.match.modality(prefix + n) is not None
                                     for s in self.of(prefix + n)})
        return rel in self._folder[1]


def _depth_sidecar(rel: str, pattern: str) -> str | None:
    try:
        return depth_relpath_for(rel, pattern)
    except InputError:                             # the pattern names a folder level this image does not have
        return None


def iter_inputs(in_root: Path, recipe: Recipe) -> Iterator[Sample | WalkFailure]:
    """Every input of the recipe's sensor under ``in_root`` in sorted path order, one at a time, and a
    :class:`~roadview_noise.walk.WalkFailure` for every path the walk could not read; depth sidecars are not
    inputs."""
    inputs = recipe.spec.inputs
    match = matcher(recipe)
    camera = recipe.sensor == "camera"
    rules = list(inputs.annotations.rules())

    def sidecars_of(rel: str) -> set[str | None]:
        found = sidecar_files(in_root, inputs.annotations, [rel]) if rules else set()
        return found | {_depth_sidecar(rel, inputs.depth)} if camera else found

    camera_globs = _globs(inputs, "camera", False) if camera else []
    sidecar = None
    if camera or rules:                            # masks, lidarseg files, depth maps … are no inputs
        local = isinstance(inputs.depth, str) and "/" not in inputs.depth and not rules
        sidecar = _Sidecars(sidecars_of, local, match, in_root)
    for item in walk(in_root, match):
        if isinstance(item, WalkFailure):
            yield item
            continue
        rel, modality, siblings = item
        if sidecar is not None and sidecar(rel, siblings):
            continue
        why = label_image_reason(rel, camera_globs) if modality == "camera" else None
        if why is not None:
            yield WalkFailure(rel, f"looks like a label image, not a photo ({why}): declare it under "
                                   "inputs.annotations.masks so that it follows its image, or leave it out "
                                   "(inputs.exclude); a camera glob naming that folder reads it as a photo")
            continue
        seq = sequence_id(rel, inputs.sequence)                      # the walk's rel: normalised
        depth = None
        if modality in ("camera", "raw") and inputs.depth_source == "file":
            candidate = depth_relpath_for(rel, inputs.depth)
            if PurePosixPath(candidate).parent == PurePosixPath(rel).parent:
                depth = candidate if PurePosixPath(candidate).name in siblings else None
            else:
                depth = candidate if (in_root / candidate).is_file() else None
        yield Sample(rel, modality, seq, depth)


def discover(in_root: Path, recipe: Recipe) -> list[Sample]:
    """Every input of the recipe's sensor under ``in_root``, sorted by path (what :func:`iter_inputs` yields, without
    the paths it could not read)."""
    return [s for s in iter_inputs(in_root, recipe) if isinstance(s, Sample)]


# --- profiles ------------------------------------------------------------------------------------------------------


def _profile_spec(spec, file_dir: Path, recipe: Recipe):
    """Resolve ``{dir}`` and relative paths of a profile given as a string: recipe folder first, then the file's."""
    if not isinstance(spec, str):
        return spec
    spec = spec.replace("{dir}", str(file_dir))
    p = Path(spec)
    if p.is_absolute() or p.suffix == "":
        return spec
    for base in (recipe.base_dir, file_dir):
        if (base / p).is_file():
            return str(base / p)
    return spec


def _sidecar_default(spec, file_dir: Path, name: str):
    """Without a profile in the recipe, a profile sidecar (``camera.yaml``, ``lidar.yaml``, ``radar.yaml``) in the
    input file's folder is used; else the built-in default."""
    if spec is None:
        path = os.path.join(file_dir, name)             # str(file_dir / name), without pathlib (once per file)
        if os.path.isfile(path):
            return path
    return spec


def _camera_profile(spec, file_dir: Path):
    """The recipe's camera profile, else ``camera.yaml`` next to the image, else the ROADVIEW Lucid."""
    from .profiles.camera import load_camera_profile

    if isinstance(spec, dict):
        return load_camera_profile(spec)
    return _camera_profile_cached(_sidecar_default(spec, file_dir, "camera.yaml"))


@lru_cache(maxsize=64)
def _camera_profile_cached(spec: str | None):
    from .profiles.camera import load_camera_profile

    return load_camera_profile(spec)


@lru_cache(maxsize=64)
def _lidar_profile(spec_key, unit, full_scale) -> LidarProfile:
    from .profiles.lidar import load_lidar_profile, with_intensity_scale

    profile = load_lidar_profile(_thawed(spec_key))
    return with_intensity_scale(profile, unit, full_scale) if unit or full_scale else profile


@lru_cache(maxsize=64)
def _radar_profile(spec_key):
    from .profiles.radar import load_radar_profile

    return load_radar_profile(_thawed(spec_key))


def _hashable(spec):
    """The cache key of a profile spec: a name or path as is, an inline mapping (with lists, e.g. a beam table's
    ``beam_elevation_deg``, which a tuple of its items could not hash) as its JSON text."""
    return ("mapping", json.dumps(spec, sort_keys=True)) if isinstance(spec, dict) else spec


def _thawed(spec_key):
    return json.loads(spec_key[1]) if isinstance(spec_key, tuple) else spec_key


# --- reading and writing -------------------------------------------------------------------------------------------


def load(sample: Sample, in_root: Path, recipe: Recipe, content: bytes | None = None,
         profiles: dict | None = None) -> SensorData:
    """Read one sample (and the sidecars the chain needs) into a frame or cloud with the recipe's conditions
    (``content``: the bytes of a point cloud or PNG/JPEG/TIFF image file, already read); InputError names the
    file. ``profiles``: a run's cloud profiles by (sensor, folder), filled here (a run's profile sidecars are
    looked up once per folder, not per file)."""
    return with_conditions(_read(sample, in_root, recipe, content, profiles), recipe)


def with_conditions(data: SensorData, recipe: Recipe) -> SensorData:
    """The input's scene conditions from the recipe's inputs (the sensor's ego velocity)."""
    ego = recipe.spec.inputs.ego_velocity_m_per_s
    if ego is not None:
        data = dataclasses.replace(data, conditions=Conditions(ego_velocity_m_per_s=tuple(map(float, ego))))
    return data


def _read(sample: Sample, in_root: Path, recipe: Recipe, content: bytes | None, profiles: dict | None) -> SensorData:
    from .camera_inputs import load_camera_sample
    from .io import pointcloud as cloud_io

    inputs = recipe.spec.inputs
    path = in_root / sample.relpath
    file_dir = path.parent
    if sample.modality in ("camera", "raw"):
        return load_camera_sample(sample, in_root, recipe, content)
    key = (sample.modality, os.path.dirname(sample.relpath))
    profile = profiles.get(key) if profiles is not None else None
    if profile is None:
        profile = cloud_profile_for(sample.modality, inputs, file_dir, recipe)
        if profiles is not None:
            profiles[key] = profile
    bin_fields = inputs.radar_bin_fields if sample.modality == "radar" else inputs.bin_fields
    cloud = cloud_io.read_pointcloud(path, sensor=sample.modality, profile=profile,
                                     field_map=dict(inputs.field_map) or None, bin_fields=bin_fields,
                                     data=content)
    if sample.modality == "radar" and inputs.radar_profile is None:
        _radar_profile_hint(cloud, file_dir)
    return cloud


def _radar_profile_hint(cloud, file_dir: Path) -> None:
    """Warn when nothing states the radar profile (no recipe profile, no ``radar.yaml`` next to the file) and the
    file is in a dataset's layout whose sensor has a built-in profile: the default generic-77ghz (200 m, 1° × 2°
    cells) is not that sensor (nuScenes' ARS 408: 2-D, 3.2° cells, a quarter of the generic clutter)."""
    import warnings

    from .io.radar_formats import RadarProfileWarning, dataset_profile

    known = dataset_profile(cloud)
    if known is None or os.path.isfile(os.path.join(file_dir, "radar.yaml")):
        return
    dataset, name = known
    warnings.warn(RadarProfileWarning(
        f"no radar profile is stated and the file is in {dataset}'s layout: read with the default "
        f"{cloud.profile.name!r}; give radar_profile {name} (the recipe's inputs.radar_profile, --radar-profile "
        f"{name}, or a radar.yaml next to the files)"), stacklevel=2)


def cloud_profile_for(sensor: str, inputs: InputsSpec, file_dir: Path, recipe: Recipe, *, sidecar: bool = True):
    """The LiDAR (with the recipe's intensity scale) or radar profile of an input in ``file_dir``: the recipe's,
    else (``sidecar``) ``lidar.yaml``/``radar.yaml`` there, else the default."""
    if sensor == "lidar":
        spec = _profile_spec(inputs.lidar_profile, file_dir, recipe)
        spec = _sidecar_default(spec, file_dir, "lidar.yaml") if sidecar else spec
        return _lidar_profile(_hashable(spec), inputs.intensity_unit, inputs.intensity_full_scale)
    spec = _profile_spec(inputs.radar_profile, file_dir, recipe)
    spec = _sidecar_default(spec, file_dir, "radar.yaml") if sidecar else spec
    return _radar_profile(_hashable(spec))


def save(data: SensorData, out_path: Path, recipe: Recipe, source: Path | None = None,
         annotations: Annotated | None = None) -> list[Path]:
    """Write a result in the input's own format (atomically, by the io writers) with its sidecars (a ``.bin``
    cloud's ``rv_effect``) and annotation files; a DNG keeps the colour metadata of its ``source``. Returns every
    file written (recorded by ``io/atomic``, so no writer can forget one), the main output first: the runner records
    each with its sha256 in the manifest."""
    image = None                               # the camera output's bytes, for label files that embed the image
    with recorded_writes() as written:         # each writer imported for its kind only (a cloud's: no OpenCV/TIFF)
        if isinstance(data, CameraFrame):
            from .io import image as image_io

            image = image_io.write_frame(out_path, data)
        elif isinstance(data, RawFrame):
            from .io import raw as raw_io

            raw_io.write_raw(out_path, data.dn, data.cfa_pattern, data.black_level_dn, data.white_level_dn,
                             data.encoding, template=source)
        else:
            from .io import pointcloud as cloud_io

            cloud_io.write_pointcloud(out_path, data, effect=recipe.spec.output.effect)
        write_annotations(annotations, image)
    return sorted(written, key=lambda p: p.name != Path(out_path).name)
