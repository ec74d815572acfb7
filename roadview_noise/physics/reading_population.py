"""What a recorded return whose reading carries no radiometric information counts as: the readings of the scan's
other returns at its range (profiles with ``threshold_calibration: datasheet``, :mod:`receiver`).

Such a sensor (KITTI's HDL-64E, nuScenes' HDL-32E) stores readings no receiver with its range could have detected:
KITTI stores 0 for 9–20 % of a scan's returns (17–39 % within 5 m, 44–96 % beyond 40 m), and readings below the
receiver's :attr:`~receiver.Receiver.recorded_floor` (the mean measured value of a detection at the threshold) say
only that the return was detected. Counted at the floor, such a return is judged as one detected at the threshold:
ray drop dropped KITTI's zero readings at 12 % against 1.4 % for its other returns, and the weather's smallest trace
moved them behind near particles. What is known of it instead: its range, and the returns the same scan read
radiometrically at that range. So it counts as the median of their range-free reading ``S·R²`` (the LiDAR equation
``S = K ρ cos θ / R²``: a target population, not a distance) in its range bin — bins of :data:`BIN_LOG_RANGE` in
ln R, the medians of bins with at least :data:`MIN_READINGS` informative returns interpolated linearly in ln R,
constant beyond the outer ones (the same population farther away reads ∝ R⁻²) — over R², and at least the floor (it
was detected). The medians come from a histogram of ln(S·R²) in steps of :data:`LOG_STEP` (one compiled pass, no
sort). A scan with no bin of enough informative readings keeps the floor.
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import jit

BIN_LOG_RANGE = 0.25        # range bin width in ln R (R × 1.28)
FIRST_RANGE_BIN = -10       # range bins k·BIN_LOG_RANGE ≤ ln R < (k+1)·BIN_LOG_RANGE from this k (0.08 m) …
RANGE_BINS = 48             # … the last (beyond 12 km) takes all beyond
MIN_READINGS = 32           # informative readings a range bin needs for its median
LOG_STEP = 0.01             # histogram step of ln(S·R²) for the medians (1 %) …
LOG_SPAN = 30.0             # … from the floor's (at 1 m) up: 10¹³ times the floor


def uninformative(signal: np.ndarray, has_target: np.ndarray, stored: np.ndarray, floor: float) -> np.ndarray:
    """The recorded returns whose reading carries no radiometric information (module doc): stored as 0, or read
    below ``floor``."""
    return has_target & ((stored <= 0) | (signal < floor))


def population_signal(signal: np.ndarray, range_m: np.ndarray, has_target: np.ndarray, unknown: np.ndarray,
                      floor: float) -> np.ndarray:
    """``signal`` with each ``unknown`` return's value replaced by the median range-free reading of the informative
    returns at its range over R², at least ``floor`` (module doc). Arrays per ray; ``unknown`` ⊆ ``has_target``."""
    out = np.array(signal, dtype=np.float64)
    if floor > 0 and unknown.any():
        _fill(out, np.ascontiguousarray(range_m, dtype=np.float64), has_target, unknown, floor)
    return out


@jit
def _fill(signal, range_m, has_target, unknown, floor):       # pragma: no cover - compiled
    """:func:`population_signal` in place: a histogram of ln(S·R²/floor) (:data:`LOG_STEP`, :data:`LOG_SPAN` wide,
    the last bin for all above) per range bin of the informative returns (:data:`BIN_LOG_RANGE` from
    :data:`FIRST_RANGE_BIN`, the last for all beyond), their medians, then each unknown return's value."""
    rows, width = RANGE_BINS, int(LOG_SPAN / LOG_STEP)
    hist = np.zeros((rows, width), np.int64)
    log_min_r = FIRST_RANGE_BIN * BIN_LOG_RANGE
    log_floor = math.log(floor)
    for i in range(len(signal)):
        if has_target[i] and not unknown[i]:
            log_r = math.log(range_m[i])
            row = min(max(int((log_r - log_min_r) / BIN_LOG_RANGE), 0), rows - 1)
            col = min(max(int((math.log(signal[i]) + 2.0 * log_r - log_floor) / LOG_STEP), 0), width - 1)
            hist[row, col] += 1
    centre = np.empty(rows)
    median = np.empty(rows)
    m = 0
    for row in range(rows):
        total = 0
        for col in range(width):
            total += hist[row, col]
        if total >= MIN_READINGS:
            seen, col = 0, 0
            while 2 * (seen + hist[row, col]) < total:
                seen += hist[row, col]
                col += 1
            centre[m] = log_min_r + (row + 0.5) * BIN_LOG_RANGE
            median[m] = log_floor + (col + 0.5) * LOG_STEP
            m += 1
    for i in range(len(signal)):
        if unknown[i]:
            if m == 0:
                signal[i] = floor
                continue
            log_r = math.log(range_m[i])
            if log_r <= centre[0]:
                reading = median[0]
            elif log_r >= centre[m - 1]:
                reading = median[m - 1]
            else:
                j = 1
                while centre[j] < log_r:
                    j += 1
                t = (log_r - centre[j - 1]) / (centre[j] - centre[j - 1])
                reading = median[j - 1] + t * (median[j] - median[j - 1])
            signal[i] = max(math.exp(reading - 2.0 * log_r), floor)
