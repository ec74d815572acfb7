"""Firing grid of a real Velodyne list (physics/firing_grid.py): a VLP-16 list as its drivers decode it (TIER IV
nebula, the ROS velodyne driver) measures the sensor's firing columns, not twice as many."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from roadview_noise.physics.firing_grid import FiringGridWarning, firing_grid, undecided_columns
from roadview_noise.profiles.lidar import load_lidar_profile
from roadview_noise.types import PointCloud

LASER_ELEVATION_DEG = np.array([-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15], float)
FIRING_S = 2.304e-6             # VLP-16 manual: lasers 2.304 µs apart,
SEQUENCE_S = 55.296e-6          # a firing sequence every 55.296 µs,
BLOCKS, SEQUENCES = 12, 2       # two sequences per data block, 12 blocks per packet
VLP16 = {"base": "hdl-32e", "beam_elevation_deg": sorted(LASER_ELEVATION_DEG.tolist()),     # as README's nebula row
         "beam_azimuth_offset_deg": [0.0] * 16, "columns": 1800}


def vlp16_list(rate_hz: float = 10.0, fill: float = 0.5, dual: bool = True, seed: int = 0):
    """A VLP-16 turn decoded as nebula's decoder does (its timing, not its code): a block's azimuth is the encoder's
    (0.01°) at its first firing; each laser's azimuth is interpolated by its firing time (to 0.01°) from the azimuth
    difference to the next distinct block — except in the packet's last one, which gets none (its second sequence
    and every laser sit at the block's azimuth, as in the real list). ``dual``: each firing's blocks come in pairs
    (last and strongest return): one point where both echoes agree, two at the same azimuth on 10 % of the rays. The
    upward beams (a ceiling) return on 77 % (+1°) … 100 % (+15°) of their firings, the others on ``fill``. Returns
    (the list with its ``ring`` field, its firing sequences per turn, its empty cells, its returns in the packets'
    last blocks)."""
    rng = np.random.default_rng(seed)
    per_packet = BLOCKS // (2 if dual else 1)                 # distinct firings (blocks) per packet
    block_s = SEQUENCES * SEQUENCE_S
    t_block = np.arange(int(np.ceil(1 / rate_hz / block_s / per_packet)) * per_packet) * block_s
    t_block = t_block[t_block < 1 / rate_hz]                   # one turn
    azimuth_cdeg = np.round(36000 * rate_hz * (t_block + rng.uniform(0, block_s))) % 36000   # encoder, 0.01°
    diff = np.mod(np.roll(azimuth_cdeg, -1) - azimuth_cdeg, 36000)
    diff[per_packet - 1::per_packet] = 0                      # the decoder's last block of a packet
    laser = np.arange(16)
    fraction = (laser[None, :] * FIRING_S + np.arange(SEQUENCES)[:, None] * SEQUENCE_S) / block_s   # (seq, laser)
    az_deg = np.round(azimuth_cdeg[:, None, None] + diff[:, None, None] * fraction[None]) / 100     # block, seq, laser
    az_deg, el_deg = az_deg.reshape(-1, 16), np.broadcast_to(LASER_ELEVATION_DEG, (az_deg.size // 16, 16))
    hit = rng.random(az_deg.shape) < np.where(LASER_ELEVATION_DEG > 0, 0.75 + LASER_ELEVATION_DEG / 60, fill)
    echoes = np.where(hit & (rng.random(az_deg.shape) < (0.1 if dual else 0.0)), 2, hit.astype(int))
    seq, lsr = np.nonzero(echoes)
    seq, lsr = np.repeat(seq, echoes[seq, lsr]), np.repeat(lsr, echoes[seq, lsr])
    r = rng.uniform(1.5, 30, len(seq))
    a, e = np.deg2rad(-az_deg[seq, lsr]), np.deg2rad(el_deg[seq, lsr])     # Velodyne azimuth turns clockwise
    pos = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], 1) * r[:, None]
    ring = np.argsort(np.argsort(LASER_ELEVATION_DEG))[lsr]
    profile = dataclasses.replace(load_lidar_profile(VLP16), sensor_z_offset_m=0.0, beam_origin_offset_m=0.0)
    cloud = PointCloud(pos, {"intensity": np.full(len(r), 50, np.uint8), "ring": ring.astype(np.uint16)}, "lidar",
                       profile)
    off_phase = np.zeros(len(t_block), bool)
    off_phase[per_packet - 1::per_packet] = True
    return (cloud, 1 / (rate_hz * SEQUENCE_S), int(np.count_nonzero(~hit)),
            int(np.count_nonzero(hit[np.repeat(off_phase, SEQUENCES)])))


@pytest.mark.parametrize("dual, fill", [(True, 0.5), (True, 0.2), (False, 0.5), (False, 0.9)])
def test_a_vlp16_list_measures_its_firing_sequences_per_turn(dual, fill):
    """Dual- and single-return lists with the decoder's last block of a packet (a tenth or a twelfth of the returns
    a fraction of a step off their beam's phase; main measured no grid or 1 834 columns, the real list 3 605): the
    turn's firing sequences to a column (1 808 at 10 Hz, the profile's 1 800 only nominal), every empty cell an empty
    ray, and at most the returns of the last blocks more (one of those in its neighbour's cell leaves its own
    empty)."""
    cloud, turn, empty, off_phase = vlp16_list(dual=dual, fill=fill)
    grid = firing_grid(cloud, cloud.profile)
    assert not isinstance(grid, str), grid
    assert abs(grid.columns - turn) < 1, (grid.columns, turn)
    assert empty <= len(grid.ring) <= empty + off_phase, (len(grid.ring), empty, off_phase)


def test_twice_the_profiles_columns_yields_to_it_when_its_step_fits_too():
    """Gaps measured on a VLP-16 list at half its step (3 616 columns, as main read the real list): the profile's
    1 800 win, warned; a real 2 048-column recording against a 1 024-column profile keeps its 2 048 (its odd gaps)."""
    cloud, turn, _, _ = vlp16_list()
    step = 2 * np.pi / turn
    gap = np.abs(np.random.default_rng(1).geometric(0.8, 3000) * step
                 + np.random.default_rng(2).normal(0, 0.02 * step, 3000))
    with pytest.warns(FiringGridWarning, match="3616 columns, twice the 1800"):
        assert undecided_columns(gap, 3616, cloud.profile) == 1800
    ouster = dataclasses.replace(cloud.profile, columns=1024)
    gap = np.random.default_rng(3).geometric(0.7, 3000) * 2 * np.pi / 2048
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert undecided_columns(gap, 2048, ouster) == 2048


def test_the_manifest_says_when_the_profiles_columns_won(monkeypatch):
    """When the profile's column count wins over the gaps' (:func:`undecided_columns`), the grid's description — the
    manifest's ``empty_rays_source`` — says so instead of "measured from the list"; otherwise it is unchanged."""
    from roadview_noise.physics import firing_grid as module

    cloud, _, _, _ = vlp16_list()
    measured = firing_grid(cloud, cloud.profile)
    assert "measured from the list" in measured.describe() and measured.gaps_columns is None
    monkeypatch.setattr(module, "undecided_columns", lambda gap, columns, profile: profile.columns)
    won = firing_grid(cloud, cloud.profile)
    assert won.columns == 1800 and won.gaps_columns == measured.columns
    assert won.describe().startswith(f"16x1800 firing grid of profile {cloud.profile.name!r}: the list's gaps fit "
                                     f"its step and {measured.columns} columns alike"), won.describe()
