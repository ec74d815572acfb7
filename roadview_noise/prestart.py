"""Start the workers' fork server before the recipe is checked, so that it imports the recipe's models while the
main process parses and validates the recipe and walks the input tree (issue 19: start-up).

:func:`guess_modules` reads the modules from the recipe's YAML (its chain's models, or its CNF's for its sensor)
through ``model_index`` without importing a model. A wrong guess costs only time: the runner asks for the modules
of the checked recipe (:func:`worker_modules`) and the fork server is restarted if it lacks one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Sequence

# What a worker would otherwise import on its first file (dataset.load/save, the sensor's profile, libraries the
# models import on first use): imported by the fork server once for all workers. A LiDAR or radar worker reads and
# writes clouds only: the image and raw readers/writers (tifffile) are for camera runs.
FIRST_USE_IMPORTS = ["roadview_noise.io.pointcloud"]
SENSOR_FIRST_USE_IMPORTS = {
    "camera": ["roadview_noise.io.image", "roadview_noise.io.raw", "roadview_noise.camera_inputs",
               "roadview_noise.io.depth", "roadview_noise.depth.holes", "roadview_noise.depth.calibration",
               "roadview_noise.profiles.camera"],
    "lidar": ["roadview_noise.profiles.lidar"],
    "radar": ["roadview_noise.profiles.radar"],
}
MODEL_FIRST_USE_IMPORTS = {          # CA-CFAR's tier ratios (physics/radar_cfar.py) solve with brentq on first use
    "roadview_noise.models.radar.rain": ["scipy.optimize"],
    "roadview_noise.models.radar.snow": ["scipy.optimize"],
}


def worker_modules(sensor: str, model_modules: Iterable[str]) -> list[str]:
    """The modules the fork server imports for a run on ``sensor`` data with models from ``model_modules``."""
    model_modules = list(model_modules)
    extra = [m for module in model_modules for m in MODEL_FIRST_USE_IMPORTS.get(module, ())]
    return FIRST_USE_IMPORTS + SENSOR_FIRST_USE_IMPORTS.get(sensor, []) + list(dict.fromkeys(extra)) + model_modules


def guess_modules(recipe_path: Path) -> list[str] | None:
    """:func:`worker_modules` of the recipe at ``recipe_path`` as far as its YAML tells without checking it; None
    when it names no indexed model (a malformed recipe fails later, at its check, with the proper message)."""
    import yaml

    from .model_index import MODULES

    try:
        body = yaml.safe_load(Path(recipe_path).read_text(encoding="utf-8"))
    except Exception:                    # the recipe check reports it
        return None
    if not isinstance(body, dict):
        return None
    ids = [step.get("model") for step in body.get("chain") or [] if isinstance(step, dict)]
    if body.get("cnf") is not None:
        from .compound import CNFS

        chains = getattr(CNFS.get(str(body["cnf"]).upper()), "chains", {})
        sensor = body.get("sensor") or (next(iter(chains)) if len(chains) == 1 else None)
        ids += chains.get(sensor, ())
    ids = [i for i in ids if isinstance(i, str) and i in MODULES]
    if not ids:
        return None
    return worker_modules(ids[0].rsplit(".", 1)[-1], dict.fromkeys(MODULES[i] for i in ids))


def start_for(recipe_path: Path) -> None:
    """Start the fork server for the recipe at ``recipe_path`` (no-op if nothing can be guessed)."""
    modules = guess_modules(recipe_path)
    if modules is not None:
        from .executor import start_server

        start_server(modules)


def local_run_recipe(argv: Sequence[str]) -> str | None:
    """The recipe of a plain local ``rvnoise augment`` run from its raw arguments: no ``--help``, ``--dry-run`` or
    other backend; a recipe given as ``--recipe R``, ``--recipe=R``, ``-r R`` or ``-rR``. None otherwise."""
    args = list(argv[1:])
    if args[:1] != ["augment"] or {"--help", "--dry-run"} & set(args):
        return None
    recipe = None
    for i, a in enumerate(args):
        value = args[i + 1] if i + 1 < len(args) else None
        if a in ("--backend", "--recipe", "-r") and value is None:
            return None
        if a == "--backend" and value != "local" or a.startswith("--backend=") and a != "--backend=local":
            return None
        if a in ("--recipe", "-r"):
            recipe = value
        elif a.startswith("--recipe="):
            recipe = a.split("=", 1)[1]
        elif a.startswith("-r") and not a.startswith("--") and len(a) > 2:
            recipe = a[2:]
    return recipe or None


def start_from_command_line(argv: Sequence[str]) -> None:
    """Start the fork server for :func:`local_run_recipe` before the command line's own imports (typer, pydantic:
    ≈ 0.15 s). The command still calls :func:`start_for` once parsed, a no-op when this one started the server (a
    ROS bag's recipe names no chain: nothing is started)."""
    recipe = local_run_recipe(argv)
    if recipe:
        start_for(Path(recipe))
