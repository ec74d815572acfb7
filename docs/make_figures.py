"""Render the README's before/after figures with the tool itself: `rvnoise augment` on sample_data/, then pair
each input with its output (camera side by side; LiDAR and radar as bird's-eye views coloured by point label).

    .venv/bin/python docs/make_figures.py        # writes docs/images/*.png
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from roadview_noise.io.image import read_image
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.physics.srgb import linear_to_code

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "images"
FRAME = "000001"
CAMERA = ["weather-fog", "weather-rain", "weather-snow", "cnf16", "cnf18", "cnf11", "cnf01", "cnf05", "cnf09"]
CLOUDS = [("weather-fog-lidar", "lidar/os1-128-grid/seq0"), ("weather-rain-lidar", "lidar/os1-128-grid/seq0"),
          ("weather-snow-lidar", "lidar/os1-128-grid/seq0"), ("weather-rain-radar", "radar/seq0")]
LABEL_BGR = {0: (200, 200, 200), 1: (255, 160, 60), 2: (0, 200, 255), 3: (60, 60, 255)}  # kept/att/moved/added


def augment(recipe: str, out: Path) -> None:
    cmd = [sys.executable, "-m", "roadview_noise.cli.main", "augment", "--recipe", f"recipes/{recipe}.yaml",
           "sample_data", str(out), "--quiet", "--workers", "2"]
    subprocess.run(cmd, cwd=ROOT, check=True)


def label(img: np.ndarray, text: str) -> np.ndarray:
    img = img.copy()
    cv2.rectangle(img, (0, 0), (img.shape[1], 22), (0, 0, 0), -1)
    cv2.putText(img, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def camera_png(path: Path) -> np.ndarray:
    linear, _, _ = read_image(path)
    return cv2.cvtColor(linear_to_code(linear, 8), cv2.COLOR_RGB2BGR)


def birds_eye(path: Path, sensor: str, extent_m: float = 40.0, px: int = 480) -> np.ndarray:
    cloud = read_pointcloud(path, sensor=sensor)
    img = np.full((px, px, 3), 20, np.uint8)
    p = cloud.positions_m
    keep = np.any(p != 0, axis=1)
    labels = cloud.fields.get("rv_effect", np.zeros(len(p), np.uint8))[keep].astype(int)   # provenance.Effect
    scale = px / (2 * extent_m)
    u = (px / 2 - p[keep, 1] * scale).astype(int)   # y left → image left
    v = (px / 2 - p[keep, 0] * scale).astype(int)   # x forward → image up
    inside = (u >= 0) & (u < px) & (v >= 0) & (v < px)
    for lab, colour in LABEL_BGR.items():
        m = inside & (labels == lab)
        img[v[m], u[m]] = colour
        if sensor == "radar":
            for x, y in zip(u[m], v[m]):
                cv2.circle(img, (int(x), int(y)), 3, colour, -1)
    return img


def main() -> None:
    IMAGES.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for recipe in CAMERA:
            out = Path(tmp) / recipe
            augment(recipe, out)
            before = camera_png(ROOT / "sample_data" / "camera" / "seq0" / f"{FRAME}.png")
            after = camera_png(out / "camera" / "seq0" / f"{FRAME}.png")
            pair = np.hstack([label(before, "input"), label(after, f"rvnoise: {recipe}")])
            cv2.imwrite(str(IMAGES / f"{recipe}.png"), pair)
        for recipe, folder in CLOUDS:
            out = Path(tmp) / recipe
            augment(recipe, out)
            sensor = "radar" if "radar" in recipe else "lidar"
            before = birds_eye(ROOT / "sample_data" / folder / f"{FRAME}.pcd", sensor)
            after = birds_eye(out / folder / f"{FRAME}.pcd", sensor)
            pair = np.hstack([label(before, "input (bird's-eye, 80 m)"),
                              label(after, f"{recipe}: grey kept, blue attenuated, yellow moved, red added")])
            cv2.imwrite(str(IMAGES / f"{recipe}.png"), pair)
    print(f"figures written to {IMAGES}")


if __name__ == "__main__":
    main()
