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

import itertools
import json
import os
import sys
import time
import traceback
import warnings
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

from . import annotations
from .allocator import keep_freed_memory
from .camera_inputs import run_warnings
from .compound import apply_models
from .dataset import Sample, iter_inputs, load, output_relpath, save
from .errors import InputError, OutputError, RecipeError, RvNoiseError
from .executor import InlineExecutor, ProcessExecutor, TaskError, WorkerDeath
from .invalid_points import drop_invalid_points
from .io.atomic import confined_to, remove_stale_temporaries, staged_writes
from .io.headers import check_size
from .lock import OutputLock
from .manifest import (MANIFEST_NAME, RUN_NAME, library_versions, read_manifest, sha256_file, write_manifest,
                       write_run_json)
from .metrics import compare
from .native_output import captured_output
from .outputs import Ledger, commit, discard, files_intact, listed_files, remove_listed
from .recipe import Recipe, draw_value
from .registry import adopt, get_model, plugin_models
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


@dataclass(frozen=True)
class RunContext:
    """What every worker receives once: real input and output roots, the recipe, the limits; whether to collect
    what native libraries print (in worker processes) into the entry's ``library_messages``."""

    in_root: Path
    out_root: Path
    recipe: Recipe
    limits: Limits = Limits()
    capture_output: bool = False


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
    warnings: list[str] = field(default_factory=list)  # about the inputs as a whole (camera_inputs.run_warnings)
    state: str = "complete"


# --- planning --------------------------------------------------------------------------------------------------------


def check_roots(in_root: Path, out_root: Path) -> tuple[Path, Path]:
    """Real paths of the roots; refuses a missing input, an output that is a file, and overlapping roots (the input
    tree is never written)."""
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


def build_models(recipe: Recipe, task: Task) -> list:
    """Instantiate the chain for one output: fixed values, sweep overrides, and per-file distribution draws."""
    overrides = recipe.variants[task.variant_index].overrides
    models = []
    for i, (model_id, params) in enumerate(zip(recipe.model_ids, recipe.step_params)):
        cls = get_model(model_id)
        integer = {p.name for p in cls.param_specs() if type(p.default) is int}
        rng = derive_rng(recipe.seed, task.out_relpath, "params", i, model_id)
        values = {k: draw_value(v, rng, integer=k in integer) for k, v in sorted(params.items())}
        values.update({k: draw_value(v, None) for k, v in overrides.get(model_id, {}).items()})
        models.append(cls(**values))
    return models


# --- one output (in a worker) ----------------------------------------------------------------------------------------


def input_path(in_root: Path, relpath: str) -> Path:
    """``in_root / relpath``, refused when it resolves (through a symlink) outside the input folder."""
    path = in_root / relpath
    real = os.path.realpath(path)
    root = os.path.realpath(in_root)
    if not real.startswith(root + os.sep):
        raise InputError(f"resolves to {real!r}, outside the input folder; rvnoise reads only inside it",
                         file=str(path))
    return path


def sha256_input(path: Path) -> str:
    try:
        return sha256_file(path)
    except OSError as exc:
        raise InputError(f"cannot read the file: {os_error_text(exc)}", file=str(path)) from None


def _check_sizes(sample: Sample, path: Path, depth: Path | None, ctx: RunContext) -> None:
    from .io.pointcloud import cloud_format

    limits = ctx.limits
    if sample.modality in ("lidar", "radar"):
        check_size(path, max_points=limits.max_points, cloud_fmt=cloud_format(path, sample.modality))
    else:
        for p in (path, depth):
            if p is not None:
                check_size(p, max_pixels=limits.max_pixels)


def _warning_list(caught: list) -> list[str]:
    counts = Counter(f"{w.category.__name__}: {w.message}" for w in caught)
    return [f"{text} (×{n})" if n > 1 else text for text, n in counts.items()]


def _model_warnings(entries: list[dict]) -> list[str]:
    """One line per distinct warning a model issued in the run (each entry keeps its own, ``warnings``), so a warning
    such as a LiDAR intensity unit read from the data reaches stderr once, not once per file."""
    files: Counter = Counter()
    for e in entries:
        files.update({w.rsplit(" (×", 1)[0] for w in e.get("warnings", ())})
    return [f"{text} ({n} file{'s' if n > 1 else ''}; in the manifest)" for text, n in files.items()]


def process(task: Task, ctx: RunContext) -> dict[str, Any]:
    """Read, run the chain, stage the output files; return the manifest entry (failures are recorded, not raised).
    The files stay fsynced temporaries listed under ``staged`` until the runner has recorded them."""
    keep_freed_memory()
    t0 = time.perf_counter()
    s, recipe = task.sample, ctx.recipe
    entry: dict[str, Any] = {
        "output": task.out_relpath, "input": s.relpath, "modality": s.modality, "sequence": s.sequence_id,
        "depth": s.depth_relpath, "variant_index": task.variant_index,
        "variant": recipe.variants[task.variant_index].overrides, "chain": list(recipe.model_ids),
    }
    with captured_output(ctx.capture_output) as printed:
        _process(task, ctx, entry)
    if printed:
        entry["library_messages"] = printed
    entry["seconds"] = round(time.perf_counter() - t0, 4)
    return entry


def _process(task: Task, ctx: RunContext, entry: dict[str, Any]) -> None:
    """The body of :func:`process`: fills ``entry``."""
    s, recipe = task.sample, ctx.recipe
    try:
        source = input_path(ctx.in_root, s.relpath)
        entry["input_sha256"] = sha256_input(source)
        depth = None
        if s.depth_relpath is not None:
            depth = input_path(ctx.in_root, s.depth_relpath)
            entry["depth_sha256"] = sha256_input(depth)
        _check_sizes(s, source, depth, ctx)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            data = load(s, ctx.in_root, recipe)
            if getattr(data, "input_notes", None):
                entry["inputs"] = dict(data.input_notes)
            data, dropped = drop_invalid_points(data, file=str(source))
            if dropped:
                entry["input_warnings"] = dropped
            spec = recipe.spec.inputs.annotations
            sidecars = annotations.read(s.relpath, ctx.in_root, spec, data)
            out, records = apply_models(build_models(recipe, task), data, seed=recipe.seed, key=task.out_relpath,
                                        sequence_id=s.sequence_id, metrics=recipe.spec.output.metrics)
            entry["steps"] = [asdict(r) for r in records]
            entry["metrics"] = compare(data, out) if recipe.spec.output.metrics else {}
            out, annotated = annotations.carry(sidecars, spec, data, out, recipe.model_ids, ctx.out_root,
                                               recipe.variants[task.variant_index].suffix)
            entry.update({k: v for k, v in (("annotations_read", annotated.read), ("objects", annotated.objects))
                          if v})
            with confined_to(ctx.out_root), staged_writes() as stage:
                save(out, ctx.out_root / task.out_relpath, recipe, source=source, annotations=annotated)
                entry["files"] = [{"path": final.relative_to(ctx.out_root).as_posix(), "sha256": sha256_file(tmp)}
                                  for tmp, final in stage.files]
                entry["staged"] = [[tmp.relative_to(ctx.out_root).as_posix(),
                                    final.relative_to(ctx.out_root).as_posix()] for tmp, final in stage.files]
        if caught:
            entry["warnings"] = _warning_list(caught)
        entry["output_sha256"] = next(f["sha256"] for f in entry["files"] if f["path"] == task.out_relpath)
        entry["status"] = "ok"
    except RvNoiseError as e:
        entry.update(status="failed", error=str(e) if s.relpath in str(e) else f"{s.relpath}: {e}")
    except OSError as e:                   # the environment: disk full, a folder outside OUT, a vanished file
        what = os_error_text(e) if e.strerror else str(e)
        hint = "; free space and run again with --resume" if e.errno == 28 else ""
        entry.update(status="failed", error=f"{s.relpath}: cannot write {task.out_relpath}: {what}{hint}")
    except Exception as e:  # a bug or a library error on one file must not stop the run; keep the trace
        entry.update(status="failed", error=f"{s.relpath}: internal error {type(e).__name__}: {e}",
                     traceback=traceback.format_exc(limit=8))
    if entry["status"] != "ok":
        for key in ("files", "output_sha256"):
            entry.pop(key, None)
        discard(ctx.out_root, entry)


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


def run(recipe: Recipe, in_root: Path, out_root: Path, *, workers: int | None = None, resume: bool = False,
        overwrite: bool = False, dry_run: bool = False, limit: int | None = None, fail_fast: bool = False,
        yes: bool = False, limits: Limits = Limits(), progress: bool = True, echo: Callable[[str], None] = print,
        warn: Callable[[str], None] | None = None) -> RunSummary:
    """Run a recipe over an input tree. Raises RecipeError / OutputError (exit 2) before writing anything if it
    cannot start; ``warn`` (default ``echo``) gets the messages meant for stderr."""
    warn = warn or echo
    started = time.time()
    in_real, out_real = check_roots(in_root, out_root)
    cap = None if yes else MAX_OUTPUTS_WITHOUT_YES
    planned, unreadable = count_plan(in_real, recipe, limit, cap)
    if cap is not None and planned > cap:
        raise RecipeError(f"the recipe plans more than {cap:,} outputs ({len(recipe.variants):,} variant(s) per "
                          "input); say --yes to run it anyway, or narrow the sweep or the inputs (--limit)")
    if planned == 0 and unreadable == 0:
        raise RecipeError(f"no {recipe.sensor} inputs under {str(in_root)!r} match the recipe's inputs")
    summary = RunSummary(planned=planned, dry_run=dry_run)
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
        previous = _previous_run(out_real, recipe, resume, overwrite)
        remove_stale_temporaries(out_real)
        n_workers, capped = choose_workers(workers, planned)
        if capped:
            warn(f"rvnoise: {capped}")
        summary.workers = n_workers
        record = _run_record(recipe, in_real, out_real, n_workers, started, limits)
        try:
            write_run_json(out_real / RUN_NAME, {**record, "state": "running"})
        except OSError as e:
            raise OutputError(f"cannot write in the output folder {str(out_root)!r}: {os_error_text(e)}") from None
        ctx = RunContext(in_real, out_real, recipe, limits, capture_output=True)
        released = _execute(ctx, previous, summary, n_workers, limit, fail_fast, progress)
        _finish(ctx, previous, released, summary, record, started, lock, prune=limit is None)
    for line in summary.warnings:
        warn(f"rvnoise: warning: {line}")
    for note in summary.notes:
        warn(f"rvnoise: {note}")
    if summary.state == "interrupted":
        raise KeyboardInterrupt
    return summary


def _previous_run(out_root: Path, recipe: Recipe, resume: bool, overwrite: bool) -> dict[str, dict]:
    """The ok entries of an earlier run in ``out_root`` that ``--resume`` may keep, by output; checks that the
    earlier run may be continued or replaced, and on ``--overwrite`` deletes the files it lists."""
    manifest, run_json = out_root / MANIFEST_NAME, out_root / RUN_NAME
    if not (manifest.exists() or run_json.exists()):
        return {}
    if not (resume or overwrite):
        raise OutputError(f"{str(out_root)!r} holds an earlier run; use --resume to complete it or --overwrite")
    entries = read_manifest(manifest)
    if overwrite:
        remove_listed(out_root, entries)
        for p in (manifest, run_json):
            p.unlink(missing_ok=True)
        return {}
    try:
        record = json.loads(run_json.read_text())
    except (OSError, ValueError):
        raise OutputError(f"{str(out_root)!r} has no readable {RUN_NAME}, so the recipe of its run is unknown; "
                          "use --overwrite to replace it") from None
    if record.get("recipe_sha256") != recipe.sha256():
        raise OutputError(f"{str(out_root)!r} was made by another recipe (sha256 {str(record.get('recipe_sha256'))[:12]}…,"
                          f" this one {recipe.sha256()[:12]}…); --resume continues the same recipe only: use "
                          "--overwrite to replace that run, or another output folder")
    ok: dict[str, dict] = {}
    for e in entries:                                   # the last line of an output wins
        if e.get("output") is not None:
            ok.pop(e["output"], None)
            if e.get("status") == "ok":
                ok[e["output"]] = e
    return ok


def _still_valid(ctx: RunContext, task: Task, entry: dict) -> bool:
    """A previous entry ``--resume`` can keep: same variant, same input (and depth) bytes, files intact."""
    if entry.get("variant_index") != task.variant_index or entry.get("input") != task.sample.relpath:
        return False
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


def _execute(ctx: RunContext, previous: dict[str, dict], summary: RunSummary, n_workers: int, limit: int | None,
             fail_fast: bool, progress: bool) -> list[dict]:
    """Run the plan; returns the released entries in plan order (see ``outputs.Ledger``)."""
    from tqdm import tqdm

    released: list[dict] = []
    log_errors: list[OSError] = []
    bar = tqdm(total=summary.planned, unit="file", disable=not progress, file=sys.stderr, dynamic_ncols=True)

    def record(entries: list[dict]) -> None:
        for e in entries:
            skipped = e.pop("skipped", False)
            released.append(e)
            if e.get("output") is not None:
                bar.update(1)
            if skipped:
                summary.skipped += 1
            elif e["status"] == "ok":
                summary.done += 1
                summary.warned += bool(e.get("input_warnings"))
            else:
                summary.failed += 1
                summary.failures.append(e["error"])

    def to_run(ledger: Ledger) -> Iterator[Task]:
        """The tasks for the workers; walk failures and outputs ``--resume`` keeps go to the ledger directly."""
        for item in iter_plan(ctx.in_root, ctx.recipe, limit):
            if ledger.stopped:
                return
            if isinstance(item, Unreadable):
                record(ledger.put(item.index, _walk_entry(item.failure)))
                continue
            kept = previous.get(item.out_relpath)
            if kept is not None and _still_valid(ctx, item, kept):
                ledger.claim(kept)
                record(ledger.put(item.index, {**kept, "skipped": True}))
                continue
            yield item

    executor = ProcessExecutor(process, ctx, n_workers, setup=(adopt, (plugin_models(),)),
                               timeout_s=ctx.limits.task_timeout_s)
    try:
        with open(ctx.out_root / MANIFEST_NAME, "a" if previous else "w", encoding="utf-8") as log:
            ledger = Ledger(ctx.out_root, log, log_errors.append, fail_fast=fail_fast)
            try:
                for task, result in executor.map(to_run(ledger)):
                    record(ledger.put(task.index, _result_entry(task, result)))
                    if ledger.stopped:
                        break
            finally:
                executor.close()
                ledger.discard_pending()
        if ledger.stopped:
            summary.state = "stopped at the first failure (--fail-fast)"
    except KeyboardInterrupt:                          # recorded like any other end; run() raises it again
        summary.state = "interrupted"
    except RuntimeError as e:                          # workers cannot start: report it, keep what was done
        summary.state = f"aborted: {e}"
        summary.notes.append(f"run aborted: {e}")
    finally:
        bar.close()
    if log_errors:
        summary.notes.append(f"could not append to {MANIFEST_NAME} ({os_error_text(log_errors[0])}); the outputs "
                             "it could not record were not kept")
    return released


def _finish(ctx: RunContext, previous: dict[str, dict], released: list[dict], summary: RunSummary, record: dict,
            started: float, lock: OutputLock, *, prune: bool) -> None:
    """Make OUT equal the manifest and write the run record, however the run ended. ``prune``: the plan was
    complete (no ``--limit``), so outputs of a previous run that it no longer has are removed."""
    out = ctx.out_root
    seen = {e.get("output") for e in released}
    kept = [e for key, e in previous.items() if key not in seen]
    if summary.state == "complete" and prune:
        claimed = {f for e in released if e.get("status") == "ok" for f in listed_files(e)}
        remove_listed(out, kept, keep=claimed)          # outputs the plan no longer has (inputs removed)
        kept = []
    remove_stale_temporaries(out)                       # dead workers, discarded results
    try:
        write_manifest(out / MANIFEST_NAME, released + kept)
    except OSError as e:
        summary.notes.append(f"could not rewrite {MANIFEST_NAME} in plan order ({os_error_text(e)}); it still "
                             "holds every entry, in completion order")
    summary.seconds = time.time() - started
    summary.warnings = run_warnings(e for e in released + kept) + _model_warnings(released + kept)
    final = {**record, "state": summary.state, "wall_seconds": round(summary.seconds, 3),
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
    if any("no space left" in f.lower() for f in summary.failures):
        summary.notes.append("the disk filled up: free space and run again with --resume to write the missing "
                             "outputs")


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
    recipe = parse_recipe(record["recipe"], source=str(run_path), base_dir=Path(record["recipe_base_dir"]))
    in_root = Path(os.path.realpath(input_root or record["input_root"]))
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
