"""What operating the pipeline costs: Dask fan-out, Prefect overhead, cached re-runs, extensions.

- Dask: one 6-segment procedural scene is generated once and copied; the `check` step (per-segment SfM)
  then runs on each copy serially (one worker, in-process) and on a 2-worker LocalCluster (cluster start-up
  included).
- Prefect (ephemeral API, no server): a fresh `plan`-only run and a fully cached run, each with the Prefect
  engine and with plain calls; per-flow overhead = cached(prefect) - cached(local); per-task overhead =
  fresh(prefect) - fresh(local) - per-flow overhead. Prefect's first start in a process (database
  migration) is excluded by a warm-up run.
- Extension: `extend` adding one segment to a complete 3-segment scene, against generating the resulting
  4-segment scene from scratch (what a user without `extend` would have to run), with the seconds of each
  step in both. The 3-segment scene's own time is reported too.

Last-line keys: `dask_speedup` (serial seconds / 2-worker seconds of the check step), `prefect_task_overhead_s`,
`prefect_flow_overhead_s`, `cached_rerun_s` (all steps cached, local engine), `extend_cost_ratio` (extend
seconds / seconds of the extended scene from scratch).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

from benchmarks.common import parse_args, report
from flows.extend import extend, extended_config
from flows.pipeline import execute, run_pipeline
from tasks import StepResult
from wonderverse.config import RunConfig, build_config


def _config(width: int, height: int, frames: int, rounds: int, directions: list[str], iterations: int) -> RunConfig:
    return build_config(
        "a small house decorated for Christmas",
        preset="preview",
        overrides={
            "scene": {
                "video": {"width": width, "height": height, "frames_per_segment": frames},
                "extensions": {"rounds": rounds, "directions": directions},
            },
            "steps": {
                "check": {"workers": 1, "sfm": {"num_threads": 1}},
                "priors": {"workers": 1},
                "splats": {"renderer": "torch", "train": {"iterations": iterations}},
                "outputs": {"video_frames": 24},
            },
        },
    )


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def dask_rows(tmp: Path, cfg: RunConfig) -> tuple[list[dict], float]:
    base = tmp / "dask_base"
    execute(base, cfg, until="generate_segments")
    seconds = {}
    for workers in (1, 2):
        d = tmp / f"dask_{workers}"
        shutil.copytree(base, d)
        steps = cfg.steps.model_copy(update={"check": cfg.steps.check.model_copy(update={"workers": workers})})
        c = cfg.model_copy(update={"steps": steps})
        seconds[workers] = _timed(lambda d=d, c=c: execute(d, c, until="check"))
    rows = [{"what": f"check step, 6 segments, {w} worker(s)", "seconds": s} for w, s in seconds.items()]
    return rows, seconds[1] / seconds[2]


def prefect_rows(tmp: Path, cfg: RunConfig, reps: int) -> tuple[list[dict], float, float]:
    run_pipeline(tmp / "warm", cfg, until="plan", engine="prefect")  # Prefect's first start: not overhead
    t: dict[tuple[str, str], float] = {}
    for engine in ("local", "prefect"):
        fresh, cached = [], []
        for r in range(reps):
            d = tmp / f"prefect_{engine}_{r}"
            fresh.append(_timed(lambda d=d, e=engine: run_pipeline(d, cfg, until="plan", engine=e)))
            cached.append(_timed(lambda d=d, e=engine: run_pipeline(d, cfg, until="plan", engine=e)))
        t[(engine, "fresh")], t[(engine, "cached")] = min(fresh), min(cached)
    flow = t[("prefect", "cached")] - t[("local", "cached")]
    task = t[("prefect", "fresh")] - t[("local", "fresh")] - flow
    rows = [{"what": f"plan only, {kind}, {engine}", "seconds": s} for (engine, kind), s in t.items()]
    return rows, task, flow


def extend_rows(tmp: Path, cfg: RunConfig) -> tuple[list[dict], float, float]:
    words = "a frozen lake beyond the trees on the left"
    d = tmp / "extend"
    before = _timed(lambda: execute(d, cfg))
    cached = _timed(lambda: execute(d, cfg))
    steps: dict[str, list[StepResult]] = {}
    added = _timed(lambda: steps.update(extend=extend(d, words, engine="local")))
    whole = _timed(lambda: steps.update(whole=execute(tmp / "whole", extended_config(cfg, words))))
    rows = [
        {"what": "3-segment scene from scratch (all steps)", "seconds": before},
        {"what": "same, all steps cached (local engine)", "seconds": cached},
        {"what": "extend: one more segment, everything updated", "seconds": added},
        {"what": "the extended 4-segment scene from scratch", "seconds": whole},
    ]
    # where the time goes: each step of the extension beside the same step from scratch
    scratch = {r.step: r.seconds for r in steps["whole"]}
    rows += [
        {"what": f"  step {r.step}: extend / from scratch", "seconds": f"{r.seconds:.1f} / {scratch[r.step]:.1f}"}
        for r in steps["extend"]
    ]
    return rows, added / whole, cached


def main() -> None:
    args = parse_args(__doc__ or "")
    size = (128, 96, 10) if args.quick else (240, 160, 17)
    iterations = 100 if args.quick else 300
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        rows, speedup = dask_rows(tmp, _config(*size, 5, ["right"], iterations))
        prows, task, flow = prefect_rows(tmp, _config(*size, 1, ["left", "right"], iterations), 2 if args.quick else 5)
        erows, ratio, cached = extend_rows(tmp, _config(*size, 1, ["left", "right"], iterations))
    headline = {
        "dask_speedup": round(speedup, 2),
        "prefect_task_overhead_s": round(task, 3),
        "prefect_flow_overhead_s": round(flow, 3),
        "cached_rerun_s": round(cached, 3),
        "extend_cost_ratio": round(ratio, 3),
    }
    report("flows: Dask, Prefect, cached re-runs, extension", rows + prows + erows, headline)


if __name__ == "__main__":
    main()
