"""COCO-format dataset files (one JSON for a whole dataset): read, checked, written back with every key kept, and
the segmentation encodings of the COCO API.

A COCO file (https://cocodataset.org/#format-data) has ``images`` (``id``, ``file_name``, ``width``, ``height``),
``annotations`` (``id``, ``image_id``, ``bbox`` [x, y, w, h], ``segmentation``, ``area``, ``iscrowd``, optional
``keypoints`` [x, y, v, …] and ``num_keypoints``), ``categories``, ``info``, ``licenses`` and any other key
(mmdetection3d's ``*_mono3d.coco.json`` adds camera matrices to images and ``bbox_cam3d``, ``center2d`` … to
annotations). Coordinates are continuous pixel positions with the image spanning [0, W] × [0, H] (pixel ``i``
covers [i, i + 1]).

Segmentations: a list of polygons ``[[x1, y1, x2, y2, …], …]``, or run-length encoding (RLE) of the mask in
column-major order starting with a run of zeros, ``{"size": [H, W], "counts": …}`` — ``counts`` a list of run
lengths ("uncompressed", COCO's crowd annotations) or the COCO API's compressed string (6 bits per character with
a continuation bit, runs after the second as differences to the run two before). Decoding and encoding use the
COCO API (``pycocotools.mask``); the uncompressed list is read and written from the mask's runs here.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .atomic import write_bytes_atomic


def read_coco(path: str | os.PathLike) -> dict[str, Any]:
    """The parsed dataset; InputError names the file when it is not a COCO dataset (``images`` with ``id`` and
    ``file_name``, ``annotations`` with ``image_id``)."""
    data = read_dataset_json(path, "COCO", "coco")
    if not isinstance(data, dict) or not isinstance(data.get("images"), list):
        raise InputError("not a COCO dataset: no list 'images' at the top level", file=str(path))
    for key, required in (("images", ("id", "file_name")), ("annotations", ("image_id",))):
        items = data.get(key, [])
        if not isinstance(items, list):
            raise InputError(f"not a COCO dataset: '{key}' is not a list", file=str(path))
        for i, item in enumerate(items):
            missing = [k for k in required if not isinstance(item, dict) or k not in item]
            if missing:
                raise InputError(f"{key}[{i}] has no {', '.join(repr(k) for k in missing)}", file=str(path))
    return data


def read_dataset_json(path: str | os.PathLike, kind: str, key: str) -> Any:
    """A dataset file's parsed JSON (``kind`` and its recipe ``key`` under inputs.annotations name it in errors)."""
    try:
        return json.loads(Path(path).read_bytes())
    except FileNotFoundError:
        raise InputError(f"the {kind} file of inputs.annotations.{key} does not exist", file=str(path)) from None
    except OSError as exc:
        raise InputError(f"cannot read the {kind} file: {exc.strerror or exc}", file=str(path)) from None
    except ValueError as exc:
        raise InputError(f"not JSON ({exc})", file=str(path)) from None


def write_coco(path: str | os.PathLike, data: dict[str, Any]) -> None:
    """The dataset as compact UTF-8 JSON, atomically (key order and every value as given)."""
    write_bytes_atomic(path, json.dumps(data, ensure_ascii=False, separators=(",", ":")).encode("utf-8"))


# --- segmentation masks ----------------------------------------------------------------------------------------------


def _mask_api():
    try:
        from pycocotools import mask
    except ImportError:
        raise InputError("RLE segmentations need the COCO API: pip install 'pycocotools>=2.0.8'") from None
    return mask


def _decode(api, rle) -> np.ndarray:
    """``pycocotools.mask.decode`` (its NumPy 2 ``copy=False`` DeprecationWarning is the library's, not the data's)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return np.ascontiguousarray(api.decode(rle))


def is_rle(segmentation: Any) -> bool:
    return isinstance(segmentation, dict) and "counts" in segmentation


def rle_size(segmentation: dict) -> tuple[int, int]:
    """(H, W) of an RLE segmentation."""
    h, w = segmentation.get("size", (None, None))
    return int(h), int(w)


def rle_decode(segmentation: dict) -> np.ndarray:
    """The uint8 mask (H, W) of an RLE segmentation, compressed or uncompressed."""
    h, w = rle_size(segmentation)
    counts = segmentation["counts"]
    if isinstance(counts, list):                     # runs alternate 0, 1, 0, … down the columns
        if sum(counts) != h * w:
            raise ValueError(f"RLE counts add up to {sum(counts)} pixels, size {h}×{w} has {h * w}")
        flat = np.repeat(np.arange(len(counts), dtype=np.uint8) & 1, counts)
        return np.ascontiguousarray(flat.reshape(w, h).T)
    api = _mask_api()
    return _decode(api, {"size": [h, w], "counts": counts.encode("ascii") if isinstance(counts, str) else counts})


def rle_encode(mask: np.ndarray, compressed: bool) -> dict:
    """RLE of a mask (H, W): ``counts`` the COCO API's string when ``compressed``, else the list of run lengths
    (column-major, starting with the run of zeros)."""
    h, w = mask.shape
    if compressed:
        rle = _mask_api().encode(np.asfortranarray(mask.astype(np.uint8)))
        return {"size": [h, w], "counts": rle["counts"].decode("ascii")}
    flat = (mask.ravel(order="F") != 0).astype(np.int8)
    edges = np.flatnonzero(np.diff(flat)) + 1
    bounds = np.concatenate([[0], edges, [flat.size]])
    runs = np.diff(bounds).tolist()
    if flat.size and flat[0]:
        runs = [0] + runs
    return {"size": [h, w], "counts": runs}

