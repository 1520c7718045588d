"""What operating the pipeline costs: Dask fan-out, Prefect overhead, cached re-runs, extensions.

- Dask: one 6-segment procedural scene is generated once and copied; the `check` step (per-segment SfM)
  then runs on each copy serially (one worker, in-process) and on a 2-worker LocalCluster (cluster start-up
  included).
- Prefect: a fresh `plan`-only run and a fully cached run, each with the Prefect engine and with plain
  calls; per-flow overhead = cached(prefect) - cached(local); per-task overhead = fresh(prefect) -
  fresh(local) - per-flow overhead. Measured twice: on Prefect's ephemeral API (no server, what local runs
  use) and against a `prefect server start` on 127.0.0.1 started by the benchmark (its own home, so never
  the user's database). Prefect's first start in a process and the server's first flow (database
  migration, registration) are excluded by warm-up runs.
- Extension: `extend` adding one segment to a complete 3-segment scene, against generating the resulting
  4-segment scene from scratch (what a user without `extend` would have to run), with the seconds of each
  step in both. The 3-segment scene's own time is reported too, and for each scene the global poses' error
  against the procedural world's true path and the held-out PSNR: a from-scratch run whose SfM went wrong
  while passing its gates is also a faster one (measured), so the ratio is read with them.

Last-line keys: `dask_speedup` (serial seconds / 2-worker seconds of the check step), `prefect_task_overhead_s`,
`prefect_flow_overhead_s` (ephemeral API), `prefect_task_overhead_server_s`, `prefect_flow_overhead_server_s`
(with a server), `cached_rerun_s` (all steps cached, local engine), `extend_cost_ratio` (extend seconds /
seconds of the extended scene from scratch), `extend_pose_ate_frac` and `whole_pose_ate_frac` (ATE of the
global poses as a share of the true path's length: extended scene, same scene from scratch).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np

from benchmarks.common import parse_args, report
from flows.extend import extend, extended_config
from flows.pipeline import execute, run_pipeline
from tasks import StepResult
from tasks.segments import attempt_path
from wonderverse.config import RunConfig, build_config
from wonderverse.metrics import ate
from wonderverse.schema import SFM, SPLATS
from wonderverse.store import SceneStore


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
                "check": {"sfm": {"num_threads": 1}},
                "splats": {"train": {"iterations": iterations}},
                "outputs": {"video_frames": 24},
            },
            "execution": {"segment_workers": 1, "renderer": "torch"},
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
        on = {"segment_workers": workers, "cluster_min_pixels": 0}  # the cluster however small the segments
        c = cfg.model_copy(update={"execution": cfg.execution.model_copy(update=on)})
        seconds[workers] = _timed(lambda d=d, c=c: execute(d, c, until="check"))
    rows = [{"what": f"check step, 6 segments, {w} worker(s)", "seconds": s} for w, s in seconds.items()]
    return rows, seconds[1] / seconds[2]


@contextmanager
def prefect_server(tmp: Path, start_s: float = 300) -> Iterator[str]:
    """`prefect server start` on a free 127.0.0.1 port with its own home under `tmp`; yields its API URL."""
    import httpx

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    api = f"http://127.0.0.1:{port}/api"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env |= {
        "PREFECT_HOME": str(tmp / "server-home"),
        "PREFECT_API_URL": api,
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    }
    with open(tmp / "server.log", "w") as log:
        cmd = [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)]
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + start_s
            while True:
                try:
                    if httpx.get(f"{api}/health", timeout=2).status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the Prefect server did not start (see {tmp / 'server.log'})")
                time.sleep(1)
            yield api
        finally:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(30)


def prefect_rows(tmp: Path, cfg: RunConfig, reps: int, api: str | None = None) -> tuple[list[dict], float, float]:
    """Per-task and per-flow seconds Prefect adds over plain calls, on the ephemeral API or at the server `api`."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    where = "ephemeral API" if api is None else "server"
    with temporary_settings(updates={PREFECT_API_URL: api}) if api else nullcontext():
        run_pipeline(tmp / f"warm_{where}", cfg, until="plan", engine="prefect")  # first start: not overhead
        t: dict[tuple[str, str], float] = {}
        for engine in ("local", "prefect"):
            fresh, cached = [], []
            for r in range(reps):
                d = tmp / f"prefect_{where}_{engine}_{r}"
                fresh.append(_timed(lambda d=d, e=engine: run_pipeline(d, cfg, until="plan", engine=e)))
                cached.append(_timed(lambda d=d, e=engine: run_pipeline(d, cfg, until="plan", engine=e)))
            t[(engine, "fresh")], t[(engine, "cached")] = min(fresh), min(cached)
    flow = t[("prefect", "cached")] - t[("local", "cached")]
    task = t[("prefect", "fresh")] - t[("local", "fresh")] - flow
    rows = [
        {"what": f"plan only, {kind}, {engine}" + (f" ({where})" if engine == "prefect" else ""), "seconds": s}
        for (engine, kind), s in t.items()
    ]
    return rows, task, flow


def pose_error(scene: Path) -> float:
    """ATE of a scene's global poses against the procedural world's true path, as a share of its length."""
    store = SceneStore.open(scene)
    segs = store.meta(SFM.path).segments
    true = {seg: store.array(attempt_path(store, seg).gt.poses) for seg in segs}
    gt = np.stack([true[segs[a]][i] for a, i in store.array(SFM.frame_index)])
    return float(ate(store.array(SFM.poses), gt)["rmse_frac"])


def _quality(scene: Path, pose_ate: float) -> str:
    psnr = SceneStore.open(scene).meta(SPLATS.path).metrics.test_psnr
    return f"{100 * pose_ate:.2f} % / {psnr:.2f} dB"


def extend_rows(tmp: Path, cfg: RunConfig) -> tuple[list[dict], float, float, dict[str, float]]:
    words = "a frozen lake beyond the trees on the left"
    d = tmp / "extend"
    before = _timed(lambda: execute(d, cfg))
    before_quality = _quality(d, pose_error(d))
    cached = _timed(lambda: execute(d, cfg))
    steps: dict[str, list[StepResult]] = {}
    added = _timed(lambda: steps.update(extend=extend(d, words, engine="local")))
    whole = _timed(lambda: steps.update(whole=execute(tmp / "whole", extended_config(cfg, words))))
    errors = {"extend_pose_ate_frac": pose_error(d), "whole_pose_ate_frac": pose_error(tmp / "whole")}
    rows = [
        {"what": "3-segment scene from scratch (all steps)", "seconds": before},
        {"what": "same, all steps cached (local engine)", "seconds": cached},
        {"what": "extend: one more segment, everything updated", "seconds": added},
        {"what": "the extended 4-segment scene from scratch", "seconds": whole},
        {"what": "  pose ATE (% of path) / held-out PSNR: 3 segments", "seconds": before_quality},
        {"what": "  ... extended", "seconds": _quality(d, errors["extend_pose_ate_frac"])},
        {
            "what": "  ... the extended scene from scratch",
            "seconds": _quality(tmp / "whole", errors["whole_pose_ate_frac"]),
        },
    ]
    # where the time goes: each step of the extension beside the same step from scratch
    scratch = {r.step: r.seconds for r in steps["whole"]}
    rows += [
        {"what": f"  step {r.step}: extend / from scratch", "seconds": f"{r.seconds:.1f} / {scratch[r.step]:.1f}"}
        for r in steps["extend"]
    ]
    return rows, added / whole, cached, errors


def main() -> None:
    args = parse_args(__doc__ or "")
    size = (128, 96, 10) if args.quick else (240, 160, 17)
    iterations = 100 if args.quick else 300
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        rows, speedup = dask_rows(tmp, _config(*size, 5, ["right"], iterations))
        pcfg, reps = _config(*size, 1, ["left", "right"], iterations), 2 if args.quick else 5
        prows, task, flow = prefect_rows(tmp, pcfg, reps)
        with prefect_server(tmp) as api:
            srows, task_server, flow_server = prefect_rows(tmp, pcfg, reps, api)
        erows, ratio, cached, errors = extend_rows(tmp, _config(*size, 1, ["left", "right"], iterations))
    headline = {
        "dask_speedup": round(speedup, 2),
        "prefect_task_overhead_s": round(task, 3),
        "prefect_flow_overhead_s": round(flow, 3),
        "prefect_task_overhead_server_s": round(task_server, 3),
        "prefect_flow_overhead_server_s": round(flow_server, 3),
        "cached_rerun_s": round(cached, 3),
        "extend_cost_ratio": round(ratio, 3),
    } | {k: round(v, 5) for k, v in errors.items()}
    report("flows: Dask, Prefect, cached re-runs, extension", rows + prows + srows + erows, headline)


if __name__ == "__main__":
    main()
