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
