"""Running the fleet's tasks: a local process pool (the default: every core, nothing else
needed) or a Dask distributed cluster (``scheduler``: the address of a running ``dask
scheduler``), the same task function (``analyse.analyse``) either way. Each result is handed to
``on_result`` in the calling process as it finishes, in whatever order the tasks finish; the
caller keeps it (``store``), so what finished before an interruption is kept.

On a cluster the workers read the logs by the paths given here: the logs must be where the
workers see them under the same path (a shared or network file system), and the workers must
have magcal installed at the same version.
"""

from __future__ import annotations

import os
from itertools import islice
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Iterable

from .analyse import analyse, unreadable


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run_local(tasks: Iterable[dict], on_result: Callable[[dict], None], workers: int | None = None) -> None:
    """The tasks on a pool of ``workers`` processes (all cores by default); at most twice as
    many in flight as there are workers, so memory stays bounded whatever the number of logs.
    One worker runs them in this process, one after another. A log that kills the process
    analysing it (a crash in a parser's compiled code, the memory a huge log takes) breaks the
    pool: the logs that were in flight are then analysed again one at a time, the one that kills
    its process alone becomes a row saying so, and the run goes on with a new pool."""
    n = workers or default_workers()
    tasks = iter(tasks)
    if n == 1:
        for t in tasks:
            on_result(analyse(t))
        return
    while (suspects := _pool_pass(tasks, on_result, n)) is not None:
        for t in suspects:
            on_result(_alone(t))


def _pool_pass(tasks, on_result: Callable[[dict], None], n: int) -> list[dict] | None:
    """Run tasks until they are done (None) or the pool breaks (the tasks in flight then)."""
    pending: dict = {}
    current = None
    try:
        with ProcessPoolExecutor(max_workers=n) as pool:
            for current in tasks:
                pending[pool.submit(analyse, current)] = current
                current = None
                if len(pending) >= 2 * n:
                    _take(pending, on_result)
            while pending:
                _take(pending, on_result)
    except BrokenProcessPool:
        return list(pending.values()) + ([current] if current is not None else [])
    return None


def _take(pending: dict, on_result: Callable[[dict], None]) -> None:
    done, _ = wait(pending, return_when=FIRST_COMPLETED)
    for f in done:
        result = f.result()  # a broken pool raises here, the task still pending
        del pending[f]
        on_result(result)


def _alone(task: dict) -> dict:
    with ProcessPoolExecutor(max_workers=1) as pool:
        try:
            return pool.submit(analyse, task).result()
        except BrokenProcessPool as exc:
            return unreadable(task, "WorkerDied", f"{task['path']}: the process analysing it died ({exc})")


def _dask():
    try:
        from dask.distributed import Client, as_completed
    except ImportError as exc:
        from ...core.errors import ConfigError

        raise ConfigError("--scheduler runs on a Dask cluster, which needs dask.distributed from the optional "
                          "extra 'fleet': pip install 'magcal-mpu9150[fleet]'") from exc
    return Client, as_completed


def run_dask(tasks: list[dict], on_result: Callable[[dict], None], scheduler: str, window: int = 0) -> None:
    """The tasks on the Dask cluster at ``scheduler`` (``tcp://host:8786``), at most ``window``
    in flight (default: 2 × the cluster's worker threads) so the client holds a bounded number
    of results whatever the fleet's size."""
    Client, as_completed = _dask()
    with Client(scheduler) as client:
        threads = sum(client.nthreads().values()) or 1
        window = window or 2 * threads
        it, of = iter(tasks), {}

        def submit(task):
            fut = client.submit(analyse, task, pure=False)
            of[fut.key] = task
            return fut

        ac = as_completed([submit(t) for t in islice(it, window)])
        for fut in ac:
            on_result(_result(fut, of.pop(fut.key)))
            del fut  # the cluster forgets a result the client no longer holds
            nxt = next(it, None)
            if nxt is not None:
                ac.add(submit(nxt))


def _result(fut, task: dict) -> dict:
    """A finished task's result; a task the cluster gave up on (its worker died on it each time
    it was tried: Dask's KilledWorker) is that log's row with the reason."""
    try:
        return fut.result()
    except Exception as exc:  # noqa: BLE001 — one log's end on the cluster is that log's row
        return unreadable(task, type(exc).__name__, f"{task['path']}: the cluster could not analyse it: {exc}")
