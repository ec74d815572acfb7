"""Recipe checks of the ``inputs:`` section that need more than a type: what ``rvnoise validate`` must catch before
a run so that no file fails for a reason the recipe already showed.

- Globs (``camera``, ``raw``, ``lidar``, ``radar``, ``exclude``) stay inside the input folder: absolute patterns and
  ``..`` segments are refused (an output path mirrors the input path, so ``../x`` would write outside OUT or onto
  the input itself). Sidecar patterns (``depth``, …) may use ``..`` to reach a sibling folder; the file they name is
  refused at read time when it resolves outside the input folder (``runner.input_path``).
- Profiles (``camera_profile``, ``lidar_profile``, ``radar_profile``) of the recipe's sensor are resolved now (a
  camera profile only when a step uses the camera geometry; without one it is never read): a
  built-in name, a file relative to the recipe (loaded and checked) or a mapping; a file next to each input is
  written ``{dir}/NAME`` and checked when it is read.
"""

from __future__ import annotations

import string
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

from .errors import InputError, RecipeError
from .registry import get_model, suggest

GLOB_KEYS = ("camera", "raw", "lidar", "radar", "exclude")
PROFILE_KEYS = {"camera": "camera_profile", "lidar": "lidar_profile", "radar": "radar_profile"}
PROFILE_FIELDS = ("dir",)                  # {dir}: the input file's folder


def escapes(pattern: str) -> str | None:
    """Why a relative path pattern could leave its root (absolute, drive, ``..``), or None."""
    if pattern.startswith(("/", "\\", "~")) or PureWindowsPath(pattern).drive:
        return "is an absolute path; patterns are relative to the input folder"
    if ".." in PurePosixPath(pattern.replace("\\", "/")).parts:
        return "contains '..'; inputs must lie inside the input folder (outputs mirror their paths)"
    return None


def placeholders(pattern: str, allowed: tuple[str, ...]) -> str | None:
    """Why ``pattern``'s ``{…}`` placeholders are not a subset of ``allowed``, or None."""
    try:
        fields = [f for _, f, _, _ in string.Formatter().parse(pattern) if f is not None]
    except ValueError as e:
        return f"is not a valid pattern ({e}); write a literal brace as {{{{ or }}}}"
    for f in fields:
        if f not in allowed:
            shown = ", ".join("{" + a + "}" for a in allowed)
            return f"has an unknown placeholder {{{f}}}{suggest(f, allowed)}; allowed: {shown}"
    return None


def check_inputs(inputs: Any, model_ids: tuple[str, ...], source: str, base_dir: Path | None) -> None:
    """Raise :class:`RecipeError` naming the key for the problems listed in the module docstring."""
    sensor = get_model(model_ids[0]).sensor
    for key in GLOB_KEYS:
        value = getattr(inputs, key)
        for pattern in [value] if isinstance(value, str) else value or []:
            problem = escapes(pattern)
            if problem:
                raise RecipeError(f"{pattern!r} {problem}", file=source, key=f"inputs.{key}")
    if sensor != "camera" or any(get_model(m).uses_camera_geometry for m in model_ids):
        key = PROFILE_KEYS[sensor]
        _check_profile(sensor, getattr(inputs, key), source, f"inputs.{key}", base_dir)


def _check_profile(sensor: str, spec: Any, source: str, where: str, base_dir: Path | None) -> None:
    if spec is None:
        return
    if isinstance(spec, str):
        problem = placeholders(spec, PROFILE_FIELDS)
        if problem:
            raise RecipeError(f"{spec!r} {problem}", file=source, key=where)
        if "{dir}" in spec:
            return
    loader, builtin = _loader(sensor)
    if isinstance(spec, str) and spec not in builtin:
        path = Path(spec) if Path(spec).is_absolute() or base_dir is None else base_dir / spec
        if not path.is_file():
            raise RecipeError(f"no {sensor} profile {spec!r}: not a built-in ({', '.join(builtin)})"
                              f"{suggest(spec, builtin)} nor a file ({str(path)!r} does not exist); a file next to "
                              "each input is written '{dir}/NAME'", file=source, key=where)
    try:
        loader(spec, base_dir=base_dir)
    except InputError as e:
        raise RecipeError(f"invalid {sensor} profile: {e}", file=source, key=where) from None


def _loader(sensor: str):
    if sensor == "camera":
        from .profiles.camera import BUILTIN, load_camera_profile
        return load_camera_profile, BUILTIN
    if sensor == "lidar":
        from .profiles.lidar import BUILTIN, load_lidar_profile
        return load_lidar_profile, BUILTIN
    from .profiles.radar import BUILTIN, load_radar_profile
    return load_radar_profile, BUILTIN
