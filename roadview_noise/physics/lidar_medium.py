"""The medium stage of the LiDAR weather pipeline: the single-scattering LiDAR equation of what lies along a ray
(models.md §3.1; Hahner et al., ICCV 2021 fog and CVPR 2022 snow) — two-way transmission of a hard target, the return
of a particle, the pulse integral of a soft target (fog). Signals are in units of the sensor constant K
(:mod:`lidar_intensity`).

Conventions
- Apparent range of a return = position of the received pulse peak minus ``c τ_H / 2`` (Hahner's shift), so a hard
  target at R appears at R.
- Pulse ``P(t) = sin²(π t / (2 τ_H))`` on ``0 ≤ t ≤ 2 τ_H``; in range it spans ``L = c τ_H``.
- Overlap (crossover) function ξ(r): 0 below R1, linear to 1 at R2, the profile's ``overlap_start_m`` and
  ``overlap_full_m`` (Hahner 2021: R1 = 0.9 m, R2 = 1.0 m); every use of ξ (particles, fog tables) takes them from
  the profile.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..table_cache import disk_cached

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0
HAHNER_FOG_PULSE_S = 20e-9              # half-power pulse width of Hahner et al. 2021
HAHNER_OVERLAP_M = (0.9, 1.0)           # receiver overlap R1, R2 of Hahner et al. 2021
SOFT_TABLE_STEP_M = 0.01                # range step of the fog pulse-integral table


def overlap(r_m, r1_m: float, r2_m: float) -> np.ndarray:
    """Receiver overlap ξ(r): 0 for r ≤ R1, linear to 1 at R2, 1 beyond (R1, R2: the profile's ``overlap_start_m``,
    ``overlap_full_m``)."""
    return np.clip((np.asarray(r_m, dtype=float) - r1_m) / (r2_m - r1_m), 0.0, 1.0)


def pulse_power(t_s, tau_h_s: float) -> np.ndarray:
    """Normalised transmitted power ``sin²(π t/(2 τ_H))`` for 0 ≤ t ≤ 2 τ_H, else 0 (peak 1, energy τ_H)."""
    t = np.asarray(t_s, dtype=float)
    return np.where((t >= 0) & (t <= 2 * tau_h_s), np.sin(np.pi * t / (2 * tau_h_s)) ** 2, 0.0)


def pulse_length_m(tau_h_s: float) -> float:
    """Range extent ``c τ_H`` of a received pulse (2 τ_H long in time, c/2 metres per second of delay)."""
    return SPEED_OF_LIGHT_M_PER_S * tau_h_s


def hard_target_signal(signal, alpha_per_m: float, range_m) -> np.ndarray:
    """Two-way Beer–Lambert loss of a hard target, ``S e^{−2αR}`` (same unit as ``signal``; R finite)."""
    t = np.exp(np.multiply(range_m, -2.0 * alpha_per_m))
    return np.multiply(signal, t, out=t) if isinstance(t, np.ndarray) else signal * t


def particle_signal(reflectance: float, beam_fraction, range_m, alpha_per_m: float, r1_m: float,
                    r2_m: float) -> np.ndarray:
    """Return of a particle in units of K, ``ρ f ξ(r) e^{−2αr} / r²`` (m⁻²; ξ with overlap R1, R2)."""
    r = np.asarray(range_m, dtype=float)
    return reflectance * beam_fraction * overlap(r, r1_m, r2_m) * np.exp(-2.0 * alpha_per_m * r) / (r * r)


def soft_target_signal(g_s_per_m2, beta_per_m_sr: float) -> np.ndarray:
    """Return of a homogeneous soft target (fog) in units of K from its pulse integral G (s m⁻²):
    ``π β (c/2) G`` — the fog as a Lambertian reflector of ρ = π β per metre of depth (Hahner 2021 Eq. 6–10 with the
    sensor constant). For R ≫ c τ_H and ξ = 1: ``π β (c τ_H/2) e^{−2αR}/R²``."""
    return np.multiply(g_s_per_m2, math.pi * beta_per_m_sr * SPEED_OF_LIGHT_M_PER_S / 2)


@dataclass(frozen=True, eq=False)
class SoftTargetTable:
    """Peak of the soft-target (fog) pulse integral per hard-target range R0, on a regular grid from 0.

    ``g_max_s_per_m2[k] = max_R G(R; R0 = k·step)`` with
    ``G(R; R0) = ∫_0^{2τ_H} sin²(πt/2τ_H) e^{−2α(R−ct/2)} ξ(R−ct/2)/(R−ct/2)² H(R0 − R + ct/2) dt`` (s m⁻²), and
    ``fog_range_m[k]`` the apparent range of that peak. Beyond the last entry both are constant. ``rise_m``: how
    long the received fog profile of an empty ray takes to rise from 10 % to 90 % of its peak (m of range) — the
    leading edge whose slope sets the range jitter of a fog return (:mod:`receiver`)."""

    step_m: float
    g_max_s_per_m2: np.ndarray
    fog_range_m: np.ndarray
    rise_m: float

    def lookup(self, r0_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = np.minimum(np.rint(np.asarray(r0_m) / self.step_m), len(self.g_max_s_per_m2) - 1).astype(np.intp)
        return self.g_max_s_per_m2[k], self.fog_range_m[k]

    @property
    def saturated(self) -> tuple[float, float]:
        """(G_max, fog range) of a target beyond the table, e.g. an empty ray."""
        return float(self.g_max_s_per_m2[-1]), float(self.fog_range_m[-1])


@disk_cached(maxsize=32)
def soft_target_table(alpha_per_m: float, tau_h_s: float, r1_m: float, r2_m: float) -> SoftTargetTable:
    """Pulse-integral table of a homogeneous soft target (Hahner 2021 Eq. 8–10), cached per (α, τ_H, R1, R2) with the
    overlap R1, R2 of the profile.

    In range form ``G(R; R0) = (2/c) ∫_{R−L}^{min(R, R0)} w(R − r) f(r) dr`` with ``w(s) = sin²(π s/L)``,
    ``f(r) = e^{−2αr} ξ(r)/r²`` and ``L = c τ_H``. For ``R ≤ R0`` it does not depend on R0, and beyond
    ``R2 + L`` f decreases over the whole window, so the peak stops moving once ``R0 ≥ R2 + L``: the table ends
    there. The integral uses the midpoint rule on a 0.01 m grid."""
    h = SOFT_TABLE_STEP_M
    length = pulse_length_m(tau_h_s)
    nw = int(math.ceil(length / h))                       # window samples
    s = (np.arange(nw) + 0.5) * length / nw               # midpoints of the window (R − r)
    w = np.sin(np.pi * s / length) ** 2 * (2.0 / SPEED_OF_LIGHT_M_PER_S) * (length / nw)
    m_max = int(math.ceil((r2_m + length) / h))           # last R0 index of the table
    n_r = m_max + nw + 1                                  # apparent ranges R_n = n h, n < n_r
    r_n = np.arange(n_r) * h
    r = r_n[:, None] - s[None, :]                         # (n_r, nw) scatterer ranges
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(r > r1_m, np.exp(-2 * alpha_per_m * r) * overlap(r, r1_m, r2_m) / (r * r), 0.0)
    terms = w[None, :] * f
    # suffix[n, j] = Σ_{j' ≥ j} terms[n, j'] : window samples with r = R_n − s_j' ≤ R_n − s_j
    suffix = np.cumsum(terms[:, ::-1], axis=1)[:, ::-1]
    full = suffix[:, 0]                                   # G(R_n) with no target cut (R_n − s ≤ R0 for all s)
    m = np.arange(m_max + 1)
    # for R_n ≤ R0: running maximum of the uncut integral (and where it was reached)
    head = full[: m_max + 1]
    best_n = np.maximum.accumulate(np.where(head == np.maximum.accumulate(head), m, 0))
    best_val = head[best_n]
    # for R0 < R_n ≤ R0 + L: only scatterers with r ≤ R0, i.e. s_j ≥ R_n − R0 (first such j = ceil((R_n−R0)/ds − ½))
    d = np.arange(1, nw + 1)
    n_idx = m[:, None] + d[None, :]
    j0 = np.ceil(d * h / (length / nw) - 0.5).astype(np.intp)
    cut = np.where(j0[None, :] < nw, suffix[n_idx, np.minimum(j0, nw - 1)[None, :]], 0.0)
    k = np.argmax(cut, axis=1)
    cut_val = cut[m, k]
    better = cut_val > best_val
    best_val = np.where(better, cut_val, best_val)
    best_n = np.where(better, m + d[k], best_n)
    fog_range = np.clip(best_n * h - length / 2, 0.0, m * h)   # Hahner's shift; never behind the target
    lead = full[: int(np.argmax(full)) + 1]
    rise = (np.argmax(lead >= 0.9 * lead[-1]) - np.argmax(lead >= 0.1 * lead[-1])) * h
    return SoftTargetTable(h, best_val, fog_range, float(rise))

