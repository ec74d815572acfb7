"""The one box mover (roadview_noise.physics.outline_warp) of KITTI / YOLO boxes (annotations.warp_boxes) and COCO
boxes (coco_warp): against a dense ground truth — 2 000 points per edge moved by the same warps — under strong
distortion, with boxes crossing and touching the border and boxes of 1–2 px; the identity gives the input back; a
YOLO box and a COCO box over the same pixels move to the same box."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from roadview_noise.annotations import warp_boxes
from roadview_noise.coco_warp import CocoImage, move_image
from roadview_noise.io.annotations import Boxes2D, read_boxes_2d, write_boxes_2d
from roadview_noise.physics.brown_conrady import COEFFICIENTS, BrownConrady
from roadview_noise.physics.outline_warp import BOX_TOLERANCE_PX, forward_through, moved_boxes
from roadview_noise.physics.warp import Warp

W, H = 640, 400
DENSE = 2000


def _grid() -> tuple[np.ndarray, np.ndarray]:
    return (np.broadcast_to(np.arange(W, dtype=np.float32), (H, W)).copy(),
            np.broadcast_to(np.arange(H, dtype=np.float32)[:, None], (H, W)).copy())


def _lens(**k) -> Warp:
    """Windscreen distortion as the model builds it: coefficients in px of a 1936-px-wide reference image."""
    unit = W / 1936
    return BrownConrady(tuple(k.get(n, 0.0) for n in COEFFICIENTS), ((W - 1) / 2, (H - 1) / 2),
                        (unit, unit)).pull_map(H, W)


def _barrel() -> Warp:
    """A plain pull map (no closed-form inverse: Warp's fixed-point forward map), strong barrel."""
    u, v = _grid()
    x, y = (u - (W - 1) / 2) / W, (v - (H - 1) / 2) / W
    f = 1 + 0.6 * (x * x + y * y)
    return Warp(((W - 1) / 2 + W * x * f).astype(np.float32), ((H - 1) / 2 + W * y * f).astype(np.float32))


# strong, with no fold over the boxes (a strong negative k1 folds the map where it cuts the input's corners away:
# there the moved edge is arbitrarily steep and no sampling is bounded; outline_warp's docstring)
WARPS = {"lens k1 +1e-6": lambda: [_lens(k1=1e-6)],                     # corners pulled in by 60 px
         "lens k1 -8e-8": lambda: [_lens(k1=-8e-8)],                     # corners pushed out by 40 px
         "tangential and prism": lambda: [_lens(k1=3e-7, p1=2e-4, p2=-3e-4, s1=2e-4, s3=-2e-4)],
         "plain pull map": lambda: [_barrel()],
         "two lenses": lambda: [_lens(k1=5e-7), _lens(k1=-5e-8, p1=1e-4)]}


def _boxes(n: int = 60) -> np.ndarray:
    """x0, y0, x1, y1 (warp coordinates): 1–600 px, some crossing the border (by ≤ 20 px); 10 of 1–2 px; 12
    touching it."""
    rng = np.random.default_rng(4)
    centre = rng.uniform([-20, -20], [W + 20, H + 20], (n, 2))
    size = np.exp(rng.uniform(0, np.log(600), (n, 2))) * [1, 0.6]
    b = np.clip(np.concatenate([centre - size / 2, centre + size / 2], axis=1), -20, [W + 20, H + 20] * 2)
    b[:10, 2:] = b[:10, :2] + rng.uniform(1, 2, (10, 2))
    b[10:13, 0], b[13:16, 1], b[16:19, 2], b[19:22, 3] = 0.0, 0.0, W - 1.0, H - 1.0
    return b


@lru_cache(maxsize=None)
def _dense_truth(name: str) -> np.ndarray:
    """Each box's outline sampled at DENSE points per edge, moved by the warps, its bounds (not clipped)."""
    boxes, warps = _boxes(), WARPS[name]()
    t = np.linspace(0.0, 1.0, DENSE)[None, :]
    x0, y0, x1, y1 = (c[:, None] for c in boxes.T)
    one = np.ones_like(t)
    xs = np.concatenate([x0 + (x1 - x0) * t, x1 * one, x1 - (x1 - x0) * t, x0 * one], axis=1)
    ys = np.concatenate([y0 * one, y0 + (y1 - y0) * t, y1 * one, y1 - (y1 - y0) * t], axis=1)
    q = forward_through(warps, np.stack([xs.ravel(), ys.ravel()], axis=1)).reshape(len(boxes), -1, 2)
    return np.concatenate([q.min(axis=1), q.max(axis=1)], axis=1)


def _records(fmt: str, boxes: np.ndarray) -> Boxes2D:
    return Boxes2D(fmt, [[str(i)] for i in range(len(boxes))], [b.reshape(2, 2) for b in boxes], [True] * len(boxes))


@pytest.mark.parametrize("name", list(WARPS))
@pytest.mark.parametrize("fmt", ["kitti", "yolo"])
def test_moved_boxes_are_within_twice_the_tolerance_of_the_dense_truth(name, fmt):
    warps, boxes = WARPS[name](), _boxes()
    lo, hi = (0.0, [W - 1, H - 1]) if fmt == "kitti" else (-0.5, [W - 0.5, H - 0.5])
    truth = np.clip(_dense_truth(name), lo, [*hi, *hi])               # = the bounds of the clipped points
    out = warp_boxes(_records(fmt, boxes), warps, W, H)
    got = {int(t[0]): p.ravel() for t, p in zip(out.tokens, out.points_px)}
    visible = {i for i, b in enumerate(truth) if np.all(b[2:] - b[:2] > 2 * BOX_TOLERANCE_PX)}
    assert visible <= set(got) and len(visible) > 30                  # nothing visible dropped
    err = np.array([np.abs(got[i] - truth[i]).max() for i in got])
    assert err.max() <= 2 * BOX_TOLERANCE_PX + 1e-6, (name, err.max())
    tiny = [np.abs(got[i] - truth[i]).max() for i in range(10) if i in got]
    assert tiny and max(tiny) <= 2 * BOX_TOLERANCE_PX
    moved = np.abs(np.array([got[i] for i in got]) - boxes[list(got)]).max()
    assert moved > 5                                                   # the warps do move the boxes


def test_identity_gives_the_input_back(tmp_path):
    boxes = np.clip(_boxes(), 0, [W - 1, H - 1] * 2)
    boxes = boxes[np.all(boxes[:, 2:] > boxes[:, :2], axis=1)]
    out = warp_boxes(_records("kitti", boxes), [Warp(*_grid())], W, H)
    np.testing.assert_allclose(np.reshape(out.points_px, (-1, 4)), boxes, rtol=0, atol=1e-9)
    src = tmp_path / "in.txt"
    src.write_text("".join(f"Car 0.00 0 -1.58 {x0:.2f} {y0:.2f} {x1:.2f} {y1:.2f} 1.50 1.60 3.90 -1.00 1.70 12.00 "
                           f"-1.59\n" for x0, y0, x1, y1 in boxes))
    write_boxes_2d(tmp_path / "out.txt", warp_boxes(read_boxes_2d(src, "kitti", W, H), [Warp(*_grid())], W, H), W, H)
    assert (tmp_path / "out.txt").read_text() == src.read_text()


def test_affine_map_moves_only_the_corners():
    """An affine map bends no edge: each box costs its 4 corners and 4 edge midpoints (one call) and lands on its
    moved corners' box."""
    calls = []

    def affine(xy):
        calls.append(len(xy))
        return xy @ np.array([[1.07, 0.0], [0.0, 0.93]]) + [6.3, -4.6]

    boxes = _boxes(20)
    got = moved_boxes(boxes, affine)
    assert calls == [160]                                              # corners and midpoints in one call
    np.testing.assert_allclose(got, np.concatenate([affine(boxes[:, :2]), affine(boxes[:, 2:])], axis=1), atol=1e-9)


def test_a_yolo_box_and_a_coco_box_over_the_same_pixels_move_alike():
    warps, boxes = WARPS["tangential and prism"](), _boxes()
    yolo = warp_boxes(_records("yolo", boxes), warps, W, H)
    coco = boxes + 0.5                                                # COCO puts pixel i on [i, i + 1]
    image = CocoImage(0, "f.png", W, H, "sha", [(i, {"id": i, "bbox": [x0, y0, x1 - x0, y1 - y0]})
                                                  for i, (x0, y0, x1, y1) in enumerate(coco)])
    record = move_image(image, (H, W), warps)
    moved = {pos: fields["bbox"] for pos, fields in record["moved"]}
    kept = [int(t[0]) for t in yolo.tokens]
    assert set(kept) <= set(moved) and all(np.prod(moved[i][2:]) == 0 for i in set(moved) - set(kept))
    for words, pts in zip(yolo.tokens, yolo.points_px):
        (x0, y0), (x1, y1) = pts + 0.5
        np.testing.assert_allclose(moved[int(words[0])], [x0, y0, x1 - x0, y1 - y0], atol=6e-4)   # 1/1000 px
