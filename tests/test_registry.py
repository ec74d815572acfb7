"""The model index (``model_index.MODULES``) that lets a run import only the models its recipe names."""

from __future__ import annotations

import subprocess
import sys

from roadview_noise import registry
from roadview_noise.model_index import MODULES


def test_index_names_every_registered_model_and_its_module():
    models = {k: c.__module__ for k, c in registry.load_all().items()
              if c.__module__.startswith("roadview_noise.models.")}
    missing = sorted(set(models) - set(MODULES))
    wrong = sorted(k for k in models if k in MODULES and MODULES[k] != models[k])
    extra = sorted(set(MODULES) - set(models))
    assert not (missing or wrong or extra), (
        f"roadview_noise/model_index.py is stale (missing {missing}, wrong module {wrong}, no such model {extra}); "
        "regenerate it: .venv/bin/python -m roadview_noise.registry")
    assert registry.index_text() == open(registry.__file__.replace("registry.py", "model_index.py")).read()


def test_a_recipe_imports_only_its_models():
    """Of the modules that define models, loading and checking a recipe imports only its models' (shared helper
    modules such as ``models.radar.weather`` may come along)."""
    code = ("import sys\n"
            "from roadview_noise.recipe import load_recipe\n"
            "r = load_recipe('recipes/weather-fog-radar.yaml'); r.sensor\n"
            "from roadview_noise.model_index import MODULES\n"
            "print(sorted(m for m in sys.modules if m in MODULES.values()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=registry.__file__.rsplit("/roadview_noise/", 1)[0]).stdout.strip()
    assert out == "['roadview_noise.models.radar.fog']"


def test_an_unindexed_model_is_still_found(monkeypatch):
    monkeypatch.setattr(registry, "MODULES", {})
    assert registry.get_model("fog.lidar").id == "fog.lidar"
    assert registry.known("fog.lidar") and not registry.known("fog.nowhere")


def test_the_fork_server_guess_matches_every_shipped_recipe():
    """``prestart.guess_modules`` (the YAML only, before the check) names exactly what the checked recipe needs, so
    the fork server the CLI starts early is never restarted for a shipped recipe."""
    from pathlib import Path

    from roadview_noise.bag_recipe import is_bag_recipe, read_recipe_yaml
    from roadview_noise.prestart import guess_modules
    from roadview_noise.recipe import load_recipe
    from roadview_noise.runner import worker_modules

    recipes = [p for p in sorted(Path(registry.__file__).parents[1].joinpath("recipes").glob("*.yaml"))
               if not is_bag_recipe(read_recipe_yaml(p))]
    assert len(recipes) > 20
    for path in recipes:
        assert set(guess_modules(path)) == set(worker_modules(load_recipe(path))), path.name
    assert guess_modules(Path(registry.__file__)) is None                  # not a recipe: nothing guessed
