"""``rvnoise``: the command line. Parses, calls the library, prints; no logic of its own.

Exit codes: 0 success; 1 some files failed (each recorded in the manifest) or a replay mismatch; 2 bad recipe,
bad arguments or an input/output problem detected before anything was written.
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


def _finish(failures: list[str], summary: str, *, label: str = "failed") -> None:
    """Print the first failures and the summary line; exit 1 when anything failed."""
    for f in failures[:10]:
        typer.secho(f"{label}: {f}", fg=typer.colors.RED, err=True)
    typer.echo(summary)
    if failures:
        raise typer.Exit(1)


@app.command(epilog="Examples: `rvnoise augment --recipe recipes/cnf16.yaml sample_data out/cnf16 --workers 2`, "
                     "`rvnoise augment --recipe recipes/bag-rehearse.yaml drive.bag out/drive-rain.bag`")
def augment(
    input_dir: Path = typer.Argument(..., help="Input tree, or a ROS bag (.bag, .mcap, .db3, ROS 2 bag folder); "
                                               "never written."),
    output_dir: Path = typer.Argument(..., help="Output tree (augmented files, manifest.jsonl, run.json), or the "
                                                "output bag (OUT.manifest.jsonl and OUT.run.json beside it)."),
    recipe: Path = typer.Option(..., "--recipe", "-r", help="Recipe YAML (a CNF or a chain of models)."),
    workers: Optional[int] = typer.Option(None, "--workers", "-j", min=1, help="Worker processes [default: all cores]."),
    resume: bool = typer.Option(False, "--resume", help="Skip outputs already in the manifest with matching sha256."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an earlier run in OUTPUT_DIR."),
    dry_run: bool = typer.Option(False, "--dry-run", help="List what would be done; write nothing."),
    limit: Optional[int] = typer.Option(None, "--limit", min=1, help="Process only the first N inputs."),
    fail_fast: bool = typer.Option(False, "--fail-fast", help="Stop at the first failing file."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Apply a recipe to every matching input under INPUT_DIR and write the augmented tree to OUTPUT_DIR; or to the
    mapped topics of a ROS bag, writing the output bag (README "ROS bags")."""
    from roadview_noise.io.rosbag import bag_kind
    from roadview_noise.recipe import load_recipe
    from roadview_noise.runner import run

    if bag_kind(input_dir) is not None:
        return _augment_bag(input_dir, output_dir, recipe, workers, overwrite, quiet,
                            refused=[o for o, on in (("--resume", resume), ("--dry-run", dry_run), ("--limit", limit),
                                                     ("--fail-fast", fail_fast)) if on])
    try:
        r = load_recipe(recipe)
        s = run(r, input_dir, output_dir, workers=workers, resume=resume, overwrite=overwrite, dry_run=dry_run,
                limit=limit, fail_fast=fail_fast, progress=not quiet, echo=typer.echo)
    except RvNoiseError as e:
        _fail(str(e))
    if s.dry_run:
        typer.echo(f"rvnoise: dry run, {s.planned} outputs planned, nothing written")
        return
    _finish(s.failures, f"rvnoise: {s.done} written, {s.skipped} skipped, {s.failed} failed in {s.seconds:.1f} s → "
                        f"{output_dir} (manifest: {output_dir / 'manifest.jsonl'})")


@app.command(epilog="Example: `rvnoise validate recipes/cnf13.yaml`")
def validate(recipe: Path = typer.Argument(..., help="Recipe YAML.")) -> None:
    """Check a recipe without running it (exit 2 naming the key when it is invalid)."""
    from roadview_noise.bag_recipe import is_bag_recipe, load_bag_recipe, read_recipe_yaml
    from roadview_noise.recipe import load_recipe

    try:
        if is_bag_recipe(read_recipe_yaml(recipe)):
            b = load_bag_recipe(recipe)
            for name, t in b.topics.items():
                typer.echo(f"ok: {recipe}: {name} ({t.sensor}) chain {' → '.join(t.recipe.model_ids)}")
            return
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
    key: str = typer.Option(..., "--key", "-k", help="Output path relative to the output root, or TOPIC@STAMP "
                                                     "for a bag's manifest (OUT.manifest.jsonl)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Also write the reproduced file here."),
    input_root: Optional[Path] = typer.Option(None, "--input-root", help="Input tree (or bag) if it moved."),
) -> None:
    """Reproduce one output from the manifest and compare its sha256 (exit 1 on mismatch)."""
    from roadview_noise.bag_runner import MANIFEST_SUFFIX, replay_bag
    from roadview_noise.runner import replay as do_replay

    try:
        if manifest.name.endswith(MANIFEST_SUFFIX):
            r = replay_bag(manifest, key, out_file=out, input_bag=input_root)
        else:
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


def _augment_bag(in_bag: Path, out_bag: Path, recipe: Path, workers: Optional[int], overwrite: bool, quiet: bool,
                 refused: list[str]) -> None:
    """``augment`` of a ROS bag (roadview_noise.bag_runner)."""
    from roadview_noise.bag_recipe import load_bag_recipe
    from roadview_noise.bag_runner import manifest_path, run_bag

    if refused:
        _fail(f"{', '.join(refused)} not supported for bags (a run writes one whole bag)")
    try:
        s = run_bag(load_bag_recipe(recipe), in_bag, out_bag, workers=workers, overwrite=overwrite,
                    progress=not quiet)
    except RvNoiseError as e:
        _fail(str(e))
    _finish(s.failures, f"rvnoise: {s.done} messages augmented, {s.failed} failed (copied unchanged) in "
                        f"{s.seconds:.1f} s → {out_bag} (manifest: {manifest_path(out_bag)})",
            label="failed (copied unchanged)")


@app.command(epilog="Example: `rvnoise export drive.bag out/drive --recipe recipes/bag-rehearse.yaml`")
def export(
    bag: Path = typer.Argument(..., help="ROS bag: .bag, .mcap, .db3 or a ROS 2 bag folder (never written)."),
    out_dir: Path = typer.Argument(..., help="Input tree to write: one folder per topic, profile sidecars."),
    recipe: Optional[Path] = typer.Option(None, "--recipe", "-r", help="Bag recipe: its topics, profiles and "
                                                                       "depth topics [default: every sensor topic]."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Write over the files of a non-empty OUT_DIR."),
) -> None:
    """Write the camera, LiDAR and radar topics of a bag as files (PNG/JPEG/raw + depth EXR, PCD, profile sidecars)
    that `rvnoise augment` reads."""
    from roadview_noise.bag_export import export_bag
    from roadview_noise.bag_recipe import parse_bag_recipe, read_recipe_yaml

    try:
        r = None
        if recipe is not None:
            r = parse_bag_recipe(read_recipe_yaml(recipe), source=str(recipe), base_dir=recipe.resolve().parent,
                                 chains_required=False)
        summary = export_bag(bag, out_dir, recipe=r, overwrite=overwrite)
    except RvNoiseError as e:
        _fail(str(e))
    topics = ", ".join(f"{t} ({n})" for t, n in summary["topics"].items())
    typer.echo(f"rvnoise: {summary['files']} files → {out_dir}: {topics}")


if __name__ == "__main__":
    app()
