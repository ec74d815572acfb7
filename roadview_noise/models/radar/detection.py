"""Detection of radar points: the detection statistic, its threshold, the radar constant and losses
(models.md §4.1 steps 2–3, §4.3 step 1). Shared by the radar weather and obstruction models.

Detection statistic D (dB), in order of preference:

- ``snr_db`` when the cloud has it;
- else ``power_db`` (SNR up to the constant receiver noise floor);
- else ``rcs_dbsm − 40 log10 r`` (SNR up to the radar constant, radar equation ``SNR = C_r σ / r⁴``) — e.g.
  View-of-Delft, whose files carry RCS but neither SNR nor power.

A loss L (dB) lowers D, SNR and power by L, and the reported RCS by L unless ``profile.rcs_compensates_weather``.

Threshold t: ``profile.snr_threshold_db`` for SNR; ``snr_threshold_db + noise floor`` (−174 dBm/Hz + 10 log10 B +
NF) for power when ``profile.power_unit`` is ``dBm``; otherwise — relative power, whose noise floor is unknown, and
always the RCS statistic, whose radar constant is unknown — the ``q`` quantile of the frame's own D before the model
acts (q = 0: the weakest detection). Frames are processed independently by parallel workers, so a "per sequence"
estimate (models.md §4.1 step 3) would need a pass over the whole sequence first, and a SEQUENCE-scope
``draw_sequence`` sees only the current frame, so it would differ between frames as well. The per-frame estimate is
deterministic per frame and, with q = 0, makes zero loss the identity (every input point has D ≥ t). It is an upper
bound of the true threshold (slight over-removal, and it varies a little from frame to frame); give
``snr_threshold_db`` in the profile for a fixed one.

Radar constant (dB) for synthetic echoes: ``C = median(D − rcs_dbsm + 40 log10 r)`` over points with RCS, so that
``D = C + 10 log10 σ − 40 log10 r`` (0 for the RCS statistic); unknown without an RCS field.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import ModelError
from ...physics.compiled import jit
from ...physics.radar_link import noise_floor_dbm
from ...profiles.radar import default_radar_profile
from ...types import PointCloud, RadarProfile

RCS_STATISTIC = "rcs_dbsm-40log10(r)"


def profile_of(cloud: PointCloud) -> RadarProfile:
    return cloud.profile if isinstance(cloud.profile, RadarProfile) else default_radar_profile()


@dataclass(frozen=True)
class Detection:
    """Detection statistic of every point of a cloud and the threshold that a point must reach."""

    statistic: str                 # "snr_db" | "power_db" | RCS_STATISTIC
    values_db: np.ndarray
    threshold_db: float
    threshold_source: str          # "profile" | "frame quantile q"

    def diagnostics(self) -> dict:
        return {"detection_statistic": self.statistic, "threshold_db": float(self.threshold_db),
                "threshold_source": self.threshold_source}


def detection(cloud: PointCloud, quantile: float, model_id: str, ranges_m: np.ndarray | None = None) -> Detection:
    """The detection statistic and threshold of ``cloud`` (see the module docstring); ``ranges_m`` if known."""
    fields = cloud.fields
    r = cloud.ranges_m if ranges_m is None else ranges_m
    if "snr_db" in fields:
        name, values = "snr_db", np.asarray(fields["snr_db"], dtype=float)
    elif "power_db" in fields:
        name, values = "power_db", np.asarray(fields["power_db"], dtype=float)
    elif "rcs_dbsm" in fields:
        name, values = RCS_STATISTIC, np.asarray(fields["rcs_dbsm"], dtype=float) - _log_r4(r)
    else:
        raise ModelError("a radar cloud needs snr_db, power_db or rcs_dbsm to decide detection "
                         f"(has {sorted(fields)}); name the file field that holds one in the recipe's field_map "
                         "(inputs: {radar: …, field_map: {FILE_FIELD: snr_db}}), e.g. {intensity: snr_db} for "
                         "ti_mmwave_rospkg clouds, whose intensity is the detection SNR in dB", model=model_id)
    profile = profile_of(cloud)
    if profile.snr_threshold_db is not None and (name == "snr_db" or
                                                 (name == "power_db" and profile.power_unit == "dBm")):
        threshold = profile.snr_threshold_db
        if name == "power_db":
            threshold += noise_floor_dbm(profile.if_bandwidth_hz, profile.noise_figure_db)
        source = "profile"
    else:
        finite = values[np.isfinite(values)]
        threshold = float(np.quantile(finite, quantile)) if len(finite) else np.inf
        source = f"frame quantile {quantile:g}"
    return Detection(name, values, float(threshold), source)


def _log_r4(r: np.ndarray) -> np.ndarray:
    """``40 log10 r`` (NaN where r = 0)."""
    if len(r) and r.min() > 0:           # every point at a range (the usual frame): no mask, no np.errstate (≈ 4 µs)
        return 40 * np.log10(r)
    with np.errstate(divide="ignore"):
        return 40 * np.log10(np.where(r > 0, r, np.nan))


def radar_constant_db(cloud: PointCloud, det: Detection, ranges_m: np.ndarray) -> float | None:
    """``C = median(D − rcs_dbsm + 40 log10 r)`` over the points with RCS (None without an RCS field)."""
    if "rcs_dbsm" not in cloud.fields:
        return None
    c = _median_of_finite(det.values_db, cloud.fields["rcs_dbsm"], _log_r4(ranges_m))
    return None if c != c else c


@jit
def _median_of_finite(values_db, rcs_dbsm, log_r4):
    """``np.median`` of the finite ``D − σ + 40 log10 r``, bit for bit but for the sign of a zero median (the
    middle value, or the two middle ones' sum over 2); NaN when none is finite."""
    c = np.empty(len(values_db))
    n = 0
    for i in range(len(values_db)):
        v = values_db[i] - np.float64(rcs_dbsm[i]) + log_r4[i]
        if np.isfinite(v):
            c[n] = v
            n += 1
    if n == 0:
        return np.nan
    s = np.sort(c[:n])
    return s[n // 2] if n % 2 else (s[n // 2 - 1] + s[n // 2]) / 2


def power_minus_snr_db(cloud: PointCloud) -> float | None:
    """Median ``power_db − snr_db`` (the noise floor in the power unit) when the cloud has both."""
    if "snr_db" not in cloud.fields or "power_db" not in cloud.fields or not len(cloud):
        return None
    return float(np.median(np.asarray(cloud.fields["power_db"], dtype=float) - cloud.fields["snr_db"]))


def with_loss(cloud: PointCloud, loss_db: np.ndarray) -> PointCloud:
    """Lower SNR and power by ``loss_db`` per point, and RCS unless the radar compensates weather losses."""
    out = {name: lowered(cloud.fields[name], loss_db) for name in lossy_fields(cloud)}
    return cloud.with_fields(**out) if out else cloud


def lossy_fields(cloud: PointCloud) -> list[str]:
    """The fields of ``cloud`` that a loss lowers (:func:`with_loss`)."""
    names = ["snr_db", "power_db"] if profile_of(cloud).rcs_compensates_weather else ["snr_db", "power_db", "rcs_dbsm"]
    return [name for name in names if name in cloud.fields]


def lowered(values: np.ndarray, loss_db: np.ndarray) -> np.ndarray:
    return (values - loss_db).astype(values.dtype, copy=False)
