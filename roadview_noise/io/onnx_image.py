"""A user-supplied image-to-image network (ONNX, e.g. a CycleGAN generator) run at full resolution.

The frame goes in as the network was trained (models.md §2.8 ``cyclegan`` back-end, D3.3 options): 8-bit-like
sRGB values scaled to [−1, 1], RGB order, NCHW float32, padded by reflection to a multiple of what the network
needs and cropped back — never D3.3's test-time resize-and-crop to 256×256, which destroys resolution and aspect
ratio. One onnxruntime session per model file and process (cached), on the CPU with ``threads`` threads.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import ModelError
from ..physics import srgb


@lru_cache(maxsize=2)
def _session(path: str, threads: int):
    try:
        import onnxruntime as ort
    except ImportError:
        raise ModelError("the onnx back-end needs onnxruntime: pip install 'roadview_noise[onnx]'") from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(path, sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for unreadable or invalid models
        raise ModelError(f"{Path(path).name}: cannot load the ONNX model ({e})") from None


def run_image_network(linear_rgb: np.ndarray, model_path: str | Path, *, multiple_px: int = 4,
                      threads: int = 1) -> np.ndarray:
    """The network's output for a linear RGB frame (H, W, 3), as linear RGB float32 of the same size."""
    path = Path(model_path)
    if not path.is_file():
        raise ModelError(f"ONNX model {str(path)!r} not found")
    session = _session(str(path.resolve()), int(threads))
    h, w = linear_rgb.shape[:2]
    x = srgb.encode(np.clip(linear_rgb, 0.0, 1.0)).astype(np.float32) * 2.0 - 1.0
    pad_h, pad_w = -h % multiple_px, -w % multiple_px
    if pad_h or pad_w:
        x = np.pad(x, ((0, pad_h), (0, pad_w), (0, 0)), mode="reflect" if min(h, w) > 1 else "edge")
    inputs = session.get_inputs()
    if len(inputs) != 1:
        raise ModelError(f"{path.name}: expected one image input, the model has {len(inputs)}")
    try:
        y = session.run(None, {inputs[0].name: np.ascontiguousarray(x.transpose(2, 0, 1)[None])})[0]
    except Exception as e:  # onnxruntime's own exception types (shape or type mismatch inside the network)
        raise ModelError(f"{path.name}: the network failed on a {x.shape[1]}×{x.shape[0]} input ({e}); does it "
                         f"need another onnx_input_multiple_px?") from None
    if y.ndim != 4 or y.shape[:2] != (1, 3) or y.shape[2] < h or y.shape[3] < w:
        raise ModelError(f"{path.name}: expected an output of shape (1, 3, ≥{h}, ≥{w}), got {tuple(y.shape)}")
    out = (np.clip(y[0, :, :h, :w].transpose(1, 2, 0), -1.0, 1.0) + 1.0) * 0.5
    return srgb.decode(out).astype(np.float32)
