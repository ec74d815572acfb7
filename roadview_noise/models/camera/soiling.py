"""Lens soiling by mud splatter (models.md §2.4; D3.5 CNF1–3, Eq. 3)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any, ClassVar

import numpy as np

from ...errors import ModelError
from ...model import Model, Scope, Stage, param
from ...param_checks import rgb
from ...physics.blob_mask import BlobMask, blob_mask
from ...physics.cfa import SiteLayout
from ...physics.photometry import SAMPLE_STEP_PX
from ...physics.soiling import soil
from ...registry import register

MASK_SEED_BITS = 62


@lru_cache(maxsize=8)
def _mud_mask(seed: int, count: int, height: int, width: int, size_px: tuple[float, float], softness: float,
              vertical_bias: float) -> BlobMask:
    """The sequence's coverage mask on a height × width frame (read-only, cached: every frame of a sequence)."""
    blobs = blob_mask((height, width), np.random.default_rng(seed), size_px=size_px, count=count,
                      softness=softness, vertical_bias=vertical_bias)
    blobs.mask.flags.writeable = False
    return blobs


@register
@dataclass(frozen=True)
class SoilingCamera(Model):
    """Mud on the lens from the spray of the vehicle ahead (models.md §2.4; D3.5 "S_min 93, S_max 271,
    Intensity 0.45", WMG framework rendering).

    Image formation (Gu et al. 2009; :mod:`roadview_noise.physics.soiling`): ``I' = I·(1 − ι M) + ι M·ρ_mud ⊙ Ī``,
    M the defocused coverage mask, ι = ``opacity``, ρ_mud the mud albedo per colour, Ī the frame's mean radiance
    per colour (the stray light the dirt scatters; it follows weather and low light). Uncovered pixels are left
    bit-identical.

    Mask (:func:`roadview_noise.physics.blob_mask.blob_mask`): K ~ Poisson(``splatter_count_mean``) splatters,
    each a union of 6–20 random ellipses within a diameter S ~ U(S_min, S_max), softened by a Gaussian of
    σ = ``softness``·S. The meaning of D3.5's three numbers is not published; our reading (models.md §2.4, a
    guess): S_min, S_max are splatter *diameters in pixels of the 1936-px-wide* D3.5 camera, scaled with the
    image width (``reference_width_px``); "Intensity 0.45" is the mud's opacity ι, not a coverage fraction.
    Sensor-instance state: the mask is drawn once per sequence (the same mud on every frame; the manifest keeps
    its seed and splatter count). Runs per site on raw Bayer mosaics: M is a pixel map, the stray light takes
    each site's colour; no demosaic. Diagnostics: covered fraction (M > 0.5), mean coverage, stray light."""

    id: ClassVar[str] = "soiling.camera"
    stage: ClassVar[Stage] = Stage.WINDOW
    scope: ClassVar[Scope] = Scope.SEQUENCE
    sensor: ClassVar[str] = "camera"
    summary: ClassVar[str] = "lens soiling: mud splatter mask, defocused, mud albedo + stray light (D3.5)"

    s_min_px: float = param(93.0, unit="px", gt=0, doc="smallest splatter diameter at reference_width_px (D3.5: 93)")
    s_max_px: float = param(271.0, unit="px", gt=0, doc="largest splatter diameter at reference_width_px "
                                                        "(D3.5: 271)")
    reference_width_px: int = param(1936, unit="px", ge=1, doc="image width the sizes refer to (D3.5: 1936)")
    opacity: float = param(0.45, unit="1", ge=0, le=1, doc="ι: opacity of the mud (D3.5 'Intensity' 0.45)")
    splatter_count_mean: float = param(12.0, unit="1", ge=0, le=1000, doc="mean number of splatters (Poisson)")
    mud_albedo: Any = param((0.30, 0.25, 0.20), unit="1", doc="ρ_mud per colour [R, G, B], brownish")
    softness: float = param(0.05, unit="1", ge=0, le=1, doc="defocus blur σ as a fraction of the splatter size")
    vertical_bias: float = param(0.0, unit="1", ge=0, le=1, doc="0 uniform; 1 splatter centres denser towards "
                                                                "the bottom (road spray)")

    def validate(self) -> None:
        if self.s_min_px > self.s_max_px:
            raise ModelError(f"s_min_px ({self.s_min_px}) exceeds s_max_px ({self.s_max_px})", model=self.id,
                             field="s_min_px")
        object.__setattr__(self, "mud_albedo", rgb(self.mud_albedo, self.id, "mud_albedo", low=0.0, high=1.0,
                                                   scalar=True))

    def draw_sequence(self, rng, data) -> dict:
        return {"mask_seed": int(rng.integers(1 << MASK_SEED_BITS)),
                "splatters": int(rng.poisson(self.splatter_count_mean))}

    def mask(self, state: dict, height: int, width: int) -> BlobMask:
        """The sequence's coverage mask (``.mask``: M (H, W) in [0, 1])."""
        scale = width / self.reference_width_px
        return _mud_mask(int(state["mask_seed"]), int(state["splatters"]), height, width,
                         (self.s_min_px * scale, self.s_max_px * scale), float(self.softness),
                         float(self.vertical_bias))

    def apply(self, data, *, state, drawn, rng):
        h, w = data.shape
        blobs = self.mask(state, h, w)
        coverage = blobs.mask
        layout = SiteLayout.of(data)
        signal = data.signal()
        mean = np.array([s.mean(dtype=np.float64) for s in layout.channel_samples(signal, step=SAMPLE_STEP_PX)])
        stray = np.asarray(self.mud_albedo) * mean
        out = soil(layout, signal, coverage, self.opacity, stray)
        return data.with_signal(out), {
            "covered_fraction": blobs.covered_fraction(),
            "mean_coverage": float(coverage.mean(dtype=np.float64)),
            "splatters": int(state["splatters"]),
            "stray_light": [float(v) for v in stray],
        }
