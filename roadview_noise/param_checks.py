"""Checks of structured model parameters (points, colour triplets, optional numbers) for ``Model.validate``: each
returns the normalised value or raises a ``ModelError`` naming the model and the field."""

from __future__ import annotations

import math
from numbers import Real
from typing import Any

from .errors import ModelError


def _is_number(v: Any) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool) and math.isfinite(v)


def point_px(value: Any, model_id: str, field: str) -> tuple[float, float] | None:
    """None, or [x, y] in pixels → (x, y)."""
    if value is None:
        return None
    if not isinstance(value, (list, tuple)) or len(value) != 2 or not all(_is_number(v) for v in value):
        raise ModelError(f"must be null or [x, y] in pixels, got {value!r}", model=model_id, field=field)
    return float(value[0]), float(value[1])


def rgb(value: Any, model_id: str, field: str, *, low: float, high: float = math.inf, low_open: bool = False,
        scalar: bool = False) -> tuple[float, float, float]:
    """[R, G, B] (or one number for all three when ``scalar``) within [low, high] (low excluded if ``low_open``)."""
    vals = (value,) * 3 if scalar and _is_number(value) else tuple(value) if isinstance(value, (list, tuple)) else ()
    ok = len(vals) == 3 and all(_is_number(v) and (v > low if low_open else v >= low) and v <= high for v in vals)
    if not ok:
        bound = f"{'>' if low_open else '≥'} {low:g}" + (f" and ≤ {high:g}" if high < math.inf else "")
        raise ModelError(f"must be {'a number or ' if scalar else ''}[R, G, B] {bound}, got {value!r}",
                         model=model_id, field=field)
    return tuple(float(v) for v in vals)


def optional_number(value: Any, model_id: str, field: str, *, above: float | None = None) -> float | None:
    """None, or a finite number (> ``above`` when given)."""
    if value is None:
        return None
    if not _is_number(value) or (above is not None and value <= above):
        need = "a finite number" if above is None else f"a number > {above:g}"
        raise ModelError(f"must be null or {need}, got {value!r}", model=model_id, field=field)
    return float(value)
