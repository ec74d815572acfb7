"""What a radar cloud tells about its sensor beyond x, y, z: 2-D (no elevation) radars, Cartesian velocity fields,
the ego velocity they imply, and the fields a sensor gives a detection it adds (models.md §0.4, §4).

- **2-D radars.** A radar without elevation measurement reports every detection in its horizontal plane: z = 0
  (Continental ARS 408-21 in nuScenes). ``RadarProfile.elevation_measured`` says so; ``None`` (default) decides from
  the data: a cloud whose every z is exactly 0 is 2-D. For a 2-D radar the whole elevation field of view is one
  resolution cell, and a point it reports — a clutter point, a point seen through a misaligned mounting — keeps
  its slant range ``r`` and azimuth and is put at ``(r cos az, r sin az, 0)`` (:func:`to_plane`).
- **Cartesian velocities.** nuScenes radar PCDs carry no radial-velocity field: ``vx, vy`` (m/s, sensor frame,
  relative to the sensor) and ``vx_comp, vy_comp`` (ego motion compensated; nuScenes devkit
  ``RadarPointCloud.from_file``). The Doppler a radar measures is the radial component, ``v_r = v · r̂`` (positive
  receding, models.md §0.4); the physics (Doppler cells of the clutter, the CFAR threshold rise) uses the raw
  ``vx, vy`` one, the compensated one only enters the ego velocity below. A detection the models add gets the
  vector ``v_r r̂`` (radial: a Doppler measurement has no tangential part) and ``v_r,comp r̂``.
- **Ego velocity from the data.** When a cloud has raw and compensated radial velocities (``v_r`` and
  ``v_r_compensated`` of View-of-Delft, or the two vector pairs of nuScenes), ``v_r,comp − v_r = v_ego · r̂`` for
  every point: least squares over the frame gives the sensor velocity (horizontal only for a 2-D radar). It is used
  when the recipe gives none (``conditions.ego_velocity_m_per_s`` all zero) and the fit holds (RMS residual ≤
  :data:`EGO_FIT_MAX_RMS_M_PER_S`, a few Doppler bins: the two fields really differ by one sensor velocity), and
  recorded in the diagnostics.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..types import PointCloud, RadarProfile
from .compiled import jit
from .return_ranges import squared_range

RAW_VECTOR = ("vx", "vy", "vz")                  # sensor-relative Cartesian velocity (nuScenes: vx, vy)
COMPENSATED_VECTOR = ("vx_comp", "vy_comp", "vz_comp")
EGO_FIT_MAX_RMS_M_PER_S = 0.5      # ARS 408 velocity codes step 0.25 m/s; a consistent frame fits far better


def point_ranges_m(cloud: PointCloud) -> np.ndarray:
    """``cloud.ranges_m`` (``np.linalg.norm`` of the rows: ``√((x² + y²) + z²)``) bit for bit, without the ≈ 4 µs
    of norm's Python on a radar frame."""
    p = cloud.positions_m
    if p.dtype != np.float64 or p.ndim != 2 or p.shape[1] != 3:
        return cloud.ranges_m
    out = np.empty(len(p))
    _row_norms(p, out)
    return out


@jit
def _row_norms(p, out):
    for i in range(len(p)):
        out[i] = math.sqrt(squared_range(p, i))


def is_planar(cloud: PointCloud, profile: RadarProfile) -> bool:
    """True for a 2-D radar: ``profile.elevation_measured`` is False, or None and every z of ``cloud`` is 0."""
    if profile.elevation_measured is not None:
        return not profile.elevation_measured
    return len(cloud) > 0 and not cloud.positions_m[:, 2].any()


def grid_profile(profile: RadarProfile, planar: bool) -> RadarProfile:
    """The profile whose angular grid the models use: for a 2-D radar, one elevation cell over the field of view."""
    if not planar or profile.elevation_resolution_deg == profile.fov_elevation_deg:
        return profile
    return dataclasses.replace(profile, elevation_resolution_deg=profile.fov_elevation_deg)


def to_plane(positions_m: np.ndarray) -> np.ndarray:
    """``(r cos az, r sin az, 0)``: the position a 2-D radar reports for a scatterer at ``positions_m``."""
    r = np.linalg.norm(positions_m, axis=1)
    az = np.arctan2(positions_m[:, 1], positions_m[:, 0])
    return np.stack([r * np.cos(az), r * np.sin(az), np.zeros_like(r)], axis=1)


def _vector_fields(cloud: PointCloud, names: tuple[str, ...]) -> list[str] | None:
    """The fields of one velocity vector present in ``cloud`` (x and y at least), else None."""
    present = [n for n in names if n in cloud.fields]
    return present if present[:2] == list(names[:2]) else None


def radial_velocity_m_per_s(cloud: PointCloud, compensated: bool = False) -> np.ndarray | None:
    """Per point radial velocity (m/s, positive receding): the ``v_r_m_per_s`` (``v_r_comp_m_per_s``) field, else
    ``v · r̂`` of the Cartesian fields (:data:`RAW_VECTOR`, :data:`COMPENSATED_VECTOR`), else None."""
    scalar = "v_r_comp_m_per_s" if compensated else "v_r_m_per_s"
    if scalar in cloud.fields:
        return np.asarray(cloud.fields[scalar], dtype=float)
    names = _vector_fields(cloud, COMPENSATED_VECTOR if compensated else RAW_VECTOR)
    if names is None:
        return None
    p = cloud.positions_m
    r = np.maximum(np.linalg.norm(p, axis=1), 1e-12)
    return sum(np.asarray(cloud.fields[n], dtype=float) * p[:, i] for i, n in enumerate(names)) / r


def ego_velocity_from_data(cloud: PointCloud, planar: bool) -> tuple[np.ndarray | None, float]:
    """Least-squares sensor velocity (m/s, sensor frame) from ``v_r,comp − v_r = v_ego · r̂`` and the fit's RMS
    residual (m/s); (None, nan) without both radial velocities or with too few points to fit."""
    comp = radial_velocity_m_per_s(cloud, compensated=True)      # (most clouds have none: the raw one not read)
    raw = None if comp is None else radial_velocity_m_per_s(cloud)
    if raw is None or comp is None:
        return None, np.nan
    p = cloud.positions_m
    r = np.linalg.norm(p, axis=1)
    ok = (r > 0) & np.isfinite(raw) & np.isfinite(comp)
    dims = 2 if planar else 3
    if ok.sum() < dims + 1:
        return None, np.nan
    u = p[ok, :dims] / r[ok, None]
    if np.linalg.matrix_rank(u) < dims:
        return None, np.nan
    d = (comp - raw)[ok]
    v = np.linalg.lstsq(u, d, rcond=None)[0]
    return np.concatenate([v, np.zeros(3 - dims)]), float(np.sqrt(np.mean((u @ v - d) ** 2)))


def ego_velocity_m_per_s(cloud: PointCloud, planar: bool) -> tuple[np.ndarray, str]:
    """The sensor velocity the models use and where it comes from: the recipe's (``conditions``) when it is not
    zero, else the data's (:func:`ego_velocity_from_data`) when its fit holds, else zero."""
    given = np.asarray(cloud.conditions.ego_velocity_m_per_s, dtype=float)
    if given.any():
        return given, "recipe"
    fitted, rms = ego_velocity_from_data(cloud, planar)
    if fitted is None:
        return given, "none (zero)"
    if not rms <= EGO_FIT_MAX_RMS_M_PER_S:
        return given, f"none (zero): compensated − raw radial velocity fits no sensor velocity (RMS {rms:.2g} m/s)"
    return fitted, f"data: compensated − raw radial velocity (fit RMS {rms:.2g} m/s)"


def new_point_velocity_fields(cloud: PointCloud, positions_m: np.ndarray, v_r_m_per_s: np.ndarray,
                              ego_velocity_m_per_s: np.ndarray) -> dict[str, np.ndarray]:
    """Velocity fields of added detections at ``positions_m`` with Doppler ``v_r_m_per_s``: the radial fields and
    the Cartesian vectors ``v_r r̂``, ``v_r,comp r̂`` (``v_r,comp = v_r + v_ego · r̂``), for those ``cloud`` has."""
    r = np.maximum(np.linalg.norm(positions_m, axis=1), 1e-12)
    unit = positions_m / r[:, None]
    comp = v_r_m_per_s + unit @ ego_velocity_m_per_s
    out = {"v_r_m_per_s": v_r_m_per_s, "v_r_comp_m_per_s": comp}
    for names, v in ((RAW_VECTOR, v_r_m_per_s), (COMPENSATED_VECTOR, comp)):
        out.update({n: v * unit[:, i] for i, n in enumerate(names)})
    return {k: v for k, v in out.items() if k in cloud.fields}


def rotated_velocity_fields(cloud: PointCloud, rotation: np.ndarray, after_m: np.ndarray,
                            ego_velocity_m_per_s: np.ndarray) -> dict[str, np.ndarray]:
    """Velocity fields of ``cloud`` seen through a mounting rotated by ``rotation`` (points now at ``after_m``):
    the raw vector turns with the sensor, ``v' = R v``; the compensation, done with the assumed mounting, moves
    from ``(v_ego·r̂) r̂`` to ``(v_ego·r̂') r̂'``, so ``v_comp' = R (v_comp − (v_ego·r̂) r̂) + (v_ego·r̂') r̂'`` and
    ``v_r,comp' = v_r,comp + v_ego·(r̂' − r̂)``. Raw radial velocities are unchanged. A 2-D radar (z = 0 before
    and after) keeps each vector's radial and in-plane tangential parts along the new reported ray."""
    before = cloud.positions_m
    r = np.maximum(np.linalg.norm(before, axis=1), 1e-12)
    u0, u1 = before / r[:, None], after_m / r[:, None]
    e0, e1 = u0 @ ego_velocity_m_per_s, u1 @ ego_velocity_m_per_s
    out = {}
    if "v_r_comp_m_per_s" in cloud.fields:
        v = cloud.fields["v_r_comp_m_per_s"]
        out["v_r_comp_m_per_s"] = v + (e1 - e0)
    planar = not after_m[:, 2].any() and not before[:, 2].any()
    for names, shift in ((RAW_VECTOR, None), (COMPENSATED_VECTOR, (e0, e1))):
        present = _vector_fields(cloud, names)
        if present is None:
            continue
        vec = np.zeros((len(before), 3))
        for i, n in enumerate(present):
            vec[:, i] = cloud.fields[n]
        if shift is not None:
            vec -= shift[0][:, None] * u0
        if planar:            # 2-D radar: radial and in-plane tangential parts follow the reported ray
            t0, t1 = (np.stack([-u[:, 1], u[:, 0], np.zeros(len(u))], axis=1) for u in (u0, u1))
            vec = (np.sum(vec * u0, axis=1)[:, None] * u1 + np.sum(vec * t0, axis=1)[:, None] * t1)
        else:
            vec = vec @ rotation.T
        if shift is not None:
            vec += shift[1][:, None] * u1
        out.update({n: vec[:, i] for i, n in enumerate(present)})
    return {k: np.asarray(v).astype(cloud.fields[k].dtype, copy=False) for k, v in out.items()}
