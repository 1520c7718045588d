"""When is a Dask LocalCluster worth starting for the per-segment steps? The check and the priors of three segments,
in the calling process and on a LocalCluster of two workers, at frame sizes from the tests' tiny video to the preview
preset's.

Per size, one scene (preview preset, procedural, the default prompt: an initial segment with one left and one right
extension, no faults, one check attempt) is made up to `generate_segments`; copies of it are then checked and given
priors (`poses` between them, as the pipeline runs) with `execution.segment_workers` 1 and with 2 and
`cluster_min_pixels: 0` (a cluster whatever the size), alternately, `--rounds` times each. The cluster's seconds
include its start (spawning the workers, each importing the project on its first task) and its shutdown.

Usage: `python -m benchmarks.cluster_start [--quick] [--rounds N]` (`--quick`: the two smaller sizes, one round).
Last line (JSON): per size (`_WxHxF` after the key), `in_process_s` and `cluster_s` (check + priors, median of the
rounds) and `pixels` (the three segments' frames x height x width); `break_even_pixels`: the fewest pixels at
which the cluster was faster (null: never in the sizes tried); `min_pixels_default` (`execution.cluster_min_pixels`,
to compare).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import report

SIZES = ((96, 64, 6), (160, 104, 9), (240, 160, 13), (320, 208, 17))
STEPS = ("check", "priors")


def config(width: int, height: int, frames: int, workers: int) -> Any:
    from wonderverse.config import build_config

    video = {"width": width, "height": height, "frames_per_segment": frames, "options": {"fault_probability": 0.0}}
    execution = {"segment_workers": workers, "cluster_min_pixels": 0}
    overrides = {"scene": {"video": video}, "steps": {"check": {"max_attempts": 1}}, "execution": execution}
    return build_config("a small house decorated for Christmas", preset="preview", overrides=overrides)


def measure(root: Path, size: tuple[int, int, int], rounds: int) -> dict[str, Any]:
    """Seconds of check + priors in-process and on a two-worker cluster (median of `rounds`), for one size."""
    from flows.pipeline import execute
    from tasks.segments import pixels, segment_ids
    from wonderverse.store import SceneStore

    base = root / "x".join(map(str, size))
    execute(base, config(*size, 1), until="generate_segments")
    seconds: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(rounds):
        for workers in (1, 2):
            scene = root / f"run{workers}"
            shutil.rmtree(scene, ignore_errors=True)
            shutil.copytree(base, scene)
            results = execute(scene, config(*size, workers), until="priors")
            seconds[workers].append(sum(r.seconds for r in results if r.step in STEPS and r.status == "ran"))
    store = SceneStore.open(base)
    return {
        "size": "x".join(map(str, size)),
        "pixels": pixels(store, segment_ids(store)),
        "in_process_s": round(float(np.median(seconds[1])), 2),
        "cluster_s": round(float(np.median(seconds[2])), 2),
    }


def main() -> None:
    from wonderverse.config import LOCAL_CLUSTER_MIN_PIXELS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="the two smaller sizes, one round")
    p.add_argument("--rounds", type=int, default=None)
    a = p.parse_args()
    sizes = SIZES[:2] if a.quick else SIZES
    rounds = a.rounds or (1 if a.quick else 2)
    root = Path(tempfile.mkdtemp(prefix="wv-cluster-"))
    try:
        rows = [measure(root, size, rounds) for size in sizes]
    finally:
        shutil.rmtree(root, ignore_errors=True)
    wins = [r["pixels"] for r in rows if r["cluster_s"] < r["in_process_s"]]
    head: dict[str, Any] = {f"{k}_{r['size']}": r[k] for r in rows for k in ("pixels", "in_process_s", "cluster_s")}
    head |= {"break_even_pixels": min(wins) if wins else None, "min_pixels_default": LOCAL_CLUSTER_MIN_PIXELS}
    report("benchmarks.cluster_start: check + priors of three segments, in-process vs a 2-worker cluster", rows, head)


if __name__ == "__main__":
    main()
