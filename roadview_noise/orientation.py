"""Photos stored turned or mirrored (EXIF/TIFF orientation 2–8, CIPA DC-008 §4.6.4) processed upright, as displayed.

A phone picture taken sideways, a dashcam mounted upside down: the file stores the pixels as the sensor read them
and an orientation tag tells a viewer how to turn them. The chain has directions (rain and snow fall down, the
ground-plane road lies at the bottom, a depth network was trained on upright photos), so such a frame is turned
upright on load (:func:`upright` on the pixels and every array aligned with them: alpha, depth sidecar, LiDAR depth;
the camera intrinsics with :func:`upright_profile`), the chain runs upright, and :func:`as_stored` turns the result
back before labels move and the file is written: the output keeps the input's tag and stored layout and displays
like the input, with the weather falling down the displayed image. Labels stay in stored pixel coordinates: a
geometric step's upright map is conjugated by the coordinate change (:class:`StoredWarp`), so the label movers
(masks, KITTI/YOLO boxes, COCO outlines and keypoints) move stored-coordinate labels through it unchanged.

Each orientation is ``(transpose, flip columns, flip rows)`` applied to the stored array in that order (pixel
centres on integers, so a flip maps ``x`` to ``W − 1 − x``); :func:`upright` turns pixels as
``PIL.ImageOps.exif_transpose`` does.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .physics.warp import Warp
from .types import CameraFrame, CameraProfile, RawFrame

# orientation → (transpose, flip columns, flip rows) taking the stored pixels to the displayed ones
_STEPS = {1: (False, False, False), 2: (False, True, False), 3: (False, True, True), 4: (False, False, True),
          5: (True, False, False), 6: (True, True, False), 7: (True, True, True), 8: (True, False, True)}


def transposes(turn: int) -> bool:
    """True when the orientation swaps width and height (5–8)."""
    return _STEPS[turn][0]


def upright(array: np.ndarray, turn: int) -> np.ndarray:
    """An (H, W[, C]) array stored with orientation ``turn`` as displayed (a new array; the array itself for 1)."""
    if turn == 1:
        return array
    swap, flip_x, flip_y = _STEPS[turn]
    return _flipped(_opencv(cv2.transpose, array) if swap else array, flip_x, flip_y)


def stored(array: np.ndarray, turn: int) -> np.ndarray:
    """The inverse of :func:`upright`: an upright (H, W[, C]) array back in the stored layout."""
    if turn == 1:
        return array
    swap, flip_x, flip_y = _STEPS[turn]
    a = _flipped(array, flip_x, flip_y)
    return _opencv(cv2.transpose, a) if swap else a


def _flipped(array: np.ndarray, flip_x: bool, flip_y: bool) -> np.ndarray:
    if not (flip_x or flip_y):
        return array
    return _opencv(cv2.flip, array, -1 if flip_x and flip_y else int(flip_x))


def _opencv(op, array: np.ndarray, *args) -> np.ndarray:
    """``op`` (OpenCV: 5–7× faster than NumPy's strided copy on a float RGB frame) of any (H, W[, C]) array."""
    a = np.ascontiguousarray(array)
    out = op(a.view(np.uint8) if a.dtype == bool else a, *args)
    out = out.reshape(out.shape[:2] + a.shape[2:])                       # (H, W, 1) stays 3-D
    return out.view(bool) if a.dtype == bool else out


def stored_shape(data) -> tuple[int, int]:
    """The (H, W) of a frame's stored pixels (a frame processed upright: :func:`upright_frame`)."""
    turn = getattr(data, "orientation", 1)
    return data.shape[::-1] if turn != 1 and transposes(turn) else data.shape


def upright_xy(points_xy: np.ndarray, turn: int, stored_shape: tuple[int, int]) -> np.ndarray:
    """Stored pixel coordinates (N, 2) x, y of an image of ``stored_shape`` (H, W) as upright ones."""
    swap, flip_x, flip_y = _STEPS[turn]
    h, w = stored_shape[::-1] if swap else stored_shape
    q = np.array(points_xy, dtype=np.float64).reshape(-1, 2)
    if swap:
        q = q[:, ::-1].copy()
    if flip_x:
        q[:, 0] = (w - 1) - q[:, 0]
    if flip_y:
        q[:, 1] = (h - 1) - q[:, 1]
    return q


def stored_xy(points_xy: np.ndarray, turn: int, upright_shape: tuple[int, int]) -> np.ndarray:
    """The inverse of :func:`upright_xy`: upright pixel coordinates of an image of ``upright_shape`` as stored."""
    swap, flip_x, flip_y = _STEPS[turn]
    h, w = upright_shape
    q = np.array(points_xy, dtype=np.float64).reshape(-1, 2)
    if flip_x:
        q[:, 0] = (w - 1) - q[:, 0]
    if flip_y:
        q[:, 1] = (h - 1) - q[:, 1]
    return q[:, ::-1].copy() if swap else q


def upright_profile(profile: CameraProfile, turn: int) -> CameraProfile:
    """The intrinsics of the stored pixels (a calibration, a profile fitted to the stored size) for the upright
    image: a transpose swaps the axes (f_x ↔ f_y, c_x ↔ c_y, W ↔ H), a flip maps ``c`` to ``W − 1 − c``."""
    if turn == 1:
        return profile
    swap, flip_x, flip_y = _STEPS[turn]
    w, h, fx, fy, cx, cy = (profile.width_px, profile.height_px, profile.fx_px, profile.fy_px, profile.cx_px,
                            profile.cy_px)
    if swap:
        w, h, fx, fy, cx, cy = h, w, fy, fx, cy, cx
    return dataclasses.replace(profile, width_px=w, height_px=h, fx_px=fx, fy_px=fy,
                               cx_px=(w - 1) - cx if flip_x else cx, cy_px=(h - 1) - cy if flip_y else cy)


@dataclasses.dataclass(frozen=True, eq=False)
class StoredWarp(Warp):
    """A geometric step's map made in the upright frame (``upright_warp``, inputs the size of its output), in
    stored pixel coordinates: ``map_x, map_y`` are its pull map turned back and re-expressed in stored
    coordinates, and :meth:`forward` goes through the upright warp's own (exact, where it has one) forward map."""

    upright_warp: Warp | None = None
    turn: int = 1

    @classmethod
    def of(cls, warp: Warp, turn: int) -> "StoredWarp":
        swap, flip_x, flip_y = _STEPS[turn]
        h, w = warp.shape
        mx = (w - 1) - warp.map_x if flip_x else warp.map_x
        my = (h - 1) - warp.map_y if flip_y else warp.map_y
        if swap:
            mx, my = my, mx                             # the stored x is the upright y
        return cls(stored(mx.astype(np.float32, copy=False), turn), stored(my.astype(np.float32, copy=False), turn),
                   upright_warp=warp, turn=turn)

    @property
    def distortion(self):
        """The upright warp's Brown–Conrady distortion in stored coordinates (or None): flips change the signs of
        the tangential and prism terms along the flipped axis, a transpose swaps p1 ↔ p2, (s1, s2) ↔ (s3, s4), the
        units and the centre's axes (the centre moves as a pixel does)."""
        from .physics.brown_conrady import BrownConrady

        bc = getattr(self.upright_warp, "distortion", None)
        if bc is None:
            return None
        swap, flip_x, flip_y = _STEPS[self.turn]
        sx, sy = (-1.0 if flip_x else 1.0), (-1.0 if flip_y else 1.0)
        k1, k2, k3, k4, k5, k6, p1, p2, s1, s2, s3, s4 = bc.coefficients
        p1, p2, s1, s2, s3, s4 = sy * p1, sx * p2, sx * s1, sx * s2, sy * s3, sy * s4
        unit = bc.unit_px
        if swap:
            p1, p2, s1, s2, s3, s4, unit = p2, p1, s3, s4, s1, s2, unit[::-1]
        centre = stored_xy([bc.centre_px], self.turn, self.upright_warp.shape)[0]
        return BrownConrady((k1, k2, k3, k4, k5, k6, p1, p2, s1, s2, s3, s4), (float(centre[0]), float(centre[1])),
                            (float(unit[0]), float(unit[1])))

    def forward(self, points_xy: np.ndarray, iterations: int = 20) -> np.ndarray:
        size = self.upright_warp.shape
        q = upright_xy(points_xy, self.turn, self.shape)
        return stored_xy(self.upright_warp.forward(q), self.turn, size)


def upright_frame(frame: CameraFrame | RawFrame, turn: int) -> CameraFrame | RawFrame:
    """A frame read as stored, turned upright (pixels with their sRGB codes, alpha; a raw mosaic with its CFA
    pattern), remembering ``turn``."""
    return _turned(frame, upright, turn, orientation=turn, profile=upright_profile(frame.profile, turn))


def cfa_pattern(pattern: str, turn: int, shape: tuple[int, int], to_upright: bool) -> str:
    """The 2×2 CFA pattern (colours of the top-left sites, row by row) of a mosaic of ``shape`` (H, W, as it is now)
    turned upright by ``turn`` (``to_upright``), or turned back to its stored layout: each new top-left site's
    colour is that of the site it comes from (a flip of an even side shifts the phase)."""
    sites = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float64)       # x, y of the new top-left 2×2
    swap = transposes(turn)
    new_shape = shape[::-1] if swap else shape
    src = stored_xy(sites, turn, new_shape) if to_upright else upright_xy(sites, turn, new_shape)
    src = np.rint(src).astype(int)
    return "".join(pattern[(y % 2) * 2 + x % 2] for x, y in src)


def as_stored(frame):
    """A frame processed upright (:func:`upright_frame`) back in its stored layout — pixels, alpha, depth, profile
    and the chain's warps (:class:`StoredWarp`) — so it is written and its labels move as stored; other data as is."""
    turn = getattr(frame, "orientation", 1)
    if turn == 1:
        return frame
    inverse = {6: 8, 8: 6}.get(turn, turn)              # the other orientations are their own inverse
    return _turned(frame, stored, turn, orientation=1, profile=upright_profile(frame.profile, inverse),
                   warps=tuple(StoredWarp.of(w, turn) for w in frame.warps))


def _turned(frame: CameraFrame | RawFrame, move, turn: int, **fields) -> CameraFrame | RawFrame:
    """``frame`` with every pixel-aligned array moved by ``move(array, turn)`` and ``fields`` replaced; 8-bit sRGB
    codes the pixels hold move along (a permutation keeps their decoding exact); a mosaic's CFA pattern follows."""
    from .physics import srgb

    aligned = {k: move(getattr(frame, k), turn) for k in ("alpha", "depth_m", "depth_valid")
               if getattr(frame, k, None) is not None}
    if isinstance(frame, RawFrame):
        pattern = cfa_pattern(frame.cfa_pattern, turn, frame.shape, to_upright=move is upright)
        return dataclasses.replace(frame, dn=move(frame.dn, turn), cfa_pattern=pattern, **aligned, **fields)
    codes = frame.undecoded_srgb8_codes()
    if codes is not None:                               # not decoded: the moved codes stand in until replaced
        codes = move(codes, turn)
        return dataclasses.replace(frame, linear_rgb=codes, **aligned, **fields).with_srgb8_codes(codes)
    linear = move(frame.linear_rgb, turn)
    for bits in (8, 16):
        kept = srgb.attached_codes(frame.linear_rgb, bits)
        if kept is not None:
            srgb.attach_codes(linear, move(kept, turn), bits)
    return dataclasses.replace(frame, linear_rgb=linear, **aligned, **fields)
