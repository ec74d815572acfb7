"""Warm a process once, before it forks workers or takes tasks: numba's compiler initialised (≈ 0.25 s) and every
compiled kernel of the loaded modules read from numba's on-disk cache (≈ 3 ms each), which each worker would
otherwise pay on its first file.

The process that forks the local workers calls :func:`warm_up` before the first fork (``executor``), so every
worker starts warm; a Dask worker calls it from its plugin. Kernels not in the cache yet (a first run after an
install or an edit) are compiled where they are first called, and cached for the next run.
"""

from __future__ import annotations

import gc

_done = False


def warm_up() -> int:
    """Load the cached compiled versions of every numba kernel of the package's loaded modules; returns how many.
    Uses numba's cache index (``Dispatcher._cache``), so an unknown numba version costs only the warm-up."""
    global _done
    if _done:
        return 0
    _done = True
    try:
        from numba.core.registry import CPUDispatcher
    except ImportError:                              # pragma: no cover - numba is a dependency
        return 0
    loaded = 0
    kernels = [o for o in gc.get_objects() if isinstance(o, CPUDispatcher)
               and getattr(o.py_func, "__module__", "").startswith("roadview_noise.")]
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
    return loaded
