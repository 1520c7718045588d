"""How long a refused command takes, under each engine: `python -m benchmarks.refusals [--runs N]`.

A refusal is what a mistyped command costs a user, and what every case of tests/test_adversarial.py costs the suite:
each call below is refused (exit 2, one `error:` line) and timed from the start of `wonderverse` (the supervising
parent included) to its exit. Prints one row per refusal and engine: median and worst of N runs, in seconds.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _setup(d: Path) -> dict[str, list[str]]:
    """The refused calls, by name, over files made in `d`."""
    from wonderverse.store import LOCK_NAME, SceneStore

    foreign = d / "photos"
    foreign.mkdir()
    (foreign / LOCK_NAME).write_text("the user's own file")
    (d / "dup.yaml").write_text("scene:\n  prompt: a\n  prompt: b\n")
    os.mkfifo(d / "fifo.yaml")
    SceneStore.open_or_create(d / "scene", spec={"prompt": "a house"})
    specs = d / "specs"
    specs.mkdir()
    (specs / "..yaml").write_text("scene: {prompt: a house}\n")
    out = ["--out", str(d / "new")]
    return {
        "empty prompt": ["generate", "", *out],
        "invisible prompt": ["generate", "\u200b\u200c", *out],
        "duplicate key in --config": ["generate", "--config", str(d / "dup.yaml"), *out],
        "--config a FIFO": ["generate", "--config", str(d / "fifo.yaml"), *out],
        "--out a foreign folder": ["generate", "a house", "--preset", "preview", "--out", str(foreign)],
        "URL with a password": ["generate", "a house", "--dask", "tcp://u:pw@127.0.0.1:8786", *out],
        "extend: empty words": ["extend", str(d / "scene"), ""],
        "extend: no completed run": ["extend", str(d / "scene"), "go left"],
        "reconstruct /dev/zero": ["reconstruct", "/dev/zero", *out],
        "batch: spec named ..yaml": ["batch", str(specs), "--out", str(d / "root")],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        calls = _setup(Path(tmp))
        env = {**os.environ, "PREFECT_HOME": str(Path(tmp) / "prefect"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
        print(f"{'refusal':32} {'engine':8} {'median s':>9} {'worst s':>8}")
        for name, call in calls.items():
            engines = ("local", "prefect") if call[0] in ("generate", "reconstruct", "extend") else ("-",)
            for engine in engines:
                argv = [sys.executable, "-m", "flows", *call] + (["--engine", engine] if engine != "-" else [])
                times = []
                for _ in range(args.runs):
                    t0 = time.perf_counter()
                    r = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=ROOT)
                    times.append(time.perf_counter() - t0)
                    if r.returncode != 2 or not r.stderr.startswith("error: "):
                        raise SystemExit(f"{name} ({engine}) was not refused: {r.returncode} {r.stderr[-500:]}")
                print(f"{name:32} {engine:8} {statistics.median(times):9.2f} {max(times):8.2f}")
        if (Path(tmp) / "prefect" / "prefect.db").exists():
            raise SystemExit("Prefect started for a refusal")


if __name__ == "__main__":
    main()
