"""Ground-plane depth against LiDAR ground truth on real frames: the flat-road prior (every pixel above the horizon
at ``sky_distance_m``) before, vertical objects standing on the ground (roadview_noise/depth/stixels.py) after.

Frames (mmdetection3d's demo data, /work/realdata/mmdet3d or $RVNOISE_REALDATA): KITTI 000008 (1242×375, HDL-64E,
the object benchmark's calib of the 2011_09_26 drives, camera 1.65 m above the road, pitch 0) and nuScenes
CAM_FRONT with LIDAR_TOP of log n015-2018-07-24-11-22-45 (1600×900, HDL-32E; the tables written in nuScenes'
layout, read by rvnoise's ``calibration: {nuscenes: …}`` support: K, camera height 1.51 m and pitch from
calibrated_sensor). Reference: the LiDAR-depth path (depth/lidar.py): the returns' pixels (nearest return, parallax
hidden ones dropped) for the errors, its dense map's sky (``inf``) for "sky stays far".

Metrics over the pixels with a LiDAR return, below / above the horizon row of the ground plane:
median |ln(d_est / d_lidar)|; the fraction of returns nearer than 30 m estimated ≥ 100 m (at sky distance); fog of
meteorological optical range 30 m (transmittance ``exp(−3.912 d / MOR)``): on the returns < 30 m in a box around
the nearest object (nuScenes: the truck, KITTI: the silver car) median range and mean T; mean |T_est − T_lidar|
over returns nearer than 30 m above the horizon (the truck, cars, walls) and over all returns nearer than 30 m;
the pixels left at sky distance of boxes of plain sky (picked by eye, listed per frame) and of the LiDAR path's
sky (above a column's highest return: on nuScenes also tree crowns and the glass building the HDL-32E's top beam
misses). Then the cost at 1920×1080 on one OpenCV thread (medians of repeats, run alternately, wall and CPU time).

    .venv/bin/python bench/bench_ground_plane_depth.py
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from roadview_noise.depth.calibration import load_calibration
from roadview_noise.depth.ground_plane import ground_plane_range
from roadview_noise.depth.lidar import drop_occluded, lidar_depth, project_returns
from roadview_noise.depth.nuscenes import nuscenes_calibration
from roadview_noise.depth.stixels import object_range
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.physics import srgb

REAL = Path(os.environ.get("RVNOISE_REALDATA", "/work/realdata/mmdet3d"))
SKY_M = 100.0
MOR_M = 30.0
# the calibrations the tests hold (one copy): KITTI's devkit calib of the 2011_09_26 drives, and the
# calibrated_sensor records of log n015-2018-07-24-11-22-45 (v1.0-mini scene-0061), here at CAM_FRONT's full
# 1600×900 (intrinsics of that camera, as mmdetection3d's nus_infos_mono3d.coco.json states them)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "depth"))
from test_lidar_top_of_view import KITTI_CALIB  # noqa: E402
from test_nuscenes_calibration import CAM, IMAGE as NUS_IMAGE, LIDAR, SCAN as NUS_SCAN  # noqa: E402

NUS_CAM = {**CAM, "camera_intrinsic": [[1266.417203046554, 0.0, 816.2670197447984],
                                       [0.0, 1266.417203046554, 491.50706579294757], [0.0, 0.0, 1.0]]}


def kitti(tmp: Path) -> dict:
    (tmp / "calib.txt").write_text(KITTI_CALIB)
    cal = load_calibration(tmp / "calib.txt")
    codes = np.asarray(Image.open(REAL / "demo/data/kitti/000008.png").convert("RGB"))
    points = np.fromfile(REAL / "demo/data/kitti/000008.bin", np.float32).reshape(-1, 4)[:, :3]
    h, w = codes.shape[:2]
    return {"name": "KITTI 000008", "srgb": codes, "K": cal.intrinsics_for(w, h), "height_m": 1.65, "pitch": 0.0,
            "points": points, "to_camera": cal.lidar_to_camera, "sky_boxes": [(770, 0, 920, 40), (640, 0, 700, 15)],
            "object": ("silver car", (355, 185, 610, 345))}


def nuscenes(tmp: Path) -> dict:
    tables = tmp / "v1.0-mini"
    tables.mkdir(exist_ok=True)
    records = [{"token": "sd-cam", "sample_token": "smp1", "calibrated_sensor_token": "cam0", "is_key_frame": True,
                "filename": NUS_IMAGE}, {"token": "sd-lid", "sample_token": "smp1", "calibrated_sensor_token": "lid0",
                                         "is_key_frame": True, "filename": NUS_SCAN}]
    (tables / "sample_data.json").write_text(json.dumps(records))
    (tables / "calibrated_sensor.json").write_text(json.dumps([NUS_CAM, LIDAR]))
    cal = nuscenes_calibration(tables, NUS_IMAGE, lidar=True)
    demo = REAL / "demo/data/nuscenes"
    codes = np.asarray(Image.open(demo / Path(NUS_IMAGE).name).convert("RGB"))
    points = read_pointcloud(demo / Path(NUS_SCAN).name, sensor="lidar").positions_m
    return {"name": "nuScenes CAM_FRONT", "srgb": codes, "K": cal.intrinsics_px, "height_m": cal.height_above_ground_m,
            "pitch": cal.pitch_rad, "points": points, "to_camera": cal.lidar_to_camera,
            "sky_boxes": [(580, 20, 900, 170), (1000, 20, 1200, 120), (1300, 150, 1380, 200), (1480, 120, 1590, 180)],
            "object": ("truck", (140, 230, 590, 610))}


def reference(frame: dict) -> dict:
    """The LiDAR returns' pixels and ranges, and the LiDAR-depth path's sky."""
    h, w = frame["srgb"].shape[:2]
    rows, cols, rng, _ = project_returns(frame["points"], frame["to_camera"], frame["K"], w, h)
    seen = drop_occluded(rows, cols, rng, (h, w), 5, 0.1)
    dense, _, _ = lidar_depth(frame["points"], frame["to_camera"], frame["K"], w, h)
    fy, cy = frame["K"][1], frame["K"][3]
    horizon = cy - fy * np.tan(frame["pitch"])
    boxes = np.zeros((h, w), bool)
    for x0, y0, x1, y1 in frame["sky_boxes"]:
        boxes[y0:y1, x0:x1] = True
    rows, cols, rng = rows[seen], cols[seen], rng[seen]
    x0, y0, x1, y1 = frame["object"][1]
    on_object = (cols >= x0) & (cols < x1) & (rows >= y0) & (rows < y1) & (rng < 30.0)
    return {"rows": rows, "cols": cols, "range_m": rng, "sky": np.isinf(dense), "below": rows > horizon,
            "sky_boxes": boxes, "object": on_object}


def metrics(depth: np.ndarray, ref: dict) -> dict:
    est = depth[ref["rows"], ref["cols"]].astype(np.float64)
    err = np.abs(np.log(est / ref["range_m"]))
    near = ref["range_m"] < 30.0
    above = ~ref["below"]
    t_est, t_ref = np.exp(-3.912 * est / MOR_M), np.exp(-3.912 * ref["range_m"] / MOR_M)
    obj = ref["object"]
    return {"object: median range m": float(np.median(est[obj])), "object: mean T": float(np.mean(t_est[obj])),
            "median |ln| below": float(np.median(err[ref["below"]])),
            "median |ln| above": float(np.median(err[above])) if above.any() else float("nan"),
            "<30 m put >=100 m": float(np.mean(est[near] >= 0.99 * SKY_M)),
            "|dT| near above": float(np.mean(np.abs(t_est - t_ref)[near & above])),
            "|dT| near all": float(np.mean(np.abs(t_est - t_ref)[near])),
            "sky boxes kept far": float(np.mean(depth[ref["sky_boxes"]] >= 0.99 * SKY_M)),
            "LiDAR sky kept far": float(np.mean(depth[ref["sky"]] >= 0.99 * SKY_M))}


def timing(repeats: int = 15) -> dict[str, tuple[float, float, float]]:
    """Median, min and max wall time and median CPU time of the calling thread (s) at 1920×1080 on one OpenCV
    thread (CPU time is what a loaded machine does not inflate), run alternately on the nuScenes photo scaled up:
    ``object_range`` on the 8-bit codes; the sRGB encoding of a linear frame (``linear_to_code``: the pipeline
    passes a decoded, unchanged frame's own codes without it, a frame from a float source pays it); the flat
    prior."""
    cv2.setNumThreads(1)
    src = Image.open(REAL / "demo/data/nuscenes" / Path(NUS_IMAGE).name).convert("RGB").resize((1920, 1080))
    codes = np.asarray(src)
    linear = srgb.decode(codes / 255.0).astype(np.float32)
    k = (1266.4 * 1.2, 1266.4 * 1.2, 979.5, 589.8)
    runs = {"object_range": lambda: object_range(codes, k, camera_height_m=1.51),
            "linear_to_code": lambda: srgb.linear_to_code(linear, 8),
            "flat prior": lambda: ground_plane_range(k, 1920, 1080, camera_height_m=1.51)}
    times: dict[str, list[float]] = {name: [] for name in runs}
    cpu: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            t0, c0 = time.perf_counter(), time.thread_time()
            run()
            cpu[name].append(time.thread_time() - c0)
            times[name].append(time.perf_counter() - t0)
    return {name: (statistics.median(v), min(v), max(v), statistics.median(cpu[name])) for name, v in times.items()}


def main() -> None:
    if not (REAL / "demo/data/kitti/000008.png").is_file():
        raise SystemExit(f"no real frames under {REAL} (set RVNOISE_REALDATA to mmdetection3d's folder)")
    with tempfile.TemporaryDirectory() as tmp:
        frames = [kitti(Path(tmp)), nuscenes(Path(tmp))]
    for frame in frames:
        ref = reference(frame)
        h, w = frame["srgb"].shape[:2]
        flat = ground_plane_range(frame["K"], w, h, camera_height_m=frame["height_m"], pitch_rad=frame["pitch"],
                                  sky_distance_m=SKY_M)
        objects, notes = object_range(frame["srgb"], frame["K"], camera_height_m=frame["height_m"],
                                      pitch_rad=frame["pitch"], sky_distance_m=SKY_M)
        before, after = metrics(flat, ref), metrics(objects, ref)
        obj = ref["object"]
        print(f"{frame['name']}: {ref['range_m'].size} returns ({np.count_nonzero(~ref['below'])} above the horizon),"
              f" LiDAR sky {ref['sky'].mean():.1%}; objects: {notes}\n  {frame['object'][0]} (box "
              f"{frame['object'][1]}, {np.count_nonzero(obj)} returns < 30 m): LiDAR median range "
              f"{np.median(ref['range_m'][obj]):.1f} m, mean T {np.mean(np.exp(-3.912 * ref['range_m'][obj] / MOR_M)):.3f}")
        for key in before:
            print(f"  {key:22s} flat {before[key]:8.3f}   objects {after[key]:8.3f}")
    print("1920x1080, one OpenCV thread, alternating (wall; the thread's CPU time): " + "; ".join(
        f"{name} median {m * 1e3:.1f} ms (min {lo * 1e3:.1f}, max {hi * 1e3:.1f}; CPU {c * 1e3:.1f})"
        for name, (m, lo, hi, c) in timing().items()))


if __name__ == "__main__":
    main()
