"""Bilinear resampling through a precomputed table equals cv2.remap (INTER_LINEAR, float maps) within float32
rounding, for every border mode, channel count and map that leaves the input."""

import cv2
import numpy as np
import pytest

from roadview_noise.physics.bilinear_table import OUTSIDE, PARTLY_INSIDE, BilinearTable, TabledWarp
from roadview_noise.physics.brown_conrady import BrownConrady

BORDERS = (cv2.BORDER_CONSTANT, cv2.BORDER_REFLECT_101, cv2.BORDER_REPLICATE, cv2.BORDER_REFLECT)


def lens_maps(h, w, k1, p1=0.0):
    warp = BrownConrady((k1, 0, 0, 0, 0, 0, p1, 0, 0, 0, 0, 0), ((w - 1) / 2, (h - 1) / 2), (1.0, 1.0))
    return warp.pull_map(h, w)


def close_to_remap(table_out, image, map_x, map_y, border, fill):
    ref = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=border, borderValue=fill)
    assert table_out.shape == ref.shape and table_out.dtype == np.float32
    np.testing.assert_allclose(table_out, ref, rtol=1e-6, atol=1e-6 * float(np.abs(image).max()))


@pytest.mark.parametrize("border", BORDERS)
@pytest.mark.parametrize("channels", [None, 1, 2, 3, 4])
@pytest.mark.parametrize("k1", [2e-6, -4e-6])          # pincushion corners outside the input; barrel inside
def test_equals_cv2_remap(border, channels, k1):
    h, w = 97, 131                                       # odd sizes
    rng = np.random.default_rng(1)
    image = rng.uniform(-1, 3, (h, w) if channels is None else (h, w, channels)).astype(np.float32)
    warp = lens_maps(h, w, k1, p1=3e-4)
    assert warp.table.accepts(image) == (channels != 2)  # cv2 blends 2 channels in 1/32-px steps: left to it
    for fill in (0.0, 0.7):
        close_to_remap(warp.apply(image, border=border, fill=fill), image, warp.map_x, warp.map_y, border, fill)


def test_cells_outside_partly_inside_and_nan():
    map_x = np.array([[0.0, 1.5, 3.0, -0.5, -2.0, 10.0, np.nan]], np.float32)
    map_y = np.array([[0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0]], np.float32)
    table = BilinearTable.of(map_x, map_y, (2, 4))
    assert table.cell.tolist() == [0, 1, PARTLY_INSIDE, PARTLY_INSIDE, OUTSIDE, OUTSIDE, PARTLY_INSIDE]
    assert table.frac_x[1] == 0.5 and table.frac_y[1] == 0.5
    assert table.edge.tolist() == [2, 3, 4, 5, 6] and table.partly.tolist() == [2, 3, 6]
    image = np.arange(8, dtype=np.float32).reshape(2, 4)
    out = table.apply(image, border=cv2.BORDER_CONSTANT, fill=-1.0)
    assert out[0, 0] == 0 and out[0, 1] == pytest.approx(3.5) and out[0, 4] == out[0, 5] == -1.0


def test_many_edge_pixels_cross_the_rows_of_edge_maps():
    """More edge pixels than one row of the cv2 edge maps (EDGE_ROW) still land where they belong."""
    h, w = 300, 400
    warp = lens_maps(h, w, 1e-5)                          # strong pincushion: most pixels sample outside
    table = BilinearTable.of(warp.map_x, warp.map_y, (h, w))
    assert table.edge.size > 3 * table.edge_map[0].shape[1]
    image = np.random.default_rng(2).random((h, w, 3), dtype=np.float32)
    close_to_remap(table.apply(image, border=cv2.BORDER_REFLECT_101), image, warp.map_x, warp.map_y,
                   cv2.BORDER_REFLECT_101, 0.0)


def test_faster_only_where_it_is():
    h, w = 120, 160
    inside, corners = (BilinearTable.of(m.map_x, m.map_y, (h, w)) for m in (lens_maps(h, w, -4e-6),
                                                                          lens_maps(h, w, 1e-5)))
    assert inside.faster(cv2.BORDER_REFLECT_101) and inside.faster(cv2.BORDER_CONSTANT)
    assert corners.faster(cv2.BORDER_CONSTANT) and not corners.faster(cv2.BORDER_REFLECT_101)


def test_tabled_warp_falls_back_to_cv2_for_other_inputs():
    h, w = 60, 80
    lens = lens_maps(h, w, 3e-6)
    warp = TabledWarp(lens.map_x, lens.map_y)
    labels = np.random.default_rng(3).integers(0, 255, (h, w)).astype(np.uint8)
    np.testing.assert_array_equal(warp.apply(labels), cv2.remap(labels, lens.map_x, lens.map_y, cv2.INTER_LINEAR,
                                                                borderMode=cv2.BORDER_REFLECT_101))
    five = np.random.default_rng(4).random((h, w, 5), dtype=np.float32)   # > 4 channels: per channel
    close_to_remap(warp.apply(five)[..., 4], five[..., 4], lens.map_x, lens.map_y, cv2.BORDER_REFLECT_101, 0.0)
    assert not warp.table.accepts(five)
    small = np.zeros((h - 1, w), np.float32)                             # not the map's size: cv2 alone
    assert warp.apply(small).shape == (h, w)
    with pytest.raises(ValueError, match="float32"):
        warp.table.apply(labels, border=cv2.BORDER_CONSTANT)
