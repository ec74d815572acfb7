"""``rvnoise``: the command line. Parses, calls the library, prints; no logic of its own.

Exit codes: 0 success; 1 some files failed (each recorded in the manifest), the run stopped early, or a replay
mismatch; 2 bad recipe, bad arguments or an input/output problem detected before anything was written (one line
on stderr, never a traceback); 130 interrupted.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from roadview_noise.errors import RvNoiseError

app = typer.Typer(name="rvnoise", no_args_is_help=True, add_completion=False, rich_markup_mode="markdown",
                  help="Batch augmentation of camera, raw Bayer, LiDAR and 4D-radar data with the ROADVIEW "
                       "compound sensor noise models (weather × noise factor, CNF01–CNF30).")


def _fail(message: str, code: int = 2) -> None:
    typer.secho(f"rvnoise: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


@app.command(epilog="Example: `rvnoise augment --recipe recipes/cnf16.yaml sample_data out/cnf16 --workers 2`")
def augment(
    input_dir: Path = typer.Argument(..., help="Input tree (never written)."),
    output_dir: Path = typer.Argument(..., help="Output tree: augmented files, manifest.jsonl, run.json."),
    recipe: Path = typer.Option(..., "--recipe", "-r", help="Recipe YAML (a CNF or a chain of models)."),
    workers: Optional[int] = typer.Option(None, "--workers", "-j", min=1, help="Worker processes [default: all cores; capped at the outputs and the memory, see README]."),
    resume: bool = typer.Option(False, "--resume", help="Skip outputs already in the manifest with matching sha256."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an earlier run in OUTPUT_DIR."),
    dry_run: bool = typer.Option(False, "--dry-run", help="List what would be done; write nothing."),
    limit: Optional[int] = typer.Option(None, "--limit", min=1, help="Process only the first N inputs."),
    fail_fast: bool = typer.Option(False, "--fail-fast", help="Stop at the first failing file."),
    yes: bool = typer.Option(False, "--yes", "-y", help="Run even when the plan has more than 100 000 outputs."),
    max_pixels: float = typer.Option(100e6, "--max-pixels", min=1,
                                     help="Refuse images (and depth maps) whose header declares more pixels."),
    max_points: float = typer.Option(20e6, "--max-points", min=1,
                                     help="Refuse point clouds whose header declares more points."),
    task_timeout: Optional[float] = typer.Option(None, "--task-timeout", min=0.1,
                                                 help="Stop a worker that spends longer on one file (seconds)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Apply a recipe to every matching input under INPUT_DIR and write the augmented tree to OUTPUT_DIR."""
    from roadview_noise.recipe import load_recipe
    from roadview_noise.runner import Limits, run

    limits = Limits(max_pixels=int(max_pixels), max_points=int(max_points), task_timeout_s=task_timeout)
    try:
        r = load_recipe(recipe)
        s = run(r, input_dir, output_dir, workers=workers, resume=resume, overwrite=overwrite, dry_run=dry_run,
                limit=limit, fail_fast=fail_fast, yes=yes, limits=limits, progress=not quiet, echo=typer.echo,
                warn=lambda m: typer.echo(m, err=True))
    except RvNoiseError as e:
        _fail(str(e))
    except KeyboardInterrupt:
        _fail("interrupted; the manifest and run.json record what was done (--resume completes it)", 130)
    if s.dry_run:
        typer.echo(f"rvnoise: dry run, {s.planned} outputs planned, nothing written")
        return
    for f in s.failures[:10]:
        typer.secho(f"failed: {f}", fg=typer.colors.RED, err=True)
    if len(s.failures) > 10:
        typer.secho(f"… and {len(s.failures) - 10} more (see the manifest)", fg=typer.colors.RED, err=True)
    if s.warned:
        typer.secho(f"warning: {s.warned} output(s) had invalid input points removed (input_warnings in the "
                    "manifest)", fg=typer.colors.YELLOW, err=True)
    typer.echo(f"rvnoise: {s.done} written, {s.skipped} skipped, {s.failed} failed in {s.seconds:.1f} s → "
               f"{output_dir} (manifest: {output_dir / 'manifest.jsonl'})")
    if s.failed or s.state != "complete" or s.notes:
        raise typer.Exit(1)


@app.command(epilog="Example: `rvnoise validate recipes/cnf13.yaml`")
def validate(recipe: Path = typer.Argument(..., help="Recipe YAML.")) -> None:
    """Check a recipe without running it (exit 2 naming the key when it is invalid)."""
    from roadview_noise.recipe import load_recipe

    try:
        r = load_recipe(recipe)
    except RvNoiseError as e:
        _fail(str(e))
    typer.echo(f"ok: {recipe}: {r.sensor} chain {' → '.join(r.model_ids)}, {len(r.variants)} variant(s), "
               f"seed {r.seed}")


@app.command("list", epilog="Example: `rvnoise list`")
def list_models() -> None:
    """List the models (id, sensor, stage, scope) and the CNF table of D3.5."""
    from roadview_noise.compound import CNFS
    from roadview_noise.registry import load_all

    models = load_all()
    typer.echo("Models:")
    for mid in sorted(models, key=lambda m: (models[m].sensor, models[m].stage, m)):
        c = models[mid]
        typer.echo(f"  {mid:<24} {c.sensor:<7} {c.stage.name:<12} {c.scope.value:<9} {c.summary}")
    typer.echo("\nCompound noise factors (D3.5 Table 6); * = a model not implemented yet:")
    for name, cnf in CNFS.items():
        chains = "; ".join(" → ".join(m if m in models else f"{m}*" for m in ids) for ids in cnf.chains.values())
        typer.echo(f"  {name}  {cnf.method:<6} {cnf.factor:<26} {cnf.weather:<5} {chains}")


@app.command(epilog="Examples: `rvnoise show CNF13`, `rvnoise show fog.lidar`")
def show(name: str = typer.Argument(..., help="A CNF (CNF01–CNF30) or a model id.")) -> None:
    """Show a CNF's steps in order, or one model, with every parameter's unit, default and range."""
    from roadview_noise.compound import CNFS
    from roadview_noise.registry import get_model, load_all, suggest

    models = load_all()
    if name.upper() in CNFS:
        cnf = CNFS[name.upper()]
        typer.echo(f"{name.upper()}: {cnf.factor} with {cnf.weather} ({cnf.method})")
        for sensor, ids in cnf.chains.items():
            typer.echo(f"\n[{sensor}]")
            for i, mid in enumerate(ids, 1):
                _show_model(mid, models, prefix=f"{i}. ")
        return
    if name not in models:
        _fail(f"{name!r} is neither a CNF nor a model{suggest(name, list(models) + list(CNFS))}")
    _show_model(name, models)
    doc = (get_model(name).__doc__ or "").strip()
    if doc:
        typer.echo("\n" + doc)


def _show_model(mid: str, models: dict, prefix: str = "") -> None:
    if mid not in models:
        typer.echo(f"{prefix}{mid}  (not implemented yet)")
        return
    c = models[mid]
    typer.echo(f"{prefix}{mid}  [{c.stage.name}, {c.scope.value}] {c.summary}")
    for p in c.param_specs():
        typer.echo(f"     {p.name:<28} {p.unit:<10} default {p.default!s:<12} {p.range_text():<20} {p.doc}")


@app.command(epilog="Example: `rvnoise replay out/demo/manifest.jsonl --key camera/seq0/000000.png`")
def replay(
    manifest: Path = typer.Argument(..., help="A run's manifest.jsonl (run.json must be next to it)."),
    key: str = typer.Option(..., "--key", "-k", help="Output path relative to the output root."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Also write the reproduced file here."),
    input_root: Optional[Path] = typer.Option(None, "--input-root", help="Input tree if it moved."),
) -> None:
    """Reproduce one output from the manifest and compare its sha256 (exit 1 on mismatch)."""
    from roadview_noise.runner import replay as do_replay

    try:
        r = do_replay(manifest, key, out_file=out, input_root=input_root)
    except RvNoiseError as e:
        _fail(str(e))
    if r["error"]:
        _fail(r["error"], 1)
    if r["input_changed"]:
        typer.secho("warning: the input file changed since the run", fg=typer.colors.YELLOW, err=True)
    status = "match" if r["match"] else "MISMATCH"
    typer.echo(f"{status}: {key} sha256 {r['got']} (manifest {r['expected']})")
    if not r["match"]:
        raise typer.Exit(1)


@app.command("sample-data", epilog="Example: `rvnoise sample-data out/sample --frames 10 --seed 0`")
def sample_data(
    out_dir: Path = typer.Argument(..., help="Folder to write the synthetic drive into."),
    frames: int = typer.Option(3, "--frames", "-n", min=1, help="Frames in the sequence."),
    seed: int = typer.Option(0, "--seed", help="Scene seed (generation is deterministic)."),
    camera_size: Optional[str] = typer.Option(None, "--camera-size", help="WxH, e.g. 484x366 [default: 1936x1464]."),
    lidar_columns: Optional[int] = typer.Option(None, "--lidar-columns", min=16,
                                                help="Azimuth columns per scan [default: the sensor's]."),
) -> None:
    """Render a synthetic ideal drive (camera, raw Bayer, LiDAR, radar) from one procedural scene, at the sensors'
    full resolutions unless told otherwise (about 40 MB per frame)."""
    from roadview_noise.sampledata.generate import generate

    size = None
    if camera_size:
        try:
            w, h = (int(v) for v in camera_size.lower().split("x"))
            size = (w, h)
        except ValueError:
            _fail(f"--camera-size must be WIDTHxHEIGHT, got {camera_size!r}")
    summary = generate(out_dir, frames=frames, seed=seed, camera_size=size, lidar_columns=lidar_columns,
                       progress=True)
    typer.echo(f"rvnoise: {len(summary['files'])} files, {summary['bytes'] / 1e6:.1f} MB in "
               f"{summary['seconds']:.1f} s → {out_dir}")


if __name__ == "__main__":
    app()
