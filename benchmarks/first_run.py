"""A new user's first run: the README's first command on a fresh copy of the project, then how fast the
command answers afterwards.

- The README's first command, verbatim, in a fresh copy of the project (the files git tracks, nothing built)
  and a fresh virtual environment: wall time of the whole command, of its install and of `generate`, the
  seconds of each step (from the scene's store), and the peak memory of the largest process.
- On the scene it made: a cached re-run of the same `generate`, and the `error:` of a bad `--out` (a path
  under a file), each with the default engine and with `--engine prefect`.
- Ctrl-C: `generate` on a fresh scene, interrupted (SIGINT to its process group, as a terminal does) once the
  splats step has started; seconds from the signal to the exit, and the exit code.

`--quick` skips the fresh copy and install: it runs the same `generate` with this environment's `wonderverse`.

Last-line keys: `readme_seconds` (the whole first command, install included), `install_seconds`,
`preview_seconds` (those three absent with --quick), `generate_seconds`, `peak_rss_mb`, `cached_rerun_s_auto`,
`cached_rerun_s_prefect`, `bad_out_error_s_auto`, `bad_out_error_s_prefect`, `ctrl_c_exit_s`, `ctrl_c_exit_code`.
"""

from __future__ import annotations

import os
import re
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import parse_args, report

ROOT = Path(__file__).resolve().parents[1]


def readme_commands(readme: Path = ROOT / "README.md") -> list[str]:
    """The README's shell blocks, in order: the first installs and runs the main job, the second the tests."""
    return re.findall(r"```bash\n(.*?)\n```", readme.read_text(), re.S)


def fresh_copy(dest: Path) -> Path:
    """The project as a fresh clone has it (tracked files and new ones git does not ignore) copied to `dest`."""
    names = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        check=True,
    ).stdout.split(b"\0")
    for name in filter(None, names):
        src = ROOT / name.decode()
        if src.is_file():
            (dest / name.decode()).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name.decode())
    return dest


def clean_env() -> dict[str, str]:
    """This environment without any virtual environment or Python path of ours: what a new shell has."""
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    venv_bin = str(Path(sys.executable).parent)
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if p != venv_bin)
    return env


def scene_of(command: str) -> str:
    """The `--out` folder of the command's `generate`."""
    words = shlex.split(command.replace("&&", " "))
    return words[words.index("--out") + 1]


def run_readme_command(workdir: Path, timeout_s: float = 1800) -> subprocess.CompletedProcess:
    """The README's first command, verbatim, with bash in `workdir`."""
    return subprocess.run(
        ["bash", "-c", readme_commands()[0]],
        cwd=workdir,
        env=clean_env(),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def _timed(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> tuple[float, int]:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=cwd, env={**os.environ, **(env or {})}, capture_output=True, text=True)
    return time.perf_counter() - t0, r.returncode


def _ctrl_c(wonderverse: str, cwd: Path, prompt: str) -> tuple[float, int]:
    """Seconds from Ctrl-C (once splats started) to the exit of `generate` on a fresh scene, and its exit code."""
    proc = subprocess.Popen(
        [wonderverse, "generate", prompt, "--out", "scenes/interrupted"],
        cwd=cwd,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )
    assert proc.stderr is not None
    for line in proc.stderr:
        if "] splats:" in line:
            break
    t0 = time.perf_counter()
    os.killpg(proc.pid, signal.SIGINT)
    proc.wait()
    return time.perf_counter() - t0, proc.returncode


def _step_seconds(scene: Path) -> dict[str, float]:
    sys.path.insert(0, str(ROOT))
    from tasks import STEPS
    from wonderverse.store import SceneStore

    store = SceneStore.open(scene)
    metas = {s.name: store.meta(s.group) for s in STEPS}  # None: the step has not completed
    return {name: round(m.seconds or 0.0, 1) if m is not None else 0.0 for name, m in metas.items()}


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    work = Path(tempfile.mkdtemp(prefix="wv-first-run-"))
    headline: dict[str, float | int] = {}
    command = readme_commands()[0]
    scene_rel = scene_of(command)
    prompt = shlex.split(command.split("generate", 1)[1])[0]
    if args.quick:
        wonderverse = str(Path(sys.executable).parent / "wonderverse")
        t0 = time.perf_counter()
        subprocess.run([wonderverse, "generate", prompt, "--out", scene_rel], cwd=work, check=True, capture_output=True)
        headline["generate_seconds"] = round(time.perf_counter() - t0, 1)
    else:  # the command's parts one after another, as `&&` runs them, each timed
        fresh_copy(work)
        parts = {"install": [], "generate": [], "preview": []}
        for part in command.split(" && "):
            kind = "generate" if " generate " in part else "preview" if " preview " in part else "install"
            t0 = time.perf_counter()
            r = subprocess.run(["bash", "-c", part], cwd=work, env=clean_env(), capture_output=True, text=True)
            if r.returncode != 0:
                sys.exit(f"{part!r} failed (exit {r.returncode}):\n{r.stderr[-3000:]}")
            parts[kind].append(time.perf_counter() - t0)
        headline |= {f"{k}_seconds": round(sum(v), 1) for k, v in parts.items()}
        headline["readme_seconds"] = round(sum(map(sum, parts.values())), 1)
        wonderverse = str(work / ".venv" / "bin" / "wonderverse")
    headline["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 0)
    steps = _step_seconds(work / scene_rel)
    again = [wonderverse, "generate", prompt, "--out", scene_rel]
    home = {"PREFECT_HOME": str(work / "prefect-home")}
    for engine in ("auto", "prefect"):
        headline[f"cached_rerun_s_{engine}"] = round(_timed([*again, "--engine", engine], work, home)[0], 2)
    (work / "a-file").write_text("x")
    for engine in ("auto", "prefect"):
        bad = [wonderverse, "generate", prompt, "--out", "a-file/scene", "--engine", engine]
        headline[f"bad_out_error_s_{engine}"] = round(_timed(bad, work, home)[0], 2)
    seconds, code = _ctrl_c(wonderverse, work, prompt)
    headline |= {"ctrl_c_exit_s": round(seconds, 2), "ctrl_c_exit_code": code}
    rows = [{"step": k, "seconds": v} for k, v in steps.items()]
    rows += [{"step": k, "seconds": v} for k, v in headline.items()]
    report("first run", rows, headline)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
