"""Per-frame time of the foundation models: compression.camera, alignment.lidar, power.lidar.

Run: ``.venv/bin/python bench/bench_foundation.py [--repeat N]``. Prints the median wall time per frame (ms) of
``model.apply`` (plus the sequence draw, done once per sequence in a run and timed separately) on
- a 1936×1464 Lucid Triton frame (synthetic, photograph-like content),
- a full 128×2048 OS1-128 grid (synthetic, 10 % no-return cells),
- the real OS1-128 scan in ../shared/data when present (107 647 returns of 128×1024; reflectivity is 8-bit).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from roadview_noise.models.camera.compression import CompressionCamera
from roadview_noise.models.lidar.alignment import AlignmentLidar
from roadview_noise.models.lidar.power import PowerLidar
from roadview_noise.physics import srgb
from roadview_noise.physics.lidar_geometry import range_image, recover_ring, velodyne_to_xyz
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.types import CameraFrame, IntensityUnit, PointCloud

SHARED_SCAN = Path(__file__).resolve().parents[2] / "shared" / "data" / "os1-128"


def median_ms(fn, repeat: int) -> float:
    fn()                                                       # warm-up (caches, page faults)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def camera_frame() -> CameraFrame:
    profile = lucid_triton_028s()
    h, w = profile.height_px, profile.width_px
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    img = np.stack([0.5 + 0.3 * np.sin(6 * x + 2 * y), 0.4 + 0.3 * np.cos(9 * y), 0.3 + 0.2 * np.sin(15 * x * y)], -1)
    for _ in range(40):
        c = tuple(int(v) for v in rng.integers(0, (w, h)))
        cv2.circle(img, c, int(rng.integers(10, 200)), tuple(float(v) for v in rng.random(3)), -1)
    img = cv2.GaussianBlur(img, (0, 0), 1.5) + cv2.GaussianBlur(rng.normal(0, 0.04, (h, w)), (0, 0), 1.0)[..., None]
    return CameraFrame((np.clip(img, 0, 1) ** 2.2).astype(np.float32), profile)


def grid_cloud() -> PointCloud:
    profile = os1_128()
    rng = np.random.default_rng(0)
    ring, col = (a.ravel() for a in np.meshgrid(np.arange(128), np.arange(2048), indexing="ij"))
    alpha = col * 2 * np.pi / 2048 + np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring]
    omega = np.deg2rad(np.asarray(profile.beam_elevation_deg))[ring]
    xyz = velodyne_to_xyz(rng.uniform(1, 120, ring.size), alpha, omega)
    empty = rng.random(ring.size) < 0.1
    xyz[empty] = 0.0
    intensity = np.where(empty, 0, rng.gamma(2.0, 200.0, ring.size)).astype(np.float32)
    return PointCloud(xyz, {"intensity": intensity, "ring": ring.astype(np.uint16)}, "lidar", profile,
                      grid_shape=(128, 2048))


def real_cloud() -> PointCloud | None:
    if not (SHARED_SCAN / "scan0.bin").is_file():
        return None
    a = np.fromfile(SHARED_SCAN / "scan0.bin", dtype=np.float32).reshape(-1, 4)
    profile = dataclasses.replace(os1_128(), columns=1024, intensity_unit=IntensityUnit.UINT8,
                                  intensity_full_scale=255.0)
    return PointCloud(a[:, :3].astype(np.float64), {"intensity": a[:, 3].copy()}, "lidar", profile)


def bench_model(model, data, repeat: int) -> tuple[float, float]:
    rng = np.random.default_rng(0)
    state = model.draw_sequence(np.random.default_rng(1), data)
    draw = median_ms(lambda: model.draw_sequence(np.random.default_rng(1), data), repeat)
    apply = median_ms(lambda: model.apply(data, state=state, drawn={}, rng=rng), repeat)
    return apply, draw


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    repeat = parser.parse_args().repeat
    cv2.setNumThreads(1)                                       # as in the runner's workers

    rows = []
    frame = camera_frame()
    rows.append(("srgb.linear_to_code", "1936×1464×3", median_ms(lambda: srgb.linear_to_code(frame.linear_rgb),
                                                                  repeat), None))
    codes = srgb.linear_to_code(frame.linear_rgb)
    rows.append(("srgb.code_to_linear", "1936×1464×3", median_ms(lambda: srgb.code_to_linear(codes), repeat), None))
    for q in (15, 95):
        model = CompressionCamera(quality=q)
        ratio = model.apply(frame, state={}, drawn={}, rng=None)[1]["compression_ratio"]
        rows.append((f"compression.camera Q{q} (ratio {ratio:.0f}:1)", "1936×1464", *bench_model(model, frame,
                                                                                                 repeat)))

    clouds = [("128×2048 grid", grid_cloud())]
    real = real_cloud()
    if real is not None:
        clouds.append(("real OS1-128 scan, ring from elevation", real))
        with_ring = real.with_fields(ring=recover_ring(real.positions_m, real.profile))
        clouds.append(("real OS1-128 scan, ring field", with_ring))
    for name, cloud in clouds:
        for model in (AlignmentLidar(), PowerLidar()):
            rows.append((model.id, f"{name} ({len(cloud)} pts)", *bench_model(model, cloud, repeat)))
        if "ring" in cloud.fields:
            rows.append(("lidar_geometry.range_image", f"{name} ({len(cloud)} pts)",
                         median_ms(lambda: range_image(cloud.positions_m, cloud.fields["ring"], cloud.profile),
                                   repeat), None))

    print(f"{'step':44s} {'input':54s} {'apply ms':>9s} {'draw ms':>8s}")
    for step, data, apply_ms, draw_ms in rows:
        draw = f"{draw_ms:8.2f}" if draw_ms is not None else f"{'':8s}"
        print(f"{step:44s} {data:54s} {apply_ms:9.1f} {draw}")
    if real is None:
        print(f"(real scan not found at {SHARED_SCAN}; skipped)")


if __name__ == "__main__":
    main()
