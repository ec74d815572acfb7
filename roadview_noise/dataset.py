"""The input tree: which files a recipe processes (sorted samples with sidecars and sequence ids), how each is read
into a frame or cloud, and how the result is written back in the input's own format.

Workers receive :class:`Sample` keys, never arrays; all reading and writing happens here and in ``io/``.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import posixpath
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path, PurePosixPath

from .annotations import Annotated, sidecar_files
from .annotations import write as write_annotations
from .errors import InputError
from .io.atomic import TMP_SUFFIX
from .recipe import InputsSpec, Recipe
from .types import CameraFrame, Conditions, LidarProfile, RawFrame, SensorData

DEFAULT_GLOBS = {
    "camera": ["**/*.png", "**/*.jpg", "**/*.jpeg", "**/*.tif", "**/*.tiff"],
    "raw": ["**/*.dng", "**/*.raw"],
    "lidar": ["**/*.pcd", "**/*.bin", "**/*.ply"],
    "radar": ["**/*.pcd", "**/*.bin"],
}
MODALITIES = {"camera": ("camera", "raw"), "lidar": ("lidar",), "radar": ("radar",)}
COMPOUND_SUFFIXES = (".pcd.bin",)


@dataclass(frozen=True)
class Sample:
    """One input file: POSIX path relative to the input root, modality, sensor instance, sidecar paths."""

    relpath: str
    modality: str                 # camera | raw | lidar | radar
    sequence_id: str
    depth_relpath: str | None = None


def split_suffix(relpath: str) -> tuple[str, str]:
    for s in COMPOUND_SUFFIXES:
        if relpath.lower().endswith(s):
            return relpath[: -len(s)], relpath[-len(s):]
    p = PurePosixPath(relpath)
    return str(p.with_suffix("")), p.suffix


def output_relpath(relpath: str, suffix: str) -> str:
    """The output path of an input for a sweep variant: ``000001.png`` → ``000001__visibility_m-30.png``."""
    stem, ext = split_suffix(relpath)
    return f"{stem}{suffix}{ext}"


def depth_relpath_for(relpath: str, pattern: str) -> str:
    """The sidecar of an input file for a pattern relative to its folder (``recipe.InputsSpec`` fields), as a
    normalised POSIX path relative to the input root (``..`` allowed)."""
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


def discover(in_root: Path, recipe: Recipe) -> list[Sample]:
    """Every input of the recipe's sensor under ``in_root``, sorted by path; depth sidecars are not inputs."""
    inputs = recipe.spec.inputs
    modalities = MODALITIES[recipe.sensor]
    explicit = any(getattr(inputs, m) is not None for m in modalities)
    found: dict[str, str] = {}
    for modality in modalities:
        for pattern in _globs(inputs, modality, explicit):
            for p in in_root.glob(pattern):
                rel = p.relative_to(in_root).as_posix()
                if not p.is_file() or TMP_SUFFIX in p.name or any(part.startswith(".") for part in p.parts[-1:]):
                    continue
                if any(fnmatch.fnmatch(rel, x) for x in inputs.exclude):
                    continue
                found.setdefault(rel, modality)
    sidecars = sidecar_files(in_root, inputs.annotations, found)         # masks, lidarseg files … are no inputs
    if recipe.sensor == "camera":
        sidecars |= {depth_relpath_for(rel, inputs.depth) for rel in found}
    found = {rel: m for rel, m in found.items() if rel not in sidecars}
    samples = []
    for rel in sorted(found):
        modality = found[rel]
        seq = str(PurePosixPath(rel).parent) if inputs.sequence == "folder" else rel
        depth = None
        if modality in ("camera", "raw") and inputs.depth_source == "file":
            candidate = depth_relpath_for(rel, inputs.depth)
            depth = candidate if (in_root / candidate).is_file() else None
        samples.append(Sample(rel, modality, seq, depth))
    return samples


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
    if spec is None and (file_dir / name).is_file():
        return str(file_dir / name)
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
    from .profiles.lidar import load_lidar_profile

    profile = load_lidar_profile(spec_key if not isinstance(spec_key, tuple) else dict(spec_key))
    return with_intensity_scale(profile, unit, full_scale) if unit or full_scale else profile


DEFAULT_FULL_SCALE = {"photons": 65535.0, "uint8": 255.0, "unit": 1.0}


def with_intensity_scale(profile: LidarProfile, unit: str | None, full_scale: float | None) -> LidarProfile:
    """The same sensor with intensities stored in another unit/full scale (the recipe's ``intensity_unit``,
    ``intensity_full_scale``): everything tied to the stored scale follows, so the physics is unchanged — for a
    ``signal`` profile the sensor constant and the threshold (signal = stored intensity), for a ``reflectivity``
    profile the white reading."""
    unit = unit or profile.intensity_unit
    new_fs = float(full_scale or DEFAULT_FULL_SCALE.get(unit, profile.intensity_full_scale))
    ratio = new_fs / profile.intensity_full_scale
    changes: dict = {"intensity_unit": unit, "intensity_full_scale": new_fs,
                     "intensity_source": "the recipe's intensity_unit / intensity_full_scale",
                     "intensity_step": profile.intensity_step if unit == profile.intensity_unit else None}
    if profile.intensity_kind == "signal":
        if profile.sensor_constant is not None:
            changes["sensor_constant"] = profile.sensor_constant * ratio
        changes["detection_threshold"] = profile.detection_threshold * ratio
    elif profile.reflectivity_white_reading is not None:
        changes["reflectivity_white_reading"] = profile.reflectivity_white_reading * ratio
    return dataclasses.replace(profile, **changes)


@lru_cache(maxsize=64)
def _radar_profile(spec_key):
    from .profiles.radar import load_radar_profile

    return load_radar_profile(spec_key if not isinstance(spec_key, tuple) else dict(spec_key))


def _hashable(spec):
    return tuple(sorted(spec.items())) if isinstance(spec, dict) else spec


# --- reading and writing -------------------------------------------------------------------------------------------


def load(sample: Sample, in_root: Path, recipe: Recipe) -> SensorData:
    """Read one sample (and the sidecars the chain needs) into a frame or cloud with the recipe's conditions;
    InputError names the file."""
    return with_conditions(_read(sample, in_root, recipe), recipe)


def with_conditions(data: SensorData, recipe: Recipe) -> SensorData:
    """The input's scene conditions from the recipe's inputs (the sensor's ego velocity)."""
    ego = recipe.spec.inputs.ego_velocity_m_per_s
    if ego is not None:
        data = dataclasses.replace(data, conditions=Conditions(ego_velocity_m_per_s=tuple(map(float, ego))))
    return data


def _read(sample: Sample, in_root: Path, recipe: Recipe) -> SensorData:
    from .camera_inputs import load_camera_sample
    from .io import pointcloud as cloud_io

    inputs = recipe.spec.inputs
    path = in_root / sample.relpath
    file_dir = path.parent
    if sample.modality in ("camera", "raw"):
        return load_camera_sample(sample, in_root, recipe)
    return cloud_io.read_pointcloud(path, sensor=sample.modality,
                                    profile=cloud_profile_for(sample.modality, inputs, file_dir, recipe),
                                    field_map=dict(inputs.field_map) or None)


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
    file written, the main output first."""
    from .io import image as image_io
    from .io import pointcloud as cloud_io
    from .io import raw as raw_io

    written = [out_path]
    if isinstance(data, CameraFrame):
        image_io.write_image(out_path, data.linear_rgb, data.encoding, alpha=data.alpha)
    elif isinstance(data, RawFrame):
        raw_io.write_raw(out_path, data.dn, data.cfa_pattern, data.black_level_dn, data.white_level_dn,
                         data.encoding, template=source)
    else:
        written = cloud_io.write_pointcloud(out_path, data, effect=recipe.spec.output.effect)
    return written + write_annotations(annotations)
