"""How many workers the machine can hold: the ``--workers`` rule.

A worker's peak resident memory on the shipped recipes at the sensors' full resolutions (camera 1936×1464 with
depth, raw DNG, OS1-128 2048 columns, VLS-128, radar) is at most 600 MB (CNF06 on the camera; LiDAR recipes ≤ 375 MB), 207 MB of it libraries
(``bench/bench_worker_memory.py``); :data:`WORKER_PEAK_BYTES` adds a margin. The number of workers is
``min(requested or the usable CPUs (affinity), outputs to write, available memory // WORKER_PEAK_BYTES)``, at least
1 (more than the usable CPUs run, with a line saying they share them); the
available memory is the kernel's ``MemAvailable``, lowered to what the cgroup still allows when it sets a limit.
Larger inputs need proportionally more (85–95 MB per camera megapixel): lower ``--workers`` or ``--max-pixels``
for them; a worker the kernel kills for memory is recorded as such and the run goes on.
"""

from __future__ import annotations

import os
from pathlib import Path

WORKER_PEAK_BYTES = 768 << 20


def available_memory_bytes() -> int | None:
    """Memory a new process can use without swapping (Linux ``MemAvailable`` and cgroup v2 limit), else the free
    physical pages, else None."""
    found = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text())
            found.append(max(0, int(limit) - used))
    except (OSError, ValueError):
        pass
    if not found:
        try:
            found.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            return None
    return min(found)


def usable_cores() -> int:
    """The CPUs this process may run on (its affinity: ``taskset``, a container's cpuset), else the machine's."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def choose_workers(requested: int | None, outputs: int, available: int | None = None,
                   cores: int | None = None) -> tuple[int, str | None]:
    """``(workers, what the user should know or None)`` by the rule of the module docstring: why there are fewer
    than requested, and that more workers than ``cores`` (default :func:`usable_cores`) share them."""
    cores = usable_cores() if cores is None else cores
    wanted = requested or cores
    available = available_memory_bytes() if available is None else available
    by_memory = max(1, available // WORKER_PEAK_BYTES) if available is not None else wanted
    n = max(1, min(wanted, max(outputs, 1), by_memory))
    shared = (f"{n} workers on {cores} core{'s' if cores > 1 else ''}: they share the cores (no faster than "
              f"--workers {cores}, more memory)") if n > cores else ""
    if requested is None or n >= requested:
        return n, f"--workers {requested}: {shared}" if shared else None
    reasons = []
    if outputs < requested:
        reasons.append(f"{outputs} output(s) to write")
    if by_memory < requested:
        reasons.append(f"{available / 2**30:.1f} GiB of available memory holds {by_memory} workers at "
                       f"{WORKER_PEAK_BYTES / 2**20:.0f} MiB each")
    return n, f"--workers {requested} capped to {n}: " + "; ".join(reasons + [shared] if shared else reasons)
