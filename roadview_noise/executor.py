"""Worker processes that survive the death of a worker, and die with their parent.

joblib/loky and ``concurrent.futures`` break the whole pool when one worker dies (a native crash on one bad file, the
kernel's out-of-memory killer): every task in flight is lost and the run aborts. :class:`ProcessExecutor` gives each
worker its own pipe and knows which task a dead worker was running: that
task is retried once on a fresh worker and reported as a :class:`WorkerDeath` if it kills a second one; no other task
is affected. Behind tasks shorter than ``QUEUE_BELOW_S`` a worker holds further tasks, queued in its pipe (about
``2 * BATCH_HOLD_S`` of them, at most ``QUEUE_MAX_TASKS`` and ``QUEUE_MAX_BYTES`` together: sending them never blocks
on a worker that is itself blocked sending a large result), so it never waits for the parent between two small files;
behind longer tasks (and before the first answer) it holds a second one while the source has at least ``2 * workers``
left (its ``operator.length_hint``, e.g. :class:`Counted`; without one, a single task), so it does not wait for the
parent between two files either (issue 19: 40–80 ms over a 12-file 2-worker camera run), at the cost of at most
about half a task of imbalance at the end of the run. Behind short tasks a worker answers in **batches**: one
message with the results it finished while more tasks were queued (at most ``BATCH_MAX`` results, held only while
the next task, as long as the last, would end within ``BATCH_HOLD_S`` of the first held one; at once when nothing
more is queued). The parent then wakes once
per batch, not once per file, and handles the batch with warm caches (issue 19: a radar file's ≈ 0.3 ms of the main
process was mostly a cold wake-up per file). A worker records the task it is running in shared memory, so a dead
worker is blamed for that task only: the ones it finished but had not sent yet and the ones queued behind are re-sent
without a death counted. Under a time bound (``timeout_s``) a worker answers each task at once (a held result would
count against the next task's time). Workers get the run context once at start and then only small task keys (never
arrays); the tasks the parent hands a worker at once (its refill after a batch) go in one message, each pickled on
its own (one write for the parent and one read for the worker per refill, not per task: issue 19's chunked
dispatch; the worker runs them one by one, recording each as it starts).

A worker exits when its parent dies: ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` on Linux, and on every platform a watchdog
thread that polls ``getppid()``. Workers are forked from a ``forkserver`` (Linux; ``spawn`` elsewhere) that imported
the models once and loaded their compiled kernels (``warmup``), so a worker starts warm in milliseconds, with
OpenBLAS/OpenMP/numba at one thread and ``cv2.setNumThreads(1)`` per worker.

``timeout_s`` bounds one task: a worker that runs longer is killed and its task reported (not retried).

The interface (:class:`Executor`): ``map(tasks)`` pulls tasks lazily from any iterable (at most ``workers`` in
flight) and yields ``(task, result)`` pairs as they complete; ``result`` is the function's return value, a
:class:`WorkerDeath` or a :class:`TaskError`. :class:`InlineExecutor` runs the same contract in the calling process.
A source that must wait for its caller (an ordered consumer bounding what it holds, the bag runner) yields
:data:`NOT_NOW` instead of a task: ``map`` yields ``(NOT_NOW, None)`` at once and asks again later; the source may do
so only while a task is running or when its caller can make progress without one. ``wake`` (a file descriptor the
caller reads) also makes ``map`` yield ``(NOT_NOW, None)`` when it becomes readable while tasks of at least
``QUEUE_BELOW_S`` run: the caller has work of its own to do then (the runner: entries whose fsync just finished,
``output_sync``); behind shorter tasks the next result comes soon enough.
"""

from __future__ import annotations

import ctypes
import io
import math
import multiprocessing as mp
import multiprocessing.spawn as mp_spawn
import operator
import os
import pickle
import select
import signal
import sys
import threading
import time
import traceback
import weakref
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any, Callable, Generic, Iterable, Iterator, Protocol, Sequence, TypeVar

T = TypeVar("T")
C = TypeVar("C")

MAX_DEATHS_PER_TASK = 2            # a task that kills this many workers is not tried again
WATCHDOG_PERIOD_S = 1.0
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "NUMBA_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}
PRELOAD = ["cv2", "roadview_noise.runner", "roadview_noise.metrics"]   # + the run's models, the warm-up (_preload)
WARM_UP = "roadview_noise.warmup"
SERVER_EXIT = "roadview_noise.server_exit"     # the server's fast exit (imported by the server only)
PR_SET_PDEATHSIG = 1
QUEUE_BELOW_S = 0.05               # tasks shorter than this get more queued behind them (see _depth)
QUEUE_MAX_BYTES = 16 * 1024        # tasks queued behind a running one hold at most this much: their send never blocks
QUEUE_MAX_TASKS = 16               # tasks a worker holds at most
BATCH_MAX = 8                      # results a worker sends in one message at most
BATCH_HOLD_S = 0.02                # a finished result waits at most this long for others to join its message


class _NotNow:
    def __repr__(self) -> str:
        return "NOT_NOW"


NOT_NOW = _NotNow()                 # "no task yet" from a task source (see the module docstring)


@dataclass(frozen=True)
class WorkerDeath:
    """The task's worker died (signal or exit) ``deaths`` times while running it."""

    reason: str
    deaths: int


@dataclass(frozen=True)
class TaskError:
    """The task function raised (it should record failures itself; this keeps the run going if it does not)."""

    message: str
    traceback: str


class Executor(Protocol):
    workers: int

    def map(self, tasks: Iterable[T]) -> Iterator[tuple[T, Any]]:
        """Run ``fn(task, context)`` for each task; yield ``(task, result)`` as tasks complete."""

    def close(self) -> None:
        """Stop the workers (also when ``map`` was left early) and wait for them."""


def death_reason(exitcode: int | None) -> str:
    """A worker's exit status in words."""
    if exitcode is None:
        return "worker vanished"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        if -exitcode == signal.SIGKILL:
            return f"worker died: signal {-exitcode} ({name}: out of memory or killed)"
        return f"worker died: signal {-exitcode} ({name}, a crash in native code)"
    return f"worker died: it exited with code {exitcode}"


# --- in the worker ---------------------------------------------------------------------------------------------------


def worker_setup(parent_pid: int | None = None) -> None:
    """One thread per numeric library; exit when the parent dies (see module docstring)."""
    os.environ.update(THREAD_ENV)
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:             # pragma: no cover - cv2 is a dependency
        pass
    if parent_pid is None:
        return
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass
    ppid = os.getppid()

    def watchdog() -> None:
        while True:
            time.sleep(WATCHDOG_PERIOD_S)
            if os.getppid() != ppid or not _alive(parent_pid):
                os._exit(1)

    threading.Thread(target=watchdog, name="rvnoise-parent-watchdog", daemon=True).start()
    if os.getppid() != ppid or not _alive(parent_pid):
        os._exit(1)


def leave_at_once(code: int = 0) -> None:
    """End this process now with ``code``, its stdout and stderr flushed, without tearing its interpreter down (its
    exit handlers, multiprocessing's finalizers: a worker told to stop, the fork server, a local run's process)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    os._exit(code)


def _worker(*args) -> None:
    """A worker process: :func:`_worker_main`, then it leaves at once (:func:`leave_at_once`; ≈ 5–10 ms less for
    the run to wait when it closes its executor, see :meth:`ProcessExecutor.close`)."""
    _worker_main(*args)
    leave_at_once()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _worker_main(conn, fn: Callable, context: Any, parent_pid: int, setup: tuple | None, running: Any = None,
                 batch: int = 1, ready: Any = None) -> None:
    """Run the tasks of ``conn`` in order; answer with lists of ``(task id, result)`` (up to ``batch``, see the
    module docstring); ``running.value``: the id of the task started last (read by the parent when this dies);
    ``ready.value``: when (``time.monotonic``) this was set up and ready for its first task."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)       # Ctrl-C is the parent's to handle
    worker_setup(parent_pid)
    if setup is not None:
        setup[0](*setup[1])
    if ready is not None:
        ready.value = time.monotonic()
    held: list = []
    inbox: deque = deque()          # tasks received and not started (a message holds one or more: _messages)
    since = took = 0.0              # when the first held result was done; how long the last task took
    while True:
        # send unless more results can join within the hold: the next task, if it takes as long as the last,
        # would keep the held ones past BATCH_HOLD_S (so a worker of ≈ 50 ms LiDAR tasks answers each at once and
        # never waits for new tasks with finished ones unsent)
        if held and (len(held) >= batch or not (inbox or conn.poll())
                     or time.monotonic() - since + took >= BATCH_HOLD_S):
            conn.send(held)
            held = []
        if not inbox:
            try:
                inbox.extend(_messages(conn.recv_bytes()))
            except (EOFError, OSError):
                return
        msg = inbox.popleft()
        if msg is None:
            return
        tid, task = msg
        if running is not None:
            running.value = tid
        start = time.monotonic()
        try:
            result = fn(task, context)
        except Exception as exc:        # the function should not raise; keep the worker alive if it does
            result = TaskError(f"{type(exc).__name__}: {exc}", traceback.format_exc(limit=8))
        now = time.monotonic()
        took = now - start
        if not held:
            since = now
        held.append((tid, result))


def _messages(data: bytes) -> list:
    """The objects of one message from the parent: its pickles one after the other (:meth:`ProcessExecutor.map`
    sends a worker's new tasks, each pickled on its own, in one message)."""
    buf = io.BytesIO(data)
    out = []
    while buf.tell() < len(data):
        out.append(pickle.load(buf))
    return out


# --- in the parent ---------------------------------------------------------------------------------------------------


def _in_order(answers: list, queue: deque) -> int:
    """How many of a worker's ``(task id, result)`` answers are for the first tasks of its ``queue``, in order."""
    n = 0
    for (tid, _), (sent, _) in zip(answers, queue):
        if tid != sent:
            break
        n += 1
    return n


def _safe_path() -> dict[str, str]:
    """``PYTHONSAFEPATH=1`` when the current folder holds a ``roadview_noise`` other than the one running: the fork
    server, started as ``python -c …``, imports PRELOAD with the current folder first on its path (Python 3.11 does
    not pass it the caller's), so a run started inside another checkout of rvnoise ran that checkout's code in its
    workers (round 22: a run from a newer checkout failed every file, "write() takes 1 positional argument")."""
    try:
        here = Path.cwd() / "roadview_noise"
        other = here.is_dir() and here.resolve() != Path(__file__).resolve().parent
    except OSError:                        # the current folder was removed: nothing to import from it
        other = False
    return {"PYTHONSAFEPATH": "1"} if other else {}


@contextmanager
def _starting() -> Iterator[None]:
    """Around starting a worker or the fork server: one thread per numeric library in the environment, and no
    re-run of the caller's ``__main__`` in the child. Workers need nothing from it (the task function and the setup
    are imported by name), and multiprocessing's default would re-import the main script in every worker:
    slow (a script that imports open3d pays it per worker) and wrong for a script without the
    ``if __name__ == "__main__"`` guard."""
    env = {**THREAD_ENV, **_safe_path()}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    original = getattr(mp_spawn, "get_preparation_data", None)

    def without_main(name):
        data = original(name)
        data.pop("init_main_from_path", None)
        data.pop("init_main_from_name", None)
        return data

    if original is not None:
        mp_spawn.get_preparation_data = without_main
    try:
        yield
    finally:
        if original is not None:
            mp_spawn.get_preparation_data = original
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _preload(models: Sequence[str] | None) -> list[str]:
    """What the fork server imports: the runner, ``models`` (None: every model module), the warm-up, then its fast
    exit (:mod:`roadview_noise.server_exit`)."""
    if models is None:
        import pkgutil

        from . import models as package

        models = [m.name for m in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]
    return PRELOAD + list(models) + [WARM_UP, SERVER_EXIT]


_live: "weakref.WeakSet[ProcessExecutor]" = weakref.WeakSet()   # executors with workers: their fork server stays


def start_server(models: Sequence[str] | None = None) -> None:
    """Start the fork server for ``models`` now, so it imports them while the caller plans the run."""
    _context(models)


def _context(models: Sequence[str] | None = None):
    """The start method: a fork server preloading ``models`` (see :func:`_preload`); one already running that lacks
    some of them is restarted with what it had and them, when no executor uses it (else a worker imports what it
    lacks on first use)."""
    if "forkserver" in mp.get_all_start_methods() and sys.platform.startswith("linux"):
        from multiprocessing import forkserver

        ctx = mp.get_context("forkserver")
        want = _preload(models)
        server = getattr(forkserver, "_forkserver", None)
        running = getattr(server, "_forkserver_pid", None) is not None
        have = list(getattr(server, "_preload_modules", ()) or ())
        if running and not set(want) <= set(have) and not _live and hasattr(server, "_stop"):
            server._stop()
            running = False
            want = _preload(list(dict.fromkeys(m for m in have + want
                                               if m not in PRELOAD and m not in (WARM_UP, SERVER_EXIT))))
        if not running:
            ctx.set_forkserver_preload(want)
            with _starting():            # the server imports numpy once, with one BLAS thread per worker
                forkserver.ensure_running()
        return ctx
    return mp.get_context("spawn")


class _Poller:
    """:func:`multiprocessing.connection.wait` with one ``poll`` object kept while the objects waited on stay the
    same (``wait`` builds and fills a selector per call: ≈ 20–30 µs of the main process per result, issue 19);
    ``wait`` itself where there is no ``poll``."""

    def __init__(self):
        self._objects: tuple = ()
        self._poll = None
        self._by_fd: dict[int, Any] = {}

    def wait(self, objects: list, timeout: float | None) -> list:
        if not hasattr(select, "poll"):                    # pragma: no cover - Windows
            return wait(objects, timeout)
        key = tuple(objects)
        if key != self._objects or self._poll is None:
            self._poll, self._objects = select.poll(), key
            self._by_fd = {o if isinstance(o, int) else o.fileno(): o for o in objects}
            for fd in self._by_fd:
                self._poll.register(fd, select.POLLIN)
        ms = None if timeout is None else max(0, int(timeout * 1000 + 0.999))
        return [self._by_fd[fd] for fd, _ in self._poll.poll(ms)]


@dataclass
class _Worker:
    proc: Any
    conn: Any
    running: Any = None                             # shared: the id of the task it started last
    ready: Any = None                               # shared: when it was ready for tasks (monotonic; 0: not yet)
    queue: deque = field(default_factory=deque)     # (tid, task) sent and not answered, in order
    sizes: deque = field(default_factory=deque)     # their pickled bytes
    started: float = 0.0                            # when the first of ``queue`` started
    stopping: bool = False                          # told to exit (ProcessExecutor.stop), not joined yet

    def died_on(self) -> int:
        """Where in ``queue`` the task it was running when it died is: those before it were done, not sent."""
        tid = self.running.value if self.running is not None else -1
        return next((k for k, (t, _) in enumerate(self.queue) if t == tid), 0)


class ProcessExecutor(Generic[T, C]):
    """``workers`` processes running ``fn(task, context)``; see the module docstring. ``setup``: ``(function,
    args)`` each worker calls once at start (importable by reference); ``models``: the model modules the workers
    need, imported once by the fork server (None: all of them)."""

    def __init__(self, fn: Callable[[T, C], Any], context: C, workers: int, *, setup: tuple | None = None,
                 max_deaths: int = MAX_DEATHS_PER_TASK, timeout_s: float | None = None,
                 models: Sequence[str] | None = None):
        self.fn, self.context, self.workers = fn, context, max(1, int(workers))
        self.setup = setup
        self.max_deaths = max_deaths
        self.timeout_s = timeout_s
        self.wake: int | None = None                # see the module docstring
        self._ctx = _context(models)
        self._pool: list[_Worker] = []
        self._task_s = float("inf")                 # recent seconds per task (moving average)
        self._poller = _Poller()
        self.deaths = 0

    def _start(self) -> _Worker:
        parent, child = self._ctx.Pipe(duplex=True)
        running, ready = self._ctx.RawValue("q", -1), self._ctx.RawValue("d", 0.0)
        batch = BATCH_MAX if self.timeout_s is None else 1
        with _starting():
            proc = self._ctx.Process(target=_worker, name="rvnoise-worker", daemon=True,
                                     args=(child, self.fn, self.context, os.getpid(), self.setup, running, batch,
                                           ready))
            proc.start()
        child.close()
        return _Worker(proc, parent, running, ready)

    def start(self) -> None:
        """Start the missing workers now rather than at :meth:`map`: a run starts them before it writes its record,
        so that their fork and set-up overlap the main process's work, not the first files."""
        _live.add(self)
        self._join([w for w in self._pool if w.stopping])      # a second map after a stop: fresh workers
        self._pool = [w for w in self._pool if not w.stopping]
        while len(self._pool) < self.workers:
            self._pool.append(self._start())

    def first_ready(self) -> float | None:
        """When (``time.monotonic``) the first of the workers was set up and ready for tasks; None before."""
        times = [w.ready.value for w in self._pool if w.ready is not None and w.ready.value > 0]
        return min(times, default=None)

    def _depth(self, left: int) -> int:
        """Tasks a worker holds: behind short tasks, enough for two batches (module docstring), so it never waits
        for the parent; a second one under a time bound (no batches), or behind longer tasks (or before the first
        answer) while the source has ``left`` ≥ 2 × workers tasks."""
        if self._task_s >= QUEUE_BELOW_S:
            return 2 if left >= 2 * self.workers else 1
        if self.timeout_s is not None:
            return 2
        return max(2, min(QUEUE_MAX_TASKS, math.ceil(2 * BATCH_HOLD_S / max(self._task_s, 1e-6))))

    def map(self, tasks: Iterable[T]) -> Iterator[tuple[T, Any]]:
        source = iter(tasks)
        retry: deque[tuple[int, T]] = deque()
        deaths: dict[int, int] = {}
        exhausted = False
        next_tid = 0
        startup_deaths = 0
        try:
            self.start()
            while True:
                for w in self._pool:
                    chunk, not_now = [], False
                    while len(w.queue) < self._depth(len(retry) + operator.length_hint(source)):
                        if retry:
                            tid, task = retry.popleft()
                        elif not exhausted:
                            try:
                                task = next(source)
                            except StopIteration:
                                exhausted = True
                                break
                            if task is NOT_NOW:            # the source waits for its caller: hand control back
                                not_now = True
                                break
                            tid, next_tid = next_tid, next_tid + 1
                        else:
                            break
                        payload = pickle.dumps((tid, task), pickle.HIGHEST_PROTOCOL)
                        if w.queue and sum(w.sizes) - w.sizes[0] + len(payload) > QUEUE_MAX_BYTES:
                            # a busy worker may be blocked sending us its result: writing more than its pipe
                            # holds would block both; the task waits for an idle worker
                            retry.appendleft((tid, task))
                            break
                        if not w.queue:
                            w.started = time.monotonic()
                        w.queue.append((tid, task))
                        w.sizes.append(len(payload))
                        chunk.append(payload)
                    if chunk:                              # the worker's new tasks in one message (one write)
                        try:
                            w.conn.send_bytes(b"".join(chunk))
                        except (BrokenPipeError, OSError):
                            pass                           # its death is seen below and its tasks re-sent
                    if not_now:
                        yield NOT_NOW, None
                busy = [w for w in self._pool if w.queue]
                if not busy:
                    if exhausted:
                        return
                    continue                               # every worker idle after NOT_NOW: ask the source again
                timeout = None
                if self.timeout_s is not None:
                    timeout = max(0.0, min(w.started for w in busy) + self.timeout_s - time.monotonic())
                wake = [] if self.wake is None or self._task_s < QUEUE_BELOW_S else [self.wake]   # short tasks:
                # the next result comes soon enough, and a wake-up per file would cost the main process a loop
                ready = set(self._poller.wait([w.conn for w in busy] + [w.proc.sentinel for w in self._pool] + wake,
                                              timeout))
                if wake and self.wake in ready:
                    yield NOT_NOW, None
                for i, w in enumerate(self._pool):
                    if w.queue and not ready & {w.conn, w.proc.sentinel} and self.timeout_s is not None \
                            and time.monotonic() - w.started >= self.timeout_s \
                            and not w.conn.poll():         # an answer that came after wait() is kept (read next)
                        w.proc.kill()
                        w.proc.join()
                        w.conn.close()
                        (_, task), *waiting = w.queue
                        retry.extend(waiting)
                        self._pool[i] = self._start()
                        yield task, WorkerDeath(f"took longer than {self.timeout_s:g} s; its worker was stopped", 1)
                        continue
                    answers: list = []
                    if w.queue and ready & {w.conn, w.proc.sentinel}:     # a dead worker's answers first
                        try:
                            answers = w.conn.recv()
                        except (EOFError, OSError):
                            answers = []
                    answers = answers[:_in_order(answers, w.queue)]
                    if answers:
                        now = time.monotonic()
                        took = (now - w.started) / len(answers)
                        self._task_s = took if self._task_s == float("inf") else 0.75 * self._task_s + 0.25 * took
                        w.started = now                    # the worker took the next queued task at once
                        for _, result in answers:
                            _, task = w.queue.popleft()
                            w.sizes.popleft()
                            yield task, result
                        continue
                    if w.proc.sentinel not in ready:
                        continue        # alive, or died after wait(): its answers are read before its death
                    w.proc.join()
                    reason = death_reason(w.proc.exitcode)
                    w.conn.close()
                    self.deaths += 1
                    if not w.queue:
                        startup_deaths += 1
                        if startup_deaths > 3 * self.workers:
                            raise RuntimeError(f"workers keep dying before they get a task ({reason})")
                    else:
                        k = w.died_on()                    # before it: done, not sent; after it: never started
                        (tid, task), waiting = w.queue[k], [t for i, t in enumerate(w.queue) if i != k]
                        retry.extend(waiting)
                        n = deaths[tid] = deaths.get(tid, 0) + 1
                        if n >= self.max_deaths:
                            self._pool[i] = self._start()
                            yield task, WorkerDeath(reason, n)
                            continue
                        retry.append((tid, task))
                    self._pool[i] = self._start()
        finally:
            self.stop()

    def stop(self) -> None:
        """Tell every idle worker to exit (a polite ``None``) without waiting for it — :meth:`close` waits; the
        runner closes the executor after the run's record is written, so their exit overlaps it — and SIGKILL busy
        ones and wait for those (``map`` does this when it ends): no worker writes anything after ``stop``."""
        killed = []
        for w in self._pool:
            if w.stopping:
                continue
            w.stopping = True
            try:
                if not w.queue and w.proc.is_alive():
                    w.conn.send(None)
                else:
                    w.proc.kill()
                    killed.append(w)
            except (BrokenPipeError, OSError):
                killed.append(w)
        self._join(killed)

    def close(self) -> None:
        """Stop every worker (:meth:`stop`) and wait for them; SIGKILL to any that lingers."""
        self.stop()
        pool, self._pool = self._pool, []
        _live.discard(self)
        self._join(pool)

    @staticmethod
    def _join(pool: list[_Worker]) -> None:
        """Wait up to 5 s for the stopped workers of ``pool`` to exit, then SIGKILL the rest."""
        deadline = time.monotonic() + 5
        for w in pool:
            w.proc.join(max(0.0, deadline - time.monotonic()))
            if w.proc.is_alive():
                w.proc.kill()
                w.proc.join()
            w.conn.close()


class Counted(Generic[T]):
    """The iterator ``items`` with ``left()`` as its length hint (``operator.length_hint``): how many items it may
    still yield, for :class:`ProcessExecutor`'s queue behind long tasks."""

    def __init__(self, items: Iterator[T], left: Callable[[], int]):
        self._items, self._left = items, left

    def __iter__(self) -> "Counted[T]":
        return self

    def __next__(self) -> T:
        return next(self._items)

    def __length_hint__(self) -> int:
        return max(0, self._left())


class InlineExecutor(Generic[T, C]):
    """The same contract in the calling process (no isolation: a crash ends the caller)."""

    workers = 1

    def __init__(self, fn: Callable[[T, C], Any], context: C):
        self.fn, self.context = fn, context

    def map(self, tasks: Iterable[T]) -> Iterator[tuple[T, Any]]:
        for task in tasks:
            if task is NOT_NOW:
                yield task, None
                continue
            try:
                yield task, self.fn(task, self.context)
            except Exception as exc:
                yield task, TaskError(f"{type(exc).__name__}: {exc}", traceback.format_exc(limit=8))

    def close(self) -> None:
        pass
