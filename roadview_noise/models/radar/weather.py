"""Shared logic of the radar weather models (models.md §4.1, §4.3): two-way attenuation, detection loss and
precipitation clutter. ``rain.radar``, ``fog.radar`` and ``snow.radar`` only say how γ and the particles follow
from their parameters."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Stage, param
from ...physics.radar_clutter import (SCATTERING, Hydrometeors, ResolutionGrid, backscatter_per_volume_per_m,
                                      clutter_cells, generate_clutter, radar_wavelength_m)
from ...physics.radar_link import detection_range_in_weather_m, two_way_loss_db
from ...types import PointCloud, PointLabel, RadarProfile
from .detection import (RCS_STATISTIC, Detection, detection, labels, mark, power_minus_snr_db, profile_of,
                        radar_constant_db, with_loss)


# Below this rate there is no measurable precipitation (and the exponential DSD laws, fitted from ~1 mm/h, lose
# meaning): no clutter is generated.
MIN_PRECIPITATION_RATE_MM_PER_H = 1e-3


@dataclass(frozen=True)
class RadarWeather(Model):
    """Attenuation and detection loss: ``L = 2 γ R/1000`` dB per point, ``SNR' = SNR − L``, ``P' = P − L``,
    ``RCS' = RCS − L`` (unless the profile says the radar compensates), points with ``D − L < t`` removed
    (models.md §4.1 [PROP]; detection statistic and threshold: models/radar/detection.py). Labels: ATTENUATED
    where L > 0, else unchanged (KEPT in a new uint8 ``label`` field)."""

    stage: ClassVar[Stage] = Stage.MEDIUM
    sensor: ClassVar[str] = "radar"

    snr_threshold_quantile: float = param(0.0, doc="quantile of the frame's clear detection statistic used as the "
                                          "threshold when the profile gives none (0: the weakest detection)",
                                          ge=0, le=0.05)

    def gamma_db_per_km(self, profile: RadarProfile) -> float:
        """Specific attenuation at the radar frequency."""
        raise NotImplementedError

    def add_clutter(self, cloud: PointCloud, clear: PointCloud, ranges_m: np.ndarray, det: Detection, gamma: float,
                    rng) -> tuple[PointCloud, dict]:
        """Precipitation models add clutter points to ``cloud``, calibrated on the ``clear`` input; fog adds none
        (backscatter ∝ D⁶ of 10 µm droplets is negligible)."""
        return cloud, {}

    def apply(self, data: PointCloud, *, state, drawn, rng):
        profile = profile_of(data)
        gamma = self.gamma_db_per_km(profile)
        r = data.ranges_m
        det = detection(data, self.snr_threshold_quantile, self.id, r)
        loss = two_way_loss_db(gamma, r)
        keep = det.values_db - loss >= det.threshold_db
        label = mark(labels(data), loss > 0, PointLabel.ATTENUATED)
        out = with_loss(data, loss).with_fields(label=label).drop(~keep)
        out, clutter_diag = self.add_clutter(out, data, r, det, gamma, rng)
        diagnostics = {
            "specific_attenuation_db_per_km": float(gamma),
            "points_in": len(data), "points_removed": int((~keep).sum()), "points_kept": int(keep.sum()),
            "mean_loss_db": float(loss.mean()) if len(loss) else 0.0,
            "max_range_clear_m": float(r.max()) if len(r) else 0.0,
            "max_range_m": float(r[keep].max()) if keep.any() else 0.0,
            "profile_max_range_in_weather_m": detection_range_in_weather_m(profile.max_range_m, gamma),
            **det.diagnostics(), **clutter_diag,
        }
        return out, diagnostics


@dataclass(frozen=True)
class PrecipitationRadar(RadarWeather):
    """Adds precipitation clutter (models.md §4.3 [PROP], physics/radar_clutter.py): per resolution cell
    (range bin × the profile's azimuth/elevation cells × Doppler bin) up to ``clutter_max_range_m``, mean RCS
    ``η V P(v)`` with the Doppler spread of falling particles seen by the moving radar in the wind
    (``cloud.conditions``), detected when ``C + 10 log10 σ − 40 log10 r − L ≥ t`` with the frame's radar constant C
    and threshold t. Added points: label ADDED, RCS/SNR/power consistent with C, ``v_r``, and ``v_r_comp = v_r +
    v_ego·r̂`` when the cloud has it; other fields zero. Needs an ``rcs_dbsm`` field to calibrate C (else no
    clutter, reported in the diagnostics).

    The detector is a fixed threshold (models.md §4.3), so the clutter count rises steeply with C − t: rain 20 mm/h,
    120° × 30° at 1° × 2°, Mie: about 100 points for C − t = 68 dB, 6 700 for 76 dB, 43 000 for 83 dB, within a few
    metres. A radar's CFAR raises its threshold inside homogeneous clutter and shows far fewer; use ``clutter:
    false`` or a smaller ``clutter_max_range_m`` when that matters."""

    clutter: bool = param(True, doc="add precipitation clutter points near the sensor")
    clutter_min_range_m: float = param(1.0, unit="m", doc="nearest clutter range (radar blind zone)", gt=0)
    clutter_max_range_m: float = param(20.0, unit="m", doc="farthest range searched for clutter (models.md §4.3)",
                                       gt=0)
    doppler_resolution_m_per_s: float = param(0.1035, unit="m/s", doc="Doppler bin width (RISE: 512 bins over "
                                              "±26.5 m/s)", gt=0)
    backscatter: str = param("mie", doc="particle backscatter: mie (accurate) or analytic (RISE Rayleigh/optical "
                             "approximation, 13 % lower for rain)", choices=SCATTERING)

    def validate(self) -> None:
        if self.clutter_max_range_m <= self.clutter_min_range_m:
            raise ModelError("must exceed clutter_min_range_m", model=self.id, field="clutter_max_range_m")

    def hydrometeors(self, profile: RadarProfile) -> Hydrometeors | None:
        """The falling particles, None when there are none (zero rate)."""
        raise NotImplementedError

    def add_clutter(self, cloud, clear, ranges_m, det, gamma, rng):
        profile = profile_of(cloud)
        h = self.hydrometeors(profile)
        if not self.clutter or h is None:
            return cloud, {"clutter_points": 0}
        constant = radar_constant_db(clear, det, ranges_m)
        max_range_m = min(self.clutter_max_range_m, profile.max_range_m)
        skipped = ("no rcs_dbsm to calibrate the radar constant" if constant is None else
                   "no points to estimate the threshold" if not np.isfinite(det.threshold_db) else
                   "clutter_min_range_m beyond the profile's max_range_m"
                   if max_range_m < self.clutter_min_range_m + profile.range_resolution_m else None)
        if skipped:
            return cloud, {"clutter_points": 0, "clutter_skipped": skipped}
        grid = ResolutionGrid(profile.fov_azimuth_deg, profile.fov_elevation_deg, profile.azimuth_resolution_deg,
                              profile.elevation_resolution_deg, profile.range_resolution_m,
                              self.doppler_resolution_m_per_s, self.clutter_min_range_m, max_range_m)
        lam = radar_wavelength_m(profile.frequency_hz)
        ego = np.asarray(cloud.conditions.ego_velocity_m_per_s, dtype=float)
        wind = np.asarray(cloud.conditions.wind_velocity_m_per_s, dtype=float)
        cells = clutter_cells(h, grid, lam, wind - ego, constant, det.threshold_db, gamma)
        pts = generate_clutter(rng, cells)
        r = np.linalg.norm(pts.positions_m, axis=1)
        rcs = pts.detection_db - constant + 40 * np.log10(r)
        if profile.rcs_compensates_weather:
            rcs = rcs + two_way_loss_db(gamma, r)
        new = {"rcs_dbsm": rcs, "v_r_m_per_s": pts.v_r_m_per_s,
               "label": np.full(len(r), PointLabel.ADDED),
               "v_r_comp_m_per_s": pts.v_r_m_per_s + pts.positions_m @ ego / np.maximum(r, 1e-12)}
        if det.statistic != RCS_STATISTIC:
            new[det.statistic] = pts.detection_db
            offset = power_minus_snr_db(clear)
            if offset is not None:
                new["power_db"] = pts.detection_db + offset
        new = {k: v for k, v in new.items() if k in cloud.fields}
        out = cloud.concat(pts.positions_m, new)
        return out, {"clutter_points": len(r), "clutter_expected_points": cells.expected_count,
                     "clutter_backscatter_per_m": backscatter_per_volume_per_m(h, lam), "radar_constant_db": constant}
