"""Camera codecs, one 1936×1464 frame, one core: PNG decode and encode by OpenCV (libpng + zlib) and by rvnoise
(``io/png.py``: ISA-L inflate, zlib-ng deflate, OpenCV's settings), the written size and whether the bytes are
OpenCV's; the EXR depth read and the sha256 of the inputs (what ``augment`` adds per file besides the models).

Frames: the sample drive's rendered camera frame made photo-like (σ = 2 codes of noise, as bench/run.py), as 8-bit
RGB, 8-bit RGBA, 16-bit RGB and 8-bit grey; each written by OpenCV's default settings (Sub filter, level 1 — what
rvnoise writes) and, for 8-bit RGB, with libpng's adaptive filters at level 6 (what other tools write: Paeth rows).

    .venv/bin/python bench/bench_camera_codecs.py
"""

from __future__ import annotations

import hashlib
import tempfile
from pathlib import Path

import cv2
import numpy as np
from bench_foundation import median_ms as _median_ms      # bench/ is the script's folder, first on sys.path

from roadview_noise.io.image import read_exr_channels
from roadview_noise.io.png import decode_png, encode_png


REPEAT = 9


def median_ms(fn) -> float:
    return _median_ms(fn, REPEAT)


def frames(root: Path) -> tuple[dict[str, np.ndarray], Path]:
    """Photo-like code values (RGB order) of the rendered frame in each kind, and its depth EXR."""
    from roadview_noise.sampledata.generate import generate

    generate(root, frames=1, seed=0)
    cam = root / "camera" / "seq0"
    rgb = cv2.imread(str(cam / "000000.png"), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float32)
    noisy = rgb + np.random.default_rng(0).normal(0, 2.0, rgb.shape)
    rgb8 = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    rgb16 = np.clip(np.rint(noisy * 257.0), 0, 65535).astype(np.uint16)
    alpha = np.full(rgb8.shape[:2], 255, np.uint8)
    alpha[:100] = 0
    return {"8-bit RGB": rgb8, "8-bit RGBA": np.dstack([rgb8, alpha]), "16-bit RGB": rgb16,
            "8-bit grey": cv2.cvtColor(rgb8, cv2.COLOR_RGB2GRAY)}, cam / "000000_depth.exr"


def bgr(codes: np.ndarray) -> np.ndarray:
    return codes if codes.ndim == 2 else np.ascontiguousarray(codes[..., [2, 1, 0, 3][:codes.shape[2]]])


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="rvnoise-codecs-") as tmp:
        kinds, depth = frames(Path(tmp))
        print("| frame (1936×1464) | input written by | input MB | OpenCV decode ms | rvnoise decode ms | "
              "OpenCV encode ms | rvnoise encode ms | written MB (OpenCV / rvnoise) | same bytes |")
        print("|---|---|---|---|---|---|---|---|---|")
        for kind, codes in kinds.items():
            stored = bgr(codes)
            writers = {"OpenCV default": []}
            if kind == "8-bit RGB":
                writers["libpng adaptive filters, level 6"] = [cv2.IMWRITE_PNG_COMPRESSION, 6, cv2.IMWRITE_PNG_FILTER,
                                                               cv2.IMWRITE_PNG_ALL_FILTERS]
            for label, params in writers.items():
                data = cv2.imencode(".png", stored, params)[1].tobytes()
                buf = np.frombuffer(data, np.uint8)
                assert np.array_equal(bgr(decode_png(data)), cv2.imdecode(buf, cv2.IMREAD_UNCHANGED))
                row = (f"| {kind} | {label} | {len(data) / 1e6:.3f} | "
                       f"{median_ms(lambda: cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)):.1f} | "
                       f"{median_ms(lambda: decode_png(data)):.1f} | ")
                if params:                              # the writers' rows: once per kind
                    print(row + "| | | |")
                    continue
                ours, theirs = encode_png(codes), cv2.imencode(".png", stored)[1].tobytes()
                print(row + f"{median_ms(lambda: cv2.imencode('.png', stored)):.1f} | "
                      f"{median_ms(lambda: encode_png(codes)):.1f} | {len(theirs) / 1e6:.3f} / {len(ours) / 1e6:.3f} "
                      f"| {'yes' if ours == theirs else 'no'} |")
        png = cv2.imencode(".png", bgr(kinds["8-bit RGB"]))[1].tobytes()
        exr = depth.read_bytes()
        print("\n| other per-file input work | ms |\n|---|---|")
        print(f"| EXR depth read (OpenEXR, float32 Z, ZIP, {len(exr) / 1e6:.1f} MB) | "
              f"{median_ms(lambda: read_exr_channels(depth)):.1f} |")
        print(f"| sha256 of the 8-bit RGB PNG ({len(png) / 1e6:.1f} MB) | "
              f"{median_ms(lambda: hashlib.sha256(png).hexdigest()):.1f} |")
        print(f"| sha256 of the depth EXR | {median_ms(lambda: hashlib.sha256(exr).hexdigest()):.1f} |")


if __name__ == "__main__":
    main()
