"""Data types passed between I/O and models: frames, point clouds, sensor profiles, coupling conditions.

Physics never sees file formats: readers build these objects, models transform them, writers encode them.
All arrays are owned by the object; models return new objects (``dataclasses.replace``) and never mutate input.

Conventions
- Vehicle/sensor frame for 3-D vectors (point positions, wind, ego velocity): x forward, y left, z up (ISO 8855).
- Camera images are linear radiance in RGB order, float32, 1.0 = full scale of the input encoding;
  sRGB ↔ linear and BGR ↔ RGB happen once, in ``roadview_noise.io`` (``physics.srgb``). A frame may instead hold
  the 8-bit sRGB codes its linear values are the decoding of (``CameraFrame.srgb8_codes``; after JPEG the linear
  values are decoded only when read).
- Raw Bayer frames keep digital numbers (as float32, exact for 16-bit) with the CFA pattern and levels as stated by
  the file; rounding/clipping happens once, at writing.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Union

import numpy as np

# ---------------------------------------------------------------------------------------------------------------
# Coupling between models (D3.5 Eq. 1 and Eq. 2)


@dataclass(frozen=True)
class Conditions:
    """Scene conditions that earlier stages hand to the weather model (models.md §1).

    - ``wind_velocity_m_per_s``: steady wind in the sensor frame (x forward, y left, z up); set by ``wind.*``.
    - ``ego_velocity_m_per_s``: sensor velocity in the sensor frame.
    - ``luminance_factor``: scene illumination relative to the input (low light sets it < 1); weather models
      scale airlight and particle radiance estimated from the image by nothing else: they estimate them from the
      (already darkened) frame, and may use this factor for parameters given in absolute terms.
    """

    wind_velocity_m_per_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ego_velocity_m_per_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    luminance_factor: float = 1.0


# ---------------------------------------------------------------------------------------------------------------
# Sensor profiles


@dataclass(frozen=True)
class CameraProfile:
    """Pinhole camera: one intrinsic matrix K is the single source of truth (models.md §2.0 [PROP]).

    Pixel centres are at integer coordinates (OpenCV): pixel (u, v) looks along ``K⁻¹ (u, v, 1)``, so a centred
    principal point is ``((W − 1)/2, (H − 1)/2)``.

    ``pixel_pitch_m`` and ``focal_length_m`` are used only for defocus (circle of confusion)."""

    name: str
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    exposure_time_s: float = 0.005
    pixel_pitch_m: float = 4.5e-6
    focal_length_m: float = 6.0e-3
    f_number: float = 2.1
    height_above_ground_m: float = 1.0
    focus_distance_m: float = math.inf

    @property
    def fov_h_deg(self) -> float:
        return math.degrees(2 * math.atan(self.width_px / (2 * self.fx_px)))

    @property
    def fov_v_deg(self) -> float:
        return math.degrees(2 * math.atan(self.height_px / (2 * self.fy_px)))

    @classmethod
    def from_fov(cls, name: str, width_px: int, height_px: int, fov_h_deg: float, fov_v_deg: float | None = None,
                 **kw: Any) -> "CameraProfile":
        """Centred pinhole from field of view; square pixels unless ``fov_v_deg`` is given (CARLA style)."""
        fx = width_px / (2 * math.tan(math.radians(fov_h_deg) / 2))
        fy = fx if fov_v_deg is None else height_px / (2 * math.tan(math.radians(fov_v_deg) / 2))
        return cls(name, width_px, height_px, fx, fy, (width_px - 1) / 2, (height_px - 1) / 2, **kw)

    def resized(self, width_px: int, height_px: int) -> "CameraProfile":
        """The same optics sampled on a different pixel grid (pitch scales with the grid; pixel centres stay at
        integer coordinates, so the principal point maps as ``(c + ½)·s − ½``)."""
        sx, sy = width_px / self.width_px, height_px / self.height_px
        return dataclasses.replace(self, width_px=width_px, height_px=height_px, fx_px=self.fx_px * sx,
                                   fy_px=self.fy_px * sy, cx_px=(self.cx_px + 0.5) * sx - 0.5,
                                   cy_px=(self.cy_px + 0.5) * sy - 0.5, pixel_pitch_m=self.pixel_pitch_m / sx)


class IntensityUnit:
    """Names of LiDAR intensity units (models.md §0.3). Every threshold is expressed in the input's unit."""

    PHOTONS = "photons"  # Ouster signal, photon-count like, up to 2**16
    UINT8 = "uint8"      # Velodyne 8-bit intensity/reflectivity
    UNIT = "unit"        # CARLA / KITTI float intensity in [0, 1]
    ALL = (PHOTONS, UINT8, UNIT)


@dataclass(frozen=True)
class LidarProfile:
    """A spinning LiDAR (models.md §3.0). Beam tables are indexed by ring (the input's ring/channel number)."""

    name: str
    beam_elevation_deg: tuple[float, ...]
    beam_azimuth_offset_deg: tuple[float, ...]
    columns: int = 2048
    wavelength_m: float = 865e-9
    beam_radius_m: float = 4.75e-3
    beam_divergence_rad: float = 0.0           # full angle: beam radius w(r) = w0 + r·θ/2
    pulse_half_power_width_s: float = 10e-9
    max_range_m: float = 120.0
    intensity_unit: str = IntensityUnit.PHOTONS
    intensity_full_scale: float = 65535.0
    intensity_kind: str = "signal"             # "signal": I = received signal S; "reflectivity": I = W·S·R²/K
    sensor_constant: float | None = None       # K: S of a ρ = 1 Lambertian target filling the beam at 1 m (signal
    #                                            units·m²); None: the intensity full scale
    reflectivity_white_reading: float | None = None  # W: reading of a ρ = 1 diffuse target (Ouster 100, VLS 110);
    #                                            None: the full scale
    detection_threshold: float = 2.42          # in SIGNAL units (the unit of K/m²), not the stored intensity
    overlap_start_m: float = 0.9               # receiver overlap ξ(r): 0 up to here (Hahner et al. 2021) ...
    overlap_full_m: float = 1.0                # ... rising linearly to 1 here
    min_range_m: float = 0.0                   # points closer are no-return placeholders, not returns (nuScenes)
    beam_origin_offset_m: float = 0.0          # Ouster lidar_origin_to_beam_origin (horizontal)
    sensor_z_offset_m: float = 0.0             # Ouster lidar_to_sensor_transform z (points are in the sensor frame)
    window: str = "static"                     # "static" (Ouster) or "rotating" (Velodyne head), §3.8
    # how the stored intensity is written (physics/lidar_intensity.py)
    intensity_step: float | None = None        # resolution of the stored value; None: 1 for count units, 0 (continuous)
    #                                            for [0, 1] floats
    faint_reading: str = "zero"                # a return whose value rounds below one step: "zero", "lowest" (one
    #                                            step) or "no_return" (the sensor drops it)
    intensity_source: str = "the profile"      # what states the unit and kind; "" = nothing (default profile): the
    #                                            data decides, with a warning
    # receiver noise and detection (physics/receiver.py)
    receiver: str = "apd"                      # "spad" (photon counting) or "apd" (linear, Gaussian)
    photons_at_threshold: float = 100.0        # detected photo-electrons of a return at the detection threshold
    threshold_over_noise: float = 4.0          # detection threshold / noise floor (ambient + receiver noise) at S = 0
    excess_noise_factor: float = 3.0           # multiplication noise of the signal's shot noise (SPAD, PIN: 1)
    threshold_calibration: str = "data"        # "data": lowered below the weakest recorded return; "datasheet": kept,
    #                                            the readings' low end is not radiometric (physics/receiver.py)
    storage_order: str = ""                    # "laser": a ring-less list stored laser by laser (KITTI), rings and
    #                                            firing columns from that order (physics/laser_order.py)
    beam_z_offset_m: tuple[float, ...] = ()    # per beam: height of its origin above the scan's (KITTI's HDL-64E:
    #                                            fitted 0.2 m / 0.1 m), for placing a crop's laser runs; () = 0
    sensor_origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)   # the sensor in the frame a file's points are
    #                                            in (Argoverse 2: the vehicle frame); the chain works about it
    firing_cycle_s: float = 0.0                # time of one firing of every beam (VLP-32C: 55.296 µs): > 0, a list
    #                                            with each return's firing time has its grid from it (firing_time.py)
    sensors: tuple[SensorMount, ...] = ()      # a sweep merging several sensors (Argoverse 2): each one's rings, pose
    #                                            and own profile (sensor_rig.py); () = one sensor, or poses unknown

    @property
    def channels(self) -> int:
        return len(self.beam_elevation_deg)


@dataclass(frozen=True)
class SensorMount:
    """One sensor of a sweep that merges several (Argoverse 2's two VLP-32C): its rings ``first_ring`` … ``first_ring
    + profile.channels − 1`` of the sweep's ring field, its pose in the sweep's frame (``rotation``: 3×3 row-major,
    sensor → sweep frame; ``translation_m``: its origin there; a point ``p = R q + t``) and its own ``profile``
    (its beams in its frame); ``source``: where the pose comes from (the calibration file)."""

    name: str
    first_ring: int
    rotation: tuple[tuple[float, float, float], ...]
    translation_m: tuple[float, float, float]
    profile: LidarProfile
    source: str = ""


@dataclass(frozen=True)
class RadarProfile:
    """A 4D imaging radar (models.md §4)."""

    name: str
    frequency_hz: float = 77e9
    fov_azimuth_deg: float = 120.0
    fov_elevation_deg: float = 30.0
    azimuth_resolution_deg: float = 1.0
    elevation_resolution_deg: float = 2.0
    range_resolution_m: float = 0.2
    velocity_resolution_m_per_s: float = 0.1035    # Doppler bin width (RISE analysis: 512 bins over ±26.5 m/s)
    max_range_m: float = 200.0
    if_bandwidth_hz: float = 20e6
    noise_figure_db: float = 12.0
    snr_threshold_db: float | None = None     # None: estimated from the clear data
    rcs_compensates_weather: bool = False
    power_unit: str = "relative"              # "dBm" when the power field is absolute received power
    elevation_measured: bool | None = None    # False: 2-D radar (z = 0); None: from the data (physics/radar_frame.py)


SensorProfile = Union[CameraProfile, LidarProfile, RadarProfile]

# ---------------------------------------------------------------------------------------------------------------
# Camera data


@dataclass(frozen=True)
class ImageEncoding:
    """How a camera frame is stored, so the writer can put it back the same way."""

    fmt: str = "png"           # png | jpeg | tiff | exr | webp | heif | avif
    bit_depth: int = 8         # 8 | 16 | 32 (float32 linear TIFF); EXR: 16 (half) | 32 (float)
    transfer: str = "srgb"     # srgb | linear | bt709 | gamma22 | gamma28 | pq | hlg (physics/transfers.py)
    channels: int = 3          # 1 (grey) | 3 (colour) | 4 (colour + alpha, kept in CameraFrame.alpha)
    jpeg_quality: int = 95
    icc_profile: bytes | None = None   # embedded ICC colour profile of the file, written back unchanged
    exif: bytes | None = None          # EXIF (TIFF-structured, orientation included) of the file, written back unchanged
    jpeg_sampling: int | None = None   # JPEG chroma subsampling as OpenCV's IMWRITE_JPEG_SAMPLING_FACTOR code
    jpeg_progressive: bool = False     # JPEG: progressive (SOF2) rather than baseline
    # the file's PNG ancillary chunks, TIFF tags or JPEG JFIF density (io/image_metadata); HEIF/AVIF: its settings
    # as (name, value) pairs: bit depth, chroma, nclx, XMP (io/heif)
    metadata: tuple = ()
    tiff_associated_alpha: bool = False   # TIFF: its alpha is associated (colours premultiplied), written so
    webp_quality: int | None = None       # WebP: the lossy quality (1–100) written, None: lossless


@dataclass(frozen=True, eq=False)
class CameraFrame:
    """Linear RGB radiance (H, W, 3) float32, 1.0 = encoding full scale; depth is range along the pixel ray (m),
    ``inf`` for sky.

    ``depth_valid`` (H, W) bool marks the depth pixels that were measured or given (None: all of them); filled
    holes and extrapolated regions are False, and scene radiances (airlight, sky) are never estimated from them.
    ``input_notes`` says how the inputs were obtained (depth source and holes, intrinsics assumed, JPEG quality);
    the runner records it in the manifest as ``inputs``."""

    linear_rgb: np.ndarray
    profile: CameraProfile
    depth_m: np.ndarray | None = None
    encoding: ImageEncoding = field(default_factory=ImageEncoding)
    conditions: Conditions = field(default_factory=Conditions)
    alpha: np.ndarray | None = None          # (H, W) alpha plane of the file (CARLA BGRA PNG), passed through as is
    depth_valid: np.ndarray | None = None
    input_notes: Mapping[str, Any] = field(default_factory=dict)
    warps: tuple = ()                        # physics.warp.Warp of each geometric step so far (masks, boxes follow)
    orientation: int = 1                     # EXIF orientation the pixels were turned upright from (orientation.py)

    @property
    def shape(self) -> tuple[int, int]:
        return self.__dict__.get("_srgb8", self.__dict__.get("linear_rgb")).shape[:2]

    # --- 8-bit sRGB codes that stand for the linear values (JPEG output, an unchanged decoded 8-bit file) --------
    def srgb8_codes(self) -> np.ndarray | None:
        """The 8-bit sRGB codes (H, W, 3) uint8 RGB, read-only, possibly a channel-reversed view) whose exact
        decoding is this frame's ``linear_rgb``, or None. Consumers that want codes (the writer, JPEG, metrics)
        use them instead of re-encoding, and a frame made by :meth:`with_srgb8_codes` is never decoded then."""
        from .physics import srgb
        kept = self.__dict__.get("_srgb8")
        return kept if kept is not None else srgb.attached_codes(self.linear_rgb, 8)

    def undecoded_srgb8_codes(self) -> np.ndarray | None:
        """The codes of a frame made by :meth:`with_srgb8_codes` while its ``linear_rgb`` has not been decoded yet
        (a reader that can work on the codes then spares the decode), else None."""
        return None if "linear_rgb" in self.__dict__ else self.__dict__.get("_srgb8")

    def with_srgb8_codes(self, codes: np.ndarray) -> "CameraFrame":
        """This frame with 8-bit sRGB ``codes`` (H, W, 3) RGB as its image: ``linear_rgb`` is their decoding
        (``physics.srgb.code_to_linear``), computed when first read."""
        if codes.dtype != np.uint8 or codes.shape != self.shape + (3,):
            raise ValueError(f"expected {self.shape + (3,)} uint8 codes, got {codes.shape} {codes.dtype}")
        frame = copy.copy(self)
        frame.__dict__.pop("linear_rgb", None)
        codes.flags.writeable = False
        frame.__dict__["_srgb8"] = codes
        return frame

    def __getattr__(self, name: str):
        """``linear_rgb`` of a frame made by :meth:`with_srgb8_codes`, decoded on first use (and kept)."""
        codes = self.__dict__.get("_srgb8")
        if name != "linear_rgb" or codes is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        from .physics import srgb
        linear = self.__dict__["linear_rgb"] = srgb.code_to_linear(codes, 8)     # keeps the codes (attach_codes)
        return linear

    # --- per-site API shared with RawFrame: per-channel physics is written once for both ----------------------
    def signal(self) -> np.ndarray:
        """Linear signal per site, (H, W, 3)."""
        return self.linear_rgb

    def channel_index(self) -> np.ndarray:
        """Colour index (0 R, 1 G, 2 B) of each site, broadcastable to ``signal()``."""
        return np.arange(3).reshape(1, 1, 3)

    def site_depth_m(self) -> np.ndarray:
        """Range along the ray per site, broadcastable to ``signal()``."""
        return self.depth_m[..., None]

    def with_signal(self, signal: np.ndarray) -> "CameraFrame":
        return dataclasses.replace(self, linear_rgb=np.asarray(signal, dtype=np.float32))


CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


def cfa_index_map(pattern: str, height: int, width: int) -> np.ndarray:
    """(H, W) int8 colour index (0 R, 1 G, 2 B) of each Bayer site for a 2×2 pattern such as ``RGGB``."""
    if pattern not in CFA_PATTERNS:
        raise ValueError(f"unknown CFA pattern {pattern!r}; expected one of {CFA_PATTERNS}")
    cell = np.array([["RGB".index(c) for c in pattern[:2]], ["RGB".index(c) for c in pattern[2:]]], dtype=np.int8)
    return np.tile(cell, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


@dataclass(frozen=True)
class RawEncoding:
    fmt: str = "dng"           # dng | raw (plain uint16 + YAML sidecar)
    bits_per_sample: int = 16
    sidecar: tuple = ()        # a plain raw's input sidecar as (key, value) pairs, in order: written back with it
    orientation: int = 1       # a DNG's Orientation tag (IFD0, 1–8): the mosaic is processed upright (orientation)


@dataclass(frozen=True, eq=False)
class RawFrame:
    """Bayer digital numbers (H, W) as float32 (exact for 16-bit), never rescaled; levels as stated by the file.
    ``depth_valid`` and ``input_notes`` as in :class:`CameraFrame`."""

    dn: np.ndarray
    cfa_pattern: str
    black_level_dn: float
    white_level_dn: float
    profile: CameraProfile
    depth_m: np.ndarray | None = None
    encoding: RawEncoding = field(default_factory=RawEncoding)
    conditions: Conditions = field(default_factory=Conditions)
    depth_valid: np.ndarray | None = None
    input_notes: Mapping[str, Any] = field(default_factory=dict)
    warps: tuple = ()                        # physics.warp.Warp of each geometric step so far (masks, boxes follow)
    orientation: int = 1                     # ≠ 1: the stored mosaic turned upright by it (orientation.upright_frame)

    @property
    def shape(self) -> tuple[int, int]:
        return self.dn.shape

    def signal(self) -> np.ndarray:
        """Linear signal per site, (H, W): 0 at black level, 1 at white level."""
        s = np.subtract(self.dn, self.black_level_dn, dtype=np.float32)
        s *= np.float32(1.0 / (self.white_level_dn - self.black_level_dn))
        return s

    def channel_index(self) -> np.ndarray:
        return cfa_index_map(self.cfa_pattern, *self.dn.shape)

    def site_depth_m(self) -> np.ndarray:
        return self.depth_m

    def with_signal(self, signal: np.ndarray) -> "RawFrame":
        dn = np.multiply(signal, np.float32(self.white_level_dn - self.black_level_dn), dtype=np.float32)
        dn += np.float32(self.black_level_dn)
        return dataclasses.replace(self, dn=dn)


# ---------------------------------------------------------------------------------------------------------------
# Point clouds


@dataclass(frozen=True)
class CloudLayout:
    """How a cloud was stored: format and the per-point fields in file order as (canonical name, file name, dtype).

    Canonical names: x, y, z, intensity, ring, time_s, rcs_dbsm, v_r_m_per_s, v_r_comp_m_per_s, snr_db, power_db;
    any other field (``label`` included) keeps its file name."""

    fmt: str                                     # pcd | kitti_bin | nuscenes_bin | ply | vod_bin | txt | npz | feather
    fields: tuple[tuple[str, str, str], ...]
    pcd_data: str = "binary"       # PCD: ascii | binary | binary_compressed; PLY: ascii | binary_little_endian | ...
    no_return: str = "zero"        # a grid's no-return cells as stored: "zero" x/y/z, or "nan" (PCL's organised clouds)
    text: object = None            # txt: header, rows and number formats to write back (io/text_table.TextTable)
    lasers_by_ring: tuple[int, ...] | None = None   # an organised PCD stored a row per firing (Velodyne's): the stored
    #                                column of each grid row (io/pointcloud.firing_row_columns); None: stored as the grid
    schema: object = None          # feather: the Arrow schema (column types, metadata) to write back (io/feather.py)
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)   # the sensor's origin in the file's frame: subtracted
    #                                from the positions read, added back when written (LidarProfile.sensor_origin_m)


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Positions (N, 3) float64 in metres plus named per-point fields, all aligned.

    ``grid_shape`` is set when the points are a full rows × columns range image in row-major order, including
    no-return cells (all-zero position): models then keep N fixed and mark removed points with zeros.

    Provenance (:mod:`roadview_noise.provenance`), aligned with the points and never written as fields:
    ``origin`` int64 index of the point each point descends from (−1: new; None: identity), ``effect`` uint8
    :class:`~roadview_noise.provenance.Effect` codes (None: none reported), ``attributes`` per-point arrays the chain
    knows but does not write. :meth:`select`, :meth:`drop` and :meth:`concat` keep all of them aligned.

    ``recorded``: the chain's input as the sensor recorded it (set by :func:`~roadview_noise.compound.apply_models`
    on the clouds of the steps after the first): what a step calibrates the sensor on, rather than on what earlier
    steps made of the data."""

    positions_m: np.ndarray
    fields: Mapping[str, np.ndarray]
    sensor: str                                          # "lidar" | "radar"
    profile: LidarProfile | RadarProfile | None = None
    layout: CloudLayout | None = None
    grid_shape: tuple[int, int] | None = None
    conditions: Conditions = field(default_factory=Conditions)
    origin: np.ndarray | None = None
    effect: np.ndarray | None = None
    attributes: Mapping[str, np.ndarray] = field(default_factory=dict)
    recorded: PointCloud | None = None

    def __post_init__(self):
        n = len(self.positions_m)
        for kind, arrays in (("field", self.fields), ("attribute", self.attributes),
                             ("provenance", {"origin": self.origin, "effect": self.effect})):
            for name, arr in arrays.items():
                if arr is not None and len(arr) != n:
                    raise ValueError(f"{kind} {name!r} has {len(arr)} values for {n} points")

    def replace(self, **changes: Any) -> "PointCloud":
        """``dataclasses.replace(self, **changes)`` (the lengths checked again) without its per-field Python: ≈ 5
        against 13 µs, paid several times per radar file (issue 19)."""
        unknown = changes.keys() - self.__dataclass_fields__.keys()
        if unknown:
            raise TypeError(f"PointCloud has no field {sorted(unknown)[0]!r}")
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        new.__post_init__()
        return new

    def __len__(self) -> int:
        return len(self.positions_m)

    @property
    def ranges_m(self) -> np.ndarray:
        return np.linalg.norm(self.positions_m, axis=1)

    def select(self, mask_or_index: np.ndarray) -> "PointCloud":
        """Keep the points selected by a boolean mask or an index array; every field, attribute and the provenance
        stay aligned."""
        if self.grid_shape is not None:
            raise ValueError("select() would break a full range-image grid; use drop() instead")
        idx = np.asarray(mask_or_index)
        if idx.dtype == bool:
            if idx.shape != (len(self),):
                raise IndexError(f"a mask of shape {idx.shape} cannot select from {len(self)} points")
            idx = np.flatnonzero(idx)
        else:
            idx = idx.astype(np.int64)                  # a copy: it may become the origin

        def take(v: np.ndarray) -> np.ndarray:          # np.take: several times faster than v[idx] on (n, 3) rows
            return np.take(v, idx, axis=0)

        return self.replace(positions_m=take(self.positions_m), fields={k: take(v) for k, v in self.fields.items()},
                            origin=idx if self.origin is None else take(self.origin),
                            effect=None if self.effect is None else take(self.effect),
                            attributes={k: take(v) for k, v in self.attributes.items()})

    def drop(self, mask: np.ndarray) -> "PointCloud":
        """Remove the points in ``mask``: deleted from a list, set to no-return (zeros, ring kept; effect REMOVED,
        attributes kept: they describe the cell) in a grid."""
        if self.grid_shape is None:
            return self.select(~mask)
        from .provenance import Effect, mark

        idx = np.flatnonzero(mask)                      # indices: faster than the mask on (n, 3) rows
        pos = self.positions_m.copy()
        pos[idx] = 0.0
        fields = {}
        for k, v in self.fields.items():
            if k == "ring":
                fields[k] = v
            else:
                v = v.copy()
                v[idx] = 0
                fields[k] = v
        return mark(self.replace(positions_m=pos, fields=fields), mask, Effect.REMOVED)

    def with_fields(self, **fields: np.ndarray) -> "PointCloud":
        return self.replace(fields={**self.fields, **fields})

    def concat(self, other_positions_m: np.ndarray, other_fields: Mapping[str, np.ndarray],
               other_attributes: Mapping[str, np.ndarray] | None = None) -> "PointCloud":
        """Append new points (e.g. weather returns: origin −1, effect ADDED); fields and attributes missing from
        ``other_*`` are zero-filled."""
        if self.grid_shape is not None:
            raise ValueError("cannot append points to a full range-image grid")
        from .provenance import ADDED, KEPT, NEW, identity

        m = len(other_positions_m)
        fields, attributes = {}, {}
        for mine, theirs, out in ((self.fields, other_fields, fields),
                                  (self.attributes, other_attributes or {}, attributes)):
            for k, v in mine.items():
                extra = theirs.get(k)
                extra = np.zeros((m,) + v.shape[1:], dtype=v.dtype) if extra is None else np.asarray(extra, v.dtype)
                out[k] = np.concatenate([v, extra])
            unknown = set(theirs) - set(mine)
            if unknown:
                raise ValueError(f"fields or attributes {sorted(unknown)} are not in the cloud")
        n = len(self)
        origin = identity(n) if self.origin is None else self.origin
        effect = np.full(n, KEPT) if self.effect is None else self.effect
        return self.replace(positions_m=np.concatenate([self.positions_m, other_positions_m]), fields=fields,
                            origin=np.concatenate([origin, np.full(m, NEW, np.int64)]),
                            effect=np.concatenate([effect, np.full(m, ADDED)]), attributes=attributes)


SensorData = Union[CameraFrame, RawFrame, PointCloud]


def sensor_kind(data: SensorData) -> str:
    """'camera' for camera and raw frames, else the cloud's sensor ('lidar' | 'radar')."""
    return "camera" if isinstance(data, (CameraFrame, RawFrame)) else data.sensor
