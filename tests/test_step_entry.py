"""A step's manifest dict (``StepRecord.as_entry``) is what ``dataclasses.asdict`` gives, without its deep copy."""

from __future__ import annotations

import dataclasses

import numpy as np

from roadview_noise.compound import StepRecord
from roadview_noise.manifest import dumps


@dataclasses.dataclass
class _Inner:
    a: float
    b: tuple


def test_as_entry_equals_asdict_for_nested_values_and_encodes_alike():
    r = StepRecord("fog.radar", {"visibility_m": 30.0, "pair": (1, 2), "inner": _Inner(1.5, (np.float32(2), "x"))},
                   state={"gains": [0.5, {"deep": _Inner(0.0, ())}]}, drawn={"n": np.int64(3), "none": None},
                   diagnostics={"arr": np.arange(3)}, seconds=0.25, metrics={"points_in": 10})
    entry, copied = r.as_entry(), dataclasses.asdict(r)
    assert list(entry) == list(copied)
    assert dumps(entry) == dumps(copied)
    assert entry["params"]["inner"] == {"a": 1.5, "b": (np.float32(2), "x")}
    assert entry["metrics"] is r.metrics
