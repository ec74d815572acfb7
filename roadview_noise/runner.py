"""Batch runner: plan tasks (input × sweep variant), run them in worker processes, write atomically, record.

Output bytes depend only on the recipe, the seed, the input bytes and library versions — never on the number of
workers, the order or resuming: every random draw comes from ``derive_rng(seed, output relpath, ...)``."""

from __future__ import annotations

import os
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from . import annotations
from .allocator import keep_freed_memory
from .camera_inputs import run_warnings
from .compound import apply_models
from .dataset import Sample, discover, load, output_relpath, save
from .errors import RecipeError, RvNoiseError
from .io.atomic import remove_stale_temporaries
from .manifest import (MANIFEST_NAME, RUN_NAME, dumps, library_versions, read_manifest, sha256_file,
                       write_manifest, write_run_json)
from .metrics import compare
from .recipe import Recipe, draw_value
from .registry import get_model
from .seeding import derive_rng


@dataclass(frozen=True)
class Task:
    sample: Sample
    variant_index: int
    out_relpath: str


@dataclass
class RunSummary:
    planned: int = 0
    done: int = 0
    skipped: int = 0
    failed: int = 0
    seconds: float = 0.0
    failures: list[str] = field(default_factory=list)
    dry_run: bool = False


def check_roots(in_root: Path, out_root: Path) -> None:
    """Refuse an output inside the input (or the reverse): the input tree is never written."""
    if not in_root.is_dir():
        raise RecipeError(f"input folder {str(in_root)!r} does not exist")
    a, b = in_root.resolve(), out_root.resolve()
    if a == b or a in b.parents or b in a.parents:
        raise RecipeError(f"output {str(out_root)!r} and input {str(in_root)!r} overlap; "
                          "the input tree is never written, choose a separate output folder")


def plan(in_root: Path, recipe: Recipe, limit: int | None = None) -> list[Task]:
    samples = discover(in_root, recipe)
    if limit is not None:
        samples = samples[:limit]
    return [Task(s, i, output_relpath(s.relpath, v.suffix)) for s in samples for i, v in enumerate(recipe.variants)]


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


def process(task: Task, in_root: Path, out_root: Path, recipe: Recipe) -> dict[str, Any]:
    """Read, run the chain, write atomically; return the manifest entry (failures are recorded, not raised)."""
    import cv2

    cv2.setNumThreads(1)
    keep_freed_memory()
    t0 = time.perf_counter()
    s = task.sample
    entry: dict[str, Any] = {
        "output": task.out_relpath, "input": s.relpath, "modality": s.modality, "sequence": s.sequence_id,
        "depth": s.depth_relpath, "variant_index": task.variant_index,
        "variant": recipe.variants[task.variant_index].overrides, "chain": list(recipe.model_ids),
    }
    try:
        entry["input_sha256"] = sha256_file(in_root / s.relpath)
        data = load(s, in_root, recipe)
        if getattr(data, "input_notes", None):
            entry["inputs"] = dict(data.input_notes)
        spec = recipe.spec.inputs.annotations
        sidecars = annotations.read(s.relpath, in_root, spec, data)
        models = build_models(recipe, task)
        out, records = apply_models(models, data, seed=recipe.seed, key=task.out_relpath,
                                    sequence_id=s.sequence_id, metrics=recipe.spec.output.metrics)
        entry["steps"] = [asdict(r) for r in records]
        entry["metrics"] = compare(data, out) if recipe.spec.output.metrics else {}
        out, annotated = annotations.carry(sidecars, spec, data, out, recipe.model_ids, out_root,
                                           recipe.variants[task.variant_index].suffix)
        files = save(out, out_root / task.out_relpath, recipe, source=in_root / s.relpath, annotations=annotated)
        entry["files"] = [{"path": p.relative_to(out_root).as_posix(), "sha256": sha256_file(p)} for p in files]
        entry["output_sha256"] = entry["files"][0]["sha256"]
        entry.update({k: v for k, v in (("annotations_read", annotated.read), ("objects", annotated.objects)) if v})
        entry["status"] = "ok"
    except RvNoiseError as e:
        entry.update(status="failed", error=str(e) if s.relpath in str(e) else f"{s.relpath}: {e}")
    except Exception as e:  # a bug or a library error on one file must not stop the run; keep the trace
        entry.update(status="failed", error=f"{s.relpath}: internal error {type(e).__name__}: {e}",
                     traceback=traceback.format_exc(limit=8))
    entry["seconds"] = round(time.perf_counter() - t0, 4)
    return entry


def _previous_ok(out_root: Path, entries: list[dict]) -> dict[str, dict]:
    """Manifest entries whose output files (main, sidecars, annotations) still exist with the recorded sha256 (what
    --resume may skip)."""
    ok = {}
    for e in entries:
        if e.get("status") == "ok":
            files = e.get("files") or [{"path": e["output"], "sha256": e.get("output_sha256")}]
            if all((out_root / f["path"]).is_file() and sha256_file(out_root / f["path"]) == f["sha256"]
                   for f in files):
                ok[e["output"]] = e
            else:
                ok.pop(e["output"], None)
    return ok


def run(recipe: Recipe, in_root: Path, out_root: Path, *, workers: int | None = None, resume: bool = False,
        overwrite: bool = False, dry_run: bool = False, limit: int | None = None, fail_fast: bool = False,
        progress: bool = True, echo: Callable[[str], None] = print) -> RunSummary:
    """Run a recipe over an input tree. Raises RecipeError (exit 2) before writing anything if it cannot start."""
    started = time.time()
    check_roots(in_root, out_root)
    tasks = plan(in_root, recipe, limit)
    summary = RunSummary(planned=len(tasks), dry_run=dry_run)
    if not tasks:
        raise RecipeError(f"no {recipe.sensor} inputs under {str(in_root)!r} match the recipe's inputs")
    manifest_path = out_root / MANIFEST_NAME
    if dry_run:
        for t in tasks:
            echo(f"{t.sample.relpath} → {t.out_relpath}  [{' → '.join(recipe.model_ids)}]")
        return summary
    if manifest_path.exists() and not (resume or overwrite):
        raise RecipeError(f"{str(out_root)!r} holds an earlier run; use --resume to complete it or --overwrite")

    out_root.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out_root)
    previous = _previous_ok(out_root, read_manifest(manifest_path)) if resume else {}
    todo = [t for t in tasks if t.out_relpath not in previous]
    summary.skipped = len(tasks) - len(todo)
    n_workers = workers or os.cpu_count() or 1

    results: dict[str, dict] = {}
    with open(manifest_path, "a" if resume else "w", encoding="utf-8") as log:
        for entry in _execute(todo, in_root, out_root, recipe, n_workers, progress):
            results[entry["output"]] = entry
            log.write(dumps(entry) + "\n")
            log.flush()
            if entry["status"] == "ok":
                summary.done += 1
            else:
                summary.failed += 1
                summary.failures.append(entry["error"])
                if fail_fast:
                    break
    final = [results.get(t.out_relpath) or previous.get(t.out_relpath) for t in tasks]
    write_manifest(manifest_path, [e for e in final if e is not None])
    summary.seconds = time.time() - started
    warnings = run_warnings(e for e in final if e is not None)
    for line in warnings:
        echo(f"rvnoise: warning: {line}")
    write_run_json(out_root / RUN_NAME, {
        "tool": "rvnoise", "versions": library_versions(), "recipe_source": recipe.source,
        "recipe_base_dir": str(recipe.base_dir), "recipe": recipe.resolved_dict(), "recipe_sha256": recipe.sha256(),
        "seed": recipe.seed, "input_root": str(in_root.resolve()), "output_root": str(out_root.resolve()),
        "workers": n_workers, "started_unix": started, "wall_seconds": round(summary.seconds, 3), "warnings": warnings,
        "counts": {"planned": summary.planned, "done": summary.done, "skipped": summary.skipped,
                   "failed": summary.failed},
    })
    return summary


def _execute(tasks: list[Task], in_root: Path, out_root: Path, recipe: Recipe, workers: int, progress: bool):
    """Yield manifest entries in task order; one process when workers == 1, else joblib's loky processes."""
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), unit="file", disable=not progress, file=sys.stderr, dynamic_ncols=True)
    try:
        if workers <= 1 or len(tasks) <= 1:
            results = (process(t, in_root, out_root, recipe) for t in tasks)
        else:
            from joblib import Parallel, delayed

            parallel = Parallel(n_jobs=workers, backend="loky", return_as="generator")
            results = parallel(delayed(process)(t, in_root, out_root, recipe) for t in tasks)
        for entry in results:
            bar.update(1)
            yield entry
    finally:
        bar.close()


def replay(manifest_path: Path, key: str, *, out_file: Path | None = None,
           input_root: Path | None = None) -> dict[str, Any]:
    """Re-run the recorded recipe for one output and compare sha256 with the manifest.

    Returns ``{"key", "expected", "got", "match", "input_changed", "output", "files"}`` (``files``: every file of
    the output — sidecars and annotations too — with expected and reproduced sha256; ``match`` needs all of them);
    raises RecipeError when the manifest, its run.json or the key is missing."""
    import json
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
        known = [e.get("output") for e in read_manifest(manifest_path)]
        from .registry import suggest
        raise RecipeError(f"no output {key!r} in {str(manifest_path)!r}{suggest(key, known)}")
    entry = entries[-1]
    recipe = parse_recipe(record["recipe"], source=str(run_path), base_dir=Path(record["recipe_base_dir"]))
    in_root = Path(input_root or record["input_root"])
    task = Task(Sample(entry["input"], entry["modality"], entry["sequence"], entry.get("depth")),
                entry["variant_index"], key)
    with tempfile.TemporaryDirectory(prefix="rvnoise-replay-") as tmp:
        new = process(task, in_root, Path(tmp), recipe)
        if new["status"] == "ok" and out_file is not None:
            Path(out_file).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(Path(tmp) / key, out_file)
    got = {f["path"]: f["sha256"] for f in new.get("files", [])}
    files = [{"path": f["path"], "expected": f["sha256"], "got": got.get(f["path"])}
             for f in entry.get("files") or [{"path": key, "sha256": entry.get("output_sha256")}]]
    return {"key": key, "expected": entry.get("output_sha256"), "got": new.get("output_sha256"),
            "match": new.get("output_sha256") is not None and all(f["expected"] == f["got"] for f in files),
            "input_changed": new.get("input_sha256") != entry.get("input_sha256"), "error": new.get("error"),
            "output": str(out_file) if out_file else None, "files": files}
