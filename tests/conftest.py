"""Shared fixtures. Real data in ../shared/data is optional: tests that use it skip when it is absent."""

from __future__ import annotations

import os
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


@pytest.fixture(scope="session", autouse=True)
def session_table_cache(tmp_path_factory) -> None:
    """The physics tables kept on disk (roadview_noise/table_cache.py) go to a folder of this session (set before
    any fork server starts: workers read the server's environment), not to the user's cache; a folder already set
    by the caller is kept."""
    os.environ.setdefault("RVNOISE_TABLE_CACHE", str(tmp_path_factory.mktemp("tables")))
