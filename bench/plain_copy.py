"""The plain copy of bench/run.py: read, decode, encode, write + fsync each file (the loop a user would write with
the same codecs), run by the executor ``augment`` uses (:class:`roadview_noise.executor.ProcessExecutor`, one task
per file, with 1 as with 2 worker processes).

So the copy's 2 w / 1 w and ``augment``'s compare like with like: both pay a worker's start and a task's hand-over
per file, and neither pays a pool forked from the benchmark's own (large) process. The module is imported by name
in the workers (bench/ is on their ``sys.path``), which is why it is not part of run.py.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import cv2
import numpy as np


def _write_synced(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def copy_one(job: tuple, context: None = None) -> None:
    """Copy one file: ``job`` is (sensor, source, destination, with the depth sidecar's decode, codec)."""
    sensor, src, dst, with_depth, codec = job
    if sensor == "camera":
        from roadview_noise.io.png import decode_png, encode_png

        data = Path(src).read_bytes()
        img = decode_png(data) if codec == "rvnoise" else cv2.imdecode(np.frombuffer(data, np.uint8),
                                                                         cv2.IMREAD_UNCHANGED)
        if with_depth:
            from roadview_noise.io.image import read_exr_channels

            read_exr_channels(str(src).replace(".png", "_depth.exr"))
        _write_synced(Path(dst), encode_png(img) if codec == "rvnoise" else cv2.imencode(".png", img)[1].tobytes())
        return
    from roadview_noise.io.pointcloud import read_pointcloud, write_pointcloud

    cloud = read_pointcloud(src, sensor=sensor)
    write_pointcloud(dst, cloud, effect="none")


def plain_copy(sensor: str, tree: Path, out: Path, processes: int, with_depth: bool = False,
               codec: str = "opencv", files: int | None = None) -> float:
    """Wall seconds of the plain copy of the first ``files`` inputs (sorted; None: all) with ``processes`` worker
    processes, their start from the fork server included; camera frames with OpenCV's PNG codec or rvnoise's (``io/png.py``, the one
    ``augment`` uses)."""
    from roadview_noise.executor import ProcessExecutor, TaskError, WorkerDeath

    paths = sorted(tree.rglob("*.png" if sensor == "camera" else "*.pcd"))[:files]
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(sensor, str(f), str(out / f.name), with_depth, codec) for f in paths]
    warm = ProcessExecutor(copy_one, None, 1, models=[])   # a one-file run first, as augment's: the fork server
    try:                                                   # has imported what it preloads when the timing starts
        list(warm.map(jobs[:1]))
    finally:
        warm.close()
    executor = ProcessExecutor(copy_one, None, processes, models=[])
    t0 = time.perf_counter()
    try:
        for job, result in executor.map(jobs):
            if isinstance(result, (TaskError, WorkerDeath)):
                raise RuntimeError(f"the plain copy of {job[1]} failed: {result}")
    finally:
        executor.close()
    return time.perf_counter() - t0
