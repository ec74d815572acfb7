"""The shared numba wrapper compiles with and without a writable cache."""

from __future__ import annotations

import numba

from roadview_noise.physics.compiled import jit


def test_kernels_compile_with_options():
    assert jit(lambda x: 2 * x)(21) == 42
    assert jit(error_model="numpy")(lambda x: x / 0.0)(1.0) == float("inf")


def test_kernels_compile_without_a_writable_cache(monkeypatch):
    """Read-only installs: numba raises RuntimeError for cache=True when no cache directory is writable; the
    kernels then compile without the cache."""
    njit = numba.njit

    def no_cache(*args, **kwargs):
        if kwargs.get("cache"):
            raise RuntimeError("cannot cache function: no locator available")
        return njit(*args, **kwargs)

    monkeypatch.setattr(numba, "njit", no_cache)
    assert jit(lambda x: 2 * x)(21) == 42
