"""Per-segment fan-out: threads in-process, or Dask (a LocalCluster by default, an existing scheduler by
address); inside a Prefect task run every segment is a task run of its own.

Each submitted function opens the store itself and writes only its own segment's groups, so
nothing big travels through the scheduler and workers never share a writer."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any, TypeVar

T = TypeVar("T")


def _in_prefect_task() -> bool:
    try:
        from prefect.context import TaskRunContext
    except ImportError:
        return False
    return TaskRunContext.get() is not None


def fan_out(step: str, items: Sequence[Any], work: Callable[[Any], T], concurrency: int = 1) -> list[T]:
    """[work(item) for item in items] with at most `concurrency` at once; results in input order.

    Inside a Prefect task run (the step's), each item runs as a nested task run named "<step> <item>",
    so the UI shows per-segment work with its own state, duration and logs; a failure fails the step."""
    if not _in_prefect_task():
        if concurrency <= 1 or len(items) <= 1:
            return [work(item) for item in items]
        with ThreadPoolExecutor(concurrency) as pool:
            return list(pool.map(work, items))
    from prefect import task
    from prefect.cache_policies import NO_CACHE

    per_item = task(name=f"{step} segment", cache_policy=NO_CACHE)(work)
    size = max(concurrency, 1)
    out: list[T] = []
    for start in range(0, len(items), size):
        chunk = items[start : start + size]
        futures = [per_item.with_options(task_run_name=f"{step} {item}").submit(item) for item in chunk]
        out += [f.result() for f in futures]
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
            n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None, host="127.0.0.1"
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
) -> list[T]:
    """[fn(item, *args) for item in items], run concurrently on Dask; results in input order.

    One item or one worker runs in-process (no cluster start-up). `step` names the per-item task runs."""
    if not items:
        return []
    if address is None and (workers <= 1 or len(items) == 1):
        return fan_out(step, items, lambda item: fn(item, *args))
    with _dask_client(address, min(workers, len(items))) as client:
        return fan_out(step, items, lambda item: client.submit(fn, item, *args, pure=False).result(), len(items))
