"""A "CVAT for images 1.1" XML (one file for a task) through camera chains: boxes and polygons follow the geometric
step's map (closed-form oracle of the affine test model, COCO-like coordinates), polylines and points move point by
point, masks are resampled as label images, every other element and attribute is kept; a photometric chain copies the file byte for byte; a shape that
is not moved (ellipse) fails its image naming it."""

from __future__ import annotations

from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest
from test_annotations import WarpTestCamera as AffineCamera
from test_annotations_scalabel import H, W, two_images

from roadview_noise.errors import RecipeError
from roadview_noise.manifest import read_manifest
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run

CVAT_XML = """<?xml version="1.0" encoding="utf-8"?>
<annotations>
  <version>1.1</version>
  <meta><task><id>7</id><name>drive</name><size>3</size><mode>annotation</mode></task></meta>
  <image id="0" name="frames/a.png" width="80" height="60">
    <box label="car" source="manual" occluded="0" xtl="10.50" ytl="12.00" xbr="40.25" ybr="30.00" z_order="0">
      <attribute name="color">red</attribute>
    </box>
    <polygon label="road" source="manual" occluded="0" points="20.00,20.00;34.50,18.25;40.00,30.00;22.00,33.00"
             z_order="0"/>
    <polyline label="lane" source="manual" occluded="0" points="78.00,59.00;30.00,35.00;33.00,31.00" z_order="0"/>
    <points label="light" source="manual" occluded="0" points="44.00,7.00" z_order="0"/>
    <box label="sign" source="manual" occluded="1" xtl="0.00" ytl="0.00" xbr="2.00" ybr="2.00" z_order="0"/>
    <mask label="puddle" source="semi-auto" occluded="0" rle="0, 3, 2, 1, 4, 2, 1, 3, 2" left="50" top="40" width="3"
          height="6" z_order="1"/>
    <tag label="daytime" source="manual"/>
  </image>
  <image id="1" name="frames/b.png" width="80" height="60"/>
  <image id="2" name="frames/gone.png" width="80" height="60"><box label="car" xtl="1" ytl="1" xbr="3" ybr="3"/></image>
</annotations>
"""


@pytest.fixture
def cvat_tree(tmp_path: Path, monkeypatch) -> Path:
    """IN/frames/{a,b}.png and IN/annotations.xml (CVAT's export: the XML beside the images folder)."""
    root = two_images(tmp_path / "in", "frames", monkeypatch)
    (root / "annotations.xml").write_text(CVAT_XML)
    return root


def _run(model: str, in_root: Path, out: Path, **extra):
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 5, "chain": [{"model": model}],
                           "inputs": {"camera": "frames/*.png", "annotations": {"cvat": "annotations.xml", **extra}}},
                          base_dir=in_root.parent)
    return run(recipe, in_root, out, progress=False, echo=lambda *_: None, workers=1)


def _forward(points) -> np.ndarray:
    """CVAT (pixel i on [i, i + 1]) positions through the affine model's closed-form forward map."""
    xy = np.asarray(points, dtype=float).reshape(-1, 2) - 0.5
    return np.stack(AffineCamera().forward(xy[:, 0], xy[:, 1], W, H), axis=1) + 0.5


def _pts(text: str) -> np.ndarray:
    return np.array([[float(v) for v in p.split(",")] for p in text.split(";")])


def test_boxes_polygons_lines_and_points_follow_the_map(cvat_tree, tmp_path):
    assert _run("warp_test.camera", cvat_tree, tmp_path / "out").failed == 0
    root = ElementTree.parse(tmp_path / "out/annotations.xml").getroot()
    source = ElementTree.fromstring(CVAT_XML)
    assert ElementTree.tostring(root.find("meta")) == ElementTree.tostring(source.find("meta"))
    a, b, gone = root.findall("image")
    assert [s.tag for s in a] == ["box", "polygon", "polyline", "points", "mask", "tag"]  # the sign left the image
    box = a.find("box")
    assert box.find("attribute").text == "red" and box.get("occluded") == "0" and box.get("label") == "car"
    np.testing.assert_allclose([float(box.get(k)) for k in ("xtl", "ytl", "xbr", "ybr")],
                               _forward([[10.5, 12.0], [40.25, 30.0]]).ravel(), atol=6e-3)
    np.testing.assert_allclose(_pts(a.find("polygon").get("points")),
                               _forward(_pts(source.find("image/polygon").get("points"))), atol=6e-3)
    line = _forward(_pts(source.find("image/polyline").get("points")))
    assert line[0, 0] > W                                                     # not clipped
    np.testing.assert_allclose(_pts(a.find("polyline").get("points")), line, atol=6e-3)
    np.testing.assert_allclose(_pts(a.find("points").get("points")), _forward([[44.0, 7.0]]), atol=6e-3)
    runs = [0, 3, 2, 1, 4, 2, 1, 3, 2]                                           # the mask: row by row over 3 × 6
    frame = np.zeros((H, W), np.uint8)
    frame[40:46, 50:53] = np.repeat(np.arange(len(runs)) & 1, runs).reshape(6, 3)
    warp = AffineCamera().warp(type("Frame", (), {"shape": (H, W)})(), state={}, drawn={})
    xs, ys = np.rint(warp.map_x).astype(int), np.rint(warp.map_y).astype(int)
    inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
    oracle = np.where(inside, frame[np.clip(ys, 0, H - 1), np.clip(xs, 0, W - 1)], 0)
    mask = a.find("mask")
    left, top, w, h = (int(mask.get(k)) for k in ("left", "top", "width", "height"))
    got = np.zeros((H, W), np.uint8)
    runs = [int(v) for v in mask.get("rle").split(",")]
    got[top:top + h, left:left + w] = np.repeat(np.arange(len(runs)) & 1, runs).reshape(h, w)
    np.testing.assert_array_equal(got, oracle)
    rows, cols = np.flatnonzero(oracle.any(axis=1)), np.flatnonzero(oracle.any(axis=0))
    assert (left, top, w, h) == (cols[0], rows[0], cols[-1] - cols[0] + 1, rows[-1] - rows[0] + 1)
    assert mask.get("source") == "semi-auto" and mask.get("z_order") == "1"
    assert ElementTree.tostring(b) == ElementTree.tostring(source.findall("image")[1])
    assert ElementTree.tostring(gone) == ElementTree.tostring(source.findall("image")[2])   # not in the run
    entry = next(e for e in read_manifest(tmp_path / "out/manifest.jsonl") if e["output"] == "annotations.xml")
    assert entry["coco"]["format"] == "cvat" and entry["coco"]["shapes_dropped"] == 1


def test_photometric_chain_copies_and_unmoved_shapes_fail_their_image(cvat_tree, tmp_path):
    assert _run("compression.camera", cvat_tree, tmp_path / "out").failed == 0
    assert (tmp_path / "out/annotations.xml").read_bytes() == (cvat_tree / "annotations.xml").read_bytes()
    (cvat_tree / "annotations.xml").write_text(CVAT_XML.replace(
        '<tag label="daytime" source="manual"/>', '<ellipse label="wheel" cx="5" cy="5" rx="2" ry="2"/>'))
    assert _run("warp_test.camera", cvat_tree, tmp_path / "out2").failed == 1
    error = next(e["error"] for e in read_manifest(tmp_path / "out2/manifest.jsonl") if e.get("status") == "failed")
    assert "CVAT ellipse shapes of 'frames/a.png' are not moved" in error
    (cvat_tree / "annotations.xml").write_text("<annotations><track id='0' label='car'/></annotations>")
    with pytest.raises(RecipeError, match="CVAT for video XML .* export the task as CVAT for images"):
        _run("warp_test.camera", cvat_tree, tmp_path / "out3")
    (cvat_tree / "annotations.xml").write_text("<dataset/>")
    with pytest.raises(RecipeError, match="not a CVAT for images XML"):
        _run("warp_test.camera", cvat_tree, tmp_path / "out4")


SKELETON = """<skeleton label="person" source="manual" z_order="0">
      <points label="nose" source="manual" outside="0" occluded="0" points="30.00,20.00"></points>
      <attribute name="pose">walking</attribute>
      <points label="ankle" source="manual" outside="0" occluded="1" points="79.00,59.00"></points>
    </skeleton>
    <cuboid label="truck" source="manual" occluded="0" z_order="0" xtl1="10.00" ytl1="10.00" xbl1="10.00"
            ybl1="30.00" xtr1="30.00" ytr1="10.00" xbr1="30.00" ybr1="30.00" xtl2="35.00" ytl2="5.00" xbl2="35.00"
            ybl2="25.00" xtr2="50.00" ytr2="5.00" xbr2="50.00" ybr2="25.00"/>
    <tag label="daytime" source="manual"/>"""


def test_skeleton_points_and_cuboid_corners_move_point_by_point(cvat_tree, tmp_path):
    """A skeleton's points (CVAT 2.x) move as ``points`` shapes, one leaving the image marked ``outside="1"``, its
    attribute child and every attribute kept; a cuboid's eight corners move point by point. Before round 22 the
    image failed under a geometric step."""
    (cvat_tree / "annotations.xml").write_text(CVAT_XML.replace('<tag label="daytime" source="manual"/>', SKELETON))
    assert _run("warp_test.camera", cvat_tree, tmp_path / "out").failed == 0
    a = ElementTree.parse(tmp_path / "out/annotations.xml").getroot().find("image")
    skeleton = a.find("skeleton")
    assert [c.tag for c in skeleton] == ["points", "attribute", "points"] and skeleton.find("attribute").text == \
        "walking"
    nose, ankle = skeleton.findall("points")
    moved = _forward([[30.0, 20.0], [79.0, 59.0]])
    assert moved[1, 0] > W
    np.testing.assert_allclose(_pts(nose.get("points")), moved[:1], atol=6e-3)
    np.testing.assert_allclose(_pts(ankle.get("points")), moved[1:], atol=6e-3)
    assert (nose.get("outside"), ankle.get("outside"), ankle.get("occluded"), nose.get("label")) == \
        ("0", "1", "1", "nose")
    cuboid = a.find("cuboid")
    source = ElementTree.fromstring(f"<i>{SKELETON}</i>").find("cuboid")
    corners = [k + n for n in "12" for c in ("tl", "bl", "tr", "br") for k in ("x" + c, "y" + c)]
    np.testing.assert_allclose([float(cuboid.get(k)) for k in corners],
                               _forward([float(source.get(k)) for k in corners]).ravel(), atol=6e-3)
    assert cuboid.get("label") == "truck" and a.find("tag").get("label") == "daytime"
