"""LiDAR sensor profiles (models.md §3.0).

Built-ins: ``os1-128`` (the real unit calibration of an Ouster OS1-128, ``signal`` photons, default for the D3.5
CNFs), ``os1-128-reflectivity`` (the same sensor storing its 8-bit calibrated reflectivity), ``vls-128`` (Velodyne
per-laser table, the sensor of D3.5 ch. 4), ``hdl-32e`` (Velodyne HDL-32E of nuScenes), ``carla-64`` (uniform
CARLA-style ray caster), and ``kitti-hdl64`` (KITTI's HDL-64E: fitted beam table, 0–1 intensities, stored laser by
laser).
Each states its intensity kind, sensor constant K (signal of a ρ = 1 target at 1 m), white reading W of a
reflectivity channel, how it stores intensities (step, faint readings), detection threshold (signal units), receiver
noise and overlap with their source (:mod:`roadview_noise.physics.lidar_intensity` converts every intensity to the
received signal, :mod:`roadview_noise.physics.receiver` detects in noise). Files: an Ouster metadata JSON of any
firmware, legacy or non-legacy format (:mod:`.ouster_metadata`; ``udp_profile_lidar`` says which channel the
intensity is, ``columns_per_frame`` the columns), a per-laser CSV (``laser_id, elevation_deg, azimuth_offset_deg``)
or a YAML profile. Without any profile the default OS1-128 does not state its intensity unit: the weather models
read it from the data and warn. Ring recovery lives in :mod:`roadview_noise.physics.lidar_geometry`.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import yaml

from ..errors import InputError
from ..physics.firing_grid import MERGED_SENSORS
from ..physics.lidar_intensity import OUSTER_WHITE_REFLECTIVITY, reflectivity_variant
from ..types import IntensityUnit, LidarProfile, SensorMount
from . import check_keys, load_profile
from .ouster_metadata import read_ouster_metadata

_DATA = Path(__file__).with_name("data")
OS1_SENSOR_CONSTANT = 65535.0           # photons·m²: signal of a ρ = 1 target at 1 m (see os1_128)
OS1_DETECTION_THRESHOLD = 3.28          # photons
VLS128_WHITE_REFLECTIVITY = 110.0       # idem, Velodyne VLS-128 (user manual §6.1)
OS1_OVERLAP_START_M = 0.5               # Ouster OS1 datasheet minimum range
OS1_OVERLAP_FULL_M = 5.0                # assumed full receiver overlap of the biaxial OS1 (see os1_128)
HDL64_DETECTION_THRESHOLD = 0.1 / 50.0 ** 2
OS1_THRESHOLD_OVER_NOISE = 3.28         # one background photon per pulse window at the datasheet threshold (see os1_128)
HDL32_SENSOR_CONSTANT = 25_000.0        # m², fitted on a real nuScenes scan (see hdl_32e)
HDL32_WHITE_REFLECTIVITY = 100.0        # HDL-32E FW 2.0: diffuse 0–100 for 0–100 %
KITTI_INTENSITY_STEP = 0.01             # KITTI stores the HDL-64E intensity as multiples of 0.01
AV2_SENSOR_ORIGIN_M = (1.35, 0.0, 1.58)  # Argoverse 2's two VLP-32C in its vehicle frame (see av2_vlp32c)
#: Ouster lidar packet profiles that carry only the 8-bit calibrated reflectivity (no signal channel)
OUSTER_REFLECTIVITY_ONLY = ("RNG15_RFL8_NIR8", "FUSA_RNG15_RFL8_NIR8_DUAL")


def _table(name: str) -> dict:
    """A shipped beam table (libyaml's parser when there: 5× faster on the 128-beam tables, the same values)."""
    return yaml.load((_DATA / name).read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


def os1_128() -> LidarProfile:
    """Ouster OS1-128: 865 nm, 2048 columns, 120 m, ``signal`` channel in photons (16-bit); real beam table.

    Beam: radius 4.75 mm at the window (D3.4 reference), full divergence 0.18° FWHM (Ouster OS1 datasheet, 128-channel
    models); without it weather particles far from the sensor would cover the beam 10–100× too much.
    Intensity scale: received signal ``S = K ρ cos θ / R²`` with K = 65535 photons·m² (a white target at 1 m fills the
    16-bit signal) and detection threshold 3.28 photons (5·10⁻⁵ of full scale, the D3.4 rain value): a 10 % / 80 %
    Lambertian target is detected to ``sqrt(K ρ / thr)`` = 45 m / 126 m (OS1-128 datasheet: 40–45 m / 120 m); the
    D3.4 fog value 2.42 would give 52 m / 147 m.
    Receiver overlap ξ: 0 up to 0.5 m (the datasheet minimum range), full at 5 m. The full-overlap range is an
    ASSUMPTION, not a measured value: the OS1 is biaxial (separate transmit and receive lenses), whose overlap
    builds up over metres rather than Hahner's 0.1 m. With Hahner's overlap (full at 1 m), homogeneous fog at 1 km
    visibility would return from every sky ray (5.2 photons at 1.47 m, threshold 3.28; empty rays see fog up to
    MOR 1.6 km), which real OS1 scans do not show; with full overlap at 5 m the fog return of an empty ray
    (``fog.lidar``, β = 0.046/MOR) is 32.1 photons at 1.42 m at MOR 30 m, 6.2 photons at 200 m and 1.3 photons
    (no return) at 1 km.
    Receiver: photon counting (SPAD), the threshold 3.28 photons; ASSUMPTION: one background photon per pulse window
    (ambient light and dark counts, B = 1), which puts the datasheet threshold 3.3 standard deviations of the
    background above it; range jitter 1.8 cm at SNR 50 (datasheet precision ±0.7–5 cm)."""
    t = _table("os1_128.yaml")
    return LidarProfile(
        "os1-128", tuple(t["beam_elevation_deg"]), tuple(t["beam_azimuth_offset_deg"]), columns=2048,
        wavelength_m=865e-9, beam_radius_m=4.75e-3, beam_divergence_rad=np.deg2rad(0.18),
        pulse_half_power_width_s=10e-9, max_range_m=120.0,
        intensity_unit=IntensityUnit.PHOTONS, intensity_full_scale=65535.0, intensity_kind="signal",
        sensor_constant=OS1_SENSOR_CONSTANT, detection_threshold=OS1_DETECTION_THRESHOLD,
        overlap_start_m=OS1_OVERLAP_START_M, overlap_full_m=OS1_OVERLAP_FULL_M,
        beam_origin_offset_m=t["beam_origin_offset_m"], sensor_z_offset_m=t["sensor_z_offset_m"], window="static",
        receiver="spad", photons_at_threshold=OS1_DETECTION_THRESHOLD, threshold_over_noise=OS1_THRESHOLD_OVER_NOISE,
        excess_noise_factor=1.0)


def os1_128_reflectivity() -> LidarProfile:
    """The same OS1-128 storing its calibrated ``reflectivity`` channel (8-bit, range-compensated), as real Ouster
    recordings often do (e.g. the low-bandwidth RNG15_RFL8_NIR8 profile).

    Same sensor as :func:`os1_128` (K = 65535 photons·m², detection threshold 3.28 photons, same overlap). Ouster's
    calibrated reflectivity reads a diffuse white (ρ = 1) target as W = 100 (retro-reflectors 101–255), so
    ``S = (I / 100) · K / R²``. Readings below 1 are stored as 1 (``faint_reading: lowest``): the real scan in
    ../shared/data has no reading 0 among its 107 647 returns and 1.6× more readings of 1 than of 2, while the
    counts rise from 2 to 4 — the faint ones pile up at 1."""
    return dataclasses.replace(reflectivity_variant(os1_128()), name="os1-128-reflectivity")


def vls_128() -> LidarProfile:
    """Velodyne VLS-128 (Alpha Prime): 903 nm, 1800 columns (0.2°), 245 m, calibrated 8-bit reflectivity
    (range-compensated), rotating head.

    Intensity scale: signal in units of the detection threshold (1); K chosen for the datasheet range 245 m at high
    (80 %) reflectivity: a ρ = 0.8 target returns the threshold at 245 m, ``K = 245² / 0.8`` (10 % then reaches
    87 m). The VLS-128 reads diffuse white as W = 110 (manual §6.1: diffuse 0–110 for 0–100 %, retro-reflectors
    111–255). Receiver overlap: Hahner's R1 = 0.9 m, R2 = 1.0 m, which he used for the Velodyne HDL-64 S3D of the
    Seeing Through Fog data; the VLS-128 is of the same (biaxial) family and no measurement of its overlap is at
    hand, so it is kept, unverified (it may reach full overlap farther out, like the OS1).
    Receiver: APD, generic ASSUMPTIONS (LidarProfile defaults): 100 photo-electrons at the threshold, excess noise
    factor 3, threshold 4 σ above the noise floor."""
    t = _table("vls_128.yaml")
    return LidarProfile(
        "vls-128", tuple(t["beam_elevation_deg"]), tuple(t["beam_azimuth_offset_deg"]), columns=1800,
        wavelength_m=903e-9, beam_radius_m=6.0e-3, beam_divergence_rad=3.0e-3 / 2, pulse_half_power_width_s=6e-9,
        max_range_m=245.0, intensity_unit=IntensityUnit.UINT8, intensity_full_scale=255.0,
        intensity_kind="reflectivity", sensor_constant=245.0 ** 2 / 0.8,
        reflectivity_white_reading=VLS128_WHITE_REFLECTIVITY, detection_threshold=1.0, window="rotating")


def uniform(name: str, channels: int, fov_up_deg: float, fov_down_deg: float, **kw) -> LidarProfile:
    """Evenly spaced beams from ``fov_up_deg`` (ring 0) down to ``fov_down_deg``, no azimuth offsets."""
    elev = np.linspace(fov_up_deg, fov_down_deg, channels)
    return LidarProfile(name, tuple(float(e) for e in elev), (0.0,) * channels, **kw)


def carla_64() -> LidarProfile:
    """CARLA ray-cast LiDAR: 64 uniform channels +2°…−24.8°, intensity in [0, 1] read as reflectivity
    (range-compensated, K = 1: a ρ = 1 target reads 1). CARLA's intensity is ``e^{−0.004 d}`` (≥ 0.67 within its
    100 m), so with the threshold of :func:`kitti_hdl64` every CARLA return is detectable. Receiver overlap:
    Hahner's (LidarProfile default)."""
    return uniform("carla-64", 64, 2.0, -24.8, columns=2048, wavelength_m=905e-9, max_range_m=100.0,
                   intensity_unit=IntensityUnit.UNIT, intensity_full_scale=1.0, intensity_kind="reflectivity",
                   sensor_constant=1.0, detection_threshold=HDL64_DETECTION_THRESHOLD)


def kitti_hdl64() -> LidarProfile:
    """KITTI's Velodyne HDL-64E S2, 905 nm, reflectance in [0, 1] (range-compensated, K = 1).

    Beam table: KITTI's unit, FITTED on real scans (``data/kitti_hdl64.yaml``: 64 elevations, ring 0 the highest, as
    KITTI stores them; +1.97° … −8.72° upper block, −8.89° … −24.83° lower, the S2 layout of +2° … −8.33° at 1/3°
    and −8.83° … −24.33° at 1/2°; the lasers' origins 0.2 m / 0.1 m above the scan's, ``beam_z_offset_m``); no
    azimuth offsets (KITTI's points are computed with them). Stored laser by laser
    (``storage_order: laser``): a ring-less ``.bin`` scan gets its rings and firing columns from that order
    (:mod:`roadview_noise.physics.laser_order`). Columns 2083: the S2 at 10 Hz (the grid of a scan is measured:
    2 162 … 2 172 on real KITTI scans).
    Detection threshold ``0.1 / (50 m)²`` (units of K/m²): HDL-64E S2 datasheet range 50 m on pavement (≈ 10 %); 80 %
    then reaches 141 m (datasheet: 120 m for cars and foliage). Receiver overlap: Hahner's R1 = 0.9 m, R2 = 1.0 m
    (LidarProfile default). Intensities in steps of 0.01 (as KITTI stores them); receiver as :func:`vls_128`.
    Threshold: the datasheet's (``threshold_calibration: datasheet``): KITTI's low readings are not radiometric (20 %
    of a scan's returns store 0, out to 80 m; calibrated from them the threshold sat 215× lower), a recorded return
    counts at least :meth:`physics.receiver.Receiver.recorded_floor`."""
    table = _table("kitti_hdl64.yaml")
    elevation = tuple(float(e) for e in table["beam_elevation_deg"])
    return LidarProfile("kitti-hdl64", elevation, (0.0,) * len(elevation), columns=2083, wavelength_m=905e-9,
                        beam_radius_m=5e-3, beam_divergence_rad=1.5e-3, pulse_half_power_width_s=5e-9,
                        max_range_m=120.0, intensity_unit=IntensityUnit.UNIT, intensity_full_scale=1.0,
                        intensity_kind="reflectivity", sensor_constant=1.0,
                        detection_threshold=HDL64_DETECTION_THRESHOLD, window="rotating",
                        intensity_step=KITTI_INTENSITY_STEP, storage_order="laser",
                        threshold_calibration="datasheet",
                        beam_z_offset_m=tuple(float(v) for v in table["beam_z_offset_m"]))


def hdl_32e() -> LidarProfile:
    """Velodyne HDL-32E (nuScenes LIDAR_TOP): 32 lasers from −30.67° to +10.67° in 4/3° steps (user manual 63-9113,
    vertical angle table: −30.67, −29.33, … +9.33, +10.67 in firing order), ring 0 the LOWEST beam (the Velodyne ROS
    driver's ring, nuScenes' fifth column: the median elevation of ring k in a real nuScenes scan is
    −30.67° + 1.33° k within 0.3°), 905 nm, 100 m (datasheet: "up to 100 m"), rotating head, no azimuth offsets.

    Columns 1085 at 20 Hz, as nuScenes records (2170 at the default 10 Hz: give ``columns: 2170``): one firing
    cycle every 46.08 µs (32 × 1.152 µs, manual's firing sequence), 21 700 per second, 695 000 points/s
    (datasheet); a real nuScenes scan holds 32 × 1084 points and its measured firing grid has 1085 columns. The
    firing grid of a list is measured anyway (:mod:`physics.firing_grid`); range images use ``columns``.
    Intensity: calibrated 8-bit reflectivity (HDL-32E firmware 2.0 description: diffuse targets 0–100 for
    0–100 % reflectivity, retro-reflectors 101–255), range-compensated: W = 100. Sensor constant: signal in units
    of the detection threshold (1); K = 25 000 m², FITTED on a real nuScenes scan: the faintest readings at
    65 / 75 / 85 m are 16 / 22 / 30, i.e. ``K = 100 R² / I`` = 26 400 / 25 600 / 24 100 (ρ = 0.8 then reaches
    141 m, 10 % 50 m; the datasheet's 100 m at ρ = 0.4).
    Minimum range 1 m (manual: "the minimum return distance for the HDL-32E is approximately 1 meter. Ignore returns
    closer than this"; nuScenes' devkit drops points within 1 m too): nuScenes stores every firing, the no-returns
    as points at the ego vehicle's displacement during the sweep (23 % of a real scan, all within 1 m): they are
    no-return rays, not returns (``min_range_m``). Receiver overlap Hahner's (0.9–1.0 m, LidarProfile default),
    ASSUMPTION as for :func:`vls_128`.
    Beam radius, divergence and pulse: ASSUMPTION, the VLS-128's (:func:`vls_128`; no HDL-32E figure at hand).
    Receiver: APD, generic ASSUMPTIONS (LidarProfile defaults). Threshold: the datasheet's (``threshold_calibration:
    datasheet``): the real scan's readings of 1–2 at 20–40 m would put it 11× below the one its far returns fit."""
    elev = tuple(round(-32.0 + 4.0 / 3.0 * (k + 1), 2) for k in range(32))       # −30.67, −29.33, … +10.67
    return LidarProfile(
        "hdl-32e", elev, (0.0,) * 32, columns=1085, wavelength_m=905e-9, beam_radius_m=6.0e-3,
        beam_divergence_rad=3.0e-3 / 2, pulse_half_power_width_s=6e-9, max_range_m=100.0, min_range_m=1.0,
        intensity_unit=IntensityUnit.UINT8, intensity_full_scale=255.0, intensity_kind="reflectivity",
        sensor_constant=HDL32_SENSOR_CONSTANT, reflectivity_white_reading=HDL32_WHITE_REFLECTIVITY,
        detection_threshold=1.0, window="rotating", threshold_calibration="datasheet")


def av2_vlp32c() -> LidarProfile:
    """Argoverse 2's LiDAR (its sensor dataset's ``sensors/lidar/*.feather`` sweeps): two stacked Velodyne VLP-32C,
    64 beams, ring = ``laser_number`` (0–31 the upper sensor, 32–63 the lower one, mounted upside down and tilted
    11.6°, each in the same order). Beam table ``data/av2_vlp32c.yaml``: the VLP-32C manual's vertical angles
    (−25° … +15°) in the order of Argoverse 2's ``laser_number``, matched on real sweeps (the median elevation of
    each laser_number in its own sensor's frame within 0.03°); no azimuth offsets here (each sensor's profile has
    them).

    The sweep stores the vehicle frame (origin on the ground under the rear axle); the sensors' origins lie at
    (1.350, 0.000, 1.640) m and (1.347–1.357, −0.003–0.005, 1.522–1.526) m in it (``egovehicle_SE3_sensor`` of the
    devkit's four test logs), so ``sensor_origin_m`` = (1.35, 0.0, 1.58): both within 6 cm, the chain's ranges and
    rays about it, the positions written back in the vehicle frame (:mod:`io.feather`). ``storage_order: merged``:
    one sweep of two sensors, the lower one flipped, has no single firing grid; with the log's
    ``calibration/egovehicle_SE3_sensor.feather`` beside the sweep each sensor runs the chain in its own frame with
    its own profile (:func:`av2_sensor`, :mod:`sensor_rig`), else weather acts on the returns only (the manifest's
    ``empty_rays_source`` says so).
    Radiometry, as the Velodyne family's (HDL-32E, VLP-16 manuals): 8-bit calibrated reflectivity, diffuse white
    W = 100 (ASSUMPTION for the VLP-32C); 903 nm; 200 m (datasheet); K = 200² / 0.4 = 100 000 m², ASSUMPTION (the
    datasheet's 200 m read at ρ = 0.4, the HDL-32E's reading of its datasheet). Threshold: the datasheet's
    (``threshold_calibration: datasheet``): real sweeps read 2 at 100–110 m, not radiometric (as nuScenes').
    Columns 1808: a 55.296 µs firing cycle at 10 Hz (the manual's timing) — not used without a firing grid.
    Beam radius, divergence, pulse and receiver: the HDL-32E's (:func:`hdl_32e`), ASSUMPTION."""
    t = _table("av2_vlp32c.yaml")
    elevation = tuple(float(e) for e in t["beam_elevation_deg"]) * 2
    return dataclasses.replace(
        hdl_32e(), name="av2-vlp32c", beam_elevation_deg=elevation, beam_azimuth_offset_deg=(0.0,) * 64,
        columns=1808, wavelength_m=903e-9, max_range_m=200.0, min_range_m=0.0, sensor_constant=200.0 ** 2 / 0.4,
        sensor_origin_m=AV2_SENSOR_ORIGIN_M, storage_order=MERGED_SENSORS)


VLP32C_FIRING_CYCLE_S = 55.296e-6      # VLP-32C manual: 16 firings of 2 lasers, 2.304 µs apart, and recharge
AV2_SENSORS = ("up_lidar", "down_lidar")    # Argoverse 2's sensor names (calibration), laser_number 0–31, 32–63


def av2_sensor(name: str) -> LidarProfile:
    """One of Argoverse 2's two VLP-32C in its own frame (``up_lidar``, ``down_lidar``: :func:`av2_mounts`): the
    32 beams of :func:`av2_vlp32c` in the order of ``laser_number`` (less 32 for the lower sensor) with the manual's
    azimuth offsets (``data/av2_vlp32c.yaml``, matched on real sweeps), origin at the sensor, the firing grid from
    each return's firing time (``offset_ns``; ``firing_cycle_s`` 55.296 µs, the manual's timing:
    :mod:`physics.firing_time`)."""
    t = _table("av2_vlp32c.yaml")
    return dataclasses.replace(
        av2_vlp32c(), name=f"av2-vlp32c:{name}", beam_elevation_deg=tuple(float(e) for e in t["beam_elevation_deg"]),
        beam_azimuth_offset_deg=tuple(float(a) for a in t["beam_azimuth_offset_deg"]), sensor_origin_m=(0.0, 0.0, 0.0),
        storage_order="", firing_cycle_s=VLP32C_FIRING_CYCLE_S)


def av2_mounts(poses: dict, source: str) -> tuple[SensorMount, ...]:
    """Argoverse 2's two sensors from the log's poses ``poses`` (sensor name → (3×3 rotation, translation m), sensor →
    vehicle frame: ``calibration/egovehicle_SE3_sensor.feather``, :func:`io.feather.read_sensor_poses`), read from
    ``source``: ``up_lidar`` holds laser_number 0–31, ``down_lidar`` 32–63 (av2 devkit ``Sweep``)."""
    mounts = []
    for k, name in enumerate(AV2_SENSORS):
        rotation, translation = poses[name]
        mounts.append(SensorMount(name, 32 * k, tuple(tuple(float(v) for v in row) for row in rotation),
                                  tuple(float(v) for v in translation), av2_sensor(name), source))
    return tuple(mounts)


BUILTIN = {"os1-128": os1_128, "os1-128-reflectivity": os1_128_reflectivity, "vls-128": vls_128,
           "carla-64": carla_64, "kitti-hdl64": kitti_hdl64, "hdl-32e": hdl_32e, "av2-vlp32c": av2_vlp32c}


def from_ouster_metadata(path: Path, **overrides) -> LidarProfile:
    """Profile from an Ouster sensor metadata JSON, legacy or non-legacy format (:mod:`.ouster_metadata`, which
    refuses malformed files): beam angles (the lit rows), beam-origin and z offsets, ``columns_per_frame`` (or
    ``lidar_mode``). ``udp_profile_lidar`` says what the intensity can be: a packet profile without a signal channel
    (RNG15_RFL8_NIR8, the low-bandwidth one) carries only the 8-bit calibrated reflectivity, which the profile then
    states; with a signal channel (LEGACY, RNG19_RFL8_SIG16_NIR16, …) a file may hold either, so the profile leaves
    it to the data (:func:`lidar_intensity.resolve_profile`, with a warning). Radiometry, range and receiver are the
    OS1-128's for every Ouster model (ASSUMPTION for OS-0 / OS-2 units: their optics differ)."""
    meta = read_ouster_metadata(path)
    elev = meta.beam_altitude_deg
    os1 = not meta.prod_line or meta.prod_line.startswith("OS-1-")
    name = "os1-128" if len(elev) == 128 and os1 else f"ouster-{meta.prod_line.lower() or len(elev)}"
    base = dataclasses.replace(os1_128(), name=name)
    if meta.udp_profile_lidar in OUSTER_REFLECTIVITY_ONLY:
        base = dataclasses.replace(reflectivity_variant(base), intensity_source=f"Ouster metadata {Path(path).name}: "
                                   f"udp_profile_lidar {meta.udp_profile_lidar} carries only the 8-bit reflectivity")
    else:
        base = dataclasses.replace(base, intensity_source="")
    return dataclasses.replace(base, name=overrides.pop("name", base.name), beam_elevation_deg=elev,
                               beam_azimuth_offset_deg=meta.beam_azimuth_deg, columns=meta.columns,
                               beam_origin_offset_m=meta.beam_origin_offset_m,
                               sensor_z_offset_m=meta.sensor_z_offset_m, **overrides)


def from_beam_table_csv(path: Path, base: LidarProfile | None = None, **overrides) -> LidarProfile:
    """Profile from a per-laser CSV ``laser_id, elevation_deg, azimuth_offset_deg`` (rows in laser order)."""
    try:
        with open(path, newline="") as fh:
            rows = sorted(csv.DictReader(fh), key=lambda r: int(r["laser_id"]))
        elev = tuple(float(r["elevation_deg"]) for r in rows)
        azim = tuple(float(r.get("azimuth_offset_deg") or 0.0) for r in rows)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"not a beam table CSV with laser_id, elevation_deg ({e})", file=str(path)) from None
    base = base or vls_128()
    return dataclasses.replace(base, name=overrides.pop("name", Path(path).stem), beam_elevation_deg=elev,
                               beam_azimuth_offset_deg=azim, **overrides)


def load_lidar_profile(spec: str | dict | None, *, base_dir: Path | None = None) -> LidarProfile:
    """A built-in name, a file (``.json`` Ouster metadata, ``.csv`` beam table, ``.yaml`` profile) or a mapping
    ``{base: NAME_OR_FILE, <LidarProfile field>: value, ...}`` overriding fields of a base profile."""
    return load_profile(spec, kind="LiDAR", builtin=BUILTIN, default=default_profile, override=_override,
                        base_dir=base_dir, loaders={".json": from_ouster_metadata, ".csv": from_beam_table_csv})


def default_profile() -> LidarProfile:
    """The profile of a cloud nobody described: the OS1-128, whose intensity unit nothing states (the weather
    models read it from the data, :func:`lidar_intensity.resolve_profile`, and say so)."""
    return dataclasses.replace(os1_128(), intensity_source="")


DEFAULT_FULL_SCALE = {"photons": 65535.0, "uint8": 255.0, "unit": 1.0}
RECIPE_SCALE = "the recipe's intensity_unit / intensity_full_scale"


def with_intensity_scale(profile: LidarProfile, unit: str | None, full_scale: float | None,
                         source: str = RECIPE_SCALE) -> LidarProfile:
    """The same sensor with intensities stored in another unit/full scale (the recipe's ``intensity_unit``,
    ``intensity_full_scale``, or a profile mapping's: ``source`` states it): everything tied to the stored scale
    follows, so the physics is unchanged — for a ``signal`` profile the sensor constant and the threshold (signal =
    stored intensity), for a ``reflectivity`` profile the white reading."""
    unit = unit or profile.intensity_unit
    new_fs = float(full_scale or DEFAULT_FULL_SCALE.get(unit, profile.intensity_full_scale))
    ratio = new_fs / profile.intensity_full_scale
    changes: dict = {"intensity_unit": unit, "intensity_full_scale": new_fs, "intensity_source": source,
                     "intensity_step": profile.intensity_step if unit == profile.intensity_unit else None}
    if profile.intensity_kind == "signal":
        if profile.sensor_constant is not None:
            changes["sensor_constant"] = profile.sensor_constant * ratio
        changes["detection_threshold"] = profile.detection_threshold * ratio
    elif profile.reflectivity_white_reading is not None:
        changes["reflectivity_white_reading"] = profile.reflectivity_white_reading * ratio
    return dataclasses.replace(profile, **changes)


def _override(base: LidarProfile, fields: dict, source: str) -> LidarProfile:
    check_keys(fields, {f.name for f in dataclasses.fields(LidarProfile)}, "LiDAR", source)
    for k in ("beam_elevation_deg", "beam_azimuth_offset_deg", "beam_z_offset_m"):
        if k in fields:
            fields[k] = tuple(float(v) for v in fields[k])
    if "beam_elevation_deg" in fields and "beam_azimuth_offset_deg" not in fields:
        fields["beam_azimuth_offset_deg"] = (0.0,) * len(fields["beam_elevation_deg"])
    if "beam_elevation_deg" in fields and "beam_z_offset_m" not in fields:
        fields["beam_z_offset_m"] = ()                 # the base's offsets belong to the base's beams
    if {"intensity_unit", "intensity_kind", "intensity_full_scale"} & set(fields):
        fields.setdefault("intensity_source", source)
    if {"intensity_unit", "intensity_full_scale"} & set(fields):      # the base's sensor, stored in another scale
        kind = dataclasses.replace(base, intensity_kind=fields.get("intensity_kind", base.intensity_kind))
        base = with_intensity_scale(kind, fields.get("intensity_unit"), fields.get("intensity_full_scale"), source)
    if len(fields.get("beam_elevation_deg", base.beam_elevation_deg)) != len(
            fields.get("beam_azimuth_offset_deg", base.beam_azimuth_offset_deg)):
        raise InputError("beam_elevation_deg and beam_azimuth_offset_deg differ in length", file=source)
    offsets = fields.get("beam_z_offset_m", base.beam_z_offset_m)
    if offsets and len(offsets) != len(fields.get("beam_elevation_deg", base.beam_elevation_deg)):
        raise InputError("beam_z_offset_m and beam_elevation_deg differ in length", file=source)
    return dataclasses.replace(base, **fields)
