"""One way to compile small numba kernels, shared by physics and I/O.

``numba.njit(cache=True)`` raises RuntimeError when numba finds no writable cache directory (a read-only install
without NUMBA_CACHE_DIR); the kernel is then compiled once per process instead."""

from __future__ import annotations

import numba


def jit(fn=None, **options):
    """``@jit`` or ``@jit(error_model="numpy")``: ``numba.njit(nogil=True, cache=True, **options)`` with the
    no-cache fallback."""
    def wrap(f):
        try:
            return numba.njit(cache=True, nogil=True, **options)(f)
        except RuntimeError:
            return numba.njit(nogil=True, **options)(f)

    return wrap(fn) if fn is not None else wrap
