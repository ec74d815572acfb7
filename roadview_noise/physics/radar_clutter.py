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
random-phase drops); ``y = μ/σ_t`` with ``σ_t = 10^{(t − C + L)/10} r⁴`` the RCS at the clear-air threshold decides
the detection probability through the detector (physics/radar_cfar.py): fixed threshold ``e^{−1/y}`` (models.md
§4.3) or CA-CFAR (≤ P_fa per cell). Cells are drawn exactly (independent Bernoulli per cell, by thinning in
probability tiers, so the work follows the expected count rather than the number of cells); the expected count
``Σ P(y)`` over all cells comes from a cached table (FFT correlation of the cells' ln μ histogram with P). A point
target's cell gives the CA-CFAR threshold rise (:meth:`ClutterCells.ratio_at`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft as sp_fft

from .compiled import jit
from .dsd import capped_snow_law, exponential_moment, marshall_palmer
from .fall_speed import atlas_srivastava_sekhon_m_per_s, snow_power_law_m_per_s
from .mie import efficiency_table
from .numpy_sums import numpy_sum
from .radar_cfar import PROBABILITY_TIERS, Detector, FixedThreshold, tier_ratios
from .radar_link import SPEED_OF_LIGHT_M_PER_S, water_permittivity
from ..table_cache import disk_cached

RAIN_D_MAX_MM = 10.0                        # RISE: Marshall–Palmer drops up to 10 mm
SNOW_D_MAX_MM = 10.0
ICE_PERMITTIVITY_77GHZ = complex(3.15, -0.005)   # −15 °C (RISE alternative), nearly frequency independent


SCATTERING = ("mie", "analytic")


def _read_only(*arrays):
    for a in arrays:
        a.flags.writeable = False
    return arrays


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
        """Rain: Atlas, Srivastava & Sekhon (1973), levelling off at 9.65 m/s for the largest drops; snow:
        ``v = 0.8 D^0.16`` (fall_speed.py)."""
        if self.kind == "rain":
            return atlas_srivastava_sekhon_m_per_s(d_mm)
        return snow_power_law_m_per_s(d_mm)


@lru_cache(maxsize=16)          # the same particles for every frame of a run (and one hash for the tables' caches)
def rain_drops(rain_rate_mm_per_h: float, frequency_hz: float = 77e9, temperature_c: float = 20.0,
               scattering: str = "mie") -> Hydrometeors:
    """Marshall–Palmer rain with the double-Debye water permittivity of ITU-R P.840 (77 GHz, 20 °C:
    8.81 − 15.90i; RISE used 12 − 25i, a value closer to ~40 GHz water)."""
    n0, lam = marshall_palmer(rain_rate_mm_per_h)
    return Hydrometeors("rain", n0, lam, RAIN_D_MAX_MM, water_permittivity(frequency_hz, temperature_c), scattering)


@lru_cache(maxsize=16)
def snow_flakes(snowfall_rate_mm_per_h: float, law: str = "gunn_marshall", scattering: str = "mie") -> Hydrometeors:
    """Exponential snow DSD (liquid-equivalent rate) as solid ice spheres of the DSD diameter, ε_ice = 3.15 − 0.005i;
    below the law's fitted range the same crystals, fewer (:func:`~roadview_noise.physics.dsd.capped_snow_law`)."""
    n0, lam = capped_snow_law(snowfall_rate_mm_per_h, law)
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


@disk_cached(maxsize=16)
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


@dataclass(frozen=True, eq=False)
class GridEdges:
    """A grid's edges, computed once per grid (read-only): range bins, their centres and ``(r_hi³ − r_lo³)/3``,
    azimuth and elevation edges, and the sines of the latter."""

    range_m: np.ndarray
    range_centre_m: np.ndarray
    shell_volume_per_sr_m3: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    elevation_sine: np.ndarray


@lru_cache(maxsize=16)
def grid_edges(grid: ResolutionGrid) -> GridEdges:
    r_e, el_e = grid.range_edges_m(), grid.elevation_edges_rad()
    return GridEdges(*_read_only(r_e, 0.5 * (r_e[:-1] + r_e[1:]), (r_e[1:] ** 3 - r_e[:-1] ** 3) / 3,
                                 grid.azimuth_edges_rad(), el_e, np.sin(el_e)))


@lru_cache(maxsize=64)
def angular_edges_rad(fov_deg: float, resolution_deg: float) -> np.ndarray:
    """Cell edges of a boresight-centred field of view: ``round(fov/res)`` equal cells (at least one; cached,
    read-only)."""
    n = max(1, int(round(fov_deg / resolution_deg)))
    half = math.radians(min(fov_deg, 180.0)) / 2
    return _read_only(np.linspace(-half, half, n + 1))[0]


def angular_cell_index(positions_m: np.ndarray, az_edges_rad: np.ndarray, el_edges_rad: np.ndarray) -> np.ndarray:
    """Flat index ``i_az · n_el + i_el`` of each point's cell on uniform edges (:func:`angular_edges_rad`),
    az = atan2(y, x), el = atan2(z, √(x² + y²)); points outside the field of view fall in the nearest edge cell."""
    p = np.asarray(positions_m, dtype=float)
    out = np.empty(len(p), dtype=np.int64)
    _cells_of_angles(point_angles(p), *_angular_axes(az_edges_rad, el_edges_rad), out)
    return out


def point_angles(positions_m: np.ndarray) -> np.ndarray:
    """Azimuths then elevations of (N, 3) float64 positions, (2N,): NumPy's ``arctan2`` of y, x and of z, √(x² + y²)
    in one call (its SIMD values, which compiled code would not reproduce bit for bit)."""
    ys, xs = np.empty(2 * len(positions_m)), np.empty(2 * len(positions_m))
    _atan2_arguments(positions_m, ys, xs)
    return np.arctan2(ys, xs)


def _angular_axes(az_edges_rad: np.ndarray, el_edges_rad: np.ndarray) -> tuple:
    """``(az0, az scale, n_az, el0, el scale, n_el)`` of uniform edges for :func:`_cells_of_angles`."""
    n_az, n_el = len(az_edges_rad) - 1, len(el_edges_rad) - 1
    return (float(az_edges_rad[0]), float(n_az / (az_edges_rad[-1] - az_edges_rad[0])), n_az,
            float(el_edges_rad[0]), float(n_el / (el_edges_rad[-1] - el_edges_rad[0])), n_el)


@jit
def _atan2_arguments(positions_m, ys, xs):
    n = len(positions_m)
    for i in range(n):
        x, y = positions_m[i, 0], positions_m[i, 1]
        ys[i], xs[i] = y, x
        ys[n + i], xs[n + i] = positions_m[i, 2], math.hypot(x, y)


@jit
def _edge_cell(angle, first, scale, n):
    """``min(max(int((angle − first) scale), 0), n − 1)`` (truncation toward zero, as NumPy's ``astype``; angles
    are bounded, so no cast overflows)."""
    f = (angle - first) * scale
    if not f > 0.0:                        # (also NaN, which NumPy's cast sends below 0)
        return 0
    return min(int(f), n - 1) if f < n else n - 1


@jit
def _cells_of_angles(angles, az0, az_scale, n_az, el0, el_scale, n_el, out):
    n = len(out)
    for i in range(n):
        out[i] = _edge_cell(angles[i], az0, az_scale, n_az) * n_el + _edge_cell(angles[n + i], el0, el_scale, n_el)


@disk_cached(maxsize=16)
def _doppler_shape_tables(h: Hydrometeors, wavelength_m: float, z_edges: tuple[float, ...], dx: float):
    """Per elevation row j, the distribution of ``X = v_t z`` (v_t backscatter-weighted over the DSD, z = sin el
    uniform over the row): CDF ``G_j`` and its integral ``H_j`` on a common grid x0 + i·dx."""
    d = (np.arange(256) + 0.5) * (h.d_max_mm / 256)
    w = np.exp(-h.lam_per_mm * d) * backscatter_cross_section_m2(d, wavelength_m, h.permittivity, h.scattering,
                                                                 h.d_max_mm)
    w = w / w.sum()
    v = np.maximum(h.fall_speed_m_per_s(d), 1e-9)       # X = v z stays defined for drops at rest (ASS, D < 0.11 mm)
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


def _solid_angles(grid: ResolutionGrid) -> np.ndarray:
    """Solid angle ΔΩ (sr) of every flat azimuth–elevation cell."""
    az_e, z_e = grid.azimuth_edges_rad(), np.sin(grid.elevation_edges_rad())
    return (np.diff(az_e)[:, None] * np.diff(z_e)[None, :]).ravel()


@lru_cache(maxsize=8)
def _pairs_by_weight(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float,
                     relative_velocity_m_per_s: tuple[float, float, float]):
    """(cell, Doppler bin) pairs sorted by decreasing ``ΔΩ P`` (clutter RCS per unit η and shell volume), so that
    the pairs that can be detected in a range bin are a prefix."""
    cell, m, p = cell_doppler_probabilities(h, grid, wavelength_m, relative_velocity_m_per_s)
    weight = _solid_angles(grid)[cell] * p
    order = np.argsort(-weight)
    return _read_only(cell[order], m[order], weight[order])


@disk_cached(maxsize=8)
def _pair_rcs_per_m3(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float,
                     relative_velocity_m_per_s: tuple[float, float, float]):
    """The sorted pairs' ``(cell, m, g, −g)`` with ``g = η ΔΩ P`` (decreasing; −g for ``searchsorted``)."""
    cell, m, weight = _pairs_by_weight(h, grid, wavelength_m, relative_velocity_m_per_s)
    g = backscatter_per_volume_per_m(h, wavelength_m) * weight
    return (cell, m) + _read_only(g, -g)


@disk_cached(maxsize=4)
def _rcs_table(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float,
               relative_velocity_m_per_s: tuple[float, float, float]) -> tuple[int, np.ndarray]:
    """``(m_min, T)``: ``T[cell, m − m_min + 1] = (ΔΩ P) η``, a dense lookup table of the pairs' g with a zero
    column either side, where every Doppler bin outside the clutter spectrum is read (clipped)."""
    cell, m, p = cell_doppler_probabilities(h, grid, wavelength_m, relative_velocity_m_per_s)
    m_min = int(m.min())
    table = np.zeros((len(_solid_angles(grid)), int(m.max()) - m_min + 3))
    table[cell, m - m_min + 1] = _solid_angles(grid)[cell] * p
    return m_min, _read_only(table * backscatter_per_volume_per_m(h, wavelength_m))[0]


_LN10_OVER_10 = math.log(10) / 10
_COUNT_STEP = 0.005        # ln-grid step of the expected-count table
_SATURATED_RATIO = 1e7     # y above which both detectors are within 1e-6 (relative) of their largest probability


def _fft_convolve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Full linear convolution of two real 1-D arrays by FFT: what ``scipy.signal.fftconvolve`` computes (same
    transform sizes, same values), without importing scipy.signal (0.15–0.5 s per worker)."""
    n = len(a) + len(b) - 1
    size = sp_fft.next_fast_len(n, True)
    return sp_fft.irfft(sp_fft.rfft(a, size) * sp_fft.rfft(b, size), size)[:n]


@disk_cached(maxsize=8)
def _count_table(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float,
                 relative_velocity_m_per_s: tuple[float, float, float], detector: Detector):
    """``(w, E)``: ``E(w) = Σ_pairs P(g_p e^w)``, the expected detections of a range bin whose cells have
    ``y = g_p s`` (g = η ΔΩ P, s = e^w), on a uniform grid of w. The pairs' ln g are histogrammed on the step
    with linear splitting and correlated (FFT) with the deficit ``P_max − P(e^v)``, which vanishes above
    ``y = 10⁷``; equal to linear interpolation of P in ln y (relative error ≲ 1e-3)."""
    weight = _pairs_by_weight(h, grid, wavelength_m, relative_velocity_m_per_s)[2]
    lg = np.log(backscatter_per_volume_per_m(h, wavelength_m) * weight)
    step = _COUNT_STEP
    pos = (lg - lg.min()) / step
    i = np.floor(pos).astype(np.int64)
    frac = pos - i
    n_u = int(i.max()) + 2
    hist = np.bincount(i, 1 - frac, minlength=n_u) + np.bincount(i + 1, frac, minlength=n_u)
    v0 = math.log(tier_ratios(detector)[-1])
    v = v0 + step * np.arange(int(math.ceil((math.log(_SATURATED_RATIO) - v0) / step)) + 1)
    p_max = detector.max_probability
    deficit = p_max - detector.probability(np.exp(v))
    # E at offset d (pair i sits at v_{i+d}): pairs with i + d < 0 are negligible, those past the table saturated
    d = np.arange(-(n_u - 1), len(v))
    suffix = np.cumsum(hist[::-1])[::-1]
    expected = p_max * suffix[np.maximum(-d, 0)] - _fft_convolve(hist[::-1], deficit)
    w = v0 - lg.min() + step * d
    return _read_only(w, np.maximum(expected, 0.0)) + (p_max * len(lg),)


@dataclass(frozen=True, eq=False)
class ClutterTables:
    """What the clutter of a frame takes from the particles, grid, wavelength, relative velocity (wind − ego) and
    detector alone (:func:`clutter_tables`; a model holds them for its frames): the (angular cell, Doppler bin)
    pairs sorted by decreasing ``g = η ΔΩ P`` (and −g, for the searches), the dense look-up of g by cell and bin
    (``rcs_table``, bin ``m`` in column ``m − doppler_bin_min + 1``), the expected-count table, the detector's
    tiers and the grid's edges."""

    hydrometeors: Hydrometeors
    grid: ResolutionGrid
    wavelength_m: float
    relative_velocity_m_per_s: tuple[float, float, float]
    detector: Detector
    pair_cell: np.ndarray
    pair_doppler_bin: np.ndarray
    pair_rcs_per_m3: np.ndarray
    minus_pair_rcs_per_m3: np.ndarray
    doppler_bin_min: int
    rcs_table: np.ndarray
    count_table: tuple[np.ndarray, np.ndarray, float]
    tier_ratios: np.ndarray
    tier_probabilities: tuple[np.ndarray, np.ndarray, bool]
    edges: GridEdges
    angular_axes: tuple                   # :func:`_angular_axes` of the edges
    backscatter_per_m: float


def clutter_tables(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float, relative_velocity_m_per_s,
                   detector: Detector = FixedThreshold()) -> ClutterTables:
    """The tables at ``relative_velocity = wind − ego`` (sensor frame), from the caches that build them."""
    rel = tuple(float(v) for v in relative_velocity_m_per_s)
    edges = grid_edges(grid)
    return ClutterTables(h, grid, wavelength_m, rel, detector, *_pair_rcs_per_m3(h, grid, wavelength_m, rel),
                         *_rcs_table(h, grid, wavelength_m, rel), _count_table(h, grid, wavelength_m, rel, detector),
                         tier_ratios(detector), _tier_probabilities(detector.max_probability), edges,
                         _angular_axes(edges.azimuth_rad, edges.elevation_rad),
                         backscatter_per_volume_per_m(h, wavelength_m))


@dataclass(frozen=True, eq=False)
class ClutterCells:
    """The resolution cells of one frame that a detector may declare: the pairs of its :class:`ClutterTables`
    crossed with the range bins, ``y = μ/σ_t = pair_rcs_per_m3 × range_ratio_per_rcs``. In range bin k, probability
    tier j (0 … 29) holds the pairs from ``tier_bounds[k, j − 1]`` (0 for j = 0) to ``tier_bounds[k, j] − 1``,
    whose cells have ``P ≤ 2^{−j} P_max`` (physics/radar_cfar.py ``tier_ratios``); the pairs past
    ``tier_bounds[k, 29]`` are negligible. ``tier_cells``: the cells of each tier over all range bins."""

    tables: ClutterTables
    radar_constant_db: float
    threshold_db: float
    gamma_db_per_km: float
    range_ratio_per_rcs: np.ndarray  # per range bin: (r_hi³ − r_lo³)/(3 σ_t) (m³/m²)
    tier_bounds: np.ndarray          # (range bins, 30): end of each probability tier among the sorted pairs
    tier_cells: np.ndarray
    expected_count: float            # Σ P(y) over all cells

    hydrometeors = property(lambda self: self.tables.hydrometeors)
    grid = property(lambda self: self.tables.grid)
    wavelength_m = property(lambda self: self.tables.wavelength_m)
    detector = property(lambda self: self.tables.detector)
    pair_cell = property(lambda self: self.tables.pair_cell)
    pair_doppler_bin = property(lambda self: self.tables.pair_doppler_bin)
    pair_rcs_per_m3 = property(lambda self: self.tables.pair_rcs_per_m3)

    def ratio_at(self, positions_m: np.ndarray, v_r_m_per_s: np.ndarray,
                 ranges_m: np.ndarray | None = None) -> np.ndarray:
        """``y = μ/σ_t`` of the resolution cell of each point (any range; ``ranges_m`` their norms, when known):
        its angular cell (nearest edge cell outside the field of view), its Doppler bin, and a range bin centred
        on it."""
        r = np.linalg.norm(positions_m, axis=1) if ranges_m is None else ranges_m
        return _point_ratios(self.tables, np.exp(_exponents(self.threshold_db - self.radar_constant_db,
                                                           self.gamma_db_per_km, _NO_RANGES, r)),
                             positions_m, v_r_m_per_s, r)


_NO_RANGES = np.zeros(0)


def _exponents(t_minus_c_db: float, gamma_db_per_km: float, r_first_m: np.ndarray, r_second_m: np.ndarray
               ) -> np.ndarray:
    """``ln10/10 (t − C + 2 γ r/1000)`` at two arrays of ranges, concatenated, whose NumPy ``exp`` (its SIMD
    values, which compiled code would not reproduce bit for bit) times ``r⁴`` is σ_t, the RCS whose statistic
    ``C + 10 log10 σ − 40 log10 r − 2 γ r/1000`` equals the threshold t."""
    out = np.empty(len(r_first_m) + len(r_second_m))
    _exponent_arguments(t_minus_c_db, 2e-3 * gamma_db_per_km, r_first_m, r_second_m, out)
    return out


@jit
def _exponent_arguments(a, b, r_first, r_second, out):
    n = len(r_first)
    for k in range(n):
        out[k] = _LN10_OVER_10 * (a + b * r_first[k])
    for i in range(len(r_second)):
        out[n + i] = _LN10_OVER_10 * (a + b * r_second[i])


def _point_ratios(tables: ClutterTables, exp_points: np.ndarray, positions_m: np.ndarray, v_r_m_per_s: np.ndarray,
                  ranges_m: np.ndarray) -> np.ndarray:
    """:meth:`ClutterCells.ratio_at` from ``exp_points``, the exponentials of the points' :func:`_exponents`."""
    p = np.asarray(positions_m, dtype=float)
    grid = tables.grid
    out = np.empty(len(p))
    dr = grid.range_resolution_m
    _point_ratio_kernel(point_angles(p), *tables.angular_axes, np.asarray(v_r_m_per_s),
                        grid.doppler_resolution_m_per_s, tables.rcs_table, tables.doppler_bin_min - 1,
                        np.asarray(ranges_m, dtype=float), dr, dr ** 3 / 12, exp_points, out)
    return out


@jit
def _point_ratio_kernel(angles, az0, az_scale, n_az, el0, el_scale, n_el, v_r, dv, table, column_offset, ranges, dr,
                        dr3_over_12, exp_points, out):
    """``y = g (r² Δr + Δr³/12)/σ_t`` (0 at r = 0) with g the table's value at the point's angular cell and Doppler
    bin ``floor(v/Δv + 1/2)`` (clipped onto the zero columns at either side) and ``σ_t = e r² r²``."""
    n, last = len(out), table.shape[1] - 1
    for i in range(n):
        cell = _edge_cell(angles[i], az0, az_scale, n_az) * n_el + _edge_cell(angles[n + i], el0, el_scale, n_el)
        f = math.floor(v_r[i] / dv + 0.5)
        g = 0.0                                                     # outside the table: its zero columns
        if abs(f) < 2.0 ** 62:
            g = table[cell, min(max(int(f) - column_offset, 0), last)]
        r = ranges[i]
        if r > 0:
            r2 = r * r
            out[i] = g * (r * r * dr + dr3_over_12) / (exp_points[i] * r2 * r2)
        else:
            out[i] = 0.0


def clutter_cells(h: Hydrometeors, grid: ResolutionGrid, wavelength_m: float, relative_velocity_m_per_s,
                  radar_constant_db: float, threshold_db: float, gamma_db_per_km: float = 0.0,
                  detector: Detector = FixedThreshold()) -> ClutterCells:
    """The cells of a frame with radar constant C (dB), clear-air threshold t (dB, same statistic) and specific
    attenuation γ; ``relative_velocity = wind − ego`` in the sensor frame. The detection statistic of an echo of RCS
    σ at range r is ``D = C + 10 log10 σ − 40 log10 r − 2 γ r/1000`` (dB)."""
    tables = clutter_tables(h, grid, wavelength_m, relative_velocity_m_per_s, detector)
    return frame_cells(tables, radar_constant_db, threshold_db, gamma_db_per_km)[0]


def frame_cells(tables: ClutterTables, radar_constant_db: float, threshold_db: float, gamma_db_per_km: float,
                positions_m: np.ndarray | None = None, v_r_m_per_s: np.ndarray | None = None,
                ranges_m: np.ndarray | None = None) -> tuple[ClutterCells, np.ndarray | None]:
    """The frame's cells (:func:`clutter_cells`) and, for points given (their radial velocities and ranges),
    :meth:`ClutterCells.ratio_at` of each: one ``exp`` for both, the rest in compiled passes."""
    edges = tables.edges
    r_bins = edges.range_centre_m
    nb = len(r_bins)
    e = np.exp(_exponents(threshold_db - radar_constant_db, gamma_db_per_km, r_bins,
                          _NO_RANGES if positions_m is None else ranges_m))
    ratio = np.empty(nb)
    bounds = np.zeros((nb, PROBABILITY_TIERS), dtype=np.intp)
    cells_per_tier = np.zeros(PROBABILITY_TIERS, dtype=np.intp)
    g = tables.pair_rcs_per_m3
    _tier_bound_kernel(e, r_bins, edges.shell_volume_per_sr_m3, tables.tier_ratios, tables.minus_pair_rcs_per_m3,
                       g[0] if len(g) else math.inf, ratio, bounds, cells_per_tier)
    expected = _expected_count(np.log(ratio), *tables.count_table)
    cells = ClutterCells(tables, radar_constant_db, threshold_db, gamma_db_per_km, ratio, bounds, cells_per_tier,
                         expected)
    return cells, None if positions_m is None else _point_ratios(tables, e[nb:], positions_m, v_r_m_per_s, ranges_m)


@jit
def _tier_bound_kernel(e, r_centre, shell, tiers, minus_g, g_max, ratio, bounds, cells_per_tier):
    """Per range bin k: ``ratio = shell/σ_t`` (σ_t = e r² r²) and, unless its lowest tier bound is at or above the
    largest g (no pair in any tier: most bins beyond a few metres), the end of each tier j among the pairs
    (``searchsorted(−g, −tiers[j]/ratio, "left")``); the cells per tier over all bins."""
    nt = len(tiers)
    for k in range(len(r_centre)):
        r2 = r_centre[k] * r_centre[k]
        ratio[k] = shell[k] / (e[k] * r2 * r2)
        if tiers[nt - 1] / ratio[k] >= g_max:
            continue
        lo, n = 0, len(minus_g)
        for j in range(nt):                  # the bounds rise with j (−tiers[j]/ratio does): gallop from the last
            key = -(tiers[j] / ratio[k])
            if key != key:                   # NaN: after every value, as NumPy sorts it
                lo = n
            elif lo < n and minus_g[lo] < key:
                last, step, hi = lo, 1, lo + 1       # minus_g[last] < key; the bound lies in (last, hi]
                while hi < n and minus_g[hi] < key:
                    last, step = hi, 2 * step
                    hi = last + step
                lo, hi = last + 1, min(hi, n)
                while lo < hi:
                    mid = (lo + hi) >> 1
                    if minus_g[mid] < key:
                        lo = mid + 1
                    else:
                        hi = mid
            bounds[k, j] = lo
            cells_per_tier[j] += lo
    for j in range(nt - 1, 0, -1):
        cells_per_tier[j] -= cells_per_tier[j - 1]


@jit
def _expected_count(log_ratio, w, table, saturated):
    """``np.interp(log_ratio, w, table, left=0, right=saturated).sum()`` bit for bit: NumPy's interpolation (the
    interval ``w[j] ≤ x < w[j+1]``, the table's value at a node, its slope formula and NaN fallbacks) and its
    sum (:func:`~roadview_noise.physics.numpy_sums.numpy_sum`)."""
    values = np.empty(len(log_ratio))
    last = len(w) - 1
    for i in range(len(log_ratio)):
        x = log_ratio[i]
        if x != x or x < w[0] or x >= w[last]:
            values[i] = x if x != x else 0.0 if x < w[0] else saturated if x > w[last] else table[last]
            continue
        lo, hi = 0, last                     # w[lo] ≤ x < w[hi]
        while hi - lo > 1:
            mid = (lo + hi) >> 1
            if w[mid] <= x:
                lo = mid
            else:
                hi = mid
        if w[lo] == x:
            values[i] = table[lo]
            continue
        slope = (table[lo + 1] - table[lo]) / (w[lo + 1] - w[lo])
        v = slope * (x - w[lo]) + table[lo]
        if v != v:
            v = slope * (x - w[lo + 1]) + table[lo + 1]
            if v != v and table[lo] == table[lo + 1]:
                v = table[lo]
        values[i] = v
    return numpy_sum(values)


@dataclass(frozen=True)
class ClutterPoints:
    positions_m: np.ndarray       # (M, 3)
    v_r_m_per_s: np.ndarray
    detection_db: np.ndarray      # D of the detected cell (≥ threshold), two-way loss included


_NO_POINTS = ClutterPoints(*_read_only(np.zeros((0, 3)), np.zeros(0), np.zeros(0)))


@lru_cache(maxsize=8)
def _tier_probabilities(max_probability: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """The probability bound ``2^{−j} P_max`` of each tier j, the same capped at 1 (read-only), and whether any
    reaches 1."""
    bound = max_probability * 0.5 ** np.arange(PROBABILITY_TIERS)
    return (*_read_only(bound, np.minimum(bound, 1.0)), bool((bound >= 1.0).any()))


def generate_clutter(rng: np.random.Generator, cells: ClutterCells) -> ClutterPoints:
    """Draw the detected cells — each cell independently with its probability P(y), by thinning: in probability tier
    j a Bernoulli(2^{−j} P_max) subset of the tier's cells, each kept with ``P(y)/(2^{−j} P_max)`` (work ∝ the
    expected count, not the number of cells) —, their RCS given the detection, and one point per detected cell: range
    uniform in the bin, direction uniform in solid angle within the angular cell, radial velocity uniform within the
    Doppler bin."""
    tables = cells.tables
    grid, detector = tables.grid, tables.detector
    hi, totals = cells.tier_bounds, cells.tier_cells
    bound, capped, certain = tables.tier_probabilities
    picks = rng.binomial(totals, capped)
    if certain:
        picks = np.where(bound >= 1.0, totals, picks)
    if not picks.any():        # the usual CA-CFAR frame (≈ 0.05 points expected): the rest would draw nothing
        return _NO_POINTS
    lo = np.concatenate([np.zeros((len(hi), 1), dtype=hi.dtype), hi[:, :-1]], axis=1)
    size = hi - lo                                              # (range bin, tier)
    ks, pairs, bounds = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)], [np.zeros(0)]
    for j in np.flatnonzero(picks):
        ends = np.cumsum(size[:, j])
        idx = np.arange(totals[j]) if picks[j] == totals[j] else rng.choice(totals[j], picks[j], replace=False)
        k = np.searchsorted(ends, idx, side="right")
        ks.append(k)
        pairs.append(lo[k, j] + idx - (ends[k] - size[k, j]))
        bounds.append(np.full(len(idx), bound[j]))
    k, pair, q = np.concatenate(ks), np.concatenate(pairs), np.concatenate(bounds)
    y = tables.pair_rcs_per_m3[pair] * cells.range_ratio_per_rcs[k]
    hit = rng.random(len(y)) * q < detector.probability(y)
    pair, k, y = pair[hit], k[hit], y[hit]
    over = detector.rcs_over_threshold(rng, y)                     # σ/σ_t ≥ 1
    edges = tables.edges
    r_e, az_e, z_e = edges.range_m, edges.azimuth_rad, edges.elevation_sine
    i_az, i_el = np.divmod(tables.pair_cell[pair], len(z_e) - 1)
    u = rng.random((4, len(pair)))
    r = r_e[k] + u[0] * (r_e[k + 1] - r_e[k])
    az = az_e[i_az] + u[1] * (az_e[i_az + 1] - az_e[i_az])
    z = z_e[i_el] + u[2] * (z_e[i_el + 1] - z_e[i_el])
    c = np.sqrt(1 - z * z)
    positions = r[:, None] * np.stack([c * np.cos(az), c * np.sin(az), z], axis=1)
    v_r = (tables.pair_doppler_bin[pair] + u[3] - 0.5) * grid.doppler_resolution_m_per_s
    return ClutterPoints(positions, v_r, cells.threshold_db + 10 * np.log10(over))
