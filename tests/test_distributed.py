"""Per-segment steps on an existing Dask cluster: a real `dask scheduler` and two `dask worker`
processes on loopback (as `wonderverse generate --dask tcp://host:8786` would use), the store on a
path all of them see. The scheduler's task stream says which worker ran which segment."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import ROOT, tiny_config

from flows.pipeline import execute
from wonderverse.store import SceneStore

pytestmark = pytest.mark.e2e  # a Dask cluster and the pipeline


BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    """Address of a scheduler with two single-threaded worker processes; all stopped afterwards."""
    if not (BIN / "dask").is_file():
        pytest.skip(f"the dask CLI is not installed in {BIN}")
    address = f"tcp://127.0.0.1:{free_port()}"
    # workers import tasks/ and wonderverse/ from the repo; idle OpenMP threads sleep on a shared machine
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1"}
    dash = ["--dashboard-address", "127.0.0.1:0"]
    port = address.rsplit(":", 1)[1]
    procs = [
        subprocess.Popen(
            [BIN / "dask", "scheduler", "--host", "127.0.0.1", "--port", port, *dash],
            env=env,
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        for _ in range(2):
            procs.append(
                subprocess.Popen(
                    [
                        BIN / "dask",
                        "worker",
                        address,
                        "--nthreads",
                        "1",
                        "--nworkers",
                        "1",
                        "--host",
                        "127.0.0.1",
                        *dash,
                    ],
                    env=env,
                    cwd=ROOT,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        from dask.distributed import Client

        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=90)
        yield address
    finally:
        for p in reversed(procs):  # workers first, so they do not try to reconnect to a gone scheduler
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=5)


def test_segments_are_checked_and_their_priors_written_on_the_cluster_workers(cluster: str, tmp_path: Path):
    from dask.distributed import Client, get_task_stream

    cfg = tiny_config(extensions={"rounds": 1}, seed=3)
    cfg = cfg.model_copy(update={"execution": cfg.execution.model_copy(update={"dask_address": cluster})})
    scene = tmp_path / "scene"
    with Client(cluster) as client:
        workers = client.run(os.getpid)  # worker address -> its process id
        t0 = time.perf_counter()
        with get_task_stream(client) as stream:
            results = execute(scene, cfg, until="priors")
        seconds = time.perf_counter() - t0
    assert [r.status for r in results] == ["ran"] * len(results) and results[-1].step == "priors"

    store = SceneStore.open(scene)
    segs = store.children("segments")
    assert segs == ["s000", "s001", "s002"]  # initial segment + one left and one right extension
    for seg in segs:
        assert store.cache_key_of(f"segments/{seg}/accepted") is not None
        assert store.cache_key_of(f"priors/{seg}") is not None
        assert store.array(f"priors/{seg}/depth").shape == (6, 64, 96)

    ran = [(t["key"], t["worker"]) for t in stream.data if t["status"] == "OK"]
    for prefix in ("check_segment", "priors_segment"):
        on = [w for key, w in ran if str(key).startswith(prefix)]
        assert len(on) == len(segs), (prefix, ran)  # one task per segment, each finished on a worker
        assert set(on) <= set(workers) and os.getpid() not in {workers[w] for w in on}
    assert len({w for _, w in ran}) == 2, ran  # both workers took part
    print(f"until priors on the 2-worker cluster: {seconds:.1f} s", [(r.step, round(r.seconds, 1)) for r in results])


def _double(x: int) -> int:
    return 2 * x


def test_a_local_cluster_says_nothing_when_port_8787_is_taken(recwarn):
    """Another cluster or dashboard on 8787 (common) must not put "Port 8787 is already in use" on the user's
    terminal: our LocalCluster serves its scheduler's HTTP on a free port."""
    import contextlib
    import socket

    from tasks.parallel import map_segments

    with socket.socket() as busy:
        with contextlib.suppress(OSError):  # taken already: the case itself
            busy.bind(("127.0.0.1", 8787))
            busy.listen()
        assert map_segments(_double, [1, 2, 3], workers=2) == [2, 4, 6]
    assert not [w for w in recwarn if "already in use" in str(w.message)], [str(w.message) for w in recwarn]
