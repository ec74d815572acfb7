"""Ouster metadata JSON of every firmware: legacy (flat) and non-legacy (nested) files built here with the key
layout of ouster-sdk's test files; malformed ones are refused naming the file and the problem. The real files
(/work/realdata/ouster_meta, not in the repo) are checked when present."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from roadview_noise.errors import InputError
from roadview_noise.profiles.lidar import load_lidar_profile
from roadview_noise.profiles.ouster_metadata import NONLEGACY_SECTIONS

REAL = Path("/work/realdata/ouster_meta")
ALT = [round(float(a), 3) for a in np.linspace(21.0, -21.0, 64)]
AZ = [[4.2, 1.4, -1.4, -4.2][i % 4] for i in range(64)]
L2S = [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 38.195, 0, 0, 0, 1]


def legacy(**changes) -> dict:
    meta = {"beam_altitude_angles": ALT, "beam_azimuth_angles": AZ, "lidar_origin_to_beam_origin_mm": 15.806,
            "lidar_to_sensor_transform": L2S, "lidar_mode": "1024x10", "prod_line": "OS-1-64",
            "data_format": {"columns_per_frame": 1024, "pixels_per_column": 64,
                            "udp_profile_lidar": "RNG19_RFL8_SIG16_NIR16"}, "build_rev": "v2.4.0"}
    meta.update(changes)
    return meta


def nonlegacy(**changes) -> dict:
    meta = {"beam_intrinsics": {"beam_altitude_angles": ALT, "beam_azimuth_angles": AZ,
                                "beam_to_lidar_transform": [1, 0, 0, 16.721, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]},
            "lidar_intrinsics": {"lidar_to_sensor_transform": L2S},
            "imu_intrinsics": {"imu_to_sensor_transform": [1, 0, 0, 0] * 4},
            "config_params": {"lidar_mode": "512x10", "udp_profile_lidar": "RNG15_RFL8_NIR8"},
            "lidar_data_format": {"columns_per_frame": 512, "pixels_per_column": 64},
            "sensor_info": {"prod_line": "OS-1-64", "build_rev": "v3.0.1"},
            "calibration_status": {"reflectivity": {"valid": True}}}
    meta.update(changes)
    return meta


def write(tmp_path, meta, name="meta.json") -> str:
    path = tmp_path / name
    path.write_text(json.dumps(meta))
    return str(path)


def test_legacy_and_nonlegacy_give_the_same_geometry(tmp_path):
    """The nested format (ouster-sdk's since FW 2.x) was refused before: both now give the beams, columns,
    beam-origin offset (from beam_to_lidar_transform when lidar_origin_to_beam_origin_mm is absent) and z."""
    old = load_lidar_profile(write(tmp_path, legacy(), "old.json"))
    new = load_lidar_profile(write(tmp_path, nonlegacy(), "new.json"))
    for p in (old, new):
        assert p.channels == 64 and p.beam_elevation_deg == tuple(ALT) and p.beam_azimuth_offset_deg == tuple(AZ)
        assert p.sensor_z_offset_m == pytest.approx(0.038195)
    assert (old.columns, new.columns) == (1024, 512)
    assert (old.beam_origin_offset_m, new.beam_origin_offset_m) == (pytest.approx(0.015806), pytest.approx(0.016721))
    # the packet profile is read from lidar_data_format or config_params: RNG15_RFL8_NIR8 is reflectivity only
    assert (old.intensity_kind, new.intensity_kind) == ("signal", "reflectivity")
    assert new.name == "ouster-os-1-64"


def test_columns_from_lidar_mode_and_sdk_defaults(tmp_path):
    """A FW 1.12 file has no data format ("error: Command not recognized."): columns come from lidar_mode; a
    reduced config without offsets gets ouster-sdk's per-product defaults."""
    p = load_lidar_profile(write(tmp_path, nonlegacy(lidar_data_format="error: Command not recognized.",
                                                     config_params={"lidar_mode": "2048x10"})))
    assert p.columns == 2048 and p.channels == 64
    reduced = load_lidar_profile(write(tmp_path, {"beam_altitude_angles": ALT, "beam_azimuth_angles": AZ,
                                                  "lidar_mode": "1024x20"}, "reduced.json"))
    assert reduced.columns == 1024 and reduced.beam_origin_offset_m == pytest.approx(0.012163)
    assert reduced.sensor_z_offset_m == pytest.approx(0.03618)


def test_unlit_rows_of_a_16_beam_unit_are_dropped(tmp_path):
    """FW 1.13 OS-1-16-A0: 64 detector angles, the 48 unlit rows at 0: the 16 lit rows are the beams."""
    lit = list(range(3, 64, 4))
    alt = [ALT[i] if i in lit else 0 for i in range(64)]
    az = [AZ[i] if i in lit else 0 for i in range(64)]
    p = load_lidar_profile(write(tmp_path, legacy(beam_altitude_angles=alt, beam_azimuth_angles=az,
                                                  prod_line="OS-1-16-A0", data_format={})))
    assert p.channels == 16 and p.beam_elevation_deg == tuple(ALT[i] for i in lit) and p.columns == 1024


@pytest.mark.parametrize("meta, problem", [
    (legacy(beam_altitude_angles=[0.0] * 64, beam_azimuth_angles=[0.0] * 64), "all 64 beam angles are 0"),
    (legacy(beam_altitude_angles=ALT[:63]), "63 beam_altitude_angles but 64 beam_azimuth_angles"),
    (legacy(data_format={"pixels_per_column": 32, "columns_per_frame": 1024}),
     r"32 beams \(pixels_per_column\) but 64 beam angles, 64 of them non-zero"),
    (legacy(prod_line="OS-1-16-A0", data_format={}), r"16 beams \(prod_line OS-1-16-A0\) but 64 beam angles"),
    (legacy(prod_line="OS-1-128", data_format={}), r"128 beams \(prod_line OS-1-128\) but only 64"),
    (legacy(data_format={"columns_per_frame": 2048}), "columns_per_frame 2048 contradicts lidar_mode '1024x10'"),
    (legacy(lidar_mode=None, data_format={}), "neither columns_per_frame nor lidar_mode"),
    (legacy(beam_altitude_angles=[[1.0] * 1024] * 64), "per-pixel angle arrays"),
    (legacy(beam_altitude_angles="x"), "beam_altitude_angles is missing or not a non-empty list"),
    (legacy(lidar_to_sensor_transform=[0] * 12), "lidar_to_sensor_transform has 12 values"),
    ({"packet_hash": "ab", "scans": []}, "no beam_altitude_angles"),
    ([1, 2], "no JSON object"),
])
def test_malformed_metadata_is_refused(tmp_path, meta, problem):
    path = write(tmp_path, meta, "bad.json")
    with pytest.raises(InputError, match=problem) as e:
        load_lidar_profile(path)
    assert "bad.json" in str(e.value)


@pytest.mark.parametrize("drop", ["sensor_info", "calibration_status"])
def test_a_mix_of_the_two_formats_is_refused(tmp_path, drop):
    """ouster-sdk refuses a file with some but not all non-legacy sections (garbled_legacy_and_nonlegacy,
    incomplete_no_sensor_info_nonlegacy, legacy_with_calibration_status): so does rvnoise, naming what lacks."""
    meta = nonlegacy()
    del meta[drop]
    with pytest.raises(InputError, match=f"mixes the legacy.*lacks {drop}"):
        load_lidar_profile(write(tmp_path, meta))
    with pytest.raises(InputError, match="has calibration_status but lacks sensor_info"):
        load_lidar_profile(write(tmp_path, legacy(calibration_status={}), "l.json"))
    assert len(NONLEGACY_SECTIONS) == 7


REFUSED = {"1_12_os1-991937000062-16A0_legacy.json", "complete_but_all_zeros_legacy.json",
           "garbled_legacy_and_nonlegacy.json", "incomplete_no_calref_nonlegacy.json",
           "incomplete_no_sensor_info_nonlegacy.json", "incorrect_nbeam_angles_legacy_113.json",
           "legacy_with_calibration_status.json"}


@pytest.mark.skipif(not REAL.is_dir(), reason="no /work/realdata/ouster_meta")
def test_every_real_ouster_metadata_file():
    """ouster-sdk's test files: every sensor metadata is read (beam count = pixels_per_column or the product's,
    columns = lidar_mode's), the malformed ones and the 1.12 16A0 (64 angles, lit rows not marked) refused."""
    read, refused = 0, set()
    for path in sorted(REAL.glob("*.json")):
        if path.name.endswith("_digest.json"):
            continue
        try:
            p = load_lidar_profile(str(path))
        except InputError as e:
            assert path.name in str(e)
            refused.add(path.name)
            continue
        read += 1
        assert p.channels in (16, 32, 64, 128) and p.columns in (512, 1024, 2048)
        assert 0.012 <= p.beam_origin_offset_m <= 0.028 and 0.036 <= p.sensor_z_offset_m <= 0.079
    assert refused == REFUSED and read == 54
