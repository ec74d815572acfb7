"""``rvnoise``: the command line. Parses, calls the library, prints; no logic of its own.

Exit codes: 0 success; 1 some files failed (each recorded in the manifest), the run stopped early, or a replay
mismatch; 2 bad recipe, bad arguments or an input/output problem detected before anything was written (one line
on stderr, never a traceback); 130 interrupted.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from typing import Any, Optional

from roadview_noise.prestart import local_run_recipe, start_from_command_line

start_from_command_line(sys.argv)        # the workers' fork server imports while typer and the recipe load

import typer  # noqa: E402
from typer.core import TyperGroup  # noqa: E402

from roadview_noise.errors import RvNoiseError

_USAGE = sys.modules[typer.BadParameter.__module__]    # click's exceptions (typer ≥ 0.20 vendors its own click)


class _OneLineUsage(TyperGroup):
    """The command group, whose usage errors (an option out of its range, an unknown option, a missing argument)
    are one line on stderr with exit 2 — ``rvnoise: augment: Invalid value for '--workers' / '-j': …`` — as the
    module docstring promises, not typer's five-line box; everything else as click's standalone mode."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except _USAGE.NoArgsIsHelpError:
            return super().main(args, prog_name, complete_var, standalone_mode=True, **extra)   # the help
        except _USAGE.UsageError as e:
            where = f"{e.ctx.info_name}: " if e.ctx is not None and e.ctx.parent is not None else ""
            print(f"rvnoise: {where}{e.format_message()}", file=sys.stderr)
            sys.exit(e.exit_code)
        sys.exit(code if isinstance(code, int) else 0)


class _App(typer.Typer):
    """The console script's app. A local ``augment`` run ends without tearing its interpreter down (numba, scipy,
    OpenCV, pydantic: ≈ 0.1 s), like its fork server (``server_exit``): by then the run has closed everything it
    wrote and released its lock. Other commands, and the app under a test runner, end as usual."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            try:
                return super().__call__(*args, **kwargs)
            except SystemExit as done:
                if isinstance(done.code, (int, type(None))) and local_run_recipe(sys.argv):
                    from roadview_noise.executor import leave_at_once

                    leave_at_once(done.code or 0)
                raise


_SHOWN: set[str] = set()


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning outside a run's own bookkeeping (preview, report, replay) once, as one line like augment's, not as
    Python's source file, line and code."""
    text = f"rvnoise: warning: {category.__name__}: {message}"
    if text not in _SHOWN:
        _SHOWN.add(text)
        print(text, file=file or sys.stderr)


app = _App(name="rvnoise", cls=_OneLineUsage, no_args_is_help=True, add_completion=False, rich_markup_mode="markdown",
           help="Batch augmentation of camera, raw Bayer, LiDAR and 4D-radar data with the ROADVIEW "
                "compound sensor noise models (weather × noise factor, CNF01–CNF30).")


def _fail(message: str, code: int = 2) -> None:
    typer.secho(f"rvnoise: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


@app.command(epilog="Examples: `rvnoise augment --recipe recipes/cnf16.yaml sample_data out/cnf16 --workers 2`, "
                     "`rvnoise augment --recipe recipes/bag-rehearse.yaml drive.bag out/drive-rain.bag`")
def augment(
    input_dir: Path = typer.Argument(..., help="Input tree, or a ROS bag (.bag, .mcap, .db3, ROS 2 bag folder); "
                                               "never written."),
    output_dir: Path = typer.Argument(..., help="Output tree (augmented files, manifest.jsonl, run.json), or the "
                                                "output bag (OUT.manifest.jsonl and OUT.run.json beside it)."),
    recipe: Path = typer.Option(..., "--recipe", "-r", help="Recipe YAML (a CNF or a chain of models)."),
    workers: Optional[int] = typer.Option(None, "--workers", "-j", min=1, help="Worker processes [default: the "
                                          "cores this process may use; capped at the outputs and the memory, see "
                                          "README]."),
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
    depth: Optional[str] = typer.Option(None, "--depth", help="Depth sidecar pattern, relative to each image's "
                                        "folder (inputs.depth), e.g. '{stem}_depth.npy'."),
    depth_source: Optional[str] = typer.Option(None, "--depth-source", help="file | lidar | onnx | ground_plane "
                                               "(inputs.depth_source; README 'Which depth do I have?')."),
    camera_profile: Optional[str] = typer.Option(None, "--camera-profile", help="Camera profile: built-in or file "
                                                 "(inputs.camera_profile)."),
    lidar_profile: Optional[str] = typer.Option(None, "--lidar-profile", help="LiDAR profile: built-in or file "
                                                "(inputs.lidar_profile)."),
    radar_profile: Optional[str] = typer.Option(None, "--radar-profile", help="Radar profile: built-in or file "
                                                "(inputs.radar_profile)."),
    report: bool = typer.Option(False, "--report", help="Write OUTPUT_DIR/report.html at the end (`rvnoise report`)."),
    backend: str = typer.Option("local", "--backend", help="local: worker processes here; dask: a Dask cluster "
                                "(--scheduler, else a LocalCluster of --workers). See README, Dask."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address, e.g. "
                                            "tcp://HOST:8786 (with --backend dask)."),
    profile: bool = typer.Option(False, "--profile", help="Record where each file's time goes (read, decode, "
                                 "convert, each model, encode, hash, write) in its manifest entry."),
) -> None:
    """Apply a recipe to every matching input under INPUT_DIR and write the augmented tree to OUTPUT_DIR.
    Input options override the recipe's and are recorded in run.json's resolved recipe. A ROS bag as INPUT_DIR:
    the recipe's topics are augmented into the output bag (README "ROS bags")."""
    from roadview_noise.io.rosbag import bag_kind

    if bag_kind(input_dir) is None and backend == "local" and not dry_run:
        from roadview_noise.prestart import start_for

        start_for(recipe)                # the workers' fork server imports the models while the recipe is checked

    from roadview_noise.overrides import with_input_overrides
    from roadview_noise.recipe import load_recipe
    from roadview_noise.runner import Limits, run

    if bag_kind(input_dir) is not None:
        options = {"--resume": resume, "--dry-run": dry_run, "--limit": limit, "--fail-fast": fail_fast,
                   "--task-timeout": task_timeout, "--depth": depth, "--depth-source": depth_source,
                   "--camera-profile": camera_profile,
                   "--lidar-profile": lidar_profile, "--radar-profile": radar_profile, "--report": report,
                   "--backend dask": backend != "local", "--scheduler": scheduler, "--profile": profile}
        return _augment_bag(input_dir, output_dir, recipe, workers, overwrite, quiet,
                            refused=[o for o, value in options.items() if value])
    limits = Limits(max_pixels=int(max_pixels), max_points=int(max_points), task_timeout_s=task_timeout)
    try:
        r = with_input_overrides(load_recipe(recipe), depth=depth, depth_source=depth_source,
                                 camera_profile=camera_profile, lidar_profile=lidar_profile,
                                 radar_profile=radar_profile)
        s = run(r, input_dir, output_dir, workers=workers, resume=resume, overwrite=overwrite, dry_run=dry_run,
                limit=limit, fail_fast=fail_fast, yes=yes, limits=limits, progress=not quiet, echo=typer.echo,
                warn=lambda m: typer.echo(m, err=True), backend=backend, scheduler=scheduler, profile=profile)
    except RvNoiseError as e:
        _fail(str(e))
    except KeyboardInterrupt:
        _fail("interrupted; the manifest and run.json record what was done (--resume completes it)", 130)
    if s.dry_run:
        typer.echo(f"rvnoise: dry run, {s.planned} outputs planned, nothing written")
        return
    _print_problems(s)
    typer.echo(f"rvnoise: {s.done} written, {s.skipped} skipped, {s.failed} failed in {s.seconds:.1f} s → "
               f"{output_dir} (manifest: {output_dir / 'manifest.jsonl'})")
    if report:
        _write_report(output_dir, None)
    if s.failed or s.state != "complete" or s.notes:
        raise typer.Exit(1)


def _print_problems(s, *, failed: str = "failed", unit: str = "output") -> None:
    """A run summary's first failures (and how many more) and its invalid-points warning, on stderr."""
    for f in s.failures[:10]:
        typer.secho(f"{failed}: {f}", fg=typer.colors.RED, err=True)
    if s.failed > 10:
        typer.secho(f"… and {s.failed - 10} more (see the manifest)", fg=typer.colors.RED, err=True)
    if s.warned:
        typer.secho(f"warning: {s.warned} {unit}(s) had invalid input points removed (input_warnings in the "
                    "manifest)", fg=typer.colors.YELLOW, err=True)


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
            typer.echo(f"\n[{sensor}] order: {' → '.join(ids)}")
            for mid in ids:
                if mid in models:
                    stage = models[mid].stage
                    typer.echo(f"  {mid}: {stage.name} ({STAGE_ROLES[stage.name]})")
            for i, mid in enumerate(ids, 1):
                _show_model(mid, models, prefix=f"{i}. ")
        return
    if name not in models:
        _fail(f"{name!r} is neither a CNF nor a model{suggest(name, list(models) + list(CNFS))}")
    _show_model(name, models)
    doc = (get_model(name).__doc__ or "").strip()
    if doc:
        typer.echo("\n" + doc)


# why a stage sits where it does in the sensing chain (models.md §1; D3.5 Eq. 1–3)
STAGE_ROLES = {
    "SCENE": "scene illumination, before the weather: Eq. 1",
    "EMITTER": "beam geometry and power at the emitter, before the weather: Eq. 1",
    "RAY_DROP": "returns missing before propagation: Eq. 1",
    "MODIFIER": "changes the weather process itself, set before it: Eq. 2",
    "MEDIUM": "propagation through the weather",
    "WINDSCREEN": "refraction by the windscreen, after the weather: Eq. 3",
    "WINDOW": "lens surface or sensor window, after the weather: Eq. 3",
    "EXPOSURE": "integration on the detector, after the weather: Eq. 3",
    "ELECTRONICS": "detector and receiver electronics, after the weather: Eq. 3",
    "ENCODING": "ISP and compression, last: Eq. 3",
}


def _show_model(mid: str, models: dict, prefix: str = "") -> None:
    if mid not in models:
        typer.echo(f"{prefix}{mid}  (not implemented yet)")
        return
    c = models[mid]
    typer.echo(f"{prefix}{mid}  [{c.stage.name}, {c.scope.value}] {c.summary}")
    specs = c.param_specs()
    rows = [(p.name, p.unit, str(p.default), p.range_text(), p.doc) for p in specs]
    widths = [max([w] + [len(r[i]) + 1 for r in rows]) for i, w in enumerate((28, 10, 12, 20))]   # ≥ 2 spaces apart
    for name, unit, default, allowed, doc in rows:
        typer.echo(f"     {name:<{widths[0]}} {unit:<{widths[1]}} default {default:<{widths[2]}} "
                   f"{allowed:<{widths[3]}} {doc}")


@app.command(epilog="Example: `rvnoise replay out/demo/cnf16-camera-wind-rain/manifest.jsonl --key "
                    "camera/seq0/000000.png` (after `make demo`)")
def replay(
    manifest: Path = typer.Argument(..., help="A run's manifest.jsonl (run.json must be next to it), or its folder."),
    key: str = typer.Option(..., "--key", "-k", help="Output path relative to the output root, or TOPIC@STAMP "
                                                     "for a bag's manifest (OUT.manifest.jsonl)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Also write the reproduced file here."),
    input_root: Optional[Path] = typer.Option(None, "--input-root", help="Input tree (or bag) if it moved."),
) -> None:
    """Reproduce one output (with its sidecars and annotations) from the manifest and compare their sha256 (exit 1
    on mismatch); a bag's message from OUT.manifest.jsonl."""
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
    for f in r["files"][1:]:                 # sidecars and annotations written with the output
        typer.echo(f"  {'match' if f['got'] == f['expected'] else 'MISMATCH'}: {f['path']} sha256 {f['got']}")
    if not r["match"]:
        raise typer.Exit(1)


@app.command(epilog="Examples: `rvnoise preview --recipe recipes/cnf16.yaml sample_data/camera/seq0/000001.png "
                    "--input-root sample_data -o cnf16.png`; `rvnoise preview --all-cnfs --input-root sample_data "
                    "sample_data/camera/seq0/000001.png sample_data/lidar/os1-128/seq0/000001.pcd -o sheets/`")
def preview(
    files: list[Path] = typer.Argument(..., help="Input file(s): image, raw, LiDAR or radar cloud."),
    recipe: Optional[str] = typer.Option(None, "--recipe", "-r", help="Recipe YAML, or a CNF id (CNF01–CNF30)."),
    all_cnfs: bool = typer.Option(False, "--all-cnfs", help="A contact sheet per file: every CNF of its sensor."),
    sensor: Optional[str] = typer.Option(None, "--sensor", help="camera, lidar or radar when the file or the CNF "
                                         "leaves it open [default: guessed; a .bin under a radar* folder, as "
                                         "View-of-Delft's, is radar]."),
    input_root: Optional[Path] = typer.Option(None, "--input-root", help="The input tree of `augment`: the random "
                                              "draws follow the path relative to it [default: the file's folder]."),
    seed: int = typer.Option(0, "--seed", help="Seed of a CNF given by its id, and of --all-cnfs."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Image to write (.png/.jpg) [default: "
                                       "preview.png]; a folder (an existing one, or a name without a suffix) "
                                       "when several files are given, or to hold one file's preview."),
    panel_px: Optional[int] = typer.Option(None, "--panel-px", min=120, help="Width of one panel "
                                           "[default: 480, 320 on contact sheets]."),
    colour: str = typer.Option("range", "--colour", help="LiDAR colour: range or intensity."),
    depth: Optional[str] = typer.Option(None, "--depth", help="Depth sidecar pattern of an image (inputs.depth)."),
    depth_source: Optional[str] = typer.Option(None, "--depth-source", help="file | lidar | onnx | ground_plane "
                                               "(inputs.depth_source), e.g. ground_plane for photos without depth."),
) -> None:
    """Show what a recipe (or every CNF) does to one file, step by step, through the same code and random draws as
    `augment`: camera frames side by side with a zoomed inset, LiDAR bird's-eye views and range images, radar
    bird's-eye views; removed, moved and added points highlighted."""
    from roadview_noise import preview as pv
    from roadview_noise.overrides import with_input_overrides
    from roadview_noise.walk import os_error_text

    if sensor not in (None, "camera", "lidar", "radar"):
        _fail(f"--sensor must be camera, lidar or radar, got {sensor!r}")
    if colour not in ("range", "intensity"):
        _fail(f"--colour must be range or intensity, got {colour!r}")
    if depth_source not in (None, "file", "lidar", "onnx", "ground_plane"):
        _fail(f"--depth-source must be file, lidar, onnx or ground_plane, got {depth_source!r}")
    if all_cnfs == (recipe is not None):
        _fail("give either --recipe (a recipe file or a CNF id) or --all-cnfs")
    if out is None:
        out = Path("preview.png") if len(files) == 1 else Path("preview")
    into_folder = len(files) > 1 or out.is_dir() or not out.suffix      # `-o sheets/` for one file too
    failed = []
    for f in files:                        # a file that fails is named, and the others are still previewed
        try:
            kind = sensor or pv.guess_sensor(f)
            target = out / f"{pv.file_label(f, input_root)}-{kind}.png" if into_folder else out
            if any(target.resolve() == g.resolve() for g in files):
                raise RvNoiseError(f"-o {str(target)!r} is an input file; a preview never writes over its input")
            if all_cnfs:
                img = pv.contact_sheet(f, kind, in_root=input_root, seed=seed, panel_px=panel_px or 320,
                                       colour_by=colour, depth=depth, depth_source=depth_source)
            else:
                r = pv.recipe_from(recipe, sensor or (kind if kind != "camera" else None), seed)
                r = with_input_overrides(r, depth=depth, depth_source=depth_source)
                pv.check_fits(r, kind, f)
                sample, root = pv.sample_for(f, r, input_root)
                img = pv.render(pv.run_chain(r, sample, root, title=f"{f.name}: {' -> '.join(r.model_ids)}"),
                                panel_px or 480, colour)
            pv.write_image_file(target, img)
            typer.echo(f"rvnoise: preview of {f} → {target} ({img.shape[1]}×{img.shape[0]})")
        except RvNoiseError as e:
            failed.append(f)
            typer.secho(f"rvnoise: {e}" if str(f) in str(e) or f.name in str(e) else f"rvnoise: {f}: {e}",
                        fg=typer.colors.RED, err=True)
        except OSError as e:               # the preview cannot be written (a folder in its place, no space, …)
            failed.append(f)
            typer.secho(f"rvnoise: {f}: cannot write the preview {str(target)!r}: {os_error_text(e)}",
                        fg=typer.colors.RED, err=True)
    if failed:
        raise typer.Exit(2)


@app.command(epilog="Example: `rvnoise report out/demo` (a run folder, or a folder of runs)")
def report(
    output_dir: Path = typer.Argument(..., help="An augment output folder, or a folder of them (one per CNF)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Page to write [default: OUTPUT_DIR/report.html]; "
                                       "its numbers beside it as the page's name with .json (report.json)."),
) -> None:
    """Write one self-contained HTML page with the runs' metrics per CNF, plots, previews, corner cases and
    failures (works on a partial run), and report.json with the numbers."""
    _write_report(output_dir, out)


def _write_report(output_dir: Path, out: Optional[Path]) -> None:
    from roadview_noise.report import numbers_path, write_report

    try:
        path = write_report(output_dir, out)
    except RvNoiseError as e:
        _fail(str(e))
    typer.echo(f"rvnoise: report → {path} (numbers: {numbers_path(path)})")


fit_app = typer.Typer(no_args_is_help=True, help="Fit noise models on your own real data.")
app.add_typer(fit_app, name="fit")


@fit_app.command("ray-drop", epilog="Example: `rvnoise fit ray-drop my_os1_scans/ -o ray_drop.json --validate`, then "
                                   "`params: {ray_drop.lidar: {backend: learned, model_file: ray_drop.json}}`")
def fit_ray_drop(
    scans: Path = typer.Argument(..., help="Real scans: a file or a folder searched recursively for .pcd, .ply, .bin "
                                 "(.pcd.bin) — full range-image grids (organised PCD, no-return cells zero) or point "
                                 "lists of one scan each (their empty rays are found on the firing grid)."),
    out: Path = typer.Option(..., "--out", "-o", help="learned: the classifier, .json or .onnx; physical: a .yaml "
                             "with the recipe params."),
    backend: str = typer.Option("learned", "--backend", help="learned (additive logistic classifier) or physical "
                                "(the coefficients of the physical back-end)."),
    lidar_profile: Optional[str] = typer.Option(None, "--lidar-profile", help="LiDAR profile: built-in or file "
                                                "[default: lidar.yaml next to each scan, else os1-128]."),
    without: list[str] = typer.Option([], "--without", help="Leave a feature out (repeatable): log_range, "
                                      "cos_incidence, elevation_rad. With one scan leave out elevation_rad: it "
                                      "learns the scene's rows, not the sensor's beams."),
    validate: bool = typer.Option(False, "--validate", help="Also fit on column halves and on 4 azimuth sectors and "
                                  "print the held-out AUC and log-loss of both back-ends and of a constant rate."),
) -> None:
    """Fit ray drop on your own real scans: their no-return rays are the sensor's ray-drop pattern."""
    import dataclasses as dc

    import numpy as np
    import yaml

    from roadview_noise import __version__
    from roadview_noise import ray_drop_fit as rf
    from roadview_noise.io.ray_drop_model import write_model
    from roadview_noise.physics.ray_drop import FEATURES

    if backend not in ("learned", "physical"):
        _fail(f"--backend must be learned or physical, got {backend!r}")
    bad = [w for w in without if w not in FEATURES[1:]]
    if bad:
        _fail(f"--without {bad[0]!r}: expected one of {', '.join(FEATURES[1:])}")
    want = (".json", ".onnx") if backend == "learned" else (".yaml", ".yml")
    if out.suffix.lower() not in want:
        _fail(f"--out must end in {' or '.join(want)} for the {backend} back-end, got {out.name!r}")
    if not scans.exists():
        _fail(f"{scans}: no such file or folder")
    try:
        done, skipped = rf.read_scans(scans, lidar_profile)
        for s in skipped:
            typer.secho(f"skipped: {s}", fg=typer.colors.YELLOW, err=True)
        cells = rf.combine(done)
    except (RvNoiseError, ValueError) as e:
        _fail(str(e))
    leave = tuple(without)
    rate = float(cells.dropped.mean())
    typer.echo(f"rvnoise: {len(done)} scan(s), {len(cells)} rays with ≥ {rf.MIN_SUPPORT} returning neighbours, "
               f"{int(cells.dropped.sum())} without a return (rate {rate:.4f})")
    if backend == "learned":
        model = rf.fit_additive(cells, leave)
        fitted = rf.scores(cells.dropped, model.drop_probability(cells.features))
    else:
        model = rf.fit_physical(cells, leave)
        fitted = rf.scores(cells.dropped, model.drop_probability(cells.features, cells.receiver))
    constant = rf.scores(cells.dropped, np.full(len(cells), rate))
    typer.echo(f"in-sample: AUC {fitted['auc']:.3f}, log-loss {fitted['log_loss']:.4f} (constant rate: "
               f"{constant['log_loss']:.4f})")
    fitted_on = {"tool": f"rvnoise {__version__}", "scans": cells.notes, "features": [f for f in FEATURES
                                                                                      if f not in leave],
                 "drop_rate": rate, "in_sample": fitted}
    if validate:
        for name, folds in (("column halves", rf.column_halves(cells, leave)),
                            ("azimuth sectors", rf.azimuth_sectors(cells, 4, leave))):
            fitted_on[name.replace(" ", "_")] = folds
            for k in ("constant", "physical", "learned"):
                typer.echo(f"held-out, {name:<15} {k:<9} AUC "
                           + " ".join(f"{f[k]['auc']:.3f}" for f in folds) + "   log-loss "
                           + " ".join(f"{f[k]['log_loss']:.4f}" for f in folds))
    try:
        if backend == "learned":
            write_model(out, model, fitted_on)
        else:
            from roadview_noise.io.atomic import write_bytes_atomic

            params = {k: round(v, 6) for k, v in dc.asdict(model).items()}
            text = (f"# rvnoise fit ray-drop --backend physical: {len(done)} scan(s), in-sample AUC "
                    f"{fitted['auc']:.3f}\n" + yaml.safe_dump({"params": {"ray_drop.lidar": params}},
                                                              sort_keys=False))
            write_bytes_atomic(out, text.encode())
    except RvNoiseError as e:
        _fail(str(e))
    typer.echo(f"rvnoise: {backend} ray drop → {out}")


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
        _fail(f"{', '.join(refused)} not supported for bags (a run writes one whole bag; profiles and depth are "
              f"given per topic in the recipe's topics:)")
    try:
        s = run_bag(load_bag_recipe(recipe), in_bag, out_bag, workers=workers, overwrite=overwrite,
                    progress=not quiet, echo=typer.echo)
    except RvNoiseError as e:
        _fail(str(e))
    _print_problems(s, failed="failed (copied unchanged)", unit="message")
    empty = f", {s.skipped} empty clouds (copied unchanged)" if s.skipped else ""
    typer.echo(f"rvnoise: {s.done} messages augmented, {s.failed} failed (copied unchanged){empty} in "
               f"{s.seconds:.1f} s → {out_bag} (manifest: {manifest_path(out_bag)})")
    if s.failed:
        raise typer.Exit(1)


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
    for line in summary["warnings"]:
        typer.echo(f"rvnoise: warning: {line}", err=True)
    topics = ", ".join(f"{t} ({n})" for t, n in summary["topics"].items())
    typer.echo(f"rvnoise: {summary['files']} files → {out_dir}: {topics}")


if __name__ == "__main__":
    app()
