"""Benchmark the sample-drive generator: 10 frames of every sensor at the default full resolutions (camera
1936×1464 + raw + depth, OS1-128 2048 columns as list/KITTI/grid, VLS-128 1800 columns, radar), written to a
temporary directory; then the per-sensor compute time per frame (no I/O).

    python bench/bench_sample_data.py [--frames 10]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from roadview_noise.sampledata import camera, lidar, radar, rig
from roadview_noise.sampledata.generate import camera_profile, generate, lidar_profiles
from roadview_noise.sampledata.scene import build_scene


def per_sensor_ms(frames: int) -> dict[str, float]:
    scene = build_scene(0)
    cam = camera_profile(None)
    os1, vls = lidar_profiles(None)
    centres = radar.sample_centres(scene, 0)
    rp = radar.sample_radar_profile()
    camera.ray_directions(cam), lidar.beam_rays(os1), lidar.beam_rays(vls)      # cached tables, built once
    totals = dict.fromkeys(("snapshot", "camera", "os1-128", "vls-128", "radar"), 0.0)
    for k in range(frames):
        t0 = time.perf_counter()
        snap = scene.snapshot(scene.frame_time_s(k))
        ego = scene.ego_position_m(snap.t_s)
        t1 = time.perf_counter()
        camera.render(snap, cam, ego + np.array([*rig.CAMERA_MOUNT_XY_M, cam.height_above_ground_m]))
        t2 = time.perf_counter()
        lidar.scan(snap, os1, ego + np.array(rig.LIDAR_MOUNT_M))
        t3 = time.perf_counter()
        lidar.scan(snap, vls, ego + np.array(rig.LIDAR_MOUNT_M))
        t4 = time.perf_counter()
        radar.detect(snap, centres, ego + np.array(rig.RADAR_MOUNT_M), rp)
        t5 = time.perf_counter()
        for key, dt in zip(totals, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
            totals[key] += dt
    return {k: 1e3 * v / frames for k, v in totals.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=10)
    frames = ap.parse_args().frames
    with tempfile.TemporaryDirectory() as tmp:
        s = generate(Path(tmp) / "full", frames=frames, seed=0)
        print(f"full resolution, {frames} frames, all sensors, written: {s['seconds']:.1f} s "
              f"({1e3 * s['seconds'] / frames:.0f} ms/frame, {s['bytes'] / 1e6:.0f} MB, {len(s['files'])} files)")
        c = generate(Path(tmp) / "committed", **rig.COMMITTED)
        print(f"committed preset {rig.COMMITTED}: {c['seconds']:.2f} s, {c['bytes'] / 1e6:.2f} MB")
    for key, ms in per_sensor_ms(frames).items():
        print(f"  {key:>8}: {ms:7.1f} ms/frame (compute only)")


if __name__ == "__main__":
    main()
