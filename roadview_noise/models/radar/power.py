"""Radar received-power error: per-point noise on the power-derived fields (models.md §4.5 [PROP])."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ...model import Model, Stage, param
from ...registry import register
from ...types import PointCloud

POWER_FIELDS = ("snr_db", "power_db", "rcs_dbsm")


@register
@dataclass(frozen=True)
class PowerRadar(Model):
    """Per-point received-power error ``ΔP ~ N(0, power_sd_db)`` dB (models.md §4.5 [PROP]; D3.5 gives no
    parameters, default 0: identity), added alike to ``snr_db``, ``power_db`` and ``rcs_dbsm`` (the radar derives
    RCS from the received power).

    Stage ELECTRONICS (models.md §1: the radar chain ends in detection): a per-point error is a measurement error
    of each detection's power estimate in the receiver, not a transmit-power change (which would be common to all
    points of a frame), so it acts after the weather, whose threshold estimate then sees the clean powers. Points are
    not re-thresholded: the input holds only detections, so removing those pushed below the threshold without
    adding the undetected ones pushed above it would bias the cloud."""

    id: ClassVar[str] = "power.radar"
    stage: ClassVar[Stage] = Stage.ELECTRONICS
    sensor: ClassVar[str] = "radar"
    summary: ClassVar[str] = "per-point received-power error N(0, σ_P) dB on SNR, power and RCS (default 0)"

    power_sd_db: float = param(0.0, unit="dB", doc="standard deviation of the per-point power error", ge=0)

    def apply(self, data: PointCloud, *, state, drawn, rng):
        present = [name for name in POWER_FIELDS if name in data.fields]
        if self.power_sd_db == 0 or not present:
            return data, {"points": len(data), "fields": present, "rms_error_db": 0.0}
        delta = rng.normal(0.0, self.power_sd_db, len(data))
        out = data.with_fields(**{n: (data.fields[n] + delta).astype(data.fields[n].dtype, copy=False)
                                  for n in present})
        return out, {"points": len(data), "fields": present,
                     "rms_error_db": float(np.sqrt(np.mean(delta ** 2))) if len(delta) else 0.0}
