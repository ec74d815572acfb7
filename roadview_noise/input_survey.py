"""What an input tree holds when a recipe's globs match nothing in it: the message that says why and what to write.

A new user's two usual mistakes are a recipe for another sensor (a LiDAR recipe on a folder of photos) and files
laid out otherwise than the globs expect (photos at the top of IN where a shipped recipe reads ``camera/**``). The
tree is looked at up to :data:`LOOK_AT` entries (a huge tree costs no more), by suffix only: images and raw frames
are camera files, ``.pcd``/``.bin``/``.ply`` clouds are LiDAR or radar files.
"""

from __future__ import annotations

import os
from pathlib import Path

from .dataset import DEFAULT_GLOBS
from .recipe import Recipe

LOOK_AT = 20_000
KIND_OF_SENSOR = {"camera": "camera", "lidar": "cloud", "radar": "cloud"}
KIND_TEXT = {"camera": "camera image(s) or raw frame(s)", "cloud": "point cloud(s)"}
KIND_PLURAL = {"camera": "camera images or raw frames", "cloud": "point clouds"}
RAW_SUFFIXES = tuple(g.rsplit("*", 1)[-1] for g in DEFAULT_GLOBS["raw"])
SUFFIXES = {"camera": tuple(g.rsplit("*", 1)[-1] for g in DEFAULT_GLOBS["camera"]) + RAW_SUFFIXES,
            "cloud": (".pcd", ".bin", ".ply")}


def survey(root: Path) -> dict[str, tuple[int, str]]:
    """Per kind (``camera``, ``cloud``): (files found, the first one's path relative to ``root``), looking at no
    more than :data:`LOOK_AT` entries; symlinked folders are not followed."""
    found: dict[str, tuple[int, str]] = {}
    seen = 0
    for folder, dirs, files in os.walk(root):
        dirs.sort()
        for name in sorted(files):
            seen += 1
            if seen > LOOK_AT:
                return found
            kind = next((k for k, sfx in SUFFIXES.items() if name.lower().endswith(sfx)), None)
            if kind is not None:
                n, first = found.get(kind, (0, ""))
                found[kind] = (n + 1, first or os.path.relpath(os.path.join(folder, name), root).replace(os.sep, "/"))
        seen += len(dirs)
    return found


def no_inputs_message(root: Path, shown_root: str, recipe: Recipe) -> str:
    """Why a plan is empty: the recipe's globs, and what the tree holds instead (files of the recipe's kind that the
    globs miss, with a glob that takes them, or only files of another sensor's kind)."""
    sensor, inputs = recipe.sensor, recipe.spec.inputs
    globs = "; ".join(f"inputs.{k}: {getattr(inputs, k)}" for k in ("camera", "raw", "lidar", "radar")
                      if getattr(inputs, k))
    text = f"no {sensor} inputs under {shown_root!r} match the recipe's inputs{f' ({globs})' if globs else ''}"
    found = survey(root)
    kind = KIND_OF_SENSOR[sensor]
    if kind in found:
        n, first = found[kind]
        suffix = "." + first.rsplit(".", 1)[-1] if "." in first.rpartition("/")[2] else ""
        key = "raw" if sensor == "camera" and first.lower().endswith(RAW_SUFFIXES) else sensor
        which = f"if they are {sensor} scans, " if kind == "cloud" else ""
        return (f"{text}; the folder holds {n} {KIND_TEXT[kind]} they miss (e.g. {first!r}): {which}set inputs.{key} "
                f"to a glob that matches them, e.g. '**/*{suffix}'")
    others = [f"{found[k][0]} {KIND_TEXT[k]} (e.g. {found[k][1]!r})" for k in found]
    if others:
        return (f"{text}; the folder holds {' and '.join(others)} and no {KIND_PLURAL[kind]}: this recipe's chain "
                f"({' → '.join(recipe.model_ids)}) is for {sensor} data; choose a recipe for the data you have "
                "(`rvnoise list`, recipes/)")
    example = (", e.g. camera: 'samples/CAM_*/*.jpg' (nuScenes), '**/image_2/*.png' (KITTI)"
               if sensor == "camera" else "")
    return f"{text}; the folder holds no file rvnoise reads (images, raw frames, point clouds): set the globs of " \
           f"your layout{example}"
