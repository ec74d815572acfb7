"""Camera depth from the paired LiDAR scan (recipe ``inputs.depth_source: lidar``), the way multi-sensor datasets
(KITTI depth completion, nuScenes, REHEARSE) are used.

1. Projection. Points in the LiDAR frame are moved into the camera frame with the calibration's rigid transform
   (``p_c = R p + t``), projected with the pinhole K to the nearest pixel centre, and each pixel keeps the nearest
   return (z-buffer); its value is the point's range from the camera centre, ``|p_c|`` — the range along the ray.
2. Parallax. The LiDAR sits elsewhere than the camera (on a roof: it sees over a car onto the road that the camera
   cannot see), so a return whose range exceeds the nearest return within ``occlusion_window_px`` by more than
   ``occlusion_tolerance`` (relative) is hidden from the camera and dropped.
3. Sky. Per image column, above its highest return there is sky (range ``inf``) — unless that return is at the
   top of the scan's vertical field of view, where the scene may go on above what the LiDAR sees: there the depth
   is extended upwards and marked not valid. Columns without a return take the nearest column's rows. The top of
   the field of view is found per range (:func:`at_top_of_view`, within ``top_beam_tolerance_deg``): the elevation
   of one beam seen from the scanner's origin is not constant, a laser that sits a height z₀ above the origin
   (HDL-64E: about 0.2 m on KITTI's scans) reaches ``atan(tan θ + z₀ / r)`` — +3.4° at 8 m and +2.1° at 70 m for
   its nominal +2° — so one threshold for the whole scan calls the far top-beam returns lower beams and puts sky
   over houses and trees.
4. Densification in image space, in inverse range: ``nearest`` gives each pixel the value of the nearest return
   (Euclidean distance in pixels; OpenCV distance transform with labels); ``bilateral`` then smooths that map with
   a joint bilateral filter guided by the image, so depth edges between returns follow image edges (OpenCV
   ximgproc), and the returns keep their measured values.

5. Below the lowest return. A roof LiDAR cannot see the ground just in front of the car, which the camera sees.
   Where a column's lowest return lies on the flat ground of the camera height and pitch (within
   ``ground_tolerance``), the ground plane (:mod:`.ground_plane`) continues the depth down to the image border;
   elsewhere the nearest return does.

Validity (for the scene radiance estimates): pixels between the highest and lowest return of their column and the
sky; the extensions above a clipped column and below the lowest return are not valid.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d

from .ground_plane import ground_plane_range

DENSIFY = ("nearest", "bilateral")
MIN_DEPTH_M = 0.1                   # points nearer than this to the camera plane are not projected
RANGE_BIN_RATIO = 1.02              # range bins of the top-of-view envelope: 2 % wide
MAX_LASER_OFFSET_M = 0.5            # a laser sits within this height of the scan's origin (HDL-64E: ≈ 0.2 m)
SPACING_MEDIAN_FACTOR = 4.0         # LiDAR column spacing: at most this × the median gap of neighbours in a row


def project_returns(points_m: np.ndarray, lidar_to_camera: np.ndarray,
                    intrinsics_px: tuple[float, float, float, float], width_px: int, height_px: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, range_m, elevation_rad)`` of the nearest return per pixel, for the points that fall in the
    image; elevation is the point's in the LiDAR frame (x forward, y left, z up)."""
    p = np.asarray(points_m, dtype=np.float64)
    p = p[np.einsum("ij,ij->i", p, p) > 1e-6]                          # no-return cells of full grids
    pc = p @ lidar_to_camera[:3, :3].T + lidar_to_camera[:3, 3]
    fx, fy, cx, cy = intrinsics_px
    z = pc[:, 2]
    front = z > MIN_DEPTH_M
    u = np.rint(fx * pc[front, 0] / z[front] + cx)
    v = np.rint(fy * pc[front, 1] / z[front] + cy)
    inside = (u >= 0) & (u < width_px) & (v >= 0) & (v < height_px)
    cols, rows = u[inside].astype(np.int64), v[inside].astype(np.int64)
    rng = np.linalg.norm(pc[front][inside], axis=1)
    q = p[front][inside]
    elev = np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1]))
    pixel = rows * width_px + cols
    order = np.lexsort((rng, pixel))                                    # nearest first within each pixel
    first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]] if order.size else order
    return rows[first], cols[first], rng[first].astype(np.float32), elev[first]


def drop_occluded(rows: np.ndarray, cols: np.ndarray, range_m: np.ndarray, shape: tuple[int, int],
                  window_px: int, tolerance: float) -> np.ndarray:
    """Boolean mask of the returns seen by the camera: a return farther than ``(1 + tolerance)`` × the nearest
    return in the ``window_px`` square around it is hidden behind that nearer surface (parallax)."""
    if window_px <= 1 or rows.size == 0:
        return np.ones(rows.size, dtype=bool)
    sparse = np.full(shape, np.inf, dtype=np.float32)
    sparse[rows, cols] = range_m
    nearest = cv2.erode(sparse, np.ones((window_px, window_px), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return range_m <= nearest[rows, cols] * np.float32(1.0 + tolerance)


def column_spacing_px(rows: np.ndarray, cols: np.ndarray) -> int:
    """Horizontal spacing of the projected LiDAR columns: the 90th percentile of the gaps between neighbouring
    returns of an image row, at most ``SPACING_MEDIAN_FACTOR`` × their median (≥ 1 px). The bound matters for a
    sparse scanner whose scan lines cross the image rows (nuScenes' HDL-32E on CAM_FRONT: neighbours in a row
    are mostly other beams' crossings, 90th percentile 711 px, median 9 px): spread over ±711 px, the highest
    return of the frame would close the sky of every column."""
    order = np.lexsort((cols, rows))
    r, c = rows[order], cols[order]
    gaps = np.diff(c)[np.diff(r) == 0]
    if not gaps.size:
        return 1
    return max(1, int(np.ceil(min(np.percentile(gaps, 90), SPACING_MEDIAN_FACTOR * np.median(gaps)))))


def at_top_of_view(range_m: np.ndarray, elevation_rad: np.ndarray, tolerance_rad: float) -> np.ndarray:
    """Boolean mask of the returns at the top of the scan's vertical field of view (module docstring, 3.).

    A beam of elevation θ whose laser sits z₀ above the origin reaches ``tan e = tan θ + z₀ / r`` at range r: a
    straight line in (1/r, tan e), above which no return lies. The top beam's line is an edge of the upper convex
    hull of the returns in that plane (of the highest return per 2 %-wide range bin) whose slope z₀ is a laser's
    offset (at most ``MAX_LASER_OFFSET_M``; a flat open road is such a line too, of slope −(LiDAR height)): the
    edge along which most of those bins' highest returns lie (within ``tolerance_rad``), else the level line
    through the highest return. A return is at the top of the view when its elevation is within
    ``tolerance_rad`` of that line at its range."""
    x = 1.0 / np.maximum(range_m, MIN_DEPTH_M)
    y = np.tan(elevation_rad)
    bins = np.floor(np.log(x) / np.log(RANGE_BIN_RATIO)).astype(np.int64)
    order = np.lexsort((-y, bins))
    first = order[np.r_[True, bins[order][1:] != bins[order][:-1]]]       # highest return per bin, by range
    bx, by = x[first], y[first]
    hx, hy = _upper_hull(bx, by)
    best, best_support = (0.0, float(hy.max())), -1
    for i in range(len(hx) - 1):
        slope = (hy[i + 1] - hy[i]) / (hx[i + 1] - hx[i])
        if abs(slope) > MAX_LASER_OFFSET_M:                # e.g. the open road: z = −(LiDAR height), a "beam" too
            continue
        line = (slope, hy[i] - slope * hx[i])
        support = int(np.count_nonzero(np.arctan(by) >= np.arctan(line[0] * bx + line[1]) - tolerance_rad))
        if support > best_support:
            best, best_support = line, support
    return elevation_rad >= np.arctan(best[0] * x + best[1]) - tolerance_rad


def _upper_hull(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of the upper convex hull of points sorted by ascending ``x`` (Andrew's monotone chain); a few
    hundred points (one per range bin)."""
    hx: list[float] = []
    hy: list[float] = []
    for px, py in zip(x.tolist(), y.tolist()):
        while len(hx) >= 2 and (hx[-1] - hx[-2]) * (py - hy[-2]) - (hy[-1] - hy[-2]) * (px - hx[-2]) >= 0:
            hx.pop()
            hy.pop()
        hx.append(px)
        hy.append(py)
    return np.array(hx), np.array(hy)


def column_extent(rows: np.ndarray, cols: np.ndarray, range_m: np.ndarray, elevation_rad: np.ndarray,
                  width_px: int, top_beam_tolerance_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per image column: row of the highest and of the lowest return within ± the LiDAR column spacing, and
    whether that highest return is at the top of the scan's field of view (clipped, :func:`at_top_of_view`).
    Columns without a return in reach take the nearest column's values."""
    clipped = at_top_of_view(range_m, elevation_rad, top_beam_tolerance_rad)
    big = np.iinfo(np.int64).max // 4
    key = np.full(width_px, big, dtype=np.int64)                    # 2·row + (0 clipped | 1): min = highest,
    np.minimum.at(key, cols, 2 * rows + (~clipped).astype(np.int64))   # a clipped return winning a tie
    bottom = np.full(width_px, -1, dtype=np.int64)
    np.maximum.at(bottom, cols, rows)
    size = 2 * column_spacing_px(rows, cols) + 1
    key = minimum_filter1d(key, size, mode="nearest")
    bottom = maximum_filter1d(bottom, size, mode="nearest")
    columns, occupied = np.arange(width_px), np.flatnonzero(bottom >= 0)
    pos = np.searchsorted(occupied, columns)
    left = occupied[np.clip(pos - 1, 0, occupied.size - 1)]
    right = occupied[np.clip(pos, 0, occupied.size - 1)]
    nearest = np.where(np.abs(columns - left) <= np.abs(right - columns), left, right)
    key, bottom = key[nearest], bottom[nearest]
    return key // 2, bottom, key % 2 == 0


def nearest_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Each pixel takes the value of the nearest known pixel (Euclidean, OpenCV ``distanceTransformWithLabels``:
    its pixel labels number the known pixels in row-major order)."""
    _, labels = cv2.distanceTransformWithLabels((~known).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    lut = np.concatenate([[0.0], values[known]]).astype(np.float32)
    return lut[labels]


def lidar_depth(points_m: np.ndarray, lidar_to_camera: np.ndarray, intrinsics_px: tuple[float, float, float, float],
                width_px: int, height_px: int, *, densify: str = "nearest", guide_srgb: np.ndarray | None = None,
                occlusion_window_px: int = 5, occlusion_tolerance: float = 0.1,
                top_beam_tolerance_deg: float = 0.5, ground: tuple[float, float] | None = None,
                ground_tolerance: float = 0.15) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(range_m, valid, notes)``: dense (H, W) float32 range along the pixel rays (``inf`` sky) from a LiDAR scan
    (module docstring). ``guide_srgb`` (H, W, 3) in [0, 1] guides ``bilateral``. ``ground`` = (camera height m,
    pitch rad): below the lowest return of a column that lies on that flat ground (its range within
    ``ground_tolerance``, relative, of the ground plane's), the ground plane continues the depth instead of the
    nearest return. ValueError when no return falls in the image."""
    if densify not in DENSIFY:
        raise ValueError(f"unknown densify {densify!r}; expected one of {DENSIFY}")
    shape = (height_px, width_px)
    rows, cols, rng, elev = project_returns(points_m, lidar_to_camera, intrinsics_px, width_px, height_px)
    n_projected = rows.size
    seen = drop_occluded(rows, cols, rng, shape, occlusion_window_px, occlusion_tolerance)
    rows, cols, rng, elev = rows[seen], cols[seen], rng[seen], elev[seen]
    if rows.size == 0:
        raise ValueError("no LiDAR return falls in the camera image: check the calibration (lidar_to_camera, K)")
    known = np.zeros(shape, dtype=bool)
    known[rows, cols] = True
    inverse = np.zeros(shape, dtype=np.float32)
    inverse[rows, cols] = 1.0 / rng
    dense = nearest_fill(inverse, known)
    if densify == "bilateral":
        guide = np.asarray(guide_srgb, dtype=np.float32)
        dense = cv2.ximgproc.jointBilateralFilter(guide, dense, d=9, sigmaColor=0.1, sigmaSpace=4.0)
        dense[known] = inverse[known]
    top, bottom, clipped = column_extent(rows, cols, rng, elev, width_px, np.radians(top_beam_tolerance_deg))
    r = np.arange(height_px)[:, None]
    sky = (r < top[None, :]) & ~clipped[None, :]
    with np.errstate(divide="ignore"):
        depth = np.float32(1.0) / dense
    depth[sky] = np.inf
    below = r > bottom[None, :]
    n_ground = 0
    if ground is not None:
        plane = ground_plane_range(intrinsics_px, width_px, height_px, camera_height_m=ground[0],
                                   pitch_rad=ground[1], sky_distance_m=np.inf)
        columns = np.arange(width_px)
        lowest = depth[bottom, columns]
        on_ground = np.abs(lowest - plane[bottom, columns]) <= ground_tolerance * lowest
        use = below & on_ground[None, :]
        depth[use] = plane[use]
        n_ground = int(np.count_nonzero(use))
    valid = sky | ((r >= top[None, :]) & ~below)
    notes = {"returns_in_image": int(n_projected), "returns_used": int(rows.size),
             "hidden_by_parallax": int(n_projected - rows.size), "densify": densify,
             "return_pixel_fraction": round(rows.size / (width_px * height_px), 6),
             "sky_fraction": round(float(sky.mean()), 6), "valid_fraction": round(float(valid.mean()), 6),
             "ground_plane_fraction": round(n_ground / (width_px * height_px), 6)}
    return depth, valid, notes
