"""Camera transfers other than sRGB (round 24, roadview_noise/physics/transfers.py): BT.709 / BT.601 / BT.2020
(H.273 transfers 1, 6, 14, 15: one OETF) and gamma 2.2 / 2.8 (4, 5) decoded by table to linear light (reference
white 1.0) and encoded back with the same curve and tag; 13 (sRGB) read as sRGB without a warning. Oracles: the
closed forms of BT.709-6 Table 1 item 1.2 (rounded constants) and BT.2020-2 Table 4 (exact α, β) written out here."""

from __future__ import annotations

import json

import numpy as np
import pytest

from roadview_noise.io.image import read_image, write_image
from roadview_noise.physics import srgb, transfers
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from tests.io.test_bt2100 import _png, _ramp, fog_on_file_and_linear

ALPHA, BETA = 1.09929682680944, 0.018053968510807          # BT.2020-2 Table 4, exact


def bt709_signal(light: float, a: float = 1.099, b: float = 0.018) -> float:
    """BT.709-6 Table 1 item 1.2: V = 1.099 L^0.45 − 0.099 for L ≥ 0.018, 4.5 L below."""
    return 4.5 * light if light < b else a * light ** 0.45 - (a - 1)


def bt709_light(signal: float, a: float = 1.099, b: float = 0.018) -> float:
    return signal / 4.5 if signal < 4.5 * b else ((signal + a - 1) / a) ** (1 / 0.45)


def test_the_bt709_curve_meets_table_1s_figures():
    """V(0.018) = 0.081, V(1) = 1 (BT.709's own figures); the exact α, β of BT.2020 differ from BT.709's rounded
    1.099 / 0.018 by at most 0.00025 in V (0.064 of an 8-bit code), at the rounded curve's step at L = 0.018."""
    assert bt709_signal(0.018 - 1e-12) == pytest.approx(0.081, abs=1e-10) and bt709_signal(1.0) == pytest.approx(1.0)
    assert bt709_signal(0.018) == pytest.approx(0.08125, abs=1e-5)            # the rounded constants' step
    assert transfers.encode(0.018, "bt709") == pytest.approx(0.081, abs=1e-12)
    assert transfers.encode(1.0, "bt709") == pytest.approx(1.0, abs=1e-12)
    light = np.linspace(0, 1, 100001)
    exact = np.array([bt709_signal(x, ALPHA, BETA) for x in light])
    rounded = np.array([bt709_signal(x) for x in light])
    np.testing.assert_allclose(transfers.encode(light, "bt709"), exact, atol=1e-12)
    assert 2.4e-4 < np.abs(exact - rounded).max() < 2.6e-4
    np.testing.assert_allclose(transfers.decode(exact, "bt709"), light, atol=1e-12)
    assert bt709_signal(BETA, ALPHA, BETA) == pytest.approx(ALPHA * BETA ** 0.45 - (ALPHA - 1), abs=1e-12)


@pytest.mark.parametrize("bits,codes", [(8, [0, 5, 20, 21, 22, 60, 128, 200, 254, 255]),
                                        (10, [0, 17, 82, 83, 84, 300, 512, 900, 1023])])
def test_bt709_codes_decode_to_table_1s_inverse_within_one_code_step(bits, codes):
    """8-bit codes and 10-bit ones (a BT.2020 10-bit HEIF, on its 16-bit carry round(c · 65535 / 1023)) against
    BT.709's rounded constants: within one code step of the light (the curves differ by ≤ 0.25 of a 10-bit code)."""
    full = 2 ** bits - 1
    table = transfers.decode_table("bt709", 8 if bits == 8 else 16)
    for c in codes:
        got = float(table[c if bits == 8 else round(c * 65535 / full)])
        step = bt709_light(min(c + 1, full) / full) - bt709_light(max(c - 1, 0) / full)
        assert abs(got - bt709_light(c / full)) <= step / 2 + 1e-7, c


@pytest.mark.parametrize("code", [0, 1, 300, 5324, 5325, 5400, 20000, 47000, 65534, 65535])
def test_16_bit_bt709_codes_decode_to_the_exact_curve_and_encode_back(code):
    """16 bits (and 12: a BT.2020 12-bit file): the exact α, β, to float32 precision; the encoder gives the code
    nearest the exact OETF of the light."""
    light = bt709_light(code / 65535, ALPHA, BETA)
    assert float(transfers.decode_table("bt709", 16)[code]) == pytest.approx(light, rel=1e-6, abs=1e-9)
    encoded = int(transfers.linear_to_code(np.float32([light]), "bt709", 16)[0])
    assert encoded == code


@pytest.mark.parametrize("curve,gamma", [("gamma22", 2.2), ("gamma28", 2.8)])
@pytest.mark.parametrize("bits", [8, 16])
def test_gamma_codes_decode_to_the_pure_power_and_encode_back(curve, gamma, bits):
    full = 2 ** bits - 1
    codes = np.array([0, 1, 2, full // 7, full // 2, full - 1, full])
    light = (codes / full) ** gamma
    np.testing.assert_allclose(transfers.decode_table(curve, bits)[codes], light, rtol=1e-6, atol=1e-30)
    mid = ((codes[1:] - 0.4) / full) ** gamma                     # just above the half-way levels: the code above
    assert transfers.linear_to_code(mid.astype(np.float32), curve, bits).tolist() == codes[1:].tolist()


@pytest.mark.parametrize("curve", transfers.CURVES)
@pytest.mark.parametrize("bits", [8, 16])
def test_every_code_decodes_and_encodes_back_and_values_between_round_to_the_nearest(curve, bits):
    codes = np.arange(2 ** bits, dtype=np.uint8 if bits == 8 else np.uint16)
    linear = transfers.code_to_linear(codes, curve, bits)
    assert np.array_equal(transfers.linear_to_code(linear, curve, bits), codes)
    rng = np.random.default_rng(1)
    signal = rng.uniform(0, 1, 20000)
    values = transfers.decode(signal, curve).astype(np.float32)
    exact = np.rint(signal * (2 ** bits - 1))       # the nearest code of the signal the float32 value decodes from
    got = transfers.linear_to_code(values, curve, bits).astype(float)
    assert np.abs(got - exact).max() <= 1 and np.mean(got != exact) < 1e-3
    ends = transfers.linear_to_code(np.float32([-1.0, np.nan, 1e9, transfers.peak(curve) * 1.01]), curve, bits)
    assert ends.tolist() == [0, 0, 2 ** bits - 1, 2 ** bits - 1]


@pytest.mark.parametrize("transfer,curve", [(1, "bt709"), (6, "bt709"), (14, "bt709"), (15, "bt709"),
                                            (4, "gamma22"), (5, "gamma28")])
@pytest.mark.parametrize("bits", [8, 16])
def test_a_png_of_a_camera_transfer_is_read_linear_and_written_back_with_its_codes_and_tag(tmp_path, transfer, curve,
                                                                                          bits):
    codes = _ramp(bits)
    _png(tmp_path / "in.png", codes, transfer)
    linear, encoding, _ = read_image(tmp_path / "in.png")
    assert encoding.transfer == curve and encoding.bit_depth == bits
    np.testing.assert_array_equal(linear, transfers.decode_table(curve, bits)[codes])
    write_image(tmp_path / "out.png", linear, encoding)
    back, again, _ = read_image(tmp_path / "out.png")
    assert again.transfer == curve and again.metadata == encoding.metadata            # the cICP chunk kept
    np.testing.assert_array_equal(back, linear)                                      # the very codes back


def test_a_run_names_the_curve_reads_13_as_srgb_silently_and_warns_only_of_transfers_still_read_as_srgb(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    for name, transfer in (("bt709", 1), ("bt601", 6), ("g28", 5), ("srgb", 13), ("log", 9)):
        _png(src / f"{name}.png", _ramp(8), transfer)
    recipe = parse_recipe({"chain": [{"model": "compression.camera"}], "seed": 1, "inputs": {"camera": "*.png"}})
    lines = []
    assert run(recipe, src, tmp_path / "out", workers=1, progress=False, echo=lines.append).failed == 0
    notes = {json.loads(e)["input"]: json.loads(e).get("inputs", {}) for e in (tmp_path / "out/manifest.jsonl")
             .read_text().splitlines()}
    assert notes["bt709.png"]["transfer"] == {"value": "bt709", "scale": transfers.TRANSFERS["bt709"].scale,
                                              "from": "the file (PNG cICP transfer 1)"}
    assert notes["bt601.png"]["transfer"]["value"] == "bt709" and notes["g28.png"]["transfer"]["value"] == "gamma28"
    assert "transfer" not in notes["srgb.png"]
    assert notes["log.png"]["transfer"]["value"] == "srgb" and notes["log.png"]["warnings"] == ["transfer_read_as_srgb"]
    assert all("warnings" not in notes[f"{n}.png"] for n in ("bt709", "bt601", "g28", "srgb"))
    assert sum("1 PNG/HEIF file(s) state a transfer function" in line for line in lines) == 1
    linear, encoding, _ = read_image(src / "srgb.png")
    assert encoding.transfer == "srgb"
    np.testing.assert_array_equal(linear, srgb.decode_table(8)[_ramp(8)])


@pytest.mark.parametrize("bits", [8, 16])
def test_fog_on_a_bt709_file_is_fog_on_the_same_radiance_given_linear(tmp_path, bits):
    """The BT.709 file's scene light and a linear-tagged 16-bit PNG of it give the same fog (30 m, airlight from the
    sky at 0.95 of white): within 2e-3 relative or two 16-bit linear steps, and one code of the output's
    depth. Read as sRGB (before round 24) a BT.709 code of light 0.2 stood for 0.158 and the sky 0.95 for
    0.944."""
    h, w = 32, 48
    radiance = np.random.default_rng(7).uniform(0.01, 0.9, (h, w, 3))
    radiance[: h // 4] = 0.95
    fog_coded, fog_lin, enc, entry = fog_on_file_and_linear(tmp_path, radiance, 1, "bt709", bits)
    assert enc.transfer == "bt709" and enc.bit_depth == bits
    codes_of = lambda x: transfers.linear_to_code(x, "bt709", bits).astype(int)      # noqa: E731
    if bits == 16:
        np.testing.assert_allclose(fog_coded, fog_lin, rtol=2e-3, atol=2 / 65535)
    assert np.abs(codes_of(fog_coded) - codes_of(fog_lin)).max() <= 1      # 8 bits: the output's rounding
    assert entry["steps"][0]["diagnostics"]["airlight"] == pytest.approx([0.95] * 3, rel=2e-3 if bits == 16 else 1e-2)
    assert "warnings" not in entry["inputs"]
