"""Warm a worker process once, before it forks or takes tasks: every compiled kernel loaded from numba's on-disk
cache (:func:`load_cached`: ≈ 0.3 s that each worker would otherwise pay on its first file), without setting up
numba's compiler, which cached code does not need (≈ 0.2 s of every run's start-up until round 15).

The fork server imports this module (``executor.PRELOAD``) after the models, so every worker forked from it starts
warm; a Dask worker calls :func:`warm_up` from its plugin. Kernels not in the cache yet (a first run after an
install or an edit) are compiled where they are first called, as before, and cached for the next run.

Kernels that only one kind of data calls (:data:`KIND_KERNELS`: the sRGB edges, the frame metrics and the lens and
windscreen warps for camera and raw frames, the point-cloud metrics, codec, return and beam geometry for LiDAR and
radar clouds) are loaded only when a model of that kind is loaded: a radar run does not load the frame metrics'
kernels (≈ 3–15 ms each) nor the warps' (≈ 50 ms once a camera run has cached them), nor a camera run the
point-cloud ones. With no model loaded, every kernel is. Kernels that only other kernels call
(:func:`inner_only`: the PNG filter's rows, the luminance sums, the sRGB code steps) are not loaded on their own:
their code is in their callers' cached code, and nothing calls them from Python.

When a camera model is loaded, physics/srgb.py's encode tables are built here too, so that the workers inherit
them instead of each building them on its first file (≈ 40 ms).
When a model whose tables are kept on disk is loaded (:mod:`roadview_noise.table_cache`), the cache's code
version is computed here once (≈ 25 ms that each worker would pay on its first table).
"""

from __future__ import annotations

import sys
from types import CodeType, FunctionType, ModuleType
from typing import Any

_done = False
# The kernels only one kind of data calls, by module (None: all of the module's); a model's kind is its package
_IMAGE = {"roadview_noise.physics.srgb": None, "roadview_noise.luminance": None, "roadview_noise.io.png": None,
          "roadview_noise.physics.bilinear_table": None, "roadview_noise.physics.brown_conrady": None,
          "roadview_noise.metrics": ("_grey_statistics", "_grey_codes", "_depth_bin_index", "_ssim_map",
                                     "_ssim_local_means", "_filter_row", "_filter_column", "_window_sum")}
_POINTS = {"roadview_noise.io.pointcloud": None, "roadview_noise.physics.return_ranges": None,
           "roadview_noise.physics.lidar_geometry": None,
           "roadview_noise.metrics": ("_pass", "_plain_pass", "_grid_pass", "_list_pass", "_step_pass", "_same_pass",
                                      "_counted_plain_pass", "_counted_grid_pass", "_counted_list_pass",
                                      "_counted_step_pass", "_counted_same_pass", "_unlinked_step_pass",
                                      "_known_step_pass", "_step_rows",
                                      "_same_position", "_is_return", "_compose", "_same_ray", "_change",
                                      "_mean_change_through", "_return_value_sum", "_radar_chain_pass")}
KIND_KERNELS = {"camera": _IMAGE, "lidar": _POINTS, "radar": _POINTS}


def loaded_kinds() -> set[str]:
    """The kinds of data (:data:`KIND_KERNELS`) the loaded model modules take; all of them when none is loaded."""
    kinds = {name.split(".")[2] for name in list(sys.modules)
             if name.startswith("roadview_noise.models.") and name.count(".") >= 3} & set(KIND_KERNELS)
    return kinds or set(KIND_KERNELS)


def needed(module: str, name: str, kinds: set[str]) -> bool:
    """Whether a run on ``kinds`` of data may call kernel ``name`` of ``module``: it is listed for no kind in
    :data:`KIND_KERNELS`, or for one of ``kinds``."""
    listed = [kind for kind, table in KIND_KERNELS.items()
              if module in table and (table[module] is None or name in table[module])]
    return not listed or bool(kinds.intersection(listed))


def _names(code: CodeType) -> set[str]:
    """The names a code object and the functions nested in it refer to (globals and attributes)."""
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, CodeType):
            names |= _names(const)
    return names


def inner_only(kernels: dict[int, Any], modules: list[ModuleType]) -> set[int]:
    """The ids of ``kernels`` that only other kernels call: named in a kernel's code, and in no Python function or
    method, nor held in a module-level container, of ``modules``. Their machine code is in their callers' cached
    code, so loading it on its own is wasted (≈ 3–10 ms each); one that Python calls after all (through a name this
    scan cannot see) loads on its first call."""
    from_kernels: set[str] = set()
    from_python: set[str] = set()
    held: set[int] = set()
    for module in modules:
        values = list(vars(module).values())
        for value in list(values):
            if isinstance(value, type) and value.__module__ == module.__name__:
                values += [getattr(v, "__func__", getattr(v, "fget", v)) for v in vars(value).values()]
            elif isinstance(value, (dict, list, tuple)):
                held.update(map(id, value.values() if isinstance(value, dict) else value))
        for value in values:
            if id(value) in kernels:
                from_kernels |= _names(value.py_func.__code__)
            elif isinstance(value, FunctionType):
                from_python |= _names(value.__code__)
    return {i for i, k in kernels.items() if i not in held and k.py_func.__name__ in from_kernels - from_python}


def load_cached(kernel: Any) -> int:
    """Load ``kernel``'s cached machine code for this CPU and source, every signature in its cache index; returns
    how many. Unlike ``kernel.compile(signature)``, which first sets numba's compiler up (``BaseContext.refresh``:
    every typing and lowering registry, numba's NumPy support, ``scipy.linalg`` for its BLAS check — ≈ 0.2 s once
    per process), this only initialises numba's runtime (NRT), which the cached code links against: calling a
    loaded kernel needs nothing else. A signature that is not cached compiles where it is first called, and sets
    the compiler up then, as before."""
    from numba.core.compiler_lock import global_compiler_lock
    from numba.core.runtime import rtsys

    cache, context = kernel._cache, kernel.targetctx
    codegen, loaded = context.codegen(), 0
    with global_compiler_lock:
        rtsys.initialize(context)
        for key in cache._cache_file._load_index():
            # another CPU's or an edited source's code is compiled where it is first called
            if cache._index_key(key[0], codegen) != key or key[0] in kernel.overloads:
                continue
            result = cache._load_overload(key[0], context)
            if result is not None and not result.objectmode:
                context.insert_user_function(result.entry_point, result.fndesc, [result.library])
                kernel.add_overload(result)
                loaded += 1
    return loaded


def warm_up() -> int:
    """Load the cached compiled versions of every numba kernel of the package's loaded modules that the loaded
    models' kinds of data may call (:func:`needed`; module-level kernels: ``@jit`` decorates module functions; a scan
    of the module dicts, not of every object) from Python (:func:`inner_only`); returns how many. Uses numba's cache
    index (``Dispatcher._cache``), so an unknown numba version costs only the warm-up."""
    global _done
    if _done:
        return 0
    _done = True
    try:
        from numba.core.registry import CPUDispatcher
    except ImportError:                              # pragma: no cover - numba is a dependency
        return 0
    loaded, kinds = 0, loaded_kinds()
    modules = [module for name, module in list(sys.modules.items()) if name.startswith("roadview_noise.")]
    kernels = {id(o): o for module in modules for o in list(vars(module).values()) if isinstance(o, CPUDispatcher)
               and getattr(o.py_func, "__module__", "").startswith("roadview_noise.")
               and needed(o.py_func.__module__, o.py_func.__name__, kinds)}
    inner = inner_only(kernels, modules)
    for kernel in [k for i, k in kernels.items() if i not in inner]:
        try:
            loaded += load_cached(kernel)
        except Exception:                            # a numba internal changed: that kernel loads on first use
            continue
    if any(name.startswith("roadview_noise.models.camera.") for name in sys.modules):
        from .physics import srgb

        srgb.encode8_table()
        srgb.encode16_table()
    if "roadview_noise.table_cache" in sys.modules:         # a model with tables on disk is loaded
        from . import table_cache

        table_cache.code_version()
    return loaded


warm_up()
