"""How OpenMP's idle threads should wait: one extension of a 3-segment world alone and two at once, per wait setting.

torch's CPU training (the splats step) runs thousands of OpenMP parallel regions a second; between them GNU
OpenMP's threads spin, then sleep. The CLI chooses the wait as a run starts (`flows/openmp.py`); this measures
the choices it has, end to end as the CLI runs an extension (the steps and the report, in a fresh process):

- `sleep` (`OMP_WAIT_POLICY=PASSIVE`), `spin3000` (`GOMP_SPINCOUNT=3000`), `default` (libgomp's own when neither
  is set: 300 000 spins, set explicitly), each alone on the machine and two at once (both started together);
- `auto`: the CLI's choice, alone, and two started 15 s apart (the second sees the first at work).

World: `benchmarks.scale`'s (preview, procedural, the default prompt with one left and one right extension); the
extension: "a frozen lake on the left" (the 4th segment).

Usage: `python -m benchmarks.openmp_wait [--quick] [--out DIR]` (`--quick`: `sleep` and `spin3000` only).
Last line (JSON): `alone_s` and `pair_s` per setting (seconds of one extension; of the slower of the pair),
`spin_speedup_alone` (sleep / spin3000, alone), `spin_slowdown_pair` (spin3000 / sleep, two at once),
`auto_alone_s`, `auto_staggered_s` (the slower of the staggered pair; full run only).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.common import report
from flows.openmp import WAIT_KEYS, command_env

WORDS = "a frozen lake on the left"
SETTINGS: dict[str, dict[str, str]] = {
    "sleep": {"OMP_WAIT_POLICY": "PASSIVE"},
    "spin3000": {"GOMP_SPINCOUNT": "3000"},
    "default": {"GOMP_SPINCOUNT": "300000"},  # libgomp's own when neither variable is set
}
STAGGER_S = 15.0


def _bare_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in WAIT_KEYS}


def _start(world: Path, scene: Path, env: dict[str, str]) -> tuple[subprocess.Popen, float]:
    """A copy of `world` at `scene`, extended by the CLI's steps and report in a fresh process."""
    shutil.rmtree(scene, ignore_errors=True)
    shutil.copytree(world, scene)
    cmd = [sys.executable, "-m", "benchmarks.scale", "--child", "extend", str(scene), WORDS]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True), time.perf_counter()


def _wait(run: tuple[subprocess.Popen, float]) -> dict[str, Any]:
    proc, t0 = run
    out = proc.stdout.read() if proc.stdout else ""
    if proc.wait() != 0:
        raise RuntimeError(f"an extension failed (status {proc.returncode})")
    steps = json.loads(out.strip().splitlines()[-1])["steps"]
    return {"seconds": time.perf_counter() - t0, "splats": steps.get("splats", 0.0)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="sleep and spin3000 only, no auto rows")
    p.add_argument("--out", type=Path, default=None, help="folder for the worlds (default: temporary)")
    a = p.parse_args()
    tmp = a.out or Path(tempfile.mkdtemp(prefix="wv-openmp-"))
    world = tmp / "world"
    if not world.exists():
        build = [sys.executable, "-m", "benchmarks.scale", "--child", "generate", str(world), json.dumps([[], None])]
        subprocess.run(build, env=_bare_env() | SETTINGS["sleep"], stdout=subprocess.DEVNULL, check=True)
    rows: list[dict[str, Any]] = []
    head: dict[str, Any] = {"alone_s": {}, "pair_s": {}}
    for name, wait in SETTINGS.items():
        if a.quick and name == "default":
            continue
        env = _bare_env() | wait
        alone = _wait(_start(world, tmp / "alone", env))
        pair = [_start(world, tmp / f"pair{i}", env) for i in range(2)]
        both = [_wait(r) for r in pair]
        slower = max(both, key=lambda r: r["seconds"])
        rows.append({"setting": name, "alone s": alone["seconds"], "alone splats s": alone["splats"]})
        rows[-1] |= {"two at once s": slower["seconds"], "two at once splats s": slower["splats"]}
        head["alone_s"][name] = round(alone["seconds"], 1)
        head["pair_s"][name] = round(slower["seconds"], 1)
    if not a.quick:
        alone = _wait(_start(world, tmp / "alone", command_env(_bare_env(), ["extend"])))
        first = _start(world, tmp / "pair0", command_env(_bare_env(), ["extend"]))
        time.sleep(STAGGER_S)
        second = _start(world, tmp / "pair1", command_env(_bare_env(), ["extend"]))
        both = [_wait(first), _wait(second)]
        slower = max(both, key=lambda r: r["seconds"])
        rows.append({"setting": "auto (CLI)", "alone s": alone["seconds"], "alone splats s": alone["splats"]})
        rows[-1] |= {"two at once s": slower["seconds"], "two at once splats s": slower["splats"]}
        head |= {"auto_alone_s": round(alone["seconds"], 1), "auto_staggered_s": round(slower["seconds"], 1)}
    head["spin_speedup_alone"] = round(head["alone_s"]["sleep"] / head["alone_s"]["spin3000"], 3)
    head["spin_slowdown_pair"] = round(head["pair_s"]["spin3000"] / head["pair_s"]["sleep"], 3)
    report("benchmarks.openmp_wait: one extension (3 -> 4 segments), alone and two at once", rows, head)
    if a.out is None:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
