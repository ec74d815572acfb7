"""One contract for every registered model: deterministic for the same rng, input untouched, fields aligned,
picklable, parameters documented with units, JSON-able records, and sequence state shared within a sequence."""

from __future__ import annotations

import dataclasses
import json
import pickle

import numpy as np
import pytest

from roadview_noise.compound import apply_models
from roadview_noise.model import Scope
from roadview_noise.profiles.camera import lucid_triton_028s
from roadview_noise.profiles.lidar import os1_128
from roadview_noise.registry import load_all
from roadview_noise.types import CameraFrame, PointCloud, RawFrame

MODELS = load_all()


def camera_frame() -> CameraFrame:
    rng = np.random.default_rng(0)
    h, w = 96, 128
    profile = lucid_triton_028s().resized(w, h)
    img = rng.uniform(0.05, 0.9, (h, w, 3)).astype(np.float32)
    depth = np.full((h, w), 25.0, np.float32)
    depth[: h // 3] = np.inf  # sky
    depth[h // 2:, : w // 2] = 6.0
    return CameraFrame(img, profile, depth)


def raw_frame() -> RawFrame:
    f = camera_frame()
    dn = (64 + f.linear_rgb[..., 1] * (4095 - 64)).astype(np.float32)
    return RawFrame(dn, "RGGB", 64.0, 4095.0, f.profile, f.depth_m)


def lidar_cloud() -> PointCloud:
    rng = np.random.default_rng(1)
    prof = os1_128()
    n = 5000
    ring = rng.integers(0, 128, n)
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.deg2rad(np.asarray(prof.beam_elevation_deg))[ring]
    r = rng.uniform(2, 80, n)
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    return PointCloud(pos, {"intensity": rng.uniform(1, 300, n).astype(np.float32),
                            "ring": ring.astype(np.uint16)}, "lidar", prof)


def radar_cloud() -> PointCloud:
    from roadview_noise.profiles.radar import load_radar_profile

    rng = np.random.default_rng(2)
    n = 800
    r = rng.uniform(3, 150, n)
    az = np.deg2rad(rng.uniform(-55, 55, n))
    el = np.deg2rad(rng.uniform(-10, 10, n))
    pos = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    rcs = rng.uniform(-10, 20, n).astype(np.float32)
    snr = (rcs + 40 * np.log10(150 / r) + 5).astype(np.float32)
    return PointCloud(pos, {"v_r_m_per_s": rng.uniform(-20, 20, n).astype(np.float32), "rcs_dbsm": rcs,
                            "snr_db": snr}, "radar", load_radar_profile(None))


def sample_for(cls):
    return {"camera": camera_frame, "lidar": lidar_cloud, "radar": radar_cloud}[cls.sensor]()


def _copy(data):
    if isinstance(data, PointCloud):
        return dataclasses.replace(data, positions_m=data.positions_m.copy(),
                                   fields={k: v.copy() for k, v in data.fields.items()})
    if isinstance(data, CameraFrame):
        return dataclasses.replace(data, linear_rgb=data.linear_rgb.copy(), depth_m=data.depth_m.copy())
    return dataclasses.replace(data, dn=data.dn.copy(), depth_m=data.depth_m.copy())


def _arrays(data):
    if isinstance(data, PointCloud):
        return [data.positions_m, *(data.fields[k] for k in sorted(data.fields))]
    if isinstance(data, CameraFrame):
        return [data.linear_rgb]
    return [data.dn]


def _chain_for(cls):
    """A modifier needs a weather model after it; pair it with the fog model of its sensor."""
    from roadview_noise.model import Stage

    if cls.stage == Stage.MODIFIER:
        return [cls(), MODELS[f"fog.{cls.sensor}"]()]
    return [cls()]


@pytest.mark.parametrize("model_id", sorted(MODELS))
def test_model_contract(model_id):
    cls = MODELS[model_id]
    doc = cls.__doc__ or ""
    assert "§" in doc or "Eq." in doc, "the docstring cites its equation (models.md section or paper)"
    assert cls.summary, "summary line for `rvnoise list`"
    for spec in cls.param_specs():
        assert spec.unit, f"{spec.name} has no unit"
    inputs = [sample_for(cls)] + ([raw_frame()] if cls.sensor == "camera" and model_id != "compression.camera"
                                   else [])
    for data in inputs:
        before = _copy(data)
        chain = _chain_for(cls)
        out1, rec1 = apply_models(chain, data, seed=5, key="k", sequence_id="s")
        out2, rec2 = apply_models(chain, data, seed=5, key="k", sequence_id="s")
        for a, b in zip(_arrays(out1), _arrays(out2)):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(_arrays(data), _arrays(before)):
            np.testing.assert_array_equal(a, b)  # input untouched
        if isinstance(out1, PointCloud):
            assert all(len(v) == len(out1.positions_m) for v in out1.fields.values())
        else:
            assert out1.signal().shape == data.signal().shape
        json.dumps([dataclasses.asdict(r) for r in rec1])  # manifest-ready
        assert pickle.loads(pickle.dumps(chain[0])) == chain[0]
        if cls.scope == Scope.SEQUENCE:
            _, rec3 = apply_models(chain, data, seed=5, key="other-frame", sequence_id="s")
            assert rec3[0].state == rec1[0].state
