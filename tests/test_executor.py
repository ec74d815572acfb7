"""The worker pool on its own: results as tasks complete, a dying worker costs only its task (retried once), the
pool refills, per-task time bound, and the same contract in-process."""

from __future__ import annotations

import os
import signal
import time

import pytest

from roadview_noise import executor
from roadview_noise.executor import (NOT_NOW, Counted, InlineExecutor, ProcessExecutor, TaskError, WorkerDeath,
                                     death_reason, start_server)


def work(task: int, context: dict) -> tuple[int, int]:
    """Square the task; die on the tasks the context names (``exit``: os._exit, ``kill``: SIGKILL once, then
    work, by a marker file), sleep on ``sleep``, raise on ``raise``; every task takes ``pause_s`` first."""
    time.sleep(context.get("pause_s", 0.0))
    if task in context.get("exit", ()):
        os._exit(3)
    if task in context.get("kill_once", ()):
        marker = os.path.join(context["dir"], f"killed-{task}")
        if not os.path.exists(marker):
            open(marker, "w").close()
            os.kill(os.getpid(), signal.SIGKILL)
    if task in context.get("sleep", ()):
        time.sleep(60)
    if task in context.get("raise", ()):
        raise ValueError(f"bad task {task}")
    return task, task * task


def test_deaths_retries_and_errors(tmp_path):
    ctx = {"exit": (3,), "kill_once": (5,), "raise": (7,), "dir": str(tmp_path)}
    ex = ProcessExecutor(work, ctx, 2)
    results = dict(ex.map(range(12)))
    assert sorted(results) == list(range(12))
    assert isinstance(results[3], WorkerDeath) and results[3].deaths == 2 and "exited with code 3" in \
        results[3].reason
    assert results[5] == (5, 25)                                   # killed once, retried on a fresh worker
    assert isinstance(results[7], TaskError) and "bad task 7" in results[7].message
    assert all(results[t] == (t, t * t) for t in range(12) if t not in (3, 7))
    assert ex.deaths == 3 and all(w.stopping for w in ex._pool)        # told to exit when map ended
    ex.close()
    assert not ex._pool


def test_timeout_and_early_close():
    ex = ProcessExecutor(work, {"sleep": (1,)}, 2, timeout_s=1.0)
    t0 = time.monotonic()
    results = dict(ex.map(range(4)))
    assert isinstance(results[1], WorkerDeath) and "longer than 1 s" in results[1].reason
    assert time.monotonic() - t0 < 30
    ex = ProcessExecutor(work, {}, 2)
    it = ex.map(iter(range(1000)))
    next(it)
    it.close()                                                     # leaving early stops every worker
    assert ex._pool and all(w.stopping for w in ex._pool)
    ex.close()                                                     # and close waits for them
    assert not ex._pool


def test_map_tells_its_workers_to_exit_and_a_second_map_gets_fresh_ones():
    """When ``map`` ends its workers are told to exit (``close`` waits for them: the runner closes after writing the
    run record); a second ``map`` on the same executor starts fresh workers, with no death counted."""
    ex = ProcessExecutor(work, {}, 2)
    try:
        assert dict(ex.map(range(4))) == {t: (t, t * t) for t in range(4)}
        first = [w.proc for w in ex._pool]
        assert len(first) == 2 and all(w.stopping for w in ex._pool)
        assert dict(ex.map(range(4, 8))) == {t: (t, t * t) for t in range(4, 8)}
        assert ex.deaths == 0 and all(not p.is_alive() for p in first)
        assert not {w.proc for w in ex._pool} & set(first)
    finally:
        ex.close()
    assert not ex._pool
def test_workers_started_before_map_take_its_tasks():
    """``start`` forks the workers before ``map`` (a run's record is written meanwhile); ``map`` uses those."""
    ex = ProcessExecutor(work, {}, 2)
    try:
        ex.start()
        started = [w.proc for w in ex._pool]
        assert len(started) == 2 and all(p.is_alive() for p in started)
        assert dict(ex.map(range(6))) == {t: (t, t * t) for t in range(6)}
        assert [w.proc for w in ex._pool] == started and ex.deaths == 0
    finally:
        ex.close()
    assert not ex._pool and all(not p.is_alive() for p in started)


def test_first_ready_is_when_a_worker_was_set_up_not_when_it_got_a_task():
    """``first_ready`` (a run's ``worker_start_seconds``): when the first worker was ready for tasks, set before any
    task is sent and kept after."""
    ex = ProcessExecutor(work, {}, 2)
    try:
        before = time.monotonic()
        assert ex.first_ready() is None
        ex.start()
        deadline = before + 60
        while ex.first_ready() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        ready = ex.first_ready()
        sent = time.monotonic()
        assert ready is not None and before < ready < sent
        assert dict(ex.map([3])) == {3: (3, 9)} and ex.first_ready() == ready
    finally:
        ex.close()


def test_a_source_that_waits_gets_control_back():
    """A source that yields NOT_NOW is handed back ``(NOT_NOW, None)`` at once and asked again later (also when no
    task is running); every real task still runs once. Here: a wait before every task (the first while nothing runs),
    and no task ahead of the results the caller saw."""
    for ex in (ProcessExecutor(work, {}, 2), InlineExecutor(work, {})):
        seen: list = []
        waits = 0

        def source():
            nonlocal waits
            for t in range(6):
                waits += 1
                yield NOT_NOW
                while t > len(seen):
                    waits += 1
                    yield NOT_NOW
                yield t

        for task, result in ex.map(source()):
            if task is NOT_NOW:
                assert result is None
            else:
                seen.append(result)
        assert seen == [(t, t * t) for t in range(6)] and waits >= 6


def test_inline_executor_same_contract():
    results = dict(InlineExecutor(work, {"raise": (2,)}).map(range(4)))
    assert results[1] == (1, 1) and isinstance(results[2], TaskError)


def test_death_reasons_in_words():
    assert death_reason(-9) == "worker died: signal 9 (SIGKILL: out of memory or killed)"
    assert "SIGSEGV" in death_reason(-11) and "native code" in death_reason(-11)
    assert death_reason(2) == "worker died: it exited with code 2"


@pytest.fixture
def queue_below_s(monkeypatch) -> float:
    """Every task counts as short, so the queue is in use from the second task on: on a loaded machine a task's
    measured time (which includes a fresh worker's start) may exceed ``QUEUE_BELOW_S``, and the queue would not be
    used when the tests need it."""
    monkeypatch.setattr(executor, "QUEUE_BELOW_S", 60.0)
    return executor.QUEUE_BELOW_S


def test_short_tasks_are_queued_and_a_death_costs_only_the_running_one(tmp_path, queue_below_s):
    """Behind short tasks each worker holds a second one; a worker that dies is blamed for the task it was running
    only: the task queued behind it runs on a fresh worker, with no death counted."""
    ctx = {"exit": (30,), "kill_once": (22,), "dir": str(tmp_path)}
    ex = ProcessExecutor(work, ctx, 2)
    results = dict(ex.map(range(40)))
    assert ex._task_s < queue_below_s                                 # the queue was in use when they died
    assert sorted(results) == list(range(40))
    assert isinstance(results[30], WorkerDeath) and results[30].deaths == 2
    assert all(results[t] == (t, t * t) for t in range(40) if t != 30)
    assert ex.deaths == 3


def test_a_worker_that_answers_then_dies_is_blamed_for_the_task_it_died_on(monkeypatch, queue_below_s):
    """A loaded machine: the parent is descheduled between ``wait()`` and reading what it returned, and meanwhile a
    worker answers its task and dies on the one queued behind it. Its answer is kept and the death is blamed on the
    task it died on (once more on retry), never on the one it answered."""
    real_wait = executor._Poller.wait

    def slow_wait(self, objects, timeout=None):
        ready = real_wait(self, objects, timeout)
        time.sleep(0.1)
        return ready

    monkeypatch.setattr(executor._Poller, "wait", slow_wait)
    ex = ProcessExecutor(work, {"exit": (3, 6), "pause_s": 0.03}, 2)
    results = dict(ex.map(range(10)))
    assert sorted(results) == list(range(10))
    assert all(isinstance(results[t], WorkerDeath) and results[t].deaths == 2 for t in (3, 6))
    assert all(results[t] == (t, t * t) for t in range(10) if t not in (3, 6))
    assert ex.deaths == 4


def test_an_answer_that_arrives_after_the_wait_is_kept_not_timed_out(monkeypatch):
    """The parent's wait() times out at the task's limit and the worker's answer arrives before the parent looks:
    the answer is kept, the worker not stopped."""
    real_wait = executor._Poller.wait

    def slow_wait(self, objects, timeout=None):
        ready = real_wait(self, objects, timeout)
        if not ready:
            time.sleep(2.0)                     # the answer (due ≈ 0.1 s after the limit) arrives meanwhile
        return ready

    monkeypatch.setattr(executor._Poller, "wait", slow_wait)
    ex = ProcessExecutor(work, {"pause_s": 0.6}, 1, timeout_s=0.5)
    assert dict(ex.map([4])) == {4: (4, 16)} and ex.deaths == 0


def test_fork_server_keeps_what_it_preloaded():
    """The fork server is started once for the modules a run needs and restarted (with what it had and the new
    ones) only when a later run needs a module it lacks."""
    from multiprocessing import forkserver

    forkserver._forkserver._stop()              # earlier tests' server preloaded every model
    start_server(["roadview_noise.models.radar.fog"])
    pid = forkserver._forkserver._forkserver_pid
    start_server(["roadview_noise.models.radar.fog"])
    assert forkserver._forkserver._forkserver_pid == pid
    start_server(["roadview_noise.models.radar.rain"])
    assert forkserver._forkserver._forkserver_pid != pid
    assert {"roadview_noise.models.radar.fog", "roadview_noise.models.radar.rain"} <= \
        set(forkserver._forkserver._preload_modules)
    assert dict(ProcessExecutor(work, {}, 1).map([3])) == {3: (3, 9)}


def echo_large(task: tuple[int, bytes], context: dict) -> bytes:
    """Answer at once with a result far larger than a pipe holds."""
    return task[1] * 8


def test_large_tasks_behind_large_results_never_deadlock(queue_below_s):
    """Short tasks are queued, but a large one is not sent to a busy worker: that worker may be blocked sending its
    own large result, and both sides would wait for each other for ever (a ROS bag's inline messages did this)."""
    import threading

    ex = ProcessExecutor(echo_large, {}, 2)
    tasks = [(i, bytes([i]) * 512 * 1024) for i in range(24)]
    done: dict = {}
    runner = threading.Thread(target=lambda: done.update(ex.map(tasks)), daemon=True)
    runner.start()
    runner.join(120)
    assert not runner.is_alive(), "the executor deadlocked"
    assert len(done) == 24 and all(done[t] == t[1] * 8 for t in tasks)
    assert ex._task_s < queue_below_s                                 # short tasks: the queue would have been used


def _count_waits(monkeypatch) -> list:
    """A list that gets an item each time the parent waits for its workers."""
    waits: list = []
    real_wait = executor._Poller.wait

    def counting_wait(self, objects, timeout=None):
        waits.append(1)
        return real_wait(self, objects, timeout)

    monkeypatch.setattr(executor._Poller, "wait", counting_wait)
    return waits


def test_short_tasks_are_answered_in_batches_and_a_death_blames_the_running_task_only(tmp_path, monkeypatch,
                                                                                      queue_below_s):
    """Behind short tasks a worker holds many and answers several per message: the parent wakes far less often than
    once per task. A worker that dies is blamed (shared memory) for the task it was running, never for the ones it
    had finished but not yet sent, which run again without a death counted."""
    waits = _count_waits(monkeypatch)
    ex = ProcessExecutor(work, {}, 1)
    assert dict(ex.map(range(300))) == {t: (t, t * t) for t in range(300)}
    assert ex._depth(0) > 2 and len(waits) < 150
    ex = ProcessExecutor(work, {"exit": (150,)}, 1)
    results = dict(ex.map(range(300)))
    assert isinstance(results[150], WorkerDeath) and results[150].deaths == 2 and ex.deaths == 2
    assert all(results[t] == (t, t * t) for t in range(300) if t != 150)


def test_a_refill_of_short_tasks_goes_to_its_worker_in_one_message(monkeypatch, queue_below_s):
    """Behind short tasks the parent hands a worker the tasks of a refill in one message (one write, not one per
    task: chunked dispatch); the worker still runs and answers each, in order."""
    from multiprocessing.connection import Connection

    sends: list = []
    real_send = Connection.send_bytes

    def counting_send(self, buf, *args):
        sends.append(1)
        return real_send(self, buf, *args)

    monkeypatch.setattr(Connection, "send_bytes", counting_send)
    ex = ProcessExecutor(work, {}, 1)
    assert list(ex.map(range(300))) == [(t, (t, t * t)) for t in range(300)]
    assert ex._depth(0) > 2 and len(sends) < 100


def test_a_time_bound_answers_each_task_at_once(monkeypatch, queue_below_s):
    """Under ``timeout_s`` a held result would count against the next task's time: one task queued, no batches
    (the parent wakes once per task)."""
    waits = _count_waits(monkeypatch)
    ex = ProcessExecutor(work, {}, 1, timeout_s=30)
    assert dict(ex.map(range(40))) == {t: (t, t * t) for t in range(40)}
    assert ex._depth(0) == 2 and len(waits) >= 40


def test_tasks_longer_than_the_hold_are_answered_each_at_once(monkeypatch, queue_below_s):
    """A short task (queued behind the running one) that takes longer than ``BATCH_HOLD_S`` is answered as soon as
    it ends: holding it for the next one would delay it by a whole task and leave the worker waiting for new tasks
    with finished ones unsent (≈ 50 ms LiDAR files)."""
    waits = _count_waits(monkeypatch)
    ex = ProcessExecutor(work, {"pause_s": 2 * executor.BATCH_HOLD_S}, 1)
    assert dict(ex.map(range(20))) == {t: (t, t * t) for t in range(20)}
    assert ex._depth(0) >= 2 and len(waits) >= 20


def test_long_tasks_get_a_second_queued_while_enough_are_left_and_a_death_blames_the_running_one(tmp_path,
                                                                                                 monkeypatch):
    """Behind tasks of at least ``QUEUE_BELOW_S`` a worker holds a second task while the source has ≥ 2 × workers
    left (its length hint), one near the end. A worker that dies with two tasks is blamed for the one it was
    running only: the one queued behind runs on a fresh worker with no death counted."""
    held: list = []                                 # (the task blamed, the tasks its worker held) per death
    died_on = executor._Worker.died_on

    def recording(self):
        k = died_on(self)
        held.append((self.queue[k][1], len(self.queue)))
        return k

    monkeypatch.setattr(executor._Worker, "died_on", recording)
    ctx = {"exit": (2,), "kill_once": (6,), "dir": str(tmp_path), "pause_s": 2 * executor.QUEUE_BELOW_S}
    pulled: list = []

    def tasks():
        for t in range(12):
            pulled.append(t)
            yield t

    ex = ProcessExecutor(work, ctx, 2)
    results = dict(ex.map(Counted(tasks(), lambda: 12 - len(pulled))))
    assert held[0] == (2, 2)                        # it died on task 2 holding task 3 behind it
    assert sorted(results) == list(range(12))
    assert isinstance(results[2], WorkerDeath) and results[2].deaths == 2
    assert all(results[t] == (t, t * t) for t in range(12) if t != 2)
    assert ex.deaths == 3 and ex._task_s >= executor.QUEUE_BELOW_S
    assert ex._depth(4) == 2 and ex._depth(3) == 1 and ex._depth(0) == 1
