"""Shared fixtures. Real data in ../shared/data is optional: tests that use it skip when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

# a loaded CI machine must never fail a property test on time: no per-example deadline, no "too slow" health check
settings.register_profile("rvnoise", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("rvnoise")

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent (real reference data is never committed)")
    return SHARED_DATA
