"""Depth of a photo stored turned (EXIF orientation 2–8) is made for the upright photo (roadview_noise.orientation):
an ONNX network sees it upright and its planar depth becomes range through the upright intrinsics."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from PIL import Image

from roadview_noise.dataset import iter_inputs, load
from roadview_noise.orientation import stored, upright_profile
from roadview_noise.recipe import parse_recipe
from roadview_noise.types import CameraProfile


@pytest.mark.parametrize("turn", [6, 7])
def test_onnx_depth_of_a_turned_photo_is_the_upright_photo_s(tmp_path, tiny_depth_model, turn):
    pytest.importorskip("onnxruntime")
    model = tiny_depth_model(tmp_path / "m.onnx", weights=(4.0, 2.0, 1.0), bias=9.0)
    h, w = 36, 60
    image = np.random.default_rng(2).integers(0, 256, (h, w, 3), np.uint8)
    profile = CameraProfile("k", w, h, 50.0, 47.0, 31.0, 16.5)
    fields = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px")
    frames = []
    stored_profile = upright_profile(profile, {6: 8}.get(turn, turn))         # the camera.yaml of the stored pixels
    for name, tag, pixels, p in (("up", 1, image, profile), ("turned", turn, stored(image, turn), stored_profile)):
        root = tmp_path / name
        root.mkdir()
        im = Image.fromarray(pixels)
        exif = im.getexif()
        exif[0x0112] = tag
        buf = io.BytesIO()
        im.save(buf, format="PNG", exif=exif)
        (root / "f.png").write_bytes(buf.getvalue())
        (root / "camera.yaml").write_text(json.dumps({k: getattr(p, k) for k in fields}))
        recipe = parse_recipe({"schema": "rvnoise.recipe/1", "chain": [{"model": "fog.camera"}],
                               "inputs": {"camera": "*.png", "depth_source": "onnx",
                                          "onnx_depth": {"model": str(model), "kind": "planar"}}},
                              base_dir=tmp_path)
        frames.append(load(next(iter(iter_inputs(root, recipe))), root, recipe))
    up, turned = frames
    assert turned.profile == up.profile and turned.shape == (h, w)
    assert np.ptp(up.depth_m) > 1 and np.array_equal(turned.depth_m, up.depth_m)
    assert turned.input_notes["camera"] == up.input_notes["camera"]                      # the upright intrinsics
