"""Built-in sensor profiles and loaders from files (camera intrinsics, LiDAR beam tables, radar parameters).

Every sensor's profile is given the same way (:func:`load_profile`): a built-in name, a file, or a mapping
``{base: NAME_OR_FILE, <field>: value, ...}`` overriding fields of a base profile (a YAML file may hold the same
mapping)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping

import yaml

from ..errors import InputError


def load_profile(spec: str | Mapping[str, Any] | None, *, kind: str, builtin: Mapping[str, Callable[[], Any]],
                 default: Callable[[], Any], override: Callable[[Any, dict, str], Any],
                 base_dir: Path | None = None, loaders: Mapping[str, Callable[[Path], Any]] | None = None) -> Any:
    """Resolve a profile spec. ``override(base, fields, source)`` applies a mapping of fields to a base profile;
    ``loaders`` maps file suffixes (e.g. ``.json``) to readers of other file formats."""
    def again(s, d):
        return load_profile(s, kind=kind, builtin=builtin, default=default, override=override, base_dir=d,
                            loaders=loaders)

    if spec is None:
        return default()
    if isinstance(spec, Mapping):
        fields = dict(spec)
        return override(again(fields.pop("base", None), base_dir), fields, f"{kind} profile")
    if spec in builtin:
        return builtin[spec]()
    path = Path(spec) if base_dir is None or Path(spec).is_absolute() else base_dir / spec
    if not path.is_file():
        raise InputError(f"no {kind} profile {spec!r}: not a built-in ({', '.join(builtin)}) nor a file",
                         file=str(path))
    reader = (loaders or {}).get(path.suffix.lower())
    if reader is not None:
        return reader(path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise InputError(f"not valid YAML ({e})", file=str(path)) from None
    if not isinstance(data, dict):
        raise InputError(f"a {kind} profile file must hold a mapping", file=str(path))
    return override(again(data.pop("base", None), path.parent), data, str(path))


def check_keys(fields: Mapping[str, Any], allowed: set[str], kind: str, source: str) -> None:
    unknown = set(fields) - allowed
    if unknown:
        raise InputError(f"unknown {kind} profile keys {sorted(unknown)} (allowed: {sorted(allowed)})", file=source)
