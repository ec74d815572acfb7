"""Command-line overrides of a recipe's input settings (``rvnoise augment --depth/--depth-source/--camera-profile/...``).

They are applied to the recipe itself, which is then validated again: the resolved recipe in ``run.json``, its
sha256, ``replay`` and ``--resume`` all see the values that were run, exactly as if the recipe had said them.
Profile files given on the command line are relative to the working directory (made absolute here); ``--depth``
is a sidecar pattern relative to each image's folder, as in the recipe.
"""

from __future__ import annotations

from pathlib import Path

from .recipe import Recipe, parse_recipe

INPUT_OVERRIDES = ("depth", "depth_source", "camera_profile", "lidar_profile", "radar_profile")


def with_input_overrides(recipe: Recipe, **values: str | None) -> Recipe:
    """``recipe`` with ``inputs.<key>`` replaced by every value given (None: keep the recipe's); RecipeError for a
    bad value, naming the key."""
    unknown = set(values) - set(INPUT_OVERRIDES)
    if unknown:
        raise ValueError(f"no input override {sorted(unknown)}; expected {INPUT_OVERRIDES}")
    changes = {k: v for k, v in values.items() if v is not None}
    if not changes:
        return recipe
    for key in ("camera_profile", "lidar_profile", "radar_profile"):
        if key in changes and Path(changes[key]).is_file():
            changes[key] = str(Path(changes[key]).resolve())
    data = recipe.spec.model_dump(mode="json", by_alias=True)
    data["inputs"].update(changes)
    return parse_recipe(data, source=f"{recipe.source} (with --{', --'.join(k.replace('_', '-') for k in changes)})",
                        base_dir=recipe.base_dir)
