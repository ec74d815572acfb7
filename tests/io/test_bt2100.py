"""BT.2100 PQ and HLG photos (round 24): PNG cICP transfer 16/18 at 8 and 16 bits (and HEIF nclx, test_heif.py)
decoded to linear light by table (reference white 203 cd/m² / 75 % HLG at 1.0), run through the chain and encoded
back with the same curve and tag. Oracles: BT.2100 Table 4 and Table 5 written out here with their constants."""

from __future__ import annotations

import json
import math
import zlib

import numpy as np
import pytest

from roadview_noise.camera_inputs import nominal_profile
from roadview_noise.io.image import read_image, write_image
from roadview_noise.io.png import encode_png
from roadview_noise.models.camera.compression import CompressionCamera
from roadview_noise.models.camera.low_light import LowLightCamera
from roadview_noise.physics import transfers
from roadview_noise.physics.sensor_noise import expose
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from roadview_noise.types import CameraFrame

# BT.2100-2 Table 4 (PQ) and Table 5 (HLG), independent of roadview_noise.physics.bt2100
M1, M2, C1, C2, C3 = 0.1593017578125, 78.84375, 0.8359375, 18.8515625, 18.6875
A, B, C = 0.17883277, 0.28466892, 0.55991073


def pq_signal(luminance_cd_per_m2: float) -> float:
    y = (luminance_cd_per_m2 / 10000.0) ** M1
    return ((C1 + C2 * y) / (1 + C3 * y)) ** M2


def pq_luminance(signal: float) -> float:
    n = signal ** (1 / M2)
    return 10000.0 * (max(n - C1, 0.0) / (C2 - C3 * n)) ** (1 / M1)


def hlg_light(signal: float) -> float:
    return signal * signal / 3 if signal <= 0.5 else (math.exp((signal - C) / A) + B) / 12


def _chunk(kind: bytes, body: bytes) -> bytes:
    return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")


def _png(path, codes: np.ndarray, transfer: int) -> None:
    """A PNG of RGB codes with a cICP chunk (BT.2020 primaries, ``transfer``, RGB, full range) after IHDR, as
    Chrome's and Adobe's HDR exports carry it."""
    data = encode_png(codes)
    path.write_bytes(data[:33] + _chunk(b"cICP", bytes([9, transfer, 0, 1])) + data[33:])


@pytest.mark.parametrize("luminance,signal", [(10000.0, 1.0), (100.0, 0.5081), (203.0, 0.5806)])
def test_pq_decode_and_encode_match_table_4_within_one_code(luminance, signal):
    assert pq_signal(luminance) == pytest.approx(signal, abs=1e-4)           # the BT.2408 figures (4 digits)
    code = round(pq_signal(luminance) * 65535)
    step = pq_luminance((code + 1) / 65535) - pq_luminance(code / 65535)
    decoded = transfers.decode_table("pq", 16)[code] * 203.0
    assert abs(decoded - pq_luminance(code / 65535)) <= 1e-4 * step + 1e-6 * luminance
    assert abs(decoded - luminance) <= step
    encoded = int(transfers.linear_to_code(np.float32([luminance / 203.0]), "pq", 16)[0])
    assert abs(encoded - pq_signal(luminance) * 65535) <= 0.5 + 1e-3


@pytest.mark.parametrize("signal,light", [(0.5, 1 / 12), (0.75, None), (1.0, 1.0), (0.25, 0.25 ** 2 / 3)])
def test_hlg_decode_and_encode_match_table_5_within_one_code(signal, light):
    """Scene light E of E' (Table 5's inverse OETF) over E(0.75): reference white 1.0."""
    reference = hlg_light(0.75)
    light = reference if light is None else light
    assert hlg_light(signal) == pytest.approx(light, rel=1e-6)
    code = round(signal * 65535)
    step = (hlg_light(min(code + 1, 65535) / 65535) - hlg_light((code - 1) / 65535)) / 2 / reference
    decoded = float(transfers.decode_table("hlg", 16)[code])
    assert abs(decoded - hlg_light(code / 65535) / reference) <= 1e-6 * max(decoded, 1e-3)
    assert abs(decoded - light / reference) <= step
    encoded = int(transfers.linear_to_code(np.float32([light / reference]), "hlg", 16)[0])
    assert abs(encoded - signal * 65535) <= 0.5 + 1e-3                 # E' = 0.5 falls on a half code: either
    white = round(0.75 * 65535)
    white_step = (hlg_light((white + 1) / 65535) - hlg_light(white / 65535)) / reference
    assert abs(transfers.decode_table("hlg", 16)[white] - 1.0) <= white_step


def _ramp(bits: int, h: int = 24, w: int = 64) -> np.ndarray:
    full = 2 ** bits - 1
    t = np.linspace(0, 1, h * w).reshape(h, w)
    return np.rint(np.stack([t, t[::-1, ::-1], 0.2 + 0.8 * t], axis=-1) * full).astype(
        np.uint8 if bits == 8 else np.uint16)


@pytest.mark.parametrize("transfer,curve", [(16, "pq"), (18, "hlg")])
@pytest.mark.parametrize("bits", [8, 16])
def test_a_pq_or_hlg_png_is_read_linear_and_written_back_with_its_codes_and_tag(tmp_path, transfer, curve, bits):
    codes = _ramp(bits)
    _png(tmp_path / "in.png", codes, transfer)
    linear, encoding, _ = read_image(tmp_path / "in.png")
    assert encoding.transfer == curve and encoding.bit_depth == bits
    np.testing.assert_array_equal(linear, transfers.decode_table(curve, bits)[codes])
    assert linear.max() == pytest.approx(transfers.peak(curve), rel=1e-6)              # highlights above white kept
    write_image(tmp_path / "out.png", linear, encoding)
    back, again, _ = read_image(tmp_path / "out.png")
    assert again.transfer == curve and again.metadata == encoding.metadata            # the cICP chunk kept
    np.testing.assert_array_equal(back, linear)                                      # the very codes back


def fog_on_file_and_linear(tmp_path, radiance: np.ndarray, transfer: int, curve: str, bits: int = 16) -> tuple:
    """Fog 30 m (sky: the top quarter, depth ``inf``; the rest at 25 m) on a ``bits``-bit PNG of ``radiance``
    (reference white 1.0) coded with ``curve`` and tagged cICP ``transfer``, and on a linear-tagged 16-bit PNG of
    the radiance that file holds / the curve's peak: (fog of the file, fog of the linear PNG × peak, the file's
    encoding, its manifest entry)."""
    h, w = radiance.shape[:2]
    codes = transfers.linear_to_code(radiance.astype(np.float32), curve, bits)
    scene = transfers.decode_table(curve, bits)[codes].astype(np.float64)          # what the file holds
    peak = transfers.peak(curve)
    src = tmp_path / "in"
    src.mkdir()
    _png(src / "coded.png", codes, transfer)
    data = encode_png(np.rint(scene / peak * 65535).astype(np.uint16))
    (src / "lin.png").write_bytes(data[:33] + _chunk(b"gAMA", (100000).to_bytes(4, "big")) + data[33:])
    depth = np.full((h, w), 25.0, np.float32)
    depth[: h // 4] = np.inf
    for stem in ("coded", "lin"):
        np.save(src / f"{stem}_depth.npy", depth)
    recipe = parse_recipe({"chain": [{"model": "fog.camera", "params": {"visibility_m": 30}}], "seed": 1,
                           "inputs": {"camera": "*.png", "depth": "{stem}_depth.npy"}})
    assert run(recipe, src, tmp_path / "out", workers=1, progress=False).failed == 0
    fog_coded, enc, _ = read_image(tmp_path / "out/coded.png")
    fog_lin, _, _ = read_image(tmp_path / "out/lin.png")
    entries = {json.loads(e)["input"]: json.loads(e) for e in (tmp_path / "out/manifest.jsonl").read_text()
               .splitlines()}
    return fog_coded, fog_lin * peak, enc, entries["coded.png"]


@pytest.mark.parametrize("transfer,curve", [(16, "pq"), (18, "hlg")])
def test_fog_on_a_pq_or_hlg_file_is_fog_on_the_same_radiance_given_linear(tmp_path, transfer, curve):
    """Same physics through another curve: the PQ (HLG) file's radiance (reference white 1.0, a sky at 3.5× white)
    and a linear-tagged 16-bit PNG of that radiance / 49.26 (3.774: its full scale) give the same fog once scaled
    back — fog is linear in radiance and its airlight comes from the frame's sky. Read as sRGB (before round 24)
    the codes gave other radiance, e.g. the PQ sky at 0.47 of the linear full scale instead of 0.071."""
    h, w = 32, 48
    rng = np.random.default_rng(5)
    radiance = rng.uniform(0.02, 2.5, (h, w, 3))
    radiance[: h // 4] = 3.5                                                    # sky, 711 cd/m² on a PQ display
    fog_pq, fog_lin, enc, entry = fog_on_file_and_linear(tmp_path, radiance, transfer, curve)
    peak = transfers.peak(curve)
    assert enc.transfer == curve
    np.testing.assert_allclose(fog_pq, fog_lin, rtol=2e-3, atol=2 * peak / 65535)
    assert fog_pq[: h // 4].min() > 3.45                                         # the airlight, 3.5× white, kept
    assert entry["inputs"]["transfer"] == {"value": curve, "scale": transfers.TRANSFERS[curve].scale,
                                           "from": f"the file (PNG cICP transfer {transfer})"}
    assert "warnings" not in entry["inputs"]
    assert entry["steps"][0]["diagnostics"]["airlight"] == pytest.approx([3.5] * 3, rel=2e-3)


def test_a_transfer_rvnoise_does_not_decode_is_read_as_srgb_with_a_warning(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    _png(src / "st240.png", _ramp(16), 7)                   # SMPTE 240M: not decoded
    _png(src / "hlg.png", _ramp(16), 18)
    recipe = parse_recipe({"chain": [{"model": "compression.camera"}], "seed": 1, "inputs": {"camera": "*.png"}})
    lines = []
    assert run(recipe, src, tmp_path / "out", workers=1, progress=False, echo=lines.append).failed == 0
    notes = {json.loads(e)["input"]: json.loads(e)["inputs"] for e in (tmp_path / "out/manifest.jsonl")
             .read_text().splitlines()}
    assert notes["st240.png"]["transfer"]["value"] == "srgb" and "SMPTE 240M" in notes["st240.png"]["transfer"]["file"]
    assert notes["st240.png"]["warnings"] == ["transfer_read_as_srgb"]
    assert notes["hlg.png"]["transfer"]["value"] == "hlg" and "warnings" not in notes["hlg.png"]
    assert sum("1 PNG/HEIF file(s) state a transfer function" in line for line in lines) == 1


def test_models_that_assume_full_scale_1_clip_highlights_above_reference_white_as_documented():
    """JPEG (compression.camera) codes 8-bit sRGB: values above reference white become white (1.0). Low light's
    notional sensor has its full well at 1.0: above 1 / (k·g) it saturates — with the defaults (k·g = 0.008) that
    is 125× white, above PQ's peak (49.3), so nothing clips; at k·g = 1 (illuminance ≥ reference / max_gain)
    highlights flatten to 1.0."""
    levels = np.float32([0.5, 1.0, 3.0, 49.0])                                      # × reference white
    linear = np.ascontiguousarray(np.broadcast_to(np.repeat(levels, 4)[None, :, None], (16, 16, 3)))
    bright = linear[..., 0] >= 1.0
    frame = CameraFrame(linear, nominal_profile(16, 16))
    out, _ = CompressionCamera(quality=100, chroma_subsampling="4:4:4").apply(frame, state=None, drawn=None,
                                                                            rng=None)
    assert out.linear_rgb.max() <= 1.0 and out.linear_rgb[bright].min() >= 0.99
    assert abs(out.linear_rgb[~bright].mean() - 0.5) < 0.01
    rng = np.random.default_rng(0)
    night = LowLightCamera(adc_bits=16)
    dark = expose(linear, night.settings(0.01), rng, noise=False)
    np.testing.assert_allclose(dark, linear * 0.008, rtol=1e-3, atol=1e-4)        # unclipped up to 49× white
    dusk = LowLightCamera(illuminance_lux=5000.0, adc_bits=16)                      # k = 0.5, g = 2
    flat = expose(linear, dusk.settings(0.01), rng, noise=False)
    np.testing.assert_allclose(flat[bright], 1.0, atol=1e-4)                        # 1×, 3×, 49× white: saturated
    np.testing.assert_allclose(flat[~bright], 0.5, atol=1e-4)


def test_without_a_sky_in_the_depth_a_lamp_above_white_is_not_taken_for_the_sky():
    """The fallback sky level (the brightest 0.1 % of the pixels) takes each pixel at most at reference white, as
    an 8-bit camera's clipped pixels give it: a lamp at 40× white in an HDR photo made the airlight 40× white."""
    from roadview_noise.models.camera.fog import FogCamera

    rng = np.random.default_rng(3)
    linear = rng.uniform(0.05, 0.8, (40, 60, 3)).astype(np.float32)
    linear[10:14, 20:26] = 40.0                                                   # a street lamp, 1 % of the frame
    frame = CameraFrame(linear, nominal_profile(60, 40), depth_m=np.full((40, 60), 30.0, np.float32))
    _, diagnostics = FogCamera().apply(frame, state=None, drawn=None, rng=None)
    assert diagnostics["airlight"] == pytest.approx([1.0] * 3)
    sdr = CameraFrame(linear / 50, nominal_profile(60, 40), depth_m=frame.depth_m)   # all below 1: as before
    _, diagnostics = FogCamera().apply(sdr, state=None, drawn=None, rng=None)
    assert diagnostics["airlight"] == pytest.approx([40.0 / 50] * 3, rel=1e-6)
