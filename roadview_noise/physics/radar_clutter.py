"""Precipitation backscatter at radar frequencies and the point-cloud clutter generator (models.md §4.3).

Backscatter per unit volume ``η = ∫ N(D) σ_b(D) dD`` (m²/m³ = m⁻¹) of an exponential drop-size distribution, with
either cross-section of models.md §4.3:

- ``mie``: ``σ_b = Q_back π r²`` (Appendix A, physics/mie.py) tabulated once on 1000 log-spaced sizes and integrated
  on 10⁴ diameters (11 mm/h, ε = 12 − 25i: η = 8.826·10⁻⁴ m⁻¹). Accurate: 77 GHz drops span the Rayleigh and Mie
  regions.
- ``analytic`` (RISE): Rayleigh region ``D < λ/π``: ``σ_b = (9/4) ρ_F π⁵ D⁶/λ⁴`` (perfect-conductor sphere scaled by
  the Fresnel power reflectivity ρ_F — a heuristic), optical region ``σ_b = ρ_F π D²/4``; closed-form integrals
  (incomplete gamma). 11 mm/h: η = 7.665·10⁻⁴ m⁻¹, 13 % below Mie.

Doppler of a falling particle seen by a moving radar: ``v_ρ = (v_p − v_radar)·r̂`` with ``v_p = wind − v_t ẑ``;
positive when receding (models.md §0.4).

Clutter generator [PROP, refined]: precipitation is a distributed target, so its echo is thresholded per
*resolution cell* — range bin × azimuth cell × elevation cell × Doppler bin — with mean RCS
``μ = η V_cell P_cell(v_m)`` (V_cell = ΔΩ (r_hi³ − r_lo³)/3, P_cell(v_m) the fraction of the cell's clutter power
in Doppler bin m), and the clear-data radar constant ``C_r = SNR r⁴/σ`` of point targets. models.md §4.3 puts the
whole field of view into one range–Doppler cell; that credits the distributed echo with the full beamforming gain
that only a point target in one angular cell receives (``C_r`` is measured on point targets), overestimating the
clutter SNR by the number of angular cells (1800 for 120°×30° at 1°×2°). Per cell the RCS is exponential (many
random-phase drops), so the cell is detected with probability ``exp(−σ_t/μ)``, ``σ_t = 10^{(t − C + L)/10} r⁴``,
and, by memorylessness, a detected cell has RCS ``σ_t + Exp(μ)``. Expected count ``Σ exp(−σ_t/μ)`` over all cells.
No CFAR adaptation is modelled (a cell-averaging CFAR would raise the threshold inside homogeneous clutter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .dsd import SNOW_LAWS, exponential_moment, marshall_palmer
from .fall_speed import atlas_ulbrich_m_per_s, snow_power_law_m_per_s
from .mie import efficiency_table
from .radar_link import SPEED_OF_LIGHT_M_PER_S, water_permittivity

RAIN_D_MAX_MM = 10.0                        # RISE: Marshall–Palmer drops up to 10 mm
SNOW_D_MAX_MM = 10.0
ATLAS_ULBRICH_D_MAX_MM = 5.0                # validity limit of v = 3.778 D^0.67; larger drops fall at the 5 mm speed
ICE_PERMITTIVITY_77GHZ = complex(3.15, -0.005)   # −15 °C (RISE alternative), nearly frequency independent
_NEGLIGIBLE_LOG = math.log(1e9)             # cells with detection probability < 1e-9 are skipped


SCATTERING = ("mie", "analytic")


@dataclass(frozen=True)
class Hydrometeors:
    """Exponential size distribution ``N(D) = N0 e^{−ΛD}`` (D in mm, N in m⁻³ mm⁻¹) on [0, d_max], with the
    complex permittivity (engineering sign), fall-speed law and backscatter model (``SCATTERING``) of the
    particles."""

    kind: str                 # "rain" | "snow"
    n0_per_m3_mm: float
    lam_per_mm: float
    d_max_mm: float
    permittivity: complex
    scattering: str = "mie"

    def fall_speed_m_per_s(self, d_mm) -> np.ndarray:
        """Rain: Atlas–Ulbrich (capped at its 5 mm validity limit); snow: ``v = 0.8 D^0.16`` (fall_speed.py)."""
        if self.kind == "rain":
            return atlas_ulbrich_m_per_s(np.minimum(d_mm, ATLAS_ULBRICH_D_MAX_MM))
        return snow_power_law_m_per_s(d_mm)


def rain_drops(rain_rate_mm_per_h: float, frequency_hz: float = 77e9, temperature_c: float = 20.0,
               scattering: str = "mie") -> Hydrometeors:
    """Marshall–Palmer rain with the double-Debye water permittivity of ITU-R P.840 (77 GHz, 20 °C:
    8.81 − 15.90i; RISE used 12 − 25i, a value closer to ~40 GHz water)."""
    n0, lam = marshall_palmer(rain_rate_mm_per_h)
    return Hydrometeors("rain", n0, lam, RAIN_D_MAX_MM, water_permittivity(frequency_hz, temperature_c), scattering)


def snow_flakes(snowfall_rate_mm_per_h: float, law: str = "gunn_marshall", scattering: str = "mie") -> Hydrometeors:
    """Exponential snow DSD (liquid-equivalent rate) as solid ice spheres of the DSD diameter, ε_ice = 3.15 − 0.005i."""
    n0, lam = SNOW_LAWS[law](snowfall_rate_mm_per_h)
    return Hydrometeors("snow", n0, lam, SNOW_D_MAX_MM, ICE_PERMITTIVITY_77GHZ, scattering)


def fresnel_reflectivity(permittivity: complex) -> float:
    """Normal-incidence power reflectivity ``|(√ε − 1)/(√ε + 1)|²`` (water, ε = 12 − 25i: 0.5264)."""
    n = np.sqrt(complex(permittivity))
    return float(abs((n - 1) / (n + 1)) ** 2)


def rayleigh_optical_boundary_mm(wavelength_m: float) -> float:
    """``D = λ/π`` (size parameter 1): 1.240 mm at 77 GHz."""
    return wavelength_m / math.pi * 1e3


def refractive_index(permittivity: complex) -> complex:
    """``m = n + iκ`` (κ ≥ 0) from ``ε = ε' − iε''``: water at 77 GHz, ε = 12 − 25i → 4.457 + 2.805i."""
    return complex(np.sqrt(complex(permittivity))).conjugate()


_MIE_TABLE_SIZE = 1000
_MIE_D_MIN_MM = 1e-3


@lru_cache(maxsize=16)
def _mie_backscatter_table(permittivity: complex, wavelength_m: float, d_max_mm: float):
    """``(log D, log Q_back)`` on 1000 log-spaced diameters from 1 µm to d_max (cached)."""
    d = np.geomspace(_MIE_D_MIN_MM, d_max_mm, _MIE_TABLE_SIZE)
    x = math.pi * d * 1e-3 / wavelength_m
    _, q_back = efficiency_table(refractive_index(permittivity), tuple(x.tolist()))
    return np.log(d), np.log(q_back)


def backscatter_cross_section_m2(d_mm, wavelength_m: float, permittivity: complex, scattering: str = "mie",
                                 d_max_mm: float = RAIN_D_MAX_MM) -> np.ndarray:
    """σ_b(D) (m²). ``mie``: ``Q_back π r²`` interpolated log–log in the cached table (below 1 µm the Rayleigh
    law ``Q_back ∝ D⁴``); ``analytic``: ``(9/4) ρ_F π⁵ D⁶/λ⁴`` below ``D = λ/π``, ``ρ_F π D²/4`` above."""
    d_m = np.asarray(d_mm, dtype=float) * 1e-3
    if scattering == "mie":
        log_d, log_q = _mie_backscatter_table(complex(permittivity), wavelength_m, max(d_max_mm, 2 * _MIE_D_MIN_MM))
        with np.errstate(divide="ignore"):
            ld = np.log(np.maximum(d_m * 1e3, 1e-300))
        log_q_d = np.where(ld < log_d[0], log_q[0] + 4 * (ld - log_d[0]), np.interp(ld, log_d, log_q))
        return np.where(d_m > 0, np.exp(log_q_d) * math.pi * d_m ** 2 / 4, 0.0)
    if scattering != "analytic":
        raise ValueError(f"scattering must be one of {SCATTERING}, got {scattering!r}")
    rho = fresnel_reflectivity(permittivity)
    rayleigh = 2.25 * rho * math.pi ** 5 * d_m ** 6 / wavelength_m ** 4
    optical = rho * math.pi * d_m ** 2 / 4
    return np.where(d_m < wavelength_m / math.pi, rayleigh, optical)


@lru_cache(maxsize=64)
def backscatter_per_volume_per_m(h: Hydrometeors, wavelength_m: float) -> float:
    """η (m²/m³) over the DSD: Mie on 10⁴ diameters (trapezoid), or the analytic cross-section in closed form."""
    if h.scattering == "mie":
        d = np.linspace(0.0, h.d_max_mm, 10_001)
        sigma = backscatter_cross_section_m2(d, wavelength_m, h.permittivity, "mie", h.d_max_mm)
        return float(np.trapezoid(h.n0_per_m3_mm * np.exp(-h.lam_per_mm * d) * sigma, d))
    rho = fresnel_reflectivity(h.permittivity)
    d_c = min(rayleigh_optical_boundary_mm(wavelength_m), h.d_max_mm)
    m6 = exponential_moment(h.n0_per_m3_mm, h.lam_per_mm, 6, 0.0, d_c) * 1e-18      # mm⁶ → m⁶
    m2 = exponential_moment(h.n0_per_m3_mm, h.lam_per_mm, 2, d_c, h.d_max_mm) * 1e-6  # mm² → m²
    return 2.25 * rho * math.pi ** 5 / wavelength_m ** 4 * m6 + rho * math.pi / 4 * m2


def radar_wavelength_m(frequency_hz: float) -> float:
    return SPEED_OF_LIGHT_M_PER_S / frequency_hz


# --- Doppler of falling particles ---------------------------------------------------------------------------------


def particle_radial_velocity_m_per_s(directions: np.ndarray, fall_speed_m_per_s, ego_velocity_m_per_s,
                                     wind_velocity_m_per_s=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``v_ρ = (wind − v_t ẑ − v_ego)·r̂`` for unit directions (N, 3) in the sensor frame (receding > 0)."""
    d = np.asarray(directions, dtype=float)
    u = np.asarray(wind_velocity_m_per_s, dtype=float) - np.asarray(ego_velocity_m_per_s, dtype=float)
    return d @ u - np.asarray(fall_speed_m_per_s, dtype=float) * d[:, 2]


# --- resolution cells ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ResolutionGrid:
    """Detection cells of a 4D imaging radar: azimuth × elevation cells (boresight-centred field of view, uniform in
    angle) × range bins [min_range, max_range) × Doppler bins centred on multiples of the Doppler resolution."""

    fov_azimuth_deg: float
    fov_elevation_deg: float
    azimuth_resolution_deg: float
    elevation_resolution_deg: float
    range_resolution_m: float
    doppler_resolution_m_per_s: float
    min_range_m: float
    max_range_m: float

    def azimuth_edges_rad(self) -> np.ndarray:
        return angular_edges_rad(self.fov_azimuth_deg, self.azimuth_resolution_deg)

    def elevation_edges_rad(self) -> np.ndarray:
        return angular_edges_rad(self.fov_elevation_deg, self.elevation_resolution_deg)

    def range_edges_m(self) -> np.ndarray:
        n = int(math.floor((self.max_range_m - self.min_range_m) / self.range_resolution_m + 1e-9))
        return self.min_range_m + self.range_resolution_m * np.arange(n + 1)


def angular_edges_rad(fov_deg: float, resolution_deg: float) -> np.ndarray:
    """Cell edges of a boresight-centred field of view: ``round(fov/res)`` equal cells (at least one)."""
    n = max(1, int(round(fov_deg / resolution_deg)))
    half = math.radians(min(fov_deg, 180.0)) / 2
    return np.linspace(-half, half, n + 1)


def angular_cell_index(positions_m: np.ndarray, az_edges_rad: np.ndarray, el_edges_rad: np.ndarray) -> np.ndarray:
    """Flat index ``i_az · n_el + i_el`` of each point's cell on uniform edges (:func:`angular_edges_rad`),
    az = atan2(y, x), el = atan2(z, √(x² + y²)); points outside the field of view fall in the nearest edge cell."""
    p = np.asarray(positions_m, dtype=float)
    az = np.arctan2(p[:, 1], p[:, 0])
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    n_az, n_el = len(az_edges_rad) - 1, len(el_edges_rad) - 1
    i_az = np.clip(((az - az_edges_rad[0]) * (n_az / (az_edges_rad[-1] - az_edges_rad[0]))).astype(np.int64),
                   0, n_az - 1)
    i_el = np.clip(((el - el_edges_rad[0]) * (n_el / (el_edges_rad[-1] - el_edges_rad[0]))).astype(np.int64),
                   0, n_el - 1)
    return i_az * n_el + i_el


@lru_cache(maxsize=16)
def _doppler_shape_tables(h: Hydrometeors, wavelength_m: float, z_edges: tuple[float, ...], dx: float):
    """Per elevation row j, the distribution of ``X = v_t z`` (v_t backscatter-weighted over the DSD, z = sin el
    uniform over the row): CDF ``G_j`` and its integral ``H_j`` on a common grid x0 + i·dx."""
    d = (np.arange(256) + 0.5) * (h.d_max_mm / 256)
    w = np.exp(-h.lam_per_mm * d) * backscatter_cross_section_m2(d, wavelength_m, h.permittivity, h.scattering,
                                                                 h.d_max_mm)
    w = w / w.sum()
    v = h.fall_speed_m_per_s(d)
    z = np.asarray(z_edges)
    x_ext = float(v.max() * np.abs(z).max()) + 2 * dx
    n = int(math.ceil(x_ext / dx))
    x = dx * np.arange(-n, n + 1)
    g = np.empty((len(z) - 1, len(x)))
    for j in range(len(z) - 1):
        frac = np.clip((x[None, :] / v[:, None] - z[j]) / (z[j + 1] - z[j]), 0.0, 1.0)
        g[j] = w @ frac
    hh = np.concatenate([np.zeros((len(g), 1)), np.cumsum((g[:, 1:] + g[:, :-1]) * (dx / 2), axis=1)], axis=1)
    x_min = np.minimum(z[:-1] * v.max(), z[:-1] * v.min())
    x_max = np.maximum(z[1:] * v.max(), z[1:] * v.min())
    return float(x[0]), g, hh, x_min, x_max


def _table_eval(table: np.ndarray, row: np.ndarray, y: np.ndarray, x0: float, dx: float, integral: bool):
    """Linear interpolation of ``table[row]`` at y; left of the grid 0, right of it G = 1 and H grows with slope 1."""
    nx = table.shape[1]
    f = (y - x0) / dx
    i = np.clip(np.floor(f).astype(np.int64), 0, nx - 2)
    t = np.clip(f - i, 0.0, 1.0)
    val = table[row, i] * (1 - t) + table[row, i + 1] * t
    right = f > nx - 1
    if integral:
        val = np.where(right, table[row, nx - 1] + (f - (nx - 1)) * dx, val)
    else:
        val = np.where(right, 1.0, val)
    return np.where(f < 0, 0.0, val)


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(owner, j)`` for ``j in range(counts[owner])`` over all owners, flattened (vectorised ragged arange)."""
    total = int(counts.sum())
    owner = np.repeat(np.arange(len(counts)), counts)
    return owner, np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)


@lru_cache(maxsize=8)
def cell_doppler_probabilities(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float,
                               relative_velocity_m_per_s: tuple[float, float, float]
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fraction of each angular cell's clutter power per Doppler bin: ``(cell, bin m, P)`` for every pair with
    P > 0 (cached: read-only arrays). ``relative_velocity = wind − ego`` in the sensor frame. In a cell
    ``v = c − X`` with ``c = relative_velocity·r̂`` taken uniform over its range across the cell (corners and
    centre) and ``X = v_t z`` from the shape tables, so ``P = E_c[G(c − v_lo) − G(c − v_hi)]``, in closed form
    through the integral H of G."""
    az_e, el_e = grid.azimuth_edges_rad(), grid.elevation_edges_rad()
    dv = grid.doppler_resolution_m_per_s
    dx = dv / 20
    x0, g, hh, x_min, x_max = _doppler_shape_tables(h, wavelength_m, tuple(np.sin(el_e).tolist()), dx)
    n_az, n_el = len(az_e) - 1, len(el_e) - 1

    def c_of(az, el):  # radial velocity of a particle at rest in the wind, on an az × el lattice
        az, el = np.broadcast_arrays(az[:, None], el[None, :])
        dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
        return particle_radial_velocity_m_per_s(dirs, 0.0, (0.0, 0.0, 0.0), relative_velocity_m_per_s
                                                ).reshape(az.shape)

    corners = c_of(az_e, el_e)
    centre = c_of(0.5 * (az_e[:-1] + az_e[1:]), 0.5 * (el_e[:-1] + el_e[1:]))
    quad = np.stack([corners[:-1, :-1], corners[1:, :-1], corners[:-1, 1:], corners[1:, 1:], centre])
    c_lo, c_hi = quad.min(axis=0).ravel(), quad.max(axis=0).ravel()
    rows = np.tile(np.arange(n_el), n_az)
    m_lo = np.floor((c_lo - x_max[rows]) / dv + 0.5).astype(np.int64)
    m_hi = np.floor((c_hi - x_min[rows]) / dv + 0.5).astype(np.int64)
    # values at the bin edges v_e = (m − 1/2) Δv, e = 0 … n per cell: P of bin m is F(v_lo) − F(v_hi) with
    # F(v) = [H(c_hi − v) − H(c_lo − v)]/(c_hi − c_lo), or G(c − v) when c does not vary across the cell
    cell_e, e = _expand(m_hi - m_lo + 2)
    row, cl, ch = rows[cell_e], c_lo[cell_e], c_hi[cell_e]
    v_edge = (m_lo[cell_e] + e - 0.5) * dv
    width = ch - cl
    spread = width > dx * 1e-3
    f = np.empty(len(e))
    s, t = spread, ~spread
    f[s] = (_table_eval(hh, row[s], ch[s] - v_edge[s], x0, dx, True)
            - _table_eval(hh, row[s], cl[s] - v_edge[s], x0, dx, True)) / width[s]
    f[t] = _table_eval(g, row[t], cl[t] - v_edge[t], x0, dx, False)
    last = np.cumsum(m_hi - m_lo + 2) - 1                  # the upper edge of each cell's last bin
    lower = np.ones(len(e), dtype=bool)
    lower[last] = False
    cell, m = cell_e[lower], (m_lo[cell_e] + e)[lower]
    p = f[:-1][lower[:-1]] - f[1:][lower[:-1]]
    keep = p > 1e-12
    out = cell[keep], m[keep], p[keep]
    for a in out:
        a.flags.writeable = False
    return out


@lru_cache(maxsize=8)
def _pairs_by_weight(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float,
                     relative_velocity_m_per_s: tuple[float, float, float]):
    """(cell, Doppler bin) pairs sorted by decreasing ``ΔΩ P`` (clutter RCS per unit η and shell volume), so that
    the pairs that can reach the threshold in a range bin are a prefix."""
    cell, m, p = cell_doppler_probabilities(h, grid, wavelength_m, relative_velocity_m_per_s)
    az_e, z_e = grid.azimuth_edges_rad(), np.sin(grid.elevation_edges_rad())
    weight = (np.diff(az_e)[:, None] * np.diff(z_e)[None, :]).ravel()[cell] * p
    order = np.argsort(-weight)
    out = cell[order], m[order], weight[order]
    for a in out:
        a.flags.writeable = False
    return out


@dataclass(frozen=True)
class ClutterCells:
    """Resolution cells that may reach the threshold (probability > 1e-9): one row per candidate cell, built
    from (angular cell, Doppler bin) pairs × range bins."""

    grid: ResolutionGrid
    radar_constant_db: float
    threshold_db: float
    gamma_db_per_km: float
    pair_cell: np.ndarray         # per pair: flat azimuth–elevation cell index
    pair_doppler_bin: np.ndarray  # per pair: Doppler bin m
    pair_rcs_per_m3: np.ndarray   # per pair: η ΔΩ P(v_m), μ per unit of (r_hi³ − r_lo³)/3
    pair: np.ndarray              # per candidate: its pair
    range_bin: np.ndarray         # per candidate: range bin k
    probability: np.ndarray       # per candidate: exp(−σ_t/μ)

    @property
    def expected_count(self) -> float:
        return float(self.probability.sum())


def _range_bins(grid: ResolutionGrid, radar_constant_db: float, threshold_db: float, gamma_db_per_km: float):
    """Edges, centres, ``(r_hi³ − r_lo³)/3`` and the threshold RCS σ_t of every range bin."""
    r_e = grid.range_edges_m()
    r_c = 0.5 * (r_e[:-1] + r_e[1:])
    shell = (r_e[1:] ** 3 - r_e[:-1] ** 3) / 3
    sigma_t = 10 ** ((threshold_db - radar_constant_db + 2 * gamma_db_per_km * r_c / 1000) / 10) * r_c ** 4
    return r_e, r_c, shell, sigma_t


def clutter_cells(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float, relative_velocity_m_per_s,
                  radar_constant_db: float, threshold_db: float, gamma_db_per_km: float = 0.0) -> ClutterCells:
    """Detection probabilities of every relevant cell. The detection statistic of an echo of RCS σ at range r is
    ``D = C + 10 log10 σ − 40 log10 r − 2 γ r/1000`` (dB); a cell is detected when ``D ≥ t``."""
    eta = backscatter_per_volume_per_m(h, wavelength_m)
    cell, m, weight = _pairs_by_weight(h, grid, wavelength_m, tuple(float(v) for v in relative_velocity_m_per_s))
    _, _, shell, sigma_t = _range_bins(grid, radar_constant_db, threshold_db, gamma_db_per_km)
    tau = sigma_t / shell                                   # μ = g · shell with g = η ΔΩ P: p = exp(−τ/g)
    g = eta * weight                                        # decreasing
    n_pairs = np.searchsorted(-g, -tau / _NEGLIGIBLE_LOG, side="left")    # pairs with g > τ/ln(1e9)
    k, pair = _expand(n_pairs)
    prob = np.exp(-tau[k] / g[pair])
    return ClutterCells(grid, radar_constant_db, threshold_db, gamma_db_per_km, cell, m, g, pair, k, prob)


@dataclass(frozen=True)
class ClutterPoints:
    positions_m: np.ndarray       # (M, 3)
    v_r_m_per_s: np.ndarray
    detection_db: np.ndarray      # D of the detected cell (≥ threshold), two-way loss included


def generate_clutter(rng: np.random.Generator, cells: ClutterCells) -> ClutterPoints:
    """Draw the detected cells (Bernoulli with ``exp(−σ_t/μ)``), their RCS ``σ_t + Exp(μ)``, and one point per
    detected cell: range uniform in the bin, direction uniform in solid angle within the angular cell, radial
    velocity uniform within the Doppler bin."""
    grid = cells.grid
    hit = np.flatnonzero(rng.random(len(cells.probability)) < cells.probability)
    pair, k = cells.pair[hit], cells.range_bin[hit]
    r_e, r_c, shell, sigma_t = _range_bins(grid, cells.radar_constant_db, cells.threshold_db, cells.gamma_db_per_km)
    sigma = sigma_t[k] + rng.exponential(cells.pair_rcs_per_m3[pair] * shell[k])
    az_e, z_e = grid.azimuth_edges_rad(), np.sin(grid.elevation_edges_rad())
    i_az, i_el = np.divmod(cells.pair_cell[pair], len(z_e) - 1)
    u = rng.random((4, len(hit)))
    r = r_e[k] + u[0] * (r_e[k + 1] - r_e[k])
    az = az_e[i_az] + u[1] * (az_e[i_az + 1] - az_e[i_az])
    z = z_e[i_el] + u[2] * (z_e[i_el + 1] - z_e[i_el])
    c = np.sqrt(1 - z * z)
    positions = r[:, None] * np.stack([c * np.cos(az), c * np.sin(az), z], axis=1)
    v_r = (cells.pair_doppler_bin[pair] + u[3] - 0.5) * grid.doppler_resolution_m_per_s
    detection = (cells.radar_constant_db + 10 * np.log10(sigma) - 40 * np.log10(r_c[k])
                 - 2 * cells.gamma_db_per_km * r_c[k] / 1000)
    return ClutterPoints(positions, v_r, detection)
