"""Work over items (a step's segments) from the calling process: in order, on threads, or, inside a Prefect task
run, as a nested task run per item; and `as_step`, which runs work as a step's (what it may write)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Any, TypeVar

from wonderverse.progress import ProgressFn, no_progress
from wonderverse.store import writing

T = TypeVar("T")


def as_step(step: str | None, fn: Callable[..., T], *args: Any) -> T:
    """`fn(*args)` as work of step `step` (what it may write: `store.writing`); on a Dask worker too, where the
    process knows nothing of the step that submitted it."""
    if step is None:
        return fn(*args)
    with writing(step):
        return fn(*args)


def in_prefect_task() -> bool:
    """Whether this runs inside a Prefect task run (without importing Prefect when the run never did)."""
    if "prefect" not in sys.modules:  # a run under the local engine never imports Prefect (1-2 s): not in a task
        return False
    from prefect.context import TaskRunContext

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
    if not in_prefect_task():
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
