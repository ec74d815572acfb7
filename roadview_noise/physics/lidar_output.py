"""The rays → cloud stage of the LiDAR weather pipeline: the output cloud of a weather model — targets in place,
weather returns moved along their ray or added on empty rays, undetected returns removed — with provenance (origin, effect), intensities
stored as the input's sensor stores them (:func:`lidar_intensity.stored_intensity`) and the counts of the manifest.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ModelError
from ..provenance import NEW
from ..types import LidarProfile, PointCloud
from .compiled import jit
from .firing_grid import FiringGrid
from .laser_order import FIRING_COLUMN
from .lidar_echo import ADDED, ATTENUATED, MOVED, NO_RETURN, REMOVED, TARGET, WEATHER, RayReturns
from .lidar_geometry import RING, beam_means, elevation_rad, far_returns, unit_vectors
from .lidar_intensity import intensity_resolution, ouster_signal_layout, reflectivity_following, stored_signal
from .lidar_rays import Rays
from . import return_ranges
from .return_ranges import RANGE_BIN_M


def _column_azimuth_model(cloud: PointCloud, has_return: np.ndarray) -> tuple[float, float, bool]:
    """(φ0, sign, offsets): azimuth of grid column c is ``φ0 + sign·2πc/W − [beam azimuth offset of the ring]``.

    Fitted on a subsample of the grid's returns (staggered Ouster grids carry the per-beam offsets, destaggered ones
    not); an empty grid gets the Ouster convention (φ0 = π, sign = −1, staggered)."""
    profile = cloud.profile
    cols = cloud.grid_shape[1]
    stride = 127                                           # < 1 % of the cells, spread over rows and columns
    valid = np.flatnonzero(has_return[::stride]) * stride
    if len(valid) == 0:
        return math.pi, -1.0, True
    p = cloud.positions_m[valid]
    phi = np.arctan2(p[:, 1], p[:, 0])
    col = valid % cols
    offs = np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[_rings(cloud, valid, profile)]
    best = None
    for sign in (-1.0, 1.0):
        for staggered in (True, False):
            e = np.exp(1j * (phi + (offs if staggered else 0.0) - sign * 2 * np.pi * col / cols)).mean()
            if best is None or abs(e) > best[0]:
                best = (abs(e), float(np.angle(e)), sign, staggered)
    return best[1], best[2], best[3]


def _measured_beam_directions(cloud: PointCloud, has_return: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Unit vectors of no-return cells ``idx`` from the grid's own returns beyond 2 m: the mean elevation of the
    cell's beam (ring field or row) and the azimuth of its column, ``φ0 + sign·2πc/W`` fitted on every return, plus
    the beam's mean residual (its azimuth offset, staggered grids); a beam without returns takes the nearest beams'
    values (:func:`lidar_geometry.beam_means`)."""
    rows, cols = cloud.grid_shape
    ring = (np.asarray(cloud.fields["ring"]).astype(np.intp) if "ring" in cloud.fields
            else np.arange(rows * cols) // cols)
    p = cloud.positions_m
    valid = far_returns(p, has_return)
    if len(valid) == 0:
        raise ModelError(f"the {rows}×{cols} grid does not fit the {cloud.profile.channels} beams of profile "
                         f"{cloud.profile.name!r} and has no return to measure its beams' directions from")
    phi = np.arctan2(p[valid, 1], p[valid, 0])
    col_phase = 2 * np.pi * (valid % cols) / cols
    fits = [np.exp(1j * (phi - sign * col_phase)).mean() for sign in (-1.0, 1.0)]
    sign = -1.0 if abs(fits[0]) >= abs(fits[1]) else 1.0
    beams = max(int(ring.max()) + 1, rows)
    beam_el = beam_means(ring[valid], elevation_rad(p[valid]), beams)[ring[idx]]
    beam_offset = beam_means(ring[valid], np.exp(1j * (phi - sign * col_phase)), beams)[ring[idx]]   # φ0 + offset
    az = beam_offset + sign * 2 * np.pi * (idx % cols) / cols
    return unit_vectors(beam_el, az)


def _rings(cloud: PointCloud, idx: np.ndarray, profile: LidarProfile) -> np.ndarray:
    rows, cols = cloud.grid_shape
    ring = np.asarray(cloud.fields["ring"])[idx].astype(np.intp) if "ring" in cloud.fields else idx // cols
    if len(ring) and (ring.min() < 0 or ring.max() >= profile.channels):
        raise ModelError(f"grid rows/rings up to {int(ring.max())} do not fit the {profile.channels} beams of "
                         f"profile {profile.name!r}")
    return ring


def empty_ray_directions(cloud: PointCloud, has_return: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Unit vectors of no-return cells ``idx`` of a full grid: elevation of the cell's beam (ring field or row),
    azimuth of its column (:func:`_column_azimuth_model`). The mm-scale beam-origin offsets are neglected. A grid
    whose row count is not the profile's beam count (another sensor's: an OS-0-32 read with the default OS1-128)
    gets each beam's direction from its own returns (:func:`_measured_beam_directions`)."""
    profile = cloud.profile
    if cloud.grid_shape[0] != profile.channels:
        return _measured_beam_directions(cloud, has_return, idx)
    phi0, sign, staggered = _column_azimuth_model(cloud, has_return)
    ring = _rings(cloud, idx, profile)
    cols = cloud.grid_shape[1]
    az = phi0 + sign * 2 * np.pi * (idx % cols) / cols
    if staggered:
        az = az - np.deg2rad(np.asarray(profile.beam_azimuth_offset_deg))[ring]
    el = np.deg2rad(np.asarray(profile.beam_elevation_deg))[ring]
    return unit_vectors(el, az)


@jit
def _place(kind, has, return_range_m, ray_range_m, reported, full_scale, integer, half_step, grid, positions,
           intensity_in, positions_out, intensity_out, effect_out, origin_out):   # pragma: no cover - compiled
    """Per point of :func:`assemble`: position, stored intensity (the reported one clipped to full scale, rounded for
    integer dtypes), effect code (provenance.Effect) and origin (the input point), written to the outputs. A point
    list's removed points are left out (outputs filled from the start), a grid's are zeroed (REMOVED). Returns the
    removed mask, the number of outputs written and the counts (kept, attenuated, moved, removed, added)."""
    removed = np.zeros(len(kind), np.bool_)
    o, counts, _ = _place_rows(0, len(kind), 0, (0, 0, 0, 0, 0), return_ranges.NO_CHANGE, False, kind, has,
                               return_range_m, ray_range_m, reported, full_scale, integer, half_step, grid, positions,
                               intensity_in, positions_out, intensity_out, effect_out, origin_out, removed)
    return removed, o, counts


@jit
def _place_counted(kind, has, return_range_m, ray_range_m, reported, full_scale, integer, half_step, grid,
                   positions, intensity_in, positions_out, intensity_out, effect_out, origin_out, flat_in, values_in,
                   valid_in, hist_in, valid_out, hist_out, scratch):   # pragma: no cover - compiled
    """:func:`_place` with the geometry of the input (unless ``flat_in`` is empty) and of the output rows counted
    block by block as they are written (:class:`return_ranges.Tally <roadview_noise.physics.return_ranges.Tally>`'s
    arrays, after the outputs), and the input's intensities summed over its returns (unless ``values_in`` is empty):
    also returns the bits of the input's and the output's largest x² + y² + z², the sum and number, and what the
    metrics' STEP_LINK pass sums over the output (:func:`return_ranges.add_return_sums
    <roadview_noise.physics.return_ranges.add_return_sums>` of the output rows after each block's count, and
    :func:`_place_rows`' changes in place)."""
    removed = np.zeros(len(kind), np.bool_)
    o, counts, change, sums = 0, (0, 0, 0, 0, 0), return_ranges.NO_CHANGE, return_ranges.NO_SUMS
    inv_bin = 1.0 / RANGE_BIN_M
    part_in, part_out = np.zeros(4 * hist_in.shape[0], np.int64), np.zeros(4 * hist_out.shape[0], np.int64)
    flat_out = positions_out.reshape(-1)
    largest_in = largest_out = 0
    total, finite = 0.0, 0
    for start in range(0, len(kind), return_ranges.BLOCK):
        stop, first = min(start + return_ranges.BLOCK, len(kind)), o
        o, counts, change = _place_rows(start, stop, o, counts, change, True, kind, has, return_range_m, ray_range_m,
                                        reported, full_scale, integer, half_step, grid, positions, intensity_in,
                                        positions_out, intensity_out, effect_out, origin_out, removed)
        if flat_in.shape[0] > 0:
            largest_in = max(largest_in, return_ranges.count_block(flat_in, start, stop, inv_bin, scratch, valid_in,
                                                                   part_in))
            if values_in.shape[0] > 0:
                total, finite = return_ranges.sum_block(valid_in, values_in, start, stop, total, finite)
        largest_out = max(largest_out, return_ranges.count_block(flat_out, first, o, inv_bin, scratch, valid_out,
                                                                 part_out))
        sums = return_ranges.add_return_sums(valid_out, effect_out, intensity_out, first, o, sums)
    return_ranges.fold_parts(part_in, hist_in)
    return_ranges.fold_parts(part_out, hist_out)
    return removed, o, counts, largest_in, largest_out, total, finite, sums, change


@jit(inline="always")
def _place_rows(start, stop, o, counts, change, summed, kind, has, return_range_m, ray_range_m, reported, full_scale,
                integer, half_step, grid, positions, intensity_in, positions_out, intensity_out, effect_out, origin_out,
                removed):   # pragma: no cover - compiled
    """:func:`_place`'s loop over points ``start`` … ``stop`` − 1, writing from output row ``o`` on, ``counts``
    carried: (the next output row, the counts, ``change``). With ``summed`` (a constant) ``change`` carries the
    metrics' mean change in place (:data:`return_ranges.NO_CHANGE <roadview_noise.physics.return_ranges.NO_CHANGE>`):
    the sum and number of the finite out − in of the rows neither MOVED nor ADDED, in order, and the MOVED rows at
    scale 1 (:func:`return_ranges.noted_link <roadview_noise.physics.return_ranges.noted_link>`)."""
    kept, attenuated, moved, n_removed, added = counts
    change_sum, changed, unmoved = change
    for i in range(np.uint64(start), np.uint64(stop)):     # (unsigned: no wrap-around test on each index)
        q = np.uintp(o)                                # (unsigned: no negative-index wraparound compiled)
        k = kind[i]
        scale = 1.0                                    # of the position
        effect = 0                                     # KEPT
        if k == NO_RETURN:
            value = intensity_in[i]
            if has[i]:
                removed[i] = True
                n_removed += 1
                if not grid:
                    continue
                scale = 0.0
                value = 0
                effect = REMOVED
        else:
            v = min(reported[i], full_scale)
            value = round(v) if integer else v
            if k == WEATHER:
                if has[i]:
                    scale = return_range_m[i] / ray_range_m[i]
                    effect = MOVED
                    moved += 1
                else:
                    scale = 0.0                        # filled by the caller (directions of empty cells)
                    effect = ADDED
                    added += 1
        intensity_out[q] = value
        if k == TARGET:                                # the stored (converted) value decides
            if abs(float(intensity_out[q]) - float(intensity_in[i])) >= half_step:
                effect = ATTENUATED
                attenuated += 1
            else:
                kept += 1
        effect_out[q] = effect
        origin_out[q] = i
        for c in range(3):
            positions_out[q, c] = positions[i, c] * scale if scale != 0.0 else 0.0     # no −0.0
        o += 1
        if summed and effect == MOVED:
            unmoved += scale == 1.0
        elif summed and effect != ADDED:
            d = np.float64(intensity_out[q]) - np.float64(intensity_in[i])   # (float64: the metrics' change)
            if np.isfinite(d):
                change_sum += d
                changed += 1
    return o, (kept, attenuated, moved, n_removed, added), (change_sum, changed, unmoved)


def assemble(cloud: PointCloud, rays: Rays, returns: RayReturns) -> tuple[PointCloud, dict]:
    """Build the output cloud: targets stay in place, weather returns move the point along its ray (MOVED) or fill an
    empty ray (ADDED: a full grid's cell, a no-return point a list stores on the ray — nuScenes' placeholders —, else
    appended to the list), rays without a return lose their point (removed from a point list, zeroed in a
    full grid like :meth:`PointCloud.drop`). Intensities are written back in the input's unit, kind and dtype
    (:func:`lidar_intensity.stored_signal`: the reported intensity at the return's range as the sensor stores it); every
    other field is the ray's.

    Provenance (:mod:`roadview_noise.provenance`): ``origin`` is the input point of the output's ray (NEW for the
    empty rays of a point list appended), ``effect`` the Effect code; targets in place are ATTENUATED when the stored
    intensity changed by at least half a step of the input's resolution (:func:`intensity_resolution`: 1 photon,
    1 count, 1/255 of a [0, 1] scale), else KEPT (a change below the file's resolution is no visible change; the
    sub-step value is still written). Attributes follow the fields; a ``ring`` (field or attribute) of an added point
    is its empty cell's."""
    profile = rays.profile
    intensity_in = np.asarray(cloud.fields["intensity"])
    reported = stored_signal(returns.signal, returns.range_m, profile)
    n = rays.n_points
    cells = np.flatnonzero(returns.kind[n:] == WEATHER)          # a list's empty rays that return weather
    size = n + len(cells)                                         # outputs at most (a list's removed points go)
    effect = np.empty(size, np.uint8)
    origin = np.empty(size, np.int64)
    positions = np.empty((size, 3))
    intensity = np.empty(size, intensity_in.dtype)
    grid = cloud.grid_shape is not None
    integer = bool(np.issubdtype(intensity_in.dtype, np.integer))
    place = (returns.kind[:n], rays.has_target[:n], returns.range_m[:n], rays.range_m[:n], reported[:n],
             float(profile.intensity_full_scale), integer, 0.5 * intensity_resolution(profile), grid,
             np.ascontiguousarray(cloud.positions_m, dtype=np.float64), intensity_in, positions, intensity, effect,
             origin)
    tally = (return_ranges.Tally(cloud.positions_m, intensity_in, size, return_ranges.bin_count(profile))
             if return_ranges.wanted() else None)      # the metrics' geometry, counted as the blocks are placed
    if tally is None:
        removed, n_out, (kept, attenuated, moved, n_removed, added) = _place(*place)
    else:
        removed, n_out, (kept, attenuated, moved, n_removed, added), *counted = _place_counted(*place, *tally.arrays)
        tally.counted(*counted)
    if added:                                          # only full grids have empty rays with a direction
        idx = np.flatnonzero((returns.kind == WEATHER) & ~rays.has_target)
        positions[idx] = empty_ray_directions(cloud, rays.has_target, idx) * returns.range_m[idx, None]
        if tally is not None:                          # (zeros when the blocks counted them)
            tally.add_rows(positions, idx)
    at, rows = _hosted(rays.listed, cells, origin[:n_out] if n_removed else None)
    if len(at):                                        # weather on a stored no-return point's ray takes its row
        positions[rows], intensity[rows] = _listed_returns(rays.listed, cells[at], returns.range_m[n:], reported[n:],
                                                           float(profile.intensity_full_scale), integer)
        effect[rows] = ADDED
        added += len(at)
        cells = np.delete(cells, at)
    total = n_out + len(cells)
    fields = {**cloud.fields, "intensity": intensity[:total]}
    origin, attributes = origin[:total], cloud.attributes
    if n_removed and grid:
        fields = {k: (v if k in ("ring", "intensity") else
                      np.where(removed.reshape(-1, *(1,) * (v.ndim - 1)), np.zeros((), v.dtype), v))
                  for k, v in fields.items()}                # (a field of COUNT > 1, PCL's `_` padding: N × count)
    if not (n_removed or len(cells)) or grid:
        origin = None                                  # point i is input point i
    else:
        if len(cells):
            positions[n_out:total], intensity[n_out:total] = _listed_returns(
                rays.listed, cells, returns.range_m[n:], reported[n:], float(profile.intensity_full_scale), integer)
            effect[n_out:total] = ADDED
            added += len(cells)
            if tally is not None:
                tally.append(positions, n_out, total, effect, intensity)
        if len(fields) > 1 or attributes:              # the ray each output takes its other fields from
            index = np.concatenate([origin[:n_out], rays.listed.like[cells]]) if len(cells) else origin
            fields = {k: (v if k == "intensity" else np.asarray(v).take(index, axis=0)) for k, v in fields.items()}
            attributes = {k: np.asarray(v).take(index, axis=0) for k, v in attributes.items()}
            for carried in (fields, attributes):       # an added point's ring is its cell's, not its column's
                if len(cells) and RING in carried:
                    carried[RING][n_out:] = rays.listed.ring[cells]
            if len(cells) and FIRING_COLUMN in attributes:  # ... and its firing column its cell's (laser order)
                attributes[FIRING_COLUMN][n_out:] = rays.listed.column[cells]
        origin[n_out:] = NEW
    if attenuated and ouster_signal_layout(fields):    # an ouster-ros reflectivity reading follows its signal
        rows = np.flatnonzero(effect[:total] == ATTENUATED)
        fields = {**fields, **reflectivity_following(fields, rows, intensity_in[rows if origin is None else
                                                                                 origin[rows]], intensity[rows])}
    out = cloud.replace(positions_m=positions[:total], fields=fields, origin=origin, effect=effect[:total],
                        attributes=attributes)
    if tally is not None:                              # for the metrics' summaries of the input and the output
        tally.note(out.positions_m, len(at) > 0, out.effect, out.fields["intensity"], out.origin)
    faint = rays.faint
    counts = {"points_in": int(np.count_nonzero(rays.has_target)), "kept": kept, "attenuated": attenuated,
              "moved": moved, "removed": n_removed, "added": added, "below_threshold_in": int(np.count_nonzero(faint)),
              "removed_below_threshold_in": int(np.count_nonzero(removed & faint)), **empty_ray_counts(rays)}
    return out, counts


def _listed_returns(listed: FiringGrid, cells: np.ndarray, range_m: np.ndarray, reported: np.ndarray,
                    full_scale: float, integer: bool) -> tuple[np.ndarray, np.ndarray]:
    """(positions, stored intensities) of the weather returns of a point list's empty rays ``cells``: along the
    cell's direction at the return's range, intensity as :func:`_place` stores it. The caller writes them as ADDED
    points, appended (it gives them the cell's ``ring`` and copies every other field from a return of the same
    firing column, same firing time) or on the no-return point stored on the ray (:func:`_hosted`)."""
    value = np.minimum(reported[cells], full_scale)
    return listed.directions(cells, range_m[cells]), (np.round(value) if integer else value)


def _hosted(listed: FiringGrid | None, cells: np.ndarray, origin: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Of a list's empty rays ``cells`` that return weather, those whose no-return point is stored in the list
    (:attr:`FiringGrid.host`): (their positions in ``cells``, their output rows; ``origin``: the input point of each
    output row so far, increasing — no-return points are never removed —, None when no point was removed)."""
    if listed is None or listed.host is None or not len(cells):
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    host = listed.host[cells]
    at = np.flatnonzero(host >= 0)
    return at, (host[at] if origin is None else np.searchsorted(origin, host[at]))


def empty_ray_counts(rays: Rays) -> dict:
    """Diagnostics of the empty rays: how many could return weather, the firing grid's columns of a point list
    (0: none) and where they came from (or why a list has none)."""
    return {"empty_rays": int(np.count_nonzero(rays.empty)),
            "firing_grid_columns": 0 if rays.listed is None else rays.listed.columns,
            "empty_rays_source": rays.empty_source}


def unchanged(cloud: PointCloud, rays: Rays) -> tuple[PointCloud, dict]:
    """The identity result of a zero-strength weather model: same points, every effect KEPT."""
    n = int(rays.has_target.sum())
    counts = {"points_in": n, "kept": n, "attenuated": 0, "moved": 0, "removed": 0, "added": 0,
              "below_threshold_in": rays.below_threshold, "removed_below_threshold_in": 0, **empty_ray_counts(rays)}
    return cloud.replace(effect=np.zeros(len(cloud), np.uint8)), counts
