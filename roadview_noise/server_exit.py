"""Imported last by the workers' fork server only (``executor._preload``): when the run's process exits, the server
leaves at once instead of tearing its interpreter down (numba, scipy, OpenCV: ≈ 0.1–0.25 s of CPU). It shares the
run's stdout and stderr, so until it is gone a caller that reads them (a pipe, ``subprocess.run``, CI) still waits.

Workers forked from the server never run its ``atexit`` handlers (multiprocessing ends them with ``os._exit``)."""

from __future__ import annotations

import atexit

from .executor import leave_at_once

atexit.register(leave_at_once)
