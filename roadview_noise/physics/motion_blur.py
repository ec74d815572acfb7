"""Motion blur during the exposure (models.md §2.6): D3.5's radial zoom blur in closed form, and the physical blur
along the optical flow of a translating and yawing camera.

Both kernels read and write planes (H, W, C) of float32 with reflect-101 borders (the reference's constant black
border darkened the frame edge: models.md §2.6 [BUG]) and take the geometry of the plane in *full-image* pixel
coordinates through ``stride`` and ``offset``: plane pixel (a, b) is image pixel (stride·b + off_x, stride·a + off_y).
An RGB image is one plane (stride 1); a Bayer mosaic is four sub-lattice planes (stride 2, offsets the 2×2 phase),
so each colour is blurred from sites of its own colour, without demosaicking.
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import jit

MAX_FLOW_SAMPLES = 256


def zoom_blur_taps(blur: float, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Scale factors and weights of D3.5's iterated radial blur: ``J_{k+1}(p) = ½ J_k(c + (1+b)(p − c)) +
    ½ J_k(c + (1−b)(p − c))`` applied n times is ``Σ_j C(n, j)/2ⁿ · I(c + (1+b)^j (1−b)^(n−j) (p − c))``."""
    j = np.arange(iterations + 1)
    scales = (1 + blur) ** j * (1 - blur) ** (iterations - j)
    weights = np.array([math.comb(iterations, int(k)) for k in j], dtype=np.float64) / 2.0 ** iterations
    return scales, weights.astype(np.float32)


def _reflect_taps(size: int, centre: float, scales: np.ndarray, stride: int, offset: int):
    """Per tap and plane index: lower source index and bilinear fraction of ``centre + s (x − centre)`` in plane
    coordinates, reflected (reflect-101) into the plane."""
    x = stride * np.arange(size, dtype=np.float64) + offset
    pos = (centre + scales[:, None] * (x[None, :] - centre) - offset) / stride
    period = 2.0 * (size - 1)
    pos = np.abs(np.mod(pos, period))
    pos = np.where(pos > size - 1, period - pos, pos)
    i0 = np.minimum(np.floor(pos), size - 2).astype(np.int32)
    return i0, (pos - i0).astype(np.float32)


@jit(fastmath=True)
def _zoom_kernel(src, weights, row_i0, row_f, col_i0, col_f, out):          # pragma: no cover - compiled
    """``out(p) = Σ_j w_j · bilinear(src, tap j)`` with separable taps: each output row takes for tap j a vertical
    lerp of two source rows (one SIMD pass over the row) and then a horizontal gather-lerp along it."""
    h, w, nch = src.shape
    n = w * nch
    flat = src.reshape(h, n)
    out_flat = out.reshape(h, n)
    row = np.zeros(n + nch, np.float32)
    for y in range(h):
        o = out_flat[y]
        for i in range(n):
            o[i] = 0.0
        for j in range(weights.shape[0]):
            r0 = flat[row_i0[j, y]]
            r1 = flat[row_i0[j, y] + 1]
            f = row_f[j, y]
            wj = weights[j]
            for i in range(n):
                row[i] = wj * (r0[i] + f * (r1[i] - r0[i]))
            ci = col_i0[j]
            cf = col_f[j]
            if nch == 3:                       # unrolled: a runtime channel loop keeps LLVM from vectorising
                for x in range(w):
                    k = ci[x] * 3
                    g = cf[x]
                    a0, a1, a2 = row[k], row[k + 1], row[k + 2]
                    o[3 * x] += a0 + g * (row[k + 3] - a0)
                    o[3 * x + 1] += a1 + g * (row[k + 4] - a1)
                    o[3 * x + 2] += a2 + g * (row[k + 5] - a2)
            elif nch == 1:
                for x in range(w):
                    k = ci[x]
                    a0 = row[k]
                    o[x] += a0 + cf[x] * (row[k + 1] - a0)
            else:
                for x in range(w):
                    k = ci[x] * nch
                    g = cf[x]
                    for c in range(nch):
                        a = row[k + c]
                        o[x * nch + c] += a + g * (row[k + nch + c] - a)


def zoom_blur(plane: np.ndarray, centre_px: tuple[float, float], blur: float, iterations: int, *, stride: int = 1,
              offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """D3.5's radial blur of a plane (H, W, C) around ``centre_px`` (image coordinates), in closed form: the
    binomial taps of :func:`zoom_blur_taps` sampled once each from the input (the reference resampled 2n times,
    which adds interpolation blur; the kernel is the same). Needs H, W ≥ 2."""
    plane = np.ascontiguousarray(plane, dtype=np.float32)
    h, w = plane.shape[:2]
    scales, weights = zoom_blur_taps(blur, iterations)
    row_i0, row_f = _reflect_taps(h, centre_px[1], scales, stride, offset[1])
    col_i0, col_f = _reflect_taps(w, centre_px[0], scales, stride, offset[0])
    out = np.empty_like(plane)
    _zoom_kernel(plane, weights, row_i0, row_f, col_i0, col_f, out)
    return out


@jit(fastmath=True, inline="always")
def _reflect(p, size):                                                       # pragma: no cover - compiled
    period = 2.0 * (size - 1)
    p = abs(p) % period
    return period - p if p > size - 1 else p


@jit(fastmath=True)
def _flow_kernel(src, depth, const_depth, stride, off_x, off_y, cx, cy, fx, fy, vel, yaw_rate, exposure_s,
                 step_px, out, stats):                                      # pragma: no cover - compiled
    """Box blur along each site's flow; ``stats`` gets (sum, max) of the blur lengths in image pixels."""
    h, w, nch = src.shape
    total = 0.0
    longest = 0.0
    for a in range(h):
        v = stride * a + off_y
        yn = (v - cy) / fy
        for b in range(w):
            u = stride * b + off_x
            xn = (u - cx) / fx
            if const_depth > 0.0:
                inv_z = 1.0 / const_depth                                  # a fronto-parallel plane at Z
            else:
                d = depth[a, b]                                            # range along the ray
                inv_z = 0.0
                if d > 0.0 and d < np.inf:
                    inv_z = math.sqrt(1.0 + xn * xn + yn * yn) / d        # planar depth z = d / |ray|
            flow_u = (vel[2] * (u - cx) - fx * vel[0]) * inv_z + yaw_rate * fx * (1.0 + xn * xn)
            flow_v = (vel[2] * (v - cy) - fy * vel[1]) * inv_z + yaw_rate * fy * xn * yn
            du = flow_u * exposure_s / stride                              # plane pixels over the exposure
            dv = flow_v * exposure_s / stride
            length = math.sqrt(du * du + dv * dv)
            total += length
            longest = max(longest, length)
            n = min(1 + int(math.ceil(length / step_px)), MAX_FLOW_SAMPLES) if length > 1e-6 else 1
            s0 = s1 = s2 = np.float32(0.0)
            for k in range(n):
                t = (k + 0.5) / n - 0.5
                px = b + t * du
                py = a + t * dv
                if px < 0.0 or px > w - 1:
                    px = _reflect(px, w)
                if py < 0.0 or py > h - 1:
                    py = _reflect(py, h)
                x0 = min(int(px), w - 2)
                y0 = min(int(py), h - 2)
                gx = np.float32(px - x0)
                gy = np.float32(py - y0)
                w00 = (1 - gx) * (1 - gy)
                w01 = gx * (1 - gy)
                w10 = (1 - gx) * gy
                w11 = gx * gy
                s0 += w00 * src[y0, x0, 0] + w01 * src[y0, x0 + 1, 0] + w10 * src[y0 + 1, x0, 0] + \
                    w11 * src[y0 + 1, x0 + 1, 0]
                if nch == 3:
                    s1 += w00 * src[y0, x0, 1] + w01 * src[y0, x0 + 1, 1] + w10 * src[y0 + 1, x0, 1] + \
                        w11 * src[y0 + 1, x0 + 1, 1]
                    s2 += w00 * src[y0, x0, 2] + w01 * src[y0, x0 + 1, 2] + w10 * src[y0 + 1, x0, 2] + \
                        w11 * src[y0 + 1, x0 + 1, 2]
            out[a, b, 0] = s0 / n
            if nch == 3:
                out[a, b, 1] = s1 / n
                out[a, b, 2] = s2 / n
    stats[0] += total * stride
    stats[1] = max(stats[1], longest * stride)


def flow_blur(plane: np.ndarray, depth_m: np.ndarray | None, *, scene_depth_m: float, intrinsics, velocity_m_per_s,
              yaw_rate_rad_per_s: float, exposure_time_s: float, step_px: float = 1.0, stride: int = 1,
              offset: tuple[int, int] = (0, 0), stats: np.ndarray | None = None) -> np.ndarray:
    """Box blur along the optical flow over the exposure (models.md §2.6 [PROP], physical mode), the input being
    the image at mid-exposure: ``J(p) = mean over τ ∈ [−T/2, T/2] of I(p − τ·ḟ(p))`` with the flow of a static
    scene seen by a camera translating with ``velocity_m_per_s`` (camera frame: x right, y down, z forward) and
    yawing left at ``yaw_rate_rad_per_s``:
    ``ḟ = ((v_z (u − c_x) − f_x v_x)/Z + ω f_x (1 + x²), (v_z (v − c_y) − f_y v_y)/Z + ω f_y x y)``, Z the planar
    depth (from the range map ``depth_m``, or a fronto-parallel plane at Z = ``scene_depth_m`` when ``depth_m`` is
    None; sky has no translation flow), (x, y) normalised coordinates. The translation term is exact for a static point at the pixel's depth;
    the rotation term is first order in ω T. Samples ≤ ``step_px`` apart (two at least for any motion, so a
    sub-pixel blur still softens) (at most ``MAX_FLOW_SAMPLES`` per pixel); the blur of a
    straight drive at constant depth is a radial box of length r·v T/Z about the focus of expansion. ``stats``
    (float64 (2,)), if given, accumulates the sum and the maximum of the blur lengths in image pixels."""
    plane = np.ascontiguousarray(plane, dtype=np.float32)
    if min(plane.shape[:2]) < 2 or plane.shape[2] not in (1, 3):
        raise ValueError("flow blur needs planes of at least 2×2 sites with 1 or 3 channels")
    fx, fy, cx, cy = intrinsics
    const = float(scene_depth_m) if depth_m is None else 0.0
    depth = (np.zeros((1, 1), np.float32) if depth_m is None else
             np.ascontiguousarray(depth_m[offset[1]::stride, offset[0]::stride], dtype=np.float32))
    out = np.empty_like(plane)
    _flow_kernel(plane, depth, const, stride, offset[0], offset[1], float(cx), float(cy), float(fx), float(fy),
                 np.asarray(velocity_m_per_s, dtype=np.float64), float(yaw_rate_rad_per_s), float(exposure_time_s),
                 float(step_px), out, np.zeros(2) if stats is None else stats)
    return out
