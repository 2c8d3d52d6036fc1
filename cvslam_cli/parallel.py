"""Order-preserving parallel map over worker processes, shared by the stages.

Workers are started with the "spawn" method: a forked child inherits the parent's threads'
locks (OpenCV's and BLAS's thread pools, tqdm's monitor), and deadlocks when it touches
them. Read-only state the jobs need (a world, rigs, a config) is pickled once per worker
into `STATE` by the initializer instead of once per job. Each worker runs OpenCV single-
threaded: the parallelism is across jobs.

The pool is `concurrent.futures.ProcessPoolExecutor`, which watches its workers: one that
dies (killed, out of memory, a crash in native code) breaks the pool at once, and the map
raises `WorkerError` naming the job it was waiting for instead of waiting forever. Workers
ignore SIGINT and SIGTERM (and are started with them blocked, so that one arriving while a
worker imports does not raise there either), so Ctrl-C (sent to the whole process group) and
SIGTERM reach only the main process, which cancels the jobs not started, lets the running
ones finish and shuts the pool down (no worker traceback, no semaphore left behind);
`cli.main` turns SIGTERM into the same unwinding as Ctrl-C. A worker killed with SIGKILL is
the WorkerError above (the map also watches the workers itself, as the pool can miss the death
of one it started on demand); the workers left are then killed too (SIGTERM, which the pool sends
them, is ignored).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import multiprocessing
import multiprocessing.connection
import multiprocessing.process
import signal
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

import cv2

from cvslam_cli.errors import CvslamError

J = TypeVar("J")
R = TypeVar("R")

STATE: dict[str, Any] = {}


class WorkerError(CvslamError):
    """A worker process died (was killed, ran out of memory, crashed) before its job ended."""


_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


def _init(state: Mapping[str, Any]) -> None:
    # Ctrl-C and SIGTERM sent to the whole process group are the main process's to handle;
    # the worker was started with them blocked (`_stop_signals_blocked`): ignored now, any
    # that came while it started up is dropped
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
    cv2.setNumThreads(1)
    STATE.clear()
    STATE.update(state)


def ordered_map(
    fn: Callable[[J], R],
    jobs: Iterable[J],
    *,
    workers: int,
    state: Mapping[str, Any],
    describe: Callable[[J], str] = lambda job: "a job",
    ahead: int = 4,
) -> Iterator[R]:
    """`fn(job)` for every job, in order; `fn` (a module-level function) reads `STATE`.
    With `workers <= 1` everything runs in this process. At most `ahead` jobs per worker
    are queued at once, so a long stream of jobs does not pile up in memory. `describe(job)`
    names a job in the error raised when a worker dies."""
    if workers <= 1:
        # STATE holds `state` only while a job runs, restored before each result is handed
        # out: a generator left unfinished (or collected late) never changes it under
        # another ordered_map
        for job in jobs:
            saved = dict(STATE)
            STATE.clear()
            STATE.update(state)
            try:
                result = fn(job)
            finally:
                STATE.clear()
                STATE.update(saved)
            yield result
        return
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(dict(state),))
    pending: collections.deque[tuple[J, Future[R]]] = collections.deque()
    try:
        it = iter(jobs)
        for job in it:
            try:
                with _stop_signals_blocked():  # submit starts the workers (spawn: on demand)
                    future = pool.submit(fn, job)
            except BrokenProcessPool:  # it broke since the last result: name the oldest job
                raise _died(pending[0][0] if pending else job, describe) from None
            pending.append((job, future))
            if len(pending) >= workers * ahead:
                yield _result(pool, *pending.popleft(), describe)
        while pending:
            yield _result(pool, *pending.popleft(), describe)
    except WorkerError:
        _kill_workers(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@contextlib.contextmanager
def _stop_signals_blocked() -> Iterator[None]:
    """SIGINT and SIGTERM held back in this thread meanwhile (delivered after): a worker
    process started now inherits the blocked mask through fork and exec, so a Ctrl-C while
    it imports (before `_init` ignores it) cannot raise KeyboardInterrupt there."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


_WATCH_S = 1.0  # how often a wait for a result checks that every worker is alive


def _result(
    pool: ProcessPoolExecutor, job: J, future: Future[R], describe: Callable[[J], str]
) -> R:
    """The job's result; WorkerError once any worker has died. The pool notices a death
    itself only for the workers it knew of when its manager thread last woke, and a worker
    started on demand (spawn) can be added just after that, so the wait also watches the
    workers' sentinels itself, every `_WATCH_S` seconds: no worker exits while the map runs."""
    while True:
        try:
            return future.result(timeout=_WATCH_S)
        except concurrent.futures.TimeoutError:
            if _a_worker_died(pool):
                raise _died(job, describe) from None
        except BrokenProcessPool:
            raise _died(job, describe) from None


def _workers(pool: ProcessPoolExecutor) -> list[multiprocessing.process.BaseProcess]:
    """The pool's worker processes (the executor keeps them in `_processes`, pid -> Process,
    on every Python this runs on)."""
    return list((getattr(pool, "_processes", None) or {}).values())


def _a_worker_died(pool: ProcessPoolExecutor) -> bool:
    sentinels = []
    for process in _workers(pool):
        with contextlib.suppress(ValueError):  # not started yet, or already closed
            sentinels.append(process.sentinel)
    return bool(multiprocessing.connection.wait(sentinels, timeout=0))


def _kill_workers(pool: ProcessPoolExecutor) -> None:
    """SIGKILL the workers left in a broken pool. The pool's own clean-up only SIGTERMs them,
    which they ignore (see the module docstring), and one can block forever on a queue lock
    the dead worker held, so the pool's shutdown would wait on it forever.

    Then close this process's copy of the result pipe's write end: a worker killed part-way
    through sending a result leaves the pool's manager thread reading the rest of that
    message, and with this process holding a write end open the read never ends (nor the
    shutdown that joins the thread). Once the workers are gone it reads end-of-file and the
    pool breaks as for any other death."""
    for process in _workers(pool):
        with contextlib.suppress(OSError, ValueError):
            process.kill()
    writer = getattr(getattr(pool, "_result_queue", None), "_writer", None)
    if writer is not None:
        with contextlib.suppress(OSError):
            writer.close()


def _died(job: J, describe: Callable[[J], str]) -> WorkerError:
    return WorkerError(
        f"a worker process died (killed, or out of memory) while working on "
        f"{describe(job)} or a job beside it"
    )
