"""Laser power variance: per-beam intensity gain and bias plus intensity noise (models.md §3.7; D3.5 ch. 4, §5.2.2;
CNF22–24, Eq. 1).

The D3.5 model maps a target reflectance x (%) to the 8-bit intensity y (counts) of a VLS-128,
``y = g_i·x + b_i``; an ideal sensor of that kind reads x counts for an x % diffuse target (gain 1, bias 0), and
retro-reflectors up to 255. Input intensities are brought to this domain by matching full scales — x = I·255/F
with F = ``profile.intensity_full_scale`` (uint8: 1 count per unit, unit [0, 1]: 255, photons: 255/65535) — and
converted back with the same factor, clipped to [0, F] and rounded when the profile's unit is uint8 (8-bit sensor).
The profile is the one the weather models read the intensities with: when nothing states the unit, the chain's
input decides it (8-bit reflectivity read from the data; a [0, 1] cloud refused), with a warning
(:func:`~roadview_noise.physics.lidar_intensity.chain_intensity_scale`). For photon counts this is a full-scale
convention, not a calibration: give the profile whose intensity unit matches the recorded field (Ouster
*reflectivity* is uint8). No-return points (zero position) keep intensity 0.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Scope, Stage, param
from ...physics.lidar_geometry import has_return, with_ring
from ...physics.lidar_intensity import IntensityWarning, chain_intensity_scale, reflectivity_following
from ...registry import register
from ...types import IntensityUnit, LidarProfile, PointCloud

COUNT_FULL_SCALE = 255.0  # full scale of the model's domain: the VLS-128 8-bit intensity


def _channels(model_id: str, cloud: PointCloud) -> int:
    if cloud.profile is None:
        raise ModelError("needs the LiDAR profile (beam table, intensity unit) of the cloud", model=model_id)
    return cloud.profile.channels


@dataclass(frozen=True)
class _Counts:
    """The returns' intensities in model counts, their mask, the counts per stored unit and the profile read with."""

    counts: np.ndarray
    hit: np.ndarray
    scale: float
    profile: LidarProfile


def _intensity_counts(model_id: str, cloud: PointCloud) -> _Counts:
    """The returns' intensities in model counts, read in the unit the chain's input decides
    (:func:`lidar_intensity.chain_intensity_scale`, as the weather models read it; its warning printed)."""
    _channels(model_id, cloud)
    if "intensity" not in cloud.fields:
        raise ModelError(f"needs an intensity field (cloud has {sorted(cloud.fields)})", model=model_id)
    read = chain_intensity_scale(cloud, model_id)
    if read.warning:
        warnings.warn(read.warning, IntensityWarning, stacklevel=3)
    hit = has_return(cloud.positions_m, cloud)      # noting its geometry for the metrics
    scale = COUNT_FULL_SCALE / read.profile.intensity_full_scale
    return _Counts(cloud.fields["intensity"][hit].astype(np.float64) * scale, hit, scale, read.profile)


def _with_intensity_counts(cloud: PointCloud, counts: np.ndarray, read: _Counts) -> tuple[PointCloud, dict]:
    """The cloud with the returns' intensity set from model counts (clipped, converted, rounded for uint8)."""
    hit, scale = read.hit, read.scale
    clipped = np.clip(counts, 0.0, COUNT_FULL_SCALE)
    values = clipped / scale
    field = cloud.fields["intensity"]
    if read.profile.intensity_unit == IntensityUnit.UINT8 or np.issubdtype(field.dtype, np.integer):
        values = np.rint(values)
    out = field.copy()
    out[hit] = values.astype(field.dtype)
    before = field[hit].astype(np.float64)
    n = int(hit.sum())
    rows = np.flatnonzero(hit)
    return cloud.with_fields(intensity=out, **reflectivity_following(cloud.fields, rows, field[rows], out[rows])), {
        "points": n,
        "mean_intensity_in": float(before.mean()) if n else 0.0,
        "mean_intensity_out": float(out[hit].astype(np.float64).mean()) if n else 0.0,
        "clipped_fraction": float(np.mean(clipped != counts)) if n else 0.0,
    }


def _electronics(counts: np.ndarray, bias_counts: np.ndarray, noise_sd_factor: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Receiver bias plus zero-mean noise of standard deviation ``noise_sd_factor·|y|`` (models.md §3.7 step 3)."""
    y = counts + bias_counts
    return y + noise_sd_factor * np.abs(y) * rng.standard_normal(len(y))


@dataclass(frozen=True)
class _ElectronicsParams(Model):
    """Receiver electronics parameters shared by ``power.lidar`` and ``power_electronics.lidar``."""

    bias_mean_counts: float = param(4.67, unit="count", doc="mean of the per-beam intensity bias (D3.5)")
    bias_sd_counts: float = param(2.64, unit="count", doc="beam-to-beam SD of the intensity bias (D3.5)", ge=0)
    noise_sd_factor: float = param(0.14, doc="per-point noise SD as a fraction of the intensity (D3.5: 0.14, "
                                   "which double counts the beam-to-beam spread; 0.118 reproduces the measured "
                                   "13.69 SD of the 80 % plate, models.md §3.7)", ge=0)


@register
@dataclass(frozen=True)
class PowerLidar(_ElectronicsParams):
    """Laser power variance of a spinning LiDAR (models.md §3.7; measured on a VLS-128, D3.5 ch. 4).

    Mode ``fgi`` (default, D3.5 ch. 4): per sensor instance, each beam i gets ``g_i ~ N(1.17, 0.084)`` and
    ``b_i ~ N(4.67, 2.64)`` counts; every return becomes ``y = g_i·x + b_i`` plus noise ``N(0, (0.14·y)²)``. With
    mean parameters x = 10/20/40/80 % gives 16.37/28.07/51.47/98.27 (D3.5 measured 12.14/28.77/57.13/94.66).
    Mode ``additive`` (D3.5 §5.2.2): ``y = x + N(0, 5²)``, no per-beam state.
    ``split_electronics`` [PROP, models.md §3.7]: apply only the gain here, before the weather (emitter power and
    responsivity scale particle returns too), and the bias and noise with ``power_electronics.lidar`` after it.
    The weather models derive their scale from the intensity, so the gain also scales particle returns — the
    intended Eq. 1 coupling. Units and scales: see the module docstring."""

    id: ClassVar[str] = "power.lidar"
    stage: ClassVar[Stage] = Stage.EMITTER
    scope: ClassVar[Scope] = Scope.SEQUENCE
    sensor: ClassVar[str] = "lidar"
    summary: ClassVar[str] = "per-beam intensity gain N(1.17, 0.084) and bias N(4.67, 2.64) + 0.14·I noise"

    mode: str = param("fgi", doc="fgi: per-beam gain/bias + proportional noise (D3.5 ch. 4); additive: N(0, 5²) "
                      "(D3.5 §5.2.2)", choices=("fgi", "additive"))
    gain_mean: float = param(1.17, unit="count/%", doc="mean of the per-beam gain (D3.5)", ge=0)
    gain_sd: float = param(0.084, unit="count/%", doc="beam-to-beam SD of the gain (D3.5)", ge=0)
    additive_sd_counts: float = param(5.0, unit="count", doc="SD of the additive mode's noise (D3.5 §5.2.2)", ge=0)
    split_electronics: bool = param(False, doc="apply only the gain here; bias and noise come from "
                                    "power_electronics.lidar after the weather [PROP]")

    def validate(self) -> None:
        if self.split_electronics and self.mode != "fgi":
            raise ModelError("split_electronics needs mode fgi", model=self.id, field="split_electronics")

    def draw_sequence(self, rng, data):
        if self.mode != "fgi":
            return {}
        n = _channels(self.id, data)
        state = {"gain": rng.normal(self.gain_mean, self.gain_sd, n).tolist()}
        if not self.split_electronics:
            state["bias_counts"] = rng.normal(self.bias_mean_counts, self.bias_sd_counts, n).tolist()
        return state

    def apply(self, data, *, state, drawn, rng):
        read = _intensity_counts(self.id, data)
        x = read.counts
        if self.mode == "additive":
            return _with_intensity_counts(data, x + rng.normal(0.0, self.additive_sd_counts, len(x)), read)
        data, ring = _beam_of_returns(self.id, data, read.hit, len(state["gain"]))
        gain = np.asarray(state["gain"])[ring]
        y = gain * x
        if not self.split_electronics:
            y = _electronics(y, np.asarray(state["bias_counts"])[ring], self.noise_sd_factor, rng)
        out, diagnostics = _with_intensity_counts(data, y, read)
        diagnostics["mean_gain"] = float(gain.mean()) if len(gain) else 0.0
        return out, diagnostics


@register
@dataclass(frozen=True)
class PowerElectronicsLidar(_ElectronicsParams):
    """Receiver half of the laser power model (models.md §3.7 [PROP] ``split_electronics``).

    Per sensor instance each beam gets a bias ``b_i ~ N(4.67, 2.64)`` counts; every return, target or weather
    particle, becomes ``y = x + b_i`` plus noise ``N(0, (0.14·y)²)``. Use after the weather together with
    ``power.lidar`` with ``split_electronics: true`` (which applies the gain before it); the two together equal
    D3.5's model except that particle returns also receive bias and noise."""

    id: ClassVar[str] = "power_electronics.lidar"
    stage: ClassVar[Stage] = Stage.ELECTRONICS
    scope: ClassVar[Scope] = Scope.SEQUENCE
    sensor: ClassVar[str] = "lidar"
    summary: ClassVar[str] = "per-beam intensity bias + 0.14·I noise after the weather (pair of power.lidar split)"

    def draw_sequence(self, rng, data):
        n = _channels(self.id, data)
        return {"bias_counts": rng.normal(self.bias_mean_counts, self.bias_sd_counts, n).tolist()}

    def apply(self, data, *, state, drawn, rng):
        read = _intensity_counts(self.id, data)
        data, ring = _beam_of_returns(self.id, data, read.hit, len(state["bias_counts"]))
        y = _electronics(read.counts, np.asarray(state["bias_counts"])[ring], self.noise_sd_factor, rng)
        return _with_intensity_counts(data, y, read)


def _beam_of_returns(model_id: str, cloud: PointCloud, hit: np.ndarray,
                     n_state: int) -> tuple[PointCloud, np.ndarray]:
    """(the cloud carrying its rings, :func:`lidar_geometry.with_ring`; the ring of every return), checked against
    the number of beams in the sensor-instance state."""
    if n_state != _channels(model_id, cloud):
        raise ModelError(f"state has {n_state} beams, profile {cloud.profile.name!r} {cloud.profile.channels}",
                         model=model_id, field="state")
    cloud, ring = with_ring(cloud)
    return cloud, ring[hit]
