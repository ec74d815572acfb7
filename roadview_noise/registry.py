"""MODELS: model id → class. ``@register`` adds a class; every module under ``roadview_noise.models`` is imported
by :func:`load_all`, so a new model needs no edit anywhere else."""

from __future__ import annotations

import difflib
import importlib
import pkgutil

from .errors import ModelError

MODELS: dict[str, type] = {}


def register(cls: type) -> type:
    """Class decorator: register a finished model under its ``id``."""
    if cls.id in MODELS and MODELS[cls.id] is not cls:
        raise ValueError(f"model id {cls.id!r} registered twice ({MODELS[cls.id].__module__}, {cls.__module__})")
    MODELS[cls.id] = cls
    return cls


_loaded = False


def load_all() -> dict[str, type]:
    """Import every module under ``roadview_noise.models`` (once) and return the registry."""
    global _loaded
    if not _loaded:
        from . import models

        for info in pkgutil.walk_packages(models.__path__, models.__name__ + "."):
            importlib.import_module(info.name)
        _loaded = True
    return MODELS


def plugin_modules() -> tuple[str, ...]:
    """Modules outside ``roadview_noise.models`` that registered models in this process (a script's or a test's own
    models): the batch workers import them, so they know the same models as the process that plans the run."""
    return tuple(sorted({c.__module__ for c in MODELS.values()
                         if not c.__module__.startswith(__package__ + ".models") and c.__module__ != "__main__"}))


def suggest(name: str, choices) -> str:
    close = difflib.get_close_matches(name, list(choices), n=3, cutoff=0.5)
    return f" (did you mean {', '.join(repr(c) for c in close)}?)" if close else ""


def get_model(model_id: str) -> type:
    models = load_all()
    try:
        return models[model_id]
    except KeyError:
        raise ModelError(f"unknown model {model_id!r}{suggest(model_id, models)}; `rvnoise list` shows all") from None
