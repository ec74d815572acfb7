"""Scene radiances estimated from the frame itself, in the frame's own linear scale (models.md §2.1–§2.3 [PROP]),
and the per-site compositing of a frame with them.

The reference code used absolute constants (airlight 600/1500, sun 6000, flakes 255 on an 8-bit scale) that
saturate fog and streaks (models.md §7.3). Estimating from the image makes every weather radiance follow the
image, including an image darkened by an earlier low-light step (D3.5 Eq. 1 coupling).
The weather's sky (fog's airlight, the cloud cover of rain and snow) takes its level from the frame's sky and its
colour from the frame's illuminant (:func:`airlight_radiance`): a clear blue sky is not the colour of fog.
Statistics use the sites of a 4-pixel lattice (1/16 of the frame; the lattice keeps a mosaic's CFA phase): the
mean of ~10⁵ sites per channel is exact to far below one code value, at 1/16 of the cost.

Compositing (:func:`composite`, :func:`site_transmission`) runs in small numba kernels, one pass over the frame:
OpenCV's 3-channel arithmetic with per-channel constants needs an expanded 3-channel copy of every (H, W) plane
and one pass per operation, and is 2–3× slower.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from ..errors import ModelError
from .cfa import SiteLayout
from .compiled import jit

SAMPLE_STEP_PX = 4
BLOCK_PX = 4                          # raw illuminant estimate: colours of 4×4-pixel block means …
BLOCK_STEP_PX = 8                     # … on an 8-pixel lattice (1/4 of the frame read)
BRIGHTEST_FRACTION = 0.001            # "sky" when the depth map has none: the brightest 0.1 % of pixels
MIN_SKY_SAMPLES = 16                  # fewer sampled sky sites per channel than this: use the brightest pixels
ENVIRONMENT_ROWS_FRACTION = 0.6       # upper 3/5 of the image ≈ the wide upward cone a raindrop refracts
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])   # Y of linear R, G, B (ITU-R BT.709 = sRGB primaries)
CLIPPED_LEVEL = 0.98                  # a pixel with a channel at/above this (full scale 1) has lost its colour
GREY_ANGLES_DEG = (15.0, 8.0)        # raw illuminant: grey blocks within this angle of the estimate, per pass
MIN_GREY_BLOCKS = 16                  # fewer grey blocks than this: keep the estimate so far


class FrameSample:
    """A frame's sites on the ``SAMPLE_STEP_PX`` lattice (:meth:`SiteLayout.lattice`, views) and the depth there
    (NaN where not valid), with its sky mask: taken once per frame and read by every estimate of it. Masks are
    evaluated on the lattice only (a full-frame mask of the depth costs more than the statistics).

    ``depth_valid`` (H, W) bool (``frame.depth_valid``: False on filled holes, extrapolated regions) marks the
    depth that is not valid as NaN in ``depth_m`` does: never sky, never among the brightest pixels."""

    def __init__(self, layout: SiteLayout, signal: np.ndarray, depth_m: np.ndarray,
                 depth_valid: np.ndarray | None = None):
        self.layout, self.signal = layout, signal
        self.sites = layout.lattice(signal, SAMPLE_STEP_PX)
        self.depth = [d for _, d in layout.lattice(depth_m, SAMPLE_STEP_PX)]
        if depth_valid is not None:
            self.depth = [np.where(v, d, np.float32(np.nan))
                          for d, (_, v) in zip(self.depth, layout.lattice(depth_valid, SAMPLE_STEP_PX))]

    @functools.cached_property
    def sky(self) -> list[np.ndarray]:
        """Per lattice view: sites of depth ``inf``."""
        return [np.isinf(d) for d in self.depth]

    def values(self, where) -> list[np.ndarray]:
        """Each channel's (R, G, B) sampled values where ``where(depth)`` is true (e.g. ``np.isfinite``)."""
        return self.layout.lattice_channels(self.sites, [where(d) for d in self.depth])


def airlight_radiance(layout: SiteLayout, signal: np.ndarray, depth_m: np.ndarray,
                      depth_valid: np.ndarray | None = None) -> np.ndarray:
    """Per-channel (R, G, B) radiance of the weather's own sky — fog's airlight at infinity, the overcast sky of
    rain and snow: level :func:`sky_luminance`, colour :func:`illuminant_chromaticity`.

    Fog droplets (size parameter ≫ 1) scatter all visible wavelengths alike, so the airlight has the colour of the
    light falling on the fog (sun + sky), not of the clear sky the fog hides (Rayleigh blue): Narasimhan & Nayar
    (2002, IJCV 48(3), dichromatic atmospheric scattering: airlight colour = the illuminant's in fog and haze;
    2003, PAMI 25(6)); Koschmieder (1924) sets its level to the horizon sky's luminance. The same holds for the
    cloud cover of rain and snow (grey, lit by the same illuminant). NaN in ``depth_m`` or False in
    ``depth_valid`` marks pixels whose depth is not valid (filled holes, :class:`FrameSample`): never sky, never
    among the brightest pixels (their colour still counts in a raw frame's illuminant estimate). On a raw mosaic
    each channel is capped at the white level (signal 1): a site records no more than saturation, and a clipped
    sky's level times a non-neutral white would otherwise exceed it (fog on a real 10-bit DNG wrote up to 1 034 DN
    over a white level of 1 023)."""
    return _airlight(FrameSample(layout, signal, depth_m, depth_valid))


def _airlight(sample: FrameSample) -> np.ndarray:
    sky = _sky_luminance(sample) * _illuminant(sample)
    return np.minimum(sky, 1.0) if sample.layout.mosaic else sky


def sky_luminance(layout: SiteLayout, signal: np.ndarray, depth_m: np.ndarray) -> float:
    """Luminance Y (BT.709 weights; on a raw mosaic the same weights on the camera's channels) of the mean sky
    radiance (sites of depth ``inf``), else — no sky in view — the mean Y of the brightest 0.1 % of the pixels with
    a valid depth (models.md §2.1 [PROP]), each taken at most 1.0 (full scale; an HDR frame's reference white):
    the estimate an 8-bit camera's clipped pixels give, so that on an HDR photo (PQ, HLG, EXR) a lamp or the sun
    at 40× white is not taken for the sky (it made fog and snow 40× white)."""
    return _sky_luminance(FrameSample(layout, signal, depth_m))


def _sky_luminance(sample: FrameSample) -> float:
    sky = sample.layout.lattice_channels(sample.sites, sample.sky)
    if all(s.size >= MIN_SKY_SAMPLES for s in sky):
        return float(LUMINANCE_WEIGHTS @ np.array([s.mean(dtype=np.float64) for s in sky]))
    y = np.minimum(pixel_samples(sample.layout, sample.signal, _valid_or_none(sample.depth[0])) @ LUMINANCE_WEIGHTS,
                   1.0)
    k = max(1, math.ceil(BRIGHTEST_FRACTION * y.size))
    return float(np.partition(y, y.size - k)[y.size - k:].mean())


def illuminant_chromaticity(layout: SiteLayout, signal: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """Colour of the scene illuminant as the frame renders a white surface, (R, G, B) scaled to luminance Y = 1.

    RGB frames are white-balanced (the camera's AWB, with the full raw data, made its illuminant estimate neutral):
    neutral. Casts such an image keeps (sunset, sodium lamps) are not estimated: on the real nuScenes and KITTI
    photos the frame estimates we tried (grey world, grey pixels, white patch) differed by up to 30 % (blue) from
    method to method — more than the casts those photos show.
    A raw mosaic is in the camera's unbalanced channels and its white (DNG AsShotNeutral) is not carried by the
    frame, so it is estimated: grey pixels (Huo et al. 2006, IEEE Trans. Consum. Electron. 52(2); on grey world,
    Buchsbaum 1980; survey: Gijsenij, Gevers & van de Weijer 2011, IEEE TIP 20(9)) — start from the grey-world
    mean of the non-sky pixels (the sky is a light source, not a reflector) averaged in 4×4 blocks (so a dark
    frame's noise does not scatter their colours), unclipped; then twice keep the blocks within 15°, then 8°, of
    the estimate and take their sum. Too few blocks: the estimate so far."""
    return _illuminant(FrameSample(layout, signal, depth_m))


def _illuminant(sample: FrameSample) -> np.ndarray:
    if not sample.layout.mosaic:
        return np.ones(3)
    planes = block_means(sample.layout, sample.signal)
    r, g, b = planes
    k = BLOCK_STEP_PX // SAMPLE_STEP_PX       # block corners: every k-th site of the sample's top-left CFA phase
    surfaces = ~np.isinf(sample.depth[0][::k, ::k][:r.shape[0], :r.shape[1]])
    p = planes[:, (surfaces if surfaces.any() else True) & (np.maximum(np.maximum(r, g), b) < CLIPPED_LEVEL) &
               (r + g + b > 0)]                       # (3, N) the unclipped blocks' R, G, B
    if p.shape[1] < MIN_GREY_BLOCKS:
        return np.ones(3)
    estimate = _block_sum(p)
    if not np.all(estimate > 0):
        return np.ones(3)
    direction = np.ascontiguousarray((p / np.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])).T)     # (N, 3)
    for angle_deg in GREY_ANGLES_DEG:
        grey = direction @ (estimate / np.linalg.norm(estimate)) >= math.cos(math.radians(angle_deg))
        if grey.sum() < MIN_GREY_BLOCKS:
            break
        estimate = _block_sum(p[:, grey])
    return estimate / float(LUMINANCE_WEIGHTS @ estimate)


def _block_sum(p: np.ndarray) -> np.ndarray:
    """R, G, B sums of (3, N) block colours, each added in block order (bit for bit the sum over the blocks of
    their (N, 3) rows)."""
    return np.cumsum(p, axis=1)[:, -1]


def block_means(layout: SiteLayout, signal: np.ndarray) -> np.ndarray:
    """(3, rows, cols) float64 R, G, B planes of the means of a mosaic's ``BLOCK_PX``² blocks (whole CFA cells)
    whose top-left sites are the ``BLOCK_STEP_PX`` lattice points."""
    b, step = BLOCK_PX, BLOCK_STEP_PX
    h, w = (n // step * step for n in signal.shape)
    blocks = signal[:h, :w].reshape(h // step, step, w // step, step)
    planes = np.zeros((3, h // step, w // step))
    count = np.zeros(3)
    for (i, j), c in layout.cells:                     # the block's sites of this CFA phase
        for y in range(i, b, 2):
            for x in range(j, b, 2):
                planes[c] += blocks[:, y, :, x]
                count[c] += 1
    planes /= count[:, None, None]
    return planes


def pixel_samples(layout: SiteLayout, signal: np.ndarray, mask: np.ndarray | None = None,
                  step: int = SAMPLE_STEP_PX) -> np.ndarray:
    """(N, 3) float64 R, G, B of the pixels on a ``step`` lattice where ``mask`` — given on that lattice (an (H, W)
    mask's ``[::step, ::step]``) — is true; on a mosaic a pixel is the 2×2 CFA cell at the lattice point (its two G
    sites averaged)."""
    if layout.mosaic:
        h, w = signal.shape
        rgb = np.zeros((len(range(0, h - 1, step)), len(range(0, w - 1, step)), 3))
        count = np.zeros(3)
        for (i, j), c in layout.cells:
            rgb[..., c] += signal[i:h - 1 + i:step, j:w - 1 + j:step]
            count[c] += 1
        rgb /= count
        mask = None if mask is None else mask[:rgb.shape[0], :rgb.shape[1]]
    else:
        rgb = signal[::step, ::step].astype(np.float64)
    return rgb.reshape(-1, 3) if mask is None else rgb[mask]


def environment_radiance(layout: SiteLayout, signal: np.ndarray, depth_m: np.ndarray, sky: np.ndarray
                         ) -> np.ndarray:
    """Per-channel mean radiance of the upper 3/5 of the image (models.md §2.2 [PROP] ``E_env``) over the sites
    with a valid depth, sky sites (depth ``inf``) counting as ``sky`` (R, G, B): under rain the drop refracts the
    cloud cover, not the clear sky of the input frame."""
    return _environment(FrameSample(layout, signal, depth_m), sky)


def _environment(sample: FrameSample, sky: np.ndarray) -> np.ndarray:
    rows = max(1, round(ENVIRONMENT_ROWS_FRACTION * sample.signal.shape[0]))
    upper = sample.layout.lattice(sample.signal[:rows], SAMPLE_STEP_PX)     # the sample's first lattice rows
    n_rows = [v.shape[0] for _, v in upper]
    seen = sample.layout.lattice_channels(upper, [np.isfinite(d[:n]) for d, n in zip(sample.depth, n_rows)])
    n_sky = [0, 0, 0]
    for (c, _), is_sky, n in zip(upper, sample.sky, n_rows):
        for ch in range(3) if c is None else (c,):
            n_sky[ch] += int(np.count_nonzero(is_sky[:n]))
    if any(s.size + n == 0 for s, n in zip(seen, n_sky)):
        return np.array([s.mean(dtype=np.float64) for s in sample.layout.lattice_channels(upper)])
    return np.array([(s.sum(dtype=np.float64) + n * a) / (s.size + n) for s, n, a in zip(seen, n_sky, sky)])


def _valid_or_none(depth_m: np.ndarray) -> np.ndarray | None:
    """Pixels with a valid depth (not NaN); None when that is every pixel or none (then all pixels are used)."""
    valid = ~np.isnan(depth_m)
    return None if valid.all() or not valid.any() else valid


def absolute_radiance(value, luminance_factor: float) -> np.ndarray:
    """A user radiance in linear full-scale units (scalar or R, G, B) for the undarkened scene, scaled by the
    luminance factor an earlier low-light step set (``Conditions.luminance_factor``)."""
    v = np.broadcast_to(np.asarray(value, dtype=float), (3,))
    return v * float(luminance_factor)


def frame_depth_m(frame, model_id: str) -> np.ndarray:
    """The frame's range map as contiguous float32 (H, W); a clear :class:`ModelError` if absent or invalid."""
    depth = frame.depth_m
    if depth is None:
        raise ModelError("needs a depth map (range along each pixel ray, metres; inf = sky); give the inputs one: "
                         "inputs.depth (depth files), or inputs.depth_source: lidar | onnx | ground_plane",
                         model=model_id, field="depth_m")
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.shape != tuple(frame.shape):
        raise ModelError(f"depth map is {depth.shape}, image is {tuple(frame.shape)}", model=model_id,
                         field="depth_m")
    if not depth.min(initial=0.0) >= 0:                   # NaN propagates through min
        raise ModelError("depth map has negative or NaN values (use inf for sky)", model=model_id, field="depth_m")
    return depth


RAIN_REFRACTED_FRACTION = 0.94        # share of a drop's radiance refracted from the environment (models.md §2.2)


def raindrop_radiance(layout: SiteLayout, signal: np.ndarray, depth_m: np.ndarray,
                      depth_valid: np.ndarray | None = None) -> np.ndarray:
    """``S_c = 0.94 E_env,c + 0.06 E_sky,c`` (models.md §2.2 [PROP], after Garg & Nayar 2007): a drop refracts a
    wide cone of the scene in front of the camera and reflects the sky — the rain's overcast sky,
    :func:`airlight_radiance`, in both terms."""
    sample = FrameSample(layout, signal, depth_m, depth_valid)
    sky = _airlight(sample)
    return (RAIN_REFRACTED_FRACTION * _environment(sample, sky) +
            (1.0 - RAIN_REFRACTED_FRACTION) * sky)


# --- per-site compositing -------------------------------------------------------------------------------------

@jit(error_model="numpy")
def _lerp_rgb(a, t, s, out):                                   # pragma: no cover - compiled
    """``out = a + t·(s − a)`` over (H, W, 3) ``t``, ``s`` and ``out`` of any strides (broadcast views of (H, W)
    planes or of per-channel constants included); ``a`` (3,) per channel."""
    a0, a1, a2 = a[0], a[1], a[2]
    for y in range(out.shape[0]):
        for x in range(out.shape[1]):
            out[y, x, 0] = a0 + t[y, x, 0] * (s[y, x, 0] - a0)
            out[y, x, 1] = a1 + t[y, x, 1] * (s[y, x, 1] - a1)
            out[y, x, 2] = a2 + t[y, x, 2] * (s[y, x, 2] - a2)


@jit(error_model="numpy")
def _lerp_rows(a, t, s, out):                                  # pragma: no cover - compiled
    """``out = a + t·(s − a)`` row by row over (H, N) ``out``; every operand is a (k, N) array whose rows repeat
    down the image: k = H (a full array), 1 (one row for all) or 2 (rows for even and odd image rows)."""
    for y in range(out.shape[0]):
        ar, tr, sr, orow = a[y % a.shape[0]], t[y % t.shape[0]], s[y % s.shape[0]], out[y]
        for i in range(orow.size):
            orow[i] = ar[i] + tr[i] * (sr[i] - ar[i])


def _channel_values(values) -> np.ndarray:
    return np.ascontiguousarray(np.broadcast_to(np.asarray(values, dtype=np.float32), (3,)))


def _mosaic_rows(layout: SiteLayout, values: np.ndarray) -> np.ndarray:
    """Per-channel values on the sites of the first two mosaic rows, (≤ 2, W): every later row repeats one."""
    return np.take(values, layout.channel_index[:2])


def composite(layout: SiteLayout, signal: np.ndarray, t: np.ndarray, values, out: np.ndarray | None = None
              ) -> np.ndarray:
    """Koschmieder-form blend per site, ``I' = S + t·(I − S)`` with S per channel (R, G, B), float32; ``t`` per
    pixel (H, W) or per site (the signal's shape). ``out`` may be ``t`` itself when ``t`` is per site."""
    v = _channel_values(values)
    signal = np.asarray(signal, dtype=np.float32)
    t = np.asarray(t, dtype=np.float32)
    out = np.empty_like(signal, order="C") if out is None else out
    if layout.mosaic:
        _lerp_rows(_mosaic_rows(layout, v), t, signal, out)
    else:
        _lerp_rgb(v, t if t.ndim == 3 else np.broadcast_to(t[..., None], signal.shape), signal, out)
    return out


def blend_operands(layout: SiteLayout, signal: np.ndarray, values) -> tuple[np.ndarray, np.ndarray]:
    """:func:`composite`'s operands for a kernel that blends row by row: the signal as contiguous float32 rows,
    (H, W·3) RGB or (H, W) sites, and S per value of a row, (k, ·) rows repeating down the image (k = 1 for RGB,
    ≤ 2 on a mosaic)."""
    v = _channel_values(values)
    signal = np.ascontiguousarray(signal, dtype=np.float32)
    rows = _mosaic_rows(layout, v) if layout.mosaic else np.tile(v, signal.shape[1])[None, :]
    return rows, signal.reshape(signal.shape[0], -1)


def capped(values: np.ndarray, cap: float, out: np.ndarray | None = None) -> np.ndarray:
    """``min(values, cap)`` of a float32 array by OpenCV, except for a single value: OpenCV takes a 1×1 array for
    a Scalar and answers 4×1 (a 1×1 photo came out of fog 4×1)."""
    if values.size == 1:
        return np.minimum(values, np.float32(cap), out=out)
    return cv2.min(values, cap, dst=out)


def site_transmission(layout: SiteLayout, distance_m: np.ndarray, sigma_per_m) -> np.ndarray:
    """Per-site Beer–Lambert transmission ``exp(−σ_c d)`` of an (H, W) distance map (inf → 0), float32, with σ
    per channel (R, G, B). Distances are capped where the optical depth reaches 80 (t < 2·10⁻³⁵ leaves no trace
    in float32 arithmetic) because exp of −inf and of sub-normal results takes a slow path."""
    sigma = _channel_values(sigma_per_m)
    if np.any(sigma < 0):
        raise ValueError("extinction coefficients must be ≥ 0")
    positive = sigma[sigma > 0]
    d = capped(np.asarray(distance_m, dtype=np.float32), 80.0 / float(positive.min()) if positive.size else 0.0)
    neg_sigma = -sigma
    # −σ_c·d per site: the blend kernels with a = 0
    if layout.mosaic:
        out = np.empty_like(d)
        _lerp_rows(np.zeros((1, d.shape[1]), np.float32), d, _mosaic_rows(layout, neg_sigma), out)
    else:
        shape = d.shape + (3,)
        out = np.empty(shape, dtype=np.float32)
        _lerp_rgb(np.zeros(3, np.float32), np.broadcast_to(d[..., None], shape), np.broadcast_to(neg_sigma, shape),
                  out)
    return cv2.exp(out, dst=out)
