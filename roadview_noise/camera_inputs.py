"""Camera and raw Bayer inputs as users have them: the pixels, the camera geometry only where a step needs it, and
the depth from what the user has (recipe ``inputs``; README "Which depth do I have?").

Camera geometry (intrinsics, exposure, pixel pitch) is looked for only when a step of the chain declares
``Model.uses_camera_geometry`` or the depth needs intrinsics (planar depth, disparity, LiDAR projection, ground
plane). Then, in order: the intrinsics of the image's calibration file (``inputs.calibration``) over the recipe's
profile or the folder's ``camera.yaml``; else the profile (fitted to the image size); else — no profile — the
intrinsics the input states (a bag camera topic's CameraInfo, :mod:`roadview_noise.bag_camera_info`) unless
``inputs.camera_fov_h_deg`` is given; else a centred pinhole with square pixels from the image size and a
horizontal field of view (``inputs.camera_fov_h_deg``, default the ROADVIEW Lucid Triton's 80.8°) with the Lucid's
optics, which a run-level warning states. A frame whose
chain needs no geometry carries a nominal profile of that kind that no step reads.

Depth (``inputs.depth_source``): ``file`` (``inputs.depth`` sidecars in any format of :mod:`roadview_noise.io.depth`),
``lidar`` (the paired scan, :mod:`roadview_noise.depth.lidar`), ``onnx`` (a monocular model,
:mod:`roadview_noise.depth.monocular`) or ``ground_plane`` (a flat-road prior, :mod:`roadview_noise.depth.ground_plane`,
with vertical objects standing on it, :mod:`roadview_noise.depth.stixels`);
holes follow ``inputs.depth_holes`` (:mod:`roadview_noise.depth.holes`). What was done goes to the frame's
``input_notes`` (the manifest's ``inputs``), and what deserves a warning is summarised once per run
(:class:`InputWarnings`).

Image files and the camera messages of ROS bags go through the same :func:`with_camera_inputs`: only where the
image comes from differs (:class:`FileImage`; ``bag_runner.TopicImage``, whose aligned depth message plays the role
of the depth file).
"""

from __future__ import annotations

import dataclasses
import math
from functools import cached_property
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .dataset import Sample, _camera_profile, _profile_spec, _sidecar_default, depth_relpath_for
from .errors import InputError
from .recipe import Recipe
from .registry import get_model
from .types import CameraFrame, CameraProfile, RawFrame

FALLBACK_FOV_H_DEG = 80.8          # the ROADVIEW Lucid Triton TRI028S + 6 mm lens (profiles/camera.py)
DEPTH_OPTIONS = ("point inputs.depth (or --depth) at your depth files, or set inputs.depth_source (or "
                 "--depth-source): lidar (the paired LiDAR scan), onnx (a monocular depth model) or ground_plane (a "
                 "flat-road prior)")


def needs_camera_geometry(recipe: Recipe) -> bool:
    """True when a step of the chain uses camera intrinsics (``Model.uses_camera_geometry``)."""
    return any(get_model(m).uses_camera_geometry for m in recipe.model_ids)


def load_camera_sample(sample: Sample, in_root: Path, recipe: Recipe,
                       content: bytes | None = None) -> CameraFrame | RawFrame:
    """Read one camera or raw sample with the depth and geometry its chain needs (``content``: a PNG/JPEG/TIFF
    image's bytes, already read); InputError names the file."""
    from .io import image as image_io
    from .io import raw as raw_io

    path = in_root / sample.relpath
    notes: dict[str, Any] = {}
    if sample.modality == "camera":
        untagged = recipe.spec.inputs.untagged_transfer
        linear, encoding, alpha = image_io.read_image(path, content, untagged_transfer=untagged or "srgb")
        frame = CameraFrame(linear, nominal_profile(linear.shape[1], linear.shape[0]), encoding=encoding,
                            alpha=alpha)
        notes.update(_transfer_note(encoding, untagged))
    else:
        stated = recipe.spec.inputs.raw_black_level_dn
        dn, pattern, black, white, raw_encoding = raw_io.read_raw(path, stated)
        frame = RawFrame(dn.astype(np.float32), pattern, float(black), float(white),
                         nominal_profile(dn.shape[1], dn.shape[0]), encoding=raw_encoding)
        if stated is not None:
            notes["black_level"] = {"value_dn": float(black), "from": "recipe inputs.raw_black_level_dn"}
    frame = with_camera_inputs(frame, recipe, FileImage(sample, in_root))
    if not notes:
        return frame
    warnings = list(frame.input_notes.get("warnings", ())) + notes.pop("warnings", [])
    return dataclasses.replace(frame, input_notes={**frame.input_notes, **notes,
                                                   **({"warnings": warnings} if warnings else {})})


#: the transfers of integer codes rvnoise decodes as a file states them (``io.image_metadata.CICP_TRANSFERS``)
_DECODED_TRANSFERS = "linear, sRGB, BT.709/601/2020, gamma 2.2/2.8, BT.2100 PQ and HLG"


def _transfer_note(encoding, untagged: str | None) -> dict:
    """``transfer`` of an integer PNG/TIFF/HEIF when it is not the plain sRGB of a file that says so: a curve of
    :mod:`.physics.transfers` (BT.709, gamma 2.2/2.8, BT.2100 PQ, HLG; with the scale of the linear values) or
    linear as the file states it; a ``cICP``/``nclx`` transfer rvnoise does not decode, read as sRGB (warned:
    ``transfer_read_as_srgb``); for a PNG/TIFF that states none, the
    recipe's ``untagged_transfer``, or sRGB by default for a 16-bit file (then warned: ``untagged_16bit``). 8-bit
    files that state nothing are the web's sRGB and get no note."""
    from .io.image_metadata import CICP_TRANSFER_NAMES, cicp_transfer, stated_transfer, unread_transfer
    from .physics import transfers

    if encoding.fmt not in ("png", "tiff", "heif") or encoding.bit_depth > 16:
        return {}
    code = cicp_transfer(encoding.fmt, encoding.metadata)
    stated_by = f"the file ({'PNG cICP' if encoding.fmt == 'png' else 'HEIF nclx'} transfer {code})"
    if encoding.transfer in transfers.CURVES:
        return {"transfer": {"value": encoding.transfer, "scale": transfers.TRANSFERS[encoding.transfer].scale,
                             "from": stated_by}}
    if unread_transfer(encoding.fmt, encoding.metadata) is not None:
        return {"transfer": {"value": "srgb", "file": f"{CICP_TRANSFER_NAMES.get(code, 'reserved')} ({stated_by})",
                             "from": f"rvnoise decodes {_DECODED_TRANSFERS} only: read as sRGB, written back "
                                     "with the file's tag"},
                "warnings": ["transfer_read_as_srgb"]}
    if encoding.fmt == "heif":
        return {"transfer": {"value": "linear", "from": stated_by}} if encoding.transfer == "linear" else {}
    stated = stated_transfer(encoding.fmt, encoding.metadata, encoding.icc_profile)
    if stated is not None:
        return {"transfer": {"value": "linear", "from": "the file (PNG gAMA 1.0 or cICP)"}} if stated == "linear" else {}
    if untagged is not None:
        return {"transfer": {"value": untagged, "from": "recipe inputs.untagged_transfer (the file states none)"}}
    if encoding.bit_depth == 16:
        return {"transfer": {"value": "srgb", "from": "default (the file states none)"},
                "warnings": ["untagged_16bit"]}
    return {}


def with_camera_inputs(frame: CameraFrame | RawFrame, recipe: Recipe, origin: Any) -> CameraFrame | RawFrame:
    """A frame as read (pixels and encoding) with the JPEG quality, camera geometry and depth its chain needs and
    the notes saying how they were obtained — the one path of image files and bag messages. ``origin`` is where
    the image comes from (:class:`FileImage`, or a bag topic's message in :mod:`roadview_noise.bag_runner`):
    ``name`` (in errors), ``folder`` (relative profile paths), ``sidecars`` (look for ``camera.yaml`` there),
    ``key(setting)`` (where the recipe states a setting) and ``depth(recipe, geometry)`` (the ``file`` depth
    source: ``(range_m with NaN holes, notes, source name)``)."""
    from .orientation import upright_frame

    notes: dict[str, Any] = {}
    h, w = frame.shape                                  # as stored: the calibration, profile and depth files' size
    exif, turn = _orientation(frame, recipe, origin)
    if turn != 1:
        frame = upright_frame(frame, turn)
    if isinstance(frame, CameraFrame) and frame.encoding.fmt == "jpeg":
        stated = recipe.spec.output.jpeg_quality
        if stated is not None:
            frame = dataclasses.replace(frame, encoding=dataclasses.replace(frame.encoding, jpeg_quality=stated))
        notes["jpeg_quality"] = {"value": frame.encoding.jpeg_quality, "from": "recipe output.jpeg_quality"
                                 if stated is not None else "input (estimated from its quantisation tables)"}
    if isinstance(frame, CameraFrame) and frame.encoding.fmt == "webp":
        quality = frame.encoding.webp_quality
        notes["webp_quality"] = {"value": "lossless", "from": "input (a VP8L bitstream)"} if quality is None else \
            {"value": quality, "from": "input (estimated from its VP8 quantiser indices)"}
    codec_warnings: list[str] = []
    if isinstance(frame, CameraFrame) and frame.encoding.fmt in ("heif", "avif"):
        from .io.heif import notes as heif_notes

        heif_written, codec_warnings = heif_notes(frame.encoding)
        notes.update(heif_written)
    geometry = _Geometry(origin, recipe, w, h, turn)
    if needs_camera_geometry(recipe):
        geometry.profile                                    # resolved now: a step of the chain uses it
    depth = valid = None
    if recipe.needs_depth():
        depth, valid, notes["depth"] = _depth(origin, recipe, geometry, lambda: _signal(frame))
    if turn != 1 and "camera" in geometry.notes:
        geometry.profile                                    # a depth source read the stored intrinsics: turn them
    notes.update(geometry.notes)
    warnings = geometry.warnings + _depth_warnings(notes.get("depth")) + _orientation_note(exif, turn, recipe,
                                                                                           notes) + codec_warnings
    if warnings:
        notes["warnings"] = warnings
    return dataclasses.replace(frame, profile=geometry.resolved or frame.profile, depth_m=depth, depth_valid=valid,
                               input_notes=notes)


def nominal_profile(width_px: int, height_px: int) -> CameraProfile:
    """The profile of a frame whose chain needs no camera geometry: no step reads it."""
    return CameraProfile.from_fov("unused: no step needs camera geometry", width_px, height_px, FALLBACK_FOV_H_DEG)


def camera_geometry(origin: Any, recipe: Recipe, width_px: int, height_px: int) -> "_Geometry":
    """The camera geometry of an image of that size from ``origin`` (see :func:`with_camera_inputs`), whatever its
    chain needs: ``.profile`` resolves it (module docstring)."""
    return _Geometry(origin, recipe, width_px, height_px)


def _signal(frame: CameraFrame | RawFrame) -> np.ndarray:
    """The frame's linear signal for the depth sources that look at the image: RGB, or Bayer DN scaled to [0, 1]."""
    if isinstance(frame, CameraFrame):
        return frame.linear_rgb
    return (frame.dn - np.float32(frame.black_level_dn)) / np.float32(frame.white_level_dn - frame.black_level_dn)


class FileImage:
    """An image file of the input tree as the origin of a frame (see :func:`with_camera_inputs`): a photo stored
    turned is processed upright (the runner turns the result back, :mod:`roadview_noise.orientation`)."""

    sidecars = upright = True

    def __init__(self, sample: Sample, in_root: Path):
        self.sample, self.in_root = sample, in_root
        self.path = in_root / sample.relpath
        self.name, self.folder = str(self.path), self.path.parent

    @staticmethod
    def key(setting: str) -> str:
        return f"inputs.{setting}"

    @staticmethod
    def stated_intrinsics(width_px: int, height_px: int) -> None:
        """Intrinsics the input itself states (a bag's CameraInfo): none for a file."""
        return None

    def sidecar(self, pattern: str, key: str, recipe_dir: Path) -> Path:
        """A sidecar pattern resolved next to the image (``..`` allowed), else in the recipe's folder."""
        rel = depth_relpath_for(self.sample.relpath, pattern)
        for candidate in (self.in_root / rel, recipe_dir / pattern):
            if candidate.is_file():
                return candidate
        raise InputError(f"no {key} file {rel!r} (inputs.{key}: {pattern!r}, relative to the image's folder or "
                         f"the recipe's)", file=self.name)

    def depth(self, recipe: Recipe, geometry: "_Geometry"):
        """The ``file`` depth source: the image's depth sidecar (``inputs.depth``)."""
        from .io import depth as depth_io

        inputs = recipe.spec.inputs
        if self.sample.depth_relpath is None:
            needing = ", ".join(m for m in recipe.model_ids if get_model(m).needs_depth)
            raise InputError(f"no depth file {depth_relpath_for(self.sample.relpath, inputs.depth)!r} (inputs.depth: "
                             f"{inputs.depth!r}; needed by {needing}); {DEPTH_OPTIONS}", file=self.name)
        depth_path = self.in_root / self.sample.depth_relpath
        fmt = depth_io.depth_format(depth_path, inputs.depth_format)
        planar = inputs.depth_kind == "planar" or fmt in depth_io.PLANAR_FORMATS
        cal = geometry.calibration
        w, h = geometry.size
        depth = depth_io.read_depth(depth_path, fmt=fmt, profile=geometry.stored_profile if planar else None,
                                    expected_shape=(h, w), planar=planar,
                                    baseline_m=cal.baseline_m if cal is not None else None)
        notes = {"source": "file", "file": self.sample.depth_relpath, "format": fmt,
                 "kind": "planar" if planar else "range"}
        return depth, notes, str(depth_path)


# --- camera geometry -----------------------------------------------------------------------------------------------


class _Geometry:
    """The camera geometry of one image, resolved on first use (module docstring): ``size`` and
    :attr:`stored_profile` are the stored pixels', :attr:`profile` the image's as the chain sees it (turned upright
    from the stored pixels by the EXIF orientation ``turn``, :mod:`roadview_noise.orientation`)."""

    def __init__(self, origin: Any, recipe: Recipe, width_px: int, height_px: int, turn: int = 1):
        self.origin, self.recipe, self.turn = origin, recipe, turn
        self.size = (width_px, height_px)
        self.resolved: CameraProfile | None = None
        self.notes: dict[str, Any] = {}
        self.warnings: list[str] = []

    @cached_property
    def calibration(self):
        """The image's calibration file (``inputs.calibration``) or None."""
        from .depth.calibration import load_calibration

        inputs = self.recipe.spec.inputs
        if inputs.calibration is None:
            return None
        if isinstance(inputs.calibration, str):
            cal = load_calibration(self.origin.sidecar(inputs.calibration, "calibration", self.recipe.base_dir),
                                   kitti_camera=inputs.kitti_camera)
        else:
            cal = self._nuscenes(inputs.calibration.nuscenes)
        self.notes["calibration"] = _relative(Path(cal.source), self.origin.in_root)
        return cal

    def _nuscenes(self, tables: str):
        """``calibration: {nuscenes: VERSION}``: the image's (and paired scan's) calibrated_sensor records."""
        from .depth.nuscenes import nuscenes_calibration

        sample = getattr(self.origin, "sample", None)
        if sample is None:
            raise InputError("calibration {nuscenes: …} needs image files under the dataroot", file=self.origin.name)
        inputs = self.recipe.spec.inputs
        root = Path(self.origin.in_root).resolve()
        folder = (root / tables).resolve()
        if not folder.is_relative_to(root):
            raise InputError(f"calibration {{nuscenes: {tables!r}}} is outside the input folder", file=self.origin.name)
        lidar = inputs.depth_source == "lidar" and inputs.lidar_depth is not None
        scan = depth_relpath_for(sample.relpath, inputs.lidar_depth.scan) \
            if lidar and inputs.lidar_depth.scan is not None else None
        return nuscenes_calibration(folder, sample.relpath, lidar=lidar, scan_rel=scan)

    @cached_property
    def profile(self) -> CameraProfile:
        from .orientation import upright_profile

        profile = upright_profile(self.stored_profile, self.turn)
        if self.turn != 1:
            self.notes["camera"].update(_intrinsics_notes(profile))
        self.resolved = profile
        return profile

    @cached_property
    def stored_profile(self) -> CameraProfile:
        inputs = self.recipe.spec.inputs
        w, h = self.size
        folder = self.origin.folder
        spec = _profile_spec(inputs.camera_profile, folder, self.recipe)
        if self.origin.sidecars:
            spec = _sidecar_default(spec, folder, "camera.yaml")
        cal = self.calibration
        intrinsics = cal.intrinsics_for(w, h) if cal is not None else None
        stated = None
        if spec is not None:
            base = _camera_profile(spec, folder)
            source = (f"recipe {self.origin.key('camera_profile')}" if inputs.camera_profile is not None
                      else "camera.yaml")
            if intrinsics is None:
                from .profiles.camera import fit_to_image

                profile = fit_to_image(base, w, h, source=self.origin.name)
            else:
                profile = dataclasses.replace(base.resized(w, h), **_intrinsics_fields(intrinsics))
        else:
            fov = inputs.camera_fov_h_deg or FALLBACK_FOV_H_DEG
            fov_key = self.origin.key("camera_fov_h_deg")
            if inputs.camera_fov_h_deg is None and intrinsics is None:
                stated = self.origin.stated_intrinsics(w, h)
            if stated is not None and stated.intrinsics is not None:
                profile, source = intrinsics_profile(stated.name, w, h, stated.intrinsics), stated.source
                self.warnings.extend(stated.warnings)
            else:
                profile = assumed_profile(w, h, fov)
                source = (f"image size and horizontal FOV {fov:g}° "
                          f"({fov_key if inputs.camera_fov_h_deg else 'default: the Lucid Triton'})")
                if intrinsics is None:
                    self.warnings.append("intrinsics_from_fov")
                else:
                    profile = dataclasses.replace(profile, name="calibration", **_intrinsics_fields(intrinsics))
        if intrinsics is not None:
            source = f"calibration intrinsics over {source}"
        self.notes["camera"] = {"profile": profile.name, "from": source, **_intrinsics_notes(profile)}
        if stated is not None:
            self.notes["camera"].update(stated.notes)
        return profile


def _intrinsics_notes(profile: CameraProfile) -> dict[str, float]:
    return {"fx_px": round(profile.fx_px, 4), "fy_px": round(profile.fy_px, 4), "cx_px": round(profile.cx_px, 4),
            "cy_px": round(profile.cy_px, 4), "fov_h_deg": round(profile.fov_h_deg, 4)}


def assumed_profile(width_px: int, height_px: int, fov_h_deg: float) -> CameraProfile:
    """Centred pinhole, square pixels, horizontal FOV ``fov_h_deg``, with the Lucid Triton's optics
    (:func:`intrinsics_profile`)."""
    pin = CameraProfile.from_fov(f"assumed_fov{fov_h_deg:g}", width_px, height_px, fov_h_deg)
    return intrinsics_profile(pin.name, width_px, height_px, (pin.fx_px, pin.fy_px, pin.cx_px, pin.cy_px))


def intrinsics_profile(name: str, width_px: int, height_px: int, intrinsics) -> CameraProfile:
    """A profile of the intrinsics ``(fx, fy, cx, cy)`` (px) with the Lucid Triton's exposure, f-number and focal
    length; the pixel pitch follows from them (``f / f_x``) so that defocus agrees with the intrinsics."""
    from .profiles.camera import lucid_triton_028s

    lucid = lucid_triton_028s()
    fields = _intrinsics_fields(intrinsics)
    return dataclasses.replace(lucid, name=name, width_px=width_px, height_px=height_px, **fields,
                               pixel_pitch_m=lucid.focal_length_m / fields["fx_px"])


def _intrinsics_fields(intrinsics) -> dict[str, float]:
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return {"fx_px": fx, "fy_px": fy, "cx_px": cx, "cy_px": cy}


def _relative(path: Path, root: Path) -> str:
    try:
        return path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return str(path)


# --- depth -----------------------------------------------------------------------------------------------------------


def _depth(origin: Any, recipe: Recipe, geometry: _Geometry, signal: Callable[[], np.ndarray]
           ) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """``(range_m, valid, notes)`` from the recipe's depth source (module docstring); ``signal()`` gives the
    frame's linear signal for the sources that look at the image."""
    from .depth.doubts import depth_doubt
    from .depth.holes import resolve_holes

    inputs = recipe.spec.inputs
    source = inputs.depth_source
    if source == "file":
        from .orientation import upright

        depth, notes, where = origin.depth(recipe, geometry)
        depth = upright(depth, geometry.turn)           # the sidecar is aligned with the stored pixels
    elif source == "lidar":
        return _depth_lidar(origin, recipe, geometry, signal)
    elif source == "onnx":
        depth, notes, where = _depth_onnx(recipe, geometry, signal)
    else:
        return _depth_ground_plane(recipe, geometry, signal)
    doubt = depth_doubt(depth)
    if doubt is not None:
        notes["doubt"] = doubt
    depth, valid, holes = resolve_holes(depth, inputs.depth_holes, source=where)
    notes.update(holes)
    return depth, valid, notes


def _depth_lidar(origin: FileImage, recipe: Recipe, geometry: _Geometry, signal):
    from .depth.lidar import lidar_depth
    from .io import pointcloud as cloud_io
    from .io.image import display_srgb
    from .orientation import stored, upright

    spec = recipe.spec.inputs.lidar_depth
    cal = geometry.calibration
    if spec.scan is None:
        if cal is None or cal.paired_scan is None:
            raise InputError("inputs.lidar_depth.scan is needed (only nuScenes tables pair the scan themselves)",
                             file=origin.name)
        scan_rel = cal.paired_scan
    else:
        scan_rel = depth_relpath_for(origin.sample.relpath, spec.scan)
    scan_path = origin.in_root / scan_rel
    if not scan_path.is_file():
        raise InputError(f"no paired LiDAR scan {scan_rel!r} (inputs.lidar_depth.scan: {spec.scan!r})",
                         file=origin.name)
    if cal is None or cal.lidar_to_camera is None:
        raise InputError("depth_source lidar needs the LiDAR → camera transform: inputs.calibration (a KITTI "
                         "calib .txt, a .yaml with lidar_to_camera, or {nuscenes: VERSION})", file=origin.name)
    profile = geometry.stored_profile                   # the calibration's camera: the stored pixels
    cloud = cloud_io.read_pointcloud(scan_path, sensor="lidar")
    ground = None
    if spec.ground_plane:
        height = cal.height_above_ground_m or profile.height_above_ground_m
        ground = (height, cal.pitch_rad or 0.0)
    guide = display_srgb(stored(signal(), geometry.turn)) if spec.densify == "bilateral" else None
    try:
        depth, valid, notes = lidar_depth(cloud.positions_m, cal.lidar_to_camera,
                                          (profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px),
                                          profile.width_px, profile.height_px, densify=spec.densify,
                                          guide_srgb=guide, ground=ground)
    except ValueError as exc:
        raise InputError(f"{exc} (scan {scan_rel})", file=origin.name) from None
    depth, valid = upright(depth, geometry.turn), None if valid is None else upright(valid, geometry.turn)
    notes = {"source": "lidar", "scan": scan_rel, **notes}
    if ground is not None:
        notes["ground_plane"] = {"camera_height_m": ground[0], "pitch_deg": round(math.degrees(ground[1]), 6)}
    return depth, valid, notes


def _depth_onnx(recipe: Recipe, geometry: _Geometry, signal):
    from .depth.monocular import model_depth
    from .io.image import display_srgb
    from .units import planar_depth_to_range

    spec = recipe.spec.inputs.onnx_depth
    model = Path(spec.model)
    model = model if model.is_absolute() else recipe.base_dir / model
    if not model.is_file():
        raise InputError(f"no ONNX depth model {str(model)!r} ({geometry.origin.key('onnx_depth')}.model, relative "
                         f"to the recipe's folder): export a metric monocular depth network to ONNX (its first "
                         f"output × scale_m must be metres) or use depth_source ground_plane",
                         file=geometry.origin.name)
    image = signal()
    if image.ndim != 3:
        raise InputError("depth_source onnx needs an RGB image; give raw Bayer frames a depth file or another "
                         "depth source", file=geometry.origin.name)
    image = display_srgb(image) if spec.input == "srgb" else image
    depth, notes = model_depth(str(model), image, mean=spec.mean, std=spec.std, layout=spec.layout,
                               scale_m=spec.scale_m)
    if spec.kind == "planar":
        p = geometry.profile
        depth = planar_depth_to_range(depth, p.fx_px, p.fy_px, p.cx_px, p.cy_px)
    return depth, {"source": "onnx", **notes, "kind": spec.kind, "input": spec.input}, str(model)


def _depth_ground_plane(recipe: Recipe, geometry: _Geometry, signal):
    from .depth.ground_plane import ground_plane_range
    from .depth.stixels import object_range
    from .physics.srgb import linear_to_code

    spec = recipe.spec.inputs.ground_plane
    profile, cal = geometry.profile, geometry.calibration
    cal_height = cal.height_above_ground_m if cal is not None else None
    height = spec.camera_height_m or cal_height or profile.height_above_ground_m
    if spec.pitch_deg is not None:
        pitch = math.radians(spec.pitch_deg)
    else:
        pitch = cal.pitch_rad if cal is not None and cal.pitch_rad is not None else 0.0
    intrinsics = (profile.fx_px, profile.fy_px, profile.cx_px, profile.cy_px)
    notes = {"source": "ground_plane", "camera_height_m": height, "pitch_deg": math.degrees(pitch),
             "sky_distance_m": spec.sky_distance_m}
    image = signal() if spec.objects else None
    if image is not None and image.ndim == 3:
        depth, found = object_range(linear_to_code(image, 8), intrinsics, camera_height_m=height, pitch_rad=pitch,
                                    sky_distance_m=spec.sky_distance_m)       # the decoded frame's own codes
        notes.update(found)
    else:
        depth = ground_plane_range(intrinsics, profile.width_px, profile.height_px, camera_height_m=height,
                                   pitch_rad=pitch, sky_distance_m=spec.sky_distance_m)
        notes["objects"] = False if image is None else "not on a raw mosaic: flat ground only"
    if not (spec.camera_height_m or cal_height):
        notes["camera_height_from"] = f"camera profile {profile.name}"
    return depth, None, notes


def _orientation(frame: CameraFrame | RawFrame, recipe: Recipe, origin: Any) -> tuple[int, int]:
    """``(EXIF/TIFF orientation of the file, the one its pixels are turned upright from)``: a photo file and a DNG
    (its IFD0 Orientation; the CFA pattern turns with the mosaic) are processed upright unless ``inputs.orientation:
    stored``; bag messages state no orientation and are processed as stored."""
    from .io.image_metadata import orientation

    exif = orientation(frame.encoding) if isinstance(frame, CameraFrame) else frame.encoding.orientation
    upright = exif != 1 and getattr(origin, "upright", False) and recipe.spec.inputs.orientation == "upright"
    return exif, exif if upright else 1


def _orientation_note(exif: int, turn: int, recipe: Recipe, notes: dict) -> list[str]:
    """``notes["orientation"]`` for a photo whose EXIF/TIFF orientation turns or mirrors it for display, and
    ``turned_photo`` when it was processed as stored while the chain has a direction: steps that use camera geometry
    (rain and snow fall down the stored columns), the ground-plane prior (road at the stored bottom) or a depth
    network (trained on upright photos)."""
    if exif == 1:
        return []
    if turn != 1:
        notes["orientation"] = {"exif": exif, "processed": "upright"}
        return []
    notes["orientation"] = {"exif": exif, "processed": "as stored"}
    directed = needs_camera_geometry(recipe) or recipe.spec.inputs.depth_source in ("ground_plane", "onnx")
    return ["turned_photo"] if directed else []


def _depth_warnings(notes: dict | None) -> list[str]:
    if not notes:
        return []
    out = []
    if notes.get("filled"):
        out.append("depth_holes_filled")
    if "doubt" in notes:
        out.append("depth_doubtful")
    if notes.get("source") == "ground_plane":
        out.append("depth_ground_plane")
        if "camera_height_from" in notes:
            out.append("ground_plane_profile_height")
    return out


# --- one warning per run -------------------------------------------------------------------------------------------


class InputWarnings:
    """One line per kind of input warning over a run's manifest entries (their ``inputs.warnings``), folded one entry
    at a time (a count and an extreme per kind, nothing per file)."""

    def __init__(self):
        self.files: dict[str, int] = {}
        self.worst_hole_fraction = 0.0
        self.fovs: set[float] = set()
        self.heights: set[float] = set()
        self.doubts: dict[str, str] = {}                  # reason → the first file's text

    def add(self, entry: dict) -> None:
        if any("absent" in r for r in entry.get("annotations_read", ())):
            self.files["yolo_file_absent"] = self.files.get("yolo_file_absent", 0) + 1
        inputs = entry.get("inputs") or {}
        for kind in inputs.get("warnings", ()):
            self.files[kind] = self.files.get(kind, 0) + 1
            if kind == "depth_holes_filled":
                self.worst_hole_fraction = max(self.worst_hole_fraction, inputs["depth"]["hole_fraction"])
            elif kind == "intrinsics_from_fov":
                self.fovs.add(inputs["camera"]["fov_h_deg"])
            elif kind == "ground_plane_profile_height":
                self.heights.add(inputs["depth"]["camera_height_m"])
            elif kind == "depth_doubtful":
                doubt = inputs["depth"]["doubt"]
                self.doubts.setdefault(doubt["reason"], f"{entry['input']}: {doubt['text']}")

    def lines(self) -> list[str]:
        """The run's warning lines, in :data:`_RUN_LINES`' order: a count of files, and for some kinds what the
        files had (the worst hole fraction, the FOVs, the doubts, the camera heights)."""
        n = self.files
        detailed = {
            "depth_holes_filled": lambda: f"depth holes filled from their neighbours in {n['depth_holes_filled']} "
                                          f"file(s), up to {100 * self.worst_hole_fraction:.1f} % of a frame "
                                          "(inputs.depth_holes: fill; counts in the manifest, inputs.depth)",
            "depth_doubtful": lambda: f"depth of {n['depth_doubtful']} file(s) does not look like metres along the "
                                      f"ray ({'; '.join(self.doubts.values())}): fog, rain and snow would be far too "
                                      "strong or weak; depth files are metres (EXR/NPY: range, or depth_kind: "
                                      "planar), not millimetres, inverse depth or disparity (inputs.depth.doubt in "
                                      "the manifest)",
            "intrinsics_from_fov": lambda: f"no camera profile for {n['intrinsics_from_fov']} file(s): intrinsics "
                                           "from the image size and a horizontal FOV of "
                                           f"{', '.join(f'{f:g}' for f in sorted(self.fovs))}° (square pixels, "
                                           "centred); state them with inputs.camera_profile, --camera-profile or "
                                           "inputs.camera_fov_h_deg (values in the manifest, inputs.camera)",
            "ground_plane_profile_height": lambda: f"ground plane of {n['ground_plane_profile_height']} file(s) seen "
                                                   "from the camera profile's height "
                                                   f"{', '.join(f'{h:g}' for h in sorted(self.heights))} m, not your "
                                                   "camera's (1.51 m on nuScenes, 1.65 m on KITTI): state "
                                                   "inputs.ground_plane.camera_height_m or a calibration with the "
                                                   "height"}
        return [detailed[kind]() if text is None else text.format(n=n[kind]) for kind, text in _RUN_LINES.items()
                if kind in n]


#: warning kind → its run line ({n}: the number of files; None: :meth:`InputWarnings.lines` says what they had)
_RUN_LINES = {
    "depth_holes_filled": None,
    "depth_doubtful": None,
    "yolo_file_absent": "{n} image(s) have no YOLO label file: augmented as images without objects (YOLO's background "
                        "images) and written without one; if they should have labels, check "
                        "inputs.annotations.boxes_2d (annotations_read in the manifest)",
    "turned_photo": "{n} photo(s) stored turned or mirrored (EXIF orientation 2–8) were processed as stored (recipe "
                    "inputs.orientation: stored, or an image in a bag; inputs.orientation in the manifest): rain and "
                    "snow fall and the ground-plane road lies along the stored image, not the displayed one",
    "avif_8bit": "{n} AVIF file(s) of 10 or 12 bits per sample read and written at 8 bits: Pillow's AVIF plugin "
                 "decodes and encodes 8 bits (inputs.heif_bit_depth in the manifest); convert them to 16-bit PNG or "
                 "TIFF, or to HEIF, to keep their depth",
    "transfer_read_as_srgb": "{n} PNG/HEIF file(s) state a transfer function (cICP/nclx) rvnoise does not decode (it "
                             f"decodes {_DECODED_TRANSFERS}) and were read as sRGB: the models saw radiance decoded "
                             "with another curve (inputs.transfer in the manifest); the output keeps the file's tag",
    "untagged_16bit": "{n} 16-bit image(s) state no transfer function (no gAMA, sRGB, iCCP or cICP chunk, no ICC "
                      "profile): read as sRGB; machine-vision and raw-converted 16-bit images usually hold linear "
                      "counts — then state inputs.untagged_transfer: linear (inputs.transfer in the manifest)",
    "intrinsics_from_fov": None,
    "depth_ground_plane": "depth of {n} file(s) from the ground-plane prior: a flat road (with objects standing on it "
                          "unless inputs.ground_plane.objects is false) and one distance for the sky, a crude guess "
                          "(parameters in the manifest, inputs.depth)",
    "ground_plane_profile_height": None,
}
