"""Per-segment fan-out on Dask: a LocalCluster by default, or an existing scheduler by address.

Each submitted function opens the store itself and writes only its own segment's groups, so
nothing big travels through the scheduler and workers never share a writer."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, TypeVar

T = TypeVar("T")


def map_segments(
    fn: Callable[..., T], items: Sequence[Any], *args: Any, workers: int = 2, address: str | None = None
) -> list[T]:
    """[fn(item, *args) for item in items], run concurrently on Dask; results in input order.

    One item or one worker runs in-process (no cluster start-up). Worker processes use one thread
    each: the work inside (SfM, rendering) sets its own thread count."""
    if not items:
        return []
    if address is None and (workers <= 1 or len(items) == 1):
        return [fn(item, *args) for item in items]
    from dask.distributed import Client, LocalCluster

    if address is not None:
        with Client(address) as client:
            return client.gather(client.map(fn, items, *[[a] * len(items) for a in args], pure=False))
    n = min(workers, len(items))
    with (
        LocalCluster(
            n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, host="127.0.0.1"
        ) as cluster,
        Client(cluster) as client,
    ):
        return client.gather(client.map(fn, items, *[[a] * len(items) for a in args], pure=False))
