"""Ray drop: returns a real sensor misses, before the weather (models.md §3.9; D3.5 CNF28–30, Eq. 1)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Stage, param
from ...physics.lidar_geometry import ring_index
from ...physics.ray_drop import PhysicalRayDrop, always_dropped, scan_rays
from ...registry import register

BACKENDS = ("physical", "learned")


@register
@dataclass(frozen=True)
class RayDropLidar(Model):
    """Rays whose return a real sensor would miss: dark, far, grazing or mixed-pixel returns (models.md §3.9, after
    Guillard et al., IROS 2022; D3.5 Eq. 1: before the weather).

    Per return, a drop probability from the features of its neighbours in the range image
    (:mod:`physics.ray_drop`: received signal over the threshold, range, incidence angle from the normal, beam
    elevation), times ``strength``; ``keep ~ Bernoulli(1 − p)`` per ray (frame draw). A return beyond the profile's
    maximum range always drops, and one whose incidence exceeds ``max_incidence_deg``.
    Back-ends: ``physical`` — the detection probability of the shared receiver (:mod:`physics.receiver`, the one the
    weather models detect with) for an effective signal with a log-normal spread; its coefficients default to the
    values fitted on a real Ouster OS1-128 range image (bench/fit_ray_drop.py; held-out AUC 0.86 against 0.5 for a
    constant rate). ``learned`` — a classifier file (``model_file``: .json additive logistic model or .onnx) written by
    ``rvnoise fit ray-drop`` from the user's own real scans.
    Dropped rays stay rays: a grid's cell becomes a no-return cell, a list loses the point and the weather's firing
    grid finds the empty cell again (:mod:`physics.firing_grid`), so the weather can still return from them
    (models.md §1). A point list without a firing grid (merged clouds) falls back to each point's own signal and
    range (incidence unknown), as the manifest says. Never adds points."""

    id: ClassVar[str] = "ray_drop.lidar"
    stage: ClassVar[Stage] = Stage.RAY_DROP
    sensor: ClassVar[str] = "lidar"
    summary: ClassVar[str] = "missing returns: receiver detection probability of dark, far, grazing rays (fitted)"

    backend: str = param("physical", choices=BACKENDS, doc="physical: receiver detection model with the coefficients "
                         "below; learned: the classifier in model_file (rvnoise fit ray-drop)")
    model_file: Any = param(None, unit="path", doc="learned: a .json or .onnx file written by `rvnoise fit ray-drop`")
    strength: float = param(1.0, doc="scales every drop probability (0: nothing drops)", ge=0, le=1)
    # defaults: fitted on the real OS1-128 scan0 range image, every column, elevation left out (bench/fit_ray_drop.py)
    log_gain: float = param(1.528, doc="physical: ln of the effective signal over the neighbours' received signal "
                            "(sensor more sensitive than its datasheet threshold: > 0)", ge=-15, le=15)
    range_exponent: float = param(-0.1569, doc="physical: effective signal ∝ (R / 10 m)^a beyond the signal's own R⁻²",
                                  ge=-6, le=1.9)
    incidence_exponent: float = param(0.3730, doc="physical: effective signal ∝ cos^a θ of the incidence angle "
                                      "beyond what the intensity holds", ge=0, le=8)
    elevation_linear_per_rad: float = param(0.0, unit="1/rad", doc="physical: ln effective signal += e1·ω (beam "
                                            "elevation ω)", ge=-20, le=20)
    elevation_quadratic_per_rad2: float = param(0.0, unit="1/rad²", doc="physical: ln effective signal += e2·ω²",
                                                ge=-200, le=200)
    log_signal_sd: float = param(1.092, doc="physical: SD of ln effective signal from ray to ray (beam cover, texture)",
                                 ge=0, le=6)
    floor_drop_probability: float = param(0.006691, doc="physical: drop probability of a strong return (specular, "
                                          "refractive surfaces)", ge=0, le=0.5)
    max_incidence_deg: float = param(90.0, unit="deg", doc="rays at larger incidence always drop (90: off; the real "
                                     "scan's rays beyond 85° drop at 18 %, not always)", ge=0, le=90)

    def validate(self) -> None:
        if self.backend == "learned" and not isinstance(self.model_file, str):
            raise ModelError("the learned back-end needs model_file: a .json or .onnx file written by "
                             "`rvnoise fit ray-drop`", model=self.id, field="model_file")

    def physical(self) -> PhysicalRayDrop:
        return PhysicalRayDrop(self.log_gain, self.range_exponent, self.incidence_exponent,
                               self.elevation_linear_per_rad, self.elevation_quadratic_per_rad2, self.log_signal_sd,
                               self.floor_drop_probability)

    def apply(self, data, *, state, drawn, rng):
        sr = scan_rays(data, self.id, empty=False)
        n = len(data)
        every = bool(sr.rays.has_target[:n].all())      # (a point list: its points, without copies)
        idx = np.arange(n) if every else np.flatnonzero(sr.rays.has_target[:n])
        r = sr.rays.range_m[:n] if every else sr.rays.range_m[idx]
        if sr.cells is not None:
            features, _ = sr.features(sr.cells.cell if every else sr.cells.cell[idx], data.positions_m)
            source = f"neighbours on the {sr.cells.source}"
        else:
            elevation = np.deg2rad(np.asarray(sr.rays.profile.beam_elevation_deg))[ring_index(data, sr.rays.profile)]
            features = np.stack([sr.log_signal[idx], np.log(r), np.ones(len(idx)), elevation[idx]], axis=1)
            source = f"each return's own signal and range ({sr.reason})"
        diagnostics = {"backend": self.backend, "features": source}
        if self.backend == "physical":
            p = self.physical().drop_probability(features, sr.receiver())
        else:
            from ...io.ray_drop_model import read_model

            p = read_model(self.model_file).drop_probability(features)
            diagnostics["model_file_sha256"] = hashlib.sha256(Path(self.model_file).read_bytes()).hexdigest()
        rule = always_dropped(r, features[:, 2], sr.rays.profile.max_range_m, self.max_incidence_deg)
        p[rule] = 1.0
        if self.strength != 1.0:
            p *= self.strength
        drop = rng.random(len(idx)) < p
        if every:
            mask = drop
        else:
            mask = np.zeros(n, dtype=bool)
            mask[idx[drop]] = True
        diagnostics.update(returns_in=len(idx), dropped=int(drop.sum()),
                           drop_fraction=float(drop.mean()) if len(idx) else 0.0,
                           mean_drop_probability=float(p.mean()) if len(idx) else 0.0,
                           beyond_max_range=int(np.count_nonzero(r > sr.rays.profile.max_range_m)),
                           **{k: v for k, v in sr.rays.notes.items() if k.startswith("intensity_")})
        return data.drop(mask), diagnostics
