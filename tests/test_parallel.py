"""One Dask cluster for several per-segment calls (`tasks.parallel.segment_pool`), as a guided flow's waves use it:
started once (ahead of time, or on the first call that needs it), used by every call, shut down at the end;
without workers everything runs in-process, submitted work deferred until its result is asked for."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
from conftest import tiny_config

from flows.pipeline import execute
from tasks import parallel
from tasks.parallel import segment_pool
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore


def _pid(_: Any) -> int:
    return os.getpid()


def _threads(_: Any) -> tuple[str | None, int]:
    import torch

    return os.environ.get("OMP_NUM_THREADS"), torch.get_num_threads()


def _fails(item: int) -> int:
    raise WonderError(f"segment s{item:03d}: it cannot be checked")


def _opened(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Counts the clusters (clients) `tasks.parallel` opens from now on."""
    opened: list[int] = []
    real = parallel._open_client

    def counting(*args: Any) -> Any:
        opened.append(1)
        return real(*args)

    monkeypatch.setattr(parallel, "_open_client", counting)
    return opened


@pytest.mark.e2e
def test_a_pool_starts_one_cluster_and_every_call_uses_it(monkeypatch: pytest.MonkeyPatch) -> None:
    opened = _opened(monkeypatch)
    me = os.getpid()
    with segment_pool(2) as pool:
        lone = pool.submit(_pid, 0, only_if_started=True)  # one segment is not worth starting workers for
        assert pool.gather("check", [0], {0: lone}) == [me] and not opened
        pool.start()  # in the background: the caller goes on meanwhile
        first = pool.map(_pid, [1, 2, 3, 4])
        assert pool.ready
        futures = {i: pool.submit(_pid, i, only_if_started=True) for i in (5, 6)}  # started: on the workers
        gathered = pool.gather("check", [6, 5], futures)
        alone = pool.map(_pid, [7])  # the cluster is up: even a lone item runs there
        with pytest.raises(WonderError, match=r"^segment s00[89]: it cannot be checked$"):
            pool.map(_fails, [8, 9])
        after = pool.map(_pid, [10, 11])  # a failed task leaves the cluster as it was
    assert len(opened) == 1
    workers = set(first) | set(gathered) | set(alone) | set(after)
    assert me not in workers and len(workers) == 2, workers  # the same two worker processes throughout
    deadline = time.monotonic() + 20
    while any(psutil.pid_exists(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(psutil.pid_exists(p) for p in workers)  # shut down with the block


@pytest.mark.e2e
def test_a_cluster_leaves_this_process_environment_as_it_was() -> None:
    """Dask's nanny sets OMP_NUM_THREADS=1 (and more) in its own process, this one, before it spawns a worker: torch
    started after that trained the splats on one thread, and a resumed run (no cluster) then gave other splats.
    The workers still get their one thread each."""
    before = dict(os.environ)
    assert parallel.map_segments(_threads, [1, 2], workers=2) == [("1", 1), ("1", 1)]
    changed = {k for k in set(before) | set(os.environ) if before.get(k) != os.environ.get(k)}
    assert not changed, changed


def test_without_workers_everything_runs_in_process_when_its_result_is_asked_for(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def no_cluster(*args: Any) -> Any:
        raise AssertionError("a pool of one worker started a cluster")

    monkeypatch.setattr(parallel, "_open_client", no_cluster)
    ran: list[int] = []

    def record(i: int) -> int:
        ran.append(i)
        return 10 * i

    with segment_pool(1) as pool:
        pool.start()
        futures = {i: pool.submit(record, i) for i in (1, 2, 3)}
        assert ran == []  # deferred, as a guided wave's checks are while its segments render
        assert pool.gather("check", [3, 1, 2], futures) == [30, 10, 20] and ran == [3, 1, 2]
        assert futures[1].result() == 10 and ran == [3, 1, 2]  # run once
        assert pool.map(_pid, [1, 2]) == [os.getpid()] * 2
        failing = pool.submit(_fails, 4)
        for _ in range(2):  # its error, each time it is asked for
            with pytest.raises(WonderError, match="segment s004"):
                failing.result()


def test_map_segments_starts_a_cluster_per_call_only_when_it_needs_one(monkeypatch: pytest.MonkeyPatch) -> None:
    opened = _opened(monkeypatch)
    assert parallel.map_segments(_pid, [1], workers=2) == [os.getpid()]  # one item: in-process
    assert parallel.map_segments(_pid, [1, 2], workers=1) == [os.getpid()] * 2
    small = {"pixels": 99, "min_pixels": 100}  # less work than a cluster's start costs
    assert parallel.map_segments(_pid, [1, 2], workers=2, **small) == [os.getpid()] * 2
    assert not opened

    def asked(*args: Any) -> Any:
        raise LookupError("a cluster was asked for")

    monkeypatch.setattr(parallel, "_open_client", asked)  # as much work as a start costs: a cluster (none started)
    with pytest.raises(LookupError, match="asked for"):
        parallel.map_segments(_pid, [1, 2], workers=2, pixels=100, min_pixels=100)


@pytest.mark.e2e
def test_a_guided_scene_checks_every_wave_on_one_cluster(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A guided 5-segment scene (initial, then two rounds of left and right: waves of 1, 2 and 2 segments) with two
    segment workers: one cluster for the whole step, each wave's two checks on it."""
    opened = _opened(monkeypatch)
    on_cluster: list[list[bool]] = []
    real_gather = parallel.SegmentPool.gather

    def gather(self: Any, step: str, items: Any, futures: dict[Any, Any], progress: Any = None) -> list[Any]:
        out = real_gather(self, step, items, futures, progress)
        on_cluster.append([type(futures[i]).__module__.startswith("distributed") for i in items])
        return out

    monkeypatch.setattr(parallel.SegmentPool, "gather", gather)
    video = {"options": {"fault_probability": 0.0, "accept_guide": True}}
    cfg = tiny_config(video=video, extensions={"rounds": 2})
    cfg = cfg.model_copy(update={"execution": cfg.execution.model_copy(update={"segment_workers": 2})})
    results = execute(tmp_path / "s", cfg, until="generate_segments")
    assert results[-1].detail.startswith("5 rendered, 0 cached; checked and placed"), results[-1]
    assert len(opened) == 1
    assert [len(w) for w in on_cluster] == [1, 2, 2] and on_cluster[1:] == [[True, True], [True, True]], on_cluster
    store = SceneStore.open(tmp_path / "s")
    for seg in ("s000", "s001", "s002", "s003", "s004"):
        assert store.cache_key_of(f"segments/{seg}/accepted") is not None  # complete
        assert store.cache_key_of(f"segments/{seg}/geometry") is not None
    # the step run again (its segments all made and checked): nothing to check, no cluster started
    from tasks import STEPS, step_keys
    from tasks import generate_segments as gs
    from tasks.base import StepContext

    ctx = StepContext(step_keys(STEPS, cfg)["generate_segments"], cfg.execution)
    detail = gs.run(SceneStore.open(tmp_path / "s", mode="r+"), gs.params(cfg), ctx)
    assert detail.startswith("0 rendered, 5 cached") and len(opened) == 1, detail
