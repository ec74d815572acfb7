"""LiDAR window obstruction: dirt, mud and water on the sensor window, after the weather (models.md §3.8; D3.5
CNF25–27, Eq. 3)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Scope, Stage, param
from ...physics.lidar_geometry import ring_index
from ...physics.lidar_intensity import intensity_resolution, reflectivity_following, stored_intensity, too_faint
from ...physics.lidar_rays import cloud_rays
from ...physics.window_obstruction import SHAPES, WINDOWS, PatchSpec, column_scale, window_pattern, window_transmission
from ...provenance import Effect, mark
from ...registry import register
from ...types import LidarProfile, PointCloud


@register
@dataclass(frozen=True)
class OcclusionLidar(Model):
    """Patches of dirt on the LiDAR window block the rays through them (models.md §3.8; D3.5: random patches on the
    range image, p = 6·10⁻⁵ per cell; Eq. 3, after the weather).

    The pattern (:mod:`physics.window_obstruction`) lies on the profile's window grid (beams by elevation × the
    profile's azimuth columns): every cell seeds a patch with probability ``seed_probability``; ``square`` patches of
    ``patch_min_cells … patch_max_cells`` rows (columns × the aspect), or ``blob`` splatters (the camera soiling mask
    generator, soft edges, wrapped over the 360° seam). A patch of ``opacity`` o passes ``(1 − o·m)²`` of a ray's
    signal (two ways, m its coverage). ``window: static`` (Ouster) blocks fixed azimuth–elevation regions; ``rotating``
    (Velodyne head) blocks whole rings; ``profile`` takes the profile's ``window``. The dirt is drawn once per sensor
    instance (``draw_sequence``: every frame of a sequence shares it; ``per_frame`` redraws it every frame, e.g.
    splashing water). Every point in a fully blocked cell is removed — input returns and weather returns alike, since
    it runs after the weather; a point behind a partial patch is attenuated and kept only if its signal still reaches
    the receiver's threshold (the one the weather models detect with, calibrated below the weakest recorded return).
    Full grids keep their cells (zeroed, effect REMOVED). Diagnostics: the blocked and obstructed fractions of the
    window and the points removed and attenuated."""

    id: ClassVar[str] = "occlusion.lidar"
    stage: ClassVar[Stage] = Stage.WINDOW
    scope: ClassVar[Scope] = Scope.SEQUENCE
    sensor: ClassVar[str] = "lidar"
    summary: ClassVar[str] = "window obstruction: patches of blocked rays (static window) or rings (rotating), p 6e-5"

    seed_probability: float = param(6e-5, doc="probability that a window cell seeds a patch (D3.5 LiDAR: 6e-5)",
                                    ge=0, le=1)
    patch_min_cells: int = param(4, unit="cells", doc="smallest patch side (rows of beams)", ge=1)
    patch_max_cells: int = param(16, unit="cells", doc="largest patch side (rows of beams)", ge=1)
    shape: str = param("square", choices=SHAPES, doc="square: D3.5's patches on the range image; blob: soiling "
                       "splatters with soft edges")
    aspect: str = param("cells", choices=("cells", "angular"), doc="cells: patches as wide as tall in range-image "
                        "cells (D3.5); angular: as wide as tall in angle (columns × beam spacing / column step)")
    opacity: float = param(1.0, doc="share of the light a fully covered cell stops, one way (1: mud; < 1: water, "
                           "dust: the ray is attenuated, then re-thresholded)", gt=0, le=1)
    softness: float = param(0.05, doc="blob: edge blur σ as a fraction of the blob size", ge=0, le=0.5)
    window: str = param("profile", choices=("profile",) + WINDOWS, doc="static: fixed azimuth–elevation patches "
                        "(Ouster); rotating: whole rings (Velodyne head); profile: the LiDAR profile's window")
    per_frame: bool = param(False, doc="draw new dirt every frame instead of once per sensor instance")

    def validate(self) -> None:
        if self.patch_max_cells < self.patch_min_cells:
            raise ModelError("must be ≥ patch_min_cells", model=self.id, field="patch_max_cells")

    def _profile(self, data: PointCloud) -> LidarProfile:
        if not isinstance(data.profile, LidarProfile):
            raise ModelError("needs the LiDAR profile (beam table, columns, window) of the cloud", model=self.id)
        return data.profile

    def _spec(self, profile: LidarProfile) -> PatchSpec:
        window = profile.window if self.window == "profile" else self.window
        if window not in WINDOWS:
            raise ModelError(f"profile {profile.name!r} has window {window!r}; expected one of {WINDOWS}",
                             model=self.id, field="window")
        return PatchSpec(window, self.shape, float(self.seed_probability), (self.patch_min_cells, self.patch_max_cells),
                         column_scale(profile, self.aspect), float(self.opacity), float(self.softness))

    def _draw(self, rng: np.random.Generator, data: PointCloud) -> dict:
        profile = self._profile(data)
        spec = self._spec(profile)
        seed = int(rng.integers(2 ** 63))
        pattern = window_pattern(spec, profile.channels, profile.columns, seed)
        return {"pattern_seed": seed, "window": spec.window, "grid": [profile.channels, profile.columns],
                "seeds": pattern.seeds, "patches": pattern.patches,
                "blocked_fraction": pattern.blocked_fraction, "obstructed_fraction": pattern.obstructed_fraction}

    def draw_sequence(self, rng, data):
        return {} if self.per_frame else self._draw(rng, data)

    def draw(self, rng, data):
        return self._draw(rng, data) if self.per_frame else {}

    def apply(self, data: PointCloud, *, state, drawn, rng):
        drawn_pattern = drawn if self.per_frame else state
        profile = self._profile(data)
        grid = [profile.channels, profile.columns]
        if list(drawn_pattern["grid"]) != grid:
            raise ModelError(f"pattern drawn for a {drawn_pattern['grid']} window grid, the profile has {grid}",
                             model=self.id, field="state")
        pattern = window_pattern(self._spec(profile), *grid, int(drawn_pattern["pattern_seed"]))
        if pattern.obstructed_fraction > 0:
            at, t = window_transmission(data.positions_m, ring_index(data, profile), profile, pattern.transmission)
        else:
            at, t = np.zeros(0, dtype=np.int64), np.zeros(0)
        blocked = at[t == 0]
        remove = np.zeros(len(data), dtype=bool)
        remove[blocked] = True
        out = data
        diagnostics = {"window": drawn_pattern["window"], "seeds": int(pattern.seeds),
                       "blocked_fraction": pattern.blocked_fraction,
                       "obstructed_fraction": pattern.obstructed_fraction, "points_blocked": len(blocked)}
        removed = len(blocked)
        partial = ((t > 0) & (t < 1)) if pattern.partial else None
        if partial is not None and partial.any():
            out, below, attenuated, notes = _attenuate(data, at[partial], t[partial], self.id)
            remove[below] = True
            removed += len(below)
            diagnostics.update(points_attenuated=attenuated, **notes)
        diagnostics["points_removed"] = removed
        return out.drop(remove), diagnostics


def _attenuate(cloud: PointCloud, at: np.ndarray, t: np.ndarray, model_id: str
               ) -> tuple[PointCloud, np.ndarray, int, dict]:
    """Returns ``at`` behind partial patches (transmission ``t``): signal and stored intensity × t (linear in the
    signal for either intensity kind), rounded as the sensor stores it; those below the receiver's threshold
    (:func:`lidar_rays.cloud_rays`: the weather's, calibrated below the weakest recorded return) or too faint to store
    are to be removed. Returns the cloud with the new intensities (effect ATTENUATED where they changed visibly), the
    indices of the points to remove, how many were attenuated and kept, and the threshold notes."""
    rays = cloud_rays(cloud, model_id, "ignore", at=at)
    profile = rays.profile
    field = cloud.fields["intensity"]
    reported = field[at].astype(np.float64) * t
    below_at = (rays.signal * t < rays.threshold) | too_faint(reported, profile)
    stored = np.asarray(stored_intensity(reported, profile), dtype=np.float64)
    values = field.copy()
    values[at] = stored.astype(field.dtype)
    changed = np.zeros(len(cloud), dtype=bool)
    changed[at] = ~below_at & (np.abs(stored - field[at]) >= 0.5 * intensity_resolution(profile))
    rows = np.flatnonzero(changed)
    out = mark(cloud.with_fields(intensity=values, **reflectivity_following(cloud.fields, rows, field[rows],
                                                                            values[rows])), changed, Effect.ATTENUATED)
    return out, at[below_at], int(np.count_nonzero(~below_at)), {k: v for k, v in rays.notes.items()}
