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


def plugin_models() -> tuple[tuple[str, str], ...]:
    """``(module, qualified name)`` of the models registered in this process from outside ``roadview_noise.models``
    (a script's or a test's own models, registered at import or later): batch workers :func:`adopt` them, so they
    know the same models as the process that plans the run. Classes defined in ``__main__`` or inside a function
    cannot be imported by name and are left out."""
    return tuple(sorted((c.__module__, c.__qualname__) for c in MODELS.values()
                        if not c.__module__.startswith(__package__ + ".models") and c.__module__ != "__main__"
                        and "<locals>" not in c.__qualname__))


def adopt(models: tuple[tuple[str, str], ...]) -> None:
    """Import and register the models :func:`plugin_models` named (in a worker process)."""
    for module, qualname in models:
        cls = importlib.import_module(module)
        for part in qualname.split("."):
            cls = getattr(cls, part)
        MODELS.setdefault(cls.id, cls)


def suggest(name: str, choices) -> str:
    close = difflib.get_close_matches(name, list(choices), n=3, cutoff=0.5)
    return f" (did you mean {', '.join(repr(c) for c in close)}?)" if close else ""


def get_model(model_id: str) -> type:
    models = load_all()
    try:
        return models[model_id]
    except KeyError:
        raise ModelError(f"unknown model {model_id!r}{suggest(model_id, models)}; `rvnoise list` shows all") from None
