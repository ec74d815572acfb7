"""The camera metrics' luminance taken inside the sRGB passes (roadview_noise.luminance) and deferred metrics
(metrics.Deferred): the same values as the separate computation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from roadview_noise import luminance, metrics
from roadview_noise.compound import apply_models
from roadview_noise.luminance import blocks_of, codes_luminance_area, luminance_area, metric_scale
from roadview_noise.physics import srgb
from roadview_noise.recipe import load_recipe
from roadview_noise.runner import RunContext, build_models, load, plan, process

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def collecting():
    luminance.collect(True)
    yield
    luminance.collect(False)


def random_codes(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


@pytest.mark.parametrize("shape", [(1464, 1936), (301, 517), (600, 601), (5, 7)])
@pytest.mark.parametrize("bgr", [False, True])
def test_decode_keeps_the_blocks_of_its_frame_bit_for_bit(collecting, shape, bgr):
    stored = random_codes(*shape)
    codes = stored[..., ::-1] if bgr else stored                    # OpenCV's BGR seen as RGB, or plain RGB
    linear = srgb.code_to_linear(codes)
    luminance.collect(False)
    plain = srgb.code_to_linear(codes.copy())
    np.testing.assert_array_equal(linear, plain)
    f = metric_scale(*shape)
    blocks = blocks_of(linear, f)
    assert blocks is not None and blocks_of(plain, f) is None and blocks_of(linear, f + 1) is None
    np.testing.assert_array_equal(blocks, luminance_area(plain, f))
    np.testing.assert_array_equal(blocks, codes_luminance_area(codes, f))
    assert srgb.attached_codes(linear, 8) is codes                  # still an unchanged decoded frame


def reference_luminance_area(rgb: np.ndarray, f: int) -> np.ndarray:
    """luminance.py's order of float32 operations in NumPy: per block row, each column summed over its f rows in
    order, then the f columns of a block in order, scaled and weighted."""
    h, w = rgb.shape[0] // f, rgb.shape[1] // f
    weights = np.asarray(luminance.LUMINANCE_WEIGHTS, np.float32)
    out = np.empty((h, w), np.float32)
    for i in range(h):
        acc = rgb[i * f, : w * f].astype(np.float32)
        for k in range(1, f):
            acc = acc + rgb[i * f + k, : w * f]
        acc = acc.reshape(w, f, 3)
        total = acc[:, 0]
        for k in range(1, f):
            total = total + acc[:, k]
        scaled = total * (np.float32(1) / np.float32(f * f))
        out[i] = (scaled[:, 0] * weights[0] + scaled[:, 1] * weights[1]) + scaled[:, 2] * weights[2]
    return out


@pytest.mark.parametrize("shape", [(9, 11), (301, 517), (600, 601), (1465, 1937)])    # f = 1, 2, 3, 7
def test_luminance_area_sums_in_the_documented_order(shape):
    linear = np.random.default_rng(3).uniform(0, 1, (*shape, 3)).astype(np.float32)
    f = metric_scale(*shape)
    np.testing.assert_array_equal(luminance_area(linear, f), reference_luminance_area(linear, f))


@pytest.mark.parametrize("shape", [(301, 517), (1465, 1937)])        # odd widths: rows start at odd pixels
@pytest.mark.parametrize("bgr", [False, True])
def test_encode_keeps_the_blocks_of_a_wanted_frame_only(collecting, shape, bgr):
    rng = np.random.default_rng(1)
    linear = rng.uniform(-0.1, 1.1, (*shape, 3)).astype(np.float32)
    linear[0, :4, 0] = [np.nan, np.inf, 0.0031308, 1.0]               # the encode's edge cases stay as they were
    other = linear.copy()
    f = metric_scale(*shape)
    plain = srgb.linear_to_code(other, 8, bgr=bgr)
    assert blocks_of(other, f) is None and other.flags.writeable      # not wanted: the plain pass
    luminance.want(linear)
    codes = srgb.linear_to_code(linear, 8, bgr=bgr)
    np.testing.assert_array_equal(codes, plain)
    assert not linear.flags.writeable                                # its blocks can never go stale
    luminance.collect(False)
    np.testing.assert_array_equal(blocks_of(linear, f), luminance_area(other, f))


def test_side_pass_leaves_grey_and_16_bit_frames_to_the_plain_passes(collecting):
    grey = random_codes(40, 60)[..., 0]
    assert blocks_of(srgb.code_to_linear(grey), metric_scale(40, 60)) is None
    wide = np.random.default_rng(2).integers(0, 65536, (40, 60, 3), dtype=np.uint16)
    assert blocks_of(srgb.code_to_linear(wide, 16), metric_scale(40, 60)) is None


@pytest.mark.parametrize("name, full_reads", [("cnf11", 0), ("cnf05", 1), ("weather-fog", 0)])
def test_runner_metrics_equal_the_eager_comparison(tmp_path, monkeypatch, name, full_reads):
    """A run's per-step and per-output metrics (deferred, luminance from the decode of the input, the JPEG step's
    and the writer's encodes) equal compare() called step by step with no sRGB side pass; the metrics read only
    ``full_reads`` float frames of their own (CNF05: the fog output, which the windscreen warp resamples)."""
    recipe = load_recipe(ROOT / "recipes" / f"{name}.yaml")
    task = next(t for t in plan(ROOT / "sample_data", recipe) if t.sample.relpath.startswith("camera/"))
    reads = []
    monkeypatch.setattr(metrics, "luminance_area", lambda rgb, f: reads.append(f) or luminance_area(rgb, f))
    entry = process(task, RunContext(ROOT / "sample_data", tmp_path, recipe))
    assert entry["status"] == "ok", entry.get("error")
    assert len(reads) == full_reads
    body = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
    body.setdefault("output", {})["metrics"] = False
    (tmp_path / "off.yaml").write_text(yaml.safe_dump(body))
    (tmp_path / "off").mkdir()
    off = process(task, RunContext(ROOT / "sample_data", tmp_path / "off", load_recipe(tmp_path / "off.yaml")))
    assert off["status"] == "ok", off.get("error")
    assert off["output_sha256"] == entry["output_sha256"] and off["metrics"] == {}   # the same output bytes
    luminance.collect(False)
    data = load(task.sample, ROOT / "sample_data", recipe)
    out, records = apply_models(build_models(recipe, task), data, seed=recipe.seed, key=task.out_relpath,
                                sequence_id=task.sample.sequence_id)
    assert [s["metrics"] for s in entry["steps"]] == [r.metrics for r in records]
    assert entry["metrics"] == (records[0].metrics if len(records) == 1 else metrics.compare(data, out))
    assert entry["metrics"]["psnr_db"] < 100 and 0 < entry["metrics"]["ssim"] < 1
