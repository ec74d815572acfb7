"""What a noise chain did to a frame or a cloud: the per-step and per-output metrics of the manifest (issue 18).

``compare(before, after)`` returns a flat JSON-able dict; ``compound.apply_models`` stores it per step
(``steps[i].metrics``: the step's input against its output) and the runner per output (``metrics``: the chain's
input against the written output). Pure NumPy/OpenCV plus one compiled pass over clouds; no I/O. Each data object
is summarised once (cached while it lives), so a chain of n steps costs n + 1 summaries and n + 1 comparisons.

Camera (``CameraFrame``, ``RawFrame``) — on the image as displayed: the linear signal clipped to [0, 1], sRGB-encoded,
grey = Rec. 601 luma (raw Bayer: the mean of each 2×2 CFA cell). Frames are first reduced by an integer factor
``metric_scale = max(1, round(min(H, W) / 256))`` with a box filter, as Wang et al.'s reference SSIM code does, so the
metrics describe the image at a ≈ 256-px viewing scale (and cost ≈ 1 % of a full-HD augment); 484×366 and smaller are
measured at full resolution.

- ``psnr_db``: 10·log10(1 / MSE) over the colour channels (code values 0–1); ``inf`` when identical.
- ``ssim``: mean SSIM of the grey images (Wang et al. 2004, IEEE TIP 13(4), Eq. 13: 11×11 Gaussian window σ = 1.5,
  K1 = 0.01, K2 = 0.03, L = 1), averaged over the pixels whose window lies inside the image.
- ``rms_contrast_in/out``: RMS contrast, the standard deviation of the grey values (Peli 1990, JOSA A 7(10)).
- ``edge_density_in/out``: fraction of pixels on a Canny edge of the 8-bit grey image (thresholds 50/150, L2).
- ``mean_level_in/out``: mean grey value (0–1).
- with depth: ``depth_bin_edges_m`` and ``rms_contrast_per_depth_bin_in/out`` (None for a bin with < 64 pixels;
  the last bin includes the sky, depth ``inf``).

LiDAR and radar (``PointCloud``) — returns are points with a non-zero position (a grid's no-return cells are not).
The per-point effect code (``effect_codes``: KEPT, ATTENUATED, MOVED, ADDED of ``types.PointLabel``) says what
happened to each output point; a point without one is KEPT.

- ``points_in/out``: returns; ``kept``: returns of ``after`` still KEPT.
- ``attenuated``, ``moved``, ``added``: net change in the number of returns with that code (for a whole chain on
  clear input: the counts); ``removed``: returns of ``before`` that are not in ``after`` (non-ADDED returns before
  minus after).
- ``max_range_m_in/out``: farthest return; ``points_per_10m_in/out``: returns per 10 m range bin from 0 m.
- LiDAR ``mean_intensity_in/out`` over the returns and ``mean_intensity_change``, the mean change of the returns
  that stayed in place (:func:`correspondence`), in the file's intensity unit (``intensity_unit``); radar the same
  for the SNR: ``mean_snr_in_db``, ``mean_snr_out_db``, ``mean_snr_change_db``.
- ``objects`` (when the cloud has per-point object ids, :func:`object_ids`): per object id, ``[points_in,
  points_out]`` of its non-ADDED returns.
"""

from __future__ import annotations

import math
import weakref
from typing import Any

import cv2
import numpy as np

from .physics.compiled import jit
from .physics.lidar_geometry import has_return
from .physics.srgb import linear_to_code
from .types import CameraFrame, LidarProfile, PointCloud, PointLabel, RawFrame, SensorData

EFFECT_FIELD = "label"                      # per-point effect code (types.PointLabel); renamed in one place
OBJECT_FIELDS = ("object_id", "ObjIdx")     # per-point object/instance id (CARLA semantic LiDAR: ObjIdx); ≤ 0 = none
RANGE_BIN_M = 10.0
DEPTH_BIN_EDGES_M = (0.0, 10.0, 20.0, 40.0, 80.0, math.inf)
VIEW_SHORT_SIDE_PX = 256                    # Wang et al.: reduce by round(min(H, W) / 256)
MIN_BIN_PX = 64
CANNY_THRESHOLDS = (50, 150)
SSIM_SIGMA_PX, SSIM_RADIUS_PX, SSIM_K1, SSIM_K2 = 1.5, 5, 0.01, 0.03
MAX_OBJECTS = 200                           # the largest objects only, so a manifest line stays small

_summaries: "weakref.WeakKeyDictionary[Any, dict]" = weakref.WeakKeyDictionary()


def effect_codes(cloud: PointCloud) -> np.ndarray | None:
    """The per-point effect code of a cloud (``types.PointLabel`` values), None when no model wrote one."""
    return cloud.fields.get(EFFECT_FIELD)


def object_ids(cloud: PointCloud) -> np.ndarray | None:
    """Per-point object ids (≤ 0: no object) when the cloud has them, else None — the hook for per-object metrics
    (3-D boxes can provide ids through an ``object_id`` field)."""
    for name in OBJECT_FIELDS:
        if name in cloud.fields:
            return np.asarray(cloud.fields[name])
    return None


def compare(before: SensorData, after: SensorData) -> dict[str, Any]:
    """Metrics of ``after`` against ``before`` (the same sensor); see the module doc for names and units."""
    if isinstance(before, PointCloud) and isinstance(after, PointCloud):
        return _compare_clouds(_summary(before), _summary(after))
    if isinstance(before, (CameraFrame, RawFrame)) and isinstance(after, (CameraFrame, RawFrame)):
        return _compare_frames(_summary(before), _summary(after))
    raise TypeError(f"cannot compare {type(before).__name__} with {type(after).__name__}")


def _summary(data: SensorData) -> dict:
    s = _summaries.get(data)
    if s is None:
        s = _cloud_summary(data) if isinstance(data, PointCloud) else _frame_summary(data)
        _summaries[data] = s
    return s


# --- camera -----------------------------------------------------------------------------------------------------


def metric_scale(height_px: int, width_px: int) -> int:
    """Integer reduction factor of the camera metrics (Wang et al.'s ``max(1, round(min(H, W) / 256))``)."""
    return max(1, int(round(min(height_px, width_px) / VIEW_SHORT_SIDE_PX)))


def _reduce(img: np.ndarray, f: int) -> np.ndarray:
    """Box-filter by f×f and decimate (the edge rows/columns that do not fill a block are left out)."""
    if f == 1:
        return img
    h, w = img.shape[0] // f, img.shape[1] // f
    return cv2.resize(img[: h * f, : w * f], (w, h), interpolation=cv2.INTER_AREA)


def _encoded(linear: np.ndarray) -> np.ndarray:
    """sRGB code values 0–1 (float32) of a linear signal, clipped to [0, 1]."""
    return linear_to_code(linear, 16).astype(np.float32) * np.float32(1 / 65535)


def _display(frame: CameraFrame | RawFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, int]:
    """(colour or grey image to compare, grey image, depth at the same pixels or None, reduction factor)."""
    if isinstance(frame, RawFrame):
        s = frame.signal()
        h, w = s.shape[0] // 2 * 2, s.shape[1] // 2 * 2
        cells = cv2.resize(s[:h, :w], (w // 2, h // 2), interpolation=cv2.INTER_AREA)   # mean of each CFA cell
        f = metric_scale(*cells.shape)
        image = grey = _encoded(_reduce(cells, f))
        block = 2 * f
    else:
        f = metric_scale(*frame.shape)
        image = _encoded(_reduce(frame.linear_rgb, f))
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        block = f
    depth = None
    if frame.depth_m is not None:
        c = block // 2
        depth = frame.depth_m[c::block, c::block][: grey.shape[0], : grey.shape[1]]
    return image, grey, depth, f


def _frame_summary(frame: CameraFrame | RawFrame) -> dict:
    image, grey, depth, f = _display(frame)
    edges = cv2.Canny(np.rint(grey * 255).astype(np.uint8), *CANNY_THRESHOLDS, L2gradient=True)
    s = {"image": image, "grey": grey, "scale": f, "rms_contrast": float(grey.std(dtype=np.float64)),
         "edge_density": float(np.count_nonzero(edges)) / edges.size, "mean_level": float(grey.mean(dtype=np.float64))}
    if depth is not None:
        s["depth_contrast"] = rms_contrast_per_depth_bin(grey, depth)
    return s


def rms_contrast_per_depth_bin(grey: np.ndarray, depth_m: np.ndarray,
                               edges_m: tuple[float, ...] = DEPTH_BIN_EDGES_M) -> list[float | None]:
    """RMS contrast of the pixels in each depth bin [e_i, e_i+1) (the last bin includes ``inf``); None for a bin
    with fewer than 64 pixels (or no depth: NaN, negative)."""
    n_bins = len(edges_m) - 1
    depth = np.nan_to_num(np.asarray(depth_m, dtype=np.float64).ravel(), nan=-1.0)
    index = np.searchsorted(np.asarray(edges_m[1:-1]), depth, side="right")
    index[depth < edges_m[0]] = n_bins                                 # no depth: a bin of its own, dropped
    g = grey.astype(np.float64).ravel()
    n = np.bincount(index, minlength=n_bins + 1)[:n_bins]
    s1 = np.bincount(index, g, minlength=n_bins + 1)[:n_bins]
    s2 = np.bincount(index, g * g, minlength=n_bins + 1)[:n_bins]
    mean = s1 / np.maximum(n, 1)
    var = np.maximum(s2 / np.maximum(n, 1) - mean * mean, 0.0)
    return [float(math.sqrt(v)) if k >= MIN_BIN_PX else None for v, k in zip(var, n)]


def psnr_db(a: np.ndarray, b: np.ndarray, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio (dB) of ``b`` against ``a``; ``inf`` when they are identical."""
    d = a.astype(np.float64) - b
    mse = float(np.mean(d * d))
    return math.inf if mse == 0 else 10.0 * math.log10(peak * peak / mse)


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float | None:
    """Mean structural similarity of two grey images (Wang et al. 2004, Eq. 13; Gaussian σ = 1.5, 11×11), over
    the pixels whose window lies inside the image; None if the image is smaller than the window."""
    r = SSIM_RADIUS_PX
    if min(a.shape) <= 2 * r:
        return None
    a = a.astype(np.float32)
    b = b.astype(np.float32)

    def blur(x):
        return cv2.GaussianBlur(x, (2 * r + 1, 2 * r + 1), SSIM_SIGMA_PX)[r:-r, r:-r].astype(np.float64)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a * mu_a
    var_b = blur(b * b) - mu_b * mu_b
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    m = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2))
    return float(m.mean())


def _compare_frames(b: dict, a: dict) -> dict[str, Any]:
    same = b["image"].shape == a["image"].shape
    out: dict[str, Any] = {
        "metric_scale": a["scale"],
        "psnr_db": psnr_db(b["image"], a["image"]) if same else None,
        "ssim": ssim(b["grey"], a["grey"]) if same else None,
    }
    for k in ("rms_contrast", "edge_density", "mean_level"):
        out[f"{k}_in"], out[f"{k}_out"] = b[k], a[k]
    if "depth_contrast" in a:
        out["depth_bin_edges_m"] = list(DEPTH_BIN_EDGES_M)
        out["rms_contrast_per_depth_bin_in"] = b.get("depth_contrast")
        out["rms_contrast_per_depth_bin_out"] = a["depth_contrast"]
    return out


# --- point clouds -------------------------------------------------------------------------------------------------


@jit
def _cloud_pass(positions, codes, values, bin_m, n_bins):       # pragma: no cover - compiled
    """One pass over a cloud: returns, returns per effect code, farthest return, returns per range bin, sum of
    ``values`` over returns (NaN values are skipped: their count is the last element of ``counts``)."""
    counts = np.zeros(6, np.int64)            # returns, KEPT, ATTENUATED, MOVED, ADDED, finite values
    hist = np.zeros(n_bins, np.int64)
    max_r = 0.0
    total = 0.0
    for i in range(positions.shape[0]):
        if not _is_return(positions[i]):
            continue
        x, y, z = positions[i, 0], positions[i, 1], positions[i, 2]
        r = math.sqrt(x * x + y * y + z * z)
        counts[0] += 1
        c = codes[i] if codes.shape[0] else 0
        if 0 <= c <= 3:
            counts[1 + c] += 1
        k = int(r / bin_m)
        hist[min(k, n_bins - 1)] += 1
        if r > max_r:
            max_r = r
        if values.shape[0]:
            v = values[i]
            if np.isfinite(v):
                total += v
                counts[5] += 1
    return counts, hist, max_r, total


def _cloud_summary(cloud: PointCloud) -> dict:
    codes = effect_codes(cloud)
    codes = np.zeros(0, np.int64) if codes is None else np.asarray(codes, dtype=np.int64)
    radar = cloud.sensor == "radar"
    values = cloud.fields.get("snr_db" if radar else "intensity")
    values = np.zeros(0) if values is None or np.ndim(values) != 1 else np.asarray(values, dtype=np.float64)
    positions = np.ascontiguousarray(cloud.positions_m, dtype=np.float64)
    max_range = getattr(cloud.profile, "max_range_m", None) or 300.0
    n_bins = int(math.ceil(max_range / RANGE_BIN_M)) + 2                 # the last bin catches anything farther
    counts, hist, max_r, total = _cloud_pass(positions, codes, values, RANGE_BIN_M, n_bins)
    used = int(np.flatnonzero(hist)[-1]) + 1 if hist.any() else 0
    s = {"returns": int(counts[0]), "codes": [int(c) for c in counts[1:5]], "max_range_m": float(max_r),
         "hist": [int(h) for h in hist[:used]], "radar": radar,
         "mean_value": float(total / counts[5]) if counts[5] else None,
         "positions": positions, "values": values, "effect": codes, "grid": cloud.grid_shape is not None}
    if isinstance(cloud.profile, LidarProfile):
        s["intensity_unit"] = cloud.profile.intensity_unit
    ids = object_ids(cloud)
    if ids is not None:
        s["objects"] = points_per_object(cloud, ids, codes)
    return s


def correspondence(before: PointCloud, after: PointCloud) -> tuple[np.ndarray, np.ndarray]:
    """For each point of ``before``: the index of the same return in ``after`` (−1: removed, or no return), and
    whether it was moved along its ray (True) or stayed in place (False).

    Full grids match cell by cell (moved: effect MOVED). Point lists rely on the models' contract: surviving points
    keep their order and ADDED points are new. When nothing was removed, the i-th point is the i-th survivor;
    otherwise a survivor is found in place when its position is unchanged, or moved when it lies on the same ray,
    and a point whose position changed otherwise (an alignment error in the same step as a removal) counts as
    removed here."""
    b, a = _summary(before), _summary(after)
    return _correspond(b, a)


def _correspond(b: dict, a: dict) -> tuple[np.ndarray, np.ndarray]:
    grid = b["grid"] and a["grid"] and len(b["positions"]) == len(a["positions"])
    effect = a["effect"] if len(a["effect"]) else np.zeros(len(a["positions"]), np.int64)
    return _match(b["positions"], a["positions"], effect, grid)


@jit
def _same_ray(p, q):       # pragma: no cover - compiled
    """Both are returns (non-zero) on the same ray from the sensor: |p × q| ≤ 1e-6 |p||q| and p·q > 0."""
    cx = p[1] * q[2] - p[2] * q[1]
    cy = p[2] * q[0] - p[0] * q[2]
    cz = p[0] * q[1] - p[1] * q[0]
    pp = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    qq = q[0] * q[0] + q[1] * q[1] + q[2] * q[2]
    dot = p[0] * q[0] + p[1] * q[1] + p[2] * q[2]
    return pp > 0 and qq > 0 and dot > 0 and cx * cx + cy * cy + cz * cz <= 1e-12 * pp * qq


@jit
def _match(pb, pa, effect_a, grid):       # pragma: no cover - compiled
    """:func:`correspondence` on positions (and the effect codes of ``after``)."""
    nb, na = pb.shape[0], pa.shape[0]
    index = np.full(nb, -1, np.int64)
    moved = np.zeros(nb, np.bool_)
    survivors = 0
    for j in range(na):
        survivors += effect_a[j] != 3
    if grid:                                   # cell by cell
        for i in range(nb):
            if _is_return(pb[i]) and _is_return(pa[i]):
                index[i] = i
                moved[i] = effect_a[i] == 2
        return index, moved
    j = 0
    for i in range(nb):
        while j < na and effect_a[j] == 3:     # ADDED: new, never a survivor
            j += 1
        if j >= na:
            break
        if survivors == nb:                    # nothing removed: survivors in order (positions may have changed)
            index[i] = j
            moved[i] = effect_a[j] == 2
            j += 1
        elif pb[i, 0] == pa[j, 0] and pb[i, 1] == pa[j, 1] and pb[i, 2] == pa[j, 2] and _is_return(pb[i]):
            index[i] = j
            j += 1
        elif _same_ray(pb[i], pa[j]):
            index[i] = j
            moved[i] = True
            j += 1
    return index, moved


@jit(inline="always")
def _is_return(p):       # pragma: no cover - compiled
    return (p[0] != 0.0 or p[1] != 0.0 or p[2] != 0.0) and np.isfinite(p[0] + p[1] + p[2])


def points_per_object(cloud: PointCloud, ids: np.ndarray, codes: np.ndarray | None = None) -> dict[int, int]:
    """Non-ADDED returns per object id (ids ≤ 0 are no object)."""
    keep = has_return(cloud.positions_m) & (np.asarray(ids) > 0)
    if codes is not None and len(codes):
        keep &= codes != PointLabel.ADDED
    uniq, n = np.unique(np.asarray(ids)[keep], return_counts=True)
    return {int(u): int(c) for u, c in zip(uniq, n)}


def _compare_clouds(b: dict, a: dict) -> dict[str, Any]:
    kept_b, att_b, moved_b, added_b = b["codes"]
    kept_a, att_a, moved_a, added_a = a["codes"]
    n_bins = max(len(b["hist"]), len(a["hist"]))
    out: dict[str, Any] = {
        "points_in": b["returns"], "points_out": a["returns"], "kept": kept_a,
        "attenuated": att_a - att_b, "moved": moved_a - moved_b, "added": added_a - added_b,
        "removed": (b["returns"] - added_b) - (a["returns"] - added_a),
        "max_range_m_in": b["max_range_m"], "max_range_m_out": a["max_range_m"],
        "points_per_10m_in": b["hist"] + [0] * (n_bins - len(b["hist"])),
        "points_per_10m_out": a["hist"] + [0] * (n_bins - len(a["hist"])),
    }
    vb, va = b["mean_value"], a["mean_value"]
    change = None
    if len(b["values"]) and len(a["values"]):
        index, moved = _correspond(b, a)
        stay = (index >= 0) & ~moved
        if stay.any():
            change = float(np.mean(a["values"][index[stay]] - b["values"][stay]))
    if a["radar"]:
        out.update(mean_snr_in_db=vb, mean_snr_out_db=va, mean_snr_change_db=change)
    else:
        out.update(mean_intensity_in=vb, mean_intensity_out=va, mean_intensity_change=change,
                   intensity_unit=a.get("intensity_unit"))
    if "objects" in a or "objects" in b:
        ob, oa = b.get("objects", {}), a.get("objects", {})
        largest = sorted(set(ob) | set(oa), key=lambda k: -ob.get(k, 0))[:MAX_OBJECTS]
        out["objects"] = {str(k): [ob.get(k, 0), oa.get(k, 0)] for k in sorted(largest)}
    return out
