"""Process-wide allocator setting of the batch workers.

glibc returns big freed blocks to the kernel (``mmap``/``munmap`` above the mmap threshold, heap trimming above the
trim threshold), so a worker that allocates the same 2–6 MB arrays every frame pays fresh page faults (and zeroing)
every frame: 4 000 faults per 128×2048 LiDAR scan, about a third of ``snow.lidar``'s time on the 2-core VM
(35 → 23 ms per scan). A 1936×1464×3 float32 camera frame (34 MB) is above the largest threshold glibc accepts, so
``mmap`` is switched off for ``malloc`` altogether (glibc still falls back to it when the heap cannot grow): windscreen
19.5 → 15.5 ms, soiling 22.6 → 16.4 ms per frame. :func:`keep_freed_memory` keeps such blocks in the heap for reuse;
the process then holds on to its peak memory, which a batch worker reaches within the first frame anyway."""

from __future__ import annotations

import ctypes
from functools import lru_cache

M_TRIM_THRESHOLD = -1          # glibc mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
M_MMAP_MAX = -4
MMAP_THRESHOLD_BYTES = 32 << 20        # glibc's largest default-range threshold on 64-bit
TRIM_THRESHOLD_BYTES = 1 << 30


@lru_cache(maxsize=1)
def keep_freed_memory() -> bool:
    """Serve every ``malloc`` from the heap (mmap threshold 32 MB, no mmap'ed chunks) and trim only above 1 GB (once
    per process); False where the C library has no ``mallopt`` (macOS, musl) or refuses the values."""
    try:
        mallopt = ctypes.CDLL(None).mallopt   # the C library already loaded (find_library runs ldconfig: ≈ 5 ms)
    except (OSError, AttributeError):
        return False
    return all(mallopt(parameter, value) for parameter, value in ((M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
                                                                   (M_MMAP_MAX, 0),
                                                                   (M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)))
