"""The OpenMP wait a command's child gets: spinning briefly on an idle machine, sleeping beside other work, and
the user's own choice kept."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from flows import openmp
from flows.openmp import AUTO_ENV, BUSY_CPUS_MAX, IDLE_SPINS, busy_cpus, command_env, wait_env
from tests.conftest import ROOT


def test_idle_machine_spins_briefly_and_busy_one_sleeps() -> None:
    idle = wait_env({"PATH": "/bin"}, busy=0.1)
    assert idle["GOMP_SPINCOUNT"] == IDLE_SPINS and "OMP_WAIT_POLICY" not in idle and idle["PATH"] == "/bin"
    busy = wait_env({"PATH": "/bin"}, busy=1.5)
    assert busy["OMP_WAIT_POLICY"] == "PASSIVE" and busy["GOMP_SPINCOUNT"] == "0"


def test_the_users_wait_is_kept_and_a_chosen_one_is_chosen_again() -> None:
    for users in ({"OMP_WAIT_POLICY": "ACTIVE"}, {"GOMP_SPINCOUNT": "10"}):
        assert wait_env(users, busy=0.0) == users
        assert wait_env(users, busy=2.0) == users
    # a child of a chosen environment (a studio job, the benchmark's children) chooses for the machine it meets
    chosen_when_busy = wait_env({}, busy=2.0)
    again = wait_env(chosen_when_busy, busy=0.0)
    assert again["GOMP_SPINCOUNT"] == IDLE_SPINS and "OMP_WAIT_POLICY" not in again and again[AUTO_ENV] == "1"


def test_busy_cpus_sees_a_spinning_process() -> None:
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        seen = busy_cpus(0.5)
    finally:
        spinner.kill()
        spinner.wait()
    assert BUSY_CPUS_MAX <= seen <= (os.cpu_count() or 1) + 1e-6


def test_the_supervised_child_gets_the_chosen_wait(tmp_path: Path) -> None:
    """The console script's parent passes a choice to the command's child (the process that loads torch): here the
    child is a shell script that writes the environment it was given."""
    seen = tmp_path / "env.txt"
    child = tmp_path / "child.sh"
    child.write_text(f"#!/bin/sh\nenv > {seen}\n")
    child.chmod(0o755)
    code = (
        "import sys\nfrom flows.supervise import run_supervised\n"
        f"sys.executable = {str(child)!r}\nsys.exit(run_supervised(['extend']))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    probe = subprocess.run([sys.executable, "-c", code], env={**env, "PYTHONPATH": str(ROOT)}, capture_output=True)
    assert probe.returncode == 0, probe.stderr
    given = dict(line.split("=", 1) for line in seen.read_text().splitlines() if "=" in line)
    assert given[AUTO_ENV] == "1" and given["GOMP_SPINCOUNT"] in (IDLE_SPINS, "0")


def test_commands_that_train_nothing_sleep_without_looking() -> None:
    for argv in (["serve"], ["studio"], ["inspect", "x"], []):
        assert command_env({}, argv)["OMP_WAIT_POLICY"] == "PASSIVE"


def test_a_wait_the_user_set_is_kept_without_looking(monkeypatch: pytest.MonkeyPatch) -> None:
    def look(*_: object) -> float:
        raise AssertionError("the machine was looked at although the user set the wait")

    monkeypatch.setattr(openmp, "busy_cpus", look)
    for env in ({"OMP_WAIT_POLICY": "PASSIVE"}, {"GOMP_SPINCOUNT": "10"}):
        assert command_env(env, ["generate", "a lake"]) == env
    chosen_before = {"GOMP_SPINCOUNT": "0", AUTO_ENV: "1"}  # chosen by a parent: chosen again, so looked at
    with pytest.raises(AssertionError, match="looked at"):
        command_env(chosen_before, ["extend", "x", "a lake"])
