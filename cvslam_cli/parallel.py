"""Order-preserving parallel map over worker processes, shared by the stages.

Workers are started with the "spawn" method: a forked child inherits the parent's threads'
locks (OpenCV's and BLAS's thread pools, tqdm's monitor), and deadlocks when it touches
them. Read-only state the jobs need (a world, rigs, a config) is pickled once per worker
into `STATE` by the initializer instead of once per job. Each worker runs OpenCV single-
threaded: the parallelism is across jobs.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any, TypeVar

import cv2

J = TypeVar("J")
R = TypeVar("R")

STATE: dict[str, Any] = {}


def _init(state: Mapping[str, Any]) -> None:
    cv2.setNumThreads(1)
    STATE.clear()
    STATE.update(state)


def ordered_map(
    fn: Callable[[J], R],
    jobs: Iterable[J],
    *,
    workers: int,
    state: Mapping[str, Any],
    chunksize: int = 2,
) -> Iterator[R]:
    """`fn(job)` for every job, in order; `fn` (a module-level function) reads `STATE`.
    With `workers <= 1` everything runs in this process."""
    if workers <= 1:
        saved = dict(STATE)
        STATE.clear()
        STATE.update(state)
        try:
            yield from map(fn, jobs)
        finally:
            STATE.clear()
            STATE.update(saved)
        return
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(workers, initializer=_init, initargs=(dict(state),)) as pool:
        yield from pool.imap(fn, jobs, chunksize=chunksize)
