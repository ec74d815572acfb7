"""NumPy's float sums reproduced in compiled code, bit for bit, for kernels that replace a ``.sum()`` whose value
reaches an output (a manifest's diagnostics): a sequential loop rounds differently from NumPy's pairwise sum."""

from __future__ import annotations

import numpy as np

from .compiled import jit


@jit
def numpy_sum(a):
    """``a.sum()`` of a 1-D float64 array, bit for bit: NumPy's ``pairwise_sum`` added to the reduction's
    identity 0 — blocks of ≤ 128 values (:func:`_block_sum`), larger ones halved (at a multiple of 8), left half
    + right half. The halving is walked with a stack (numba's cache does not load recursive functions)."""
    starts, sizes = np.empty(64, np.int64), np.empty(64, np.int64)
    lefts, on_right = np.empty(64), np.zeros(64, np.bool_)
    starts[0], sizes[0], top, value, descending = 0, len(a), 1, 0.0, True
    while True:
        i = top - 1
        if descending:
            if sizes[i] <= 128:
                value = _block_sum(a, starts[i], sizes[i])
                top -= 1
                descending = False
            else:                                            # the left half first
                starts[top], sizes[top], on_right[i] = starts[i], _left_size(sizes[i]), False
                top += 1
            continue
        if top == 0:
            return 0.0 + value
        if on_right[i]:
            value = lefts[i] + value
            top -= 1
        else:                                                # then the right half
            half = _left_size(sizes[i])
            lefts[i], on_right[i] = value, True
            starts[top], sizes[top] = starts[i] + half, sizes[i] - half
            top += 1
            descending = True


@jit
def _left_size(n):
    half = n // 2
    return half - half % 8


@jit
def _block_sum(a, start, n):
    """NumPy's pairwise sum of ``n ≤ 128`` values: in order below 8, else 8 accumulators, combined pairwise, then
    the rest in order."""
    if n < 8:
        res = -0.0
        for i in range(n):
            res += a[start + i]
        return res
    r = a[start:start + 8].copy()
    i = 8
    while i < n - n % 8:
        for j in range(8):
            r[j] += a[start + i + j]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    for k in range(i, n):
        res += a[start + k]
    return res
