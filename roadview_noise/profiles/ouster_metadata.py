"""Reading an Ouster sensor metadata JSON, both formats ouster-sdk reads (facts from ouster-sdk's metadata parser and
its test files, firmware 1.12 … 3.0):

- *legacy* (flat, firmware ≤ 2.x and ouster-sdk < 0.5 writers): ``beam_altitude_angles``, ``beam_azimuth_angles``,
  ``lidar_origin_to_beam_origin_mm``, ``beam_to_lidar_transform``, ``lidar_to_sensor_transform``, ``lidar_mode``,
  ``prod_line`` and ``data_format`` {``columns_per_frame``, ``pixels_per_column``, ``udp_profile_lidar``} at the top;
- *non-legacy* (nested, what ouster-sdk writes since firmware 2.x): the same keys under ``beam_intrinsics``,
  ``lidar_intrinsics``, ``lidar_data_format``, ``config_params`` (``lidar_mode``, ``udp_profile_lidar``) and
  ``sensor_info`` (``prod_line``), next to ``imu_intrinsics`` and ``calibration_status``.

A file is non-legacy when it has all seven non-legacy sections, legacy when it has none; a mix is refused, as
ouster-sdk refuses it. Also refused, naming the file and the problem: angle lists of different lengths, all-zero
angles, a beam count (``pixels_per_column``, else the beam count in ``prod_line``) the angles do not match,
``columns_per_frame`` contradicting ``lidar_mode``, and no column count at all. Early 16- and 32-beam OS1 units
list all 64 detector angles with the unlit rows at 0 (firmware 1.13): the lit rows are taken, in order.
Missing ``lidar_origin_to_beam_origin_mm``: the translation of ``beam_to_lidar_transform``, else ouster-sdk's
per-product default (OS-0 27.67 mm, OS-1 15.806 mm, OS-2 13.762 mm, gen 1 12.163 mm); missing
``lidar_to_sensor_transform``: ouster-sdk's default (lidar origin 36.18 mm above the sensor-frame origin).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError

#: the top-level sections of a non-legacy metadata JSON (ouster-sdk: all or none)
NONLEGACY_SECTIONS = ("sensor_info", "beam_intrinsics", "imu_intrinsics", "lidar_intrinsics", "config_params",
                      "lidar_data_format", "calibration_status")
#: ouster-sdk's default lidar_origin_to_beam_origin_mm by product-line prefix (gen 1 otherwise)
DEFAULT_BEAM_ORIGIN_MM = {"OS-0-": 27.67, "OS-1-": 15.806, "OS-2-": 13.762}
GEN1_BEAM_ORIGIN_MM = 12.163
IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
#: ouster-sdk's lidar_to_sensor_transform when a file has none (mm): 180° about z, lidar origin 36.18 mm up
DEFAULT_LIDAR_TO_SENSOR = (-1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 36.18, 0.0, 0.0, 0.0, 1.0)
_PROD_LINE_BEAMS = re.compile(r"^\w+-(?:\d+|DOME)(?:-MAX)?-(\d+)")
_LIDAR_MODE = re.compile(r"^(\d+)x(\d+)$")


@dataclass(frozen=True)
class OusterMetadata:
    """What a LiDAR profile needs from an Ouster metadata JSON (angles in degrees, offsets in metres)."""

    layout: str                                  # "legacy" or "non-legacy"
    beam_altitude_deg: tuple[float, ...]
    beam_azimuth_deg: tuple[float, ...]
    beam_origin_offset_m: float                  # horizontal lidar-origin → beam-origin distance
    sensor_z_offset_m: float                     # height of the beam origins above the sensor-frame origin
    columns: int                                 # columns_per_frame
    udp_profile_lidar: str                       # "" when the file does not say
    prod_line: str                               # "" when the file does not say


def read_ouster_metadata(path: Path) -> OusterMetadata:
    """Parse and check an Ouster metadata JSON (module docstring); :class:`InputError` naming the file otherwise."""
    path = Path(path)

    def fail(problem: str) -> InputError:
        return InputError(f"Ouster metadata JSON: {problem}", file=str(path))

    try:
        root = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise fail(f"cannot read it as JSON ({e})") from None
    if not isinstance(root, dict):
        raise fail("the file holds no JSON object")
    present = [s for s in NONLEGACY_SECTIONS if s in root]
    if present and len(present) < len(NONLEGACY_SECTIONS):
        missing = [s for s in NONLEGACY_SECTIONS if s not in root]
        raise fail(f"mixes the legacy (flat) and non-legacy (nested) formats: has {', '.join(present)} but lacks "
                   f"{', '.join(missing)} (ouster-sdk refuses such a file too)")
    layout = "non-legacy" if present else "legacy"

    def section(name: str) -> dict:
        value = root.get(name) if present else root
        if name == "lidar_data_format" and not isinstance(value, dict):
            return {}            # FW 1.12 answered "error: Command not recognized."; ouster-sdk then uses lidar_mode
        if not isinstance(value, dict):
            raise fail(f"{name} is not a JSON object")
        return value

    beams, lidar, fmt = section("beam_intrinsics"), section("lidar_intrinsics"), section("lidar_data_format")
    if not present:
        fmt = root.get("data_format") or {}
        if not isinstance(fmt, dict):
            raise fail("data_format is not a JSON object")
    config, info = section("config_params"), section("sensor_info")
    if "beam_altitude_angles" not in beams:
        where = "beam_intrinsics.beam_altitude_angles" if present else "beam_altitude_angles"
        raise fail(f"no {where} (not a sensor metadata file?)")
    altitude = _angles(beams, "beam_altitude_angles", fail)
    azimuth = _angles(beams, "beam_azimuth_angles", fail)
    if len(altitude) != len(azimuth):
        raise fail(f"{len(altitude)} beam_altitude_angles but {len(azimuth)} beam_azimuth_angles")
    if not any(altitude) and not any(azimuth):
        raise fail(f"all {len(altitude)} beam angles are 0 (an uncalibrated or blanked file)")
    prod_line = str(info.get("prod_line") or "")
    beam_count, counted_by = _beam_count(fmt, prod_line, len(altitude), fail)
    altitude, azimuth = _lit_rows(altitude, azimuth, beam_count, counted_by, fail)
    return OusterMetadata(
        layout=layout, beam_altitude_deg=altitude, beam_azimuth_deg=azimuth,
        beam_origin_offset_m=_beam_origin_mm(beams, prod_line, fail) / 1000.0,
        sensor_z_offset_m=(_transform(lidar, "lidar_to_sensor_transform", fail, DEFAULT_LIDAR_TO_SENSOR)[11]
                           + _transform(beams, "beam_to_lidar_transform", fail, IDENTITY)[11]) / 1000.0,
        columns=_columns(fmt, config, fail),
        udp_profile_lidar=str(fmt.get("udp_profile_lidar") or config.get("udp_profile_lidar") or ""),
        prod_line=prod_line)


def _angles(beams: dict, key: str, fail) -> tuple[float, ...]:
    values = beams.get(key)
    if not isinstance(values, list) or not values:
        raise fail(f"{key} is missing or not a non-empty list")
    if any(isinstance(v, list) for v in values):
        raise fail(f"{key} holds per-pixel angle arrays, which rvnoise does not read; give a beam table CSV")
    try:
        return tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise fail(f"{key} holds values that are not numbers") from None


def _number(mapping: dict, key: str, fail) -> float | None:
    value = mapping.get(key)
    if value is None:
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        raise fail(f"{key} is not a number ({value!r})") from None


def _beam_count(fmt: dict, prod_line: str, n_angles: int, fail) -> tuple[int, str]:
    """The beam count and what states it: pixels_per_column, else the beam count in prod_line (``OS-1-16-A0`` →
    16), else the number of angles."""
    ppc = _number(fmt, "pixels_per_column", fail)
    if ppc is not None:
        if ppc < 1 or ppc != int(ppc):
            raise fail(f"pixels_per_column {ppc:g} is not a positive whole number")
        return int(ppc), "pixels_per_column"
    match = _PROD_LINE_BEAMS.match(prod_line)
    return (int(match.group(1)), f"prod_line {prod_line}") if match else (n_angles, "the angles")


def _lit_rows(altitude, azimuth, beam_count: int, counted_by: str, fail):
    """The beams of the data: all angles, or (more angles than beams) the rows whose angles are not both 0."""
    if len(altitude) == beam_count:
        return altitude, azimuth
    said = f"{beam_count} beams ({counted_by})"
    lit = [i for i, (a, b) in enumerate(zip(altitude, azimuth)) if a or b]
    if len(altitude) > beam_count and len(lit) == beam_count:
        return tuple(altitude[i] for i in lit), tuple(azimuth[i] for i in lit)
    if len(altitude) > beam_count:
        raise fail(f"{said} but {len(altitude)} beam angles, {len(lit)} of them non-zero: which rows are lit is "
                   f"not stated; give a metadata file with {beam_count} angles or a beam table CSV")
    raise fail(f"{said} but only {len(altitude)} beam angles")


def _transform(mapping: dict, key: str, fail, default: tuple[float, ...] = IDENTITY) -> list[float]:
    """A 4×4 row-major homogeneous transform (millimetres); ``default`` when absent."""
    values = mapping.get(key)
    if values is None:
        return list(default)
    try:
        out = [float(v) for v in values]
    except (TypeError, ValueError):
        raise fail(f"{key} holds values that are not numbers") from None
    if len(out) != 16:
        raise fail(f"{key} has {len(out)} values, not the 16 of a 4×4 matrix")
    return out


def _beam_origin_mm(beams: dict, prod_line: str, fail) -> float:
    value = _number(beams, "lidar_origin_to_beam_origin_mm", fail)
    if value is not None:
        return value
    if "beam_to_lidar_transform" in beams:
        return _transform(beams, "beam_to_lidar_transform", fail, IDENTITY)[3]
    return next((mm for prefix, mm in DEFAULT_BEAM_ORIGIN_MM.items() if prod_line.startswith(prefix)),
                GEN1_BEAM_ORIGIN_MM)


def _columns(fmt: dict, config: dict, fail) -> int:
    """columns_per_frame, checked against lidar_mode (``1024x10`` → 1024); one of them must be there."""
    mode = config.get("lidar_mode")
    from_mode = None
    if mode is not None:
        match = _LIDAR_MODE.match(str(mode))
        if not match:
            raise fail(f"lidar_mode {mode!r} is not COLUMNSxRATE (e.g. 1024x10)")
        from_mode = int(match.group(1))
    cpf = _number(fmt, "columns_per_frame", fail)
    if cpf is None:
        if from_mode is None:
            raise fail("neither columns_per_frame nor lidar_mode: the number of columns is not stated")
        return from_mode
    if cpf < 1 or cpf != int(cpf):
        raise fail(f"columns_per_frame {cpf:g} is not a positive whole number")
    if from_mode is not None and int(cpf) != from_mode:
        raise fail(f"columns_per_frame {int(cpf)} contradicts lidar_mode {mode!r}")
    return int(cpf)

