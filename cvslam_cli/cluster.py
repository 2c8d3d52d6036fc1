"""Scale-out on Dask (`dask.distributed`): the cluster `cvslam batch`, `cvslam sweep` and
`cvslam extract --scheduler` run their tasks on.

`cluster(scheduler, local_workers)` connects to a running scheduler (`tcp://host:8786`: a
cluster started with `dask scheduler` / `dask worker`, or by dask-jobqueue, dask-kubernetes,
`dask ssh`; see docs/batch.md) or starts a `LocalCluster` of `local_workers` processes with
one thread each (a cvslam task uses one core; the parallelism is across tasks). Workers read
and write the same paths as the client: a shared filesystem is assumed.

`ordered_chunk_map` is the distributed form of `parallel.ordered_map`: jobs are sent in
chunks, a bounded number in flight, and the results come back in job order, so what is
built from them is byte-identical to the local run.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any, TypeVar

from cvslam_cli.errors import CvslamError

J = TypeVar("J")
R = TypeVar("R")

# a worker thread's jobs read `parallel.STATE`; one chunk at a time per worker process
_STATE_LOCK = threading.Lock()


def _distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise CvslamError(
            "Dask is not installed: pip install 'dask[distributed]' (a dependency of cvslam)"
        ) from None
    return distributed


@contextlib.contextmanager
def cluster(scheduler: str | None, local_workers: int | None = None) -> Iterator[Any]:
    """A `distributed.Client`: on the scheduler at `scheduler`, else on a new local cluster
    of `local_workers` processes (default: one per core), closed on exit."""
    distributed = _distributed()
    if scheduler:
        try:
            client = distributed.Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise CvslamError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        with client:
            yield client
        return
    n = local_workers or os.cpu_count() or 1
    with (
        distributed.LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.ERROR,
        ) as local,
        distributed.Client(local) as client,
    ):
        yield client


def _run_chunk(fn: Callable[[J], R], chunk: list[J], state: Mapping[str, Any]) -> list[R]:
    """On a worker: `fn` over `chunk` with `parallel.STATE` set to `state`."""
    import cv2

    from cvslam_cli.parallel import STATE

    with _STATE_LOCK:
        cv2.setNumThreads(1)
        STATE.clear()
        STATE.update(state)
        try:
            return [fn(j) for j in chunk]
        finally:
            STATE.clear()


def ordered_chunk_map(
    fn: Callable[[J], R],
    jobs: Iterable[J],
    *,
    scheduler: str,
    state: Mapping[str, Any],
    chunk_size: int = 8,
    in_flight_per_worker: int = 2,
) -> Iterator[R]:
    """`fn(job)` for every job on the cluster at `scheduler`, in job order; `fn` (a module-
    level function) reads `parallel.STATE`, set on each worker from `state` (sent once).
    At most `in_flight_per_worker` chunks per worker are out at a time, so memory stays
    bounded however long the stream of jobs."""
    distributed = _distributed()
    with cluster(scheduler) as client:
        shared = client.scatter(dict(state), broadcast=True)
        workers = max(1, len(client.scheduler_info()["workers"]))
        it = iter(jobs)
        pending: deque[Any] = deque()

        def submit() -> None:
            chunk = list(itertools.islice(it, chunk_size))
            if chunk:
                pending.append(client.submit(_run_chunk, fn, chunk, shared, pure=False))

        for _ in range(workers * in_flight_per_worker):
            submit()
        while pending:
            future = pending.popleft()
            submit()
            try:
                results = future.result()
            except distributed.KilledWorker as exc:
                raise CvslamError(f"--scheduler {scheduler}: a worker died ({exc})") from None
            finally:
                if future.status != "finished":
                    for f in pending:
                        f.cancel()
            yield from results
