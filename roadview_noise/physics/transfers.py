"""Transfer functions other than sRGB that camera files state (PNG ``cICP``, HEIF ``nclx``: ITU-T H.273 Table 3),
between integer codes and linear light, by table.

A transfer is a pair of functions — signal E' (0–1) → light and back, float64 — and the light of reference white,
which the linear scale puts at **1.0**, the level an 8-bit sRGB photo's full scale stands for, so a model's absolute
levels (fog's airlight estimate, low light's ADC full scale, the JPEG step's 8-bit sRGB) mean the same whatever the
curve. Codes ↔ linear go through tables as for sRGB (:mod:`.srgb`: the 2^bits decoded values; linear → code by the
exact bucket table of the decision levels of the float64 curve), never a per-pixel power:

- ``bt709`` (H.273 transfers 1, 6, 14, 15: BT.709, BT.601, BT.2020 10- and 12-bit, one OETF): scene light L of
  the camera's OETF ``V = α L^0.45 − (α − 1)`` for ``L ≥ β``, ``4.5 L`` below (BT.709-6 Table 1 item 1.2,
  BT.2020-2 Table 4), inverted; full code = 1.0. The constants are BT.2020's exact α = 1.09929682680944,
  β = 0.018053968510807, for which the two segments meet (value and slope); BT.709's rounded 1.099 / 0.018 leave
  a step of 0.00025 at L = 0.018 (V = 0.081 below, 0.08125 above), so the inverse would fall back across it and the
  decision levels would not be sorted. The two differ by at most 0.00025 in V (0.06 of an 8-bit code, 0.25 of a
  10-bit one), at L = 0.018.
- ``gamma22``, ``gamma28`` (H.273 transfers 4 and 5: BT.470 System M and B/G): the pure power ``L = V^γ``; full
  code = 1.0.
- ``pq``, ``hlg`` (H.273 16 and 18: BT.2100, :mod:`.bt2100`): PQ display light / 203 cd/m² (full code 49.26), HLG
  scene light / E(75 % signal) (full code 3.774), reference white of ITU-R BT.2408.

Values above the full code's (PQ, HLG highlights above reference white up to the peak) go through the chain as
such; the writer clips to [0, :func:`peak`] only.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np

from . import bt2100, srgb

BT2020_ALPHA, BT2020_BETA = 1.09929682680944, 0.018053968510807   # BT.2020-2 Table 4 (exact; BT.709: 1.099, 0.018)


@dataclass(frozen=True)
class Transfer:
    """A transfer function: ``light(signal)`` and ``signal(light)`` (float64, signal 0–1) and the light of
    reference white (linear 1.0); ``scale`` says so in the manifest (``inputs.transfer.scale``)."""

    light: Callable[[np.ndarray], np.ndarray]
    signal: Callable[[np.ndarray], np.ndarray]
    white: float
    scale: str


def bt709_oetf(light: np.ndarray) -> np.ndarray:
    """Signal V (0–1) of scene light L (0–1): BT.709-6 Table 1 item 1.2 with BT.2020's exact α, β."""
    v = np.asarray(light, dtype=float)
    return np.where(v < BT2020_BETA, 4.5 * v, BT2020_ALPHA * np.abs(v) ** 0.45 - (BT2020_ALPHA - 1))


def bt709_inverse_oetf(signal: np.ndarray) -> np.ndarray:
    """Scene light L (0–1) of signal V (0–1), the inverse of :func:`bt709_oetf`."""
    v = np.asarray(signal, dtype=float)
    return np.where(v < 4.5 * BT2020_BETA, v / 4.5, ((np.abs(v) + BT2020_ALPHA - 1) / BT2020_ALPHA) ** (1 / 0.45))


def _power(gamma: float) -> Transfer:
    """The pure power ``L = V^gamma`` (H.273 transfers 4, 5: BT.470's assumed display gamma)."""
    return Transfer(lambda v: np.abs(np.asarray(v, dtype=float)) ** gamma,
                    lambda x: np.abs(np.asarray(x, dtype=float)) ** (1 / gamma), 1.0,
                    f"1.0 = full code (reference white): L = V^{gamma} (H.273 / BT.470)")


TRANSFERS = {
    "bt709": Transfer(bt709_inverse_oetf, bt709_oetf, 1.0,
                      "1.0 = full code (reference white): scene light of the BT.709 / BT.2020 inverse OETF"),
    "gamma22": _power(2.2),
    "gamma28": _power(2.8),
    "pq": Transfer(bt2100.pq_eotf, bt2100.pq_inverse_eotf, bt2100.REFERENCE_WHITE_CD_PER_M2,
                   "1.0 = reference white 203 cd/m² (ITU-R BT.2408): L / 203 cd/m², full code 49.26"),
    "hlg": Transfer(bt2100.hlg_inverse_oetf, bt2100.hlg_oetf, bt2100.HLG_REFERENCE_LIGHT,
                    "1.0 = reference white, 75 % HLG signal (ITU-R BT.2408): scene light E / 0.2650 (BT.2100 "
                    "inverse OETF), full code 3.774"),
}
CURVES = tuple(TRANSFERS)


def _transfer(curve: str) -> Transfer:
    if curve not in TRANSFERS:
        raise ValueError(f"unknown transfer {curve!r}; expected one of {CURVES}")
    return TRANSFERS[curve]


def decode(signal: np.ndarray, curve: str) -> np.ndarray:
    """Linear value (reference white 1.0) of signal E' (0–1) of ``curve``, float64."""
    t = _transfer(curve)
    return t.light(signal) / t.white


def encode(linear: np.ndarray, curve: str) -> np.ndarray:
    """Signal E' (0–1) of ``curve`` of a linear value (reference white 1.0, 0 … :func:`peak`), float64."""
    t = _transfer(curve)
    return t.signal(np.asarray(linear, dtype=float) * t.white)


def peak(curve: str) -> float:
    """The linear value of the full code: 1.0 (BT.709, gamma), 49.26 (PQ), 3.774 (HLG)."""
    return float(decode(1.0, curve))


@lru_cache(maxsize=8)
def decode_table(curve: str, bits: int) -> np.ndarray:
    """The 2^bits linear values of ``curve``'s codes, float32."""
    table = decode(np.arange(2 ** bits) / (2 ** bits - 1), curve).astype(np.float32)
    table.flags.writeable = False
    return table


@lru_cache(maxsize=8)
def encode_table(curve: str, bits: int) -> tuple:
    """:func:`.srgb.bucket_table` of ``curve``'s ``bits``-bit linear → code."""
    return srgb.bucket_table(srgb.decision_levels(bits, lambda e: decode(e, curve)), peak(curve),
                             f"{curve} {bits}-bit")


def code_to_linear(codes: np.ndarray, curve: str, bits: int) -> np.ndarray:
    """Linear values (float32, reference white 1.0, C order) of uint8/uint16 ``curve`` codes, by table."""
    return srgb.code_to_linear(codes, bits, table=decode_table(curve, bits))


def linear_to_code(linear: np.ndarray, curve: str, bits: int) -> np.ndarray:
    """``bits``-bit ``curve`` codes (uint8/uint16) of linear values: clipped to [0, :func:`peak`], rounded to the
    nearest code exactly (the decision levels of the float64 curve); NaN gives 0."""
    return srgb.linear_to_code(linear, bits, table=encode_table(curve, bits))
