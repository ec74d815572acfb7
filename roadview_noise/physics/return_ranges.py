"""Which points of a cloud are returns, how many, the farthest one's range and the returns per 10 m range bin — the
geometry half of a cloud's metrics summary (:mod:`roadview_noise.metrics`, issue 18), found once per positions array.

A return is a point with 0 < x² + y² + z² < ∞ (a grid's no-return cells are all-zero); its range bin is
⌊√(x² + y² + z²) / 10 m⌋, the last bin catching anything farther (:func:`range_bin`; the metrics' own pass computes
the same expression inline, where a call compiled 15–25 % slower). While the chain records metrics
(:func:`collect`) a model notes the geometry of its input and output arrays (:func:`note`), so the metrics read
neither array's positions again (:func:`noted`): a loop that reads and writes every position anyway (the alignment's
:func:`write_rows`, the laser power's and the alignment's return mask of their input, :func:`returns_noted`, with
its intensity sum) counts it on the way;
the weather models' output stage (:func:`lidar_output.assemble <roadview_noise.physics.lidar_output.assemble>`)
counts its input and output block by block as it places the points (:class:`Tally`: :func:`count`'s vectorised
loop over each block of points right after the placement wrote it, while its positions are in the caches — fewer
instructions than binning inside the placement loop, whose branches it would add to, and no second read of the
clouds from memory); the metrics note what they count themselves, so an array a step hands on unchanged is counted
once. Same operations on the same values: the same geometry either way.
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from .compiled import jit

RANGE_BIN_M = 10.0
DEFAULT_MAX_RANGE_M = 300.0          # a cloud without a profile range
_KEPT = 4                            # arrays whose geometry is kept (a chain's last step input and output, and more)

_collecting = [False]
_noted: dict[int, tuple] = {}        # id(array) → (weakref to it, key, geometry)
_sums: dict[int, tuple] = {}         # id(values) → (weakref to them, weakref to the positions, (sum, number))
_links: dict[int, tuple] = {}        # id(positions) → (weakrefs to the step output's arrays, its STEP_LINK sums)
NO_SUMS = (0, 0, 0, 0, 0.0, 0)       # :func:`add_return_sums` of no point
NO_CHANGE = (0.0, 0, 0)              # the placement's sum of changes in place, their number, MOVED rows at scale 1
_NO_VALUES = np.zeros(0)
_LARGEST = np.finfo(np.float64).max


def bin_count(profile) -> int:
    """Range bins of a cloud of this sensor profile: up to its max range (300 m without one), then one for the
    farther returns and one spare."""
    max_range = getattr(profile, "max_range_m", None) or DEFAULT_MAX_RANGE_M
    return int(math.ceil(max_range / RANGE_BIN_M)) + 2


@jit(inline="always")
def range_bin(x, y, z, inv_bin, top):       # pragma: no cover - compiled
    """Point (x, y, z) (m, float64): (its range bin, −1 if it is no return; x² + y² + z²) with ``inv_bin`` = 1 / the
    bin width and ``top`` the last bin (it holds everything farther)."""
    r2 = x * x + y * y + z * z
    if not (r2 > 0.0 and r2 < np.inf):
        return -1, r2
    b = math.sqrt(r2) * inv_bin
    return (np.int64(b) if b < top else top), r2


@jit(inline="always")
def squared_range(positions, j):       # pragma: no cover - compiled
    """x² + y² + z² of point ``j`` of ``positions``, as :func:`range_bin` computes it."""
    x, y, z = positions[j, 0], positions[j, 1], positions[j, 2]
    return x * x + y * y + z * z


@jit(inline="always")
def add_point(positions, j, inv_bin, top, hist, valid, returns, max_r2):       # pragma: no cover - compiled
    """Count point ``j`` of ``positions`` into ``hist`` and ``valid`` (:func:`range_bin`): (its bin, its
    x² + y² + z², ``returns`` and ``max_r2`` with it counted)."""
    b, r2 = range_bin(positions[j, 0], positions[j, 1], positions[j, 2], inv_bin, top)
    valid[j] = b >= 0
    if b < 0:
        return b, r2, returns, max_r2
    hist[np.uint64(b)] += 1                            # ≥ 0: no wrap-around test
    return b, r2, returns + 1, max(max_r2, r2)


@intrinsic
def _bits(typingctx, x):
    """The IEEE 754 bits of a float64 as an int64 in compiled code: for values ≥ 0 ordered as the values, so a
    largest value is an integer maximum, which LLVM vectorises (a float maximum it does not without fast-math)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@jit
def _bin_points(flat, inv_bin, top, bins, valid):       # pragma: no cover - compiled
    """Per point j of the positions ``flat`` (x, y, z, x, … float64): ``valid[j]`` whether it is a return and
    ``bins[j]`` its :func:`range_bin` + 1 (0: none), with the same operations (r² ≤ the largest float: < ∞; the bin
    clipped as a float, then converted); returns the bits of the largest x² + y² + z² of a return. Branch-free with
    constant strides: vectorised (4 points an AVX2 instruction, ≈ 10 instructions a point)."""
    return _bin_range(flat, 0, bins.shape[0], inv_bin, top, bins, valid)


@jit(inline="always")
def _bin_range(flat, start, stop, inv_bin, top, bins, valid):       # pragma: no cover - compiled
    """:func:`_bin_points` of points ``start`` … ``stop`` − 1: ``valid[j]`` and ``bins[j − start]`` (indices, not
    slices: a slice's view is typed as of any layout, and its loop is not vectorised)."""
    largest, last = 0, float(top)
    for j in range(start, stop):
        k = np.uint64(3 * j)
        x, y, z = flat[k], flat[k + np.uint64(1)], flat[k + np.uint64(2)]
        r2 = x * x + y * y + z * z
        ok = (r2 > 0.0) & (r2 <= _LARGEST)
        b = math.sqrt(r2) * inv_bin
        bins[np.uint64(j - start)] = (np.int32(b if b < last else last) + np.int32(1)) if ok else np.int32(0)
        valid[np.uint64(j)] = ok
        largest = max(largest, _bits(r2) if ok else 0)
    return largest


@jit(inline="always")
def _histogram(bins, hist):       # pragma: no cover - compiled
    """Add the count of each value of ``bins`` to ``hist`` in four interleaved partial histograms: a scan's
    successive points mostly share a bin, and one histogram's increments would then wait on each other through
    memory (≈ 0.30 ms for 235 k points against 0.10, one core)."""
    part = np.zeros(4 * hist.shape[0], np.int64)
    _add_to_parts(bins, bins.shape[0], part)
    fold_parts(part, hist)


@jit(inline="always")
def _add_to_parts(bins, n, part):       # pragma: no cover - compiled
    """Count the first ``n`` values of ``bins`` into the four interleaved partial histograms ``part``
    (:func:`_histogram`)."""
    k = np.uint64(part.shape[0] // 4)
    n4 = n - n % 4
    for j in range(0, n4, 4):
        part[np.uint64(bins[j])] += 1
        part[k + np.uint64(bins[j + 1])] += 1
        part[2 * k + np.uint64(bins[j + 2])] += 1
        part[3 * k + np.uint64(bins[j + 3])] += 1
    for j in range(n4, n):
        part[np.uint64(bins[j])] += 1


@jit(inline="always")
def fold_parts(part, hist):       # pragma: no cover - compiled
    """Add the four partial histograms ``part`` (:func:`_add_to_parts`) to ``hist``."""
    k = hist.shape[0]
    for i in range(k):
        hist[i] += part[i] + part[k + i] + part[2 * k + i] + part[3 * k + i]


@jit
def _count(flat, inv_bin, bins, valid, hist):       # pragma: no cover - compiled
    """:func:`count`'s geometry, ``hist`` (one more entry than bins, zeros) counting :func:`_bin_points`' bins."""
    largest = _bin_points(flat, inv_bin, hist.shape[0] - 2, bins, valid)
    _histogram(bins, hist)
    return geometry_of(bins.shape[0] - hist[0], hist[1:], np.array([largest]).view(np.float64)[0], valid)


def count(positions: np.ndarray, n_bins: int) -> tuple:
    """The geometry of a positions array (float64 (N, 3), C-contiguous) with ``n_bins`` bins, as :func:`noted`
    gives it: (returns, the bins up to the farthest return's, its range m, the per-point return mask) — the metrics'
    own pass's figures, in two passes of few instructions a point (:func:`_bin_points`, then the histogram)."""
    bins = np.empty(len(positions), np.uint8 if n_bins < 256 else np.uint16)
    return _count(positions.reshape(-1), 1.0 / RANGE_BIN_M, bins, np.empty(len(positions), np.bool_),
                  np.zeros(n_bins + 1, np.int64))


BLOCK = 4096                         # points a block of :class:`Tally`: its arrays stay in the caches (≈ 0.4 MB)


class Tally:
    """The geometry of a model's input and output positions (float64 (N, 3) C-contiguous) counted block by block as
    the model writes its output (``lidar_output``'s placement: :func:`count_block` right after each block of
    :data:`BLOCK` input points and the output rows they made), while their positions are still in the caches — not
    in passes of their own after the model, which read every position again from memory (6.3 MB a 262 k-point
    cloud) —, and the sum of the input's intensities over its returns (:func:`sum_block`, the metrics' sum). Rows the
    model writes after the blocks are counted by :meth:`add_rows` and :meth:`append`. :func:`count`'s operations in the same order: the
    same geometry. The blocks also sum what the metrics' STEP_LINK pass over the output sums (:func:`add_return_sums`
    of the output rows, the placement's changes in place), so that a chain of one step reads its output no more
    (:func:`noted_link`)."""

    def __init__(self, inputs: np.ndarray, values: np.ndarray | None, size: int, n_bins: int) -> None:
        self.n_bins = n_bins
        counted = (inputs.ndim == 2 and inputs.shape[1] == 3 and inputs.dtype == np.float64
                   and inputs.flags.c_contiguous and noted(inputs, n_bins) is None)
        self.inputs = inputs if counted else None
        summed = counted and isinstance(values, np.ndarray) and values.shape == (len(inputs),)
        self.values = values if summed else None
        n = len(inputs) if counted else 0
        self.arrays = (inputs.reshape(-1) if counted else _NO_VALUES, values if summed else _NO_VALUES,
                       np.empty(n, np.bool_), np.zeros(n_bins + 1, np.int64), np.empty(size, np.bool_),
                       np.zeros(n_bins + 1, np.int64), np.empty(BLOCK, np.uint8 if n_bins < 256 else np.uint16))
        self.values_in = values
        self._input = self._largest_out = self._link = None

    def counted(self, largest_in: int, largest_out: int, total: float, finite: int, sums: tuple | None = None,
                change: tuple | None = None) -> None:
        """Keep what the blocks counted: the bits of the input's and the output's largest x² + y² + z², the sum
        and number of the input's finite values over its returns, and the output's STEP_LINK sums
        (:func:`add_return_sums` of its rows and the placement's change in place, as :data:`NO_CHANGE`; None: none
        noted)."""
        self._input = (largest_in, total, finite)
        self._largest_out = largest_out
        self._link = None if sums is None or change is None else (sums, change)

    def add_rows(self, positions: np.ndarray, rows: np.ndarray) -> None:
        """Count output rows the model wrote after the blocks in rows of zeros the blocks counted (a grid's ADDED
        cells: they become returns out of the sums' order, so no STEP_LINK sums are noted)."""
        self._link = None
        valid_out, hist_out = self.arrays[4], self.arrays[5]
        largest = _count_rows(positions.reshape(-1), np.asarray(rows, np.int64), 1.0 / RANGE_BIN_M, hist_out,
                              valid_out)
        self._largest_out = max(self._largest_out, largest)

    def append(self, positions: np.ndarray, start: int, stop: int, codes: np.ndarray | None = None,
               values: np.ndarray | None = None) -> None:
        """Count output rows ``start`` … ``stop`` − 1 the model wrote after the blocks' last (a list's appended
        points), block by block as the blocks are (:func:`count_block`: vectorised), and add them to the STEP_LINK
        sums with their effect ``codes`` and ``values`` (the output's arrays; not given: no sums noted)."""
        _, _, _, _, valid_out, hist_out, scratch = self.arrays
        largest = _count_range(positions.reshape(-1), start, stop, 1.0 / RANGE_BIN_M, hist_out, valid_out, scratch)
        self._largest_out = max(self._largest_out, largest)
        if self._link is not None and codes is not None and values is not None:
            self._link = (add_return_sums(valid_out, codes, values, start, stop, self._link[0]), self._link[1])
        else:
            self._link = None

    def note(self, outputs: np.ndarray, recount: bool = False, codes: np.ndarray | None = None,
             values: np.ndarray | None = None, origin: np.ndarray | None = None) -> None:
        """:func:`note` the output's geometry (``outputs``: the output cloud's positions, rows 0 … of the blocks'
        array; ``recount``: rows the blocks counted were rewritten, so count it anew), then the input's and its
        intensity sum (:func:`noted_sum`), and the output's STEP_LINK sums for :func:`noted_link` (``codes``,
        ``values``, ``origin``: the output cloud's effect codes, intensities and origin — None: point i is input
        point i —; not noted when rows were rewritten or a MOVED row kept its position: see :func:`noted_link`)."""
        _, _, valid_in, hist_in, valid_out, hist_out, _ = self.arrays
        n = len(outputs)
        note(outputs, self.n_bins, count(outputs, self.n_bins) if recount else geometry_of(
            n - hist_out[0], hist_out[1:], _value(self._largest_out), valid_out[:n]))
        if self.inputs is not None:
            largest, total, finite = self._input
            note(self.inputs, self.n_bins, geometry_of(len(self.inputs) - hist_in[0], hist_in[1:], _value(largest),
                                                       valid_in))
            if self.values is not None:
                _sums[id(self.values)] = (weakref.ref(self.values), weakref.ref(self.inputs), (total, finite))
        if not recount and self._link is not None and self._link[1][2] == 0 and codes is not None \
                and values is not None and isinstance(self.values_in, np.ndarray):
            refs = tuple(None if a is None else weakref.ref(a) for a in (outputs, codes, values, origin,
                                                                          self.values_in))
            _links[id(outputs)] = (refs, (*self._link[0], *self._link[1][:2]))


def _value(bits: int) -> float:
    """The float64 whose IEEE bits are ``bits``."""
    return float(np.array([bits], np.int64).view(np.float64)[0])


@jit(inline="always")
def count_block(flat, start, stop, inv_bin, scratch, valid, part):       # pragma: no cover - compiled
    """Count points ``start`` … ``stop`` − 1 (≤ :data:`BLOCK`) of the positions ``flat`` into ``valid`` and the
    partial histograms ``part`` of :class:`Tally`'s histogram (:func:`_bin_points`, :func:`_add_to_parts`;
    ``scratch``: their bins): the bits of their largest x² + y² + z²."""
    largest = _bin_range(flat, start, stop, inv_bin, part.shape[0] // 4 - 2, scratch, valid)
    _add_to_parts(scratch, stop - start, part)
    return largest


@jit(inline="always")
def sum_block(valid, values, start, stop, total, finite):       # pragma: no cover - compiled
    """``total``, ``finite`` with the finite ``values`` of the returns ``valid`` among points ``start`` … ``stop``
    − 1 added, in order (the metrics' sum of a cloud's values)."""
    for j in range(np.uint64(start), np.uint64(stop)):     # (unsigned: no wrap-around test on each index)
        if valid[j]:
            v = float(values[j])
            if np.isfinite(v):
                total += v
                finite += 1
    return total, finite


@jit(inline="always")
def add_return_sums(valid, codes, values, start, stop, sums):       # pragma: no cover - compiled
    """``sums`` (the counts per effect code KEPT, ATTENUATED, MOVED, ADDED, the sum and number of the finite
    ``values``, over the returns ``valid``; no codes: all KEPT; :data:`NO_SUMS`: none yet) with points ``start`` …
    ``stop`` − 1 added, in order: the metrics' pass over a cloud adds each block after its link, the weather
    placement each block after placing it (their arrays still in the caches). The counts in a branch-free loop of
    their own, the values' sum in order."""
    c0, c1, c2, c3, total, finite = sums     # (in registers: an array's increments would wait on each other)
    if codes.shape[0] > 0:
        for j in range(np.uint64(start), np.uint64(stop)):     # (unsigned: no wrap-around test on each index)
            c, ok = codes[j], valid[j]
            c0 += ok & (c == 0)
            c1 += ok & (c == 1)
            c2 += ok & (c == 2)
            c3 += ok & (c == 3)
    else:
        for j in range(np.uint64(start), np.uint64(stop)):
            c0 += valid[j]
    if values.shape[0] > 0:
        total, finite = sum_block(valid, values, start, stop, total, finite)
    return c0, c1, c2, c3, total, finite


@jit
def _count_range(flat, start, stop, inv_bin, hist, valid, scratch):       # pragma: no cover - compiled
    """Count points ``start`` … ``stop`` − 1 of the positions ``flat`` into ``hist`` (:func:`count`'s: bin + 1, 0
    none) and ``valid`` block by block (:func:`count_block`; ``scratch``: a block's bins). Returns the bits of their
    largest x² + y² + z²."""
    part = np.zeros(4 * hist.shape[0], np.int64)
    largest = 0
    for first in range(start, stop, BLOCK):
        largest = max(largest, count_block(flat, first, min(first + BLOCK, stop), inv_bin, scratch, valid, part))
    fold_parts(part, hist)
    return largest


@jit
def _count_rows(flat, rows, inv_bin, hist, valid):       # pragma: no cover - compiled
    """Count the points ``rows`` of the positions ``flat`` into ``hist`` (:func:`count`'s: bin + 1, 0 none) and
    ``valid`` as :func:`_bin_points` does, each counted before as a point of zeros. Returns the bits of their
    largest x² + y² + z²."""
    largest, last = 0, float(hist.shape[0] - 2)
    for r in rows:
        k = np.uint64(3 * r)
        x, y, z = flat[k], flat[k + np.uint64(1)], flat[k + np.uint64(2)]
        r2 = x * x + y * y + z * z
        ok = (r2 > 0.0) & (r2 <= _LARGEST)
        b = math.sqrt(r2) * inv_bin
        hist[0] -= 1
        hist[(np.int32(b if b < last else last) + np.int32(1)) if ok else np.int32(0)] += 1
        valid[r] = ok
        largest = max(largest, _bits(r2) if ok else 0)
    return largest


@jit
def _write_rows(out, mask, rows, inv_bin, hist, valid):       # pragma: no cover - compiled
    """``out[mask] = rows`` (in order) with every point of ``out`` counted into ``hist`` and ``valid``
    (:func:`add_point`) on the way: (returns, their largest x² + y² + z²)."""
    returns, max_r2, top, k = 0, 0.0, hist.shape[0] - 1, 0
    for j in range(out.shape[0]):
        if mask[j]:
            for c in range(3):
                out[j, c] = rows[k, c]
            k += 1
        returns, max_r2 = add_point(out, j, inv_bin, top, hist, valid, returns, max_r2)[2:]
    return returns, max_r2


def write_rows(positions: np.ndarray, mask: np.ndarray, rows: np.ndarray, profile) -> None:
    """``positions[mask] = rows`` for a model that moves points (``positions``: its output, not yet handed on);
    while a chain records metrics (:func:`wanted`) the output's geometry is counted in the same pass and noted
    (float64 C-contiguous arrays; the metrics would read a converted copy of any other)."""
    if not (wanted() and positions.dtype == np.float64 and positions.flags.c_contiguous):
        positions[mask] = rows
        return
    n_bins = bin_count(profile)
    hist, valid = np.zeros(n_bins, np.int64), np.empty(len(positions), np.bool_)
    returns, max_r2 = _write_rows(positions, mask, np.ascontiguousarray(rows, dtype=np.float64), 1.0 / RANGE_BIN_M,
                                  hist, valid)
    note(positions, n_bins, geometry_of(returns, hist, max_r2, valid))


@jit
def _returns_counted(positions, values, inv_bin, hist, valid, hit):       # pragma: no cover - compiled
    """``hit`` = :func:`lidar_geometry.has_return <roadview_noise.physics.lidar_geometry.has_return>` of
    ``positions`` (finite x + y + z, not the origin) with every point counted into ``hist`` and ``valid``
    (:func:`add_point`) in the same pass: (returns, their largest x² + y² + z², the sum and the number of the finite
    ``values`` of the returns in order, as the metrics' pass sums them; ``values`` empty: 0.0, 0)."""
    returns, max_r2, top, total, finite = 0, 0.0, hist.shape[0] - 1, 0.0, 0
    has_values = values.shape[0] > 0
    for j in range(positions.shape[0]):
        x, y, z = positions[j, 0], positions[j, 1], positions[j, 2]
        hit[j] = np.isfinite(x + y + z) and (x != 0.0 or y != 0.0 or z != 0.0)
        returns, max_r2 = add_point(positions, j, inv_bin, top, hist, valid, returns, max_r2)[2:]
        if has_values and valid[j]:
            v = float(values[j])
            if np.isfinite(v):
                total += v
                finite += 1
    return returns, max_r2, total, finite


def returns_noted(cloud) -> np.ndarray | None:
    """The return mask of :func:`lidar_geometry.has_return <roadview_noise.physics.lidar_geometry.has_return>` of a
    cloud's positions for a model that reads its input's returns (the laser power, the alignment), with the array's
    geometry and the sum of its intensities over the returns counted in the same pass and noted while a chain records
    metrics (:func:`wanted`; :func:`noted`, :func:`noted_sum`) — so the metrics' summary of the chain input reads
    neither —; None when none is wanted, the geometry is noted already, or the positions are not float64 C-contiguous
    (the metrics would read a converted copy)."""
    positions = cloud.positions_m
    if not (wanted() and cloud.profile is not None and positions.ndim == 2 and positions.shape[1] == 3
            and positions.dtype == np.float64 and positions.flags.c_contiguous):
        return None
    n_bins = bin_count(cloud.profile)
    if noted(positions, n_bins) is not None:
        return None
    values = cloud.fields.get("intensity")
    values = values if isinstance(values, np.ndarray) and values.shape == (len(positions),) else None
    hist, valid, hit = np.zeros(n_bins, np.int64), np.empty(len(positions), np.bool_), np.empty(len(positions), bool)
    returns, max_r2, total, finite = _returns_counted(positions, _NO_VALUES if values is None else values,
                                                      1.0 / RANGE_BIN_M, hist, valid, hit)
    note(positions, n_bins, geometry_of(returns, hist, max_r2, valid))
    if values is not None:
        _sums[id(values)] = (weakref.ref(values), weakref.ref(positions), (total, finite))
    return hit


def noted_sum(positions: np.ndarray, values: np.ndarray) -> tuple | None:
    """(sum, number) of the finite ``values`` of the returns of ``positions`` (:func:`returns_noted`) when a model
    noted them for these very arrays, else None."""
    got = _sums.get(id(values))
    if got is None or got[0]() is not values or got[1]() is not positions:
        return None
    return got[2]


def noted_link(positions: np.ndarray, codes: np.ndarray, values: np.ndarray, origin: np.ndarray,
               values_before: np.ndarray) -> tuple | None:
    """What the metrics' STEP_LINK pass over a weather step's output sums (:func:`add_return_sums`' counts and
    value sum, then the sum and number of the finite changes ``values`` − ``values_before`` of the rows neither MOVED
    nor ADDED, in order) as the placement summed them (:meth:`Tally.note`), when noted for these very arrays
    (``origin``: the step's, empty for none), else None. The pass takes a MOVED row as moved unless it is at its
    input's position and that is a return; a row moved by the factor ``scale`` ≠ 1 (return range / ray range) has
    another position whenever its input is a return (r² > 0: a coordinate of magnitude ≥ 1e-154, which × scale
    rounds to another float), so with no MOVED row at scale 1 the sums need neither the walk nor ``before``'s
    positions."""
    got = _links.get(id(positions))
    if got is None:
        return None
    want = (positions, codes, values, origin if len(origin) else None, values_before)
    if not all((None if r is None else r()) is w for r, w in zip(got[0], want)):
        return None
    return got[1]


@jit
def geometry_of(returns, hist, max_r2, valid):       # pragma: no cover - compiled
    """The geometry as :func:`noted` gives it: (returns, the bins up to the farthest return's, its range m, the
    per-point return mask)."""
    used = hist.shape[0]
    while used > 0 and hist[used - 1] == 0:
        used -= 1
    return returns, hist[:used], math.sqrt(max_r2), valid


def collect(on: bool) -> None:
    """Whether models note the geometry of the arrays they write (:func:`wanted`): on while a chain records
    metrics (``compound.apply_models``)."""
    _collecting[0] = on
    if not on:
        _noted.clear()
        _sums.clear()
        _links.clear()


def wanted() -> bool:
    """A model that reads or writes every position should :func:`note` their geometry."""
    return _collecting[0]


def _key(positions: np.ndarray, n_bins: int) -> tuple:
    return positions.shape, positions.strides, positions.dtype, n_bins


def note(positions: np.ndarray, n_bins: int, geometry: tuple) -> None:
    """Keep the geometry (:func:`geometry_of`, ``n_bins`` bins) of this positions array (float64 (N, 3),
    C-contiguous) for :func:`noted`; it must not change afterwards (models hand their output on unchanged)."""
    if len(_noted) >= _KEPT:
        for k in [k for k, (ref, _, _) in _noted.items() if ref() is None] or list(_noted)[:1]:
            del _noted[k]
        _sums.clear()
        _links.clear()
    _noted[id(positions)] = (weakref.ref(positions), _key(positions, n_bins), geometry)


def noted(positions: np.ndarray, n_bins: int) -> tuple | None:
    """The geometry :func:`note` kept for this very array (identity, shape, strides) and bin count, else None."""
    got = _noted.get(id(positions))
    if got is None or got[0]() is not positions or got[1] != _key(positions, n_bins):
        return None
    return got[2]
