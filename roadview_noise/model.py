"""The model contract: stages (D3.5 compounding positions), scopes, unit-named validated parameters.

A model is a frozen dataclass whose fields are its physical parameters, declared with :func:`param` (unit, range,
documentation). It implements:

- ``draw_sequence(rng, data) -> dict``: sensor-instance state (scope SEQUENCE only), drawn once per sequence from
  ``derive_rng(seed, "sequence", sequence_id, model_id)``; JSON-able (lists, floats), recorded in the manifest.
- ``draw(rng, data) -> dict``: per-frame scalar random choices, recorded in the manifest.
- ``apply(data, *, state, drawn, rng) -> (data, diagnostics)``: deterministic given ``state`` and ``drawn`` except
  for high-dimensional noise taken from ``rng`` (None for a model whose ``uses_frame_rng`` is False); never mutates
  ``data``; diagnostics is a JSON-able dict. A cloud model that removes, adds or reorders points does it with
  ``select``/``drop``/``concat`` (or sets ``origin`` and ``effect`` itself), so annotations follow
  (:mod:`roadview_noise.provenance`); it never touches label fields.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
from abc import ABC, abstractmethod
from dataclasses import dataclass
from enum import Enum, IntEnum
from typing import TYPE_CHECKING, Any, ClassVar, Sequence

import numpy as np

from .errors import ModelError

if TYPE_CHECKING:
    from .physics.warp import Warp


class Stage(IntEnum):
    """Position in the sensing chain (models.md §1): scene → emitter → medium → window/lens → detector → encoding.

    Eq. 1 factors sit before MEDIUM, Eq. 2 factors are MODIFIERs of the medium, Eq. 3 factors come after it."""

    SCENE = 10         # scene illumination (low light)                                   Eq. 1
    EMITTER = 20       # beam geometry and power (LiDAR alignment, gain; radar mounting)  Eq. 1
    RAY_DROP = 30      # returns missing before propagation                               Eq. 1
    MODIFIER = 40      # changes the weather process itself (wind)                         Eq. 2
    MEDIUM = 50        # propagation through fog, rain, snow
    WINDSCREEN = 60    # refraction by the windscreen                                     Eq. 3
    WINDOW = 70        # lens surface, sensor window, radome (soiling, obstruction)       Eq. 3
    EXPOSURE = 80      # integration on the detector (motion blur)                        Eq. 3
    ELECTRONICS = 90   # detector and receiver electronics (bias, noise)                  Eq. 3
    ENCODING = 100     # ISP and lossy compression                                        Eq. 3


class Scope(str, Enum):
    FRAME = "frame"          # everything drawn per frame
    SEQUENCE = "sequence"    # has sensor-instance state shared by every frame of a sequence


@dataclass(frozen=True)
class ParamSpec:
    """What ``rvnoise show`` prints and the recipe validates for one parameter."""

    name: str
    unit: str
    default: Any
    doc: str
    ge: float | None = None
    le: float | None = None
    gt: float | None = None
    lt: float | None = None
    choices: tuple | None = None

    def range_text(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(map(str, self.choices))
        lo = f"≥ {self.ge:g}" if self.ge is not None else (f"> {self.gt:g}" if self.gt is not None else "")
        hi = f"≤ {self.le:g}" if self.le is not None else (f"< {self.lt:g}" if self.lt is not None else "")
        return ", ".join(p for p in (lo, hi) if p) or "any"

    def _number_hint(self, value: Any) -> str:
        """How to write a number given as text: ``'30'`` without quotes; ``'30m'`` for a parameter in m as 30 (the
        unit is in the parameter's name); another unit is not converted (``'30 km'``: say it in m)."""
        number = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*", value) \
            if isinstance(value, str) else None
        if number is None:
            text = value.strip().lower() if isinstance(value, str) else ""
            sign = "-" if text.startswith("-") else ""
            return f": YAML writes infinity .inf, {self.name}: {sign}.inf" if text.lstrip("+-") in ("inf", "infinity") \
                else ""
        digits, written = number.groups()
        if not written:
            return f": write it without quotes, {self.name}: {digits}"
        if self.unit in ("1", ""):
            return ": write a bare number (this parameter has no unit)"
        if written.replace(" ", "") == self.unit.replace(" ", ""):
            return f": write the bare number (its unit, {self.unit}, is part of the name), {self.name}: {digits}"
        return f": write the number in {self.unit}, bare (the unit is part of the name; no unit is converted)"

    def check(self, value: Any) -> str | None:
        """None if ``value`` is allowed, else the reason."""
        if self.choices is not None:
            return None if value in self.choices else f"must be {self.range_text()}, got {value!r}"
        if isinstance(self.default, bool):
            return None if isinstance(value, bool) else f"must be true or false, got {value!r}"
        if isinstance(self.default, (int, float)) and not isinstance(self.default, bool):
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                return f"must be a number, got {value!r}{self._number_hint(value)}"
            if isinstance(self.default, int) and not float(value).is_integer():
                return f"must be an integer, got {value!r}"
            v = float(value)
            if math.isnan(v):
                return "must not be NaN"
            for bound, ok in ((self.ge, lambda b: v >= b), (self.le, lambda b: v <= b),
                              (self.gt, lambda b: v > b), (self.lt, lambda b: v < b)):
                if bound is not None and not ok(bound):
                    return f"must be {self.range_text()}, got {value!r}"
        return None


def param(default: Any, *, unit: str = "1", doc: str = "", ge: float | None = None, le: float | None = None,
          gt: float | None = None, lt: float | None = None, choices: Sequence | None = None) -> Any:
    """Declare a model parameter (a dataclass field carrying its unit, range and documentation)."""
    meta = dict(unit=unit, doc=doc, ge=ge, le=le, gt=gt, lt=lt, choices=tuple(choices) if choices else None)
    if isinstance(default, (list, tuple)):
        default = tuple(default)
    return dataclasses.field(default=default, metadata={"rvnoise": meta})


@dataclass(frozen=True)
class Model(ABC):
    """Base class of every noise model; subclasses are frozen dataclasses registered with ``@register``."""

    id: ClassVar[str]
    stage: ClassVar[Stage]
    sensor: ClassVar[str]                    # "camera" | "lidar" | "radar"
    scope: ClassVar[Scope] = Scope.FRAME
    needs_depth: ClassVar[bool] = False      # camera models that need a depth map
    uses_camera_geometry: ClassVar[bool] = False  # camera models that need intrinsics (K, exposure, pixel pitch)
    summary: ClassVar[str] = ""              # one line for `rvnoise list`

    def __post_init__(self) -> None:
        for spec in self.param_specs():
            problem = spec.check(getattr(self, spec.name))
            if problem:
                raise ModelError(problem, model=self.id, field=spec.name)
        self.validate()

    def validate(self) -> None:
        """Cross-parameter checks; raise ``ModelError`` naming the field."""

    @classmethod
    def param_specs(cls) -> list[ParamSpec]:
        return list(_param_specs(cls))

    def params(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in _param_names(type(self))}

    @property
    def uses_frame_rng(self) -> bool:
        """Whether ``draw`` or ``apply`` take anything from the frame generator; False: they get None, and the chain
        skips its derivation (≈ 20 µs per step and file, issue 19)."""
        return True

    def draw_sequence(self, rng: np.random.Generator, data: Any) -> dict:
        return {}

    def draw(self, rng: np.random.Generator, data: Any) -> dict:
        return {}

    def warp(self, data: Any, *, state: dict, drawn: dict) -> "Warp | None":
        """Geometric camera models return the pixel map their ``apply`` resamples the image with (masks and boxes
        follow it, :mod:`roadview_noise.physics.warp`); photometric models return None."""
        return None

    @abstractmethod
    def apply(self, data: Any, *, state: dict, drawn: dict, rng: np.random.Generator) -> tuple[Any, dict]:
        """The model's effect on one frame or cloud: ``(new data, diagnostics)``."""


@functools.cache
def _param_specs(cls: type) -> tuple[ParamSpec, ...]:
    """A model class's parameters (its fields with rvnoise metadata), in field order; once per class (a step's
    ``params()`` is recorded per file)."""
    return tuple(ParamSpec(name=f.name, default=f.default, **f.metadata["rvnoise"]) for f in dataclasses.fields(cls)
                 if "rvnoise" in f.metadata)


@functools.cache
def _param_names(cls: type) -> tuple[str, ...]:
    return tuple(s.name for s in _param_specs(cls))
