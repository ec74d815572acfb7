"""What a COCO image's camera became through the chain's geometric steps, written into its ``images`` entry.

A geometric step (lens or windscreen distortion) moves the pixels, so the image no longer follows the pinhole
projection of its camera matrix (mmdetection3d's ``cam_intrinsic``): ``center2d`` and the 2-D boxes move with the
image (:mod:`roadview_noise.coco_warp`), while ``cam_intrinsic`` and ``bbox_cam3d`` (a box in camera coordinates)
stay as they were. The image entry gets ``rv_distortion``: the list of the distortions applied since the pinhole
image that ``cam_intrinsic`` describes, in order (an input that already has one, from an earlier rvnoise run, keeps
its steps first). Loaders read the image keys they know by name (mmdetection3d's ``LoadImageFromFileMono3D``:
``cam_intrinsic``; the COCO API and mmdetection: ``file_name``, ``width``, ``height``), so the key is ignored by
them.

A Brown–Conrady step (:class:`~roadview_noise.physics.brown_conrady.LensWarp`) is written as
``{"model": "brown_conrady", "k1": …, …, "s4": …, "centre_px": [c_x, c_y], "unit_px": [f_x, f_y]}``: the pixel
(u, v) of the image after the step shows what the image before it showed at ``(c_x + f_x x_d, c_y + f_y y_d)``,
with ``x = (u − c_x)/f_x``, ``y = (v − c_y)/f_y`` and ``x_d, y_d`` the distortion of models.md §2.5
(:mod:`roadview_noise.physics.brown_conrady`), all in the file's COCO coordinates (pixel ``i`` on [i, i + 1]:
the centre is the warp's, which puts pixel centres on integers, plus ½ px). A 3-D point's position in the output
image is therefore its pinhole projection through ``cam_intrinsic`` moved through each step's inverse, which is
how ``center2d`` moved. Any other warp is ``{"model": "pixel_map"}`` (no closed form to state).
"""

from __future__ import annotations

from typing import Any

from .physics.brown_conrady import COEFFICIENTS

KEY = "rv_distortion"


def steps(warps) -> list[dict]:
    """The ``rv_distortion`` steps of a chain's (non-identity) warps, in order."""
    return [_step(w) for w in warps]


def _step(warp) -> dict[str, Any]:
    bc = getattr(warp, "distortion", None)      # a LensWarp's, or one turned to a photo's stored pixels (StoredWarp)
    if bc is None:
        return {"model": "pixel_map"}
    (cx, cy), (fx, fy) = bc.centre_px, bc.unit_px
    return {"model": "brown_conrady", **{k: float(v) for k, v in zip(COEFFICIENTS, bc.coefficients)},
            "centre_px": [float(cx) + 0.5, float(cy) + 0.5], "unit_px": [float(fx), float(fy)]}


def image_entry(image: dict, record: dict) -> dict:
    """The ``images`` entry of an image whose worker record is ``record``: with the record's distortion steps
    appended to the entry's own ``rv_distortion`` (the entry as read when the chain moved no pixel)."""
    new = record.get("distortion")
    if not new:
        return image
    before = image.get(KEY)
    return {**image, KEY: (list(before) if isinstance(before, list) else []) + list(new)}
