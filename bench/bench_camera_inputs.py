"""Camera inputs: the cost of getting depth from what users have, at the Lucid Triton's 1936×1464 unless stated.

- hole filling (pull–push in inverse depth) with 7 % of the pixels in blobs, policies fill and sky, against OpenCV's
  Telea inpainting of the same holes; a sparse KITTI-size map (1242×375, 10 % valid);
- decoding a KITTI depth PNG and a Cityscapes disparity PNG (2048×1024) into range;
- LiDAR depth from the sample drive's OS1-128 scan (the committed 484×366 camera, and its intrinsics scaled ×4);
- the ground-plane prior; a 1×1-convolution ONNX model at full resolution (onnxruntime overhead, when installed).

    .venv/bin/python bench/bench_camera_inputs.py
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from roadview_noise.depth.calibration import load_calibration
from roadview_noise.depth.ground_plane import ground_plane_range
from roadview_noise.depth.holes import resolve_holes
from roadview_noise.depth.lidar import lidar_depth
from roadview_noise.io.depth import read_depth
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.profiles.camera import load_camera_profile
from roadview_noise.types import CameraProfile

ROOT = Path(__file__).resolve().parents[1]
W, H = 1936, 1464


def median_ms(fn, repeat=9) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times)


def blob_holes(h, w, fraction, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    mask = np.zeros((h, w), np.uint8)
    while mask.mean() < fraction:
        cv2.circle(mask, (int(rng.integers(0, w)), int(rng.integers(0, h))), int(rng.integers(10, 60)), 1, -1)
    return mask.astype(bool)


def main() -> None:
    cv2.setNumThreads(1)
    v, u = np.mgrid[0:H, 0:W]
    depth = (5 + 20 * u / W + 10 * v / H).astype(np.float32)
    depth[: H // 5] = np.inf
    holes = blob_holes(H, W, 0.07)
    noisy = np.where(holes, np.float32(np.nan), depth)
    print(f"hole filling, {W}×{H}, {100 * holes.mean():.1f} % holes in blobs")
    print(f"  depth_holes fill                   {median_ms(lambda: resolve_holes(noisy, 'fill')):8.1f} ms")
    print(f"  depth_holes sky                    {median_ms(lambda: resolve_holes(noisy, 'sky')):8.1f} ms")
    inverse = np.where(holes, 0, 1 / depth).astype(np.float32)
    mask8 = holes.astype(np.uint8)
    print(f"  cv2.inpaint Telea r=5 (reference)  "
          f"{median_ms(lambda: cv2.inpaint(inverse, mask8, 5, cv2.INPAINT_TELEA), 3):8.1f} ms")
    sparse_known = np.random.default_rng(1).random((375, 1242)) < 0.1
    sparse = np.where(sparse_known, np.float32(10.0), np.float32(np.nan))
    print(f"  sparse 1242×375, 10 % valid, fill  {median_ms(lambda: resolve_holes(sparse, 'fill')):8.1f} ms")

    with tempfile.TemporaryDirectory() as tmp:
        codes = np.random.default_rng(2).integers(0, 65535, (1024, 2048), dtype=np.uint16)
        cv2.imwrite(f"{tmp}/d.png", codes)
        prof = CameraProfile("cs", 2048, 1024, 2262.52, 2265.30, 1096.98, 513.137)
        print("decoding 2048×1024 16-bit PNGs to range")
        print(f"  KITTI depth PNG                    "
              f"{median_ms(lambda: read_depth(f'{tmp}/d.png', fmt='kitti', profile=prof)):8.1f} ms")
        print(f"  Cityscapes disparity PNG           "
              f"{median_ms(lambda: read_depth(f'{tmp}/d.png', fmt='cityscapes', profile=prof, baseline_m=0.21)):8.1f} ms")

    sample = ROOT / "sample_data"
    if sample.is_dir():
        cam = load_camera_profile(str(sample / "camera" / "seq0" / "camera.yaml"))
        cal = load_calibration(ROOT / "recipes" / "examples" / "calibration" / "sample-drive.yaml")
        points = read_pointcloud(sample / "lidar" / "os1-128" / "seq0" / "000000.pcd").positions_m
        print(f"LiDAR depth from the sample OS1-128 scan ({len(points)} points), nearest, ground plane below")
        for scale in (1, 4):
            k = (cam.fx_px * scale, cam.fy_px * scale, (cam.cx_px + 0.5) * scale - 0.5,
                 (cam.cy_px + 0.5) * scale - 0.5)
            w, h = cam.width_px * scale, cam.height_px * scale
            ms = median_ms(lambda: lidar_depth(points, cal.lidar_to_camera, k, w, h, ground=(1.0, 0.0)))
            print(f"  {w}×{h:<26}         {ms:8.1f} ms")
    print(f"ground-plane prior {W}×{H}            "
          f"{median_ms(lambda: ground_plane_range((1137.4, 1137.4, 967.5, 731.5), W, H, camera_height_m=1.0)):8.1f} ms")
    try:
        import onnx
        import onnxruntime  # noqa: F401  (model_depth needs it)
    except ImportError:
        return
    from onnx import TensorProto, helper

    from roadview_noise.depth.monocular import model_depth

    with tempfile.TemporaryDirectory() as tmp:
        x = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "H", "W"])
        y = helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 1, "H", "W"])
        graph = helper.make_graph([helper.make_node("Conv", ["image", "w", "b"], ["depth"])], "tiny", [x], [y],
                                  [helper.make_tensor("w", TensorProto.FLOAT, [1, 3, 1, 1], [1.0, 1.0, 1.0]),
                                   helper.make_tensor("b", TensorProto.FLOAT, [1], [5.0])])
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
        model.ir_version = 8
        onnx.save(model, f"{tmp}/m.onnx")
        image = np.random.default_rng(3).random((H, W, 3), dtype=np.float32)
        print(f"ONNX 1×1 conv at {W}×{H} (I/O overhead)  "
              f"{median_ms(lambda: model_depth(f'{tmp}/m.onnx', image), 5):8.1f} ms")


if __name__ == "__main__":
    main()
