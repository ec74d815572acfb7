"""Malformed inputs of every format through the whole runner (seeded, reproducible): truncations, bit flips and
headers that lie, in PNG, EXR (depth), DNG, PCD (ascii, binary, binary_compressed), PLY (ascii, binary) and KITTI
``.bin``. Every file gets exactly one manifest entry; a truncated file or a lying header fails with a message naming
the file, never with a traceback; no file takes long; the input tree is byte-identical afterwards; no temporary is
left and every file in OUT is listed in the manifest."""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from test_cli import _cloud, _image

from roadview_noise.io.depth import write_depth_exr
from roadview_noise.io.image import write_image
from roadview_noise.io.pointcloud import write_pointcloud
from roadview_noise.io.raw import write_dng
from roadview_noise.manifest import read_manifest, sha256_file
from roadview_noise.recipe import parse_recipe
from roadview_noise.runner import run
from roadview_noise.types import CloudLayout, ImageEncoding

SEED = 12
H, W = 48, 64
PER_FILE_S = 5.0
CAMERA_PROFILE = {"width_px": W, "height_px": H, "fov_h_deg": 80.8}


def _truncations(data: bytes, rng, n: int, avoid_multiple_of: int = 0) -> list[bytes]:
    out = []
    while len(out) < n:
        k = int(rng.integers(len(data) // 10, len(data) * 9 // 10))
        if avoid_multiple_of and k % avoid_multiple_of == 0:
            continue
        out.append(data[:k])
    return out


def _bit_flips(data: bytes, rng, n: int, start: int = 0) -> list[bytes]:
    out = []
    for _ in range(n):
        b = bytearray(data)
        for pos in rng.integers(start, len(b), int(rng.integers(1, 9))):
            b[pos] ^= 1 << int(rng.integers(8))
        out.append(bytes(b))
    return out


def _png_lies(data: bytes) -> list[bytes]:
    def with_size(w: int, h: int) -> bytes:
        ihdr = data[12:16] + struct.pack(">II", w, h) + data[24:29]
        return data[:12] + ihdr + struct.pack(">I", zlib.crc32(ihdr)) + data[33:]

    return [with_size(W * 2, H), with_size(W, H // 2), with_size(40000, 40000), with_size(0, H)]


def _exr_lies(data: bytes) -> list[bytes]:
    at = data.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    out = []
    for x1, y1 in ((W * 2 - 1, H - 1), (W - 1, H // 2 - 1), (99999, 99999), (-5, H - 1)):
        out.append(data[:at + 8] + struct.pack("<ii", x1, y1) + data[at + 16:])
    return out


def _dng_lies(path: Path) -> list[bytes]:
    import tifffile

    data = path.read_bytes()
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        spots = [(tags[name].valueoffset, tags[name].dtype) for name in ("ImageWidth", "ImageLength")]
    out = []
    for which, value in ((0, W * 4), (1, H // 2), (0, 60000), (1, 0)):
        offset, dtype = spots[which]
        fmt = "<I" if int(dtype) == 4 else "<H"
        out.append(data[:offset] + struct.pack(fmt, value) + data[offset + struct.calcsize(fmt):])
    return out


def _count_lies(data: bytes, key: bytes, n: int) -> list[bytes]:
    return [re.sub(key + rb" \d+", key + b" " + str(v).encode(), data, count=1)
            for v in (n // 2, n + 7, 10**12, -3)]


def _write_all(folder: Path, stem: str, valid: bytes, variants: list[bytes], suffix: str) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, v in enumerate(variants):
        name = f"{stem}{i:02d}{suffix}"
        (folder / name).write_bytes(v)
        names.append(name)
    return names


@pytest.fixture(scope="module")
def fuzz_tree(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """The tree and, per file, the kind of damage (``trunc`` and ``lie`` must fail; ``flip`` may pass)."""
    rng = np.random.default_rng(SEED)
    root = tmp_path_factory.mktemp("fuzz") / "in"
    kinds: dict[str, str] = {}
    scratch = root.parent / "scratch"

    def add(folder: str, stem: str, valid: bytes, suffix: str, trunc, flips, lies, depth: bytes | None = None):
        for kind, variants in (("trunc", trunc), ("flip", flips), ("lie", lies)):
            for name in _write_all(root / folder, f"{stem}_{kind}", valid, variants, suffix):
                kinds[f"{folder}/{name}"] = kind
                if depth is not None:
                    (root / folder / name.replace(suffix, "_depth.exr")).write_bytes(depth)

    write_image(scratch / "a.png", _image(rng, H, W), ImageEncoding())
    png = (scratch / "a.png").read_bytes()
    write_depth_exr(scratch / "d.exr", np.full((H, W), 25.0, np.float32))
    exr = (scratch / "d.exr").read_bytes()
    add("cam", "png", png, ".png", _truncations(png, rng, 4), _bit_flips(png, rng, 6, start=8), _png_lies(png),
        depth=exr)
    for kind, variants in (("trunc", _truncations(exr, rng, 4)), ("flip", _bit_flips(exr, rng, 6)),
                           ("lie", _exr_lies(exr))):
        for i, v in enumerate(variants):
            name = f"exr_{kind}{i:02d}"
            (root / "cam" / f"{name}.png").write_bytes(png)
            (root / "cam" / f"{name}_depth.exr").write_bytes(v)
            kinds[f"cam/{name}.png"] = kind

    write_dng(scratch / "r.dng", rng.integers(64, 4095, (H, W)).astype(np.uint16), "RGGB", 64, 4095)
    dng = (scratch / "r.dng").read_bytes()
    add("raw", "dng", dng, ".dng", _truncations(dng, rng, 4), _bit_flips(dng, rng, 6), _dng_lies(scratch / "r.dng"),
        depth=exr)

    cloud = _cloud(rng, n=600)
    for mode in ("ascii", "binary", "binary_compressed"):
        layout = CloudLayout("pcd", cloud.layout.fields, mode)
        write_pointcloud(scratch / f"c_{mode}.pcd", type(cloud)(cloud.positions_m, cloud.fields, "lidar",
                                                                   cloud.profile, layout))
        pcd = (scratch / f"c_{mode}.pcd").read_bytes()
        header_end = pcd.index(b"DATA")
        add("lidar", f"pcd_{mode}", pcd, ".pcd", _truncations(pcd, rng, 3),
            _bit_flips(pcd, rng, 3, start=header_end if mode != "ascii" else 0), _count_lies(pcd, b"POINTS", 600))
    for mode in ("ascii", "binary_little_endian"):
        layout = CloudLayout("ply", cloud.layout.fields, mode)
        write_pointcloud(scratch / f"c_{mode}.ply", type(cloud)(cloud.positions_m, cloud.fields, "lidar",
                                                                   cloud.profile, layout))
        ply = (scratch / f"c_{mode}.ply").read_bytes()
        add("lidar", f"ply_{mode}", ply, ".ply", _truncations(ply, rng, 3), _bit_flips(ply, rng, 3),
            _count_lies(ply, b"element vertex", 600))
    table = np.hstack([cloud.positions_m, cloud.fields["intensity"][:, None]]).astype("<f4").tobytes()
    add("lidar", "bin", table, ".bin", _truncations(table, rng, 4, avoid_multiple_of=16), _bit_flips(table, rng, 4),
        [table + b"\0" * 7, table[:-3]])
    return root, kinds


RECIPES = {
    "cam": {"chain": [{"model": "fog.camera", "params": {"visibility_m": 40}}], "seed": 1,
            "inputs": {"camera": "cam/*.png", "camera_profile": CAMERA_PROFILE}},
    "raw": {"chain": [{"model": "fog.camera", "params": {"visibility_m": 40}}], "seed": 1,
            "inputs": {"raw": "raw/*.dng", "camera_profile": CAMERA_PROFILE}},
    "lidar": {"chain": [{"model": "fog.lidar"}], "seed": 1,
              "inputs": {"lidar": ["lidar/*.pcd", "lidar/*.ply", "lidar/*.bin"], "lidar_profile": "os1-128",
                         "intensity_unit": "uint8"}},
}


@pytest.mark.parametrize("folder", list(RECIPES))
def test_malformed_inputs_fail_cleanly(tmp_path, fuzz_tree, folder):
    from roadview_noise.runner import Limits

    root, kinds = fuzz_tree
    before = {p: sha256_file(p) for p in sorted(root.rglob("*")) if p.is_file()}
    out = tmp_path / "out"
    summary = run(parse_recipe(RECIPES[folder]), root, out, workers=2, progress=False, echo=lambda m: None,
                  limits=Limits(max_pixels=10**6, max_points=10**6, task_timeout_s=60))
    entries = {e["input"]: e for e in read_manifest(out / "manifest.jsonl")}
    mine = {k: v for k, v in kinds.items() if k.startswith(folder + "/")}
    assert set(entries) == set(mine) and summary.done + summary.failed == len(mine)
    for rel, e in entries.items():
        assert "traceback" not in e and "internal error" not in e.get("error", ""), (rel, e.get("error"))
        assert e["seconds"] < PER_FILE_S, (rel, e["seconds"])
        if e["status"] != "ok":
            assert rel in e["error"] or rel.replace(".png", "_depth.exr") in e["error"], e["error"]
        if mine[rel] in ("trunc", "lie"):
            assert e["status"] == "failed", (rel, mine[rel])
    assert {p: sha256_file(p) for p in sorted(root.rglob("*")) if p.is_file()} == before
    assert not [p for p in out.rglob("*") if "rvnoise-tmp" in p.name]
    listed = {f["path"] for e in entries.values() if e["status"] == "ok" for f in e["files"]}
    assert {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()} == \
        listed | {"manifest.jsonl", "run.json"}
