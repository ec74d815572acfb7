"""Radar obstruction: blocked patches of the radome on the azimuth–elevation grid (models.md §4.4; D3.5 CNF25–27
radar variant, Eq. 3: after the weather, so clutter points are blocked too)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Scope, Stage, param
from ...physics.radar_clutter import angular_cell_index, angular_edges_rad
from ...registry import register
from ...provenance import Effect, mark
from ...types import PointCloud
from .detection import detection, profile_of, with_loss


@register
@dataclass(frozen=True)
class OcclusionRadar(Model):
    """Dirt, mud or a water film on the radome (models.md §4.4 [PROP]).

    The field of view is split into azimuth × elevation cells at the profile's angular resolution (120° × 30° at
    1° × 2°: 1800 cells). Each cell seeds a patch with probability ``seed_probability`` (D3.5: 2·10⁻³, so 3.6
    expected seeds), and a seed blocks a square of ``s ~ U{patch_min_cells … patch_max_cells}`` cells centred on
    it (clipped at the field-of-view edge). Points in blocked cells are removed (``mode = remove``, D3.5's holes),
    or lose ``two_way_loss_db`` and are re-thresholded (``mode = attenuate``: mud/water films attenuate before
    they block; threshold as in models/radar/detection.py, estimated from this model's input). Points outside
    the field of view count in the nearest edge cell. The pattern is a sensor-instance draw shared by every frame
    of a sequence (``static``), or drawn per frame."""

    id: ClassVar[str] = "occlusion.radar"
    stage: ClassVar[Stage] = Stage.WINDOW
    scope: ClassVar[Scope] = Scope.SEQUENCE
    sensor: ClassVar[str] = "radar"
    summary: ClassVar[str] = "radome obstruction: square patches of blocked az–el cells, seed probability 2e-3"

    seed_probability: float = param(2e-3, doc="probability that a cell seeds a patch (D3.5 radar: 2e-3)", ge=0, le=1)
    patch_min_cells: int = param(1, unit="cells", doc="smallest patch side", ge=1)
    patch_max_cells: int = param(3, unit="cells", doc="largest patch side", ge=1)
    mode: str = param("remove", doc="remove: blocked points are deleted; attenuate: they lose two_way_loss_db and "
                      "are re-thresholded", choices=("remove", "attenuate"))
    two_way_loss_db: float = param(10.0, unit="dB", doc="two-way loss of a blocked cell in attenuate mode", ge=0)
    static: bool = param(True, doc="one pattern per sensor instance (sequence); false: a new pattern every frame")
    snr_threshold_quantile: float = param(0.0, doc="threshold quantile of the input's detection statistic when "
                                          "the profile gives none (attenuate mode)", ge=0, le=0.05)

    def validate(self) -> None:
        if self.patch_max_cells < self.patch_min_cells:
            raise ModelError("must be ≥ patch_min_cells", model=self.id, field="patch_max_cells")

    def _edges(self, data: PointCloud) -> tuple[np.ndarray, np.ndarray]:
        p = profile_of(data)
        return (angular_edges_rad(p.fov_azimuth_deg, p.azimuth_resolution_deg),
                angular_edges_rad(p.fov_elevation_deg, p.elevation_resolution_deg))

    def _pattern(self, rng: np.random.Generator, data: PointCloud, sequence: bool = False) -> dict:
        """The pattern drawn from ``rng``; a sequence's (``sequence``: its generator is used for nothing else) is
        drawn once per worker."""
        az_e, el_e = self._edges(data)
        n_az, n_el = len(az_e) - 1, len(el_e) - 1
        state = rng.bit_generator.state
        seeds, blocked = (_drawn_pattern(self, _pcg64_key(state), n_az, n_el)
                          if sequence and state["bit_generator"] == "PCG64" else self._draw_pattern(rng, n_az, n_el))
        return {"grid_cells": [n_az, n_el], "seeds": seeds, "blocked_cells": list(blocked)}

    def _draw_pattern(self, rng: np.random.Generator, n_az: int, n_el: int) -> tuple[int, tuple[int, ...]]:
        """(seeds, blocked flat cells) of one draw."""
        seeds = np.flatnonzero(rng.random(n_az * n_el) < self.seed_probability)
        side = rng.integers(self.patch_min_cells, self.patch_max_cells + 1, len(seeds))
        offsets = np.arange(self.patch_max_cells)
        i_az, i_el = np.divmod(seeds, n_el)
        start_az, start_el = i_az - (side - 1) // 2, i_el - (side - 1) // 2
        da, de = np.meshgrid(offsets, offsets, indexing="ij")
        inside = (da[None] < side[:, None, None]) & (de[None] < side[:, None, None])
        a = start_az[:, None, None] + da[None]
        e = start_el[:, None, None] + de[None]
        inside &= (a >= 0) & (a < n_az) & (e >= 0) & (e < n_el)
        blocked = np.unique((a * n_el + e)[inside])
        return len(seeds), tuple(blocked.tolist())

    @property
    def uses_frame_rng(self) -> bool:
        return not self.static      # a static pattern is the sequence's

    def draw_sequence(self, rng, data):
        return self._pattern(rng, data, sequence=True) if self.static else {}

    def draw(self, rng, data):
        return {} if self.static else self._pattern(rng, data)

    def apply(self, data: PointCloud, *, state, drawn, rng):
        pattern = state if self.static else drawn
        az_e, el_e = self._edges(data)
        if list(pattern["grid_cells"]) != [len(az_e) - 1, len(el_e) - 1]:
            raise ModelError(f"pattern drawn for a {pattern['grid_cells']} grid, the profile has "
                             f"{[len(az_e) - 1, len(el_e) - 1]}", model=self.id, field="state")
        blocked_cells = np.asarray(pattern["blocked_cells"], dtype=np.int64)
        n_cells = (len(az_e) - 1) * (len(el_e) - 1)
        is_blocked = np.zeros(n_cells, dtype=bool)     # a look-up per cell: np.isin sorts (≈ 30 µs per frame)
        is_blocked[blocked_cells] = True
        blocked = is_blocked[angular_cell_index(data.positions_m, az_e, el_e)]
        diagnostics = {"seeds": int(pattern["seeds"]), "expected_seeds": self.seed_probability * n_cells,
                       "blocked_cells": len(blocked_cells), "blocked_fraction": len(blocked_cells) / n_cells,
                       "points_blocked": int(blocked.sum())}
        if self.mode == "remove":
            remove = blocked
            out = data
        else:
            det = detection(data, self.snr_threshold_quantile, self.id)
            loss = np.where(blocked, self.two_way_loss_db, 0.0)
            remove = det.values_db - loss < det.threshold_db
            out = mark(with_loss(data, loss), blocked & (self.two_way_loss_db > 0), Effect.ATTENUATED)
            diagnostics.update(det.diagnostics())
        diagnostics["points_removed"] = int(remove.sum())
        return (out.drop(remove) if diagnostics["points_removed"] else out), diagnostics   # (the usual frame: none)


def _pcg64_key(state: dict) -> tuple:
    """A PCG64 generator's complete state (``bit_generator.state``) as a hashable key."""
    return state["state"]["state"], state["state"]["inc"], state["has_uint32"], state["uinteger"]


@lru_cache(maxsize=64)
def _drawn_pattern(model: "OcclusionRadar", pcg64_key: tuple, n_az: int, n_el: int) -> tuple[int, tuple[int, ...]]:
    """A pattern is a function of the model's parameters, the generator's state and the grid: a sequence's pattern
    (a static one is drawn again for every frame from the same sequence generator) is drawn once per worker."""
    state, inc, has_uint32, uinteger = pcg64_key
    bit_generator = np.random.PCG64()
    bit_generator.state = {"bit_generator": "PCG64", "state": {"state": state, "inc": inc},
                           "has_uint32": has_uint32, "uinteger": uinteger}
    return model._draw_pattern(np.random.Generator(bit_generator), n_az, n_el)
