"""``sensor_msgs/CameraInfo`` → the pinhole intrinsics of the images it describes (README "ROS bags").

CameraInfo.msg and REP 104: ``K`` (3×3, row-major) is the camera matrix of the raw (distorted) image, ``P`` (3×4)
the projection of the rectified image (its left 3×3 is that image's camera matrix); both are given for the
calibration resolution ``width`` × ``height`` (normally the full sensor). ``binning_x``/``binning_y`` (0 ≡ 1)
combine b × b pixels into one, and ``roi`` (all zeros ≡ the full image) is the window read out, in full-resolution,
unbinned pixels: the published image is ``⌊roi.width / binning_x⌋ × ⌊roi.height / binning_y⌋``. ``K[0] == 0``
marks an uncalibrated camera. ``D`` (``distortion_model``: ``plumb_bob`` k1 k2 t1 t2 k3, ``rational_polynomial``
k1 k2 t1 t2 k3 k4 k5 k6, ``equidistant`` k1 k2 k3 k4) describes the lens distortion of the raw image.

rvnoise's camera models are pinhole (:class:`..types.CameraProfile`): they take fx, fy, cx, cy and nothing of D.
:func:`distortion_shift_px` measures what that costs (the largest distance on the image border between where the
lens puts a ray and where the pinhole K puts it), so the manifest and the run's warning can say it.

ROI and binning map pixel centres, which sit at integer coordinates (OpenCV): a binned pixel k covers full pixels
``b·k … b·k + b − 1``, its centre is at ``b·k + (b − 1)/2``, so ``c' = (c − offset + ½)/b − ½`` and ``f' = f/b``
(image_geometry's ``c/b`` is half a full pixel off for b = 2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from .ros_messages import CAMERA_INFO

__all__ = ["CAMERA_INFO", "CameraInfoIntrinsics", "camera_info_intrinsics", "camera_info_topic", "default_matrix",
           "distortion_shift_px"]
TRANSPORT_SUBTOPICS = ("compressed",)          # image_transport's sub-topic of a CompressedImage stream
DISTORTION_COEFFICIENTS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}


def camera_info_topic(image_topic: str) -> str:
    """The CameraInfo topic of an image topic by ROS convention (CameraInfo.msg; image_transport): ``camera_info``
    in the image's namespace, the transport sub-topic (``…/compressed``) dropped:
    ``/cam/image_raw`` and ``/cam/image_raw/compressed`` → ``/cam/camera_info``."""
    base = image_topic.rstrip("/")
    head, _, last = base.rpartition("/")
    if last in TRANSPORT_SUBTOPICS and head:
        base = head
    return f"{base.rpartition('/')[0]}/camera_info"


def default_matrix(image_topic: str) -> str:
    """``P`` for a rectified image (the image pipeline's ``image_rect``/``image_rect_color``), else ``K``."""
    base = image_topic.rstrip("/")
    head, _, last = base.rpartition("/")
    if last in TRANSPORT_SUBTOPICS and head:
        last = head.rpartition("/")[2]
    return "P" if last.startswith("image_rect") else "K"


@dataclass(frozen=True)
class CameraInfoIntrinsics:
    """The pinhole intrinsics of the published image (binning and ROI applied), and what they came from."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int                    # published image size
    height_px: int
    matrix: str                      # K | P
    distortion_model: str
    distortion: tuple[float, ...]
    binning: tuple[int, int]
    roi: tuple[int, int, int, int] | None     # x_offset, y_offset, width, height (full-resolution pixels)
    calibrated_size: tuple[int, int]

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        return self.fx_px, self.fy_px, self.cx_px, self.cy_px

    def notes(self) -> dict[str, Any]:
        """For the manifest (``inputs.camera.camera_info``)."""
        out: dict[str, Any] = {"matrix": self.matrix, "calibrated_size": list(self.calibrated_size),
                               "distortion_model": self.distortion_model,
                               "distortion": [round(d, 9) for d in self.distortion]}
        if self.binning != (1, 1):
            out["binning"] = list(self.binning)
        if self.roi is not None:
            out["roi"] = list(self.roi)
        if self.matrix == "K" and any(self.distortion):
            shift = distortion_shift_px(self)
            out["distortion_shift_px"] = None if shift is None else round(shift, 2)
        return out


def _field(msg: Any, name: str) -> Any:
    """A CameraInfo field by its ROS 1 (``K``) or ROS 2 (``k``) name."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.lower())


def camera_info_intrinsics(msg: Any, *, matrix: str = "K", source: str) -> CameraInfoIntrinsics | None:
    """The intrinsics of the image a CameraInfo describes (module docstring), None for an uncalibrated camera
    (``K[0] == 0``); InputError for values that describe no image."""
    k = np.asarray(_field(msg, "K"), float)
    if k.size != 9 or k[0] == 0:
        return None
    m = k.reshape(3, 3) if matrix == "K" else np.asarray(_field(msg, "P"), float).reshape(3, 4)[:, :3]
    fx, fy, cx, cy = m[0, 0], m[1, 1], m[0, 2], m[1, 2]
    if not (fx > 0 and fy > 0 and np.isfinite([cx, cy]).all()):
        raise InputError(f"CameraInfo {matrix} has no usable focal lengths (fx {fx:g}, fy {fy:g})", file=source)
    width, height = int(msg.width), int(msg.height)
    bx, by = max(int(msg.binning_x), 1), max(int(msg.binning_y), 1)
    roi = msg.roi
    window = None
    x0 = y0 = 0
    w, h = width, height
    if int(roi.width) > 0 and int(roi.height) > 0:
        x0, y0, w, h = int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height)
        if (x0, y0, w, h) != (0, 0, width, height):
            window = (x0, y0, w, h)
            if width and height and (x0 + w > width or y0 + h > height):
                raise InputError(f"CameraInfo roi {w}×{h} at ({x0}, {y0}) lies outside the calibrated "
                                 f"{width}×{height} image", file=source)
    if window is not None and matrix == "P":
        raise InputError("CameraInfo of a rectified image with a roi: its rectified window is not stated; give the "
                         "topic a camera_profile", file=source)
    model = str(msg.distortion_model)
    d = tuple(float(v) for v in _field(msg, "D"))
    return CameraInfoIntrinsics(fx / bx, fy / by, (cx - x0 + 0.5) / bx - 0.5, (cy - y0 + 0.5) / by - 0.5, w // bx,
                                h // by, matrix, model, d, (bx, by), window, (width, height))


def distortion_shift_px(info: CameraInfoIntrinsics, samples: int = 64) -> float | None:
    """Largest distance (px) on the image border between a pixel and where the pinhole K would put its ray
    (OpenCV's iterated ``undistortPoints``: the plumb_bob / rational_polynomial model, or ``fisheye`` for
    equidistant); None for a distortion model OpenCV does not know."""
    import cv2

    n = DISTORTION_COEFFICIENTS.get(info.distortion_model)
    if n is None or len(info.distortion) < min(n, 4):
        return None
    w, h = info.width_px - 1, info.height_px - 1
    t = np.linspace(0.0, 1.0, samples)
    border = np.concatenate([np.stack([t * w, np.zeros_like(t)], 1), np.stack([t * w, np.full_like(t, h)], 1),
                             np.stack([np.zeros_like(t), t * h], 1), np.stack([np.full_like(t, w), t * h], 1)])
    k = np.array([[info.fx_px, 0, info.cx_px], [0, info.fy_px, info.cy_px], [0, 0, 1]])
    pts = border.reshape(-1, 1, 2)
    d = np.asarray(info.distortion[:n], float)
    converged = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)   # the default 5 steps are not
    if info.distortion_model == "equidistant":
        ideal = cv2.fisheye.undistortPoints(pts, k, d, P=k, criteria=converged)
    else:
        iterated = getattr(cv2, "undistortPointsIter", None)       # OpenCV 4's name of the overload with criteria
        ideal = iterated(pts, k, d, None, k, converged) if iterated else \
            cv2.undistortPoints(pts, k, d, R=None, P=k, criteria=converged)
    shift = np.linalg.norm(ideal.reshape(-1, 2) - border, axis=1)
    return float(np.nanmax(shift)) if np.isfinite(shift).any() else None
