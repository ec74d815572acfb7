"""Brown–Conrady distortion (models.md §2.5): rational radial k1–k6, tangential p1–p2, thin prism s1–s4 — the
model of OpenCV's camera calibration — as a pull map for the image and a forward map for annotations.

Distortion coordinates are ``x = (u − c_x)/f_x``, ``y = (v − c_y)/f_y`` with ``r² = x² + y²``:

    x_d = x·(1 + k1 r² + k2 r⁴ + k3 r⁶)/(1 + k4 r² + k5 r⁴ + k6 r⁶) + 2 p1 x y + p2 (r² + 2x²) + s1 r² + s2 r⁴
    y_d = y·(same ratio)                                            + p1 (r² + 2y²) + 2 p2 x y + s3 r² + s4 r⁴

and the output pixel ``(u, v)`` samples the input at ``(c_x + f_x x_d, c_y + f_y y_d)`` (a *pull* map, as in the
D3.5 library). ``f`` is the focal length in pixels for normalised coefficients, or the pixel size of the D3.5
reference units (1 px of a 1936-px-wide image, scaled with the image width) for coefficients in px⁻².
Every pixel is computed directly (no quadrant mirroring, which breaks the tangential terms: models.md §2.5 [BUG]).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bilinear_table import TabledWarp
from .compiled import jit

COEFFICIENTS = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "s1", "s2", "s3", "s4")
NEWTON_ITERATIONS = 30
NEWTON_TOLERANCE_PX = 1e-7


@dataclass(frozen=True)
class BrownConrady:
    """Distortion with ``coefficients`` in :data:`COEFFICIENTS` order, around ``centre_px`` (c_x, c_y), with
    ``unit_px`` (f_x, f_y) pixels per distortion-coordinate unit."""

    coefficients: tuple[float, ...]
    centre_px: tuple[float, float]
    unit_px: tuple[float, float]

    def __post_init__(self):
        if len(self.coefficients) != len(COEFFICIENTS):
            raise ValueError(f"{len(COEFFICIENTS)} coefficients expected ({', '.join(COEFFICIENTS)})")

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted coordinates of (x, y) in distortion units (float64 arrays, broadcast)."""
        return _distort(np.asarray(x, np.float64), np.asarray(y, np.float64), self._c)

    def _jacobian(self, x: np.ndarray, y: np.ndarray):
        """Partial derivatives (∂x_d/∂x, ∂x_d/∂y, ∂y_d/∂x, ∂y_d/∂y) in distortion units."""
        return _jacobian(x, y, self._c)

    @property
    def _c(self) -> np.ndarray:
        return np.asarray(self.coefficients, np.float64)

    def pull_map(self, height: int, width: int) -> "LensWarp":
        """The pull map of an image of ``height`` × ``width`` pixels (float32 maps, output the input size; each
        pixel computed in float64 in one compiled pass)."""
        (cx, cy), (fx, fy) = self.centre_px, self.unit_px
        map_x, map_y = _pull_grid(height, width, cx, cy, fx, fy, self._c)
        return LensWarp(map_x, map_y, self)

    def undistort_px(self, points_xy: np.ndarray) -> np.ndarray:
        """Output pixel positions (N, 2) whose pull-map source is ``points_xy`` (the forward map of annotations):
        Newton's method on the closed-form model with its analytic Jacobian. Points with no solution on the
        unfolded part of the map (beyond the largest pull radius of a strong negative k1) are NaN."""
        p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        (cx, cy), (fx, fy) = self.centre_px, self.unit_px
        tx, ty = (p[:, 0] - cx) / fx, (p[:, 1] - cy) / fy
        x, y = tx.copy(), ty.copy()
        tol = NEWTON_TOLERANCE_PX / max(fx, fy)
        for _ in range(NEWTON_ITERATIONS):
            xd, yd = self.distort(x, y)
            ex, ey = xd - tx, yd - ty
            a, b, c, d = self._jacobian(x, y)
            det = a * d - b * c
            with np.errstate(divide="ignore", invalid="ignore"):
                dx = (d * ex - b * ey) / det
                dy = (a * ey - c * ex) / det
            x -= dx
            y -= dy
            if np.all(np.abs(dx) + np.abs(dy) < tol):
                break
        xd, yd = self.distort(x, y)
        a, b, c, d = self._jacobian(x, y)
        num, den = _radial(x * x + y * y, self._c)
        # a solution on a folded-over branch of the map (the radial factor or the Jacobian changed sign) is no
        # position any output pixel shows
        ok = (np.hypot((xd - tx) * fx, (yd - ty) * fy) < 1e-4) & (a * d - b * c > 0) & (num / den > 0)
        return np.where(ok[:, None], np.stack([cx + fx * x, cy + fy * y], axis=1), np.nan)


# The model's formulas, compiled: each works on scalars and on (broadcast) arrays alike; c = the coefficients in
# COEFFICIENTS order (float64 array).

@jit
def _radial(r2, c):                                           # pragma: no cover - compiled
    """Numerator and denominator of the rational radial factor at r²."""
    return 1 + r2 * (c[0] + r2 * (c[1] + r2 * c[2])), 1 + r2 * (c[3] + r2 * (c[4] + r2 * c[5]))


@jit
def _distort(x, y, c):                                        # pragma: no cover - compiled
    p1, p2, s1, s2, s3, s4 = c[6], c[7], c[8], c[9], c[10], c[11]
    r2 = x * x + y * y
    num, den = _radial(r2, c)
    radial = num / den
    xy2 = 2 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x) + r2 * (s1 + s2 * r2)
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2 + r2 * (s3 + s4 * r2)
    return xd, yd


@jit
def _jacobian(x, y, c):                                       # pragma: no cover - compiled
    k1, k2, k3, k4, k5, k6, p1, p2, s1, s2, s3, s4 = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], \
        c[9], c[10], c[11]
    r2 = x * x + y * y
    num, den = _radial(r2, c)
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    radial = num / den
    dradial = (dnum * den - num * dden) / (den * den)      # d(radial)/d(r²)
    sx = s1 + 2 * s2 * r2                                  # d(s1 r² + s2 r⁴)/d(r²)
    sy = s3 + 2 * s4 * r2
    a = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x + 2 * x * sx
    b = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y + 2 * y * sx
    cc = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y + 2 * x * sy
    d = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x + 2 * y * sy
    return a, b, cc, d


@jit
def _pull_grid(height, width, cx, cy, fx, fy, c):             # pragma: no cover - compiled
    """Pull map (map_x, map_y), float32 (height, width): output pixel (u, v) samples (c_x + f_x x_d, c_y + f_y y_d)."""
    map_x = np.empty((height, width), np.float32)
    map_y = np.empty((height, width), np.float32)
    for v in range(height):
        y = (v - cy) / fy
        for u in range(width):
            xd, yd = _distort((u - cx) / fx, y, c)
            map_x[v, u] = cx + fx * xd
            map_y[v, u] = cy + fy * yd
    return map_x, map_y


@dataclass(frozen=True, eq=False)
class LensWarp(TabledWarp):
    """A :class:`~roadview_noise.physics.warp.Warp` whose forward map is the exact inverse of its Brown–Conrady
    pull map (Newton), not the generic fixed-point inversion of the sampled map; it resamples through a bilinear
    table (:class:`~roadview_noise.physics.bilinear_table.TabledWarp`)."""

    distortion: BrownConrady | None = None

    def forward(self, points_xy: np.ndarray, iterations: int = NEWTON_ITERATIONS) -> np.ndarray:
        """Output positions of input points; a point no output position sees (beyond a fold of the map) is put
        far outside the image in its direction from the centre, so clipping to the image puts it on the edge."""
        q = self.distortion.undistort_px(points_xy)
        lost = np.isnan(q[:, 0])
        if lost.any():
            c = np.asarray(self.distortion.centre_px)
            p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)[lost] - c
            far = 4.0 * float(np.hypot(*self.shape))
            q[lost] = c + p * (far / np.maximum(np.hypot(p[:, 0], p[:, 1]), 1e-12))[:, None]
        return q
