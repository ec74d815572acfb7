"""Sequences (sensor instances) of real dataset layouts: every frame of one recording shares its sensor-instance
state (lens soiling, beam offsets: ``derive_rng(seed, "sequence", sequence_id, model)``), recordings differ — KITTI raw's one folder per drive, and nuScenes' one folder
per channel holding every log (``samples/CAM_FRONT/<log>__CAM_FRONT__<µs>.jpg``)."""

from __future__ import annotations

import numpy as np

from roadview_noise.dataset import discover
from roadview_noise.io.image import ImageEncoding, write_image
from roadview_noise.preview import sample_for
from roadview_noise.recipe import parse_recipe

LOG_A, LOG_B = "n015-2018-07-24-11-22-45+0800", "n008-2018-08-01-15-16-36-0400"
FILES = [
    "kitti/2011_09_26_drive_0001_sync/image_02/data/0000000000.png",
    "kitti/2011_09_26_drive_0001_sync/image_02/data/0000000001.png",
    "kitti/2011_09_26_drive_0002_sync/image_02/data/0000000000.png",
    f"nuscenes/samples/CAM_FRONT/{LOG_A}__CAM_FRONT__1532402927612460.png",
    f"nuscenes/samples/CAM_FRONT/{LOG_A}__CAM_FRONT__1532402928112460.png",
    f"nuscenes/samples/CAM_FRONT/{LOG_B}__CAM_FRONT__1533151603512404.png",
    f"flat/{LOG_A}__CAM_FRONT__1532402927612460.png",                 # every channel in one folder
    f"flat/{LOG_A}__CAM_BACK__1532402927637525.png",
]


def _tree(root):
    rng = np.random.default_rng(0)
    for rel in FILES:
        write_image(root / rel, rng.uniform(0, 1, (48, 64, 3)).astype(np.float32), ImageEncoding())


def test_sequences_of_kitti_drives_and_nuscenes_logs(tmp_path):
    _tree(tmp_path)
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 3,
                           "chain": [{"model": "soiling.camera", "params": {"opacity": 0.45}}]})
    samples = {s.relpath: s for s in discover(tmp_path, recipe)}
    seq = {rel: samples[rel].sequence_id for rel in FILES}
    assert seq[FILES[0]] == seq[FILES[1]] != seq[FILES[2]]            # KITTI: one drive folder, one sequence
    assert seq[FILES[3]] == seq[FILES[4]] != seq[FILES[5]]            # nuScenes: one log, one sequence (was one folder)
    assert seq[FILES[3]] != seq[FILES[6]] != seq[FILES[7]]            # a flattened folder: one sequence per channel
    assert all(sample_for(tmp_path / rel, recipe, tmp_path)[0].sequence_id == seq[rel] for rel in FILES)  # = preview

    per_file = parse_recipe({"schema": "rvnoise.recipe/1", "chain": [{"model": "soiling.camera"}],
                             "inputs": {"sequence": "file"}})
    assert {s.relpath: s.sequence_id for s in discover(tmp_path, per_file)} == {rel: rel for rel in FILES}

