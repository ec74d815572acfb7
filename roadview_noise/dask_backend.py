"""Run the same per-file tasks on a Dask cluster (``rvnoise augment --backend dask [--scheduler tcp://HOST:8786]``).

:class:`DaskExecutor` has the interface of ``executor.ProcessExecutor`` (``map(tasks)`` → ``(task, result)`` as
tasks complete, ``close()``), so the runner, the ``outputs.Ledger`` and the manifest are those of a local run: the
client holds the OUT lock, workers run ``runner.process`` and stage fsynced temporaries in OUT, and the client
records each entry and renames its files, in plan order. Output bytes are those of the local backend (every draw
is keyed by seed and output path), provided the workers run the client's library versions (checked at start).

- Workers get the run context once, in a worker plugin (which also limits them to one thread per numeric library
  and loads the compiled kernels, ``warmup``), then only task keys. Each worker must run one task at a time
  (``dask worker --nthreads 1``): the per-file capture of native output and of warnings is per process.
- At most two tasks per worker thread are submitted ahead; progress follows completed futures.
- A worker that dies is replaced by the nanny and its task rescheduled once (``distributed.scheduler.allowed-
  failures`` = 1 on a local cluster; a remote scheduler uses its own setting), then recorded as a worker death.
- ``timeout_s``: a task running longer is cancelled and its worker restarted (needs a nanny), then recorded.
- Without ``scheduler`` a ``distributed.LocalCluster`` of ``workers`` processes on 127.0.0.1 (no dashboard) is
  started for the run and closed after it.

IN and OUT must be on storage every worker sees at the same paths (a shared file system).
"""

from __future__ import annotations

import time
import traceback
import uuid
from typing import Any, Callable, Iterable, Iterator

from .errors import RecipeError
from .executor import MAX_DEATHS_PER_TASK, THREAD_ENV, TaskError, WorkerDeath, worker_setup
from .manifest import library_versions

POLL_S = 0.5
AHEAD_PER_THREAD = 2


def _plugin_class():
    from distributed.diagnostics.plugin import WorkerPlugin

    class RunPlugin(WorkerPlugin):
        """Holds the run's task function and context on a worker; sets the worker up once."""

        def __init__(self, fn: Callable, context: Any, setup: tuple | None, name: str):
            self.fn, self.context, self.setup_call, self.name = fn, context, setup, name

        def setup(self, worker) -> None:
            from . import warmup

            worker_setup()
            if self.setup_call is not None:
                self.setup_call[0](*self.setup_call[1])
            warmup.warm_up()

    return RunPlugin


def _run_task(task: Any, plugin_name: str) -> Any:
    """On a worker: the run's function on one task, with the context its plugin holds."""
    from distributed import get_worker

    plugin = get_worker().plugins[plugin_name]
    return plugin.fn(task, plugin.context)


class DaskExecutor:
    """``fn(task, context)`` for each task on a Dask cluster; see the module docstring."""

    def __init__(self, fn: Callable, context: Any, *, workers: int | None = None, scheduler: str | None = None,
                 setup: tuple | None = None, timeout_s: float | None = None):
        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError:
            raise RecipeError("--backend dask needs dask.distributed: pip install 'roadview_noise[dask]'") from None
        self.timeout_s = timeout_s
        self.cluster = None
        self.name = f"rvnoise-{uuid.uuid4().hex[:12]}"
        try:
            if scheduler is None:
                with dask.config.set({"distributed.scheduler.allowed-failures": MAX_DEATHS_PER_TASK - 1}):
                    self.cluster = LocalCluster(n_workers=max(1, workers or 1), threads_per_worker=1, processes=True,
                                                host="127.0.0.1", dashboard_address=None, env=dict(THREAD_ENV),
                                                silence_logs=40)
                self.client = Client(self.cluster)
            else:
                self.client = Client(scheduler, timeout=30)
        except OSError as e:
            self._close_cluster()
            raise RecipeError(f"cannot reach the Dask scheduler {scheduler or 'of a LocalCluster'}: {e}") from None
        try:
            self._check_workers()
            self.client.register_plugin(_plugin_class()(fn, context, setup, self.name), name=self.name)
        except BaseException:
            self.close()
            raise
        self.workers = max(1, sum(self.client.nthreads().values()))
        self.deaths = 0
        self._pending: dict[Any, Any] = {}

    def _check_workers(self) -> None:
        """Refuse workers that would give other bytes (other library versions or CPU math extensions) or run several
        files at once."""
        self.client.wait_for_workers(1, timeout=60)
        threads = {w: n for w, n in self.client.nthreads().items() if n != 1}
        if threads:
            raise RecipeError(f"Dask workers must run one task at a time (dask worker --nthreads 1 --nworkers N); "
                              f"{len(threads)} have more threads: {', '.join(sorted(threads))[:200]}")
        mine = library_versions()
        for worker, theirs in self.client.run(library_versions).items():
            if theirs != mine:
                diff = {k: (mine.get(k), theirs.get(k)) for k in set(mine) | set(theirs) if mine.get(k) !=
                        theirs.get(k)}
                raise RecipeError(f"Dask worker {worker} runs other library versions or CPU math extensions, so "
                                  f"its outputs could differ (here, there): {diff}; install the same versions on "
                                  f"every worker and use machines of one CPU family")

    def map(self, tasks: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        from distributed import wait

        source = iter(tasks)
        pending: dict[Any, Any] = self._pending        # future → task
        started: dict[str, float] = {}                # key → when the client first saw it processing
        exhausted = False

        def submit() -> None:
            nonlocal exhausted
            while not exhausted and len(pending) < AHEAD_PER_THREAD * self.workers:
                try:
                    task = next(source)
                except StopIteration:
                    exhausted = True
                    return
                pending[self.client.submit(_run_task, task, self.name, pure=False,
                                           key=f"{self.name}-{uuid.uuid4().hex}")] = task

        submit()
        while pending:
            try:
                done = wait(list(pending), timeout=POLL_S if self.timeout_s else None,
                            return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = set()
            for future in done:
                task = pending.pop(future)
                started.pop(future.key, None)
                yield task, self._result(future)
                future.release()
            if self.timeout_s:
                for future, task in self._overdue(pending, started):
                    pending.pop(future)
                    yield task, WorkerDeath(f"took longer than {self.timeout_s:g} s; its worker was restarted", 1)
            submit()

    def _overdue(self, pending: dict, started: dict[str, float]) -> list:
        """Futures running longer than the timeout: cancelled, and their workers restarted."""
        now = time.monotonic()
        by_key = {f.key: f for f in pending}
        late, workers = [], set()
        for worker, keys in self.client.processing().items():
            for key in keys:
                if key in by_key:
                    started.setdefault(key, now)
                    if now - started[key] >= self.timeout_s:
                        late.append(by_key[key])
                        workers.add(worker)
        if late:
            self.client.cancel(late)
            try:
                self.client.restart_workers(sorted(workers), raise_for_error=False)
            except Exception:                          # no nanny: the worker finishes the task, its result is dropped
                pass
        for f in late:
            started.pop(f.key, None)
        return [(f, pending[f]) for f in late]

    def _result(self, future) -> Any:
        if future.status == "finished":
            return future.result()
        exc = future.exception()
        from distributed import KilledWorker

        if isinstance(exc, KilledWorker):
            self.deaths += 1
            return WorkerDeath(f"worker died (Dask: {exc})", MAX_DEATHS_PER_TASK)
        tb = "".join(traceback.format_tb(future.traceback())) if future.traceback() is not None else ""
        return TaskError(f"{type(exc).__name__}: {exc}", tb)

    def close(self) -> None:
        """Cancel what is left, forget the plugin; close the client (and the local cluster this run started)."""
        client = getattr(self, "client", None)
        if client is not None:
            try:
                if getattr(self, "_pending", None):
                    client.cancel(list(self._pending))
                    self._pending.clear()
                if self.cluster is None:
                    client.unregister_worker_plugin(self.name)
            except Exception:
                pass
            client.close()
            self.client = None
        self._close_cluster()

    def _close_cluster(self) -> None:
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None
