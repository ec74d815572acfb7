"""Lossy JPEG compression of the camera output (models.md §2.7; D3.5 CNF10–12, Eq. 3)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2

from ...errors import ModelError
from ...model import Model, Scope, Stage, param
from ...physics import srgb
from ...registry import register
from ...types import CameraFrame

# OpenCV's names for the libjpeg component sampling factors (luma H×V, chroma 1×1)
CHROMA_SUBSAMPLING = {
    "4:4:4": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
    "4:2:2": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422,
    "4:2:0": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420,
    "4:4:0": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_440,
    "4:1:1": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_411,
}


@register
@dataclass(frozen=True)
class CompressionCamera(Model):
    """Baseline JPEG encode/decode of the camera's 8-bit sRGB output (models.md §2.7; D3.5 CNF10–12).

    The linear frame is clipped to [0, 1], sRGB-encoded and rounded to 8 bits — the bytes a camera would hand to
    its encoder (this fixes the reference's [BUG] of passing unclipped float arrays) — then JPEG-coded with
    OpenCV/libjpeg at ``quality`` (D3.5: 15) and decoded; the result holds the decoded codes
    (``CameraFrame.with_srgb8_codes``): its linear values are computed only if a later step reads them, and an 8-bit
    sRGB writer stores the codes as they are. A frame that holds valid codes (``CameraFrame.srgb8_codes``: unchanged
    since it was read, or a JPEG output) is coded from them. ``chroma_subsampling``
    defaults to libjpeg's 4:2:0, which D3.5 used implicitly. Diagnostic ``compression_ratio`` = H·W·3 / bitstream
    bytes (D3.5 reports ≈125:1 rain, 142:1 fog, 104:1 snow at Q 15 on its CARLA frame). Raw Bayer frames are refused:
    a camera never JPEG-codes the mosaic."""

    id: ClassVar[str] = "compression.camera"
    stage: ClassVar[Stage] = Stage.ENCODING
    scope: ClassVar[Scope] = Scope.FRAME
    sensor: ClassVar[str] = "camera"
    summary: ClassVar[str] = "JPEG encode/decode of the 8-bit sRGB image (D3.5: quality 15, 4:2:0)"

    quality: int = param(15, doc="JPEG quality factor (libjpeg scale)", ge=1, le=100)
    chroma_subsampling: str = param("4:2:0", doc="chroma subsampling of the encoder (libjpeg default 4:2:0)",
                                    choices=tuple(CHROMA_SUBSAMPLING))

    def apply(self, data, *, state, drawn, rng):
        if not isinstance(data, CameraFrame):
            raise ModelError("JPEG acts on the demosaicked RGB image; a camera never JPEG-codes the raw Bayer "
                             "mosaic (models.md §2.7). Compress the camera's RGB output instead: give the PNG/TIFF "
                             "frames after the ISP, or keep compression.camera out of the chains for raw inputs "
                             "(e.g. `inputs: {camera: ...}` without `raw:`)", model=self.id)
        kept = data.srgb8_codes()                                  # the frame's own codes when nothing changed it
        bgr = srgb.linear_to_code(data.linear_rgb, 8, bgr=True) if kept is None else srgb.bgr_order(kept)
        ok, bitstream = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.quality,
                                                   cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                                   CHROMA_SUBSAMPLING[self.chroma_subsampling]])
        if not ok:
            raise ModelError("OpenCV could not JPEG-encode the frame", model=self.id)
        decoded = cv2.imdecode(bitstream, cv2.IMREAD_COLOR)
        out = data.with_srgb8_codes(decoded[..., ::-1])           # linear values decoded only when read
        return out, {
            "compression_ratio": float(bgr.size / bitstream.size),
            "bytes": int(bitstream.size),
            "psnr_db": float(cv2.PSNR(bgr, decoded)),
            "chroma_subsampling": self.chroma_subsampling,
        }
