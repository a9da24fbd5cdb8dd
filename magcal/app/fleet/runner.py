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
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, as_completed, wait
from typing import Callable, Iterable

from .analyse import analyse


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run_local(tasks: Iterable[dict], on_result: Callable[[dict], None], workers: int | None = None) -> None:
    """The tasks on a pool of ``workers`` processes (all cores by default); at most twice as
    many in flight as there are workers, so memory stays bounded whatever the number of logs.
    One worker runs them in this process, one after another."""
    n = workers or default_workers()
    tasks = iter(tasks)
    if n == 1:
        for t in tasks:
            on_result(analyse(t))
        return
    with ProcessPoolExecutor(max_workers=n) as pool:
        pending = set()
        for t in tasks:
            pending.add(pool.submit(analyse, t))
            if len(pending) >= 2 * n:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    on_result(f.result())
        for f in as_completed(pending):
            on_result(f.result())


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
        it = iter(tasks)
        first = [client.submit(analyse, t, pure=False) for t in islice(it, window)]
        ac = as_completed(first)
        for fut in ac:
            on_result(fut.result())
            del fut  # the cluster forgets a result the client no longer holds
            nxt = next(it, None)
            if nxt is not None:
                ac.add(client.submit(analyse, nxt, pure=False))
