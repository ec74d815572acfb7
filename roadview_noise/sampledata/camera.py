"""Camera rendering for the sample drive: linear RGB radiance, range along the ray, and an RGGB Bayer mosaic.

Camera frame: OpenCV pinhole (x right, y down, z forward along the vehicle's +x), no rotation against the vehicle.
Pixel (u, v) = (column, row) looks along ``K⁻¹ (u, v, 1)``: integer pixel indices are pixel centres, the convention of
``roadview_noise.units.planar_depth_to_range``. Shading is Lambertian: ``albedo · (ambient · (3 + n_z)/4 + sun ·
max(0, n·s) · lit)`` with a hard sun shadow from a second ray cast, and a sky gradient for rays that hit nothing.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..types import CameraProfile, cfa_index_map
from .scene import Hits, Snapshot, surface_properties

AMBIENT = 0.30                   # sky irradiance on a horizontal surface, as linear radiance of a white diffuser
SUN = 0.80                       # direct sun at normal incidence, same scale (white ρ = 0.75 lit: ≈ 0.82)
SKY_HORIZON = np.array([0.62, 0.70, 0.82])
SKY_ZENITH = np.array([0.18, 0.32, 0.68])
SHADOW_OFFSET_M = 2e-3           # start shadow rays off the surface


@lru_cache(maxsize=8)
def ray_directions(profile: CameraProfile) -> np.ndarray:
    """Unit ray directions (H, W, 3) in vehicle axes (x forward, y left, z up) for every pixel centre."""
    u = (np.arange(profile.width_px, dtype=np.float64) - profile.cx_px) / profile.fx_px
    v = (np.arange(profile.height_px, dtype=np.float64) - profile.cy_px) / profile.fy_px
    uu, vv = np.meshgrid(u, v)
    d = np.stack([np.ones_like(uu), -uu, -vv], axis=-1)     # camera (x_c, y_c, z_c) → vehicle (z_c, −x_c, −y_c)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d.setflags(write=False)
    return d


def sky_radiance(directions: np.ndarray) -> np.ndarray:
    """Linear RGB sky: horizon to zenith blend by the square root of the ray's sine of elevation."""
    s = np.sqrt(np.clip(directions[..., 2:3], 0.0, 1.0))
    return (1 - s) * SKY_HORIZON + s * SKY_ZENITH


def render(snapshot: Snapshot, profile: CameraProfile, origin_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB (H, W, 3) float32 and range along the ray (H, W) float32, ``inf`` for sky."""
    h, w = profile.height_px, profile.width_px
    d = ray_directions(profile).reshape(-1, 3)
    hits = snapshot.cast(origin_m, d)
    hit = hits.hit
    rgb = sky_radiance(d)
    t = hits.t_m[hit]
    p = origin_m + t[:, None] * d[hit]
    sub = Hits(t, hits.normal[hit], hits.material[hit], hits.object_index[hit])
    albedo, _ = surface_properties(p, sub)
    sun = snapshot.scene.sun_direction
    cos_sun = sub.normal @ sun
    facing = cos_sun > 0
    lit = np.zeros(len(t), dtype=bool)
    lit[facing] = ~snapshot.occluded(p[facing] + SHADOW_OFFSET_M * sub.normal[facing], sun)
    irradiance = AMBIENT * (3.0 + sub.normal[:, 2]) / 4.0 + SUN * np.where(lit, cos_sun, 0.0)
    rgb[hit] = albedo * irradiance[:, None]
    depth = np.where(hit, hits.t_m, np.inf)
    return rgb.reshape(h, w, 3).astype(np.float32), depth.reshape(h, w).astype(np.float32)


def mosaic(linear_rgb: np.ndarray, pattern: str, black_level_dn: int, white_level_dn: int) -> np.ndarray:
    """Bayer digital numbers (H, W) uint16: each site keeps its CFA colour, ``black + signal · (white − black)``."""
    h, w = linear_rgb.shape[:2]
    idx = cfa_index_map(pattern, h, w)
    signal = np.take_along_axis(linear_rgb, idx[..., None].astype(np.int64), axis=2)[..., 0]
    dn = black_level_dn + np.clip(signal, 0.0, 1.0) * (white_level_dn - black_level_dn)
    return np.rint(dn).astype(np.uint16)
