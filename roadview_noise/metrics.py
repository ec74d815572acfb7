"""What a noise chain did to a frame or a cloud: the per-step and per-output metrics of the manifest (issue 18).

``compare(before, after)`` returns a flat JSON-able dict; ``compound.apply_models`` stores it per step
(``steps[i].metrics``: the step's input against its output) and the runner per output (``metrics``: the chain's
input against the written output). Pure NumPy/OpenCV plus compiled passes over clouds; no I/O. Each data object is
summarised once (cached while it lives; a step that returns the same pixels shares its input's summary), so a
chain of n steps costs at most n + 1 summaries and n + 1 comparisons; positions and depth maps that steps hand on
unchanged are binned once. A run's radar chain is compared without summaries, in one compiled call at its end
(:class:`Deferred`, :func:`_radar_chain_pass`).

Camera (``CameraFrame``, ``RawFrame``) — on the grey image as displayed: relative luminance Y = 0.2126 R +
0.7152 G + 0.0722 B of the linear signal (raw Bayer: the mean of each 2×2 CFA cell), clipped to [0, 1] and
sRGB-encoded (IEC 61966-2-1). Frames are first reduced with a box filter by the smallest integer factor
``metric_scale`` that leaves at most 65 536 pixels — the ≈ 256-px scale at which Wang et al.'s reference code
evaluates SSIM — so a metric describes the image at that viewing scale and costs about the same at any resolution.
The reduced luminance comes from :mod:`roadview_noise.luminance`: in a run, the 8-bit sRGB decode of the input and
the encodes of the JPEG step and the writer take it in their pass (:class:`Deferred`), else a read of its own.

- ``psnr_db``: 10·log10(1 / MSE) of the grey images (0–1); ``inf`` when identical.
- ``ssim``: mean SSIM of the grey images (Wang et al. 2004, IEEE TIP 13(4), Eq. 13: 11×11 Gaussian window σ = 1.5,
  K1 = 0.01, K2 = 0.03, L = 1), averaged over the pixels whose window lies inside the image (float32 local means,
  one compiled separable pass per image and one per comparison).
- ``rms_contrast_in/out``: RMS contrast, the standard deviation of the grey values (Peli 1990, JOSA A 7(10)).
- ``edge_density_in/out``: fraction of pixels whose grey gradient (3×3 Sobel / 8, per pixel) is ≥ 0.025, so a step
  of the 5 % visibility contrast (CIE; Hautière et al. 2006) marks the two pixels beside it.
- ``mean_level_in/out``: mean grey value (0–1).
- with depth: ``depth_bin_edges_m`` and ``rms_contrast_per_depth_bin_in/out`` (None for a bin with < 64 pixels;
  the last bin includes the sky, depth ``inf``).

LiDAR and radar (``PointCloud``) — returns are points with a non-zero position (a grid's no-return cells are not).
The per-point effect code (``effect_codes``: KEPT, ATTENUATED, MOVED, ADDED of :data:`Effect`) says what
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

import dataclasses
import math
import weakref
from typing import Any

import cv2
import numpy as np

from .luminance import blocks_of, codes_luminance_area, luminance_area, metric_scale, want
from .physics.compiled import jit
from .physics import return_ranges
from .physics.lidar_geometry import has_return
from .physics.return_ranges import RANGE_BIN_M
from .physics.srgb import _code16, encode16_table
from .provenance import Effect
from .types import CameraFrame, LidarProfile, PointCloud, RawFrame, SensorData

OBJECT_FIELDS = ("object_id", "ObjIdx")     # per-point object/instance id (CARLA semantic LiDAR: ObjIdx); ≤ 0 = none
DEPTH_BIN_EDGES_M = (0.0, 10.0, 20.0, 40.0, 80.0, math.inf)
MIN_BIN_PX = 64
EDGE_GRADIENT_PER_PX = 0.025                # half of a 5 % step (a step's Sobel/8 on each side is half the step)
SSIM_SIGMA_PX, SSIM_RADIUS_PX, SSIM_K1, SSIM_K2 = 1.5, 5, 0.01, 0.03
MAX_OBJECTS = 200                           # the largest objects only, so a manifest line stays small

_summaries: "weakref.WeakKeyDictionary[Any, dict]" = weakref.WeakKeyDictionary()


def effect_codes(cloud: PointCloud) -> np.ndarray | None:
    """The per-point effect code of a cloud (:class:`provenance.Effect` values), None when no model wrote one."""
    return cloud.effect


def with_effect_codes(cloud: PointCloud, codes: np.ndarray) -> PointCloud:
    """The cloud with these per-point effect codes (the other side of :func:`effect_codes`, for synthetic data)."""
    return dataclasses.replace(cloud, effect=np.asarray(codes, np.uint8))


def object_ids(cloud: PointCloud) -> np.ndarray | None:
    """Per-point object ids (≤ 0: no object) when the cloud has them, else None — the hook for per-object metrics
    (3-D boxes can provide ids through an ``object_id`` field)."""
    for name in OBJECT_FIELDS:
        if name in cloud.fields:
            return np.asarray(cloud.fields[name])
    return None


def compare(before: SensorData, after: SensorData, step: SensorData | None = None,
            linked: bool = True) -> dict[str, Any]:
    """Metrics of ``after`` against ``before`` (the same sensor); see the module doc for names and units.

    ``step``: for clouds, the chain step's own output of which ``after`` is ``provenance.follow(before, step)``
    — its step-relative ``origin`` and ``effect`` tell which point of ``before`` each point of ``after`` is, so
    :func:`correspondence` reads them instead of matching positions (the same result on clouds that keep the
    models' contract; see :func:`_pass`). ``linked=False``: no later comparison is expected to read this step's
    correspondence (a chain of one step), so a pass that would write it does not (:func:`_link` makes it if
    asked)."""
    if isinstance(before, PointCloud) and isinstance(after, PointCloud):
        fn = _compare_clouds
    elif isinstance(before, (CameraFrame, RawFrame)) and isinstance(after, (CameraFrame, RawFrame)):
        fn = _compare_frames
        if after not in _summaries and _pixels(after) is _pixels(before) and after.depth_m is before.depth_m:
            _summaries[after] = _summary(before)          # the step changed no pixel (wind: conditions only)
    else:
        raise TypeError(f"cannot compare {type(before).__name__} with {type(after).__name__}")
    b = _summary(before)
    a = _summary(after, b, step if isinstance(step, PointCloud) else None, linked)
    done = a.setdefault("compared", {})                 # (before summary, result) by id: a chain whose step left
    if id(b) not in done:                               # the pixels alone compares input and output once
        done[id(b)] = (b, fn(b, a))
    return dict(done[id(b)][1])


class Deferred:
    """:func:`compare` calls whose results are filled in later, by :meth:`settle`: by then a camera frame may have
    gone through an 8-bit sRGB pass that kept its luminance blocks (:func:`luminance.collect`: the next step's JPEG
    encode, the writer's encode), so its summary reads no full frame of its own. With ``radar_chains`` a radar
    chain's comparisons (each step's, the output's) are held to the chain's end too and made together in one
    compiled call over its clouds (:func:`_compare_radar_chain`; a radar file's metrics are Python and call
    overhead, not arithmetic); the clouds are then not summarised, so a later :func:`compare` or
    :func:`correspondence` of them would link the output to the input by position, not through the steps (on in
    the runner, which compares nothing after the chain; off for callers that do: preview, bags).
    The results are :func:`compare`'s, computed in the order of the calls; other data (raw frames, LiDAR clouds)
    is compared at once."""

    def __init__(self, radar_chains: bool = False) -> None:
        self._calls: list[tuple[SensorData, SensorData, dict]] = []
        self._radar: list[tuple[PointCloud, PointCloud, SensorData | None, dict]] | None = [] if radar_chains \
            else None

    def compare(self, before: SensorData, after: SensorData, step: SensorData | None = None,
                linked: bool = True) -> dict[str, Any]:
        """An empty dict that :meth:`settle` fills with ``compare(before, after)`` (at once unless a frame or a
        held radar chain's, then with ``step`` and ``linked``: :func:`compare`)."""
        if self._radar is not None and isinstance(after, PointCloud) and after.sensor == "radar" and \
                isinstance(before, PointCloud):
            result: dict[str, Any] = {}
            self._radar.append((before, after, step, result))
            return result
        if not isinstance(after, CameraFrame):
            self.settle()
            return compare(before, after, step, linked)
        for frame in (before, after):
            if isinstance(frame, CameraFrame) and frame.undecoded_srgb8_codes() is None:   # not a JPEG output's
                want(frame.linear_rgb)
        result = {}
        self._calls.append((before, after, result))
        return result

    def settle(self, keep: SensorData | None = None) -> None:
        """Fill the dicts of the calls made so far, in order, up to the first whose ``after`` is ``keep`` (data that
        a later pass may still go through); a held radar chain's when no ``keep`` is given (the chain's end)."""
        calls, self._calls = self._calls, []
        for i, (before, after, result) in enumerate(calls):
            if after is keep:
                self._calls = calls[i:]
                return
            result.update(compare(before, after))
        if keep is None and self._radar:
            self.settle_clouds()

    def settle_clouds(self) -> None:
        """Fill the dicts of a held radar chain's calls now (the chain has ended: no later pass goes through a
        cloud, so a run need not wait for its writer)."""
        if self._radar:
            radar, self._radar = self._radar, []
            _compare_radar_chain(radar)


def _summary(data: SensorData, before: dict | None = None, step: PointCloud | None = None,
             linked: bool = True) -> dict:
    """The summary of ``data`` (cached); a cloud's first one is linked to ``before``, its step input's, when given
    (:func:`_cloud_summary`)."""
    s = _summaries.get(data)
    if s is None:
        s = _cloud_summary(data, before, step, linked) if isinstance(data, PointCloud) else _frame_summary(data)
        _summaries[data] = s
    return s


# --- camera -----------------------------------------------------------------------------------------------------


def _pixels(frame: CameraFrame | RawFrame) -> np.ndarray:
    """The array that holds the frame's pixels (not decoding held sRGB codes)."""
    if isinstance(frame, RawFrame):
        return frame.dn
    codes = frame.undecoded_srgb8_codes()
    return frame.linear_rgb if codes is None else codes


def _reduce(img: np.ndarray, f: int) -> np.ndarray:
    """Box-filter by f×f and decimate (the edge rows/columns that do not fill a block are left out)."""
    if f == 1:
        return img
    h, w = img.shape[0] // f, img.shape[1] // f
    return cv2.resize(img[: h * f, : w * f], (w, h), interpolation=cv2.INTER_AREA)


def _grey(frame: CameraFrame | RawFrame) -> tuple[np.ndarray, np.ndarray | None, int]:
    """(sRGB-encoded grey image 0–1 float32 at the metric scale, depth at the same pixels or None, factor)."""
    if isinstance(frame, RawFrame):
        h, w = frame.shape[0] // 2 * 2, frame.shape[1] // 2 * 2
        f = metric_scale(h // 2, w // 2)
        cells = _reduce(frame.dn[:h, :w], 2 * f)                       # mean DN of whole CFA cells: the signal
        y = dataclasses.replace(frame, dn=cells).signal()               # is affine in DN, so reduce first
        block = 2 * f
    else:
        f = metric_scale(*frame.shape)
        codes = frame.undecoded_srgb8_codes()             # a JPEG output: its codes, not a decode of them
        if codes is not None:
            y = codes_luminance_area(codes, f)
        else:                                             # kept by an sRGB pass over the frame, else read here
            y = blocks_of(frame.linear_rgb, f)
            y = luminance_area(frame.linear_rgb, f) if y is None else y
        block = f
    grey = np.empty(y.shape, np.float32)
    _grey_codes(np.ascontiguousarray(y, dtype=np.float32).reshape(-1).view(np.uint32), *encode16_table(),
                grey.reshape(-1))
    depth = None
    if frame.depth_m is not None:
        c = block // 2
        depth = frame.depth_m[c::block, c::block][: grey.shape[0], : grey.shape[1]]
    return grey, depth, f


@jit
def _grey_codes(ybits, first, code, nxt_bits, out):                     # pragma: no cover - compiled
    """``out`` = the 16-bit sRGB codes of the luminance values whose float32 bit patterns are ``ybits``, scaled to
    0–1 (``srgb.linear_to_code(y, 16)`` as float32 × (1 / 65535), in one pass)."""
    scale = np.float32(1 / 65535)
    for i in range(ybits.size):
        out[i] = np.float32(_code16(ybits[i], first, code, nxt_bits)) * scale


def _frame_summary(frame: CameraFrame | RawFrame) -> dict:
    grey, depth, f = _grey(frame)
    n_bins = len(DEPTH_BIN_EDGES_M) - 1
    bins = np.zeros((0, 0), np.int8)
    if depth is not None:                   # the steps share the depth map: its bins are found once
        bins = _per_array(_last_depth, frame.depth_m, depth, DEPTH_BIN_EDGES_M,
                          lambda: _depth_bin_index(np.asarray(depth, np.float32), np.asarray(DEPTH_BIN_EDGES_M)))
    total, squares, edges, per_bin = _grey_statistics(grey, _edge_limit(), bins, n_bins)
    mean = total / grey.size
    s = {"grey": grey, "scale": f, "rms_contrast": math.sqrt(max(squares / grey.size - mean * mean, 0.0)),
         "edge_density": edges / grey.size, "mean_level": mean, "ssim_moments": _ssim_moments(grey)}
    if depth is not None:
        s["depth_contrast"] = _contrast_of_sums(*per_bin)
    return s


@jit
def _grey_statistics(grey, limit, bins, n_bins):               # pragma: no cover - compiled
    """One pass over a grey image (float32, ≥ 1×1): the sum and the sum of squares of its values (float64), the
    number of pixels whose squared 3×3 Sobel gradient is ≥ ``limit`` (:func:`edge_density`: replicated borders,
    OpenCV's separable-filter order of float32 operations; a gradient within float32 rounding of the threshold
    may be counted differently), and with ``bins`` (the pixels' depth bin, −1 none; empty: no bins) the count,
    sum and sum of squares per bin (pixels of bin −1 are left out)."""
    h, w = grey.shape
    with_bins = bins.shape[0] == h and bins.shape[1] == w
    n, bin_total, bin_squares = np.zeros(n_bins, np.int64), np.zeros(n_bins), np.zeros(n_bins)
    total, squares, edges = 0.0, 0.0, 0
    two = np.float32(2.0)
    for i in range(h):
        up, down = grey[max(i - 1, 0)], grey[min(i + 1, h - 1)]
        row = grey[i]
        for j in range(w):
            left, right = max(j - 1, 0), min(j + 1, w - 1)
            gx = two * (row[right] - row[left]) + ((up[right] - up[left]) + (down[right] - down[left]))
            above = two * up[j] + (up[left] + up[right])
            below = two * down[j] + (down[left] + down[right])
            gy = below - above
            if gx * gx + gy * gy >= limit:
                edges += 1
            g = np.float64(row[j])
            total += g
            squares += g * g
            if with_bins:
                b = bins[i, j]
                if b >= 0:
                    n[b] += 1
                    bin_total[b] += g
                    bin_squares[b] += g * g
    return total, squares, edges, (n, bin_total, bin_squares)


_last_depth: list = [None, None, None]      # weakref to a depth map, the key of its view (_per_array), bin index


def _per_array(slot: list, owner: np.ndarray, view: np.ndarray, extra, compute):
    """``compute()``, or the result kept in ``slot`` when the last call had the same ``owner`` array (identity)
    and the same ``view`` of it (shape, strides, address — not read for the owner itself, whose data cannot move
    while its shape stays: ``ctypes.data`` costs µs) and ``extra``: what the steps of a chain that hand an array
    on unchanged need to derive from it once."""
    ref, key, result = slot
    now = (view.shape, view.strides, None if view is owner else view.ctypes.data, extra)
    if ref is not None and ref() is owner and key == now:
        return result
    result = compute()
    slot[:] = [weakref.ref(owner), now, result]
    return result


def edge_density(grey: np.ndarray) -> float:
    """Fraction of pixels whose gradient (3×3 Sobel / 8, grey levels per pixel) is ≥ ``EDGE_GRADIENT_PER_PX``."""
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, borderType=cv2.BORDER_REPLICATE)
    return float(np.count_nonzero(gx * gx + gy * gy >= _edge_limit())) / grey.size


def _edge_limit() -> np.float32:
    """The squared Sobel gradient of :func:`edge_density`'s threshold (a float32 step of exactly 5 % counts)."""
    return np.float32((8 * EDGE_GRADIENT_PER_PX) ** 2) * np.float32(1 - 1e-6)


def rms_contrast_per_depth_bin(grey: np.ndarray, depth_m: np.ndarray,
                               edges_m: tuple[float, ...] = DEPTH_BIN_EDGES_M) -> list[float | None]:
    """RMS contrast of the pixels in each depth bin [e_i, e_i+1) (the last bin includes ``inf``); None for a bin
    with fewer than 64 pixels (or no depth: NaN, negative)."""
    bins = _depth_bin_index(np.asarray(depth_m, np.float32), np.asarray(edges_m, np.float64))
    return _contrast_per_bin(grey, bins, len(edges_m) - 1)


def _contrast_per_bin(grey: np.ndarray, bins: np.ndarray, n_bins: int) -> list[float | None]:
    """:func:`rms_contrast_per_depth_bin` from the pixels' bin index (:func:`_depth_bin_index`)."""
    return _contrast_of_sums(*_grey_statistics(np.asarray(grey, np.float32), _edge_limit(), bins, n_bins)[3])


def _contrast_of_sums(n: np.ndarray, total: np.ndarray, squares: np.ndarray) -> list[float | None]:
    """RMS contrast per bin from its pixel count, sum and sum of squares (None below ``MIN_BIN_PX`` pixels)."""
    return [math.sqrt(max(q / k - (t / k) ** 2, 0.0)) if k >= MIN_BIN_PX else None
            for k, t, q in zip(n.tolist(), total.tolist(), squares.tolist())]


@jit
def _depth_bin_index(depth, edges):                        # pragma: no cover - compiled
    """Per pixel: its depth bin of ``edges`` (the last one open above), −1 without depth (NaN, negative)."""
    bins = edges.size - 1
    index = np.empty(depth.shape, np.int8)
    for i in range(depth.shape[0]):
        for j in range(depth.shape[1]):
            d = depth[i, j]
            b = bins - 1
            while b > 0 and d < edges[b]:
                b -= 1
            index[i, j] = b if d >= edges[0] else -1
    return index


def psnr_db(a: np.ndarray, b: np.ndarray, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio (dB) of ``b`` against ``a``; ``inf`` when they are identical."""
    mse = cv2.norm(np.asarray(a, np.float32), np.asarray(b, np.float32), cv2.NORM_L2SQR) / np.size(a)
    return math.inf if mse == 0 else 10.0 * math.log10(peak * peak / mse)


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float | None:
    """Mean structural similarity of two grey images (Wang et al. 2004, Eq. 13; Gaussian σ = 1.5, 11×11), over
    the pixels whose window lies inside the image; None if the image is smaller than the window."""
    return _ssim(a, b, _ssim_moments(a), _ssim_moments(b), data_range)


def _ssim_moments(x: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Local mean μ and local mean of the square of a grey image over the SSIM window (window inside the image);
    a frame's are computed once (its summary) for all comparisons it is part of."""
    if min(x.shape) <= 2 * SSIM_RADIUS_PX:
        return None
    x = np.ascontiguousarray(x, np.float32)
    shape = (x.shape[0] - 2 * SSIM_RADIUS_PX, x.shape[1] - 2 * SSIM_RADIUS_PX)
    mu, mean_square = np.empty(shape, np.float32), np.empty(shape, np.float32)
    _ssim_local_means(x, _SSIM_WINDOW, mu, mean_square)
    return mu, mean_square


def _ssim(a: np.ndarray, b: np.ndarray, moments_a, moments_b, data_range: float = 1.0) -> float | None:
    """:func:`ssim` from the images and their :func:`_ssim_moments`."""
    if moments_a is None or moments_b is None:
        return None
    c1, c2 = np.float32((SSIM_K1 * data_range) ** 2), np.float32((SSIM_K2 * data_range) ** 2)
    return float(_ssim_map(np.ascontiguousarray(a, np.float32), np.ascontiguousarray(b, np.float32),
                           _SSIM_WINDOW, *moments_a, *moments_b, c1, c2))


def _ssim_window() -> np.ndarray:
    """The normalised 1-D Gaussian of the SSIM window (float32; 2 r + 1 taps, σ = ``SSIM_SIGMA_PX``; the 2-D window
    is its outer product, as OpenCV's ``getGaussianKernel``)."""
    x = np.arange(-SSIM_RADIUS_PX, SSIM_RADIUS_PX + 1, dtype=np.float64)
    w = np.exp(-x * x / (2 * SSIM_SIGMA_PX ** 2))
    return (w / w.sum()).astype(np.float32)


_SSIM_WINDOW = _ssim_window()


@jit(inline="always")
def _window_sum(w, x0, x1, x2, x3, x4, x5, x6, x7, x8, x9, x10):       # pragma: no cover - compiled
    """Σ_k w[k] x_k for the symmetric 11-tap window ``w`` (``SSIM_RADIUS_PX`` = 5; float32, the pairs of equal
    weight added first)."""
    return (((((w[0] * (x0 + x10) + w[1] * (x1 + x9)) + w[2] * (x2 + x8)) + w[3] * (x3 + x7))
             + w[4] * (x4 + x6)) + w[5] * x5)


@jit
def _filter_row(src, window, out):                  # pragma: no cover - compiled
    """out[j] = :func:`_window_sum` of src[j … j + 10] (the taps in registers: vectorised over j)."""
    for j in range(out.shape[0]):
        out[j] = _window_sum(window, src[j], src[j + 1], src[j + 2], src[j + 3], src[j + 4], src[j + 5],
                             src[j + 6], src[j + 7], src[j + 8], src[j + 9], src[j + 10])


@jit
def _filter_column(rows, i, window, out):           # pragma: no cover - compiled
    """out[j] = :func:`_window_sum` of rows[i … i + 10, j]."""
    r0, r1, r2, r3, r4, r5 = rows[i], rows[i + 1], rows[i + 2], rows[i + 3], rows[i + 4], rows[i + 5]
    r6, r7, r8, r9, r10 = rows[i + 6], rows[i + 7], rows[i + 8], rows[i + 9], rows[i + 10]
    for j in range(out.shape[0]):
        out[j] = _window_sum(window, r0[j], r1[j], r2[j], r3[j], r4[j], r5[j], r6[j], r7[j], r8[j], r9[j], r10[j])


@jit
def _ssim_local_means(x, window, mu, mean_square):       # pragma: no cover - compiled
    """``mu``, ``mean_square`` = the Gaussian-window means of x and x² over the windows inside x (separable:
    :func:`_filter_row` then :func:`_filter_column`, float32)."""
    n = x.shape[1]
    rows, rows_sq = np.empty((x.shape[0], mu.shape[1]), np.float32), np.empty((x.shape[0], mu.shape[1]), np.float32)
    square = np.empty(n, np.float32)
    for i in range(x.shape[0]):
        row = x[i]
        for j in range(n):
            square[j] = row[j] * row[j]
        _filter_row(row, window, rows[i])
        _filter_row(square, window, rows_sq[i])
    for i in range(mu.shape[0]):
        _filter_column(rows, i, window, mu[i])
        _filter_column(rows_sq, i, window, mean_square[i])


@jit(error_model="numpy")
def _ssim_map(a, b, window, mu_a, mean_aa, mu_b, mean_bb, c1, c2):       # pragma: no cover - compiled
    """The mean of Wang et al.'s Eq. 13 over the windows inside the images (float32 per pixel, summed in float64)
    from the local means of a, a², b, b² (:func:`_ssim_local_means`) and of ab, filtered here the same way (so
    ab = a² when a is b: SSIM 1 exactly); variances and covariance: local mean of the product − product of the
    means."""
    n = a.shape[1]
    width = mu_a.shape[1]
    rows, product = np.empty((a.shape[0], width), np.float32), np.empty(n, np.float32)
    for i in range(a.shape[0]):
        for j in range(n):
            product[j] = a[i, j] * b[i, j]
        _filter_row(product, window, rows[i])
    mean_ab, value, total = np.empty(width, np.float32), np.empty(width, np.float32), np.zeros(width)
    two = np.float32(2.0)
    for i in range(mu_a.shape[0]):
        _filter_column(rows, i, window, mean_ab)
        ma, mb, aa, bb = mu_a[i], mu_b[i], mean_aa[i], mean_bb[i]
        for j in range(width):
            mu_aa, mu_bb, mu_ab = ma[j] * ma[j], mb[j] * mb[j], ma[j] * mb[j]
            num = (two * mu_ab + c1) * (two * (mean_ab[j] - mu_ab) + c2)
            den = (mu_aa + mu_bb + c1) * ((aa[j] - mu_aa) + (bb[j] - mu_bb) + c2)
            value[j] = num / den
        for j in range(width):
            total[j] += value[j]
    mean = 0.0                      # total.sum() in its order, without numba.np.arraymath's import (see warmup)
    for j in range(width):
        mean += total[j]
    return mean / mu_a.size


def _compare_frames(b: dict, a: dict) -> dict[str, Any]:
    same = b["grey"].shape == a["grey"].shape
    identical = a is b
    out: dict[str, Any] = {
        "metric_scale": a["scale"],
        "psnr_db": math.inf if identical else (psnr_db(b["grey"], a["grey"]) if same else None),
        "ssim": 1.0 if identical else (_ssim(b["grey"], a["grey"], b["ssim_moments"], a["ssim_moments"]) if same
                                       else None),
    }
    for k in ("rms_contrast", "edge_density", "mean_level"):
        out[f"{k}_in"], out[f"{k}_out"] = b[k], a[k]
    if "depth_contrast" in a:
        out["depth_bin_edges_m"] = list(DEPTH_BIN_EDGES_M)
        out["rms_contrast_per_depth_bin_in"] = b.get("depth_contrast")
        out["rms_contrast_per_depth_bin_out"] = a["depth_contrast"]
    return out


# --- point clouds -------------------------------------------------------------------------------------------------


NO_LINK, GRID_LINK, LIST_LINK, STEP_LINK, SAME_LINK = 0, 1, 2, 3, 4   # _cloud_pass: no correspondence, cell
#                       by cell, in list order, by the step's provenance, point i is point i (:func:`_same_points`)
_NO_STEP = (np.zeros(0, np.int64), np.zeros(0, np.uint8))
_NO_CODES, _NO_VALUES = np.zeros(0, np.uint8), np.zeros(0)     # a cloud without effect codes, without values
_NO_INDEX, _NO_MASK = np.zeros(0, np.int32), np.zeros(0, np.bool_)
_NOT_LINKED = (_NO_INDEX, _NO_MASK, math.nan)                   # a NO_LINK pass's correspondence


def _cloud_pass(positions, known_valid, codes, values, bin_m, n_bins, link, pb, valid_b, values_b, step=_NO_STEP,
                linked=True):
    """:func:`_pass` compiled for this ``link`` and for the returns known or not (constants there, so each variant's
    loop holds only its own branches: one with the returns known keeps none of the geometry's live values, and
    spills fewer of its own); ``linked=False``: a STEP_LINK pass over known returns writes no correspondence
    (:func:`_unlinked_step_pass`)."""
    counted = len(known_valid) == len(positions) and len(positions) > 0
    fn = _unlinked_step_pass if not linked and counted and link == STEP_LINK else _PASSES[link, counted]
    return fn(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b, step)


@jit(inline="always")
def _pass(positions, known_valid, codes, values, bin_m, n_bins, link, known, pb, valid_b, values_b,
          step):  # pragma: no cover
    """One pass over a cloud (``after``): which points are returns, how many, the farthest return's range,
    returns per range bin — or, when ``known`` (``known_valid``, as many as the points, says which are returns),
    none of these — and over the returns the counts per effect code (KEPT, ATTENUATED, MOVED, ADDED; none given: all
    KEPT) and the sum and count of the finite ``values`` (NaN values are skipped;
    :func:`return_ranges.add_return_sums`, after).

    With ``link`` (GRID_LINK, LIST_LINK, STEP_LINK, SAME_LINK), in the same pass: :func:`correspondence` of the
    points of ``before`` (positions ``pb``, returns ``valid_b``) with this cloud's — for each point of ``before`` the
    index of its return here (−1: none) and whether it moved along its ray — and the mean change from ``values_b``
    to ``values`` of the points that stayed in place (NaN if none). A list is walked in order (surviving points keep
    their order, ADDED points are new); ``before``'s positions are read only to tell its removed points. With
    STEP_LINK, ``step`` (the step's own origin and effect codes, :mod:`~roadview_noise.provenance`; empty: the
    identity, KEPT) says where each point comes from: the walk's result without walking, ``before``'s positions
    read only where the step moved a point (a MOVED return at its old position stayed in place). With SAME_LINK
    (:func:`_same_points`: point i of ``before`` is point i here, none moved) the correspondence is known and not
    written (``index`` and ``moved`` come back empty): only the mean change is taken, over every point, or with
    ``valid_b`` (a grid) over the cells that are returns in both."""
    n = positions.shape[0]
    valid = known_valid if known else np.empty(n, np.bool_)
    hist = np.zeros(n_bins, np.int64)
    has_codes, has_values = codes.shape[0] > 0, values.shape[0] > 0
    inv_bin, top = 1.0 / bin_m, n_bins - 1
    returns, max_r2 = 0, 0.0
    nb = pb.shape[0] if link != NO_LINK and link != SAME_LINK else 0
    masked = link == SAME_LINK and valid_b.shape[0] > 0
    index = np.full(nb, -1, np.int32)
    moved = np.zeros(nb, np.bool_)
    changes = has_values and values_b.shape[0] > 0
    step_origin, step_codes = step
    has_origin, has_step_codes = step_origin.shape[0] > 0, step_codes.shape[0] > 0
    in_order = True                         # a list without removals: its i-th survivor is before's i-th point
    if link == LIST_LINK or link == STEP_LINK:
        survivors = n
        if known:
            for j in range(n if has_codes else 0):      # branch-free: vectorised
                survivors -= (codes[j] == 3) & valid[j]
        else:
            for j in range(n if has_codes else 0):
                if codes[j] == 3 and _is_return(positions, j):
                    survivors -= 1
        in_order = survivors == nb
    change, changed, i = 0.0, 0, 0
    for j in range(n):
        c = codes[j] if has_codes else 0
        found, away = False, False          # the point of before it is (index i), moved along its ray
        if link == GRID_LINK:
            i, found, away = j, True, c == 2
        elif link == LIST_LINK and c != 3 and i < nb:   # ADDED: new, never a survivor
            found, away = True, c == 2
            if not in_order:
                while i < nb:
                    if _same_position(pb, i, positions, j) and valid_b[i]:
                        away = False
                        break
                    if _same_ray(pb, i, positions, j):
                        away = True
                        break
                    i += 1                  # before's point i was removed
                found = i < nb
        elif link == SAME_LINK:
            i, found = j, True
        elif link == STEP_LINK and c != 3:
            i = step_origin[j] if has_origin else j
            found = i >= 0
            if in_order:
                away = c == 2
            else:                           # moved by the step, unless to where it was
                away = found and has_step_codes and step_codes[j] == 2 and not (
                    _same_position(pb, np.uint64(i), positions, j) and valid_b[np.uint64(i)])
        if known:
            ok = valid[j]
        else:
            x, y, z = positions[j, 0], positions[j, 1], positions[j, 2]
            r2 = x * x + y * y + z * z
            ok = r2 > 0.0 and r2 < np.inf
            valid[j] = ok
            if ok:
                returns += 1
                max_r2 = max(max_r2, r2)
                b = math.sqrt(r2) * inv_bin
                hist[np.int64(b) if b < top else top] += 1
        if not found or ((link == GRID_LINK or masked) and not (ok and valid_b[j])):
            continue
        k = np.uint64(i)                    # ≥ 0 here: indexed without the wrap-around test
        if link != SAME_LINK:
            index[k] = j
            moved[k] = away
        if changes and not away:
            change, changed = _add_change(values_b, k, values, j, change, changed)
        i += 1
    sums = return_ranges.add_return_sums(valid, codes, values, 0, n,    # a loop of their own: the link's holds
                                         return_ranges.NO_SUMS)        # fewer values
    used = n_bins                           # the bins up to the farthest return's
    while used > 0 and hist[used - 1] == 0:
        used -= 1
    return ((returns, hist[:used], math.sqrt(max_r2), valid), np.array(sums[:4], np.int64), sums[4], sums[5],
            (index, moved, change / changed if changed else np.nan))


@jit
def _plain_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
                step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, NO_LINK, False, pb, valid_b, values_b, step)


@jit
def _counted_plain_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
                        step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, NO_LINK, True, pb, valid_b, values_b, step)


@jit
def _grid_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
               step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, GRID_LINK, False, pb, valid_b, values_b, step)


@jit
def _counted_grid_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
                       step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, GRID_LINK, True, pb, valid_b, values_b, step)


@jit
def _list_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
               step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, LIST_LINK, False, pb, valid_b, values_b, step)


@jit
def _counted_list_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
                       step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, LIST_LINK, True, pb, valid_b, values_b, step)


@jit
def _step_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
               step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, STEP_LINK, False, pb, valid_b, values_b, step)


@jit
def _counted_step_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
                       step):  # pragma: no cover
    """:func:`_pass` with STEP_LINK and the returns known (a weather step's output: its model counted them), in a
    loop of its own (:func:`_known_step_pass`)."""
    return _known_step_pass(positions, known_valid, codes, values, pb, valid_b, values_b, step, True)


@jit
def _unlinked_step_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
                        step):  # pragma: no cover
    """:func:`_counted_step_pass` without the correspondence (``index`` and ``moved`` come back empty): the
    step of a chain of one, whose link a run never reads (:func:`_link` makes it if asked)."""
    return _known_step_pass(positions, known_valid, codes, values, pb, valid_b, values_b, step, False)


@jit(inline="always")
def _known_step_pass(positions, known_valid, codes, values, pb, valid_b, values_b, step,
                     linked):  # pragma: no cover
    """:func:`_pass` with STEP_LINK over a cloud whose returns are known: the link by the step's provenance and the
    mean change, then the block's sums, block by block (no geometry, no walk, no return test: ≈ 0.7 × the generic
    loop's instructions on a 220 k-point list); with ``linked`` (a constant) the correspondence written. Same
    values in the same order."""
    n, nb = positions.shape[0], pb.shape[0]
    index, moved = np.full(nb if linked else 0, -1, np.int32), np.zeros(nb if linked else 0, np.bool_)
    has_codes = codes.shape[0] > 0
    changes = values.shape[0] > 0 and values_b.shape[0] > 0
    step_origin, step_codes = step
    has_origin, has_step_codes = step_origin.shape[0] > 0, step_codes.shape[0] > 0
    survivors = n
    for j in range(n if has_codes else 0):          # branch-free: vectorised
        survivors -= (codes[j] == 3) & known_valid[j]
    in_order = survivors == nb                      # a list without removals: a MOVED code says moved
    change, changed = 0.0, 0
    sums = return_ranges.NO_SUMS
    usual = has_codes and changes and (in_order or has_step_codes)     # a weather step's: constants below
    for start in range(0, n, return_ranges.BLOCK):
        stop = min(start + return_ranges.BLOCK, n)
        link = (start, stop, codes, step_origin, step_codes, values, values_b, pb, positions, valid_b, index, moved,
                change, changed)
        if usual and has_origin and in_order:
            change, changed = _step_rows(link, True, True, linked, True, True, True)
        elif usual and has_origin:
            change, changed = _step_rows(link, True, False, linked, True, True, True)
        elif usual and in_order:
            change, changed = _step_rows(link, False, True, linked, True, True, True)
        elif usual:
            change, changed = _step_rows(link, False, False, linked, True, True, True)
        else:
            change, changed = _step_rows(link, has_origin, in_order, linked, has_codes, changes, has_step_codes)
        sums = return_ranges.add_return_sums(known_valid, codes, values, start, stop, sums)
    return ((0, np.zeros(0, np.int64), 0.0, known_valid), np.array(sums[:4], np.int64), sums[4], sums[5],
            (index, moved, change / changed if changed else np.nan))


@jit(inline="always")
def _step_rows(link, has_origin, in_order, linked, has_codes, changes, has_step_codes):  # pragma: no cover
    """:func:`_known_step_pass`'s link of rows ``start`` … ``stop`` − 1 (``link``: them, the arrays, ``change`` and
    ``changed`` carried): the new ``change``, ``changed``; the flags are constants where the caller can make them
    so (LLVM then drops their branches: ≈ 10 fewer instructions a row than with them tested on each)."""
    start, stop, codes, origin, step_codes, values, values_b, pb, positions, valid_b, index, moved, change, \
        changed = link
    for j in range(np.uint64(start), np.uint64(stop)):     # (unsigned: no wrap-around test on each index)
        c = codes[j] if has_codes else 0
        i = origin[j] if has_origin else np.int64(j)
        if c == 3 or i < 0:                             # ADDED, or new by the step: no point of before
            continue
        k = np.uint64(i)
        if in_order:
            away = c == 2
        else:                                           # moved by the step, unless to where it was
            away = has_step_codes and step_codes[j] == 2 and not (
                _same_position(pb, k, positions, j) and valid_b[k])
        if linked:
            index[k] = j
            moved[k] = away
        if changes and not away:
            change, changed = _add_change(values_b, k, values, j, change, changed)
    return change, changed


@jit
def _same_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
               step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, SAME_LINK, False, pb, valid_b, values_b, step)


@jit
def _counted_same_pass(positions, known_valid, codes, values, bin_m, n_bins, pb, valid_b, values_b,
                       step):  # pragma: no cover
    return _pass(positions, known_valid, codes, values, bin_m, n_bins, SAME_LINK, True, pb, valid_b, values_b, step)


_PASSES = {(NO_LINK, False): _plain_pass, (GRID_LINK, False): _grid_pass, (LIST_LINK, False): _list_pass,
           (STEP_LINK, False): _step_pass, (SAME_LINK, False): _same_pass, (NO_LINK, True): _counted_plain_pass,
           (GRID_LINK, True): _counted_grid_pass, (LIST_LINK, True): _counted_list_pass,
           (STEP_LINK, True): _counted_step_pass, (SAME_LINK, True): _counted_same_pass}


@jit(inline="always")
def _same_position(p, i, q, j):       # pragma: no cover - compiled
    return p[i, 0] == q[j, 0] and p[i, 1] == q[j, 1] and p[i, 2] == q[j, 2]


@jit(inline="always")
def _is_return(p, j):       # pragma: no cover - compiled
    """Point ``j`` of positions ``p`` is a return (as :func:`_cloud_pass` tells it)."""
    r2 = p[j, 0] * p[j, 0] + p[j, 1] * p[j, 1] + p[j, 2] * p[j, 2]
    return r2 > 0.0 and r2 < np.inf


def _summarise_points(positions: np.ndarray, codes: np.ndarray, values: np.ndarray, n_bins: int,
                      link: int, before: dict | None, step: tuple = _NO_STEP, cells: bool = True,
                      keep_link: bool = True) -> tuple:
    """:func:`_cloud_pass`, linked to the summary ``before`` unless ``link`` is NO_LINK. The geometry of a positions
    array is found once (:mod:`~roadview_noise.physics.return_ranges`): an array a step hands on unchanged
    (intensity models), or whose geometry the model that wrote it noted, is not read again; only the attributes are
    counted — of a chain input without codes only its values' sum (:func:`_return_value_sum`), and not even that
    when the model that read it noted the sum too (:func:`return_ranges.noted_sum`: the laser power, the
    alignment); of a chain's only step (``keep_link`` False) nothing, when the weather placement that wrote it
    noted the pass's sums (:func:`return_ranges.noted_link`). SAME_LINK takes the mean change over the cells
    that are returns in both when ``cells`` (grids), else over every point; ``keep_link``: :func:`_cloud_pass`'s ``linked``."""
    if before is None:
        linked = (positions[:0], np.zeros(0, np.bool_), values[:0], step)
    else:
        valid_b = before["valid"] if link != SAME_LINK or cells else _NO_MASK
        linked = (before["positions"], valid_b, before["values"], step)
    geometry = return_ranges.noted(positions, n_bins)
    if geometry is not None and link == NO_LINK and not len(codes):   # all KEPT: only the values' sum is wanted
        sums = return_ranges.noted_sum(positions, values) or _return_value_sum(geometry[3], values)
        return geometry, np.array([geometry[0], 0, 0, 0], np.int64), *sums, _NOT_LINKED
    if geometry is not None and link == STEP_LINK and not keep_link and len(positions):
        sums = return_ranges.noted_link(positions, codes, values, step[0], before["values"])
        if sums is not None:                # the weather placement summed them: :func:`_unlinked_step_pass`'s
            return (geometry, np.array(sums[:4], np.int64), sums[4], sums[5],
                    (_NO_INDEX, _NO_MASK, sums[6] / sums[7] if sums[7] else math.nan))
    if geometry is None:
        full = _cloud_pass(positions, np.zeros(0, np.bool_), codes, values, RANGE_BIN_M, n_bins, link, *linked)
        return_ranges.note(positions, n_bins, full[0])
        return full
    return (geometry, *_cloud_pass(positions, geometry[3], codes, values, RANGE_BIN_M, n_bins, link, *linked,
                                   linked=keep_link)[1:])


@jit
def _return_value_sum(valid, values):       # pragma: no cover - compiled
    """(sum, number) of the finite ``values`` of the returns ``valid``, in order: :func:`_pass`'s sums of a cloud
    without effect codes whose returns are known (a chain input the weather step counted)."""
    return return_ranges.sum_block(valid, values, 0, values.shape[0], 0.0, 0)


def _link_mode(b: dict, a: dict, by_step: bool = False) -> int:
    if _cell_by_cell(b, a):
        return GRID_LINK
    return STEP_LINK if by_step else LIST_LINK


def _cell_by_cell(b: dict, a: dict) -> bool:
    """Two summaries of full grids of one size: their points correspond cell by cell (GRID_LINK)."""
    return b["grid"] and a["grid"] and len(b["positions"]) == len(a["positions"])


def _same_points(link: int, b: dict, a: dict, step_origin: np.ndarray) -> int:
    """SAME_LINK when ``link`` would find point i of ``b`` as point i of ``a``, unmoved: as many points, no effect
    codes (no point MOVED, ADDED or REMOVED) and no origin — a step that changed values only (laser power) or turned
    points without saying so (the alignment: its links, too, take no point as moved); else ``link``. Its
    correspondence is then not written but made when read (:func:`_link`)."""
    if link == NO_LINK or len(a["effect"]) or len(a["positions"]) != len(b["positions"]):
        return link
    return SAME_LINK if link != STEP_LINK or len(step_origin) == 0 else link


def _link(s: dict) -> tuple[np.ndarray, np.ndarray]:
    """The correspondence of summary ``s`` with its parent (index, moved), made here for a SAME_LINK one (point i
    is point i; of a grid only the cells that are returns in both, as GRID_LINK finds them) and for a step's whose
    pass did not write it (``relink``: the step's provenance; :func:`compare`'s ``linked``), then kept."""
    before, index, moved = s["parent"][:3]
    if index is None and "relink" in s:
        index, moved = _cloud_pass(s["positions"], s["valid"], s["effect"], s["values"], RANGE_BIN_M, 1, STEP_LINK,
                                   before["positions"], before["valid"], before["values"], s.pop("relink"))[-1][:2]
        s["parent"] = (before, index, moved, s["parent"][3])
    elif index is None:
        n = len(before["positions"])
        index, moved = np.arange(n, dtype=np.int32), np.zeros(n, np.bool_)
        if _cell_by_cell(before, s):
            index[~(s["valid"] & before["valid"])] = -1
    return index, moved


def _step_provenance(step: PointCloud | None) -> tuple[np.ndarray, np.ndarray]:
    """A step's own origin and effect codes (:func:`_pass`'s ``step``; empty arrays: identity, KEPT)."""
    if step is None:
        return _NO_STEP
    origin, codes = step.origin, step.effect
    return (_NO_STEP[0] if origin is None else np.asarray(origin, np.int64),
            _NO_STEP[1] if codes is None else np.asarray(codes, np.uint8))


def _cloud_summary(cloud: PointCloud, before: dict | None = None, step: PointCloud | None = None,
                   linked: bool = True) -> dict:
    """The summary of a cloud; with ``before`` (the summary of the cloud it came from: its step's input), also
    its correspondence with ``before`` (``parent``: before, index, moved, mean value change in place), from
    ``step``'s provenance when given (:func:`compare`; not written but made when read if not ``linked``). Counts and range bins are Python lists, made once (the
    pass trims the bins, ``tolist`` converts them) for every comparison that reads them."""
    codes = effect_codes(cloud)
    codes = _NO_CODES if codes is None else np.asarray(codes)
    radar = cloud.sensor == "radar"
    values = _values(cloud)
    positions = np.ascontiguousarray(cloud.positions_m, dtype=np.float64)
    n_bins = return_ranges.bin_count(cloud.profile)
    s = {"positions": positions, "values": values, "grid": cloud.grid_shape is not None, "effect": codes}
    provenance = _step_provenance(step)
    link = NO_LINK if before is None else _same_points(_link_mode(before, s, step is not None), before, s,
                                                       provenance[0])
    (returns, hist, max_r, valid), counts, total, finite, matched = _summarise_points(
        positions, codes, values, n_bins, link, before, provenance, before is not None and _cell_by_cell(before, s),
        linked)
    s.update({"returns": returns, "codes": counts.tolist(), "max_range_m": max_r, "hist": hist.tolist(),
              "radar": radar, "mean_value": total / finite if finite else None, "valid": valid})
    if before is not None:
        unlinked = link == STEP_LINK and len(matched[0]) != len(before["positions"])   # (:func:`_link` makes it)
        s["parent"] = (before, None, None, matched[2]) if link == SAME_LINK or unlinked else (before, *matched)
        if unlinked:
            s["relink"] = provenance
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
    otherwise a survivor is found in place when its position is unchanged, or moved when it lies on the same ray.
    A chain step compared with its own output (``compare(before, after, step)``, as ``apply_models`` does) is
    linked by that output's provenance instead, with the same result and without the search (:func:`_pass`).
    Across several steps (``after`` came from ``before`` through compared steps, as in ``apply_models``) the
    correspondences of the steps are composed, so an alignment error in one step and removals in the next are
    told apart."""
    b = _summary(before)
    a = _summary(after, b)
    if a is b:
        n = len(b["positions"])
        return np.arange(n), np.zeros(n, bool)
    chain = _chain(b, a)
    if chain is None:
        return _direct_link(b, a)[:2]
    index, moved = _link(chain[-2])
    for s in reversed(chain[:-2]):
        index, moved = _compose(index, moved, *_link(s))
    return index, moved


def _mean_change(b: dict, a: dict) -> float:
    """The mean value change (intensity, SNR) from summary ``b`` to ``a`` of the points that stayed in place
    (:func:`correspondence`; NaN if none)."""
    if a is b:
        return 0.0 if len(b["values"]) else math.nan
    chain = _chain(b, a)
    if chain is None:
        return _direct_link(b, a)[2]
    if len(chain) == 2:
        return a["parent"][3]
    first = chain[-2]
    if first["parent"][1] is None and "relink" not in first and len(chain) == 3:       # a → b the same points (SAME_LINK): not made
        both = first["valid"] & b["valid"] if _cell_by_cell(b, first) else _NO_MASK
        return _mean_change_through(_NO_INDEX, both, *_link(a), b["values"], a["values"])
    index, moved = _link(first)
    for s in reversed(chain[1:-2]):
        index, moved = _compose(index, moved, *_link(s))
    return _mean_change_through(index, moved, *_link(a), b["values"], a["values"])


def _chain(b: dict, a: dict) -> list[dict] | None:
    """The summaries from ``a`` back to ``b`` through their parents (steps), or None if ``b`` is not one."""
    chain = [a]
    while chain[-1] is not b and "parent" in chain[-1] and len(chain) < 64:
        chain.append(chain[-1]["parent"][0])
    return chain if chain[-1] is b else None


def _direct_link(b: dict, a: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """Correspondence and mean value change of two summaries that are not linked by steps; the first summary
    ``a`` is matched with becomes its parent."""
    index, moved, change = _cloud_pass(a["positions"], a["valid"], a["effect"], a["values"], RANGE_BIN_M, 1,
                                       _link_mode(b, a), b["positions"], b["valid"], b["values"])[-1]
    a.setdefault("parent", (b, index, moved, change))
    return index, moved, change


@jit
def _compose(index_ab, moved_ab, index_bc, moved_bc):       # pragma: no cover - compiled
    """Correspondence a → c from a → b and b → c."""
    index = np.full(index_ab.shape[0], -1, np.int32)
    moved = np.zeros(index_ab.shape[0], np.bool_)
    for i in range(index_ab.shape[0]):
        k = index_ab[i]
        if k >= 0:
            index[i] = index_bc[k]
            moved[i] = moved_ab[i] or moved_bc[k]
    return index, moved


@jit(inline="always")
def _same_ray(p, i, q, j):       # pragma: no cover - compiled
    """Returns ``p[i]`` and ``q[j]`` lie on the same ray from the sensor: |p × q| ≤ 1e-6 |p||q| and p·q > 0."""
    px, py, pz, qx, qy, qz = p[i, 0], p[i, 1], p[i, 2], q[j, 0], q[j, 1], q[j, 2]
    cx, cy, cz = py * qz - pz * qy, pz * qx - px * qz, px * qy - py * qx
    pp, qq = px * px + py * py + pz * pz, qx * qx + qy * qy + qz * qz
    dot = px * qx + py * qy + pz * qz
    return pp > 0 and qq > 0 and dot > 0 and cx * cx + cy * cy + cz * cz <= 1e-12 * pp * qq


@jit(inline="always")
def _change(values_b, i, values_a, k):       # pragma: no cover - compiled
    """Value change of point ``i`` of before, now point ``k`` of after (float64)."""
    return np.float64(values_a[k]) - np.float64(values_b[i])


@jit(inline="always")
def _add_change(values_b, i, values_a, k, change, changed):       # pragma: no cover - compiled
    """``change``, ``changed`` (a sum of value changes and their number) with point ``i`` of before's, now point
    ``k`` of after, added if it is finite."""
    d = _change(values_b, i, values_a, k)
    return (change + d, changed + 1) if np.isfinite(d) else (change, changed)


@jit
def _mean_change_through(index_ab, moved_ab, index_bc, moved_bc, values_a, values_c):       # pragma: no cover
    """Mean of ``values_c[k] - values_a[i]`` over the points ``i`` of a that stayed in place through a → b → c
    (correspondences a → b and b → c; :func:`_compose` and the mean in one pass; NaN if none). ``index_ab``
    empty: a → b keeps every point in place (SAME_LINK), ``moved_ab`` then the points that are returns in both
    (a grid's link; empty: all)."""
    total, n = 0.0, 0
    if values_a.shape[0] == 0 or values_c.shape[0] == 0:
        return np.nan
    same = index_ab.shape[0] == 0
    masked = same and moved_ab.shape[0] > 0
    for i in range(index_bc.shape[0] if same else index_ab.shape[0]):
        if same:
            k, away = (i if not masked or moved_ab[i] else -1), False
        else:
            k = index_ab[i]
            away = k >= 0 and moved_ab[i]
        if k >= 0 and index_bc[k] >= 0 and not (away or moved_bc[k]):
            d = _change(values_a, i, values_c, index_bc[k])
            if np.isfinite(d):
                total += d
                n += 1
    return total / n if n else np.nan


def points_per_object(cloud: PointCloud, ids: np.ndarray, codes: np.ndarray | None = None) -> dict[int, int]:
    """Non-ADDED returns per object id (ids ≤ 0 are no object)."""
    keep = has_return(cloud.positions_m) & (np.asarray(ids) > 0)
    if codes is not None and len(codes):
        keep &= codes != Effect.ADDED
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
    change = float(_mean_change(b, a))
    change = None if math.isnan(change) else change
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


# --- radar chains ---------------------------------------------------------------------------------------------------
# A radar cloud holds tens of points: its metrics cost Python and numba's call overhead, not arithmetic (a run's
# radar file ≈ 2.6 ms CPU; docs/metrics-cost.md, rounds 19–21). A run holds a radar chain's comparisons to the
# chain's end (:class:`Deferred`) and makes them all — every step's and the output's — in one compiled call over its
# clouds, with no summaries: :func:`_radar_chain_pass` gives :func:`compare`'s values bit for bit.

_SIZES = 6                                              # per cloud in the layout: points, codes, values, origin,
#                                                         step codes, range bins


def _compare_radar_chain(calls: list[tuple[PointCloud, PointCloud, SensorData | None, dict]]) -> None:
    """Fill the dicts of a radar chain's held :func:`compare` calls — each step's (``before``, its output as
    ``after`` and the step's own output: consecutive) and any pair of its clouds without a step, the earlier one
    first (the output's) — from one :func:`_radar_chain_pass`; calls of another shape, grids and clouds with
    object ids are compared one by one."""
    clouds, steps, pairs = [calls[0][0]], [None], []
    for before, after, step, _ in calls:
        if before is clouds[-1] and after is not before and isinstance(step, PointCloud):
            clouds.append(after)
            steps.append(step)
            pairs += (len(clouds) - 2, len(clouds) - 1)
            continue
        i, j = _index_of(clouds, before), _index_of(clouds, after)
        if step is not None or j <= i or i < 0:
            return _compare_one_by_one(calls)
        pairs += (i, j)
    layout, values, codes, step_codes, origins = [len(clouds), len(calls)], [], [], [], []
    n_bins = return_ranges.bin_count(clouds[0].profile)
    for c, step in zip(clouds, steps):
        if c.grid_shape is not None or object_ids(c) is not None:
            return _compare_one_by_one(calls)
        value, code = _values(c), c.effect
        origin, by_step = (None, None) if step is None else (step.origin, step.effect)
        values.append(value)
        if code is not None:
            codes.append(code)
        if by_step is not None:
            step_codes.append(by_step)
        if origin is not None:
            origins.append(origin)
        layout += (len(c.positions_m), 0 if code is None else len(code), len(value), 0 if origin is None else
                   len(origin), 0 if by_step is None else len(by_step),
                   n_bins if c.profile is clouds[0].profile else return_ranges.bin_count(c.profile))
    ints, floats = _radar_chain_pass(  # two arrays: each array argument and each concatenation costs ≈ 1–12 k
        np.concatenate([*(c.positions_m.reshape(-1) for c in clouds), *values], dtype=np.float64),
        np.concatenate([layout + pairs, *origins, *codes, *step_codes], dtype=np.int64))
    ints, floats = ints.tolist(), floats.tolist()
    k = len(clouds)
    means = [m if finite else None for m, finite in zip(floats[k: 2 * k], ints)]
    o = k
    for q, call in enumerate(calls):
        i, j, n, change = pairs[2 * q], pairs[2 * q + 1], ints[o + 7], floats[2 * k + q]
        call[3].update({
            "points_in": ints[o], "points_out": ints[o + 1], "kept": ints[o + 2], "attenuated": ints[o + 3],
            "moved": ints[o + 4], "added": ints[o + 5], "removed": ints[o + 6], "max_range_m_in": floats[i],
            "max_range_m_out": floats[j], "points_per_10m_in": ints[o + 8: o + 8 + n],
            "points_per_10m_out": ints[o + 8 + n: o + 8 + 2 * n], "mean_snr_in_db": means[i],
            "mean_snr_out_db": means[j], "mean_snr_change_db": change if change == change else None})
        o += 8 + 2 * n


def _compare_one_by_one(calls: list[tuple[PointCloud, PointCloud, SensorData | None, dict]]) -> None:
    """Fill the dicts of held calls with :func:`compare`'s results, in order."""
    for before, after, step, result in calls:
        result.update(compare(before, after, step))


def _index_of(clouds: list, cloud: SensorData) -> int:
    """The position of ``cloud`` (identity) in ``clouds``, −1 if absent."""
    return next((i for i, c in enumerate(clouds) if c is cloud), -1)


def _values(cloud: PointCloud) -> np.ndarray:
    """A cloud's metric values, one per point: the LiDAR intensity, the radar SNR (dB); none: empty."""
    values = cloud.fields.get("snr_db" if cloud.sensor == "radar" else "intensity")
    return _NO_VALUES if values is None or np.ndim(values) != 1 else np.asarray(values)


@jit
def _radar_chain_pass(data, layout):  # pragma: no cover - compiled
    """:func:`_compare_clouds` of a chain's clouds, concatenated: ``layout`` = [clouds k, pairs p, per cloud its
    number of points, effect codes, values (0 or as many as the points), its step's origin and effect codes (the
    step's own output; cloud 0: none), range bins (:func:`return_ranges.bin_count`), then the p pairs (before,
    after) of cloud indices, the steps' origins, the clouds' effect codes, the steps' effect codes]; ``data``: the
    clouds' positions (m, x y z per point), then their values. Cloud 0 is summarised unlinked, cloud c linked to
    cloud c − 1 by its step (:func:`_pass` with STEP_LINK, or SAME_LINK as :func:`_same_points` finds it); a pair
    of consecutive clouds takes the step's mean value change, a pair further apart the change through the steps'
    links composed (:func:`_mean_change`: summed over ``before``'s points in order). Returns (int64: per cloud its number of
    finite values, then per pair points in/out, kept, attenuated, moved, added, removed, n bins, the two clouds'
    returns per bin padded to n; float64: per cloud the farthest return's range, the mean value (NaN: none), then
    per pair the mean value change, NaN if none)."""
    k, p = layout[0], layout[1]
    no_mask = np.zeros(0, np.bool_)
    n_bins = 0
    for c in range(k):
        n_bins = max(n_bins, layout[2 + _SIZES * c + 5])
    returns, finite, used = np.zeros(k, np.int64), np.zeros(k, np.int64), np.zeros(k, np.int64)
    counts, hists = np.zeros((k, 4), np.int64), np.zeros((k, n_bins), np.int64)
    floats = np.full(2 * k + p, np.nan)
    change = np.full(k, np.nan)
    link_at = np.zeros(k + 1, np.int64)             # cloud c's link to c − 1: entries link_at[c] … of index, moved
    for c in range(1, k):
        link_at[c + 1] = link_at[c] + layout[2 + _SIZES * (c - 1)]
    index, moved = np.empty(link_at[k], np.int32), np.empty(link_at[k], np.bool_)
    start = np.zeros(5, np.int64)                   # cloud c's first point, code, value, origin, step code
    start[3] = 2 + _SIZES * k + 2 * p
    points, codes_at = 0, start[3]
    for c in range(k):
        points += layout[2 + _SIZES * c]
        codes_at += layout[2 + _SIZES * c + 3]
        start[4] += layout[2 + _SIZES * c + 1]
    codes = layout[codes_at:]
    positions, values = data[: 3 * points].reshape((points, 3)), data[3 * points:]
    prev = np.zeros(5, np.int64)
    prev_valid = no_mask
    for c in range(k):
        at = 2 + _SIZES * c
        n, nc, nv, no, ns, nb = layout[at], layout[at + 1], layout[at + 2], layout[at + 3], layout[at + 4], \
            layout[at + 5]
        pos = positions[start[0]: start[0] + n]
        value = values[start[2]: start[2] + nv]
        if c == 0:
            link, pb, valid_b, values_b = NO_LINK, pos[:0], no_mask, value[:0]
        else:
            link = SAME_LINK if nc == 0 and no == 0 and n == layout[2 + _SIZES * (c - 1)] else STEP_LINK
            pb = positions[prev[0]: start[0]]
            valid_b = no_mask if link == SAME_LINK else prev_valid
            values_b = values[prev[2]: start[2]]
        (r, hist, max_r, valid), counted, total, fin, (idx, mv, ch) = _pass(
            pos, no_mask, codes[start[1]: start[1] + nc], value, RANGE_BIN_M, nb, link, False, pb, valid_b,
            values_b, (layout[start[3]: start[3] + no], codes[start[4]: start[4] + ns]))
        returns[c], floats[c], finite[c], change[c] = r, max_r, fin, ch
        counts[c] = counted
        used[c] = hist.shape[0]
        hists[c, : used[c]] = hist
        floats[k + c] = total / finite[c] if finite[c] else np.nan
        for i in range(link_at[c + 1] - link_at[c]):  # SAME_LINK: point i is point i
            index[link_at[c] + i] = i if link == SAME_LINK else idx[i]
            moved[link_at[c] + i] = False if link == SAME_LINK else mv[i]
        prev[:] = start
        start[0] += n
        start[1] += nc
        start[2] += nv
        start[3] += no
        start[4] += ns
        prev_valid = valid
    pairs = layout[2 + _SIZES * k: 2 + _SIZES * k + 2 * p]
    size = k
    for q in range(p):
        size += 8 + 2 * max(used[pairs[2 * q]], used[pairs[2 * q + 1]])
    ints = np.zeros(size, np.int64)
    ints[:k] = finite
    o = k
    for q in range(p):
        i, j = pairs[2 * q], pairs[2 * q + 1]
        nb = max(used[i], used[j])
        ints[o], ints[o + 1], ints[o + 2], ints[o + 7] = returns[i], returns[j], counts[j, 0], nb
        for e in range(1, 4):                       # attenuated, moved, added: the change of their counts
            ints[o + 2 + e] = counts[j, e] - counts[i, e]
        ints[o + 6] = (returns[i] - counts[i, 3]) - (returns[j] - counts[j, 3])
        ints[o + 8: o + 8 + used[i]] = hists[i, : used[i]]
        ints[o + 8 + nb: o + 8 + nb + used[j]] = hists[j, : used[j]]
        o += 8 + 2 * nb
        floats[2 * k + q] = change[j] if j == i + 1 else _change_through(i, j, layout, values, index, moved, link_at)
    return ints, floats


@jit
def _change_through(i, j, layout, values, index, moved, link_at):  # pragma: no cover - compiled
    """:func:`_mean_change` from cloud ``i`` to cloud ``j`` > i + 1 of :func:`_radar_chain_pass`'s chain: the mean of
    the value change of cloud i's points (in order) that reach cloud j through the links, moved by none (NaN: none,
    or a cloud without values)."""
    first_value = 0
    for c in range(i):
        first_value += layout[2 + _SIZES * c + 2]
    last_value = first_value
    for c in range(i, j):
        last_value += layout[2 + _SIZES * c + 2]
    if layout[2 + _SIZES * i + 2] == 0 or layout[2 + _SIZES * j + 2] == 0:
        return np.nan
    total, n = 0.0, 0
    for x in range(layout[2 + _SIZES * i]):
        at, away, s = x, False, i + 1
        while s <= j and at >= 0:
            away = away or moved[link_at[s] + at]
            at = index[link_at[s] + at]
            s += 1
        if at >= 0 and not away:
            d = _change(values, first_value + x, values, last_value + at)
            if np.isfinite(d):
                total += d
                n += 1
    return total / n if n else np.nan
