"""Test-only models that misbehave on purpose: kill their worker, or sleep.

They are registered only while a test's ``injected`` fixture runs (tests/test_guarantees.py); the batch workers
import and register them because ``registry.plugin_models()`` names them (a model registered in the planning
process is adopted by every worker), so no environment variable or recipe key is involved. Never shipped.
"""

from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from roadview_noise.model import Model, Stage, param

POISON = 1.0              # a frame whose top-left pixel is white in every channel is poison


def _trace(path: str, text: str) -> None:
    if path:
        with open(path, "a") as fh:
            fh.write(text + "\n")


def _poisoned(frame) -> bool:
    return bool((frame.linear_rgb[0, 0] >= POISON - 1e-6).all())


@dataclass(frozen=True)
class CrashCamera(Model):
    """Kills its own worker (SIGKILL, as the out-of-memory killer does) on a poison frame; other frames unchanged."""

    id: ClassVar[str] = "test_crash.camera"
    stage: ClassVar[Stage] = Stage.ENCODING
    sensor: ClassVar[str] = "camera"
    trace_path: str = param("", doc="file that gets one line per call")

    def apply(self, data, *, state, drawn, rng):
        _trace(self.trace_path, f"{os.getpid()} {'poison' if _poisoned(data) else 'ok'}")
        if _poisoned(data):
            os.kill(os.getpid(), signal.SIGKILL)
        return data, {}


@dataclass(frozen=True)
class SleepCamera(Model):
    """Sleeps, then passes the frame on (keeps workers busy for the parent-death and timeout tests)."""

    id: ClassVar[str] = "test_sleep.camera"
    stage: ClassVar[Stage] = Stage.ENCODING
    sensor: ClassVar[str] = "camera"
    sleep_s: float = param(0.5, unit="s", ge=0)
    pid_dir: str = param("", doc="folder that gets one file per worker pid")
    trace_path: str = param("", doc="file that gets one line per call")

    def apply(self, data, *, state, drawn, rng):
        _trace(self.trace_path, str(os.getpid()))
        if self.pid_dir:
            Path(self.pid_dir, str(os.getpid())).touch()
        time.sleep(self.sleep_s if not _poisoned(data) else 3600)
        return data, {}


INJECTED = (CrashCamera, SleepCamera)
