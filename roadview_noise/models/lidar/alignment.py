"""Laser alignment error: per-beam azimuth/elevation offsets (models.md §3.6; D3.5 ch. 4, §5.2.1; CNF19–21)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Scope, Stage, param
from ...physics import return_ranges
from ...physics.lidar_geometry import has_return, ring_source, velodyne_to_xyz, with_ring, xyz_to_velodyne
from ...registry import register


@register
@dataclass(frozen=True)
class AlignmentLidar(Model):
    """Beam misalignment of a spinning LiDAR (models.md §3.6; measured on a VLS-128, D3.5 ch. 4).

    Each beam i of a simulated sensor gets a constant offset ``Δα_i ~ N(0, azimuth_sd_deg)``,
    ``Δω_i ~ N(0, elevation_sd_deg)`` (D3.5: 0.001°, 0.127°), drawn once per sensor instance (``draw_sequence``),
    so every frame of a sequence shares them. Points are turned in the D3.5 Eq. (6)/(4) convention about the
    sensor origin — ``α = atan2(x, y)``, ``ω = atan2(z, sqrt(x² + y²))``, ``α' = α + Δα_i``,
    ``ω' = ω + Δω_i`` — at unchanged range; all other fields are kept. The beam index comes from the ``ring`` field (or
    the ``ring`` attribute an earlier step stored) or, without one, from the clean elevation and the profile's beam
    table, before perturbing — and then travels with every point as ``attributes['ring']``
    (:func:`lidar_geometry.with_ring`), so later steps (the weather's firing grid) never recover rings from the
    tilted elevations; the output's profile is the misaligned sensor's (:func:`tilted_beams`), so a weather return
    added on an empty ray of a tilted beam lies on that beam. The cloud's fields are not changed.
    No-return points (zero position) stay zero. ``mode = per_point`` is D3.5 §5.2.1's alternative reading: an
    independent offset for every point of every frame (models.md §7.8).

    The Ouster optical centre sits 36 mm above the sensor-frame origin; turning about the origin instead moves a
    point by 36 mm·Δω ≈ 0.08 mm at 1σ, far below the effect modelled."""

    id: ClassVar[str] = "alignment.lidar"
    stage: ClassVar[Stage] = Stage.EMITTER
    scope: ClassVar[Scope] = Scope.SEQUENCE
    sensor: ClassVar[str] = "lidar"
    summary: ClassVar[str] = "per-beam azimuth/elevation misalignment, N(0, 0.001°) / N(0, 0.127°) per sensor"

    azimuth_sd_deg: float = param(0.001, unit="deg", doc="standard deviation of the per-beam azimuth offset", ge=0)
    elevation_sd_deg: float = param(0.127, unit="deg", doc="standard deviation of the per-beam elevation offset",
                                    ge=0)
    mode: str = param("per_beam", doc="per_beam: one offset per beam and sensor (D3.5 ch. 4); per_point: a new "
                      "offset for every point of every frame", choices=("per_beam", "per_point"))

    def _channels(self, data) -> int:
        if data.profile is None:
            raise ModelError("needs the LiDAR profile (beam table) of the cloud", model=self.id)
        return data.profile.channels

    def draw_sequence(self, rng, data):
        if self.mode != "per_beam":
            return {}
        n = self._channels(data)
        return {"azimuth_offset_deg": rng.normal(0.0, self.azimuth_sd_deg, n).tolist(),
                "elevation_offset_deg": rng.normal(0.0, self.elevation_sd_deg, n).tolist()}

    def apply(self, data, *, state, drawn, rng):
        n_beams = self._channels(data)
        hit = has_return(data.positions_m, data)      # noting its geometry for the metrics
        diagnostics = {"ring_source": ring_source(data)}
        data, ring = with_ring(data)                   # before the points move: later steps read it
        if self.mode == "per_beam":
            if len(state["elevation_offset_deg"]) != n_beams:
                raise ModelError(f"state has {len(state['elevation_offset_deg'])} beams, the profile "
                                 f"{data.profile.name!r} {n_beams}", model=self.id, field="state")
            ring = ring[hit]
            d_alpha = np.deg2rad(np.asarray(state["azimuth_offset_deg"]))[ring]
            d_omega = np.deg2rad(np.asarray(state["elevation_offset_deg"]))[ring]
        else:
            n = int(hit.sum())
            d_alpha = rng.normal(0.0, np.deg2rad(self.azimuth_sd_deg), n)
            d_omega = rng.normal(0.0, np.deg2rad(self.elevation_sd_deg), n)

        before = data.positions_m[hit]
        r, alpha, omega = xyz_to_velodyne(before)
        after = velodyne_to_xyz(r, alpha + d_alpha, omega + d_omega)
        if self.mode == "per_beam":                    # the misaligned sensor's beam table, for later steps
            data = dataclasses.replace(data, profile=tilted_beams(data.profile, state["azimuth_offset_deg"],
                                                                  state["elevation_offset_deg"]))
        positions = data.positions_m.copy()
        return_ranges.write_rows(positions, hit, after, data.profile)     # with its geometry for the metrics
        shift = after - before
        squared_shift = shift[:, 0] ** 2 + shift[:, 1] ** 2 + shift[:, 2] ** 2
        diagnostics.update(
            points=len(after),
            rms_vertical_displacement_m=_rms(shift[:, 2] ** 2),
            rms_displacement_m=_rms(squared_shift),
            max_displacement_m=float(np.sqrt(squared_shift.max())) if len(after) else 0.0,
            rms_elevation_offset_deg=float(np.rad2deg(_rms(d_omega ** 2))),
        )
        return dataclasses.replace(data, positions_m=positions), diagnostics


def tilted_beams(profile, azimuth_offset_deg, elevation_offset_deg):
    """The profile of a sensor whose beam i is turned by (Δα_i, Δω_i) (Velodyne convention, degrees): elevation
    ``ω_i + Δω_i``; azimuth offset ``offset_i + Δα_i`` (a point fired at encoder angle F lies at
    ``atan2(y, x) = F − offset_i − Δα_i``)."""
    return dataclasses.replace(
        profile, beam_elevation_deg=tuple(np.add(profile.beam_elevation_deg, elevation_offset_deg).tolist()),
        beam_azimuth_offset_deg=tuple(np.add(profile.beam_azimuth_offset_deg, azimuth_offset_deg).tolist()))


def _rms(squares: np.ndarray) -> float:
    """Root of the mean of squared values (0 for none)."""
    return float(np.sqrt(np.mean(squares))) if len(squares) else 0.0
