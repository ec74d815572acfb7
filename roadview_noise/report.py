"""``rvnoise report OUT/``: one self-contained static HTML page (and ``report.json``) summarising augment runs.

``OUT`` is one run (it holds ``manifest.jsonl``) or a folder of runs (every sub-folder with a manifest, e.g. one per
CNF). The page has: the CNF coverage (every CNF of D3.5: run here, runnable, or not implemented yet), per sensor a
table of the runs' metrics (``roadview_noise.metrics``, from the manifests) and matplotlib plots embedded as PNG,
the corner cases (outputs and steps with the largest data loss, linked to their previews), previews rendered by
``roadview_noise.preview`` (the recorded recipe re-run on the recorded input, as ``replay`` does), and every failure.
A run still going or killed (no ``run.json``) is reported from its manifest, marked partial, without previews.
No script, no external resource: it renders offline in any browser.

Data loss, the corner-case score: camera 1 − SSIM; LiDAR/radar the fraction of the input returns removed or moved.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from .compound import CNFS
from .dataset import Sample
from .errors import RecipeError, RvNoiseError
from .io.atomic import write_bytes_atomic
from .manifest import MANIFEST_NAME, RUN_NAME, read_manifest
from .registry import load_all

REPORT_NAME = "report.html"
SENSORS = ("camera", "lidar", "radar")
SENSOR_TITLES = {"camera": "Camera", "lidar": "LiDAR", "radar": "Radar"}
CORNER_CASES_PER_SENSOR = 5
PREVIEW_PANEL_PX = 320


@dataclass
class Run:
    """One augment run read back from its output folder."""

    path: Path
    name: str
    entries: list[dict]
    record: dict | None                     # run.json, None while running or after a kill
    chain: list[str]
    sensor: str
    cnf: str | None

    @property
    def ok(self) -> list[dict]:
        return [e for e in self.entries if e.get("status") == "ok"]

    @property
    def failed(self) -> list[dict]:
        return [e for e in self.entries if e.get("status") != "ok"]

    @property
    def partial(self) -> bool:
        if self.record is None:
            return True
        return len(self.entries) < self.record.get("counts", {}).get("planned", 0)

    @property
    def label(self) -> str:
        if self.cnf and Path(self.name).name.lower().startswith(self.cnf.lower()):
            return self.cnf
        return f"{self.cnf} ({self.name})" if self.cnf else self.name

    @property
    def description(self) -> str:
        return ((self.record or {}).get("recipe") or {}).get("description", "")


def find_runs(root: Path) -> list[Path]:
    """``root`` when it holds a manifest, else every folder below it that does (sorted)."""
    root = Path(root)
    if (root / MANIFEST_NAME).is_file():
        return [root]
    return sorted(p.parent for p in root.rglob(MANIFEST_NAME)
                  if not any(part.startswith(".") for part in p.relative_to(root).parts))


def cnf_of(chain: list[str]) -> str | None:
    """The CNF whose chain (for some sensor) is exactly ``chain``."""
    for name, cnf in CNFS.items():
        if tuple(chain) in cnf.chains.values():
            return name
    return None


def read_run(path: Path, root: Path) -> Run:
    from .registry import get_model

    entries = read_manifest(path / MANIFEST_NAME)
    record = None
    if (path / RUN_NAME).is_file():
        try:
            record = json.loads((path / RUN_NAME).read_text())
        except (OSError, ValueError):
            record = None
    chain = next((e["chain"] for e in entries if e.get("chain")), None)
    if chain is None and record:
        chain = [s["model"] for s in record.get("recipe", {}).get("chain", [])]
    chain = list(chain or [])
    try:
        sensor = get_model(chain[0]).sensor if chain else "camera"
    except RvNoiseError:
        sensor = "camera"
    name = path.relative_to(root).as_posix() if path != root else path.name
    return Run(path, name or ".", entries, record, chain, sensor, cnf_of(chain))


# --- numbers ----------------------------------------------------------------------------------------------------


def _finite(values) -> list[float]:
    return [float(v) for v in values if isinstance(v, (int, float)) and math.isfinite(v)]


def _mean(values) -> float | None:
    v = _finite(values)
    return sum(v) / len(v) if v else None


def data_loss(metrics: dict, sensor: str) -> float | None:
    """The corner-case score of one comparison (see the module doc)."""
    if not metrics:
        return None
    if sensor == "camera":
        s = metrics.get("ssim")
        return None if s is None else 1.0 - float(s)
    n = metrics.get("points_in") or 0
    return (metrics.get("removed", 0) + metrics.get("moved", 0)) / n if n > 0 else None


def summarise(run: Run) -> dict[str, Any]:
    """The numbers of one run for the table and report.json: counts, means of the per-output metrics, per step."""
    ms = [e.get("metrics") or {} for e in run.ok]
    ms = [m for m in ms if m]
    out: dict[str, Any] = {
        "name": run.name, "cnf": run.cnf, "sensor": run.sensor, "chain": run.chain, "description": run.description,
        "outputs_ok": len(run.ok), "outputs_failed": len(run.failed), "partial": run.partial,
        "planned": (run.record or {}).get("counts", {}).get("planned"), "with_metrics": len(ms),
        "wall_seconds": (run.record or {}).get("wall_seconds"),
    }
    if run.sensor == "camera":
        psnr = [m.get("psnr_db") for m in ms]
        out.update(psnr_db_mean=_mean(psnr), identical_outputs=sum(1 for p in psnr if p == math.inf),
                   ssim_mean=_mean(m.get("ssim") for m in ms))
        for k in ("rms_contrast", "edge_density", "mean_level"):
            out[f"{k}_in_mean"] = _mean(m.get(f"{k}_in") for m in ms)
            out[f"{k}_out_mean"] = _mean(m.get(f"{k}_out") for m in ms)
        with_depth = [m for m in ms if m.get("depth_bin_edges_m")]
        if with_depth:
            edges = with_depth[0]["depth_bin_edges_m"]
            out["depth_bin_edges_m"] = [e if math.isfinite(e) else None for e in edges]
            for side in ("in", "out"):
                out[f"rms_contrast_per_depth_bin_{side}_mean"] = [
                    _mean((m.get(f"rms_contrast_per_depth_bin_{side}") or [None] * (len(edges) - 1))[i]
                          for m in with_depth) for i in range(len(edges) - 1)]
    else:
        for k in ("points_in", "points_out", "kept", "attenuated", "moved", "added", "removed"):
            out[f"{k}_total"] = sum(int(m.get(k, 0)) for m in ms)
        for k in ("max_range_m_in", "max_range_m_out", "mean_intensity_change", "mean_snr_change_db"):
            v = _mean(m.get(k) for m in ms)
            if v is not None:
                out[f"{k}_mean"] = v
        for side in ("in", "out"):
            hists = [m.get(f"points_per_10m_{side}") or [] for m in ms]
            n = max((len(h) for h in hists), default=0)
            out[f"points_per_10m_{side}_total"] = [sum(h[i] for h in hists if i < len(h)) for i in range(n)]
    out["data_loss_mean"] = _mean(data_loss(m, run.sensor) for m in ms)
    out["steps"] = []
    for i, model in enumerate(run.chain):
        step = [e["steps"][i].get("metrics") or {} for e in run.ok if len(e.get("steps", [])) > i]
        out["steps"].append({"model": model, "data_loss_mean": _mean(data_loss(m, run.sensor) for m in step)})
    return out


def corner_cases(runs: list[Run], per_sensor: int = CORNER_CASES_PER_SENSOR) -> list[dict]:
    """The outputs and single steps with the largest data loss, ``per_sensor`` per sensor, largest first."""
    cases = []
    for r_i, run in enumerate(runs):
        for e in run.ok:
            loss = data_loss(e.get("metrics") or {}, run.sensor)
            if loss is not None:
                cases.append({"run": r_i, "sensor": run.sensor, "output": e["output"], "step": None, "loss": loss})
            for s_i, step in enumerate(e.get("steps", [])):
                loss = data_loss(step.get("metrics") or {}, run.sensor)
                if loss is not None and len(run.chain) > 1:
                    cases.append({"run": r_i, "sensor": run.sensor, "output": e["output"], "step": s_i,
                                  "model": step.get("model"), "loss": loss})
    out = []
    for sensor in SENSORS:
        mine = sorted((c for c in cases if c["sensor"] == sensor), key=lambda c: -c["loss"])
        out += mine[:per_sensor]
    return out


# --- previews ---------------------------------------------------------------------------------------------------


def render_preview(run: Run, entry: dict) -> tuple[str, str] | str:
    """(mime type, base64 image) of one output's preview, or why there is none."""
    from .preview import encode_image, render, run_chain
    from .recipe import parse_recipe

    if run.record is None:
        return "no preview: the run has no run.json yet (still running or killed)"
    in_root = Path(run.record.get("input_root", ""))
    if not (in_root / entry["input"]).is_file():
        return f"no preview: the input {entry['input']!r} is not under {str(in_root)!r} any more"
    try:
        recipe = parse_recipe(run.record["recipe"], source=str(run.path / RUN_NAME),
                              base_dir=Path(run.record.get("recipe_base_dir", ".")))
        sample = Sample(entry["input"], entry["modality"], entry["sequence"], entry.get("depth"))
        chain = run_chain(recipe, sample, in_root, variant_index=entry.get("variant_index", 0),
                          title=f"{run.label}: {entry['output']}", key=entry["output"])
        img = render(chain, PREVIEW_PANEL_PX)
    except (RvNoiseError, KeyError, OSError) as e:
        return f"no preview: {e}"
    suffix = ".jpg" if run.sensor == "camera" else ".png"
    mime = "image/jpeg" if suffix == ".jpg" else "image/png"
    return mime, base64.b64encode(encode_image(img, suffix, jpeg_quality=85)).decode()


# --- plots ------------------------------------------------------------------------------------------------------


def _figure_png(draw: Callable, width_in: float = 9.0, height_in: float = 3.2) -> str:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=90, layout="constrained")
    draw(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return base64.b64encode(buf.getvalue()).decode()


def camera_plot(summaries: list[dict]) -> str | None:
    rows = [s for s in summaries if s["with_metrics"]]
    if not rows:
        return None

    def draw(fig):
        names = [s["cnf"] or s["name"] for s in rows]
        ax1, ax2, ax3 = fig.subplots(1, 3)
        x = range(len(rows))
        ax1.bar(x, [s["ssim_mean"] or 0 for s in rows], color="#4a7fb0")
        ax1.set_ylim(min([s["ssim_mean"] or 1 for s in rows] + [0.8]) - 0.02, 1.0)
        ax1.set_title("mean SSIM vs input")
        ax2.bar(x, [s["psnr_db_mean"] or 0 for s in rows], color="#b0704a")
        ax2.set_title("mean PSNR vs input (dB)")
        for ax in (ax1, ax2):
            ax.set_xticks(list(x), names, rotation=60, fontsize=7)
        depth = [s for s in rows if s.get("depth_bin_edges_m")]
        if depth:
            edges = depth[0]["depth_bin_edges_m"]
            labels = [f"{int(a)}-{int(b)}" if b is not None else f">{int(a)}" for a, b in zip(edges, edges[1:])]
            ax3.plot(labels, depth[0]["rms_contrast_per_depth_bin_in_mean"], "k--", label="input")
            for s in depth:
                ax3.plot(labels, s["rms_contrast_per_depth_bin_out_mean"], marker=".", label=s["cnf"] or s["name"])
            ax3.set_title("RMS contrast per depth bin (m)")
            ax3.tick_params(labelsize=7)
            ax3.legend(fontsize=6, ncols=2)
        else:
            ax3.set_axis_off()

    return _figure_png(draw)


def cloud_plot(summaries: list[dict]) -> str | None:
    rows = [s for s in summaries if s["with_metrics"]]
    if not rows:
        return None

    def draw(fig):
        ax1, ax2 = fig.subplots(1, 2)
        hist_in = rows[0]["points_per_10m_in_total"]
        n_in = max(sum(hist_in), 1)
        ax1.plot([10 * i + 5 for i in range(len(hist_in))], [h / n_in for h in hist_in], "k--", label="input")
        for s in rows:
            h = s["points_per_10m_out_total"]
            ax1.plot([10 * i + 5 for i in range(len(h))], [v / n_in for v in h], marker=".",
                     label=s["cnf"] or s["name"])
        ax1.set_yscale("log")
        ax1.set_xlabel("range (m)")
        ax1.set_title("returns per 10 m bin (fraction of input returns)")
        ax1.legend(fontsize=6, ncols=2)
        names = [s["cnf"] or s["name"] for s in rows]
        x = list(range(len(rows)))
        ax2.bar([i - 0.2 for i in x], [s.get("max_range_m_in_mean") or 0 for s in rows], 0.4, label="input",
                color="#999999")
        ax2.bar([i + 0.2 for i in x], [s.get("max_range_m_out_mean") or 0 for s in rows], 0.4, label="output",
                color="#4a7fb0")
        ax2.set_xticks(x, names, rotation=60, fontsize=7)
        ax2.set_title("mean maximum detection range (m)")
        ax2.legend(fontsize=7)

    return _figure_png(draw)


# --- page -------------------------------------------------------------------------------------------------------


CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:24px;color:#222;max-width:1500px}
h1{font-size:22px}h2{font-size:18px;margin-top:32px;border-bottom:1px solid #ccc}h3{font-size:15px}
table{border-collapse:collapse;margin:8px 0;font-size:12.5px}td,th{border:1px solid #ddd;padding:3px 7px;
text-align:right}th{background:#f3f3f3}td.l,th.l{text-align:left}.bad{color:#b00}.part{color:#a60}
.muted{color:#777}img{max-width:100%;border:1px solid #ccc}figure{margin:12px 0}figcaption{font-size:12px;color:#555}
.cov td{text-align:center}.cov td.run{background:#d8f0d8}.cov td.can{background:#eef}.cov td.no{background:#eee}
"""


def _f(v: Any, fmt: str = "{:.3f}") -> str:
    if v is None:
        return "–"
    if isinstance(v, float) and not math.isfinite(v):
        return "∞" if v > 0 else "−∞"
    return fmt.format(v) if isinstance(v, (int, float)) else html.escape(str(v))


def _coverage_table(runs: list[Run]) -> str:
    models = load_all()
    by_cnf: dict[str, list[int]] = {}
    for i, r in enumerate(runs):
        if r.cnf:
            by_cnf.setdefault(r.cnf, []).append(i)
    cells = []
    for name, cnf in CNFS.items():
        runnable = all(m in models for ids in cnf.chains.values() for m in ids)
        if name in by_cnf:
            links = " ".join(f'<a href="#run-{i}">{html.escape(runs[i].sensor)}</a>' for i in by_cnf[name])
            cells.append(f'<td class="run" title="{html.escape(cnf.factor)} + {cnf.weather}">'
                         f"<b>{name}</b><br>{links}</td>")
        else:
            kind, text = ("can", "not in this run") if runnable else ("no", "not implemented yet")
            cells.append(f'<td class="{kind}" title="{html.escape(cnf.factor)} + {cnf.weather}">{name}<br>'
                         f'<span class="muted">{text}</span></td>')
    rows = "".join("<tr>" + "".join(cells[i:i + 10]) + "</tr>" for i in range(0, len(cells), 10))
    return f'<table class="cov">{rows}</table>'


def _run_table(runs: list[tuple[int, Run, dict]], sensor: str) -> str:
    if sensor == "camera":
        heads = ["outputs", "PSNR dB", "SSIM", "contrast in → out", "edges in → out", "level in → out", "loss"]
    else:
        heads = ["outputs", "returns in → out", "removed", "moved", "added", "max range m in → out",
                 "Δ intensity" if sensor == "lidar" else "Δ SNR dB", "loss"]
    th = "".join(f"<th>{h}</th>" for h in ["run", "chain"] + heads)
    body = []
    for i, run, s in runs:
        status = f'{s["outputs_ok"]} ok'
        if s["outputs_failed"]:
            status += f' <span class="bad">{s["outputs_failed"]} failed</span>'
        if s["partial"]:
            status += ' <span class="part">partial</span>'
        cols = [f'<a href="#run-{i}">{html.escape(run.label)}</a>', html.escape(" → ".join(run.chain)), status]
        if sensor == "camera":
            cols += [_f(s.get("psnr_db_mean"), "{:.1f}"), _f(s.get("ssim_mean")),
                     f'{_f(s.get("rms_contrast_in_mean"))} → {_f(s.get("rms_contrast_out_mean"))}',
                     f'{_f(s.get("edge_density_in_mean"))} → {_f(s.get("edge_density_out_mean"))}',
                     f'{_f(s.get("mean_level_in_mean"))} → {_f(s.get("mean_level_out_mean"))}']
        else:
            change = s.get("mean_intensity_change_mean" if sensor == "lidar" else "mean_snr_change_db_mean")
            cols += [f'{s["points_in_total"]} → {s["points_out_total"]}', str(s["removed_total"]),
                     str(s["moved_total"]), str(s["added_total"]),
                     f'{_f(s.get("max_range_m_in_mean"), "{:.1f}")} → {_f(s.get("max_range_m_out_mean"), "{:.1f}")}',
                     _f(change, "{:+.2f}")]
        cols.append(_f(s.get("data_loss_mean")))
        body.append("<tr>" + "".join(f'<td class="l">{c}</td>' if k < 2 else f"<td>{c}</td>"
                                     for k, c in enumerate(cols)) + "</tr>")
    return f"<table><tr>{th}</tr>{''.join(body)}</table>"


def build(root: Path, *, echo: Callable[[str], None] = lambda m: None) -> tuple[str, dict]:
    """(HTML page, report.json content) of the runs under ``root``."""
    root = Path(root)
    paths = find_runs(root)
    if not paths:
        raise RecipeError(f"no {MANIFEST_NAME} in {str(root)!r} or below it: nothing to report")
    runs = [read_run(p, root) for p in paths]
    summaries = [summarise(r) for r in runs]
    cases = corner_cases(runs)
    previews: list[dict] = []

    def preview_of(run_index: int, output: str) -> int:
        for k, p in enumerate(previews):
            if p["run"] == run_index and p["output"] == output:
                return k
        run = runs[run_index]
        entry = next(e for e in run.ok if e["output"] == output)
        result = render_preview(run, entry)
        previews.append({"run": run_index, "output": output,
                         **({"note": result} if isinstance(result, str) else {"mime": result[0], "b64": result[1]})})
        return len(previews) - 1

    for i, run in enumerate(runs):
        if run.ok:
            preview_of(i, run.ok[0]["output"])
    for c in cases:
        c["preview"] = preview_of(c["run"], c["output"])
    echo(f"report: {len(runs)} run(s), {len(previews)} preview(s)")

    parts = [f"<h1>rvnoise report: {html.escape(str(root))}</h1>",
             f'<p class="muted">{len(runs)} run(s), {sum(len(r.ok) for r in runs)} outputs written, '
             f'{sum(len(r.failed) for r in runs)} failed; generated {time.strftime("%Y-%m-%d %H:%M:%S")}. '
             "Metrics: <code>rvnoise show</code> / README; data loss = 1 − SSIM (camera), fraction of input "
             "returns removed or moved (LiDAR, radar).</p>",
             "<h2>Compound noise factors (D3.5 Table 6)</h2>", _coverage_table(runs)]
    for sensor in SENSORS:
        mine = [(i, r, s) for i, (r, s) in enumerate(zip(runs, summaries)) if r.sensor == sensor]
        if not mine:
            continue
        parts.append(f"<h2>{SENSOR_TITLES[sensor]}</h2>")
        parts.append(_run_table(mine, sensor))
        plot = camera_plot([s for _, _, s in mine]) if sensor == "camera" else cloud_plot([s for _, _, s in mine])
        if plot:
            parts.append(f'<figure><img alt="{sensor} metrics" src="data:image/png;base64,{plot}"></figure>')
        mine_cases = [c for c in cases if c["sensor"] == sensor]
        if mine_cases:
            parts.append("<h3>Corner cases: largest data loss</h3><table><tr><th>loss</th><th class=l>run</th>"
                         "<th class=l>output</th><th class=l>step</th><th class=l>preview</th></tr>")
            for c in mine_cases:
                step = "whole chain" if c["step"] is None else f'{c["step"] + 1}. {c.get("model", "")}'
                parts.append(f'<tr><td>{c["loss"]:.3f}</td><td class=l>{html.escape(runs[c["run"]].label)}</td>'
                             f'<td class=l>{html.escape(c["output"])}</td><td class=l>{html.escape(step)}</td>'
                             f'<td class=l><a href="#preview-{c["preview"]}">preview</a></td></tr>')
            parts.append("</table>")
    parts.append("<h2>Runs</h2>")
    for i, (run, s) in enumerate(zip(runs, summaries)):
        state = ('<span class="part">partial: no run.json (still running or killed)</span>' if run.record is None
                 else '<span class="part">partial</span>' if run.partial else "complete")
        parts.append(f'<h3 id="run-{i}">{html.escape(run.label)}</h3><p>{html.escape(run.description)}<br>'
                     f'chain {html.escape(" → ".join(run.chain))}; {s["outputs_ok"]} ok, {s["outputs_failed"]} '
                     f'failed; {state}; folder <code>{html.escape(str(run.path))}</code></p>')
        steps = "".join(f'<tr><td class=l>{k + 1}. {html.escape(st["model"])}</td><td>{_f(st["data_loss_mean"])}'
                        "</td></tr>" for k, st in enumerate(s["steps"]))
        if steps:
            parts.append(f"<table><tr><th class=l>step</th><th>mean data loss of the step</th></tr>{steps}</table>")
        for k, p in enumerate(previews):
            if p["run"] == i:
                parts.append(_preview_html(k, p))
        if run.failed:
            rows = "".join(f'<tr><td class=l>{html.escape(e.get("output") or e.get("input") or "?")}</td><td class="l bad">'
                           f'{html.escape(str(e.get("error", "")))}</td></tr>' for e in run.failed)
            parts.append(f"<h4>Failures</h4><table><tr><th class=l>output</th><th class=l>error</th></tr>{rows}"
                         "</table>")
    page = ("<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>rvnoise report</title>"
            f"<style>{CSS}</style></head><body>{''.join(parts)}</body></html>")
    numbers = {"schema": "rvnoise.report/1", "root": str(root), "generated_unix": time.time(), "runs": summaries,
               "corner_cases": [{k: v for k, v in c.items() if k != "preview"} | {"run": runs[c["run"]].name}
                                for c in cases],
               "failures": [{"run": r.name, "output": e.get("output"), "error": e.get("error")}
                            for r in runs for e in r.failed]}
    return page, _json_safe(numbers)


def _preview_html(k: int, p: dict) -> str:
    caption = html.escape(p["output"])
    if "note" in p:
        return f'<p id="preview-{k}" class="muted">{caption}: {html.escape(p["note"])}</p>'
    return (f'<figure id="preview-{k}"><img alt="preview of {caption}" src="data:{p["mime"]};base64,{p["b64"]}">'
            f"<figcaption>{caption}</figcaption></figure>")


def _json_safe(v: Any) -> Any:
    """Non-finite floats (PSNR of identical images) become None, so report.json is strict JSON."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    return v


def numbers_path(page: Path) -> Path:
    """Where the numbers of the page ``page`` go: its name with ``.json`` (``report.html`` → ``report.json``)."""
    return Path(page).with_suffix(".json")


def write_report(root: Path, out: Path | None = None, *, echo: Callable[[str], None] = lambda m: None) -> Path:
    """Write the page (default ``root/report.html``) and its numbers beside it under the page's name with ``.json``
    (``report.json``; ``-o DIR/x.html`` → ``DIR/x.json``, so two reports in one folder keep their own); return the
    page's path."""
    if out is not None and Path(out).suffix.lower() not in (".html", ".htm"):     # `-o photo.png` wrote HTML over it
        raise RecipeError(f"-o {str(out)!r}: the report is an HTML page (its numbers go beside it as .json); give a "
                          ".html name")
    page, numbers = build(root, echo=echo)
    out = Path(out) if out is not None else Path(root) / REPORT_NAME
    out.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(out, page.encode("utf-8"))
    write_bytes_atomic(numbers_path(out), (json.dumps(numbers, indent=1) + "\n").encode("utf-8"))
    return out
