"""Shared logic of the radar weather models (models.md §4.1, §4.3): two-way attenuation, detection loss and
precipitation clutter. ``rain.radar``, ``fog.radar`` and ``snow.radar`` only say how γ and the particles follow
from their parameters."""

from __future__ import annotations

import math
from abc import abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Stage, param
from ...physics.compiled import jit
from ...physics.numpy_sums import numpy_sum
from ...physics.radar_cfar import CaCfar, FixedThreshold
from ...physics.radar_clutter import (SCATTERING, ClutterCells, ClutterTables, Hydrometeors, ResolutionGrid,
                                      clutter_tables, frame_cells, generate_clutter, radar_wavelength_m)
from ...io.radar_formats import added_detection_fields
from ...physics.radar_frame import (ego_velocity_m_per_s, grid_profile, is_planar, new_point_velocity_fields,
                                    point_ranges_m, radial_velocity_m_per_s, to_plane)
from ...physics.radar_link import detection_range_in_weather_m, two_way_loss_db
from ...provenance import ATTENUATED, KEPT, Effect, mark
from ...types import PointCloud, RadarProfile
from .detection import (RCS_STATISTIC, Detection, detection, lossy_fields, lowered, power_minus_snr_db, profile_of,
                        radar_constant_db, with_loss)


# Below this rate there is no measurable precipitation (and the exponential DSD laws, fitted from ~1 mm/h, lose
# meaning): no clutter is generated.
MIN_PRECIPITATION_RATE_MM_PER_H = 1e-3


@dataclass(frozen=True)
class RadarWeather(Model):
    """Attenuation and detection loss: ``L = 2 γ R/1000`` dB per point, ``SNR' = SNR − L``, ``P' = P − L``,
    ``RCS' = RCS − L`` (unless the profile says the radar compensates), points with ``D − L < t + ΔT`` removed
    (models.md §4.1 [PROP]; detection statistic and threshold: models/radar/detection.py; ΔT the CFAR threshold rise
    in precipitation clutter, 0 without clutter). Effect (provenance.Effect): ATTENUATED where L > 0, else
    KEPT. 2-D radars, Cartesian velocity fields and the ego velocity: physics/radar_frame.py."""

    stage: ClassVar[Stage] = Stage.MEDIUM
    sensor: ClassVar[str] = "radar"

    snr_threshold_quantile: float = param(0.0, doc="quantile of the frame's clear detection statistic used as the "
                                          "threshold when the profile gives none (0: the weakest detection)",
                                          ge=0, le=0.05)

    @abstractmethod
    def gamma_db_per_km(self, profile: RadarProfile) -> float:
        """Specific attenuation at the radar frequency."""

    def frame_clutter(self, data: PointCloud, ranges_m: np.ndarray, det: Detection, gamma: float,
                      ego_m_per_s: np.ndarray, planar: bool) -> tuple[ClutterCells | None, np.ndarray, dict]:
        """The precipitation clutter of the frame, the rise of each point's detection threshold in it (dB) and its
        diagnostics; fog has none (backscatter ∝ D⁶ of 10 µm droplets is negligible)."""
        return None, np.zeros(len(ranges_m)), {}

    def apply(self, data: PointCloud, *, state, drawn, rng):
        profile = profile_of(data)
        gamma, range_in_weather_m = per_profile(self, profile, False, _attenuation)
        r = point_ranges_m(data)
        n = len(r)
        det = detection(data, self.snr_threshold_quantile, self.id, r)
        loss = two_way_loss_db(gamma, r)
        planar = is_planar(data, profile)
        ego, ego_source = ego_velocity_m_per_s(data, planar)
        cells, rise, clutter_diag = self.frame_clutter(data, r, det, gamma, ego, planar)
        removed, attenuated = np.empty(n, dtype=bool), np.empty(n, dtype=bool)
        kept, loss_sum, r_max, r_kept_max, cfar_lost, rise_max, rise_sum = _detection_summary(
            det.values_db, loss, det.threshold_db, rise, r, removed, attenuated)
        out = _attenuate_and_drop(data, loss, attenuated, removed)
        diagnostics = {
            "specific_attenuation_db_per_km": float(gamma),
            "points_in": n, "points_removed": n - kept, "points_kept": kept,
            "mean_loss_db": loss_sum / n if n else 0.0,     # np.mean's value, less Python
            "max_range_clear_m": r_max, "max_range_m": r_kept_max,
            "profile_max_range_in_weather_m": range_in_weather_m,
            **det.diagnostics(), **clutter_diag,
        }
        if cells is not None:
            diagnostics.update({"ego_velocity_m_per_s": ego.tolist(), "ego_velocity_source": ego_source,
                                "elevation_measured": not planar})
            out, added = _add_clutter(out, data, det, cells, rng, ego, planar)
            diagnostics.update(added)
            if isinstance(cells.detector, CaCfar):
                diagnostics.update({"cfar_points_lost": cfar_lost, "cfar_max_threshold_rise_db": rise_max,
                                    "cfar_mean_threshold_rise_db": rise_sum / n if n else 0.0})
        return out, diagnostics


def _attenuate_and_drop(cloud: PointCloud, loss_db: np.ndarray, attenuated: np.ndarray,
                        removed: np.ndarray) -> PointCloud:
    """``mark(with_loss(cloud, loss_db), attenuated, Effect.ATTENUATED).drop(removed)``, for a point list without
    provenance or attributes yet (a radar file's cloud) in one copy of the kept points instead of three clouds."""
    if cloud.grid_shape is not None or cloud.origin is not None or cloud.effect is not None or cloud.attributes:
        return mark(with_loss(cloud, loss_db), attenuated, Effect.ATTENUATED).drop(removed)
    kept = np.flatnonzero(~removed)
    fields = {name: np.take(v, kept) for name, v in cloud.fields.items()}
    loss_kept = np.take(loss_db, kept)
    fields.update({name: lowered(fields[name], loss_kept) for name in lossy_fields(cloud)})
    return cloud.replace(positions_m=np.take(cloud.positions_m, kept, axis=0), fields=fields, origin=kept,
                         effect=np.where(np.take(attenuated, kept), ATTENUATED, KEPT))


@jit
def _detection_summary(values_db, loss_db, threshold_db, rise_db, ranges_m, removed, attenuated):
    """Per point: removed unless ``D − L − t ≥ rise``, attenuated where L > 0; and the frame's kept count, ΣL,
    largest range, largest kept range, CFAR points lost (``D − L ≥ t`` but removed), largest rise and Σ rise — NumPy's
    sums and maxima (NaN kept) bit for bit, 0 for a maximum over no points."""
    kept = lost = 0
    r_max = r_kept_max = rise_max = 0.0
    for i in range(len(values_db)):
        margin = values_db[i] - loss_db[i] - threshold_db
        keep = margin >= rise_db[i]
        removed[i], attenuated[i] = not keep, loss_db[i] > 0
        r_max = ranges_m[i] if i == 0 else _nan_max(r_max, ranges_m[i])
        rise_max = rise_db[i] if i == 0 else _nan_max(rise_max, rise_db[i])
        if keep:
            r_kept_max = ranges_m[i] if kept == 0 else _nan_max(r_kept_max, ranges_m[i])
            kept += 1
        elif margin >= 0:
            lost += 1
    return kept, numpy_sum(loss_db), r_max, r_kept_max, lost, rise_max, numpy_sum(rise_db)


@jit
def _nan_max(a, b):
    return a if a != a else b if (b != b or b > a) else a


def _attenuation(model: RadarWeather, profile: RadarProfile, planar: bool) -> tuple[float, float]:
    """γ (dB/km) of the model's weather at the profile's frequency, and the profile's largest range in it."""
    gamma = model.gamma_db_per_km(profile)
    return gamma, detection_range_in_weather_m(profile.max_range_m, gamma)


def _cell_doppler_m_per_s(cloud: PointCloud, ego: np.ndarray, ranges_m: np.ndarray) -> np.ndarray:
    """The Doppler of each point's own resolution cell, for its CA-CFAR threshold rise: the raw radial velocity
    (``v_r_m_per_s``, or ``v·r̂`` of Cartesian ``vx, vy``), or a static world ``−v_ego·r̂``."""
    v_r = radial_velocity_m_per_s(cloud)
    return -(cloud.positions_m @ ego) / np.maximum(ranges_m, 1e-12) if v_r is None else v_r


def _add_clutter(cloud: PointCloud, clear: PointCloud, det: Detection, cells: ClutterCells,
                 rng, ego: np.ndarray, planar: bool) -> tuple[PointCloud, dict]:
    """Draw the clutter points and give them the fields of ``cloud`` (calibrated on the ``clear`` input); a 2-D
    radar reports them in its plane (physics/radar_frame.py)."""
    profile = profile_of(cloud)
    constant, gamma = cells.radar_constant_db, cells.gamma_db_per_km
    pts = generate_clutter(rng, cells)
    summary = {"clutter_expected_points": cells.expected_count,
               "clutter_backscatter_per_m": cells.tables.backscatter_per_m,
               "radar_constant_db": constant}
    if not len(pts.v_r_m_per_s) and cloud.grid_shape is None:    # most CA-CFAR frames: appending nothing would
        return cloud, {"clutter_points": 0, **summary}             # only copy the cloud
    positions = to_plane(pts.positions_m) if planar else pts.positions_m
    r = np.linalg.norm(positions, axis=1)
    rcs = pts.detection_db - constant + 40 * np.log10(r)
    if profile.rcs_compensates_weather:
        rcs = rcs + two_way_loss_db(gamma, r)
    new = {**added_detection_fields(clear, len(r)), "rcs_dbsm": rcs,
           **new_point_velocity_fields(cloud, positions, pts.v_r_m_per_s, ego)}
    if det.statistic != RCS_STATISTIC:
        new[det.statistic] = pts.detection_db
        offset = power_minus_snr_db(clear)
        if offset is not None:
            new["power_db"] = pts.detection_db + offset
    new = {k: v for k, v in new.items() if k in cloud.fields}
    out = cloud.concat(positions, new)
    return out, {"clutter_points": len(r), **summary}


@dataclass(frozen=True)
class PrecipitationRadar(RadarWeather):
    """Precipitation clutter (models.md §4.3 [PROP], physics/radar_clutter.py, physics/radar_cfar.py): per
    resolution cell (range bin × the profile's azimuth/elevation cells × Doppler bins of
    ``profile.velocity_resolution_m_per_s``) mean RCS ``μ = η V P(v)`` with the Doppler spread of falling particles
    seen by the moving radar in the wind (``cloud.conditions``), exponentially distributed; the frame's radar
    constant C and threshold t put ``σ_t = 10^{(t − C + L)/10} r⁴`` at the clear-air threshold.

    Detector (``detector``):

    - ``cfar`` (default): cell-averaging CFAR with ``cfar_reference_cells`` reference cells and per-cell false-alarm
      probability ``cfar_pfa`` (``α = N(P_fa^{−1/N} − 1)``; Richards, Fundamentals of Radar Signal Processing,
      §6.5.3). A clutter point is declared where the cell's clutter exceeds the CFAR threshold, which rises with the
      local clutter, and the clear-air threshold: at most P_fa per cell, whatever ``C − t``. Rain 20 mm/h,
      120° × 30° at 1° × 2°, 1–20 m, car at 10 m/s, defaults: about 0.05 / 1.5 / 8 points per frame for
      C − t = 68 / 76 / 83 dB. Real points lose sensitivity where the clutter fills their own cell: their threshold
      rises by ``10 log10(1 + CNR)`` dB (CNR = α μ/σ_t; Doppler bin from ``v_r_m_per_s``, else a static world
      ``−v_ego·r̂``), at any range: a static target on boresight at C − t = 76 dB loses 10 / 4 / 0.3 dB at
      2 / 5 / 20 m.
    - ``fixed`` (models.md §4.3): a cell is declared when its clutter exceeds σ_t; no sensitivity loss. The count
      explodes with ``C − t``: about 60 / 6 000 / 44 000 points for 68 / 76 / 83 dB, all within a few metres.

    ``cfar_pfa`` default 1e-4: the lower end of the 10⁻⁴–10⁻⁶ per cell quoted for automotive CFAR, and with 16
    reference cells α = 10.95 dB, i.e. a clear-air threshold ≈ 11 dB above noise, typical of automotive radar
    detections (the 10⁻⁶ textbook value gives α = 13.4 dB and about 70× fewer clutter points). Per 4D cell the
    figure is generous (the radar's cube holds ~10⁹ cells), which keeps a visible trace of the clutter.

    Added points (effect ADDED; annotations give them the clutter class): RCS/SNR/power consistent with C (never
    below t), ``v_r``, and ``v_r_comp = v_r + v_ego·r̂`` when the cloud has it; other fields zero. Needs an
    ``rcs_dbsm`` field to calibrate C (else no clutter and no CFAR loss, reported in the diagnostics).
    ``clutter: false``: attenuation only."""

    clutter: bool = param(True, doc="precipitation clutter: added points (and, with cfar, the sensitivity loss)")
    detector: str = param("cfar", doc="cfar: cell-averaging CFAR (few clutter points, sensitivity loss near the "
                          "sensor); fixed: fixed threshold (models.md §4.3, count explodes with C − t)",
                          choices=("cfar", "fixed"))
    cfar_pfa: float = param(1e-4, doc="CA-CFAR false-alarm probability per resolution cell", gt=0, le=0.1)
    cfar_reference_cells: int = param(16, unit="cells", doc="CA-CFAR reference cells (range–Doppler window)", ge=1)
    clutter_min_range_m: float = param(1.0, unit="m", doc="nearest clutter range (radar blind zone)", gt=0)
    clutter_max_range_m: float = param(20.0, unit="m", doc="farthest range searched for clutter points "
                                       "(models.md §4.3)", gt=0)
    backscatter: str = param("mie", doc="particle backscatter: mie (accurate) or analytic (RISE Rayleigh/optical "
                             "approximation, 13 % lower for rain)", choices=SCATTERING)

    def validate(self) -> None:
        if self.clutter_max_range_m <= self.clutter_min_range_m:
            raise ModelError("must exceed clutter_min_range_m", model=self.id, field="clutter_max_range_m")

    @abstractmethod
    def hydrometeors(self, profile: RadarProfile) -> Hydrometeors | None:
        """The falling particles, None when there are none (zero rate)."""

    def frame_clutter(self, data, ranges_m, det, gamma, ego_m_per_s, planar):
        setup = per_profile(self, profile_of(data), planar, _ClutterSetup.of)
        rise = np.zeros(len(ranges_m))
        if setup is None:
            return None, rise, {"clutter_points": 0}
        constant = radar_constant_db(data, det, ranges_m)
        skipped = ("no rcs_dbsm to calibrate the radar constant" if constant is None else
                   "no points to estimate the threshold" if not math.isfinite(det.threshold_db) else
                   "clutter_min_range_m beyond the profile's max_range_m" if setup.grid is None else None)
        if skipped:
            return None, rise, {"clutter_points": 0, "clutter_skipped": skipped}
        wind = np.asarray(data.conditions.wind_velocity_m_per_s, dtype=float)
        tables = setup.tables(wind - ego_m_per_s)
        if isinstance(setup.detector, FixedThreshold) or not len(data):    # no sensitivity loss
            return frame_cells(tables, constant, det.threshold_db, gamma)[0], rise, dict(setup.diagnostics)
        cells, ratio = frame_cells(tables, constant, det.threshold_db, gamma, data.positions_m,
                                   _cell_doppler_m_per_s(data, ego_m_per_s, ranges_m), ranges_m)
        return cells, setup.detector.threshold_rise_db(ratio), dict(setup.diagnostics)


@dataclass(frozen=True)
class _ClutterSetup:
    """What a precipitation model's clutter takes from its parameters and the radar profile alone, the same for
    every frame of a run (:func:`per_profile`): the particles, the resolution grid (None: the clutter's ranges lie
    beyond the profile's), the detector and the wavelength. Made once, they are also the same objects for the
    clutter's table caches (found by identity, not compared field by field)."""

    hydrometeors: Hydrometeors
    grid: ResolutionGrid | None
    detector: CaCfar | FixedThreshold
    wavelength_m: float
    diagnostics: dict
    by_velocity: dict = field(default_factory=dict, compare=False)

    def tables(self, relative_velocity_m_per_s: np.ndarray) -> ClutterTables:
        """The clutter's tables at ``relative_velocity = wind − ego`` (one for every frame unless the ego velocity
        is fitted per frame), found by the velocity's value instead of hashing the particles and grid."""
        key = tuple(relative_velocity_m_per_s.tolist())
        held = self.by_velocity.get(key)
        if held is None:
            if len(self.by_velocity) >= MAX_PER_PROFILE:
                self.by_velocity.clear()
            held = self.by_velocity[key] = clutter_tables(self.hydrometeors, self.grid, self.wavelength_m, key,
                                                          self.detector)
        return held

    @staticmethod
    def of(model: PrecipitationRadar, profile: RadarProfile, planar: bool) -> _ClutterSetup | None:
        """None when the model makes no clutter (``clutter: false`` or no particles)."""
        profile = grid_profile(profile, planar)
        h = model.hydrometeors(profile)
        if not model.clutter or h is None:
            return None
        max_range_m = min(model.clutter_max_range_m, profile.max_range_m)
        grid = None if max_range_m < model.clutter_min_range_m + profile.range_resolution_m else ResolutionGrid(
            profile.fov_azimuth_deg, profile.fov_elevation_deg, profile.azimuth_resolution_deg,
            profile.elevation_resolution_deg, profile.range_resolution_m, profile.velocity_resolution_m_per_s,
            model.clutter_min_range_m, max_range_m)
        detector = CaCfar(model.cfar_pfa, model.cfar_reference_cells) if model.detector == "cfar" else FixedThreshold()
        diagnostics = {"detector": model.detector}
        if isinstance(detector, CaCfar):
            diagnostics["cfar_multiplier_db"] = float(10 * np.log10(detector.multiplier))
        return _ClutterSetup(h, grid, detector, radar_wavelength_m(profile.frequency_hz), diagnostics)


MAX_PER_PROFILE = 32
_per_profile: dict[tuple, tuple] = {}        # (build, model id, profile id, planar) → (model, profile, value)


def per_profile(model: Model, profile: RadarProfile, planar: bool, build: Callable) -> Any:
    """``build(model, profile, planar)``, made once per model, profile and geometry instead of per frame (a run's
    frames share one profile object and, without drawn parameters, one model object); they are held with it, so
    that their ids identify them."""
    key = (build, id(model), id(profile), planar)
    held = _per_profile.get(key)
    if held is None:
        if len(_per_profile) >= MAX_PER_PROFILE:       # models with drawn parameters: one per frame
            _per_profile.clear()
        held = _per_profile[key] = (model, profile, build(model, profile, planar))
    return held[2]
