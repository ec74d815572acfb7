"""The input tree: which files a recipe processes (sorted samples with sidecars and sequence ids), how each is read
into a frame or cloud, and how the result is written back in the input's own format.

Workers receive :class:`Sample` keys, never arrays; all reading and writing happens here and in ``io/``.
"""

from __future__ import annotations

import dataclasses
import fnmatch
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Callable

import numpy as np

from .errors import InputError
from .io.atomic import TMP_SUFFIX
from .recipe import InputsSpec, Recipe
from .types import CameraFrame, CameraProfile, Conditions, LidarProfile, RawFrame, SensorData

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
    p = PurePosixPath(relpath)
    stem, _ = split_suffix(p.name)
    return str(p.parent / pattern.format(stem=stem, name=p.name))


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
    if recipe.sensor == "camera":
        sidecars = {depth_relpath_for(rel, inputs.depth) for rel in found}
        found = {rel: m for rel, m in found.items() if rel not in sidecars}
    samples = []
    for rel in sorted(found):
        modality = found[rel]
        seq = str(PurePosixPath(rel).parent) if inputs.sequence == "folder" else rel
        depth = None
        if modality in ("camera", "raw"):
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
    changes: dict = {"intensity_unit": unit, "intensity_full_scale": new_fs}
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
    from .io import depth as depth_io
    from .io import image as image_io
    from .io import pointcloud as cloud_io
    from .io import raw as raw_io
    from .profiles.camera import fit_to_image

    inputs = recipe.spec.inputs
    path = in_root / sample.relpath
    file_dir = path.parent
    if sample.modality in ("camera", "raw"):
        profile = camera_profile_for(inputs, file_dir, recipe)
        if sample.modality == "camera":
            linear, encoding, alpha = image_io.read_image(path)
            h, w = linear.shape[:2]
            frame = CameraFrame(linear, fit_to_image(profile, w, h, source=str(path)), encoding=encoding,
                                alpha=alpha)
        else:
            dn, pattern, black, white, encoding = raw_io.read_raw(path)
            h, w = dn.shape
            frame = RawFrame(dn.astype("float32"), pattern, float(black), float(white),
                             fit_to_image(profile, w, h, source=str(path)), encoding=encoding)
        sidecar = None if sample.depth_relpath is None else in_root / sample.depth_relpath

        def read_sidecar(camera: CameraProfile, shape: tuple[int, int]):
            return depth_io.read_depth(sidecar, profile=camera, expected_shape=shape,
                                       planar=inputs.depth_kind == "planar")

        return with_depth(frame, recipe, None if sidecar is None else read_sidecar, source=str(path),
                          missing=f"no depth sidecar {depth_relpath_for(sample.relpath, inputs.depth)!r}")
    return cloud_io.read_pointcloud(path, sensor=sample.modality,
                                    profile=cloud_profile_for(sample.modality, inputs, file_dir, recipe),
                                    field_map=dict(inputs.field_map) or None)


def camera_profile_for(inputs: InputsSpec, file_dir: Path, recipe: Recipe, *, sidecar: bool = True):
    """The camera profile of an input in ``file_dir``: the recipe's, else (``sidecar``) ``camera.yaml`` there, else
    the default."""
    spec = _profile_spec(inputs.camera_profile, file_dir, recipe)
    return _camera_profile_cached(None) if spec is None and not sidecar else _camera_profile(spec, file_dir)


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


def with_depth(frame, recipe: Recipe, read_depth: Callable[[CameraProfile, tuple[int, int]], np.ndarray] | None, *,
               source: str, missing: str):
    """The frame with the range along each pixel ray (m) when the chain needs depth — the one place depth is resolved
    for files and bag messages: ``read_depth(profile, shape)`` reads the input's own depth (sidecar file or aligned
    depth message); without one, InputError names ``source`` and says what is ``missing``."""
    if not recipe.needs_depth():
        return frame
    if read_depth is None:
        needing = [m for m in recipe.model_ids if _needs_depth(m)]
        raise InputError(f"{missing} (needed by {', '.join(needing)})", file=source)
    return dataclasses.replace(frame, depth_m=read_depth(frame.profile, frame.shape))


def _needs_depth(model_id: str) -> bool:
    from .registry import get_model

    return get_model(model_id).needs_depth


def save(data: SensorData, out_path: Path, recipe: Recipe, source: Path | None = None) -> None:
    """Write a result in the input's own format (atomically, by the io writers); a DNG keeps the colour metadata
    of its ``source``."""
    from .io import image as image_io
    from .io import pointcloud as cloud_io
    from .io import raw as raw_io

    if isinstance(data, CameraFrame):
        image_io.write_image(out_path, data.linear_rgb, data.encoding, alpha=data.alpha)
    elif isinstance(data, RawFrame):
        raw_io.write_raw(out_path, data.dn, data.cfa_pattern, data.black_level_dn, data.white_level_dn,
                         data.encoding, template=source)
    else:
        cloud_io.write_pointcloud(out_path, data, labels=recipe.spec.output.labels)
