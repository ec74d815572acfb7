"""Property audit of every registered model on every real file we have (never committed: /work/realdata,
../shared/data) and on sample_data's radar, run exactly as ``augment`` runs a one-step recipe (reader, profile,
``apply_models``, writer).

Properties, per model × input:

- ``identity``: at vanishing strength (rate 0, visibility 10⁹ m, probability 0, …: ``VANISH``) the output equals
  the input: at most 0.1 % of the points / pixels changed (in-memory result against the input as read);
- ``range``: the written file holds what the sensor can report: no NaN/inf the input lacked; LiDAR intensity
  ≤ the profile's full scale, whole counts for 8-bit units; no new point beyond the profile's ``max_range_m``;
  z = 0 on a 2-D radar; the written file has the input's dtype / column layout (image dtype and channels, .bin
  column count, PCD FIELDS/SIZE/TYPE);
- ``monotone``: weather at three strengths, mean over 5 seeds: LiDAR/radar lost returns do not fall as the rate
  rises (visibility falls); camera fog lowers the luminance contrast as the visibility falls, rain and snow change
  more as the rate rises. A fall counts when it exceeds 3 standard errors of the difference of the means (seed
  noise does not); a fall of LiDAR rain/snow's lost returns is physics, not a violation, when the closed-form count
  of targets a particle outshines falls too (:func:`expected_outshone`): where targets are so faint that sub-mm
  flakes outshine them, lost returns follow the number of small flakes, and an exponential DSD has fewer of those
  in heavier snow (Gunn & Marshall 1958, models.md §2.3: N(D ≥ d) = N0/Λ e^{−Λd}, N0 ∝ S^−0.87, Λ ∝ S^−0.48);
- ``determinism``: the same seed writes byte-identical files.

``python bench/audit_real_data.py [--quick]`` prints the table (``ok`` or the violation with numbers); ``--quick``
keeps one nuScenes photo and one DNG. Files absent on this machine are skipped and listed.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import shutil
import sys
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from roadview_noise.compound import apply_models
from roadview_noise.dataset import Sample, load, save
from roadview_noise.errors import InputError, ModelError
from roadview_noise.physics.srgb import linear_to_code
from roadview_noise.provenance import Effect
from roadview_noise.recipe import SCHEMA, parse_recipe
from roadview_noise.registry import load_all
from roadview_noise.runner import Task, build_models
from roadview_noise.types import CameraFrame, PointCloud, RawFrame

ROOT = Path(__file__).resolve().parents[1]
REAL = Path("/work/realdata")
DEMO = REAL / "mmdet3d" / "demo" / "data"
SHARED = ROOT.parent / "shared" / "data"
WAYMO_FIELDS = ["x", "y", "z", "intensity", "elongation", "timestamp"]
WAYMO_FULL_SCALE = 30.0      # the README's advice for Waymo (a stated unit and scale): above both files' maxima 1.04, 27.1
# (read without a stated unit, Waymo's fractional intensities are refused since 2026-11-27: no audit row)


@dataclass(frozen=True)
class Input:
    name: str
    path: Path
    sensor: str                       # camera | raw | lidar | radar
    inputs: dict = field(default_factory=dict)


GROUND_PLANE = {"depth_source": "ground_plane", "ground_plane": {"camera_height_m": 1.5, "pitch_deg": 0.0}}


def real_inputs(quick: bool = False) -> list[Input]:
    """Every real file of the audit that exists on this machine."""
    nus = sorted((DEMO / "nuscenes").glob("*CAM_*.jpg"))
    dngs = sorted((REAL / "dng").glob("*.dng"))
    waymo = sorted((REAL / "mmdet3d/tests/data/waymo/kitti_format/training/velodyne").glob("*.bin"))
    items = [
        Input("kitti-000008.bin", DEMO / "kitti/000008.bin", "lidar", {"lidar_profile": "kitti-hdl64"}),
        *[Input("nuscenes-LIDAR_TOP", p, "lidar", {"lidar_profile": "hdl-32e"})
          for p in sorted((DEMO / "nuscenes").glob("*LIDAR_TOP*.pcd.bin"))],
        *[Input(f"waymo-unit30-{p.name}", p, "lidar", {"bin_fields": WAYMO_FIELDS, "intensity_unit": "unit",
                                                        "intensity_full_scale": WAYMO_FULL_SCALE})
          for p in waymo[:1 if quick else None]],
        Input("ouster-scan0.bin", SHARED / "os1-128/scan0.bin", "lidar", {"lidar_profile": "os1-128-reflectivity"}),
        Input("kitti-000008.png", DEMO / "kitti/000008.png", "camera", GROUND_PLANE),
        *[Input("nuscenes-" + p.name.split("__")[1], p, "camera", GROUND_PLANE) for p in nus[:1 if quick else None]],
        *[Input("dng-" + p.stem, p, "raw", GROUND_PLANE) for p in dngs[:2 if quick else None]],
        Input("sample-radar-000000.pcd", ROOT / "sample_data/radar/seq0/000000.pcd", "radar"),
    ]
    return [i for i in items if i.path.is_file()]


# the strength parameters at which each model must do nothing (its params schema's vanishing end)
VANISH: dict[str, dict] = {
    "alignment.lidar": {"azimuth_sd_deg": 0.0, "elevation_sd_deg": 0.0},
    "alignment.radar": {"yaw_sd_deg": 0.0, "pitch_sd_deg": 0.0, "roll_sd_deg": 0.0},
    "fog.camera": {"visibility_m": 1e15},
    "fog.lidar": {"visibility_m": 1e15},
    "fog.radar": {"visibility_m": 1e15},
    # low light's identity (its docstring): RGB frames through the finest ADC; a raw mosaic keeps its own ADC
    "low_light.camera": {"illuminance_lux": 10000.0, "read_noise_e": 0.0, "dark_current_e_per_s": 0.0,
                         "shot_noise": "off", "adc_bits": 16},
    "motion_blur.camera": {"blur": 0.0},
    "occlusion.lidar": {"seed_probability": 0.0},
    "occlusion.radar": {"seed_probability": 0.0},
    "power.lidar": {"bias_mean_counts": 0.0, "bias_sd_counts": 0.0, "noise_sd_factor": 0.0, "gain_mean": 1.0,
                    "gain_sd": 0.0, "additive_sd_counts": 0.0},
    "power.radar": {"power_sd_db": 0.0},
    "power_electronics.lidar": {"bias_mean_counts": 0.0, "bias_sd_counts": 0.0, "noise_sd_factor": 0.0},
    "rain.camera": {"rain_rate_mm_per_h": 1e-9},          # the schema asks for a rate > 0
    "rain.lidar": {"rain_rate_mm_per_h": 0.0},
    "rain.radar": {"rain_rate_mm_per_h": 0.0},
    "ray_drop.lidar": {"strength": 0.0},
    "snow.camera": {"snowfall_rate_mm_per_h": 1e-9},
    "snow.lidar": {"snowfall_rate_mm_per_h": 0.0},
    "snow.radar": {"snowfall_rate_mm_per_h": 0.0},
    "soiling.camera": {"opacity": 0.0},
    "wind.camera": {"wind_speed_m_per_s": 0.0},           # run before rain.camera (it needs a weather model)
    "windscreen.camera": {"k1": 0.0},
}
# models with no vanishing strength: JPEG at any quality is lossy
NO_VANISH = {"compression.camera": "no vanishing strength (JPEG is lossy at quality 100)"}

# weather strengths, weakest first: (parameter, values)
MONOTONE: dict[str, tuple[str, tuple]] = {
    "rain.lidar": ("rain_rate_mm_per_h", (1.0, 20.0, 100.0)),
    "snow.lidar": ("snowfall_rate_mm_per_h", (0.5, 2.5, 10.0)),
    "fog.lidar": ("visibility_m", (300.0, 80.0, 20.0)),
    "rain.radar": ("rain_rate_mm_per_h", (1.0, 20.0, 100.0)),
    "snow.radar": ("snowfall_rate_mm_per_h", (0.5, 2.5, 10.0)),
    "fog.radar": ("visibility_m", (300.0, 80.0, 20.0)),
    "fog.camera": ("visibility_m", (1000.0, 200.0, 50.0)),
    "rain.camera": ("rain_rate_mm_per_h", (2.0, 20.0, 100.0)),
    "snow.camera": ("snowfall_rate_mm_per_h", (0.5, 3.0, 10.0)),
}
SEEDS = (1, 2, 3, 4, 5)
NOISE_SE = 3.0                   # a fall of a mean beyond this many standard errors is no seed noise
OUTSHONE_RAYS = 1000             # expected_outshone: rays it integrates over (evenly spaced through the cloud)
OUTSHONE_STEP_M = 0.05           # … and its range step
FOLLOWER = {"wind.camera": "rain.camera"}        # wind moves the particles of the weather model after it
POSITION_ROUNDOFF_M = 1e-9       # a turn by 0° about the origin moves points by float64 round-off (3·10⁻¹⁴ m)


def models_for(item: Input) -> list[str]:
    sensor = "camera" if item.sensor == "raw" else item.sensor
    return sorted(k for k, c in load_all().items() if c.sensor == sensor)


def recipe_for(item: Input, model_id: str, params: dict, seed: int):
    """A one-step recipe; a model that modifies the next weather model runs before it (at vanishing strength
    when ``params`` are the model's vanishing ones)."""
    chain = [{"model": model_id, "params": params}]
    if model_id in FOLLOWER:
        after = FOLLOWER[model_id]
        chain.append({"model": after, "params": VANISH[after] if params == VANISH[model_id] else {}})
    return parse_recipe({"schema": SCHEMA, "chain": chain, "seed": seed, "inputs": item.inputs},
                        source=f"<audit {model_id}>")


def run(item: Input, model_id: str, params: dict, seed: int = 1):
    """(input as read, output) of a one-step recipe on ``item``, as ``augment`` computes it."""
    recipe = recipe_for(item, model_id, params, seed)
    sample = Sample(item.path.name, item.sensor, "audit")
    task = Task(sample, 0, item.path.name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = load(sample, item.path.parent, recipe)
        out, _ = apply_models(build_models(recipe, task), data, seed=seed, key=item.path.name,
                              sequence_id="audit", metrics=False)
    return recipe, data, out


def written(item: Input, recipe, out, scratch: Path) -> Path:
    path = scratch / item.path.name
    for old in scratch.iterdir():
        old.unlink()
    save(out, path, recipe, source=item.path)
    return path


# --- comparisons -------------------------------------------------------------------------------------------


def _image(frame) -> np.ndarray:
    if isinstance(frame, np.ndarray):
        return frame
    if isinstance(frame, RawFrame):
        return np.asarray(frame.dn)
    codes = frame.srgb8_codes()
    return codes if codes is not None else linear_to_code(np.asarray(frame.linear_rgb), 8)


def changed_fraction(a, b) -> float:
    """Fraction of points (pixels) of ``a`` not found unchanged in ``b``."""
    if isinstance(a, PointCloud):
        if len(a.positions_m) != len(b.positions_m):
            return abs(len(a.positions_m) - len(b.positions_m)) / max(len(a.positions_m), 1) + (
                0.0 if b.effect is None else float(np.mean(b.effect != Effect.KEPT)))
        diff = np.any(np.abs(a.positions_m - b.positions_m) > POSITION_ROUNDOFF_M, axis=1)
        for k, v in a.fields.items():
            w = b.fields.get(k)
            diff |= True if w is None else ~((np.asarray(v) == np.asarray(w)) | (np.isnan(v) & np.isnan(w)))
        return float(diff.mean())
    x, y = _image(a), _image(b)
    if x.shape != y.shape:
        return 1.0
    d = x != y
    return float((d.any(axis=-1) if d.ndim == 3 else d).mean())


def lost_returns(a: PointCloud, b: PointCloud) -> int:
    """The input's returns the output no longer holds in place (removed, or moved to a particle)."""
    n_in = int(np.count_nonzero(np.any(a.positions_m != 0, axis=1)))
    kept = np.any(b.positions_m != 0, axis=1)
    if b.origin is not None:                      # None: point i descends from point i
        kept &= b.origin >= 0
    if b.effect is not None:
        kept &= (b.effect == Effect.KEPT) | (b.effect == Effect.ATTENUATED)
    return n_in - int(np.count_nonzero(kept))


def luminance_contrast(frame) -> float:
    """RMS contrast (std / mean) of the luminance; of a Bayer mosaic, the mean over its colour channels' (the
    mosaic's own pattern is no scene contrast)."""
    if isinstance(frame, RawFrame):
        s, ci = frame.signal().astype(np.float64), frame.channel_index()
        return float(np.mean([s[ci == c].std() / max(s[ci == c].mean(), 1e-12) for c in np.unique(ci)]))
    img = _image(frame).astype(np.float64)
    lum = img.mean(axis=-1) if img.ndim == 3 else img
    return float(lum.std() / max(lum.mean(), 1e-12))


def mean_change(a, b) -> float:
    return float(np.abs(_image(a).astype(np.float64) - _image(b).astype(np.float64)).mean())


def pcd_header(path: Path) -> list[str]:
    lines = []
    with open(path, "rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").strip()
            if line.split(" ")[0] in ("FIELDS", "SIZE", "TYPE", "COUNT"):
                lines.append(line)
            if line.startswith("DATA"):
                break
    return lines


def strip_effect(header: list[str]) -> list[str]:
    """A PCD header without the ``rv_effect`` field the writer appends (``output.effect: field``)."""
    fields = header[0].split(" ") if header else []
    if "rv_effect" not in fields:
        return header
    k = fields.index("rv_effect")
    return [" ".join(w for j, w in enumerate(line.split(" ")) if j != k) for line in header]


def range_problems(item: Input, data, out, path: Path) -> list[str]:
    """What the written output holds that the sensor cannot report (empty: none)."""
    bad = []
    if isinstance(out, PointCloud):
        profile = out.profile
        for name, v in {"xyz": out.positions_m, **out.fields}.items():
            src = data.positions_m if name == "xyz" else data.fields.get(name)
            n = int(np.count_nonzero(~np.isfinite(np.asarray(v, dtype=np.float64))))
            n0 = 0 if src is None else int(np.count_nonzero(~np.isfinite(np.asarray(src, dtype=np.float64))))
            if n > n0:
                bad.append(f"{name}: {n} non-finite (input {n0})")
        r = np.linalg.norm(out.positions_m, axis=1)
        max_r = getattr(profile, "max_range_m", None)
        if max_r:                     # the input may hold returns beyond the datasheet's range: count only the rise
            beyond = int(np.count_nonzero(r > max_r * 1.0001))
            before = int(np.count_nonzero(np.linalg.norm(data.positions_m, axis=1) > max_r * 1.0001))
            if beyond > before:
                bad.append(f"{beyond} points beyond max_range_m {max_r:g} (input {before}; max {r.max():.1f} m)")
        if out.sensor == "lidar" and "intensity" in out.fields and len(r):
            i = np.asarray(out.fields["intensity"], dtype=np.float64)
            fs = float(profile.intensity_full_scale)
            if np.nanmax(i) > fs * (1 + 1e-6):
                bad.append(f"intensity max {np.nanmax(i):g} > full scale {fs:g}")
            if np.nanmin(i) < 0:
                bad.append(f"intensity min {np.nanmin(i):g} < 0")
            if str(profile.intensity_unit.value if hasattr(profile.intensity_unit, "value") else
                   profile.intensity_unit) == "uint8" and np.any(i != np.round(i)):
                bad.append(f"8-bit intensity: {int(np.count_nonzero(i != np.round(i)))} non-integer values")
        if out.sensor == "radar" and (profile.elevation_measured is False or (
                profile.elevation_measured is None and not np.any(data.positions_m[:, 2]))):
            if np.any(out.positions_m[:, 2] != 0):
                bad.append(f"2-D radar: {int(np.count_nonzero(out.positions_m[:, 2]))} points with z ≠ 0")
        suffix = item.path.name.lower()
        if suffix.endswith(".pcd"):
            if strip_effect(pcd_header(path)) != pcd_header(item.path):
                bad.append(f"PCD header {pcd_header(path)} ≠ input's {pcd_header(item.path)}")
        elif suffix.endswith(".bin"):
            cols = len(item.inputs.get("bin_fields") or (5 if suffix.endswith(".pcd.bin") else 4) * [0])
            if path.stat().st_size % (4 * cols):
                bad.append(f".bin size {path.stat().st_size} not a multiple of {cols} float32 columns")
    elif isinstance(out, CameraFrame):
        a = cv2.imread(str(item.path), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if b is None or a.dtype != b.dtype or a.shape != b.shape:
            bad.append(f"written {None if b is None else (b.dtype, b.shape)} ≠ input {(a.dtype, a.shape)}")
        v = np.asarray(out.linear_rgb)
        if not np.all(np.isfinite(v)):
            bad.append(f"{int(np.count_nonzero(~np.isfinite(v)))} non-finite linear values")
    else:
        from roadview_noise.io.raw import read_raw

        v = np.asarray(out.dn)
        if not np.all(np.isfinite(v)):
            bad.append(f"{int(np.count_nonzero(~np.isfinite(v)))} non-finite DN")
        dn = read_raw(path)[0]
        src = np.asarray(data.dn)
        if dn.shape != src.shape:
            bad.append(f"written DNG {dn.shape} ≠ input {src.shape}")
        if dn.max() > out.white_level_dn or dn.min() < 0:
            bad.append(f"DN {dn.min():g}…{dn.max():g} outside 0…white {out.white_level_dn:g}")
    return bad


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --- the audit ----------------------------------------------------------------------------------------------


def audit(item: Input, model_id: str, scratch: Path) -> dict[str, str]:
    cells: dict[str, str] = {}
    try:
        if model_id in NO_VANISH:
            cells["identity"] = "n/a: " + NO_VANISH[model_id]
        else:
            recipe, data, out = run(item, model_id, VANISH[model_id])
            if isinstance(out, RawFrame):     # DN are whole numbers in the file: compare what is written
                from roadview_noise.io.raw import read_raw

                frac = changed_fraction(read_raw(item.path)[0], read_raw(written(item, recipe, out, scratch))[0])
            else:
                frac = changed_fraction(data, out)
            cells["identity"] = "ok" if frac <= 1e-3 else f"FAIL {VANISH[model_id]}: {100 * frac:.2f} % changed"
        recipe, data, out = run(item, model_id, {}, seed=1)
        path = written(item, recipe, out, scratch)
        bad = range_problems(item, data, out, path)
        cells["range"] = "ok" if not bad else "FAIL " + "; ".join(bad)
        first = digest(path)
        recipe, _, out = run(item, model_id, {}, seed=1)
        cells["determinism"] = "ok" if digest(written(item, recipe, out, scratch)) == first else "FAIL bytes differ"
        if model_id in MONOTONE:
            cells["monotone"] = monotone(item, model_id)
    except (InputError, ModelError) as e:             # a file or chain refused with its reason: by design
        cells["refused"] = f"n/a: {type(e).__name__}: {str(e)[:160]}"
    except Exception as e:                            # noqa: BLE001 - the audit reports every failure
        cells["error"] = f"{type(e).__name__}: {str(e)[:160]}"
    return cells


def falls(means, ses) -> list[int]:
    """Steps i where the mean falls from strength i to i + 1 by more than ``NOISE_SE`` standard errors."""
    return [i for i in range(len(means) - 1)
            if means[i + 1] < means[i] - NOISE_SE * math.hypot(ses[i], ses[i + 1]) - 1e-9]


def expected_outshone(data: PointCloud, model_id: str, params: dict) -> float:
    """Closed-form count of the cloud's returns that a particle of rain/snow ``model_id`` outshines: per ray of
    target signal S at range R (units of K), ``1 − e^{−Λ}``, ``Λ = ∫_{R1}^{R} π w(r)² N(D ≥ D_c(r)) dr`` with D_c the
    smallest particle whose return reaches ``S e^{−2αR}`` (:func:`lidar_particles.visibility_diameter_mm`), summed
    over ``OUTSHONE_RAYS`` rays and scaled to the cloud — the Monte-Carlo draw, pulse summing and detection left out."""
    from roadview_noise.physics.lidar_particles import Beam, visibility_diameter_mm
    from roadview_noise.physics.lidar_rays import cloud_rays

    medium = load_all()[model_id](**params).medium()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                   # the intensity-unit warning: run() silenced it already
        rays = cloud_rays(data, model_id, "ignore")
    hit = np.flatnonzero(rays.has_target)
    pick = hit[np.linspace(0, len(hit) - 1, min(len(hit), OUTSHONE_RAYS)).astype(int)] if len(hit) else hit
    if medium is None or not len(pick):
        return 0.0
    beam = Beam.of(rays.profile)
    big_r = rays.range_m[pick][:, None]
    level = rays.decision_signal[pick][:, None] * np.exp(-2 * medium.alpha_per_m * big_r)
    r = np.arange(beam.overlap_start_m, big_r.max(), OUTSHONE_STEP_M)[None, :]
    density = np.pi * beam.radius_at(r) ** 2 * medium.count_above(visibility_diameter_mm(medium, beam, level, r))
    lam = np.sum(np.where(r < big_r, density, 0.0), axis=1) * OUTSHONE_STEP_M
    return float(np.sum(1 - np.exp(-lam)) * len(hit) / len(pick))


def monotone(item: Input, model_id: str) -> str:
    name, values = MONOTONE[model_id]
    means, ses = [], []
    for v in values:
        per_seed = []
        for s in SEEDS:
            _, data, out = run(item, model_id, {name: v}, seed=s)
            if isinstance(out, PointCloud):
                per_seed.append(lost_returns(data, out))
            elif model_id.startswith("fog."):
                per_seed.append(-luminance_contrast(out))           # contrast falls: −contrast rises
            else:
                per_seed.append(mean_change(data, out))
        means.append(float(np.mean(per_seed)))
        ses.append(float(np.std(per_seed, ddof=1) / math.sqrt(len(per_seed))))
    what = ("lost returns" if item.sensor in ("lidar", "radar") else
            "−contrast" if model_id.startswith("fog.") else "mean |Δ|")
    text = (f"{what} at {name}={values}, mean ± SE of {len(SEEDS)} seeds: "
            + ", ".join(f"{m:.4g} ± {e:.2g}" for m, e in zip(means, ses)))
    fell = falls(means, ses)
    if not fell:
        return "ok " + text
    if item.sensor == "lidar" and hasattr(load_all()[model_id], "medium"):       # rain, snow
        expected = [expected_outshone(data, model_id, {name: v}) for v in values]
        text += "; closed-form outshone " + ", ".join(f"{x:.4g}" for x in expected)
        if all(expected[i + 1] < expected[i] for i in fell):
            return "ok " + text + " (falls with the flakes able to outshine the targets: physics)"
    return "FAIL " + text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="one nuScenes photo, two DNGs, one Waymo scan")
    ap.add_argument("--model", action="append", help="only these model ids")
    ap.add_argument("--input", action="append", help="only inputs whose name contains this")
    args = ap.parse_args(argv)
    items = real_inputs(args.quick)
    if args.input:
        items = [i for i in items if any(s in i.name for s in args.input)]
    scratch = Path(tempfile.mkdtemp(prefix="rv-audit-"))
    failures = 0
    try:
        print("| model | input | property | result |\n|---|---|---|---|")
        for item in items:
            for model_id in models_for(item):
                if args.model and model_id not in args.model:
                    continue
                for prop, text in audit(item, model_id, scratch).items():
                    failures += not (text.startswith("ok") or text.startswith("n/a"))
                    print(f"| {model_id} | {item.name} | {prop} | {text} |", flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    print(f"\n{failures} violations", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
