"""Depth readers/writers: EXR/npy round trips, CARLA 24-bit decoding, planar → range, bad input."""

from __future__ import annotations

import math

import cv2
import numpy as np
import OpenEXR
import pytest

from roadview_noise.errors import InputError
from roadview_noise.io.depth import read_depth, write_carla_depth_png, write_depth_exr, write_depth_npy
from roadview_noise.types import CameraProfile

PROFILE = CameraProfile("test", 40, 30, fx_px=20.0, fy_px=20.0, cx_px=20.0, cy_px=15.0)  # explicit K


def _depth(shape=(30, 40)):
    d = np.random.default_rng(0).uniform(0.5, 300.0, shape).astype(np.float32)
    d[0, :5] = np.inf
    return d


@pytest.mark.parametrize("writer,name", [(write_depth_exr, "d.exr"), (write_depth_npy, "d.npy")])
def test_float_roundtrip(tmp_path, writer, name):
    d = _depth()
    writer(tmp_path / name, d)
    back = read_depth(tmp_path / name, expected_shape=(30, 40))
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, d)
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_exr_is_zip_single_z(tmp_path):
    write_depth_exr(tmp_path / "d.exr", _depth())
    with OpenEXR.File(str(tmp_path / "d.exr")) as exr:
        assert exr.header()["compression"] == OpenEXR.ZIP_COMPRESSION
        assert list(exr.channels()) == ["Z"]


@pytest.mark.parametrize("channels,expected", [({"B": 1, "G": 2, "R": 3}, 3), ({"depth": 4, "A": 5}, 4),
                                               ({"Z": 6, "Y": 7}, 6), ({"b": 8, "a": 9}, 9),
                                               # Blender's multilayer EXR: the depth pass is a layer's Z, and the
                                               # layer's alpha sorts first (it was read as 1 m everywhere)
                                               ({"ViewLayer.Combined.A": 1, "ViewLayer.Combined.R": 0.5,
                                                 "ViewLayer.Depth.Z": 26.5}, 26.5)])
def test_exr_channel_choice(tmp_path, channels, expected):
    arrays = {k: np.full((4, 5), v, np.float32) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, arrays) as exr:
        exr.write(str(tmp_path / "c.exr"))
    assert read_depth(tmp_path / "c.exr")[0, 0] == expected        # "a" sorts first in the file: the first channel


def test_carla_png_decoding_oracle(tmp_path):
    bgr = np.zeros((30, 40, 3), np.uint8)
    bgr[...] = (3, 2, 1)                          # B, G, R → code 1 + 2·256 + 3·65536
    bgr[5, 7] = (255, 255, 255)                   # far plane: sky
    cv2.imwrite(str(tmp_path / "carla.png"), bgr)
    d = read_depth(tmp_path / "carla.png", profile=PROFILE)
    z = 1000.0 * (1 + 2 * 256 + 3 * 65536) / (2 ** 24 - 1)
    u, v = 0, 29
    factor = math.sqrt(1 + ((u - 20) / 20) ** 2 + ((v - 15) / 20) ** 2)
    assert d[v, u] == pytest.approx(z * factor, rel=1e-6)
    assert d[15, 20] == pytest.approx(z, rel=1e-6)                 # principal point: range = z
    assert np.isinf(d[5, 7]) and np.isfinite(d).sum() == d.size - 1


@pytest.mark.parametrize("grey", [np.array([[0, 60], [93, 255]]), np.array([[140, 141], [255, 255]])])
def test_carla_grey_visualisation_refused(tmp_path, grey):
    """CARLA's Depth / LogarithmicDepth converters save R = G = B (BGRA): read as the 24-bit code, a log-grey 93
    (≈ 26 m) became 365 m and fog turned the frame white; such a file is refused, naming the converter to use."""
    g = np.kron(grey, np.ones((15, 20), np.int64)).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "log.png"), np.dstack([g, g, g, np.full_like(g, 255)]))
    with pytest.raises(InputError, match="grey.*ColorConverter.Raw") as err:
        read_depth(tmp_path / "log.png", profile=PROFILE)
    assert "log.png" in str(err.value)
    sky = np.full((30, 40, 4), 255, np.uint8)                      # raw depth that is all far plane: sky, not refused
    cv2.imwrite(str(tmp_path / "sky.png"), sky)
    assert np.isinf(read_depth(tmp_path / "sky.png", profile=PROFILE)).all()


def test_carla_png_roundtrip(tmp_path):
    z = _depth()
    write_carla_depth_png(tmp_path / "z.png", z)
    img = cv2.imread(str(tmp_path / "z.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (30, 40, 4) and (img[..., 3] == 255).all()
    got = read_depth(tmp_path / "z.png", profile=PROFILE)
    finite = np.isfinite(z)
    np.testing.assert_array_equal(np.isinf(got), ~finite)
    step = 1000.0 / (2 ** 24 - 1)                                  # one code of planar depth
    error = np.abs(got[finite] - _range(z)[finite])
    assert np.all(error <= 0.5 * step * _ray_factor()[finite] + 1e-4)


def _ray_factor():
    """‖ray‖ / z for PROFILE: sqrt(1 + ((u − cx)/fx)² + ((v − cy)/fy)²) (models.md §0.2)."""
    v, u = np.mgrid[0:30, 0:40]
    return np.sqrt(1 + ((u - 20) / 20.0) ** 2 + ((v - 15) / 20.0) ** 2)


def _range(z):
    return z * _ray_factor()


def test_planar_exr_converted(tmp_path):
    z = _depth()
    write_depth_exr(tmp_path / "p.exr", z)
    got = read_depth(tmp_path / "p.exr", profile=PROFILE, planar=True)
    np.testing.assert_allclose(got, _range(z), rtol=1e-6)


def test_bad_depth_inputs(tmp_path):
    d = _depth()
    write_depth_npy(tmp_path / "d.npy", d)
    with pytest.raises(InputError, match=r"30×40.*20×40") as err:
        read_depth(tmp_path / "d.npy", expected_shape=(20, 40))
    assert "d.npy" in str(err.value)
    with pytest.raises(InputError, match="camera profile"):
        read_depth(tmp_path / "d.npy", planar=True)
    with pytest.raises(InputError, match="'small' is 15×20"):
        read_depth(tmp_path / "d.npy", planar=True, profile=CameraProfile("small", 20, 15, 10, 10, 10, 7.5))

    bad = d.copy()
    bad[1, 1], bad[2, 2], bad[3, 3], bad[4, 4] = np.nan, -1.0, -2.0, 0.0
    np.save(tmp_path / "bad.npy", bad)
    got = read_depth(tmp_path / "bad.npy")              # holes come back as NaN; depth_holes decides (depth/holes.py)
    assert np.isnan(got).sum() == 4 and all(np.isnan(got[k, k]) for k in range(1, 5))
    assert np.isinf(got[0, :5]).all()                   # sky stays sky

    np.save(tmp_path / "mm.npy", np.ones((3, 3), np.uint16))
    with pytest.raises(InputError, match="float array"):
        read_depth(tmp_path / "mm.npy")

    write_depth_exr(tmp_path / "t.exr", d)
    (tmp_path / "t.exr").write_bytes((tmp_path / "t.exr").read_bytes()[:300])
    with pytest.raises(InputError, match="EXR") as err:
        read_depth(tmp_path / "t.exr")
    assert "t.exr" in str(err.value)

    (tmp_path / "d.tif").write_bytes(b"II*\x00")
    with pytest.raises(InputError, match="unknown depth suffix"):
        read_depth(tmp_path / "d.tif")
    write_carla_depth_png(tmp_path / "cut.png", d)
    (tmp_path / "cut.png").write_bytes((tmp_path / "cut.png").read_bytes()[:-12])
    with pytest.raises(InputError, match="IEND") as err:
        read_depth(tmp_path / "cut.png", profile=PROFILE)
    assert "cut.png" in str(err.value)


def test_holes_become_nan_in_the_readers_own_arrays_and_on_a_copy_of_any_other():
    from roadview_noise.io.depth import _holes_as_nan

    d = np.array([[1.0, 0.0], [-1.0, np.inf]], np.float32)
    fixed = _holes_as_nan(d)                            # a reader's fresh float32 array: in place, no copy
    assert fixed is d and np.isnan(d[0, 1]) and np.isnan(d[1, 0]) and d[0, 0] == 1 and np.isinf(d[1, 1])
    frozen = np.array([[2.0, -3.0]], np.float32)
    frozen.flags.writeable = False
    got = _holes_as_nan(frozen)
    assert got is not frozen and frozen[0, 1] == -3 and np.isnan(got[0, 1])
    half = np.array([[0.0, 5.0]], np.float16)           # an EXR HALF channel
    got = _holes_as_nan(half)
    assert got.dtype == np.float32 and np.isnan(got[0, 0]) and half[0, 0] == 0
