"""Photos stored turned or mirrored (EXIF orientation 2–8) are processed upright and written back as stored
(roadview_noise.orientation): pixels turn as Pillow's ``exif_transpose`` turns them, the intrinsics and depth with
them, labels in stored pixel coordinates move as the upright photo's labels moved and turned back."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageOps

from roadview_noise.io.image import read_image
from roadview_noise.orientation import stored, stored_xy, upright, upright_profile, upright_xy
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from roadview_noise.types import CameraProfile

INVERSE = {6: 8, 8: 6}


def _tagged(array: np.ndarray, turn: int, fmt: str = "PNG") -> bytes:
    im = Image.fromarray(array)
    exif = im.getexif()
    exif[0x0112] = turn
    buf = io.BytesIO()
    im.save(buf, format=fmt, exif=exif)
    return buf.getvalue()


@pytest.mark.parametrize("turn", range(1, 9))
def test_pixels_and_coordinates_turn_as_pillow_shows_the_photo(turn):
    stored_px = (np.arange(5 * 7 * 3) % 251).astype(np.uint8).reshape(5, 7, 3)
    shown = np.asarray(ImageOps.exif_transpose(Image.open(io.BytesIO(_tagged(stored_px, turn)))))
    up = upright(stored_px, turn)
    assert up.shape == shown.shape and np.array_equal(up, shown)
    assert np.array_equal(stored(up, turn), stored_px)
    ys, xs = np.mgrid[0:5, 0:7]
    xy = np.c_[xs.ravel(), ys.ravel()]
    q = upright_xy(xy, turn, (5, 7)).astype(int)
    assert np.array_equal(up[q[:, 1], q[:, 0]], stored_px[xy[:, 1], xy[:, 0]])
    assert np.array_equal(stored_xy(q, turn, up.shape[:2]), xy)


@pytest.mark.parametrize("turn", range(1, 9))
def test_intrinsics_turn_with_the_pixels(turn):
    """The principal point moves as a pixel does; a transpose swaps the focal lengths; turning back is exact."""
    p = CameraProfile("k", 7, 5, 6.0, 5.0, 2.25, 1.5)
    up = upright_profile(p, turn)
    assert (up.height_px, up.width_px) == upright(np.zeros((5, 7)), turn).shape
    assert upright_xy([[p.cx_px, p.cy_px]], turn, (5, 7))[0] == pytest.approx([up.cx_px, up.cy_px])
    assert {up.fx_px, up.fy_px} == {6.0, 5.0} and (up.fx_px == 6.0) == (turn < 5)
    assert upright_profile(up, INVERSE.get(turn, turn)) == p


@pytest.mark.parametrize("turn", range(1, 9))
def test_a_lens_map_turned_to_stored_pixels_is_the_lens_it_states(turn):
    """A Brown–Conrady step's map in stored coordinates (StoredWarp) is the pull map of the distortion it states
    for COCO's ``rv_distortion`` (tangential and prism terms swapped and signed by the orientation)."""
    from roadview_noise.orientation import StoredWarp
    from roadview_noise.physics.brown_conrady import BrownConrady

    lens = BrownConrady((2e-6, 1e-10, 0, 0, 0, 0, 3e-4, -4e-4, 2e-4, 1e-7, -3e-4, 2e-7), (31.0, 17.5), (1.1, 0.9))
    warp = StoredWarp.of(lens.pull_map(40, 64), turn)
    stated = warp.distortion.pull_map(*warp.shape)
    assert np.abs(stated.map_x - warp.map_x).max() < 1e-3 and np.abs(stated.map_y - warp.map_y).max() < 1e-3


def _kitti(box) -> str:
    return "Car 0.00 0 0.00 " + " ".join(f"{v:.3f}" for v in box) + " 1.5 1.6 3.9 1.0 1.5 20.0 0.0\n"


def _tree(root: Path, image: np.ndarray, turn: int, profile: CameraProfile, box, polygon, mask) -> None:
    """IN/img/f.png (tagged ``turn``), its KITTI box, label mask, a COCO polygon and the camera profile of its
    pixels."""
    (root / "img").mkdir(parents=True)
    (root / "img" / "f.png").write_bytes(_tagged(image, turn))
    Image.fromarray(mask).save(root / "img" / "f_mask.png")
    (root / "img" / "f.txt").write_text(_kitti(box))
    h, w = image.shape[:2]
    ann = {"id": 1, "image_id": 0, "category_id": 1, "segmentation": [list(polygon)], "area": 1.0, "iscrowd": 0,
           "bbox": [min(polygon[0::2]), min(polygon[1::2]), np.ptp(polygon[0::2]), np.ptp(polygon[1::2])]}
    (root / "img" / "coco.json").write_text(json.dumps(
        {"images": [{"id": 0, "file_name": "f.png", "width": w, "height": h}], "annotations": [ann]}))
    fields = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px")
    (root / "camera.yaml").write_text(json.dumps({k: getattr(profile, k) for k in fields}))


def _moved(root: Path, out: Path, tmp_path: Path):
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 1,
                           "chain": [{"model": "windscreen.camera", "params": {"k1": 4e-7}}],
                           "inputs": {"camera": "img/*.png", "camera_profile": str(root / "camera.yaml"),
                                      "annotations": {"coco": "img/coco.json", "boxes_2d": "{stem}.txt",
                                                      "masks": "{stem}_mask.png"}}},
                           base_dir=tmp_path)
    assert run(recipe, root, out, workers=1, progress=False, echo=lambda *_: None).failed == 0
    box = [float(v) for v in (out / "img" / "f.txt").read_text().split()[4:8]]
    coco = json.loads((out / "img" / "coco.json").read_text())
    polygon = coco["annotations"][0]["segmentation"][0]
    entry = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
    entry["distortion"] = coco["images"][0]["rv_distortion"]
    mask = np.asarray(Image.open(out / "img" / "f_mask.png"))
    return box, np.reshape(polygon, (-1, 2)), mask, entry, read_image(out / "img" / "f.png")


def _pulled(step: dict, xy: np.ndarray) -> np.ndarray:
    """Where a COCO ``rv_distortion`` Brown–Conrady step pulls points (COCO coordinates) from."""
    from roadview_noise.physics.brown_conrady import COEFFICIENTS, BrownConrady

    c, f = np.subtract(step["centre_px"], 0.5), np.asarray(step["unit_px"])
    bc = BrownConrady(tuple(step[k] for k in COEFFICIENTS), tuple(c), tuple(f))
    q = (np.asarray(xy, np.float64) - 0.5 - c) / f
    return np.stack(bc.distort(q[:, 0], q[:, 1]), axis=1) * f + c + 0.5


@pytest.mark.parametrize("turn", [6, 2])
def test_labels_of_a_turned_photo_move_as_those_of_the_upright_photo_turned(tmp_path, turn):
    """A KITTI box, a COCO polygon and a label mask on a photo stored turned (orientation 6, 2) move through the
    windscreen distortion to the labels of the same photo stored upright (orientation 1) moved and then turned,
    within 0.5 px (the mask: equal); the written image is that photo's output turned, with its tag."""
    h, w = 120, 200
    rng = np.random.default_rng(3)
    image = (rng.uniform(0, 255, (h, w, 3))).astype(np.uint8)
    profile = CameraProfile("k", w, h, 150.0, 140.0, 103.0, 55.0)
    box = [12.0, 20.0, 80.0, 70.0]
    polygon = [150.5, 10.0, 195.0, 30.0, 185.0, 110.0, 120.0, 90.0]           # COCO: pixel i on [i, i + 1]
    mask = (np.add.outer(np.arange(h) // 9, np.arange(w) // 13) % 7).astype(np.uint8)
    _tree(tmp_path / "up", image, 1, profile, box, polygon, mask)
    inverse = INVERSE.get(turn, turn)
    corners = stored_xy(np.reshape(box, (2, 2)), turn, (h, w))
    ring = stored_xy(np.reshape(polygon, (-1, 2)) - 0.5, turn, (h, w)) + 0.5
    _tree(tmp_path / "turned", upright(image, inverse), turn, upright_profile(profile, inverse),
          [*corners.min(axis=0), *corners.max(axis=0)], ring.ravel().tolist(), stored(mask, turn))
    up_box, up_ring, up_mask, up_entry, up_out = _moved(tmp_path / "up", tmp_path / "out_up", tmp_path)
    box, ring, moved_mask, entry, out = _moved(tmp_path / "turned", tmp_path / "out_turned", tmp_path)

    assert entry["inputs"]["orientation"] == {"exif": turn, "processed": "upright"}
    assert np.ptp(np.subtract(up_box, [12.0, 20.0, 80.0, 70.0])) > 1                          # visibly moved
    turned = stored_xy(np.reshape(up_box, (2, 2)), turn, (h, w))
    assert box == pytest.approx([*turned.min(axis=0), *turned.max(axis=0)], abs=0.5)
    expected = stored_xy(up_ring - 0.5, turn, (h, w)) + 0.5
    assert ring.shape == expected.shape and np.abs(ring - expected).max() <= 0.5
    assert not np.array_equal(up_mask, mask) and np.array_equal(moved_mask, stored(up_mask, turn))
    (up_step,), (step,) = up_entry["distortion"], entry["distortion"]            # COCO's camera: pulls alike
    assert step["model"] == up_step["model"] == "brown_conrady"
    sh, sw = stored_size = moved_mask.shape
    grid = np.stack(np.meshgrid(np.arange(0, sw, 7.0), np.arange(0, sh, 5.0)), -1).reshape(-1, 2)  # stored, COCO
    from_up = stored_xy(_pulled(up_step, upright_xy(grid - 0.5, turn, stored_size) + 0.5) - 0.5, turn, (h, w)) + 0.5
    assert np.abs(_pulled(step, grid) - from_up).max() < 1e-6
    linear, encoding, _ = out
    assert encoding.exif is not None and np.array_equal(linear, stored(up_out[0], turn))


def test_depth_file_of_a_turned_photo_is_turned_with_it(tmp_path):
    """The depth sidecar is aligned with the stored pixels: fog on a photo stored turned (orientation 8) is the
    upright photo's fog turned back, and ``inputs.orientation: stored`` keeps the stored processing and warns."""
    from roadview_noise.io.depth import write_depth_npy

    h, w = 40, 64
    rng = np.random.default_rng(5)
    image = rng.uniform(0, 255, (h, w, 3)).astype(np.uint8)
    depth = np.linspace(5, 80, h * w, dtype=np.float32).reshape(h, w)
    for name, turn, img, dep in (("up", 1, image, depth), ("turned", 8, stored(image, 8), stored(depth, 8))):
        (tmp_path / name).mkdir()
        (tmp_path / name / "f.png").write_bytes(_tagged(img, turn))
        write_depth_npy(tmp_path / name / "f_depth.npy", dep)
    recipe = {"schema": "rvnoise.recipe/1", "seed": 1, "chain": [{"model": "fog.camera"}],
              "inputs": {"camera": "*.png", "depth": "{stem}_depth.npy"}}
    for name in ("up", "turned"):
        assert run(parse_recipe(recipe, base_dir=tmp_path), tmp_path / name, tmp_path / f"out_{name}", workers=1,
                   progress=False, echo=lambda *_: None).failed == 0
    up = read_image(tmp_path / "out_up" / "f.png")[0]
    assert np.array_equal(read_image(tmp_path / "out_turned" / "f.png")[0], stored(up, 8))

    recipe["inputs"]["orientation"] = "stored"
    assert run(parse_recipe(recipe, base_dir=tmp_path), tmp_path / "turned", tmp_path / "out_stored", workers=1,
               progress=False, echo=lambda *_: None).failed == 0
    entry = json.loads((tmp_path / "out_stored" / "manifest.jsonl").read_text().splitlines()[0])
    assert entry["inputs"]["orientation"] == {"exif": 8, "processed": "as stored"}


def test_the_default_orientation_leaves_the_recorded_recipe_as_it_was():
    """``inputs.orientation: upright`` (the default) is left out of run.json and the recipe's sha256."""
    spec = {"schema": "rvnoise.recipe/1", "chain": [{"model": "fog.camera"}], "inputs": {"camera": "*.png"}}
    plain = parse_recipe(spec)
    explicit = parse_recipe({**spec, "inputs": {"camera": "*.png", "orientation": "upright"}})
    kept = parse_recipe({**spec, "inputs": {"camera": "*.png", "orientation": "stored"}})
    assert "orientation" not in plain.resolved_dict()["inputs"] and plain.sha256() == explicit.sha256()
    assert kept.resolved_dict()["inputs"]["orientation"] == "stored" and kept.sha256() != plain.sha256()


def test_a_sequence_mixing_orientations_gets_its_mud_mask_per_frame_shape(tmp_path):
    """Lens soiling draws its mask once per sequence from the sequence's seed, at each frame's (upright) size: a
    folder with a landscape photo and one stored landscape but shown portrait (orientation 6) is augmented whole,
    the portrait frame with a mask of its own shape, written back in its stored layout."""
    rng = np.random.default_rng(9)
    image = rng.uniform(0, 255, (40, 64, 3)).astype(np.uint8)
    (tmp_path / "in").mkdir()
    for name, turn in (("a.png", 1), ("b.png", 6)):
        (tmp_path / "in" / name).write_bytes(_tagged(image, turn))
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 2, "chain": [{"model": "soiling.camera"}],
                           "inputs": {"camera": "*.png"}})
    assert run(recipe, tmp_path / "in", tmp_path / "out", workers=1, progress=False,
               echo=lambda *_: None).failed == 0
    a, b = (read_image(tmp_path / "out" / n)[0] for n in ("a.png", "b.png"))
    assert a.shape == b.shape == (40, 64, 3) and not np.array_equal(a, b)


@pytest.mark.parametrize("turn", [3, 6])
def test_ground_plane_depth_lies_at_the_displayed_bottom(tmp_path, turn):
    """Fog on ground-plane depth (a road at the bottom, objects standing on it): a photo stored upside down (3) or
    sideways (6), with the camera profile of its stored pixels, gets the upright photo's fog, turned back."""
    h, w = 48, 80
    y = np.arange(h)[:, None, None]
    image = np.broadcast_to(np.where(y < h // 2, 200, 90), (h, w, 3)).astype(np.uint8).copy()   # sky over road
    profile = CameraProfile("k", w, h, 60.0, 58.0, 41.0, 22.5)
    inverse = INVERSE.get(turn, turn)
    fields = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px")
    for name, tag, img, p in (("up", 1, image, profile), ("turned", turn, stored(image, turn),
                                                          upright_profile(profile, inverse))):
        (tmp_path / name).mkdir()
        (tmp_path / name / "f.png").write_bytes(_tagged(img, tag))
        (tmp_path / name / "camera.yaml").write_text(json.dumps({k: getattr(p, k) for k in fields}))
    recipe = {"schema": "rvnoise.recipe/1", "seed": 1, "chain": [{"model": "fog.camera",
                                                                  "params": {"visibility_m": 40}}],
              "inputs": {"camera": "*.png", "depth_source": "ground_plane"}}
    for name in ("up", "turned"):
        assert run(parse_recipe(recipe, base_dir=tmp_path), tmp_path / name, tmp_path / f"out_{name}", workers=1,
                   progress=False, echo=lambda *_: None).failed == 0
    up = read_image(tmp_path / "out_up" / "f.png")[0]
    assert not np.array_equal(up[:4], up[-4:])                        # fogged: the far sky and the near road differ
    assert np.array_equal(read_image(tmp_path / "out_turned" / "f.png")[0], stored(up, turn))


@pytest.mark.parametrize("turn", range(1, 9))
def test_a_tiff_is_read_as_stored_whatever_its_orientation(turn, tmp_path):
    """OpenCV turns a TIFF's pixels by its orientation tag (a PNG's or JPEG's it does not): they are read as stored,
    so the chain turns them upright once and the output is written as stored (before, an oriented TIFF came out
    turned twice as displayed). A tiled one, which OpenCV decodes scrambled, is refused."""
    import tifffile

    from roadview_noise.errors import InputError
    from roadview_noise.physics.srgb import linear_to_code

    codes = (np.arange(5 * 7 * 3) % 251).astype(np.uint8).reshape(5, 7, 3)
    tifffile.imwrite(tmp_path / "f.tif", codes, photometric="rgb", extratags=[(274, 3, 1, turn, True)])
    linear, encoding, _ = read_image(tmp_path / "f.tif")
    assert np.array_equal(linear_to_code(linear, 8), codes)
    big = np.random.default_rng(1).integers(0, 255, (32, 48, 3), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "t.tif", big, photometric="rgb", tile=(16, 16), compression="deflate",
                     extratags=[(274, 3, 1, turn, True)])
    if turn == 1:
        assert np.array_equal(linear_to_code(read_image(tmp_path / "t.tif")[0], 8), big)
    else:
        with pytest.raises(InputError, match="tiled TIFF with orientation"):
            read_image(tmp_path / "t.tif")


def test_resume_redoes_a_turned_photo_an_earlier_run_processed_as_stored(tmp_path):
    """``--resume`` keeps an output processed upright, and redoes one whose entry says it was processed as stored
    (rvnoise before round 20, whose recipe's sha256 is the same)."""
    (tmp_path / "in").mkdir()
    image = np.random.default_rng(4).integers(0, 255, (20, 30, 3), dtype=np.uint8)
    (tmp_path / "in" / "f.png").write_bytes(_tagged(image, 6))
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 1, "chain": [{"model": "rain.camera"}],
                           "inputs": {"camera": "*.png", "depth_source": "ground_plane"}})
    kw = {"workers": 1, "progress": False, "echo": lambda *_: None}
    assert run(recipe, tmp_path / "in", tmp_path / "out", **kw).done == 1
    assert run(recipe, tmp_path / "in", tmp_path / "out", resume=True, **kw).skipped == 1
    manifest = tmp_path / "out" / "manifest.jsonl"
    manifest.write_text(manifest.read_text().replace('"processed": "upright"', '"processed": "as stored, not '
                                                                                 'turned upright"'))
    summary = run(recipe, tmp_path / "in", tmp_path / "out", resume=True, **kw)
    assert summary.skipped == 0 and summary.done == 1


def test_the_alpha_plane_of_a_turned_photo_is_written_back_where_it_was(tmp_path):
    """An RGBA photo stored sideways (orientation 8) through soiling: its alpha plane turns with the pixels and back."""
    rng = np.random.default_rng(6)
    rgba = rng.integers(0, 255, (24, 40, 4), dtype=np.uint8)
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "f.png").write_bytes(_tagged(rgba, 8))
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 2, "chain": [{"model": "soiling.camera"}],
                           "inputs": {"camera": "*.png"}})
    assert run(recipe, tmp_path / "in", tmp_path / "out", workers=1, progress=False,
               echo=lambda *_: None).failed == 0
    _, _, alpha = read_image(tmp_path / "out" / "f.png")
    assert np.array_equal(alpha, rgba[..., 3])


SAMPLE_RAW = Path(__file__).resolve().parents[1] / "sample_data/raw/seq0"


@pytest.mark.parametrize("turn", range(1, 9))
@pytest.mark.parametrize("shape", [(4, 6), (5, 7), (4, 7)])
def test_a_cfa_pattern_turns_with_its_mosaic(turn, shape):
    """The CFA pattern of a mosaic turned upright (and back) is the colours of its new top-left sites, also when a
    flip of an even side shifts the phase: the oracle turns the whole colour map."""
    from roadview_noise.orientation import cfa_pattern

    for pattern in ("RGGB", "GRBG", "GBRG", "BGGR"):
        colours = np.array(list(pattern)).reshape(2, 2)[np.arange(shape[0])[:, None] % 2, np.arange(shape[1]) % 2]
        up = upright(colours.view(np.uint32), turn).view(colours.dtype)
        assert cfa_pattern(pattern, turn, shape, to_upright=True) == "".join(up[:2, :2].ravel())
        assert cfa_pattern("".join(up[:2, :2].ravel()), turn, up.shape, to_upright=False) == pattern


@pytest.mark.parametrize("turn", [3, 6])
def test_a_dng_is_processed_upright_by_its_orientation_tag(tmp_path, monkeypatch, turn):
    """A DNG whose IFD0 Orientation turns it for display (a camera held sideways) is processed upright — the mosaic
    with its CFA pattern and depth — and written back as stored with its tag: the output is the upright DNG's
    output turned back (CNF05: fog, then windscreen distortion). Before round 21 a DNG was processed as stored:
    ``--resume`` redoes such an output (its entry has no ``inputs.orientation``)."""
    import tifffile

    from roadview_noise.io.image import read_exr_channels, write_exr_channels
    from roadview_noise.io.raw import read_dng, write_dng
    from roadview_noise.manifest import read_manifest
    from roadview_noise.orientation import cfa_pattern

    if not (SAMPLE_RAW / "000000.dng").is_file():
        pytest.skip("sample_data/raw is absent")
    dn, pattern, black, white = read_dng(SAMPLE_RAW / "000000.dng")
    depth = read_exr_channels(SAMPLE_RAW / "000000_depth.exr")[0]
    imwrite = tifffile.imwrite
    for name, tag in (("turned", turn), ("up", 1)):
        folder = tmp_path / name / "raw"
        folder.mkdir(parents=True)
        mosaic = dn if tag != 1 else upright(dn, turn)
        cfa = pattern if tag != 1 else cfa_pattern(pattern, turn, dn.shape, to_upright=True)
        monkeypatch.setattr(tifffile, "imwrite", lambda *a, extratags=(), **k: imwrite(
            *a, extratags=[*extratags, (274, "H", 1, tag, True)], **k))
        write_dng(folder / "f.dng", mosaic, cfa, black, white)
        write_exr_channels(folder / "f_depth.exr", {k: v if tag != 1 else upright(v, turn) for k, v in depth.items()})
    monkeypatch.setattr(tifffile, "imwrite", imwrite)
    recipe = parse_recipe({"schema": "rvnoise.recipe/1", "seed": 3, "cnf": "CNF05",
                           "inputs": {"raw": "raw/*.dng", "depth": "{stem}_depth.exr"}}, base_dir=tmp_path)
    for name in ("turned", "up"):
        assert run(recipe, tmp_path / name, tmp_path / f"out_{name}", workers=1, progress=False,
                   echo=lambda *_: None).failed == 0
    out_up = read_dng(tmp_path / "out_up/raw/f.dng")
    out_turned = read_dng(tmp_path / "out_turned/raw/f.dng")
    assert out_turned[1] == pattern and out_up[1] == cfa_pattern(pattern, turn, dn.shape, to_upright=True)
    assert not np.array_equal(out_up[0], upright(dn, turn))                        # fogged and distorted
    np.testing.assert_array_equal(out_turned[0], stored(out_up[0], turn))
    with tifffile.TiffFile(tmp_path / "out_turned/raw/f.dng") as tif:
        assert tif.pages[0].tags[274].value == turn
    entry = read_manifest(tmp_path / "out_turned/manifest.jsonl")[0]
    assert entry["inputs"]["orientation"] == {"exif": turn, "processed": "upright"}
    kw = {"workers": 1, "progress": False, "echo": lambda *_: None, "resume": True}
    assert run(recipe, tmp_path / "turned", tmp_path / "out_turned", **kw).skipped == 1
    manifest = tmp_path / "out_turned/manifest.jsonl"            # as an earlier version wrote it: no orientation
    lines = [json.loads(line) for line in manifest.read_text().splitlines()]
    for e in lines:
        e.get("inputs", {}).pop("orientation", None)
    manifest.write_text("".join(json.dumps(e) + "\n" for e in lines))
    summary = run(recipe, tmp_path / "turned", tmp_path / "out_turned", **kw)
    assert summary.skipped == 0 and summary.done == 1                 # redone upright
