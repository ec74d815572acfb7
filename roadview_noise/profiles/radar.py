"""4D imaging radar profiles (models.md §4) and their loader.

Built-ins (nominal figures of the radar class, not datasheet values; override any field with a YAML file or a
mapping):

- ``generic-77ghz`` (default): 77 GHz, 120° × 30° field of view at 1° × 2°, 0.2 m range bins, 200 m, SNR threshold
  estimated from the data.
- ``rehearse``: REHEARSE-style long-range 4D radar (ROADVIEW test-track recordings; PCD fields velocity, snr,
  power, rcs): 77 GHz, 120° × 28°, 300 m.
- ``vod``: View-of-Delft-style short-range 3+1D radar (ZF FRGen21 class): 77 GHz, 100 m; its files carry RCS and
  radial velocities but no SNR/power, so detection works on ``rcs_dbsm − 40 log10 r`` (models/radar/detection.py).
- ``ars408``: Continental ARS 408-21, the 2-D radar of nuScenes (``RADAR_*`` PCDs). From its datasheet
  (ARS 408-21 technical data, Continental Engineering Services): 76–77 GHz; far range 0.20–250 m, near range up to
  70/100 m at ±45° and 20 m at ±60°; range resolution 0.39 m near / 1.79 m far; velocity resolution 0.43 km/h
  near / 0.37 km/h far. The clutter model works in the first 20 m, so the profile takes the near-range scan:
  120° azimuth, 0.39 m, 0.43 km/h = 0.119 m/s, and the far scan's 250 m as ``max_range_m``. Assumed (datasheet
  values not re-checked here; override if yours differ): 3.2° near-range azimuth resolution at boresight and a
  20° elevation beam. No elevation measurement (z = 0 in the files): one 20° elevation cell,
  ``elevation_measured: false``. Its files carry RCS (dBsm) but neither SNR nor power, so IF bandwidth and noise
  figure (defaults) are unused.
- ``astyx-6455``: Astyx 6455 HiRes, the 3-D radar of the Astyx HiRes2019 dataset (``radar_6455/*.txt``). From the
  dataset paper (Meyer & Kuschk, "Automotive Radar Dataset for Deep Learning Based 3D Object Detection", EuRAD
  2019, §II): 110° × 10° field of view, 100 m range, 13 Hz. From the files (io/radar_formats.py; 13 frames of
  the public copy): ranges in 0.075 m steps (range resolution), radial velocities in 0.0812 m/s steps (Doppler
  bin) within ±5.2 m/s, detections out to about ±65° azimuth (87° at most) and ±19° elevation (beyond the
  paper's field of view, which the profile keeps: it only sizes the clutter grid, and these files have no clutter). Assumed (no datasheet found; override if yours differ): 77 GHz, 1° × 2° angular
  resolution (the generic grid). Elevation is measured (z varies). Its ``Mag`` is a relative level in dB
  (``power_db``, ``power_unit: relative``): the threshold is the frame's weakest detection (45 in every frame
  checked); there is no RCS, so no clutter.
- ``oculii-eagle``: Oculii Eagle, the 4D radar of TJ4DRadSet (``training/velodyne/*.bin``, io/radar_formats.py).
  From the Oculii EAGLE User's Manual (§4.5, sensor radiation cone): 120° horizontal × 40° vertical field of view.
  From the 41 sample frames of the dataset (github.com/TJRadarLab/TJ4DRadSet, 108 222 detections): detections out
  to 374 m (``max_range_m`` 375) and within ±60° azimuth. Assumed (no datasheet figures found; override if yours
  differ): 77 GHz, 1° × 2° angular cells and 0.2 m range bins (the generic grid). Elevation is measured. Its
  ``Power`` is the detection SNR in dB (``snr_db``, dataset README); there is no RCS, so no clutter.
- ``ars548``: Continental ARS 548 RDI (Dual-Radar's ``ars548/*.bin``; ars548_ros' PointCloudDetection). From
  Dual-Radar's sensor table (github.com/adept-thu/Dual-Radar, README Table 1): range resolution 0.22 m, azimuth
  resolution 1.2° within ±15° (1.68° at ±45°), elevation resolution 2.3°, 300 m, ±60° azimuth, ±14° elevation
  (±4° at 300 m), 20 Hz; 77 GHz (ars548_ros' paper abstract). Velocity resolution not given (default).
- ``arbe-phoenix``: Arbe Phoenix in middle-range mode (Dual-Radar's ``arbe/*.bin``). From the same table: 0.3 m,
  1.25° azimuth, 2° elevation, 153.6 m, 100° × 30°, 20 Hz. Assumed: 77 GHz; velocity resolution default.
  Neither Dual-Radar file states its columns' units (io/radar_formats.py): name them with ``radar_bin_fields``.

Every profile has a Doppler bin width ``velocity_resolution_m_per_s`` (default 0.1035 m/s, the RISE analysis: 512
bins over ±26.5 m/s; it sets the Doppler cells of the clutter model) and a ``power_unit``: ``relative`` (default;
power is only known up to a constant, so an SNR threshold cannot be turned into a power threshold) or ``dBm``
(absolute received power: threshold = SNR threshold + receiver noise floor).

Per-point field names of these datasets map to the canonical ``rcs_dbsm``, ``v_r_m_per_s``, ``v_r_comp_m_per_s``,
``snr_db``, ``power_db`` in the I/O layer; profiles hold sensor parameters only.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path


from ..errors import InputError
from ..types import RadarProfile
from . import check_keys, load_profile


def generic_77ghz() -> RadarProfile:
    """Generic 77 GHz 4D imaging radar: the RadarProfile defaults (the ROADVIEW 1° × 2° grid of models.md §4.4)."""
    return RadarProfile("generic-77ghz")


def rehearse() -> RadarProfile:
    """REHEARSE-style long-range 4D imaging radar (nominal)."""
    return RadarProfile("rehearse", frequency_hz=77e9, fov_azimuth_deg=120.0, fov_elevation_deg=28.0,
                        azimuth_resolution_deg=1.0, elevation_resolution_deg=2.0, range_resolution_m=0.2,
                        max_range_m=300.0, if_bandwidth_hz=20e6, noise_figure_db=12.0)


def vod() -> RadarProfile:
    """View-of-Delft-style short-range 3+1D radar (ZF FRGen21 class, nominal); RCS but no SNR in the data."""
    return RadarProfile("vod", frequency_hz=77e9, fov_azimuth_deg=120.0, fov_elevation_deg=30.0,
                        azimuth_resolution_deg=1.5, elevation_resolution_deg=1.5, range_resolution_m=0.2,
                        max_range_m=100.0, if_bandwidth_hz=20e6, noise_figure_db=12.0)


def ars408() -> RadarProfile:
    """Continental ARS 408-21 (nuScenes), near-range scan and far-range reach (module docstring)."""
    return RadarProfile("ars408", frequency_hz=76.5e9, fov_azimuth_deg=120.0, fov_elevation_deg=20.0,
                        azimuth_resolution_deg=3.2, elevation_resolution_deg=20.0, range_resolution_m=0.39,
                        velocity_resolution_m_per_s=0.43 / 3.6, max_range_m=250.0, elevation_measured=False)


def astyx_6455() -> RadarProfile:
    """Astyx 6455 HiRes (Astyx HiRes2019): paper and file values, assumptions marked (module docstring)."""
    return RadarProfile("astyx-6455", frequency_hz=77e9, fov_azimuth_deg=110.0, fov_elevation_deg=10.0,
                        azimuth_resolution_deg=1.0, elevation_resolution_deg=2.0, range_resolution_m=0.075,
                        velocity_resolution_m_per_s=0.0812, max_range_m=100.0, elevation_measured=True)


def oculii_eagle() -> RadarProfile:
    """Oculii Eagle (TJ4DRadSet): manual and file values, assumptions marked (module docstring)."""
    return RadarProfile("oculii-eagle", frequency_hz=77e9, fov_azimuth_deg=120.0, fov_elevation_deg=40.0,
                        azimuth_resolution_deg=1.0, elevation_resolution_deg=2.0, range_resolution_m=0.2,
                        max_range_m=375.0, elevation_measured=True)


def ars548() -> RadarProfile:
    """Continental ARS 548 RDI (Dual-Radar's sensor table; module docstring)."""
    return RadarProfile("ars548", frequency_hz=77e9, fov_azimuth_deg=120.0, fov_elevation_deg=28.0,
                        azimuth_resolution_deg=1.2, elevation_resolution_deg=2.3, range_resolution_m=0.22,
                        max_range_m=300.0, elevation_measured=True)


def arbe_phoenix() -> RadarProfile:
    """Arbe Phoenix, middle-range mode (Dual-Radar's sensor table; module docstring)."""
    return RadarProfile("arbe-phoenix", frequency_hz=77e9, fov_azimuth_deg=100.0, fov_elevation_deg=30.0,
                        azimuth_resolution_deg=1.25, elevation_resolution_deg=2.0, range_resolution_m=0.3,
                        max_range_m=153.6, elevation_measured=True)


POWER_UNITS = ("relative", "dBm")

BUILTIN = {"generic-77ghz": generic_77ghz, "rehearse": rehearse, "vod": vod, "ars408": ars408,
           "astyx-6455": astyx_6455, "oculii-eagle": oculii_eagle, "ars548": ars548, "arbe-phoenix": arbe_phoenix}


def default_radar_profile() -> RadarProfile:
    return generic_77ghz()


def load_radar_profile(spec: str | dict | None, *, base_dir: Path | None = None) -> RadarProfile:
    """A built-in name, a YAML file (a mapping of RadarProfile fields, optionally ``base: NAME_OR_FILE``) or a
    mapping ``{base: NAME_OR_FILE, <RadarProfile field>: value, ...}`` overriding fields of a base profile."""
    return load_profile(spec, kind="radar", builtin=BUILTIN, default=default_radar_profile, override=_override,
                        base_dir=base_dir)


def _override(base: RadarProfile, fields: dict, source: str) -> RadarProfile:
    check_keys(fields, {f.name for f in dataclasses.fields(RadarProfile)}, "radar", source)
    for key, value in fields.items():
        if key == "name" or (key == "snr_threshold_db" and value is None):
            continue
        if key in ("rcs_compensates_weather", "elevation_measured"):
            if not isinstance(value, bool) and not (key == "elevation_measured" and value is None):
                raise InputError(f"{key} must be true or false, got {value!r}", file=source)
            continue
        if key == "power_unit":
            if value not in POWER_UNITS:
                raise InputError(f"{key} must be one of {POWER_UNITS}, got {value!r}", file=source)
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{key} must be a number, got {value!r}", file=source)
        if key != "snr_threshold_db" and key != "noise_figure_db" and value <= 0:
            raise InputError(f"{key} must be > 0, got {value!r}", file=source)
        fields[key] = float(value)
    return dataclasses.replace(base, **fields)
