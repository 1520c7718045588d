"""Ctrl-C and SIGTERM stop a `wonderverse` command at once and cleanly (`main` here is the console script).

The command runs in a child process of its own session, and the parent only waits for it. A
terminal's Ctrl-C (SIGINT), SIGTERM and SIGHUP therefore reach the parent alone: it kills the child's whole
process group (the run, its Dask workers, Prefect's ephemeral server) with SIGKILL, says so in one line and
exits 128 + the signal's number (130 for Ctrl-C, 143 for SIGTERM). Should the parent itself be killed
(kill -9), a tiny reaper process in the child's group kills it as soon as the parent is gone, so no run, Dask worker
or Prefect server outlives the command. The parent also chooses how the child's OpenMP threads wait
(`flows.openmp`), before the child loads torch.

Why a kill and not a graceful stop: the main thread may sit for a minute inside a C call (COLMAP's mapper,
Open3D) where Python cannot interrupt it, Prefect and Dask react to SIGINT in their own ways (the first
Ctrl-C killed Prefect's server while the run spun on), and pycolmap's glog handler prints a C stack on
SIGTERM. A kill is safe here because the store only ever commits whole groups (staged, renamed, marked
complete last): every step and segment complete before the signal is kept, and the same command resumes.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys

from flows.openmp import command_env

CHILD_ENV = "WONDERVERSE_CHILD"  # set in the child: it runs the command itself
_STOPS = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM", signal.SIGHUP: "SIGHUP"}


def _kill_group(child: subprocess.Popen) -> None:
    """SIGKILL the child's process group, and any descendant that left it."""
    try:
        import psutil

        descendants = psutil.Process(child.pid).children(recursive=True)
    except Exception:  # already gone, or psutil missing: the group kill below still covers the usual case
        descendants = []
    with contextlib.suppress(ProcessLookupError):
        os.killpg(child.pid, signal.SIGKILL)
    for p in descendants:
        with contextlib.suppress(Exception):
            p.kill()


# Kills its process group (the child's: the run, its workers, Prefect's server) once the parent is gone,
# however it went (kill -9 included): it waits for the end of a pipe whose only writer is the parent. As a
# member of the group it also keeps the group's id from being reused by an unrelated process meanwhile.
_REAPER = """import os, signal
os.read(0, 1)
os.killpg(os.getpgrp(), signal.SIGKILL)
"""
_PARENT_FD_ENV = "WONDERVERSE_PARENT_FD"


def run_supervised(argv: list[str]) -> int:
    """Run `python -m flows.cli ARGV` as a child in its own session; returns the exit code to use."""
    parent_alive, _writer = os.pipe()  # the write end stays open in this process only, until it exits
    child = subprocess.Popen(
        [sys.executable, "-m", "flows.cli", *argv],
        env={**command_env(os.environ, argv), CHILD_ENV: "1", _PARENT_FD_ENV: str(parent_alive)},
        start_new_session=True,
        pass_fds=(parent_alive,),
    )
    os.close(parent_alive)
    stops: list[int] = []

    def stop(signum: int, frame: object) -> None:
        if not stops:
            stops.append(signum)
            _kill_group(child)

    for s in _STOPS:
        signal.signal(s, stop)
    rc = child.wait()
    if stops:
        _kill_group(child)  # a grandchild that outlived its parent
        signum = stops[0]
        if sys.stderr.isatty():  # the live progress bar was cut mid-line and its cursor hidden
            sys.stderr.write("\r\x1b[2K\x1b[?25h")
        kept = (
            ""
            if argv[:1] in (["view"], ["serve"], ["inspect"], ["report"], ["preview"])
            else ": every step and segment already complete is kept in the scene; run the same command again to resume"
        )
        print(f"stopped by {_STOPS[signal.Signals(signum)]}{kept}", file=sys.stderr)
        return 128 + signum
    if rc < 0:  # killed from outside (the OOM killer, kill -9 of the child)
        print(
            f"error: the run was killed by signal {-rc}; what was complete is kept in the scene, run the same "
            "command again to resume",
            file=sys.stderr,
        )
        return 128 - rc
    return rc


def main() -> None:
    """The `wonderverse` console script and `python -m flows`: supervise the command. This module imports only the
    standard library, so the parent, which merely waits, starts in milliseconds (the command's own imports, typer,
    pydantic and the rest, happen once, in the child)."""
    sys.exit(run_supervised(sys.argv[1:]))


def start_reaper() -> None:
    """In the child: start the reaper of this process group, reading the parent's pipe."""
    fd = os.environ.pop(_PARENT_FD_ENV, None)
    if fd is None:
        return
    # -I -S: no site-packages, no user paths, no .pth finders: it needs only os and signal
    subprocess.Popen([sys.executable, "-I", "-S", "-c", _REAPER], stdin=int(fd))
    os.close(int(fd))
