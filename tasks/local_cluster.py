"""The Dask LocalCluster the per-segment steps start when no scheduler is given (`tasks.parallel`): worker processes
bound to 127.0.0.1, one thread each, no dashboard, and this process's environment left as it was."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

# What Dask's nanny would set in its own process before spawning a worker (`distributed.nanny.pre-spawn-environ`):
# set inside each worker instead (`distributed.nanny.environ`), so that numerical libraries there use one thread each
# while this process keeps its own. Left in this process, OMP_NUM_THREADS=1 reached torch whenever its OpenMP started
# after the cluster did: the splats then trained on one thread, with other sums, than a run that started none.
WORKER_ENVIRON = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


@contextmanager
def _environment_kept() -> Iterator[None]:
    """This process's environment as it was before the block (the nanny still sets PYTHONHASHSEED in it)."""
    before = dict(os.environ)
    try:
        yield
    finally:
        for name in set(os.environ) - set(before):
            del os.environ[name]
        os.environ.update(before)


def local_cluster(n_workers: int) -> Any:
    """A new LocalCluster of `n_workers` worker processes of one thread each (the work inside, SfM or rendering,
    sets its own thread count)."""
    import dask
    from dask.distributed import LocalCluster

    environ = {"distributed.nanny.pre-spawn-environ": {}, "distributed.nanny.environ": WORKER_ENVIRON}
    with dask.config.set(environ), _environment_kept():
        return LocalCluster(
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
        )
