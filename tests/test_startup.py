"""Start-up (issue 19): the fork server started from the raw command line, before typer loads; the server leaving
at once when the run's process exits."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from roadview_noise import prestart
from test_cli import tree  # noqa: F401 - fixture


@pytest.mark.parametrize("argv, recipe", [
    (["augment", "--recipe", "r.yaml", "in", "out"], "r.yaml"),
    (["augment", "in", "out", "-r", "r.yaml", "--workers", "2"], "r.yaml"),
    (["augment", "--recipe=r.yaml", "in", "out", "--backend", "local"], "r.yaml"),
    (["augment", "-rr.yaml", "in", "out", "--backend=local"], "r.yaml"),
    (["augment", "--recipe", "r.yaml", "in", "out", "--dry-run"], None),
    (["augment", "--recipe", "r.yaml", "in", "out", "--backend", "dask"], None),
    (["augment", "--recipe", "r.yaml", "in", "out", "--backend=dask"], None),
    (["augment", "--recipe", "r.yaml", "--help"], None),
    (["augment", "in", "out", "--recipe"], None),
    (["validate", "r.yaml"], None),
    ([], None),
])
def test_fork_server_started_from_the_raw_command_line(monkeypatch, argv, recipe):
    started = []
    monkeypatch.setattr(prestart, "start_for", lambda path: started.append(str(path)))
    prestart.start_from_command_line(["rvnoise", *argv])
    assert started == ([recipe] if recipe else [])


def test_the_fork_server_leaves_without_tearing_down(tmp_path):
    """A module the server preloaded registers an exit handler; the server's fast exit, imported after it, runs
    first (handlers run last-in first-out), so the handler never runs: the interpreter is not torn down. The run's
    process still gets its result and its pipes close."""
    marker = tmp_path / "torn-down"
    (tmp_path / "teardown_marker.py").write_text(textwrap.dedent(f"""
        import atexit
        atexit.register(lambda: open({str(marker)!r}, "w").close())
    """))
    script = textwrap.dedent(f"""
        from roadview_noise.executor import ProcessExecutor
        from tests.test_executor import work

        print(dict(ProcessExecutor(work, {{}}, 1, models=["teardown_marker"]).map([4])))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          cwd=str(Path(__file__).resolve().parents[1]),
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(
                              filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")]))})   # the server's path
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "{4: (4, 16)}"
    assert not marker.exists()


def test_run_json_records_the_worker_start(tmp_path, tree):
    """run.json's ``worker_start_seconds``: from starting the workers to the first one ready for tasks, a part of
    the run's wall time."""
    from test_cli import CAMERA, _recipe

    from roadview_noise.recipe import load_recipe
    from roadview_noise.runner import run

    run(load_recipe(_recipe(tmp_path, CAMERA)), tree, tmp_path / "o", workers=2, progress=False, echo=lambda m: None)
    record = json.loads((tmp_path / "o" / "run.json").read_text())
    assert 0 <= record["worker_start_seconds"] < record["wall_seconds"]


@pytest.mark.parametrize("model, built", [("roadview_noise.models.camera.fog", "1 1"),
                                          ("roadview_noise.models.radar.fog", "0 0")])
def test_warm_up_builds_the_srgb_tables_for_camera_runs_only(model, built):
    """The fork server's warm-up builds physics/srgb.py's tables once when a camera model is loaded (the workers
    inherit them), and not for other sensors' runs."""
    code = (f"import {model}, roadview_noise.warmup; from roadview_noise.physics import srgb; "
            "print(srgb.encode8_table.cache_info().currsize, srgb.encode16_table.cache_info().currsize)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == built


@pytest.mark.parametrize("model, computed", [("roadview_noise.models.lidar.snow", "1"),
                                             ("roadview_noise.models.radar.rain", "1"),
                                             ("roadview_noise.models.camera.fog", "0")])
def test_warm_up_computes_the_table_cache_version_where_tables_are_cached(model, computed):
    """The fork server's warm-up computes the table cache's code version (roadview_noise/table_cache.py) once when
    a model whose tables are kept on disk is loaded (the workers inherit it), and does not load the cache for
    camera runs."""
    code = (f"import sys, {model}, roadview_noise.warmup; t = sys.modules.get('roadview_noise.table_cache'); "
            "print(t.code_version.cache_info().currsize if t else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == computed
def test_every_kernel_listed_by_kind_exists():
    """The warm-up's lists of kernels by kind of data name real kernels (a renamed kernel would be loaded on first
    use instead, silently)."""
    import importlib

    from numba.core.registry import CPUDispatcher

    from roadview_noise.warmup import KIND_KERNELS

    for table in KIND_KERNELS.values():
        for module, names in table.items():
            kernels = {o.py_func.__name__ for o in vars(importlib.import_module(module)).values()
                       if isinstance(o, CPUDispatcher)}
            assert kernels and set(names or ()) <= kernels, (module, set(names or ()) - kernels)


def test_warm_up_loads_only_the_kernels_of_the_loaded_kinds():
    """A radar run's warm-up skips the frame metrics and sRGB kernels, a camera run's the point-cloud ones; kernels
    of no listed kind (a model's physics) and runs with no model loaded keep everything."""
    from roadview_noise.warmup import needed

    assert not needed("roadview_noise.metrics", "_ssim_map", {"radar"})
    assert not needed("roadview_noise.physics.srgb", "_encode8_reversed_kernel", {"lidar"})
    assert needed("roadview_noise.metrics", "_list_pass", {"radar"})
    assert not needed("roadview_noise.metrics", "_list_pass", {"camera"})
    assert needed("roadview_noise.metrics", "_ssim_map", {"camera"})
    assert needed("roadview_noise.physics.firing_grid", "_cells", {"camera"})
    assert needed("roadview_noise.metrics", "_ssim_map", {"camera", "radar"})
    code = "import roadview_noise.models.radar.fog, roadview_noise.warmup as w; print(sorted(w.loaded_kinds()))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "['radar']"
    from roadview_noise.warmup import KIND_KERNELS

    code = "import roadview_noise.warmup as w; print(sorted(w.loaded_kinds()))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.stdout.strip() == str(sorted(KIND_KERNELS)), done.stderr


def test_warm_up_skips_kernels_only_other_kernels_call():
    """A kernel that only other kernels call is compiled into its callers' cached code: the warm-up does not load it
    on its own. One that Python calls (a function, a method, a module-level table) is loaded, and so is a camera
    run's every kernel that it calls, but not the LiDAR geometry's."""
    import types

    from numba.core.registry import CPUDispatcher

    from roadview_noise.warmup import inner_only, needed

    module = types.ModuleType("kernels_of_a_test")
    exec(textwrap.dedent("""
        import numba

        @numba.njit
        def helper(x):
            return x + 1

        @numba.njit
        def shared(x):
            return x - 1

        @numba.njit
        def tabled(x):
            return x

        @numba.njit
        def kernel(x):
            return helper(x) + shared(x) + tabled(x)

        TABLE = {"t": tabled}

        def entry(x):
            return kernel(x)

        class User:
            def method(self, x):
                return shared(x)
        """), module.__dict__)
    kernels = {id(o): o for o in vars(module).values() if isinstance(o, CPUDispatcher)}
    assert {kernels[i].py_func.__name__ for i in inner_only(kernels, [module])} == {"helper"}
    from roadview_noise.io import png

    real = {id(o): o for o in (png._unfilter, png._paeth_row)}
    assert inner_only(real, [png]) == {id(png._paeth_row)}
    assert not needed("roadview_noise.physics.lidar_geometry", "_azimuths", {"camera"})
    assert needed("roadview_noise.physics.lidar_geometry", "_azimuths", {"lidar"})


def test_warm_up_loads_cached_kernels_without_setting_up_the_compiler():
    """The warm-up loads a kernel's cached code without numba's compiler set-up (its typing and lowering
    registries, numba's NumPy support, scipy.linalg: ≈ 0.2 s of every run's start-up); the loaded kernel then runs
    without it and gives what a process that compiled or loaded it the usual way gives."""
    call = ("import numpy as np; from roadview_noise.physics import srgb; "
            "x = np.linspace(-0.1, 1.1, 30001, dtype=np.float32); "
            "print((srgb.linear_to_code(x, 8).tobytes() + srgb.linear_to_code(x, 16).tobytes()).hex())")
    usual = subprocess.run([sys.executable, "-c", call], capture_output=True, text=True, timeout=300)
    assert usual.returncode == 0, usual.stderr             # compiled (and cached) or loaded with the set-up
    warm = textwrap.dedent("""
        import sys
        from numba.core.cpu import CPUContext
        set_up = []
        CPUContext.refresh = lambda self: set_up.append(self)
        from roadview_noise.physics import srgb
        import roadview_noise.warmup
        loaded = bool(srgb._encode8_kernel.overloads) and bool(srgb._encode16_kernel.overloads)
        """) + call.replace("; ", "\n") + textwrap.dedent("""
        print(loaded, len(set_up), "numba.np.arraymath" in sys.modules, "scipy.linalg" in sys.modules)
        """)
    done = subprocess.run([sys.executable, "-c", warm], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    codes, facts = done.stdout.split("\n")[:2]
    assert codes == usual.stdout.strip()
    assert facts == "True 0 False False"


def test_the_warmed_ssim_kernel_needs_no_blas_check():
    """SSIM's cached kernel does not use numba's NumPy reductions (``numba.np.arraymath``), whose import runs
    numba's BLAS check and so imports scipy.linalg (≈ 0.1 s of every camera run's warm-up); the value is SSIM's."""
    call = ("import numpy as np; from roadview_noise import metrics; r = np.random.default_rng(0); "
            "a = r.random((40, 50)); b = np.clip(a + 0.1 * r.random((40, 50)), 0, 1); print(repr(metrics.ssim(a, b)))")
    usual = subprocess.run([sys.executable, "-c", call], capture_output=True, text=True, timeout=300)
    assert usual.returncode == 0, usual.stderr             # compiled (and cached) or loaded with the set-up
    warm = call.replace("; r =", "; import sys, roadview_noise.warmup; r =") + \
        "; print(bool(metrics._ssim_map.overloads), 'numba.np.arraymath' in sys.modules, 'scipy.linalg' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", warm], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[:2] == [usual.stdout.strip(), "True False False"]


def test_a_cloud_run_needs_no_image_writers(tmp_path):
    """A LiDAR/radar run's server does not preload the image and raw readers/writers, and a radar worker's file
    (reading it whole, its chain, saving the cloud) imports neither them (nor tifffile) nor the LiDAR laser order:
    the worker never needs them."""
    from roadview_noise.prestart import worker_modules

    assert "roadview_noise.io.image" in worker_modules("camera", [])
    modules = worker_modules("radar", ["roadview_noise.models.radar.fog"])
    assert not {"roadview_noise.io.image", "roadview_noise.io.raw"} & set(modules)
    code = textwrap.dedent(f"""
        import importlib, sys
        import numpy as np
        for m in {modules!r}: importlib.import_module(m)
        from types import SimpleNamespace
        from roadview_noise.dataset import save
        from roadview_noise.types import PointCloud
        cloud = PointCloud(np.ones((4, 3), np.float32), {{"intensity": np.ones(4, np.float32)}}, "radar")
        recipe = SimpleNamespace(spec=SimpleNamespace(output=SimpleNamespace(effect="none")))
        from roadview_noise.compound import apply_models
        from roadview_noise.dataset import Sample
        from roadview_noise.runner import _read_whole
        assert _read_whole(Sample("a.pcd", "radar", "s"), __import__("pathlib").Path("a.pcd"))
        cloud, _ = apply_models([], cloud, seed=0, key="a.pcd", sequence_id="s")
        save(cloud, __import__("pathlib").Path({str(tmp_path / "a.pcd")!r}), recipe)
        print(sorted(m for m in ("tifffile", "roadview_noise.io.image", "roadview_noise.io.raw",
                                 "roadview_noise.physics.laser_order") if m in sys.modules))
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
    assert (tmp_path / "a.pcd").stat().st_size > 0


@pytest.mark.parametrize("command, torn_down", [("augment", False), ("validate", True)])
def test_a_local_run_ends_without_tearing_down(tmp_path, tree, command, torn_down):
    """The console script's app: after a local ``augment`` the process leaves at once (an exit handler registered
    before it never runs) with the command's exit code and everything written; other commands end as usual."""
    from test_cli import CAMERA, _recipe

    recipe, marker, out = _recipe(tmp_path, CAMERA), tmp_path / "torn-down", tmp_path / "o"
    args = ["augment", "--recipe", str(recipe), str(tree), str(out), "--workers", "1", "--quiet"] \
        if command == "augment" else ["validate", str(recipe)]
    code = textwrap.dedent(f"""
        import atexit, sys
        atexit.register(lambda: open({str(marker)!r}, "w").close())
        sys.argv = ["rvnoise", *{args!r}]
        from roadview_noise.cli.main import app
        app()
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert marker.exists() == torn_down
    if command == "augment":
        assert "written" in done.stdout
        assert json.loads((out / "run.json").read_text())["state"] == "complete"
