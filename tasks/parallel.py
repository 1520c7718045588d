"""Per-segment fan-out: threads in-process, or Dask (a LocalCluster by default, an existing scheduler by
address); inside a Prefect task run every segment is a task run of its own.

Each submitted function opens the store itself and writes only its own segment's groups, so
nothing big travels through the scheduler and workers never share a writer."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from typing import Any, TypeVar

from wonderverse.progress import ProgressFn, no_progress

T = TypeVar("T")


def _in_prefect_task() -> bool:
    try:
        from prefect.context import TaskRunContext
    except ImportError:
        return False
    return TaskRunContext.get() is not None


def fan_out(
    step: str,
    items: Sequence[Any],
    work: Callable[[Any], T],
    concurrency: int = 1,
    progress: ProgressFn | None = None,
) -> list[T]:
    """[work(item) for item in items] with at most `concurrency` at once; results in input order.

    progress(items finished, len(items), the item just finished) is called once before any item (0 of N)
    and then as each item finishes, in completion order, from the calling thread (where the step's reporter
    and Prefect task run are; worker threads see neither).

    Inside a Prefect task run (the step's), each item runs as a nested task run named "<step> <item>",
    so the UI shows per-segment work with its own state, duration and logs; a failure fails the step."""
    report = progress or no_progress
    n = len(items)
    if n:
        report(0, n, "")
    out: list[Any] = [None] * n
    if not _in_prefect_task():
        if concurrency <= 1 or n <= 1:
            for k, item in enumerate(items):
                out[k] = work(item)
                report(k + 1, n, str(item))
            return out
        with ThreadPoolExecutor(concurrency) as pool:
            index = {pool.submit(work, item): k for k, item in enumerate(items)}
            for done, future in enumerate(as_completed(index), 1):
                out[index[future]] = future.result()
                report(done, n, str(items[index[future]]))
        return out
    from prefect import task
    from prefect.cache_policies import NO_CACHE
    from prefect.futures import as_completed as prefect_as_completed

    per_item = task(name=f"{step} segment", cache_policy=NO_CACHE)(work)
    size = max(concurrency, 1)
    done = 0
    for start in range(0, n, size):
        futures = [
            per_item.with_options(task_run_name=f"{step} {item}").submit(item) for item in items[start : start + size]
        ]
        where = {id(f): start + j for j, f in enumerate(futures)}
        for future in prefect_as_completed(futures):
            k = where[id(future)]
            out[k] = future.result()
            done += 1
            report(done, n, str(items[k]))
    return out


@contextmanager
def _dask_client(address: str | None, n_workers: int) -> Iterator[Any]:
    from dask.distributed import Client, LocalCluster

    if address is not None:
        with Client(address) as client:
            yield client
        return
    # Worker processes use one thread each: the work inside (SfM, rendering) sets its own thread count.
    with (
        LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            # The scheduler serves HTTP whatever the dashboard setting; on a free port, so a busy 8787 (another
            # cluster, a dashboard) costs no "Port 8787 is already in use" warning. No dashboard.
            dashboard_address="127.0.0.1:0",
            scheduler_kwargs={"dashboard": False},
            # A task's failure reaches the user once, as the step's error; the workers must not print it too.
            silence_logs=logging.CRITICAL,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def map_segments(
    fn: Callable[..., T],
    items: Sequence[Any],
    *args: Any,
    workers: int = 2,
    address: str | None = None,
    step: str = "segments",
    progress: ProgressFn | None = None,
) -> list[T]:
    """[fn(item, *args) for item in items], run concurrently on Dask; results in input order.

    One item or one worker runs in-process (no cluster start-up). `step` names the per-item task runs;
    `progress` hears of each finished item as in `fan_out`."""
    if not items:
        return []
    if address is None and (workers <= 1 or len(items) == 1):
        return fan_out(step, items, lambda item: fn(item, *args), progress=progress)
    if progress is not None:
        progress(0, len(items), "starting Dask workers" if address is None else "connecting to Dask")
    with _dask_client(address, min(workers, len(items))) as client:
        return fan_out(
            step, items, lambda item: client.submit(fn, item, *args, pure=False).result(), len(items), progress
        )
