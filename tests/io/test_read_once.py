"""Camera inputs are read once: the runner hashes the bytes and hands them to the decoder (io.image.hand_over)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import cv2
import numpy as np

from roadview_noise.io import image as image_io
from roadview_noise.runner import sha256_input


def _png(path: Path, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    cv2.imwrite(str(path), rng.integers(0, 256, (12, 16, 3), dtype=np.uint8))
    return path


def test_decoder_takes_the_hashed_bytes_without_reading_again(tmp_path, monkeypatch):
    path = _png(tmp_path / "a.png", 0)
    expected = image_io.read_image(path)[0]
    digest = sha256_input(path, keep=True)
    assert digest == hashlib.sha256(path.read_bytes()).hexdigest()
    reads = []
    real = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda self: reads.append(self) or real(self))
    np.testing.assert_array_equal(image_io.read_image(path)[0], expected)
    assert reads == []                              # decoded from the kept bytes
    image_io.read_image(path)                       # one use: the next read reads the file
    assert reads == [path]


def test_a_file_changed_after_the_hash_is_read_anew(tmp_path):
    path = _png(tmp_path / "a.png", 0)
    sha256_input(path, keep=True)
    _png(tmp_path / "b.png", 1).replace(path)       # another file (inode) under the same name
    np.testing.assert_array_equal(image_io.read_image(path)[0], image_io.read_image(_png(tmp_path / "c.png", 1))[0])


def test_another_file_read_in_between_empties_the_slot(tmp_path):
    a, b = _png(tmp_path / "a.png", 0), _png(tmp_path / "b.png", 1)
    sha256_input(a, keep=True)
    image_io.read_image(b)
    assert image_io._handed is None
    os.utime(a)                                     # (still read correctly from the file)
    assert image_io.read_image(a)[0].shape == (12, 16, 3)


def test_exr_images_are_not_kept(tmp_path):
    path = tmp_path / "x.exr"
    image_io.write_exr_channels(path, {c: np.full((4, 5), 0.5, np.float32) for c in "RGB"})
    assert sha256_input(path, keep=True) == hashlib.sha256(path.read_bytes()).hexdigest()
    assert image_io._handed is None
