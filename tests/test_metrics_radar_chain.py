"""A radar chain's comparisons held to its end and made in one compiled call (``metrics.Deferred(radar_chains=True)``,
issue 18): the same metrics as :func:`metrics.compare` step by step, on hand-built and random chains."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roadview_noise.metrics import Deferred, compare
from roadview_noise.provenance import Effect, follow_points, mark, step_input
from roadview_noise.types import PointCloud, RadarProfile

from test_metrics_provenance import STEPS, random_list


def hand_chain() -> tuple[list[PointCloud], list[PointCloud]]:
    """Four detections (SNR 20, 10, 30, 40 dB at 5, 15, 25, 45 m); step 1 removes the second and attenuates the
    third by 3 dB; step 2 moves the last to half its range and adds a clutter point (5 m, 7 dB)."""
    c0 = PointCloud(np.array([[5.0, 0, 0], [0, 15.0, 0], [0, 0, 25.0], [0, -45.0, 0]]),
                    {"snr_db": np.array([20, 10, 30, 40], np.float32)}, "radar", profile=RadarProfile("r"))
    s = step_input(c0)
    out1 = mark(s.with_fields(snr_db=s.fields["snr_db"] - np.float32([0, 0, 3, 0])), np.array([0, 0, 1, 0], bool),
                Effect.ATTENUATED).select(np.array([True, False, True, True]))
    c1 = follow_points(c0, out1, 0)
    s = step_input(c1)
    pos = s.positions_m.copy()
    pos[2] *= 0.5
    out2 = mark(dataclasses.replace(s, positions_m=pos), np.array([0, 0, 1], bool), Effect.MOVED).concat(
        np.array([[3.0, 4.0, 0.0]]), {"snr_db": np.array([7], np.float32)})
    c2 = follow_points(c1, out2, 1)
    return [c0, c1, c2], [out1, out2]


def held(clouds: list[PointCloud], outputs: list[PointCloud], pairs=((0, -1),)) -> list[dict]:
    """The metrics of each step and of ``pairs`` of clouds as a run's :class:`Deferred` gives them."""
    deferred = Deferred(radar_chains=True)
    got = [deferred.compare(clouds[i - 1], clouds[i], outputs[i - 1]) for i in range(1, len(clouds))]
    got += [deferred.compare(clouds[i], clouds[j]) for i, j in pairs]
    deferred.settle(keep=clouds[-1])             # a step's settle: the chain is held to its end
    assert all(m == {} for m in got)
    deferred.settle()
    return got


def one_by_one(clouds: list[PointCloud], outputs: list[PointCloud], pairs=((0, -1),)) -> list[dict]:
    """The same by :func:`compare` at once, on new objects (summaries of their own)."""
    clouds = [dataclasses.replace(c) for c in clouds]
    return ([compare(clouds[i - 1], clouds[i], outputs[i - 1]) for i in range(1, len(clouds))]
            + [compare(clouds[i], clouds[j]) for i, j in pairs])


def test_a_held_radar_chain_gives_the_hand_computed_metrics():
    clouds, outputs = hand_chain()
    step1, step2, output = held(clouds, outputs)
    assert step1 == {"points_in": 4, "points_out": 3, "kept": 2, "attenuated": 1, "moved": 0, "added": 0,
                     "removed": 1, "max_range_m_in": 45.0, "max_range_m_out": 45.0,
                     "points_per_10m_in": [1, 1, 1, 0, 1], "points_per_10m_out": [1, 0, 1, 0, 1],
                     "mean_snr_in_db": 25.0, "mean_snr_out_db": 29.0, "mean_snr_change_db": -1.0}
    assert step2 == {"points_in": 3, "points_out": 4, "kept": 1, "attenuated": 0, "moved": 1, "added": 1,
                     "removed": 0, "max_range_m_in": 45.0, "max_range_m_out": 25.0,
                     "points_per_10m_in": [1, 0, 1, 0, 1], "points_per_10m_out": [2, 0, 2, 0, 0],
                     "mean_snr_in_db": 29.0, "mean_snr_out_db": 23.5, "mean_snr_change_db": 0.0}
    assert output == {"points_in": 4, "points_out": 4, "kept": 1, "attenuated": 1, "moved": 1, "added": 1,
                      "removed": 1, "max_range_m_in": 45.0, "max_range_m_out": 25.0,
                      "points_per_10m_in": [1, 1, 1, 0, 1], "points_per_10m_out": [2, 0, 2, 0, 0],
                      "mean_snr_in_db": 25.0, "mean_snr_out_db": 23.5, "mean_snr_change_db": -1.5}
    assert [list(m) for m in (step1, step2, output)] == [list(m) for m in one_by_one(clouds, outputs)]
    assert repr([step1, step2, output]) == repr(one_by_one(clouds, outputs))


@pytest.mark.parametrize("seed", range(40))
def test_a_held_radar_chain_gives_the_per_step_metrics(seed):
    """Random chains (removals, moves, additions, value-only steps, an alignment first; NaN SNRs, no-return points,
    clouds without SNR): every step's metrics, the output's and those of a pair inside the chain, bit for bit."""
    rng = np.random.default_rng(300 + seed)
    clouds = [random_list(rng, int(rng.integers(1, 90)), "radar", ring=False)]
    if seed % 3 == 0:
        clouds[0].fields["snr_db"][rng.random(len(clouds[0])) < 0.2] = np.nan
    if seed % 4 == 1:
        clouds[0].positions_m[: len(clouds[0]) // 5] = 0.0
    if seed % 7 == 3:
        del clouds[0].fields["snr_db"]                                  # no values: no mean, no change
    outputs = []
    chain = ["alignment"] * (seed % 5 == 2) + list(rng.choice(list(STEPS)[:-1], size=int(rng.integers(1, 5))))
    if seed % 7 == 3:
        chain = [name for name in chain if name not in ("gain", "weather", "add", "drop", "move")] or ["alignment"]
    for i, name in enumerate(chain):
        outputs.append(STEPS[name](step_input(clouds[-1]), rng))
        clouds.append(follow_points(clouds[-1], outputs[-1], i))
    pairs = ((0, len(clouds) - 1),) + (((1, len(clouds) - 1),) if len(clouds) > 3 else ())
    got = held(clouds, outputs, pairs)
    assert repr(got) == repr(one_by_one(clouds, outputs, pairs))
    assert all("mean_snr_change_db" in m for m in got)


def test_calls_that_are_no_chain_are_compared_one_by_one():
    """A held call whose clouds do not follow each other (or with object ids) is compared by :func:`compare`."""
    clouds, outputs = hand_chain()
    other = dataclasses.replace(clouds[0])
    want = one_by_one(clouds, outputs) + [compare(dataclasses.replace(clouds[2]), dataclasses.replace(other))]
    deferred = Deferred(radar_chains=True)
    got = [deferred.compare(clouds[0], clouds[1], outputs[0]), deferred.compare(clouds[1], clouds[2], outputs[1]),
           deferred.compare(clouds[0], clouds[2]), deferred.compare(clouds[2], other)]
    deferred.settle()
    assert repr(got) == repr(want)
    with_ids = [c.with_fields(object_id=np.arange(len(c))) for c in hand_chain()[0]]
    deferred = Deferred(radar_chains=True)
    got = deferred.compare(with_ids[0], with_ids[1], outputs[0])
    deferred.settle()
    assert got["objects"] == compare(dataclasses.replace(with_ids[0]), dataclasses.replace(with_ids[1]),
                                     outputs[0])["objects"]


def test_settle_clouds_fills_a_held_chain_before_the_writer():
    """The runner settles a radar chain's calls before writing (``settle_clouds``), so that the line of a failed
    write keeps its metrics; a second call finds nothing held."""
    clouds, outputs = hand_chain()
    deferred = Deferred(radar_chains=True)
    got = [deferred.compare(clouds[0], clouds[1], outputs[0]), deferred.compare(clouds[1], clouds[2], outputs[1]),
           deferred.compare(clouds[0], clouds[2])]
    deferred.settle_clouds()
    assert repr(got) == repr(one_by_one(clouds, outputs))
    deferred.settle_clouds()                       # nothing held: nothing changes
    assert repr(got) == repr(one_by_one(clouds, outputs))
