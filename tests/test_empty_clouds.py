"""A cloud with nothing to augment (0 points; nuScenes' radar sweep without detections: one all-NaN point) is written
unchanged by ``augment``, so the output tree stays complete; it is not a failure."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_cli import _augment, _recipe

from roadview_noise.errors import EmptyCloudError
from roadview_noise.io.pointcloud import read_pointcloud
from roadview_noise.manifest import sha256_file
from roadview_noise.runner import replay

HEADER = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rcs vx vy\nSIZE 4 4 4 4 4 4\n"
          "TYPE F F F F F F\nCOUNT 1 1 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")


def _radar_pcd(path: Path, points: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(HEADER.format(n=len(points)).encode() + points.astype("<f4").tobytes())
    return path


def test_empty_and_nan_marked_frames_are_copied_unchanged(tmp_path):
    rng = np.random.default_rng(0)
    frames = {"0_points.pcd": np.zeros((0, 6)), "nan_marker.pcd": np.full((1, 6), np.nan),
              "targets.pcd": np.column_stack([rng.uniform(5, 60, (40, 2)), np.zeros(40), rng.uniform(-5, 20, 40),
                                              rng.uniform(-3, 3, (40, 2))])}
    root = tmp_path / "in"
    for name, points in frames.items():
        _radar_pcd(root / "radar" / name, points)
    recipe = _recipe(tmp_path, {"chain": [{"model": "rain.radar", "params": {"rain_rate_mm_per_h": 20}}],
                                "seed": 3, "inputs": {"radar": "radar/*.pcd", "radar_profile": "ars408"}})
    result = _augment(root, tmp_path / "out", "--recipe", recipe)
    assert result.exit_code == 0, result.output
    entries = {e["input"]: e for e in map(json.loads, (tmp_path / "out" / "manifest.jsonl").read_text().splitlines())}
    for name in ("0_points.pcd", "nan_marker.pcd"):
        e = entries[f"radar/{name}"]
        assert e["status"] == "ok" and e["copied_unchanged"] and e["steps"] == []
        assert sha256_file(tmp_path / "out" / "radar" / name) == sha256_file(root / "radar" / name)
        assert e["output_sha256"] == sha256_file(root / "radar" / name)
    assert entries["radar/targets.pcd"]["status"] == "ok" and "copied_unchanged" not in entries["radar/targets.pcd"]
    assert len(entries["radar/targets.pcd"]["steps"]) == 1
    assert replay(tmp_path / "out" / "manifest.jsonl", "radar/nan_marker.pcd")["match"]


def test_reader_names_empty_frames(tmp_path):
    with pytest.raises(EmptyCloudError, match="empty frame's marker"):
        read_pointcloud(_radar_pcd(tmp_path / "a.pcd", np.full((1, 6), np.nan)), sensor="radar")
    with pytest.raises(EmptyCloudError, match=r"empty \(0 points\)"):
        read_pointcloud(_radar_pcd(tmp_path / "b.pcd", np.zeros((0, 6))), sensor="radar")
