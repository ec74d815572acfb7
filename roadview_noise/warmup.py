"""Warm a worker process once, before it forks or takes tasks: every compiled kernel loaded from numba's on-disk
cache, and numba's compiler initialised (≈ 0.3 s that each worker would otherwise pay on its first file).

The fork server imports this module (``executor.PRELOAD``) after the models, so every worker forked from it starts
warm; a Dask worker calls :func:`warm_up` from its plugin. Kernels not in the cache yet (a first run after an
install or an edit) are compiled where they are first called, as before, and cached for the next run.

A model module whose first file builds a constant table may define ``warm_up()``: it is called here too, once, so
that the workers inherit the table instead of each building it; when a camera model is loaded, the sRGB tables of
:data:`CAMERA_TABLES` are built too.
"""

from __future__ import annotations

import sys

_done = False
# physics/srgb.py's lookup tables that every camera output (and the camera metrics) needs, built on first use
# (≈ 40 ms of one core per worker): built here when a camera model is loaded, so that every worker inherits them
CAMERA_TABLES = ("encode8_table", "encode16_table")


def warm_up() -> int:
    """Load the cached compiled versions of every numba kernel of the package's loaded modules (module-level
    kernels: ``@jit`` decorates module functions; a scan of the module dicts, not of every object); returns how
    many. Uses numba's cache index (``Dispatcher._cache``), so an unknown numba version costs only the warm-up."""
    global _done
    if _done:
        return 0
    _done = True
    try:
        from numba.core.registry import CPUDispatcher
    except ImportError:                              # pragma: no cover - numba is a dependency
        return 0
    loaded = 0
    kernels = {id(o): o for name, module in list(sys.modules.items()) if name.startswith("roadview_noise.")
               for o in list(vars(module).values()) if isinstance(o, CPUDispatcher)
               and getattr(o.py_func, "__module__", "").startswith("roadview_noise.")}.values()
    for kernel in kernels:
        try:
            cache = kernel._cache
            codegen = kernel.targetctx.codegen()
            for key in cache._cache_file._load_index():
                if cache._index_key(key[0], codegen) == key:      # this CPU and this source: a load, not a compile
                    kernel.compile(key[0])
                    loaded += 1
        except Exception:                            # a numba internal changed: that kernel loads on first use
            continue
    for name, module in list(sys.modules.items()):
        if name.startswith("roadview_noise.models.") and callable(getattr(module, "warm_up", None)):
            module.warm_up()
    if any(name.startswith("roadview_noise.models.camera.") for name in sys.modules):
        from .physics import srgb

        for table in CAMERA_TABLES:
            build = getattr(srgb, table, None)
            if callable(build):
                build()
    return loaded


warm_up()
