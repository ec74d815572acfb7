"""Vertical objects standing on the flat ground (recipe ``inputs.ground_plane.objects``): the stixel world of
Badino, Franke & Pfeiffer (2009, DAGM, "The Stixel World") without stereo, with the ground / vertical / sky split
of Hoiem, Efros & Hebert (2005, SIGGRAPH, "Automatic Photo Pop-up"), from one photo, the camera height and pitch.

Per image column, from the bottom up: road, the lowest object standing on it, whatever is above that, sky.

1. Road. Its look is learnt from the ego lane ahead (ground points 4–10 m forward, ±1.5 m sideways on the flat
   ground of :mod:`.ground_plane`: the lane the vehicle drives in, free in most frames), cut into 10 bands of rows:
   a colour (a bin of luminance × chromaticity, 16³, with its neighbours) is the road's when it is common in at
   least 30 % of the bands — sunlit and shadowed asphalt both, not a lead car filling the lane's far rows. A pixel
   looks like road when its colour is the road's and its texture (mean absolute Laplacian) not above 1.5 × the
   lane's 95th percentile (5×5 majority); not-road gaps in a row narrower than a lane mark (0.25 m at 4 m) close.
2. Contact row. Per column, the lowest row r from which the rows up that a ``MIN_OBJECT_M`` (0.25 m) tall object
   standing at r's ground distance covers (``0.25 f_y / Z(r)``, ≥ 3) are all not road: the bottom of the lowest
   object — a kerb, a road mark or a lane line seen edge-on is lower than that.
3. Sky. Smooth (texture < 0.1), blue pixels above the horizon brighter than 0.9 × the lane's median luminance,
   connected to the top border (thin dark lines, cables, closed), give the sky's level; then smooth blue or grey
   pixels above 0.9 × that level connected to the top (clouds join), what they enclose without reaching the
   horizon, and a 3-px band at their edge where the colour alone decides (the texture window reaches past the
   edge). Without a blue sky (overcast) the grey pixels above 0.9 × the lane's median luminance. The photometry's
   own sky test (depth ``inf``) needs a depth map, so this one reads the photo.
4. Depth. Below the contact row the flat ground (range ``h |r| / r_down``); from it up a vertical plane facing the
   camera at the contact point's horizontal distance ``Z = h r_fwd / r_down`` (level frame, pitch θ:
   ``r_fwd = cos θ − y sin θ``, ``r_down = y cos θ + sin θ``, ``y = (v − c_y) / f_y``), range ``Z |r| / r_fwd``.
   Sky, columns whose contact is at or above the horizon, and anything beyond ``sky_distance_m``:
   ``sky_distance_m``. One object per column: what stands behind the lowest object (a hedge behind a parked car)
   gets its depth.

Steps 1–3 run on the image reduced to about ``WORK_HEIGHT_PX`` rows (INTER_AREA), so a contact row is exact to
the reduction factor (1 up to 599 rows, 2 up to 999, 3 at 1080); step 4 at full resolution. Deterministic.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.ndimage import uniform_filter

from ..units import ray_factor

WORK_HEIGHT_PX = 400                # steps 1–3 at about this image height
SEED_FORWARD_M = (4.0, 10.0)        # the ego lane ahead whose look is the road's
SEED_HALF_WIDTH_M = 1.5
MIN_SEED_PIXELS = 200               # fewer: no road is learnt and the flat prior stays
COLOUR_BINS = 16                    # per axis: luminance, (r − g)/Σ, (b − g)/Σ
CHROMA_RANGE = 0.2                  # chromaticity differences binned over ±this
ROAD_BIN_FRACTION = 0.0135          # a colour is in a band of the lane when its bin and 26 neighbours hold this
LANE_BANDS = 10                     # the lane cut in bands of rows, near to far
ROAD_BAND_SHARE = 0.3               # a road colour is in this share of the bands: a lead car's far rows are not
ROAD_TEXTURE_FACTOR = 1.5           # × the lane's 95th-percentile texture
LANE_MARK_M = 0.25
MIN_OBJECT_M = 0.25                 # the lowest object is at least this tall (a kerb, a road mark is not)
SKY_TEXTURE = 0.1                   # mean |Laplacian| of sRGB luminance
SKY_LUMA_RATIO = 0.9                # × the lane's median luminance; × the blue sky's for clouds
SKY_NEUTRAL = 0.005                 # (b − g)/Σ above this: blue; −this…this: grey
SKY_MAX_RG = 0.02


def object_range(srgb: np.ndarray, intrinsics_px: tuple[float, float, float, float], *, camera_height_m: float,
                 pitch_rad: float = 0.0, sky_distance_m: float = 100.0) -> tuple[np.ndarray, dict]:
    """``(range_m, notes)``: (H, W) float32 range along the pixel rays of a flat ground with vertical objects
    standing on it (module docstring), from the sRGB image ``srgb`` (H, W, 3): 8-bit codes (uint8) or floats in
    [0, 1]."""
    if not camera_height_m > 0 or not sky_distance_m > 0:
        raise ValueError("camera_height_m and sky_distance_m must be > 0")
    img = np.asarray(srgb)
    height_px, width_px = img.shape[:2]
    fx, fy, cx, cy = intrinsics_px
    scale = max(1, int(round(height_px / WORK_HEIGHT_PX)))
    small = img if scale == 1 else cv2.resize(img, (width_px // scale, height_px // scale),
                                              interpolation=cv2.INTER_AREA)
    small = small.astype(np.float32) * np.float32(1 / 255) if small.dtype == np.uint8 else small.astype(np.float32)
    sh, sw = small.shape[:2]
    s_fwd, s_ground, s_horizon = _rows(sh, fy / scale, (cy + 0.5) / scale - 0.5, pitch_rad, camera_height_m)
    luma, rg, bg, texture = _features(small)
    seed = _seed_mask(s_fwd, s_ground, fx / scale, (cx + 0.5) / scale - 0.5, sw)
    n_seed = int(np.count_nonzero(seed))
    if n_seed < MIN_SEED_PIXELS:
        contact, sky = np.full(sw, -1), np.zeros((sh, sw), bool)
    else:
        road = _road_like(luma, rg, bg, texture, seed, lane_mark_px=LANE_MARK_M * fx / scale / SEED_FORWARD_M[0])
        object_rows = MIN_OBJECT_M * fy / scale / np.minimum(s_ground * s_fwd, sky_distance_m)
        contact = _contact_rows(road, object_rows)
        sky = _sky(luma, rg, bg, texture, s_horizon, float(np.median(luma[seed])))

    fwd, ground, horizon = _rows(height_px, fy, cy, pitch_rad, camera_height_m)
    contact = np.where(contact >= 0, contact * scale + scale - 1, -1)              # the block's bottom row
    contact = np.pad(np.repeat(contact, scale), (0, width_px - sw * scale), mode="edge")
    distance = ground * fwd                                                         # horizontal, per row
    z = np.where(contact >= horizon, distance[np.maximum(contact, 0)], np.inf)      # per column
    per_unit = z.astype(np.float32)[None, :] / fwd.astype(np.float32)[:, None]      # standing: Z / r_fwd
    np.copyto(per_unit, ground.astype(np.float32)[:, None],
              where=np.arange(height_px)[:, None] > contact[None, :])               # below the contact: ground
    if sky.any():
        full_sky = sky if scale == 1 else cv2.resize(sky.view(np.uint8), (sw * scale, sh * scale),
                                                     interpolation=cv2.INTER_NEAREST).view(bool)
        np.copyto(per_unit[:full_sky.shape[0], :full_sky.shape[1]], np.float32(np.inf), where=full_sky)
    depth = np.multiply(per_unit, ray_factor(width_px, height_px, fx, fy, cx, cy), out=per_unit)
    np.minimum(depth, np.float32(sky_distance_m), out=depth)
    notes = {"objects": True, "road_seed_pixels": n_seed, "sky_fraction": round(float(sky.mean()), 6),
             "object_columns": round(float(np.mean(z < sky_distance_m)), 6)}
    return depth, notes


def _rows(height_px: int, fy: float, cy: float, pitch_rad: float, camera_height_m: float
          ) -> tuple[np.ndarray, np.ndarray, int]:
    """Per row, the horizontal-forward component ``r_fwd`` of the pixel ray (x, y, 1) in the level frame and the
    ground's distance along it, ``h / r_down`` (inf at and above the horizon); and the first row below the
    horizon."""
    y = (np.arange(height_px, dtype=np.float64) - cy) / fy
    down = y * math.cos(pitch_rad) + math.sin(pitch_rad)
    with np.errstate(divide="ignore"):
        ground = np.where(down > 0, camera_height_m / down, np.inf)
    fwd = np.maximum(math.cos(pitch_rad) - y * math.sin(pitch_rad), 1e-9)      # > 0 short of the zenith/nadir
    return fwd, ground, int(np.searchsorted(down, 0.0, side="right"))


def _features(img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Luminance (sRGB codes in [0, 1], BT.709 weights), chromaticity (r − g and b − g over r + g + b) and texture
    (mean absolute Laplacian of the luminance over 5×5 px)."""
    luma = cv2.transform(img, np.array([[0.2126, 0.7152, 0.0722]], np.float32))
    diffs = cv2.transform(img, np.array([[1, -1, 0], [0, -1, 1], [1, 1, 1]], np.float32))   # r − g, b − g, Σ
    inv = 1.0 / (diffs[..., 2] + np.float32(1e-3))
    texture = cv2.blur(np.abs(cv2.Laplacian(luma, cv2.CV_32F, ksize=3)), (5, 5))
    return luma, diffs[..., 0] * inv, diffs[..., 1] * inv, texture


def _seed_mask(fwd: np.ndarray, ground: np.ndarray, fx: float, cx: float, width_px: int) -> np.ndarray:
    """The ego lane ahead on the flat ground: ``SEED_FORWARD_M`` forward, ±``SEED_HALF_WIDTH_M`` sideways."""
    forward = ground * fwd
    rows = (forward >= SEED_FORWARD_M[0]) & (forward <= SEED_FORWARD_M[1])
    lateral = np.abs(np.arange(width_px) - cx) / fx
    return rows[:, None] & (lateral[None, :] * np.where(rows, ground, 0.0)[:, None] <= SEED_HALF_WIDTH_M)


def _road_like(luma, rg, bg, texture, seed, lane_mark_px: float) -> np.ndarray:
    """Pixels whose colour is common in the lane and whose texture is not above the lane's (module docstring, 1.)."""
    b = COLOUR_BINS
    code = _bins(luma, b, 0.0) * (b * b) + _bins(rg, b / (2 * CHROMA_RANGE), b / 2) * b \
        + _bins(bg, b / (2 * CHROMA_RANGE), b / 2)
    lane_rows, _ = np.nonzero(seed)                                                # ascending
    band = (np.arange(lane_rows.size) * LANE_BANDS // max(lane_rows.size, 1)).astype(np.int32)
    band = band[np.searchsorted(lane_rows, lane_rows)]                             # a row in one band only
    hist = np.bincount(band * b ** 3 + code[seed], minlength=LANE_BANDS * b ** 3).astype(np.float32)
    hist = uniform_filter(hist.reshape(LANE_BANDS, b, b, b), size=(1, 3, 3, 3), mode="constant") * 27
    per_band = np.bincount(band, minlength=LANE_BANDS).astype(np.float32)[:, None, None, None]
    present = hist >= ROAD_BIN_FRACTION * np.maximum(per_band, 1)                  # a bin and its neighbours
    common = (present.mean(axis=0) >= ROAD_BAND_SHARE).ravel()
    ok = common[code] & (texture <= ROAD_TEXTURE_FACTOR * np.percentile(texture[seed], 95))
    road = cv2.blur(ok.view(np.uint8) * np.uint8(255), (5, 5)) >= 128
    k = max(3, int(round(lane_mark_px)) | 1)
    return cv2.morphologyEx(road.view(np.uint8), cv2.MORPH_CLOSE, np.ones((1, k), np.uint8)).view(bool)


def _bins(values: np.ndarray, per_unit: float, offset: float) -> np.ndarray:
    """``floor(values × per_unit + offset)`` clipped to 0 … COLOUR_BINS − 1, as int32."""
    q = values * np.float32(per_unit)
    q += np.float32(offset)
    return np.clip(q, 0, COLOUR_BINS - 1, out=q).astype(np.int32)


def _contact_rows(road: np.ndarray, object_rows: np.ndarray) -> np.ndarray:
    """Per column, the lowest row r from which ``object_rows[r]`` (≥ 3) rows up are all not road (−1: none): an
    object at least ``MIN_OBJECT_M`` tall standing there, not a mark on the ground."""
    h = road.shape[0]
    k = np.clip(np.ceil(object_rows).astype(np.int64), 3, np.arange(h) + 1)        # window per row, in the image
    counts = np.cumsum(~road, axis=0, dtype=np.int32)
    above = np.arange(h) - k                                                       # the row above the window
    window = counts - np.where(above[:, None] >= 0, counts[np.maximum(above, 0)], 0)
    run = window >= k[:, None]
    last = h - 1 - np.argmax(run[::-1], axis=0)
    return np.where(run.any(axis=0), last, -1)


def _sky(luma, rg, bg, texture, horizon: int, lane_luma: float) -> np.ndarray:
    """Sky pixels (module docstring, 3.)."""
    colour = (rg < SKY_MAX_RG) & (bg > -SKY_NEUTRAL)
    colour[horizon:] = False
    smooth = colour & (texture < SKY_TEXTURE)
    blue = _top_connected(smooth & (bg > SKY_NEUTRAL) & (luma > SKY_LUMA_RATIO * lane_luma), horizon)
    if np.count_nonzero(blue) >= MIN_SEED_PIXELS:       # a blue sky: neutral pixels as bright as it (clouds) join
        level = SKY_LUMA_RATIO * float(np.median(luma[blue]))
    else:                                                 # overcast: bright neutral pixels
        level = SKY_LUMA_RATIO * lane_luma
    colour &= luma > level
    sky = _top_connected(smooth & colour, horizon)
    # the texture (3×3 Laplacian, 5×5 mean) reaches 3 px past an edge: there the colour alone decides
    sky |= cv2.dilate(sky.view(np.uint8), np.ones((7, 7), np.uint8)).view(bool) & colour
    if horizon:                                   # what the sky encloses without reaching the horizon is sky too
        n, labels = cv2.connectedComponents((~sky[:horizon]).view(np.uint8), connectivity=8)
        grounded = np.zeros(n, bool)
        grounded[labels[-1]] = True
        sky[:horizon] |= ~grounded[labels]
    return sky


def _top_connected(like: np.ndarray, horizon: int) -> np.ndarray:
    """The pixels of ``like`` above the horizon connected to the top border, thin horizontal gaps (cables: 1 % of
    the image height) closed."""
    k = max(3, like.shape[0] // 100 | 1)
    like = cv2.morphologyEx(like.view(np.uint8), cv2.MORPH_CLOSE, np.ones((k, 1), np.uint8))
    like[horizon:] = 0
    n, labels = cv2.connectedComponents(like, connectivity=4)
    top = np.zeros(n, bool)
    top[labels[0]] = True
    top[0] = False
    return top[labels]
