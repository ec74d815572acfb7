"""``rvnoise preview``: what a recipe does to one file, step by step, through the same code as ``augment``.

The file is read with ``dataset.load``, the chain built with ``runner.build_models`` and run with
``compound.apply_models`` under the output key ``augment`` would use (the path relative to the input root), so the
final panel is what ``augment`` writes. The output of step k is ``apply_models`` on the first k models: the same
random draws (they depend on the step index), no hook in the engine.

Rendering (OpenCV, BGR uint8; labels are ASCII because OpenCV's fonts are):
- camera: input, every step and the final image side by side, each with a zoomed inset of the region that changed
  most, and its metrics against the input (PSNR, SSIM, RMS contrast);
- LiDAR: a bird's-eye view per stage coloured by range or intensity, weather returns (ADDED) red, returns moved to
  a particle yellow, removed returns magenta at their old place; below, the range images before and after;
- radar: a bird's-eye view per stage, SNR-coloured disks, clutter (ADDED) circled red, removed points as grey rings.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from .compound import CNFS, apply_models
from .dataset import DEFAULT_GLOBS, Sample, depth_relpath_for, load, output_relpath, sequence_id
from .errors import InputError, RecipeError, RvNoiseError
from .io.atomic import write_bytes_atomic
from .metrics import Effect, compare, correspondence, effect_codes
from .physics.laser_order import with_laser_order
from .recipe import SCHEMA, Recipe, parse_recipe
from .registry import load_all, suggest
from .runner import Task, build_models
from .types import CameraFrame, PointCloud, RawFrame, SensorData, sensor_kind

FONT = cv2.FONT_HERSHEY_SIMPLEX
BAR_PX = 20
BACKGROUND = (24, 24, 24)
ADDED_BGR = (40, 40, 255)           # weather returns / clutter
MOVED_BGR = (0, 220, 255)           # returns moved to a particle
REMOVED_BGR = (255, 60, 255)        # returns lost (drawn at their old place)
RADAR_REMOVED_BGR = (150, 150, 150)
TEXT_BGR = (235, 235, 235)
INSET_FRACTION = 0.2                # zoomed region: this fraction of the frame's width and height
INSET_WIDTH = 0.45                  # inset width as a fraction of the panel
CAMERA_SUFFIXES = tuple(g.rsplit("*", 1)[-1] for g in DEFAULT_GLOBS["camera"])
RAW_SUFFIXES = tuple(g.rsplit("*", 1)[-1] for g in DEFAULT_GLOBS["raw"])


@dataclass
class ChainRun:
    """A chain run on one file: ``stages`` = [("input", data), (model id, output after that step), …]."""

    title: str
    stages: list[tuple[str, SensorData]]
    records: list
    total: dict[str, Any]

    @property
    def sensor(self) -> str:
        return sensor_kind(self.stages[0][1])


# --- recipes and samples --------------------------------------------------------------------------------------


def guess_sensor(path: Path) -> str:
    """camera for images and raw files; for clouds radar when the file has radar fields (RCS, Doppler, SNR), else
    lidar; a ``.txt`` table is radar (Astyx); a ``.bin`` is radar when the nearest folder named for a sensor
    (``radar*`` or ``lidar*``) is a radar's (View-of-Delft's ``radar/training/velodyne/``, as the recipes'
    ``radar/**/*.bin`` globs read it), or when it holds TJ4DRadSet's layout (``training/velodyne/``), else lidar."""
    name = path.name.lower()
    if name.endswith(CAMERA_SUFFIXES + RAW_SUFFIXES):
        return "camera"
    if name.endswith(".txt"):
        return "radar"
    if name.endswith(".bin"):
        named = [p.lower()[:5] for p in reversed(path.resolve().parent.parts) if p.lower()[:5] in ("radar", "lidar")]
        if named:
            return named[0]
        from .io.radar_formats import is_tj4d_bin

        return "radar" if path.is_file() and is_tj4d_bin(path.read_bytes()) else "lidar"   # TJ4DRadSet's layout
    from .io.pointcloud import read_pointcloud

    fields = read_pointcloud(path, sensor="lidar").fields
    return "radar" if {"rcs_dbsm", "v_r_m_per_s", "snr_db"} & set(fields) else "lidar"


def check_fits(recipe: Recipe, kind: str, path: Path) -> None:
    """RecipeError when a camera file meets a cloud recipe or a cloud a camera recipe (a file's camera kind is
    certain from its suffix; LiDAR and radar clouds are told apart by guessing, so they are not compared)."""
    if (kind == "camera") != (recipe.sensor == "camera"):
        what = "a camera image" if kind == "camera" else "a point cloud"
        raise RecipeError(f"{path} is {what}, but the recipe's chain ({' → '.join(recipe.model_ids)}) is for "
                          f"{recipe.sensor} data; give a {'camera' if kind == 'camera' else 'LiDAR or radar'} recipe "
                          "or CNF (`rvnoise list`)")


def cnf_recipe(name: str, sensor: str, seed: int = 0) -> Recipe:
    """The recipe of one CNF for one sensor with its D3.5 defaults (RecipeError if it cannot run)."""
    return parse_recipe({"schema": SCHEMA, "cnf": name, "sensor": sensor, "seed": seed}, source=f"<{name}>")


def recipe_from(spec: str, sensor: str | None, seed: int) -> Recipe:
    """A recipe file, or a CNF id (``CNF16``) with its defaults."""
    from .recipe import load_recipe

    if not Path(spec).exists() and spec.upper() not in CNFS:
        raise RecipeError(f"--recipe {spec!r} is neither a recipe file nor a CNF id{suggest(spec, CNFS)}")
    if Path(spec).is_file() or spec.upper() not in CNFS:
        return load_recipe(spec)
    chains = CNFS[spec.upper()].chains
    if sensor is None and len(chains) > 1:
        raise RecipeError(f"{spec.upper()} exists for {', '.join(chains)}; say which with --sensor")
    return cnf_recipe(spec.upper(), sensor or next(iter(chains)), seed)


def applicable_cnfs(sensor: str, seed: int = 0) -> list[tuple[str, Recipe | str]]:
    """Every CNF with a chain for ``sensor``: its recipe, or why it cannot run (a model not implemented yet)."""
    models = load_all()
    out: list[tuple[str, Recipe | str]] = []
    for name, cnf in CNFS.items():
        ids = cnf.chains.get(sensor)
        if ids is None:
            continue
        missing = [m for m in ids if m not in models]
        out.append((name, f"not implemented yet: {', '.join(missing)}" if missing else cnf_recipe(name, sensor, seed)))
    return out


def sample_for(path: Path, recipe: Recipe, in_root: Path | None = None) -> tuple[Sample, Path]:
    """The sample ``augment`` would make of ``path`` under ``in_root`` (default: the file's folder): relative path
    (the random draws' key), modality, sequence (sensor instance) and depth sidecar, by the recipe's inputs."""
    path = Path(path).resolve()
    root = Path(in_root).resolve() if in_root is not None else path.parent
    if not path.is_file():
        raise InputError("no such file", file=str(path))
    try:
        rel = path.relative_to(root).as_posix()
    except ValueError:
        raise InputError(f"not inside the input root {str(root)!r}", file=str(path)) from None
    inputs = recipe.spec.inputs
    modality = recipe.sensor
    if modality == "camera" and path.name.lower().endswith(RAW_SUFFIXES):
        modality = "raw"
    sequence = sequence_id(rel, inputs.sequence)
    depth = None
    if recipe.sensor == "camera":
        candidate = depth_relpath_for(rel, inputs.depth)
        depth = candidate if (root / candidate).is_file() else None
    return Sample(rel, modality, sequence, depth), root


def file_label(path: Path, in_root: Path | None = None) -> str:
    """A file name for the preview of ``path``: its path under ``in_root`` (or its folder and name), without the
    suffix, ``/`` → ``_``."""
    path = Path(path).resolve()
    try:
        rel = path.relative_to(Path(in_root).resolve()) if in_root is not None else None
    except ValueError:
        rel = None
    parts = (rel or Path(path.parent.name) / path.name).with_suffix("").parts
    return "_".join(p for p in parts if p not in ("", "."))


def run_chain(recipe: Recipe, sample: Sample, in_root: Path, *, variant_index: int = 0, title: str = "",
              key: str | None = None) -> ChainRun:
    """Run ``recipe`` on one sample exactly as ``augment`` does for output ``key`` (default: the sample's output
    path for the variant), keeping every intermediate result."""
    key = key or output_relpath(sample.relpath, recipe.variants[variant_index].suffix)
    task = Task(sample, variant_index, key)
    original = load(sample, in_root, recipe)
    if isinstance(original, PointCloud):          # a KITTI scan's rings from its storage order, as apply_models finds
        original = with_laser_order(original)     # them, so the input panel's range image has them too
    models = build_models(recipe, task)
    stages: list[tuple[str, SensorData]] = [("input", original)]
    records: list = []
    for k in range(1, len(models) + 1):
        data, records = apply_models(models[:k], original, seed=recipe.seed, key=key, sequence_id=sample.sequence_id)
        stages.append((models[k - 1].id, data))
    return ChainRun(title or " -> ".join(recipe.model_ids), stages, records, compare(original, stages[-1][1]))


# --- drawing helpers ------------------------------------------------------------------------------------------


def text_bar(width: int, text: str, colour=TEXT_BGR, background=(0, 0, 0), height: int = BAR_PX) -> np.ndarray:
    bar = np.empty((height, width, 3), np.uint8)
    bar[:] = background
    cv2.putText(bar, _ascii(text), (6, height - 6), FONT, 0.42, colour, 1, cv2.LINE_AA)
    return bar


def _ascii(text: str) -> str:
    for a, b in (("→", "->"), ("·", "|"), ("×", "x"), ("–", "-"), ("—", "-"), ("≤", "<="), ("≥", ">="), ("°", " deg")):
        text = text.replace(a, b)
    return text.encode("ascii", "replace").decode()


def stack_rows(rows: Sequence[np.ndarray], gap: int = 4) -> np.ndarray:
    """Rows of different widths stacked, padded with the background colour."""
    width = max(r.shape[1] for r in rows)
    out = []
    for r in rows:
        if r.shape[1] < width:
            pad = np.empty((r.shape[0], width - r.shape[1], 3), np.uint8)
            pad[:] = BACKGROUND
            r = np.hstack([r, pad])
        out.append(r)
        out.append(np.full((gap, width, 3), BACKGROUND, np.uint8))
    return np.vstack(out[:-1])


def side_by_side(panels: Sequence[np.ndarray], gap: int = 4) -> np.ndarray:
    height = max(p.shape[0] for p in panels)
    parts = []
    for p in panels:
        if p.shape[0] < height:
            p = np.vstack([p, np.full((height - p.shape[0], p.shape[1], 3), BACKGROUND, np.uint8)])
        parts += [p, np.full((height, gap, 3), BACKGROUND, np.uint8)]
    return np.hstack(parts[:-1])


def _colormap(values: np.ndarray, lo: float, hi: float, cmap: int = cv2.COLORMAP_TURBO) -> np.ndarray:
    """(N, 3) BGR colours of ``values`` scaled from [lo, hi]."""
    scaled = np.clip((np.asarray(values, np.float64) - lo) / max(hi - lo, 1e-9), 0, 1) * 255
    return cv2.applyColorMap(scaled.astype(np.uint8).reshape(-1, 1), cmap).reshape(-1, 3)


def _splat(img: np.ndarray, u: np.ndarray, v: np.ndarray, colours, radius: int = 0, ring: bool = False) -> None:
    """Draw points (disks of ``radius`` px, or rings) in place, vectorised over points."""
    h, w = img.shape[:2]
    colours = np.broadcast_to(np.asarray(colours, np.uint8), (len(u), 3))
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            d = np.hypot(du, dv)
            if d > radius + 0.5 or (ring and d < radius - 0.5):
                continue
            uu, vv = u + du, v + dv
            inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            img[vv[inside], uu[inside]] = colours[inside]


def encode_image(img: np.ndarray, suffix: str = ".png", jpeg_quality: int = 88) -> bytes:
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if suffix.lower() in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(suffix, img, params)
    if not ok:
        raise RecipeError(f"cannot encode a {suffix} image")
    return buf.tobytes()


def write_image_file(path: Path, img: np.ndarray) -> None:
    suffix = Path(path).suffix.lower() or ".png"
    if suffix not in (".png", ".jpg", ".jpeg"):
        raise RecipeError(f"{str(path)!r}: previews are written as .png or .jpg")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, encode_image(img, suffix))


# --- camera ---------------------------------------------------------------------------------------------------


def _display_rgb(frame: CameraFrame | RawFrame, gains: np.ndarray | None = None) -> np.ndarray:
    """BGR uint8 of a frame as displayed; raw Bayer: half-resolution RGB of the CFA cells with ``gains``."""
    from .physics.srgb import linear_to_code

    if isinstance(frame, RawFrame):
        rgb = _cfa_cells(frame)
        rgb = rgb * (gains if gains is not None else 1.0)
    else:
        rgb = frame.linear_rgb
        if rgb.ndim == 2:
            rgb = np.repeat(rgb[..., None], 3, axis=2)
    return cv2.cvtColor(linear_to_code(rgb, 8), cv2.COLOR_RGB2BGR)


def _cfa_cells(frame: RawFrame) -> np.ndarray:
    """(H/2, W/2, 3) linear RGB: each 2×2 CFA cell's R, mean G and B."""
    s = frame.signal()
    h, w = s.shape[0] // 2 * 2, s.shape[1] // 2 * 2
    idx = frame.channel_index()
    rgb = np.zeros((h // 2, w // 2, 3), np.float32)
    count = np.zeros(3, np.float32)
    for dy in (0, 1):
        for dx in (0, 1):
            c = int(idx[dy, dx])
            rgb[..., c] += s[dy:h:2, dx:w:2]
            count[c] += 1
    return rgb / count


def _grey_world_gains(frame: RawFrame) -> np.ndarray:
    means = _cfa_cells(frame).reshape(-1, 3).mean(axis=0)
    return (means[1] / np.maximum(means, 1e-6)).astype(np.float32)


def _changed_region(before: np.ndarray, after: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the window of ``INSET_FRACTION`` of the frame where the fine structure of ``after`` differs
    most from ``before`` (streaks, flakes, lost edges rather than a uniform veil; the centre when nothing
    changed)."""
    h, w = before.shape[:2]
    rw, rh = max(8, int(w * INSET_FRACTION)), max(8, int(h * INSET_FRACTION))
    scale = min(1.0, 320.0 / w)
    small = (max(1, int(w * scale)), max(1, int(h * scale)))

    def detail(img):
        g = cv2.cvtColor(cv2.resize(img, small, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2GRAY).astype(np.float32)
        return g - cv2.blur(g, (5, 5))

    diff = np.abs(detail(after) - detail(before))
    if not diff.any():
        return (w - rw) // 2, (h - rh) // 2, rw, rh
    k = (max(1, int(rw * scale)), max(1, int(rh * scale)))
    score = cv2.boxFilter(diff, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    cy, cx = np.unravel_index(int(np.argmax(score)), score.shape)
    x = int(np.clip(cx / scale - rw / 2, 0, w - rw))
    y = int(np.clip(cy / scale - rh / 2, 0, h - rh))
    return x, y, rw, rh


def render_camera(run: ChainRun, panel_px: int = 480) -> np.ndarray:
    first = run.stages[0][1]
    gains = _grey_world_gains(first) if isinstance(first, RawFrame) else None
    images = [_display_rgb(d, gains) for _, d in run.stages]
    x, y, rw, rh = _changed_region(images[0], images[-1])
    panels = []
    for i, ((name, data), img) in enumerate(zip(run.stages, images)):
        h, w = img.shape[:2]
        ph = max(1, round(h * panel_px / w))
        panel = cv2.resize(img, (panel_px, ph), interpolation=cv2.INTER_AREA if w > panel_px else cv2.INTER_LINEAR)
        s = panel_px / w
        cv2.rectangle(panel, (int(x * s), int(y * s)), (int((x + rw) * s), int((y + rh) * s)), (0, 255, 255), 1)
        iw = int(panel_px * INSET_WIDTH)
        ih = max(1, round(rh * iw / rw))
        if ih < ph - 4:
            inset = cv2.resize(img[y:y + rh, x:x + rw], (iw, ih), interpolation=cv2.INTER_NEAREST)
            panel[ph - ih - 2:ph - 2, panel_px - iw - 2:panel_px - 2] = inset
            cv2.rectangle(panel, (panel_px - iw - 3, ph - ih - 3), (panel_px - 2, ph - 2), (0, 255, 255), 1)
        m = compare(run.stages[0][1], data)
        title = "input" if i == 0 else f"{i}. {name}" + (" (final)" if i == len(run.stages) - 1 else "")
        if i == 0:
            line = f"contrast {m['rms_contrast_out']:.3f} | edges {m['edge_density_out'] * 100:.1f} %"
        else:
            line = (f"PSNR {m['psnr_db']:.1f} dB | SSIM {m['ssim']:.3f} | contrast {m['rms_contrast_out']:.3f}"
                    if m["ssim"] is not None else f"PSNR {m['psnr_db']:.1f} dB")
        panels.append(np.vstack([text_bar(panel_px, title), text_bar(panel_px, line), panel]))
    return side_by_side(panels)


# --- LiDAR and radar ------------------------------------------------------------------------------------------


def _returns(cloud: PointCloud) -> np.ndarray:
    from .physics.lidar_geometry import has_return

    return has_return(cloud.positions_m)


def _codes(cloud: PointCloud) -> np.ndarray:
    c = effect_codes(cloud)
    return np.zeros(len(cloud), np.uint8) if c is None else np.asarray(c)


def _extent_m(cloud: PointCloud) -> float:
    r = cloud.ranges_m[_returns(cloud)]
    return float(np.clip(np.percentile(r, 98) * 1.05 if len(r) else 50.0, 10.0, 150.0))


def _bev_uv(positions: np.ndarray, extent_m: float, px: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of a bird's-eye view ``px`` wide showing ±extent: x forward up, y left to the left; the sensor at the
    centre of a square view, at the bottom centre of a half-height (forward-looking, radar) view."""
    scale = px / (2 * extent_m)
    u = np.rint(px / 2 - positions[:, 1] * scale).astype(np.int64)
    origin_v = px / 2 if height == px else height - 1
    v = np.rint(origin_v - positions[:, 0] * scale).astype(np.int64)
    return u, v


RADAR_SHADES = (("snr_db", "SNR colour"), ("power_db", "power colour"), ("rcs_dbsm", "RCS colour"))


def _radar_shade(cloud: PointCloud) -> tuple[np.ndarray | None, str]:
    """The detection field a radar cloud is coloured by (SNR, else power, else RCS) and its legend label."""
    return next(((cloud.fields[k], label) for k, label in RADAR_SHADES if k in cloud.fields), (None, "no SNR/RCS"))


def _point_colours(cloud: PointCloud, colour_by: str, lo: float, hi: float) -> np.ndarray:
    if cloud.sensor == "radar":
        values = _radar_shade(cloud)[0]
        values = np.zeros(len(cloud)) if values is None else values
        return _colormap(values, lo, hi, cv2.COLORMAP_VIRIDIS)
    if colour_by == "intensity" and "intensity" in cloud.fields:
        return _colormap(np.asarray(cloud.fields["intensity"], np.float64), lo, hi)
    return _colormap(cloud.ranges_m, lo, hi)


def _value_range(cloud: PointCloud, colour_by: str, extent_m: float) -> tuple[float, float]:
    if cloud.sensor == "radar":
        v = _radar_shade(cloud)[0]
        v = np.zeros(1) if v is None else np.asarray(v, np.float64)
        return float(np.percentile(v, 2)), float(np.percentile(v, 98)) + 1e-6
    if colour_by == "intensity" and "intensity" in cloud.fields:
        v = np.asarray(cloud.fields["intensity"], np.float64)[_returns(cloud)]
        return (0.0, float(np.percentile(v, 98)) + 1e-6) if len(v) else (0.0, 1.0)
    return 0.0, extent_m


def _bev(before: PointCloud, cloud: PointCloud, *, extent_m: float, px: int, colour_by: str, lo: float, hi: float,
         is_input: bool) -> np.ndarray:
    radar = cloud.sensor == "radar"
    height = px // 2 if radar else px
    img = np.empty((height, px, 3), np.uint8)
    img[:] = BACKGROUND
    if radar:
        for r in np.arange(10.0, extent_m, 10.0 if extent_m < 80 else 20.0):      # range rings every 10/20 m
            cv2.circle(img, (px // 2, height - 1), int(r * px / (2 * extent_m)), (55, 55, 55), 1, cv2.LINE_AA)
    else:
        cv2.circle(img, (px // 2, px // 2), 3, (200, 200, 200), -1)
    ok = _returns(cloud)
    codes = _codes(cloud)
    u, v = _bev_uv(cloud.positions_m, extent_m, px, height)
    colours = _point_colours(cloud, colour_by, lo, hi)
    if not is_input:                                     # lost returns first, at their old place
        index, moved = correspondence(before, cloud)
        lost = (index < 0) & _returns(before)
        bu, bv = _bev_uv(before.positions_m[lost], extent_m, px, height)
        if radar:
            _splat(img, bu, bv, RADAR_REMOVED_BGR, radius=4, ring=True)
        else:
            _splat(img, bu, bv, REMOVED_BGR, radius=0)
    plain = ok & (codes != Effect.ADDED) & (codes != Effect.MOVED)
    _splat(img, u[plain], v[plain], colours[plain], radius=3 if radar else 0)
    for code, bgr in ((Effect.MOVED, MOVED_BGR), (Effect.ADDED, ADDED_BGR)):
        m = ok & (codes == code)
        if radar:
            _splat(img, u[m], v[m], colours[m], radius=3)
            _splat(img, u[m], v[m], bgr, radius=5, ring=True)
        else:
            _splat(img, u[m], v[m], bgr, radius=0)
    return img


def _range_image(cloud: PointCloud, hi_m: float, columns: int | None) -> tuple[np.ndarray, int] | None:
    """(rows × columns BGR, columns) of a LiDAR cloud coloured by range, ADDED red, MOVED yellow; None without a
    grid or a beam table."""
    codes = _codes(cloud)
    if cloud.grid_shape is not None:
        rows, cols = cloud.grid_shape
        index = np.arange(rows * cols).reshape(rows, cols)
    else:
        from .physics.firing_grid import firing_grid
        from .physics.lidar_geometry import range_image, ring_index

        if cloud.profile is None:
            return None
        try:
            ring = ring_index(cloud, cloud.profile)
        except InputError:
            return None
        if columns is None:
            grid = firing_grid(cloud, cloud.profile)
            columns = grid.columns if not isinstance(grid, str) else cloud.profile.columns
        index = range_image(cloud.positions_m, ring, cloud.profile, columns=columns).index
        rows, cols = index.shape
    shown = index >= 0
    flat = index[shown]
    img = np.zeros((rows, cols, 3), np.uint8)
    colours = _colormap(cloud.ranges_m[flat], 0.0, hi_m)
    c = codes[flat]
    colours[c == Effect.MOVED] = MOVED_BGR
    colours[c == Effect.ADDED] = ADDED_BGR
    colours[~_returns(cloud)[flat]] = 0
    img[shown] = colours
    return img, cols


def render_cloud(run: ChainRun, panel_px: int = 480, colour_by: str = "range") -> np.ndarray:
    first = run.stages[0][1]
    radar = first.sensor == "radar"
    extent = _extent_m(first)
    lo, hi = _value_range(first, colour_by, extent)
    panels = []
    for i, (name, cloud) in enumerate(run.stages):
        m = compare(first, cloud)
        title = "input" if i == 0 else f"{i}. {name}" + (" (final)" if i == len(run.stages) - 1 else "")
        if i == 0:
            line = f"{m['points_out']} returns | max {m['max_range_m_out']:.1f} m"
        else:
            line = (f"removed {m['removed']} | moved {m['moved']} | added {m['added']} | "
                    f"max {m['max_range_m_out']:.1f} m")
        bev = _bev(first, cloud, extent_m=extent, px=panel_px, colour_by=colour_by, lo=lo, hi=hi, is_input=i == 0)
        panels.append(np.vstack([text_bar(panel_px, title), text_bar(panel_px, line), bev]))
    rows = [side_by_side(panels)]
    width = rows[0].shape[1]
    if radar:
        shade = _radar_shade(first)[1]
        rows.append(_legend(width, [(shade, TEXT_BGR), ("clutter (added)", ADDED_BGR),
                                    ("removed", RADAR_REMOVED_BGR)], extent))
        return stack_rows(rows)
    columns = None
    for name, cloud in (run.stages[0], run.stages[-1]):
        ri = _range_image(cloud, extent, columns)
        if ri is None:
            continue
        img, columns = ri
        scale = max(1, 256 // img.shape[0])
        img = cv2.resize(img, (width, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
        rows.append(np.vstack([text_bar(width, f"range image, {name}"), img]))
    colour = "range" if colour_by != "intensity" else "intensity"
    rows.append(_legend(width, [(f"{colour} colour", TEXT_BGR), ("moved to a particle", MOVED_BGR),
                                ("added (weather)", ADDED_BGR), ("removed (old place)", REMOVED_BGR)], extent))
    return stack_rows(rows)


def _legend(width: int, items: list[tuple[str, tuple]], extent_m: float) -> np.ndarray:
    bar = text_bar(width, "")
    x = 6
    for text, bgr in items + [(f"view +/-{extent_m:.0f} m", TEXT_BGR)]:
        cv2.putText(bar, text, (x, BAR_PX - 6), FONT, 0.42, bgr, 1, cv2.LINE_AA)
        x += cv2.getTextSize(text, FONT, 0.42, 1)[0][0] + 18
    return bar


def render(run: ChainRun, panel_px: int = 480, colour_by: str = "range") -> np.ndarray:
    """The preview of one chain run (BGR uint8), with its title on top."""
    body = render_camera(run, panel_px) if run.sensor == "camera" else render_cloud(run, panel_px, colour_by)
    return np.vstack([text_bar(body.shape[1], run.title, background=(60, 40, 20), height=BAR_PX + 4), body])


def note_row(width: int, text: str) -> np.ndarray:
    return text_bar(width, text, colour=(170, 170, 170), background=(40, 40, 40), height=BAR_PX + 4)


def contact_sheet(path: Path, sensor: str, *, in_root: Path | None = None, seed: int = 0, panel_px: int = 320,
                  colour_by: str = "range", progress: bool | None = None, **input_overrides: str | None) -> np.ndarray:
    """Every CNF applicable to ``sensor`` on one file: one row per CNF, a note for a CNF that cannot run;
    ``input_overrides`` (``depth``, ``depth_source``, …: :func:`overrides.with_input_overrides`) apply to each.
    ``progress``: a bar on stderr, one step per CNF (None: when stderr is a terminal; a full-size camera frame
    takes ≈ 18 s for its 18 CNFs)."""
    from tqdm import tqdm

    from .overrides import with_input_overrides

    rows: list[np.ndarray | str] = []
    cnfs = applicable_cnfs(sensor, seed)
    for name, recipe in tqdm(cnfs, desc=f"{path.name}", unit="CNF", leave=False, disable=None if progress is None
                             else not progress):
        cnf = CNFS[name]
        head = f"{name}: {cnf.factor} + {cnf.weather} ({cnf.method})"
        if isinstance(recipe, str):
            rows.append(f"{head}: {recipe}")
            continue
        try:
            recipe = with_input_overrides(recipe, **input_overrides)
            sample, root = sample_for(path, recipe, in_root)
            run = run_chain(recipe, sample, root, title=f"{head}: {' -> '.join(recipe.model_ids)}")
            rows.append(render(run, panel_px, colour_by))
        except RvNoiseError as e:
            rows.append(f"{head}: {e}")
    width = max([r.shape[1] for r in rows if not isinstance(r, str)], default=960)
    return stack_rows([note_row(width, r) if isinstance(r, str) else r for r in rows], gap=8)

