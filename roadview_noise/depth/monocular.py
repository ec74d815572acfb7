"""Camera depth from a user-supplied monocular metric-depth model in ONNX format, run with onnxruntime (recipe
``inputs.depth_source: onnx`` with ``inputs.onnx_depth``; install the ``onnx`` extra: ``pip install
'roadview_noise[onnx]'``).

The model gets the whole frame at full resolution as one float32 tensor, (1, 3, H, W) (``nchw``) or (1, H, W, 3)
(``nhwc``), RGB, ``(x − mean) / std`` per channel with x the 8-bit sRGB code / 255 (``input: srgb``, what such
models are trained on) or the linear radiance (``input: linear``). A model whose input has fixed spatial dimensions
gets the frame resized to them (area interpolation) and its output is resized back (bilinear), which the manifest
records. The first output, squeezed to (h, w), times ``scale_m`` is the depth in metres: planar z (``kind:
planar``, most models) or range along the ray (``kind: range``). Non-positive and NaN outputs are holes
(``inputs.depth_holes``). Sessions are cached per process, one thread each (workers run in parallel).
"""

from __future__ import annotations

import os
from functools import lru_cache

import cv2
import numpy as np

from ..errors import InputError


@lru_cache(maxsize=4)
def _session(path: str, mtime_ns: int):
    try:
        import onnxruntime as ort
    except ImportError:
        raise InputError("depth_source onnx needs onnxruntime: pip install 'roadview_noise[onnx]'",
                         file=path) from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(path, sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as exc:            # onnxruntime raises its own exception types for unreadable models
        raise InputError(f"onnxruntime cannot load the model: {exc}", file=path) from None


def model_depth(model_path: str, image: np.ndarray, *, mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0),
                layout: str = "nchw", scale_m: float = 1.0) -> tuple[np.ndarray, dict]:
    """``(depth, notes)``: the model's (H, W) float32 depth in metres (NaN where not positive) for an (H, W, 3)
    image already in the model's input scale (sRGB or linear, see module docstring)."""
    session = _session(model_path, os.stat(model_path).st_mtime_ns)
    spec = session.get_inputs()[0]
    h, w = image.shape[:2]
    dims = list(spec.shape)
    hw = dims[2:4] if layout == "nchw" else dims[1:3]
    fixed = all(isinstance(d, int) and d > 0 for d in hw) and len(dims) == 4
    x = np.asarray(image, dtype=np.float32)
    if fixed and tuple(hw) != (h, w):
        x = cv2.resize(x, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
    x = (x - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    x = x.transpose(2, 0, 1)[None] if layout == "nchw" else x[None]
    try:
        out = session.run(None, {spec.name: np.ascontiguousarray(x, dtype=np.float32)})[0]
    except Exception as exc:            # shape/type mismatches are reported by onnxruntime
        raise InputError(f"the depth model failed on a {w}×{h} image ({spec.name} {dims}): {exc}",
                         file=model_path) from None
    depth = np.squeeze(np.asarray(out, dtype=np.float32))
    if depth.ndim != 2:
        raise InputError(f"the depth model's first output has shape {np.shape(out)}; expected (…, h, w)",
                         file=model_path)
    notes = {"model": os.path.basename(model_path), "scale_m": scale_m, "output_px": list(depth.shape[::-1])}
    if depth.shape != (h, w):
        depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_LINEAR)
        notes["resized_to_image"] = True
    depth = depth * np.float32(scale_m)
    depth[~(depth > 0)] = np.nan
    return depth, notes
