"""Radar mounting misalignment: a sensor-instance rotation of the whole cloud (models.md §4.5 [PROP]; Eq. 1)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ...model import Model, Scope, Stage, param
from ...physics.radar_frame import ego_velocity_m_per_s, is_planar, rotated_velocity_fields, to_plane
from ...registry import register
from ...types import PointCloud
from .detection import profile_of


def rotation_matrix(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """``R = Rz(yaw) · Ry(pitch) · Rx(roll)`` (ISO 8855 sensor frame, angles in degrees)."""
    y, p, r = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    return rz @ ry @ rx


@register
@dataclass(frozen=True)
class AlignmentRadar(Model):
    """Mounting error of a 4D radar (models.md §4.5 [PROP]; D3.5 gives no parameters, default σ = 0: identity).

    Yaw, pitch and roll ~ N(0, σ) are drawn once per sensor instance and every point is turned about the sensor
    origin, ``p' = R p`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)``: the cloud as reported in the assumed mounting
    frame. Ranges, radial velocities, RCS and SNR are unchanged (a rotation keeps the ray); the ego-motion
    compensated velocity, computed by the radar with the assumed mounting, becomes
    ``v_r_comp' = v_r_comp + v_ego·(r̂' − r̂)``; Cartesian velocity fields (nuScenes ``vx, vy``, ``vx_comp,
    vy_comp``) turn with the sensor (physics/radar_frame.py, which also gives the ego velocity: the recipe's, else
    the data's). A 2-D radar (z = 0) reports the turned point in its plane at the same range and azimuth."""

    id: ClassVar[str] = "alignment.radar"
    stage: ClassVar[Stage] = Stage.EMITTER
    scope: ClassVar[Scope] = Scope.SEQUENCE
    sensor: ClassVar[str] = "radar"
    summary: ClassVar[str] = "mounting yaw/pitch/roll error per sensor instance, N(0, σ) (default σ = 0)"

    yaw_sd_deg: float = param(0.0, unit="deg", doc="standard deviation of the mounting yaw error", ge=0)
    pitch_sd_deg: float = param(0.0, unit="deg", doc="standard deviation of the mounting pitch error", ge=0)
    roll_sd_deg: float = param(0.0, unit="deg", doc="standard deviation of the mounting roll error", ge=0)

    def draw_sequence(self, rng, data):
        yaw, pitch, roll = rng.normal(0.0, 1.0, 3) * (self.yaw_sd_deg, self.pitch_sd_deg, self.roll_sd_deg)
        return {"yaw_deg": float(yaw), "pitch_deg": float(pitch), "roll_deg": float(roll)}

    def apply(self, data: PointCloud, *, state, drawn, rng):
        rot = rotation_matrix(state["yaw_deg"], state["pitch_deg"], state["roll_deg"])
        before = data.positions_m
        planar = is_planar(data, profile_of(data))
        after = to_plane(before @ rot.T) if planar else before @ rot.T
        ego, _ = ego_velocity_m_per_s(data, planar)
        out = dataclasses.replace(data, positions_m=after).with_fields(
            **rotated_velocity_fields(data, rot, after, ego))
        shift = np.linalg.norm(after - before, axis=1)
        return out, {"points": len(data), "rms_displacement_m": float(np.sqrt(np.mean(shift ** 2))) if len(shift)
                     else 0.0, "rotation_deg": float(np.rad2deg(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))))}
