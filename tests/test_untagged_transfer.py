"""16-bit camera images whose file states no transfer function (round 20): a mono16 PNG or TIFF written by OpenCV,
PIL or a machine-vision SDK carries no gAMA/sRGB/iCCP/cICP chunk and usually linear sensor counts. The PNG spec
leaves the reading to the user ("choose a likely default … but allow the user to select a new one"): sRGB by
default, counted in one warning line per run and recorded in the manifest; ``inputs.untagged_transfer: linear``
reads them as linear; a file that states gAMA 1.0 or a linear cICP is read linear whatever the recipe says."""

from __future__ import annotations

import zlib
from pathlib import Path

import cv2
import numpy as np

from roadview_noise.io.image import read_image, write_image
from roadview_noise.manifest import read_manifest
from roadview_noise.physics import srgb
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run


def _chunk(kind: bytes, body: bytes) -> bytes:
    return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")


def _mono16(path: Path, *chunks: bytes) -> np.ndarray:
    """A 16-bit grey PNG (or TIFF, by the suffix) as OpenCV writes it, with ``chunks`` after IHDR."""
    codes = (np.arange(40 * 64).reshape(40, 64) * 25).astype(np.uint16)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), codes)
    if chunks:
        data = path.read_bytes()
        path.write_bytes(data[:33] + b"".join(chunks) + data[33:])
    return codes


def test_what_the_file_states_wins_and_the_recipe_decides_the_rest(tmp_path):
    codes = _mono16(tmp_path / "plain.png")
    _mono16(tmp_path / "plain.tif")
    _mono16(tmp_path / "gamma1.png", _chunk(b"gAMA", (100000).to_bytes(4, "big")))
    _mono16(tmp_path / "gamma045.png", _chunk(b"gAMA", (45455).to_bytes(4, "big")))
    _mono16(tmp_path / "srgb_over_gamma1.png", _chunk(b"sRGB", b"\x00"), _chunk(b"gAMA", (100000).to_bytes(4, "big")))
    _mono16(tmp_path / "cicp_linear.png", _chunk(b"cICP", bytes([1, 8, 0, 1])))
    as_srgb = srgb.code_to_linear(codes, 16)
    as_linear = codes / np.float32(65535)
    expected = {"plain.png": (as_srgb, as_linear), "plain.tif": (as_srgb, as_linear),
                "gamma1.png": (as_linear, as_linear), "gamma045.png": (as_srgb, as_srgb),
                "srgb_over_gamma1.png": (as_srgb, as_srgb), "cicp_linear.png": (as_linear, as_linear)}
    for name, (default, untagged_linear) in expected.items():
        for untagged, want in (("srgb", default), ("linear", untagged_linear)):
            linear, encoding, _ = read_image(tmp_path / name, untagged_transfer=untagged)
            np.testing.assert_allclose(linear[..., 0], want, rtol=1e-6, err_msg=f"{name}, untagged {untagged}")
            assert encoding.transfer == ("linear" if want is as_linear else "srgb")
    linear, encoding, _ = read_image(tmp_path / "plain.png", untagged_transfer="linear")
    write_image(tmp_path / "back.png", linear, encoding)                 # written back with the codes it had
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "back.png"), cv2.IMREAD_UNCHANGED), codes)


def test_untagged_16_bit_files_are_warned_once_and_recorded(tmp_path):
    root = tmp_path / "in"
    for name in ("a.png", "b.tif"):
        _mono16(root / name)
        np.save(root / f"{Path(name).stem}_depth.npy", np.full((40, 64), 20.0, np.float32))
    _mono16(root / "c.png", _chunk(b"gAMA", (100000).to_bytes(4, "big")))
    np.save(root / "c_depth.npy", np.full((40, 64), 20.0, np.float32))

    def augment(out, **inputs):
        recipe = parse_recipe({"chain": [{"model": "fog.camera", "params": {"visibility_m": 30}}], "seed": 1,
                               "inputs": {"camera": ["*.png", "*.tif"], "depth": "{stem}_depth.npy", **inputs}})
        lines = []
        assert run(recipe, root, tmp_path / out, workers=1, progress=False, echo=lines.append).failed == 0
        notes = {e["input"]: e["inputs"] for e in read_manifest(tmp_path / out / "manifest.jsonl")}
        return notes, [line for line in lines if "state no transfer function" in line]

    notes, warned = augment("default")
    assert len(warned) == 1 and "2 16-bit image(s)" in warned[0] and "untagged_transfer: linear" in warned[0]
    for name in ("a.png", "b.tif"):
        assert notes[name]["transfer"] == {"value": "srgb", "from": "default (the file states none)"}
        assert "untagged_16bit" in notes[name]["warnings"]
    assert notes["c.png"]["transfer"]["value"] == "linear" and "warnings" not in notes["c.png"]
    notes, warned = augment("linear", untagged_transfer="linear")
    assert warned == [] and notes["a.png"]["transfer"]["value"] == "linear"
    # the same linear counts through the same fog: the sRGB reading brightened the dark half far more
    dark = slice(0, 20)
    lin = cv2.imread(str(tmp_path / "linear/a.png"), cv2.IMREAD_UNCHANGED)[dark].mean()
    dflt = cv2.imread(str(tmp_path / "default/a.png"), cv2.IMREAD_UNCHANGED)[dark].mean()
    assert dflt > lin * 1.03
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "linear/a.png"), cv2.IMREAD_UNCHANGED),
                                  cv2.imread(str(tmp_path / "default/c.png"), cv2.IMREAD_UNCHANGED))
