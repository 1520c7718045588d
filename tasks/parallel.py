"""Per-segment work on Dask (a LocalCluster by default, an existing scheduler by address), gathered through
`tasks.fan_out` (so inside a Prefect task run every segment is a task run of its own).

`map_segments` starts a cluster for its one call; `segment_pool` keeps one open for a block of calls (a guided
flow's waves), started ahead of time if wanted, with work submitted per segment as soon as it is ready. Each
submitted function opens the store itself and writes only its own segment's groups, so nothing big travels through
the scheduler and workers never share a writer."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, wait
from contextlib import ExitStack, contextmanager, suppress
from typing import Any, TypeVar

from tasks.fan_out import as_step, fan_out
from wonderverse.progress import ProgressFn

T = TypeVar("T")


def _open_client(address: str | None, n_workers: int, closing: ExitStack) -> Any:
    """A Dask client of the scheduler at `address`, else of a new LocalCluster of `n_workers` processes; both are
    closed by `closing`. (Not `with Client(...)`: a client entered as a context must be left in the thread that
    entered it, and `SegmentPool` starts its cluster in a thread of its own.)"""
    from dask.distributed import Client

    from tasks.local_cluster import local_cluster

    if address is not None:
        cluster: Any = address
    else:
        cluster = local_cluster(n_workers)
        closing.callback(cluster.close)
    client = Client(cluster)
    closing.callback(client.close)
    return client


def _send(client: Any, step: str | None, fn: Callable[..., Any], *args: Any) -> Any:
    """`fn(*args)` on the cluster as work of `step`, keyed after `fn` as a plain submit is (`check_segment-…`)."""
    from dask.utils import funcname  # dask loads only when there is a cluster

    return client.submit(as_step, step, fn, *args, key=f"{funcname(fn)}-{uuid.uuid4().hex}", pure=False)


class _Deferred:
    """The in-process stand-in for a Dask future: `fn(*args)` runs when its result is first asked for (so work
    submitted while rendering runs afterwards, in the order results are asked for, as without workers)."""

    def __init__(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        self.fn, self.args, self.started = fn, args, False
        self._done: Future[Any] = Future()
        self._lock = threading.Lock()

    def result(self) -> Any:
        """`fn(*args)`, run on the first call (its error raised on every call)."""
        with self._lock:
            if not self.started:
                self.started = True
                try:
                    self._done.set_result(self.fn(*self.args))
                except BaseException as e:
                    self._done.set_exception(e)
        return self._done.result()


class SegmentPool:
    """Per-segment work on one Dask cluster kept open across calls: a LocalCluster of `workers` processes (or an
    existing scheduler at `address`), started on the first call that needs it or ahead of time with `start`, and
    shut down when the `segment_pool` block ends. Without workers (1, no address) everything runs in-process.

    Starting a LocalCluster costs seconds (spawning the worker processes, each importing the project on its
    first task): a flow that maps segments wave after wave pays that once instead of per wave."""

    def __init__(self, workers: int, address: str | None, step: str | None = None) -> None:
        self.workers, self.address, self.step = workers, address, step
        self._stack = ExitStack()
        self._lock = threading.Lock()
        self._started: Future[Any] | None = None

    @property
    def in_process(self) -> bool:
        """Whether there are no workers: everything runs in the calling process."""
        return self.address is None and self.workers <= 1

    @property
    def ready(self) -> bool:
        """Whether the cluster is up (or was asked for and failed: asking for it raises the error)."""
        return self._started is not None and self._started.done()

    def start(self) -> None:
        """Start the cluster now, in the background, so its start-up overlaps the caller's own work."""
        if self.in_process:
            return
        with self._lock:
            if self._started is not None:
                return
            self._started = Future()
        threading.Thread(target=self._open, name="dask-cluster-start", daemon=True).start()

    def _open(self) -> None:
        assert self._started is not None
        try:
            client = _open_client(self.address, self.workers, self._stack)
        except BaseException as e:  # the first caller that needs the cluster raises it
            self._started.set_exception(e)
        else:
            self._started.set_result(client)

    def client(self, progress: ProgressFn | None = None, n: int = 0) -> Any:
        """The cluster's client, once it is up (`progress` hears "starting Dask workers" when it is not yet)."""
        if not self.ready and progress is not None:
            progress(0, n, "starting Dask workers" if self.address is None else "connecting to Dask")
        self.start()
        assert self._started is not None
        return self._started.result()

    def submit(self, fn: Callable[..., T], *args: Any, only_if_started: bool = False) -> Any:
        """`fn(*args)` on a worker: a future whose `result()` waits for it (and raises its error). In-process (no
        workers, or `only_if_started` and no LocalCluster started yet) it is deferred: it runs when its result is
        first asked for, unless `gather` sends it to the cluster first. A scheduler given by address takes it."""
        if self.in_process or (only_if_started and self.address is None and self._started is None):
            return _Deferred(fn, args)
        return _send(self.client(), self.step, fn, *args)

    def gather(
        self, step: str, items: Sequence[Any], futures: dict[Any, Any], progress: ProgressFn | None = None
    ) -> list[Any]:
        """The results of the work submitted per item (`futures[item]`), in input order, through `fan_out` (so
        each is a Prefect task run of its own under Prefect). Deferred work of two or more items goes to the
        cluster (started now if need be); a lone item's runs in-process (as `map` runs one item)."""
        if not self.in_process and (len(items) > 1 or self.address is not None):
            for item in items:
                f = futures[item]
                if isinstance(f, _Deferred) and not f.started:
                    futures[item] = _send(self.client(progress, len(items)), self.step, f.fn, *f.args)
        on_cluster = any(not isinstance(futures[item], _Deferred) for item in items)
        return fan_out(step, items, lambda item: futures[item].result(), len(items) if on_cluster else 1, progress)

    @staticmethod
    def settle(futures: Iterable[Any]) -> None:
        """Wait for the submitted work that is running on the cluster, its errors ignored (deferred work is not
        run): after a failure, so that what the workers are writing is finished before the cluster stops."""
        for f in (f for f in futures if not isinstance(f, _Deferred)):
            with suppress(Exception):
                f.result()

    def map(
        self,
        fn: Callable[..., T],
        items: Sequence[Any],
        *args: Any,
        step: str = "segments",
        progress: ProgressFn | None = None,
    ) -> list[T]:
        """[fn(item, *args) for item in items] on the cluster; results in input order. One item runs in-process
        while no cluster is up (none is started for it); `step` and `progress` as in `fan_out`."""
        if not items:
            return []
        if self.in_process or (self.address is None and len(items) == 1 and not self.ready):
            return fan_out(step, items, lambda item: fn(item, *args), progress=progress)
        client = self.client(progress, len(items))
        on = self.step or step
        return fan_out(step, items, lambda item: _send(client, on, fn, item, *args).result(), len(items), progress)

    def close(self) -> None:
        """Shut the cluster down (once its start-up, if still going on, has finished)."""
        try:
            if self._started is not None:
                wait([self._started])
        finally:
            self._stack.close()


@contextmanager
def segment_pool(workers: int, address: str | None = None, step: str | None = None) -> Iterator[SegmentPool]:
    """A `SegmentPool` for the block: one cluster for every `map` and `submit` in it, shut down at its end; `step`:
    the step whose work it runs (what that work may write)."""
    pool = SegmentPool(workers, address, step)
    try:
        yield pool
    finally:
        pool.close()


def map_segments(
    fn: Callable[..., T],
    items: Sequence[Any],
    *args: Any,
    workers: int = 2,
    address: str | None = None,
    step: str = "segments",
    progress: ProgressFn | None = None,
    pixels: int = 0,
    min_pixels: int = 0,
) -> list[T]:
    """[fn(item, *args) for item in items], run concurrently on Dask; results in input order.

    One item, one worker or, without a scheduler's `address`, fewer `pixels` (the items' frames) than `min_pixels`
    run in-process (no cluster start-up). `step` names the per-item task runs; `progress` hears of each finished
    item as in `fan_out`. A cluster of its own for this call (min(workers, items) processes); `segment_pool` keeps
    one for several."""
    if not items:
        return []
    workers = 1 if address is None and pixels < min_pixels else workers
    with segment_pool(min(workers, len(items)), address, step) as pool:
        return pool.map(fn, items, *args, step=step, progress=progress)
