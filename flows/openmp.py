"""How idle OpenMP threads wait, chosen by how busy the machine is when a command starts.

torch's CPU kernels (splat training) run in OpenMP parallel regions thousands of times a second. Between regions
GNU OpenMP's threads spin before they sleep. On an idle machine spinning is what makes training fast (waking a
sleeping thread costs more than a short region); on a busy one spinning threads steal the cores that the work
needs. Measured on the 2-core machine, extending a 3-segment preview world (`python -m benchmarks.openmp_wait`):
alone, 64 s with libgomp's default spin (300 000), 65 s with 3000 spins, 79 s with sleeping threads
(`OMP_WAIT_POLICY=PASSIVE`); two at once, 308 s, 99 s and 86 s each. So a command that starts on an idle machine
spins briefly (nearly all of the default's gain alone; beside another run 16 % slower than sleeping, not 3.6x) and
one that starts beside other work sleeps at once. Commands that may run for long beside others (`serve`, whose
scheduled runs may overlap; `studio`, whose jobs choose again as they start) and those that train nothing sleep.

Standard library only: the supervising parent (`flows.supervise`) chooses before the command's child loads torch.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping

AUTO_ENV = "WONDERVERSE_OPENMP_AUTO"  # marks a choice made here, so that a child started later chooses afresh
WAIT_KEYS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
IDLE_SPINS = "3000"  # a few tens of microseconds: enough to bridge torch's gaps between regions, no more
BUSY_CPUS_MAX = 0.5  # spinning only when less than half a core is in use by anything else
SAMPLED_COMMANDS = ("generate", "extend", "reconstruct", "batch")  # runs that train, one at a time
SAMPLE_S = 0.25  # /proc/stat counts in 10 ms ticks: a shorter look mistakes a process starting up for load


def busy_cpus(sample_s: float = SAMPLE_S) -> float:
    """How many cores are busy now (0 to the core count): the machine's non-idle share over `sample_s` seconds
    (/proc/stat), or the 1-minute load average where there is no /proc."""

    def totals() -> tuple[int, int] | None:
        try:
            with open("/proc/stat") as f:
                fields = [int(x) for x in f.readline().split()[1:]]
        except (OSError, ValueError):
            return None
        idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
        return sum(fields), idle

    before = totals()
    if before is None:
        return os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    time.sleep(sample_s)
    after = totals() or before
    total, idle = after[0] - before[0], after[1] - before[1]
    return (os.cpu_count() or 1) * (1.0 - idle / total) if total > 0 else 0.0


def users_wait(environ: Mapping[str, str]) -> bool:
    """Whether the user set the wait (either variable, not marked as chosen here)."""
    return environ.get(AUTO_ENV) != "1" and any(k in environ for k in WAIT_KEYS)


def wait_env(environ: Mapping[str, str], busy: float) -> dict[str, str]:
    """`environ` with the OpenMP wait chosen for a machine with `busy` cores in use: a few spins when it is idle,
    sleeping threads otherwise. A wait the user set is kept."""
    if users_wait(environ):
        return dict(environ)
    env = {k: v for k, v in environ.items() if k not in WAIT_KEYS}
    # GOMP_SPINCOUNT overrides the policy in libgomp; OMP_WAIT_POLICY speaks to other OpenMP runtimes
    if busy < BUSY_CPUS_MAX:
        chosen = {"GOMP_SPINCOUNT": IDLE_SPINS}
    else:
        chosen = {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "0"}
    return env | chosen | {AUTO_ENV: "1"}


def command_env(environ: Mapping[str, str], argv: list[str]) -> dict[str, str]:
    """The environment for the child that runs `wonderverse ARGV`: the machine is looked at only for a run that
    trains, and only when the user set no wait (the look costs every such command, a refusal too, `SAMPLE_S`)."""
    sampled = bool(argv) and argv[0] in SAMPLED_COMMANDS and not users_wait(environ)
    return wait_env(environ, busy_cpus() if sampled else math.inf)
