"""The on-disk table cache (roadview_noise/table_cache.py): a stored table is bit for bit what the function builds,
in this process and in a worker; its key follows the arguments and the code version; torn files are rebuilt;
concurrent writers leave one whole file; the folder stays within its budget; a run's outputs do not depend on it."""

from __future__ import annotations

import hashlib
import math
import multiprocessing as mp
import pickle
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from roadview_noise import table_cache
from roadview_noise.executor import ProcessExecutor
from roadview_noise.models.radar import weather as radar_weather
from roadview_noise.physics import lidar_medium, lidar_strongest, radar_clutter, radar_cfar
from roadview_noise.physics.lidar_particles import Beam, ParticleMedium, faint_background

BUILT: list[tuple] = []                 # the calls that built a table (not read it back) in this process


@table_cache.disk_cached(maxsize=4)
def _table(n: int, scale: float, pause_s: float = 0.0) -> dict:
    BUILT.append((n, scale))
    time.sleep(pause_s)
    rng = np.random.default_rng(n)
    return {"values": rng.normal(size=(n, 7)) * scale, "index": np.arange(n, dtype=np.int32), "scale": scale}


def _digest(value) -> str:
    """SHA-256 of the value's bytes (protocol 4: protocol 5 pickles a read-only array, as tables read back are,
    differently from a writeable one with the same bytes)."""
    return hashlib.sha256(pickle.dumps(value, protocol=4)).hexdigest()


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes() if isinstance(a[k], np.ndarray) else a[k] == b[k]
        for k in a)


@pytest.fixture(autouse=True)
def write_budget(monkeypatch) -> None:
    """Each test starts with this process's write budget unused (other tests of the session spend it)."""
    monkeypatch.setattr(table_cache, "_writes", 0)


@pytest.fixture
def folder(tmp_path, monkeypatch) -> Path:
    d = tmp_path / "tables"
    monkeypatch.setenv(table_cache.ENV, str(d))
    _table.cache_clear()
    BUILT.clear()
    return d


def _files(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.pkl"))


def test_a_stored_table_reads_back_bit_for_bit(folder):
    built = _table(50, 2.5)
    _table.cache_clear()                                  # a new worker: nothing in memory
    read = _table(50, 2.5)
    assert BUILT == [(50, 2.5)] and read is not built
    assert _same(read, built) and _same(read, _table.uncached(50, 2.5))
    assert len(_files(folder)) == 1


def test_the_key_follows_arguments_and_code_version(folder, monkeypatch):
    _table(20, 1.0)
    _table(20, 1.5)                                        # another argument: another table
    _table(21, 1.0)
    assert len(BUILT) == 3 and len(_files(folder)) == 3
    _table.cache_clear()
    monkeypatch.setattr(table_cache, "code_version", lambda: "another version of the package")
    _table(20, 1.0)                                        # an edit or an upgrade: built again, not read
    assert len(BUILT) == 4 and len(_files(folder)) == 4


def test_the_code_version_covers_the_package_source_and_libraries():
    v = table_cache.code_version()
    assert len(v) == 64 and v == table_cache.code_version()
    assert "miepython" in table_cache.VERSIONED and "numpy" in table_cache.VERSIONED


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage"])
def test_a_torn_or_damaged_file_is_rebuilt(folder, damage):
    expected = _table(30, 3.0)
    (path,) = _files(folder)
    blob = bytearray(path.read_bytes())
    if damage == "truncate":
        blob = blob[: len(blob) // 2]
    elif damage == "flip":
        blob[-10] ^= 0xFF
    else:
        blob = bytearray(b"not a table")
    path.write_bytes(bytes(blob))
    _table.cache_clear()
    assert _same(_table(30, 3.0), expected) and len(BUILT) == 2
    assert table_cache.read(path) is not table_cache._MISSING     # replaced by a whole file


def test_off_and_unwritable_folders_cost_only_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(table_cache.ENV, "off")
    _table.cache_clear()
    assert table_cache.cache_dir() is None
    assert _same(_table(10, 1.0), _table.uncached(10, 1.0))
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    monkeypatch.setenv(table_cache.ENV, str(blocker / "tables"))   # cannot be created
    _table.cache_clear()
    assert _same(_table(10, 1.0), _table.uncached(10, 1.0))
    assert blocker.read_text() == "x"


def test_a_process_writes_a_bounded_number_of_tables(folder, monkeypatch):
    """Keys that change with every file (parameters drawn per file) stop being written after the budget; what is
    stored is still read."""
    monkeypatch.setattr(table_cache, "MAX_WRITES_PER_PROCESS", 3)
    for n in range(1, 7):
        _table(n, 1.0)
    assert len(_files(folder)) == 3 and len(BUILT) == 6
    _table.cache_clear()
    _table(1, 1.0)                                         # stored: read, not built
    assert len(BUILT) == 6


def test_prune_keeps_the_most_recent_within_the_budget(folder):
    for n in (100, 101, 102):
        _table(n, 1.0)
        time.sleep(0.02)
    files = {p.name: p.stat().st_size for p in _files(folder)}
    newest = max(_files(folder), key=lambda p: p.stat().st_mtime)
    table_cache.prune(folder, max_bytes=files[newest.name] + 1)
    assert _files(folder) == [newest]


def _write_concurrently(folder: str, n: int, queue) -> None:
    import os

    os.environ[table_cache.ENV] = folder
    _table.cache_clear()
    queue.put(_digest(_table(n, 1.25, 0.2)))


def test_concurrent_writers_leave_one_whole_file(folder):
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_write_concurrently, args=(str(folder), 400, queue)) for _ in range(4)]
    for p in procs:
        p.start()
    seen = set()
    while any(p.is_alive() for p in procs):                 # a reader never sees a partial file
        for path in _files(folder):
            value = table_cache.read(path)
            assert value is table_cache._MISSING or _same(value, _table.uncached(400, 1.25))
            seen.add(path.name)
        time.sleep(0.005)
    for p in procs:
        p.join()
        assert p.exitcode == 0
    digests = {queue.get(timeout=5) for _ in procs}
    assert digests == {_digest(_table.uncached(400, 1.25))}
    assert len(_files(folder)) == 1 and not list(folder.glob(".tmp-*"))


OS1_BEAM = Beam(4.75e-3, math.pi / 1000, 0.5, 5.0)
RAIN = ParticleMedium(8000.0, 4.1 * 25.0 ** -0.21, 0.5, 6.0, 0.02, 2 * math.pi / 4 * 1e-6 * 8000.0 * 2
                      / (4.1 * 25.0 ** -0.21) ** 3)
PHYSICS_TABLES = [
    (lidar_strongest.brightest_tables, (RAIN, OS1_BEAM, 2e-7, 3.0)),
    (faint_background, (RAIN, OS1_BEAM, 2e-7, 3.0)),
    (lidar_medium.soft_target_table, (0.03, 10e-9, 0.5, 5.0)),
    (radar_clutter._mie_backscatter_table, (complex(12, -25), 3.9e-3, 6.0)),
    (radar_cfar.tier_ratios, (radar_cfar.CaCfar(1e-6, 16),)),
    *((fn, (radar_clutter.rain_drops(20.0), radar_clutter.ResolutionGrid(120, 30, 1, 2, 0.2, 0.1035, 1.0, 20.0),
            3.9e-3, (-10.0, 0.0, 0.0)) + extra)
      for fn, extra in ((radar_clutter._pair_rcs_per_m3, ()), (radar_clutter._rcs_table, ()),
                        (radar_clutter._count_table, (radar_cfar.CaCfar(1e-4, 16),)))),
]


def _in_worker(task: int, context: None) -> tuple[str, bool]:
    """The table's digest in a worker, and whether its file was there to be read."""
    fn, args = PHYSICS_TABLES[task]
    stored = (table_cache.cache_dir() / table_cache.key(fn.uncached, args, {})).is_file()
    return _digest(fn(*args)), stored


@pytest.mark.parametrize("i", range(len(PHYSICS_TABLES)), ids=[f.__name__ for f, _ in PHYSICS_TABLES])
def test_the_physics_tables_read_back_exactly(folder, i):
    """Each table the workers keep on disk, built here, read back here, and read by a worker process: one value."""
    fn, args = PHYSICS_TABLES[i]
    fn.cache_clear()
    built = _digest(fn.uncached(*args))
    assert _digest(fn(*args)) == built                     # built and stored
    fn.cache_clear()
    assert _digest(fn(*args)) == built                     # read back
    assert any(p.name.startswith(f"{fn.__module__}.{fn.__qualname__}-") for p in _files(folder))
    fn.cache_clear()


def test_a_worker_reads_the_tables_this_process_built(tmp_path):
    """Workers inherit the fork server's environment, so this test uses the session's folder (conftest), the one
    the server uses: a table built and stored here is what a worker returns."""
    if table_cache.cache_dir() is None:
        pytest.skip("the table cache is off in this session")
    expected = []
    for fn, args in PHYSICS_TABLES:
        fn.cache_clear()
        expected.append(_digest(fn(*args)))
    ex = ProcessExecutor(_in_worker, None, 2)
    try:
        got = dict(ex.map(range(len(PHYSICS_TABLES))))
    finally:
        ex.close()
    assert [got[i] for i in range(len(PHYSICS_TABLES))] == [(d, True) for d in expected]


@pytest.mark.parametrize("name, prefix", [("weather-snow-lidar", "lidar/os1-128/"), ("weather-fog-lidar", "lidar/"),
                                          ("weather-rain-radar", "radar/"), ("weather-snow-radar", "radar/")])
def test_outputs_do_not_depend_on_the_cache(tmp_path, monkeypatch, name, prefix):
    """One file's output bytes with the cache off, with tables built into an empty cache, and read back from it."""
    from roadview_noise.recipe import load_recipe
    from roadview_noise.runner import RunContext, plan, process

    root = Path(__file__).resolve().parents[1]
    recipe = load_recipe(root / "recipes" / f"{name}.yaml")
    task = next(t for t in plan(root / "sample_data", recipe) if t.sample.relpath.startswith(prefix))
    outputs = []
    for i, setting in enumerate(["off", str(tmp_path / "tables"), str(tmp_path / "tables")]):
        monkeypatch.setenv(table_cache.ENV, setting)
        for fn, _ in PHYSICS_TABLES + [(radar_clutter._doppler_shape_tables, ()),
                                       (radar_clutter.cell_doppler_probabilities, ())]:
            fn.cache_clear()                                # a new worker
        radar_weather._per_profile.clear()                  # (which holds its models' clutter tables)
        out = tmp_path / f"out{i}"
        out.mkdir()
        entry = process(task, RunContext(root / "sample_data", out.resolve(), recipe))
        assert entry["status"] == "ok", entry.get("error")
        outputs.append(entry["output_sha256"])
        if i == 1:
            assert _files(tmp_path / "tables")                # the run stored its tables
    assert outputs[0] == outputs[1] == outputs[2]


def test_library_version_is_the_distributions(monkeypatch):
    """An imported library's ``__version__`` stands for its distribution's version (no metadata scan); a library
    not imported is looked up; one not installed is "-"."""
    from importlib import metadata

    for name in ("numpy", "scipy", "numba", "llvmlite"):
        assert table_cache.library_version(name) == metadata.version(name)
    monkeypatch.delitem(sys.modules, "llvmlite")
    assert table_cache.library_version("llvmlite") == metadata.version("llvmlite")
    assert table_cache.library_version("rvnoise-no-such-library") == "-"
