"""An input is read once: the runner hashes its bytes and hands them to the sample's reader (runner.sha256_input
with ``whole``, dataset.load's ``content``)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np

from roadview_noise.dataset import Sample
from roadview_noise.io import image as image_io
from roadview_noise.runner import _read_whole, sha256_input


def _png(path: Path, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    cv2.imwrite(str(path), rng.integers(0, 256, (12, 16, 3), dtype=np.uint8))
    return path


def test_the_reader_decodes_the_hashed_bytes_without_reading_again(tmp_path, monkeypatch):
    path = _png(tmp_path / "a.png", 0)
    expected = image_io.read_image(path)[0]
    digest, content = sha256_input(path, whole=True)
    assert digest == hashlib.sha256(path.read_bytes()).hexdigest() == hashlib.sha256(content).hexdigest()
    _png(tmp_path / "b.png", 1).replace(path)       # changed after the hash: the reader decodes what was hashed
    monkeypatch.setattr(Path, "read_bytes", lambda self: (_ for _ in ()).throw(AssertionError("read again")))
    np.testing.assert_array_equal(image_io.read_image(path, content)[0], expected)


def test_streamed_hash_keeps_no_bytes(tmp_path):
    path = _png(tmp_path / "a.png", 0)
    digest, content = sha256_input(path)
    assert content is None and digest == hashlib.sha256(path.read_bytes()).hexdigest()


def test_which_inputs_are_read_whole(tmp_path):
    def sample(relpath, modality):
        return Sample(relpath=relpath, modality=modality, sequence_id="s")

    assert _read_whole(sample("a.png", "camera"), tmp_path / "a.png")
    assert _read_whole(sample("a.JPG", "camera"), tmp_path / "a.JPG")
    assert not _read_whole(sample("a.exr", "camera"), tmp_path / "a.exr")     # OpenEXR reads the path
    assert _read_whole(sample("a.pcd", "lidar"), tmp_path / "a.pcd")
    assert _read_whole(sample("a.pcd", "radar"), tmp_path / "a.pcd")
    assert not _read_whole(sample("a.dng", "raw"), tmp_path / "a.dng")


def test_a_cloud_header_is_checked_in_the_bytes_already_read(tmp_path):
    """The point limit reads a cloud's declared size from its bytes when the runner has them (no second open): the
    same count as from the file, for PCD (POINTS, or WIDTH × HEIGHT), PLY and a fixed-layout .bin."""
    import pytest

    from roadview_noise.errors import InputError
    from roadview_noise.io.headers import check_size, cloud_points

    pcd = Path(__file__).resolve().parents[2] / "sample_data/radar/seq0/000000.pcd"
    ply = tmp_path / "a.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 7\nproperty float x\nend_header\n"
                    + bytes(28))
    organised = tmp_path / "o.pcd"
    organised.write_bytes(b"VERSION 0.7\nFIELDS x\nSIZE 4\nTYPE F\nCOUNT 1\nWIDTH 4\nHEIGHT 3\nDATA binary\n"
                          + bytes(48))
    kitti = tmp_path / "k.bin"
    kitti.write_bytes(bytes(16 * 5))
    for path, fmt, n in ((pcd, "pcd", None), (ply, "ply", 7), (organised, "pcd", 12), (kitti, "kitti_bin", 5)):
        data = path.read_bytes()
        assert cloud_points(path, fmt, data) == cloud_points(path, fmt) == (n or cloud_points(path, fmt))
        assert cloud_points(tmp_path / "missing", fmt, data) == cloud_points(path, fmt)   # the bytes only
    with pytest.raises(InputError, match="declares 12 points"):
        check_size(tmp_path / "missing.pcd", max_points=11, cloud_fmt="pcd", data=organised.read_bytes())
