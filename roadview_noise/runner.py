"""Batch runner: plan tasks (input × sweep variant) lazily, run them in worker processes, record, then write.

Output bytes depend only on the recipe, the seed, the input bytes and library versions — never on the number of
workers, the order or resuming: every random draw comes from ``derive_rng(seed, output relpath, ...)``, and results
are released in plan order (``outputs.Ledger``).

What a run promises (README "Guarantees"): it reads only inside IN and writes only inside OUT (``io/atomic``
confinement, ``input_checks``); one run per OUT (``lock``); a dying worker fails only its own file (``executor``);
every file in OUT is in the manifest with its sha256 (``outputs``); inputs larger than ``--max-pixels`` /
``--max-points`` fail before they are decoded (``io/headers``); the manifest and ``run.json`` are written however
the run ends, except when the runner itself is killed (``--resume`` then completes it).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import sys
import time
import traceback
import warnings
from collections import Counter
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from . import annotations, coco, prestart, profiling
from .allocator import keep_freed_memory
from .camera_inputs import InputWarnings
from .compound import apply_models
from .dataset import Sample, iter_inputs, load, output_relpath, save
from .errors import EmptyCloudError, InputError, OutputError, RecipeError, RvNoiseError
from .executor import NOT_NOW, Counted, InlineExecutor, ProcessExecutor, TaskError, WorkerDeath, start_server
from .input_survey import no_inputs_message
from .invalid_points import drop_invalid_points
from .io.atomic import confined_to, remove_stale_temporaries, staged_writes, write_bytes_atomic
from .io.headers import check_size
from .lock import OutputLock
from .manifest import (MANIFEST_NAME, RUN_NAME, encoded, iter_manifest, library_versions, read_manifest,
                       sha256_file, write_manifest, write_run_json)
from .native_output import captured_output
from .output_sync import SyncPool, write_error
from .outputs import Ledger, PreviousRun, commit, discard, files_intact, remove_listed
from .profiling import span
from .real_folders import real_file
from .recipe import Recipe, draw_value
from .registry import adopt, get_model, model_modules, plugin_models
from .resources import choose_workers
from .seeding import derive_rng
from .walk import WalkFailure, os_error_text

MAX_OUTPUTS_WITHOUT_YES = 100_000
DEFAULT_MAX_PIXELS = 100_000_000         # 100 MP: 3× an 8K frame (33 MP)
DEFAULT_MAX_POINTS = 20_000_000          # 20 M points: 76 OS1-128 2048-column scans merged


@dataclass(frozen=True)
class Limits:
    """Per-file resource caps, checked on the headers before decoding; ``task_timeout_s`` ends a worker that runs
    one file longer (None: no limit)."""

    max_pixels: int = DEFAULT_MAX_PIXELS
    max_points: int = DEFAULT_MAX_POINTS
    task_timeout_s: float | None = None


@dataclass(frozen=True)
class Task:
    sample: Sample
    variant_index: int
    out_relpath: str
    index: int = 0                      # position in the plan (walk failures included)
    coco: Any = field(default=None, compare=False)   # an image of the run's dataset file (coco.CocoRun): .move()


@dataclass(frozen=True)
class RunContext:
    """What every worker receives once: real input and output roots, the recipe, the limits; whether to collect
    what native libraries print (in worker processes) into the entry's ``library_messages``; whether to record
    where each file's time goes (``profile``, :mod:`roadview_noise.profiling`); whether the worker fsyncs its staged
    files (``fsync_outputs``; False: the run's main process does, before their manifest lines, ``output_sync``)."""

    in_root: Path
    out_root: Path
    recipe: Recipe
    limits: Limits = Limits()
    capture_output: bool = False
    profile: bool = False
    fsync_outputs: bool = True


@dataclass
class RunSummary:
    planned: int = 0
    done: int = 0
    skipped: int = 0
    failed: int = 0
    seconds: float = 0.0
    failures: list[str] = field(default_factory=list)
    dry_run: bool = False
    workers: int = 0
    warned: int = 0                     # outputs whose entry records input warnings (dropped invalid points)
    notes: list[str] = field(default_factory=list)   # what the user must know (disk full, stopped early, …)
    warnings: list[str] = field(default_factory=list)  # about the inputs as a whole (camera_inputs.InputWarnings)
    state: str = "complete"
    worker_start_s: float | None = None  # from starting the workers to the first one ready (see _execute)


# --- planning --------------------------------------------------------------------------------------------------------


def check_roots(in_root: Path, out_root: Path) -> tuple[Path, Path]:
    """Real paths of the roots; refuses a missing input, an output that is a file, and overlapping roots (the input
    tree is never written)."""
    if Path(in_root).exists() and not Path(in_root).is_dir():
        raise RecipeError(f"input {str(in_root)!r} is a file; augment reads a folder (its files that the recipe's "
                          "inputs globs match): give the folder holding it, or see one file's result with `rvnoise "
                          "preview`")
    if not Path(in_root).is_dir():
        raise RecipeError(f"input folder {str(in_root)!r} does not exist")
    if Path(out_root).exists() and not Path(out_root).is_dir():
        raise OutputError(f"output {str(out_root)!r} exists and is not a folder")
    a, b = Path(os.path.realpath(in_root)), Path(os.path.realpath(out_root))
    if a == b or a in b.parents or b in a.parents:
        raise RecipeError(f"output {str(out_root)!r} and input {str(in_root)!r} overlap; "
                          "the input tree is never written, choose a separate output folder")
    return a, b


@dataclass(frozen=True)
class Unreadable:
    """A path of the plan the walk could not read (a failed manifest entry)."""

    failure: WalkFailure
    index: int


def iter_plan(in_root: Path, recipe: Recipe, limit: int | None = None) -> Iterator[Task | Unreadable]:
    """Tasks in plan order (input path, then variant) and the paths the walk could not read, one at a time;
    ``limit`` counts inputs."""
    n = 0
    index = itertools.count()
    for item in iter_inputs(in_root, recipe):
        if isinstance(item, WalkFailure):
            yield Unreadable(item, next(index))
            continue
        if limit is not None and n >= limit:
            return
        n += 1
        for i, v in enumerate(recipe.variants):
            yield Task(item, i, output_relpath(item.relpath, v.suffix), next(index))


def iter_tasks(in_root: Path, recipe: Recipe, limit: int | None = None) -> Iterator[Task]:
    return (t for t in iter_plan(in_root, recipe, limit) if isinstance(t, Task))


def plan(in_root: Path, recipe: Recipe, limit: int | None = None) -> list[Task]:
    """Every task of the plan as a list (small trees, tests); a run streams them with :func:`iter_tasks`."""
    return list(iter_tasks(in_root, recipe, limit))


def count_plan(in_root: Path, recipe: Recipe, limit: int | None, stop_above: int | None) -> tuple[int, int]:
    """(outputs, unreadable paths) of the plan, counting inputs only until the outputs exceed ``stop_above``."""
    inputs = failures = 0
    per_input = len(recipe.variants)
    for item in iter_inputs(in_root, recipe):
        if isinstance(item, WalkFailure):
            failures += 1
            continue
        if limit is not None and inputs >= limit:
            break
        inputs += 1
        if stop_above is not None and inputs * per_input > stop_above:
            break
    return inputs * per_input, failures


@lru_cache(maxsize=None)
def _integer_params(cls: type) -> frozenset[str]:
    """The parameters of a model class whose default is an int (their draws are integers)."""
    return frozenset(p.name for p in cls.param_specs() if type(p.default) is int)


_fixed_steps: dict[tuple[int, int], Any] = {}     # (variant, step) → model, for the recipe in _fixed_steps_of
_fixed_steps_of: list[Recipe] = []


def build_models(recipe: Recipe, task: Task) -> list:
    """Instantiate the chain for one output: fixed values, sweep overrides, and per-file distribution draws (their
    generator derived only for a step that has one). A step without draws is the same (frozen) model for every
    file of a variant: built once per process and recipe."""
    if not _fixed_steps_of or _fixed_steps_of[0] is not recipe:
        _fixed_steps.clear()
        _fixed_steps_of[:] = [recipe]
    overrides = recipe.variants[task.variant_index].overrides
    models = []
    for i, (model_id, params) in enumerate(zip(recipe.model_ids, recipe.step_params)):
        drawn = any(isinstance(v, dict) for v in params.values())
        if not drawn and (task.variant_index, i) in _fixed_steps:
            models.append(_fixed_steps[task.variant_index, i])
            continue
        cls = get_model(model_id)
        integer = _integer_params(cls)
        rng = derive_rng(recipe.seed, task.out_relpath, "params", i, model_id) if drawn else None
        values = {k: draw_value(v, rng, integer=k in integer) for k, v in sorted(params.items())}
        values.update({k: draw_value(v, None) for k, v in overrides.get(model_id, {}).items()})
        models.append(cls(**values))
        if not drawn:
            _fixed_steps[task.variant_index, i] = models[-1]
    return models


# --- one output (in a worker) ----------------------------------------------------------------------------------------


_run_state: list = [None, {}]        # [the run's context, what its files look up once (per_run)]


def per_run(ctx: RunContext, name: str) -> dict:
    """A dict named ``name`` kept while ``ctx`` is the run's context (a worker receives it once per run): what every
    file of a run would look up the same, looked up once (a folder's cloud profile, …)."""
    if _run_state[0] is not ctx:
        _run_state[:] = [ctx, {}]
    return _run_state[1].setdefault(name, {})


@lru_cache(maxsize=8)
def _real_root(in_root: Path) -> str:
    return os.path.realpath(in_root)


def input_path(in_root: Path, relpath: str) -> Path:
    """``in_root / relpath``, refused when it resolves (through a symlink) outside the input folder (whose real path
    is taken once per process, its folders' too: :mod:`roadview_noise.real_folders`)."""
    path = in_root / relpath
    real = real_file(str(path))
    root = _real_root(in_root)
    if not real.startswith(root + os.sep):
        raise InputError(f"resolves to {real!r}, outside the input folder; rvnoise reads only inside it",
                         file=str(path))
    return path


READ_ONCE_MAX_BYTES = 64 << 20      # an input up to this size is read once, for its sha256 and its reader


def sha256_input(path: Path, *, whole: bool = False) -> tuple[str, bytes | None]:
    """sha256 of an input file (its reading and hashing are profiled apart) and, with ``whole``, its bytes when it
    holds at most ``READ_ONCE_MAX_BYTES`` (its reader takes them: one read, and the decoded bytes are the hashed
    ones); InputError names an unreadable one."""
    h = hashlib.sha256()
    try:
        with open(path, "rb", buffering=0) as fh:       # unbuffered: no isatty/fstat of a buffered reader
            if whole and (size := os.fstat(fh.fileno()).st_size) <= READ_ONCE_MAX_BYTES:
                with span("read"):
                    data = _read_to_end(fh, size)
                with span("hash"):
                    h.update(data)
                return h.hexdigest(), data
            while True:
                with span("read"):
                    chunk = fh.read(1 << 20)
                if not chunk:
                    return h.hexdigest(), None
                with span("hash"):
                    h.update(chunk)
    except OSError as exc:
        raise InputError(f"cannot read the file: {os_error_text(exc)}", file=str(path)) from None


def _read_to_end(fh, size: int) -> bytes:
    """The bytes of an unbuffered file from its position to its end, ``size`` expected: one ``read`` when the file
    holds them (``fh.read()`` asks again until it gets nothing, after an ``lseek`` and an ``fstat``)."""
    data = fh.read(size + 1)
    if len(data) == size:
        return data
    parts = [data]                           # shorter (a short read) or longer (the file grew): read to its end
    while parts[-1]:
        parts.append(fh.read(1 << 20))
    return b"".join(parts)


def _read_whole(sample: Sample, path: Path) -> bool:
    """True when the sample's reader takes the file's bytes (a point cloud, a PNG/JPEG/TIFF image; OpenEXR and the
    raw readers open the path themselves)."""
    if sample.modality != "camera":        # a LiDAR or radar worker never imports the image codecs
        return sample.modality in ("lidar", "radar")
    from .io.image import image_format

    return image_format(path) != "exr"


def _check_sizes(sample: Sample, path: Path, depth: Path | None, ctx: RunContext, content: bytes | None) -> None:
    """The header limits of the input (a cloud's header read from ``content``, its bytes, when read already)."""
    from .io.pointcloud import bin_point_bytes, cloud_format

    limits = ctx.limits
    if sample.modality in ("lidar", "radar"):
        inputs = ctx.recipe.spec.inputs
        fmt = cloud_format(path, sample.modality)
        row = bin_point_bytes(fmt, inputs.radar_bin_fields if sample.modality == "radar" else inputs.bin_fields,
                              content)
        check_size(path, max_points=limits.max_points, cloud_fmt=fmt, data=content, point_bytes=row)
    else:
        for p in (path, depth):
            if p is not None:
                check_size(p, max_pixels=limits.max_pixels)


def _warning_list(caught: list) -> list[str]:
    counts = Counter(f"{w.category.__name__}: {w.message}" for w in caught)
    return [f"{text} (×{n})" if n > 1 else text for text, n in counts.items()]


def process(task: Task, ctx: RunContext) -> dict[str, Any]:
    """Read, run the chain, stage the output files; return the manifest entry (failures are recorded, not raised).
    The files stay temporaries listed under ``staged`` (fsynced, unless ``ctx.fsync_outputs`` leaves that to the
    run's main process) until the runner has recorded them."""
    keep_freed_memory()
    t0, cpu0 = time.perf_counter(), time.thread_time() if ctx.profile else 0.0   # (a system call: profiled only)
    s, recipe = task.sample, ctx.recipe
    entry: dict[str, Any] = {
        "output": task.out_relpath, "input": s.relpath, "modality": s.modality, "sequence": s.sequence_id,
        "depth": s.depth_relpath, "variant_index": task.variant_index,
        "variant": recipe.variants[task.variant_index].overrides, "chain": list(recipe.model_ids),
    }
    with captured_output(ctx.capture_output) as printed, profiling.collect(ctx.profile) as spans:
        _process(task, ctx, entry)
    if printed:
        entry["library_messages"] = printed
    entry["seconds"] = round(time.perf_counter() - t0, 4)
    if ctx.profile:
        entry["profile"] = _profile_split(spans, entry, time.thread_time() - cpu0)
    return entry


def process_encoded(task: Task, ctx: RunContext) -> dict[str, Any]:
    """:func:`process` as a run's workers run it: the entry with its manifest line encoded in the worker
    (``manifest.encoded``), for the main process to write as it is."""
    return encoded(process(task, ctx))


def _profile_split(spans: dict[str, float], entry: dict, cpu_s: float) -> dict[str, Any]:
    """The manifest's ``profile`` of one file (seconds; :mod:`roadview_noise.profiling`) from the spans, with the
    worker thread's CPU seconds for the file (``cpu``: below ``total`` by the time it waited for storage or for a
    core)."""
    steps: dict[str, float] = {}
    for step in entry.get("steps", ()):
        steps[step["model"]] = steps.get(step["model"], 0.0) + step["seconds"]
    get = spans.get
    split = {"read": get("read", 0.0), "hash": get("hash", 0.0),
             "decode": get("load", 0.0) - get("load.convert", 0.0),
             "convert": get("load.convert", 0.0) + get("save.convert", 0.0),
             "metrics": get("chain", 0.0) - sum(steps.values()) + get("metrics", 0.0),
             "encode": get("save", 0.0) - get("save.convert", 0.0) - get("save.write", 0.0),
             "write": get("save.write", 0.0) + get("sync", 0.0)}
    split["other"] = entry["seconds"] - sum(split.values()) - sum(steps.values())
    rounded = {k: round(max(v, 0.0), 5) for k, v in split.items()}
    return {**rounded, "models": {m: round(x, 5) for m, x in steps.items()}, "total": entry["seconds"],
            "cpu": round(cpu_s, 5), "peak_rss_mb": _peak_rss_mb()}


def _peak_rss_mb() -> float:
    """This process's peak resident set size so far (Linux ``VmHWM``; elsewhere ``ru_maxrss``)."""
    try:
        with open("/proc/self/status") as fh:
            return round(next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:")) / 1024, 1)
    except (OSError, StopIteration):
        import resource

        return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / (1024 if sys.platform != "darwin" else
                                                                            1024 ** 2), 1)


def _process(task: Task, ctx: RunContext, entry: dict[str, Any]) -> None:
    """The body of :func:`process`: fills ``entry``."""
    s, recipe = task.sample, ctx.recipe
    try:
        from . import luminance, metrics, orientation      # numba, OpenCV: imported where files are processed only

        luminance.collect(recipe.spec.output.metrics)   # the frames' sRGB passes keep their luminance for the metrics
        deferred = metrics.Deferred(radar_chains=True)  # filled after the writer's encode (metrics.Deferred)
        source = input_path(ctx.in_root, s.relpath)
        entry["input_sha256"], content = sha256_input(source, whole=_read_whole(s, source))
        depth = None
        if s.depth_relpath is not None:
            depth = input_path(ctx.in_root, s.depth_relpath)
            entry["depth_sha256"] = sha256_input(depth)[0]
        _check_sizes(s, source, depth, ctx, content)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with profiling.phase("load", "convert"):
                try:
                    data, content = load(s, ctx.in_root, recipe, content, per_run(ctx, "profiles")), None
                except EmptyCloudError as e:
                    return _copy_unchanged(task, ctx, source, entry, str(e))
            if getattr(data, "input_notes", None):
                entry["inputs"] = dict(data.input_notes)
            data, dropped = drop_invalid_points(data, file=str(source))
            if dropped:
                entry["input_warnings"] = dropped
            spec = recipe.spec.inputs.annotations
            sidecars = annotations.read(s.relpath, ctx.in_root, spec, data,
                                        task.coco.panoptic_pngs() if task.coco is not None else frozenset())
            with profiling.span("chain"):
                out, records = apply_models(build_models(recipe, task), data, seed=recipe.seed,
                                            key=task.out_relpath, sequence_id=s.sequence_id,
                                            metrics=recipe.spec.output.metrics, deferred=deferred)
            with profiling.span("metrics"):
                if not recipe.spec.output.metrics:
                    entry["metrics"] = {}
                elif len(records) == 1:                    # one step: its metrics compare input and output already
                    entry["metrics"] = records[0].metrics
                else:
                    entry["metrics"] = deferred.compare(data, out)
                deferred.settle_clouds()                   # a radar chain's, before the writer (metrics.Deferred)
            out = orientation.as_stored(out)             # a photo processed upright is written and labelled as stored
            out, annotated = annotations.carry(sidecars, spec, data, out, recipe.model_ids, ctx.out_root,
                                               recipe.variants[task.variant_index].suffix)
            entry.update({k: v for k, v in (("annotations_read", annotated.read), ("objects", annotated.objects))
                          if v})
            if task.coco is not None:
                entry["coco"] = task.coco.move(orientation.stored_shape(data), out.warps, annotated.masks)
            with confined_to(ctx.out_root), staged_writes(sync=ctx.fsync_outputs) as stage:
                with profiling.phase("save", "convert", "write"):
                    save(out, ctx.out_root / task.out_relpath, recipe, source=source, annotations=annotated)
                with profiling.span("metrics"):
                    deferred.settle()
                entry["steps"] = [r.as_entry() for r in records]
                with profiling.span("hash"):
                    _staged_files(stage, ctx, task, entry)
        if caught:
            entry["warnings"] = _warning_list(caught)
        entry["status"] = "ok"
    except RvNoiseError as e:
        entry.update(status="failed", error=str(e) if s.relpath in str(e) else f"{s.relpath}: {e}")
    except OSError as e:                   # the environment: disk full, a folder outside OUT, a vanished file
        entry.update(status="failed", error=write_error(s.relpath, task.out_relpath, e))
    except Exception as e:  # a bug or a library error on one file must not stop the run; keep the trace
        entry.update(status="failed", error=f"{s.relpath}: internal error {type(e).__name__}: {e}",
                     traceback=traceback.format_exc(limit=8))
    if entry["status"] != "ok":
        for key in ("files", "output_sha256"):
            entry.pop(key, None)
        discard(ctx.out_root, entry)


def _staged_files(stage, ctx: RunContext, task: Task, entry: dict[str, Any]) -> None:
    """The entry's ``files`` (path, sha256 of the staged bytes), ``staged`` (temporary → final) and
    ``output_sha256``."""
    root = os.fspath(ctx.out_root)
    rel = [[_relative_posix(tmp, root), _relative_posix(final, root)] for tmp, final in stage.files]
    entry["files"] = [{"path": final, "sha256": stage.sha256_of(tmp) or sha256_file(tmp)}
                      for (tmp, _), (_, final) in zip(stage.files, rel)]
    entry["staged"] = rel
    entry["output_sha256"] = next(f["sha256"] for f in entry["files"] if f["path"] == task.out_relpath)


def _relative_posix(path: Path, root: str) -> str:
    """``path.relative_to(root).as_posix()`` of a path under the real ``root`` (both normalised, as the staged
    files' are), by string: pathlib parses both paths each time (≈ 10 µs a file, issue 19)."""
    prefix = root.rstrip(os.sep) + os.sep
    text = os.fspath(path)
    if not text.startswith(prefix):
        raise ValueError(f"{text!r} is not in the subpath of {root!r}")
    return text[len(prefix):].replace(os.sep, "/")


def _copy_unchanged(task: Task, ctx: RunContext, source: Path, entry: dict[str, Any], why: str) -> None:
    """An input with nothing to augment (:class:`EmptyCloudError`: a radar frame without detections) is written
    unchanged, so that the output tree stays complete (a dataset's loader expects every sweep); no steps run."""
    with confined_to(ctx.out_root), staged_writes(sync=ctx.fsync_outputs) as stage:
        write_bytes_atomic(ctx.out_root / task.out_relpath, source.read_bytes())
        _staged_files(stage, ctx, task, entry)
    entry.update(status="ok", copied_unchanged=True, note=why.removeprefix(f"{source}: "), metrics={}, steps=[])


def _result_entry(task: Task, result: Any) -> dict:
    """A manifest entry for what the executor returned: the worker's entry, or a failure it could not record."""
    if isinstance(result, dict):
        return result
    base = {"output": task.out_relpath, "input": task.sample.relpath, "modality": task.sample.modality,
            "sequence": task.sample.sequence_id, "depth": task.sample.depth_relpath,
            "variant_index": task.variant_index, "status": "failed"}
    if isinstance(result, WorkerDeath):
        again = " (tried twice, not retried again)" if result.deaths > 1 else ""
        return {**base, "error": f"{task.sample.relpath}: {result.reason}{again}", "worker_deaths": result.deaths}
    assert isinstance(result, TaskError)
    return {**base, "error": f"{task.sample.relpath}: internal error {result.message}",
            "traceback": result.traceback}


def _walk_entry(failure: WalkFailure) -> dict:
    return {"output": None, "input": failure.relpath, "status": "failed",
            "error": f"{failure.relpath}: {failure.error}"}


# --- the run ---------------------------------------------------------------------------------------------------------


BACKENDS = ("local", "dask")


def run(recipe: Recipe, in_root: Path, out_root: Path, *, workers: int | None = None, resume: bool = False,
        overwrite: bool = False, dry_run: bool = False, limit: int | None = None, fail_fast: bool = False,
        yes: bool = False, limits: Limits = Limits(), progress: bool = True, echo: Callable[[str], None] = print,
        warn: Callable[[str], None] | None = None, backend: str = "local", scheduler: str | None = None,
        profile: bool = False) -> RunSummary:
    """Run a recipe over an input tree. Raises RecipeError / OutputError (exit 2) before writing anything if it
    cannot start; ``warn`` (default ``echo``) gets the messages meant for stderr. ``backend``: ``local`` (worker
    processes of this machine, :mod:`roadview_noise.executor`) or ``dask`` (the Dask scheduler at ``scheduler``,
    else a local ``distributed.LocalCluster``; :mod:`roadview_noise.dask_backend`); ``profile`` records where each
    file's time goes in its manifest entry."""
    warn = warn or echo
    started = time.time()
    if backend not in BACKENDS:
        raise RecipeError(f"unknown backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if scheduler is not None and backend != "dask":
        raise RecipeError("--scheduler needs --backend dask")
    in_real, out_real = check_roots(in_root, out_root)
    if backend == "local" and not dry_run:
        start_server(worker_modules(recipe))               # it imports while the input tree is walked
    cap = None if yes else MAX_OUTPUTS_WITHOUT_YES
    planned, unreadable = count_plan(in_real, recipe, limit, cap)
    if cap is not None and planned > cap:
        raise RecipeError(f"the recipe plans more than {cap:,} outputs ({len(recipe.variants):,} variant(s) per "
                          "input); say --yes to run it anyway, or narrow the sweep or the inputs (--limit)")
    if planned == 0 and unreadable == 0:
        raise RecipeError(no_inputs_message(in_real, str(in_root), recipe))
    coco_run = coco.open_run(in_real, recipe)
    for note in coco_run.notes() if coco_run else ():
        warn(f"rvnoise: warning: {note}")
    summary = RunSummary(planned=planned + (len(recipe.variants) if coco_run else 0), dry_run=dry_run)
    if dry_run:
        for t in iter_plan(in_real, recipe, limit):
            if isinstance(t, Unreadable):
                echo(f"{t.failure.relpath}: cannot be processed: {t.failure.error}")
            else:
                echo(f"{t.sample.relpath} → {t.out_relpath}  [{' → '.join(recipe.model_ids)}]")
        return summary
    try:
        out_real.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create the output folder {str(out_root)!r}: {os_error_text(e)}") from None
    with OutputLock(out_real, echo=warn) as lock, confined_to(out_real):
        n_workers, capped = (workers, None) if backend == "dask" and scheduler is not None else \
            choose_workers(workers, planned)
        ctx = RunContext(in_real, out_real, recipe, limits, capture_output=True, profile=profile,
                         fsync_outputs=backend != "local")          # local: the main process fsyncs them
        workers_started = time.monotonic()
        executor = _executor(ctx, n_workers, backend, scheduler)       # the fork server imports meanwhile
        getattr(executor, "start", lambda: None)()      # workers fork and set up while the run record is written
        previous = PreviousRun()
        try:
            previous = _previous_run(out_real, recipe, resume, overwrite)
            remove_stale_temporaries(out_real)
            if capped:
                warn(f"rvnoise: {capped}")
            summary.workers = executor.workers
            record = _run_record(recipe, in_real, out_real, executor.workers, started, limits)
            record.update(backend=backend, scheduler=scheduler)
            try:
                write_run_json(out_real / RUN_NAME, {**record, "state": "running"})
            except OSError as e:
                raise OutputError(f"cannot write in the output folder {str(out_root)!r}: {os_error_text(e)}") \
                    from None
            tally, log = _execute(ctx, previous, summary, executor, limit, fail_fast, progress, workers_started,
                                  coco_run)
            _finish(ctx, previous, tally, log, summary, record, started, lock, prune=limit is None)
        finally:
            executor.close()
            previous.close()
    for line in summary.warnings:
        warn(f"rvnoise: warning: {line}")
    for note in summary.notes:
        warn(f"rvnoise: {note}")
    if summary.state == "interrupted":
        raise KeyboardInterrupt
    return summary


def worker_modules(recipe: Recipe) -> list[str]:
    """The modules the fork server imports for a run of ``recipe`` (:mod:`roadview_noise.prestart`)."""
    return prestart.worker_modules(recipe.sensor, model_modules(recipe.model_ids))


def _executor(ctx: RunContext, workers: int | None, backend: str, scheduler: str | None):
    """The executor of a backend (see :func:`run`); both run :func:`process_encoded` on tasks and yield as
    completed."""
    setup = (adopt, (plugin_models(),))
    if backend == "dask":
        from .dask_backend import DaskExecutor

        return DaskExecutor(process_encoded, ctx, workers=workers, scheduler=scheduler, setup=setup,
                            timeout_s=ctx.limits.task_timeout_s)
    return ProcessExecutor(process_encoded, ctx, workers or 1, setup=setup, timeout_s=ctx.limits.task_timeout_s,
                           models=worker_modules(ctx.recipe))


def _previous_run(out_root: Path, recipe: Recipe, resume: bool, overwrite: bool) -> PreviousRun:
    """The ok entries of an earlier run in ``out_root`` that ``--resume`` may keep, by output; checks that the
    earlier run may be continued or replaced, and on ``--overwrite`` deletes the files it lists."""
    manifest, run_json = out_root / MANIFEST_NAME, out_root / RUN_NAME
    if not (manifest.exists() or run_json.exists()):
        return PreviousRun()
    if not (resume or overwrite):
        raise OutputError(f"{str(out_root)!r} holds an earlier run{_earlier_run_text(run_json, recipe)}; use "
                          "--resume to complete it (the same recipe only) or --overwrite to replace it")
    if overwrite:
        remove_listed(out_root, iter_manifest(manifest))
        for p in (manifest, run_json):
            p.unlink(missing_ok=True)
        return PreviousRun()
    try:
        record = json.loads(run_json.read_text())
    except (OSError, ValueError):
        raise OutputError(f"{str(out_root)!r} has no readable {RUN_NAME}, so the recipe of its run is unknown; "
                          "use --overwrite to replace it") from None
    if record.get("recipe_sha256") != recipe.sha256():
        raise OutputError(f"{str(out_root)!r} was made by another recipe (sha256 {str(record.get('recipe_sha256'))[:12]}…,"
                          f" this one {recipe.sha256()[:12]}…); --resume continues the same recipe only: use "
                          "--overwrite to replace that run, or another output folder")
    return PreviousRun(manifest)


def _earlier_run_text(run_json: Path, recipe: Recipe) -> str:
    """`` (interrupted: 121 of 600 outputs done, another recipe)``: what an earlier run's record says, or ''."""
    try:
        record = json.loads(run_json.read_text())
        counts = record.get("counts") or {}
        done = (counts.get("done") or 0) + (counts.get("skipped") or 0)
        other = ", another recipe" if record.get("recipe_sha256") != recipe.sha256() else ""
        return f" ({record['state']}: {done} of {counts.get('planned', '?')} outputs done{other})"
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return ""


def _turned_dng(path: Path) -> bool:
    """A DNG whose Orientation turns it (an entry without ``inputs.orientation`` for it is from before round 21,
    which processed it as stored)."""
    from .io.raw import dng_orientation

    return path.suffix.lower() == ".dng" and dng_orientation(path) != 1


def _still_valid(ctx: RunContext, task: Task, entry: dict) -> bool:
    """A previous entry ``--resume`` can keep: same variant, same input (and depth) bytes, files intact."""
    if entry.get("variant_index") != task.variant_index or entry.get("input") != task.sample.relpath:
        return False
    turned = (entry.get("inputs") or {}).get("orientation")
    if ctx.recipe.spec.inputs.orientation == "upright" and (turned["processed"] != "upright" if turned else
                                                            _turned_dng(ctx.in_root / task.sample.relpath)):
        return False     # a photo stored turned, processed as stored before round 20 (a DNG: 21): redone upright
    try:
        if sha256_file(ctx.in_root / task.sample.relpath) != entry.get("input_sha256"):
            return False
        if task.sample.depth_relpath != entry.get("depth"):
            return False
        if task.sample.depth_relpath and sha256_file(ctx.in_root / task.sample.depth_relpath) != \
                entry.get("depth_sha256"):
            return False
    except OSError:
        return False
    return files_intact(ctx.out_root, entry)


class _Tally:
    """What the run summary needs of every entry, folded as entries are released (nothing kept per entry)."""

    MAX_FAILURES = 100                                 # error lines kept for the summary; the manifest has all

    def __init__(self, summary: RunSummary):
        self.summary = summary
        self.inputs = InputWarnings()
        self.model_warnings: Counter = Counter()

    def add(self, e: dict, *, released: bool = True) -> None:
        self.inputs.add(e)
        self.model_warnings.update({w.rsplit(" (×", 1)[0] for w in e.get("warnings", ())})
        if released:
            self.count(e)

    def count(self, e: dict) -> None:
        s = self.summary
        if e.pop("skipped", False):
            s.skipped += 1
        elif e["status"] == "ok":
            s.done += 1
            s.warned += bool(e.get("input_warnings"))
        else:
            s.failed += 1
            if len(s.failures) < self.MAX_FAILURES:
                s.failures.append(e["error"])

    def warnings(self) -> list[str]:
        """Input warnings, then one line per distinct warning a model issued, in the order of their texts (so a
        warning such as a LiDAR intensity unit read from the data reaches stderr once, not once per file, and run.json
        does not depend on the order files finished in or on Python's string hashing)."""
        return self.inputs.lines() + [f"{text} ({n} file{'s' if n > 1 else ''}; in the manifest)"
                                      for text, n in sorted(self.model_warnings.items())]


def _recount(manifest: Path, start: int, tally: _Tally) -> None:
    """The run's counts from its own manifest lines (:func:`_final_lines`: a superseded line dropped) after an
    interrupt, which can land between an entry's line and its count."""
    counted = _Tally(RunSummary())
    try:
        for e in _final_lines(manifest, start, (), counted):
            counted.count(e)
    except OSError:                                    # the counts as tallied, at most one short
        return
    s, c = tally.summary, counted.summary
    s.done, s.skipped, s.failed, s.warned, s.failures = c.done, c.skipped, c.failed, c.warned, c.failures


@dataclass
class _Log:
    """Where this run's lines start in the manifest, whether a line was superseded (a rewrite is due), and the
    files this run's entries claimed (``outputs.DiskIndex``, closed by :func:`_finish`)."""

    start: int = 0
    superseded: bool = False
    claimed: Any = None


def _execute(ctx: RunContext, previous: PreviousRun, summary: RunSummary, executor: Any, limit: int | None,
             fail_fast: bool, progress: bool, workers_started: float,
             coco_run: coco.CocoRun | None = None) -> tuple[_Tally, _Log]:
    """Run the plan, appending each entry to the manifest as it is released in plan order (``outputs.Ledger``);
    a COCO file's output is released after the plan. ``summary.worker_start_s``: from ``workers_started``
    (monotonic; the executor's creation) to the first worker set up and ready for tasks (the fork server's imports
    and warm-up it waited for, the fork, the set-up; not the main process's own work meanwhile: the run record,
    the walk to the first task); without that time from the executor (Dask), to the first file's start in a worker
    (its result's arrival minus its in-worker seconds)."""
    from tqdm import tqdm

    tally, where = _Tally(summary), _Log()
    log_errors: list[OSError] = []
    bar = tqdm(total=summary.planned, unit="file", disable=not progress, file=sys.stderr, dynamic_ncols=True)

    def record(entries: list[dict]) -> None:
        for e in entries:
            if e.get("output") is not None:
                bar.update(1)
            tally.add(e)
            if coco_run is not None:
                coco_run.collect(e)

    left = [summary.planned - (len(ctx.recipe.variants) if coco_run is not None else 0)]   # outputs not walked yet

    def to_run(ledger: Ledger) -> Iterator[Task]:
        """The tasks for the workers; walk failures and outputs ``--resume`` keeps go to the ledger directly."""
        resuming = bool(previous)                      # a fresh run asks nothing per file of the previous run's index
        for item in iter_plan(ctx.in_root, ctx.recipe, limit):
            if ledger.stopped:
                return
            if isinstance(item, Unreadable):
                record(ledger.put(item.index, _walk_entry(item.failure)))
                continue
            left[0] -= 1
            item = coco_run.attach(item) if coco_run is not None else item
            kept = previous.get(item.out_relpath) if resuming else None
            if kept is not None and _still_valid(ctx, item, kept) and \
                    (coco_run is None or coco_run.keeps(item, kept)):
                ledger.claim(kept)
                record(ledger.put(item.index, {**kept, "skipped": True}))
                continue
            yield item

    ledger = None
    sync = None if ctx.fsync_outputs else SyncPool(ctx.out_root)
    try:
        with open(ctx.out_root / MANIFEST_NAME, "a" if previous else "w", encoding="utf-8") as log:
            where.start = log.tell()
            ledger = Ledger(ctx.out_root, log, log_errors.append, fail_fast=fail_fast, sync=sync)
            if sync is not None:
                executor.wake = sync.wake                  # an fsync finished: its entry is released at once
            try:
                for task, result in executor.map(Counted(to_run(ledger), lambda: left[0])):
                    if task is NOT_NOW:
                        record(ledger.synced())
                        if ledger.stopped:
                            break
                        continue
                    if summary.worker_start_s is None and isinstance(result, dict):
                        ready = getattr(executor, "first_ready", lambda: None)() or \
                            time.monotonic() - result.get("seconds", 0.0)
                        summary.worker_start_s = round(ready - workers_started, 4)
                    record(ledger.put(task.index, _result_entry(task, result)))
                    if ledger.stopped:
                        break
                record(ledger.drain())                     # the COCO file follows every image's entry
                if coco_run is not None:
                    ledger.sync = None                     # its file is staged and fsynced by this process
                    record(() if ledger.stopped else coco_run.release(ledger, ctx.out_root, previous))
                    summary.notes += coco_run.run_notes(written=not ledger.stopped)
            finally:
                getattr(executor, "stop", executor.close)()   # run() waits for the workers after the run record
                ledger.discard_pending()
                ledger.folders.close()
                if sync is not None:
                    sync.close()
        if ledger.stopped:
            summary.state = "stopped at the first failure (--fail-fast)"
    except KeyboardInterrupt:                          # recorded like any other end; run() raises it again
        summary.state = "interrupted"
        if ledger is not None:
            _recount(ctx.out_root / MANIFEST_NAME, where.start, tally)
    except RuntimeError as e:                          # workers cannot start: report it, keep what was done
        summary.state = f"aborted: {e}"
        summary.notes.append(f"run aborted: {e}")
    finally:
        bar.close()
        if ledger is not None:
            where.superseded, where.claimed = ledger.superseded, ledger.claimed
    if log_errors:
        summary.notes.append(f"could not append to {MANIFEST_NAME} ({os_error_text(log_errors[0])}); the outputs "
                             "it could not record were not kept")
    return tally, where


def _finish(ctx: RunContext, previous: PreviousRun, tally: _Tally, log: _Log, summary: RunSummary, record: dict,
            started: float, lock: OutputLock, *, prune: bool) -> None:
    """Make OUT equal the manifest and write the run record, however the run ended. ``prune``: the plan was
    complete (no ``--limit``), so outputs of a previous run that it no longer has are removed. The manifest is
    rewritten (streamed) only when it holds lines of an earlier run or a superseded line."""
    out = ctx.out_root
    claimed = log.claimed
    try:
        if previous and summary.state == "complete" and prune:
            remove_listed(out, previous.unseen(), keep=claimed if claimed is not None else frozenset())
            kept: Iterable[dict] = ()
        else:
            kept = previous.unseen() if previous else ()
        remove_stale_temporaries(out)                   # dead workers, discarded results
        if previous or log.superseded:
            try:
                write_manifest(out / MANIFEST_NAME, _final_lines(out / MANIFEST_NAME, log.start, kept, tally))
            except OSError as e:
                summary.notes.append(f"could not rewrite {MANIFEST_NAME} in plan order ({os_error_text(e)}); it "
                                     "still holds every entry, in completion order")
    finally:
        if claimed is not None:
            claimed.close()
    summary.seconds = time.time() - started
    summary.warnings = tally.warnings()
    if any("no space left" in f.lower() for f in summary.failures):     # in run.json's notes too
        summary.notes.append("the disk filled up: free space and run again with --resume to write the missing "
                             "outputs")
    final = {**record, "state": summary.state, "wall_seconds": round(summary.seconds, 3),
             "worker_start_seconds": summary.worker_start_s,
             "warnings": summary.warnings,
             "counts": {"planned": summary.planned, "done": summary.done, "skipped": summary.skipped,
                        "failed": summary.failed}, "notes": summary.notes}
    try:
        write_run_json(out / RUN_NAME, final)
    except OSError as e:
        if e.errno != 28:
            raise OutputError(f"cannot write {out / RUN_NAME}: {os_error_text(e)}") from None
        lock.release_reserve()                          # the lock file's reserved space makes room
        write_run_json(out / RUN_NAME, final)


def _final_lines(manifest: Path, start: int, kept: Iterable[dict], tally: _Tally) -> Iterator[dict]:
    """This run's entries from byte ``start`` of the manifest (a line superseded by the next one, same output,
    dropped), then the previous run's entries it kept without reaching them (``--limit``)."""
    with open(manifest, encoding="utf-8") as fh:
        fh.seek(start)
        held = None
        for line in fh:
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            if held is not None and not (held.get("output") is not None and held.get("output") == entry.get("output")):
                yield held
            held = entry
        if held is not None:
            yield held
    for e in kept:
        tally.add(e, released=False)
        yield e


def _run_record(recipe: Recipe, in_root: Path, out_root: Path, workers: int, started: float,
                limits: Limits) -> dict:
    return {"tool": "rvnoise", "versions": library_versions(), "recipe_source": recipe.source,
            "recipe_base_dir": str(recipe.base_dir), "recipe": recipe.resolved_dict(),
            "recipe_sha256": recipe.sha256(), "seed": recipe.seed, "input_root": str(in_root),
            "output_root": str(out_root), "workers": workers, "started_unix": started,
            "limits": asdict(limits)}


def replay(manifest_path: Path, key: str, *, out_file: Path | None = None,
           input_root: Path | None = None) -> dict[str, Any]:
    """Re-run the recorded recipe for one output and compare sha256 (of every file it wrote) with the manifest.

    Returns ``{"key", "expected", "got", "match", "input_changed", "output", "files"}`` (``files``: every file of
    the output — sidecars and annotations too — with expected and reproduced sha256; ``match`` needs all of them);
    raises RecipeError when the manifest, its run.json or the key is missing."""
    import shutil
    import tempfile

    from .recipe import parse_recipe

    manifest_path = Path(manifest_path)
    if manifest_path.is_dir():                          # OUT/ for OUT/manifest.jsonl
        manifest_path = manifest_path / MANIFEST_NAME
    if not manifest_path.is_file():                     # make demo's out/demo is a folder of runs
        runs = sorted(f"{p.parent.name}/{MANIFEST_NAME}" for p in manifest_path.parent.glob(f"*/{MANIFEST_NAME}"))
        hint = f"; {str(manifest_path.parent)!r} holds runs: give one's manifest ({', '.join(runs)})" if runs else ""
        raise RecipeError(f"no manifest {str(manifest_path)!r}{hint}")
    run_path = manifest_path.with_name(RUN_NAME)
    if not run_path.is_file():
        raise RecipeError(f"no {RUN_NAME} next to {str(manifest_path)!r}; replay needs the run record")
    record = json.loads(run_path.read_text())
    entries = [e for e in read_manifest(manifest_path) if e.get("output") == key]
    if not entries:
        known = [e.get("output") for e in read_manifest(manifest_path) if e.get("output")]
        from .registry import suggest
        raise RecipeError(f"no output {key!r} in {str(manifest_path)!r}{suggest(key, known)}")
    entry = entries[-1]
    if entry.get("modality") == "coco":
        raise RecipeError(f"{key!r} is the run's COCO file, assembled from its images' entries (their 'coco' "
                          "records): replay an image")
    recipe = parse_recipe(record["recipe"], source=str(run_path), base_dir=Path(record["recipe_base_dir"]))
    in_root = Path(os.path.realpath(input_root or record["input_root"]))
    if out_file is not None:                            # never into IN, nor into OUT (OUT equals its manifest)
        target = Path(os.path.realpath(out_file))
        for root, what in ((in_root, "input tree"), (Path(os.path.realpath(manifest_path.parent)), "output folder")):
            if target == root or root in target.parents:
                raise RecipeError(f"--out {str(out_file)!r} is inside the run's {what} {str(root)!r}; replay writes "
                                  "into neither: give a path outside them")
    limits = Limits(**{k: v for k, v in record.get("limits", {}).items() if k in Limits.__dataclass_fields__})
    task = Task(Sample(entry["input"], entry["modality"], entry["sequence"], entry.get("depth")),
                entry["variant_index"], key)
    with tempfile.TemporaryDirectory(prefix="rvnoise-replay-") as tmp:
        ctx = RunContext(in_root, Path(os.path.realpath(tmp)), recipe, limits)
        new = next(InlineExecutor(process, ctx).map([task]))[1]
        if new["status"] == "ok":
            commit(ctx.out_root, new)
            if out_file is not None:
                Path(out_file).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(ctx.out_root / key, out_file)
    got = {f["path"]: f["sha256"] for f in new.get("files", [])}
    files = [{"path": f["path"], "expected": f["sha256"], "got": got.get(f["path"])}
             for f in entry.get("files") or [{"path": key, "sha256": entry.get("output_sha256")}]]
    return {"key": key, "expected": entry.get("output_sha256"), "got": new.get("output_sha256"),
            "match": new.get("status") == "ok" and all(f["expected"] == f["got"] for f in files),
            "input_changed": new.get("input_sha256") != entry.get("input_sha256"), "error": new.get("error"),
            "output": str(out_file) if out_file else None, "files": files}
