"""Procedural rendering, store writes and a cached re-run.

Last-line keys: `render_fps` (procedural frames/s at 480x320), `store_write_mb_s` (frames written to
the store through a staged commit, MB/s), `store_read_mb_s` (the same frames read back whole by another process,
MB/s), `cached_rerun_s` (seconds to re-run a complete scene whose
steps are all cached, after start-up: imports done, Prefect not involved).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import parse_args, report
from flows.pipeline import execute
from wonderverse.config import build_config
from wonderverse.schema import ATTEMPT
from wonderverse.store import SceneStore, cache_key, write_array
from wonderverse.video import initial_pose, make_video_model


def _read_seconds(scene: Path, path: str, expected: np.ndarray) -> float:
    """Seconds to read an array back whole through `SceneStore.array`, as a later run does: in a fresh process,
    so nothing this one verified or cached is reused (the files are in the page cache either way)."""
    import subprocess
    import sys

    code = (
        "import sys, time; from wonderverse.store import SceneStore; s = SceneStore.open(sys.argv[1]); "
        "t = time.perf_counter(); a = s.array(sys.argv[2]); print(time.perf_counter() - t, int(a.sum()))"
    )
    out = subprocess.run([sys.executable, "-c", code, str(scene), path], capture_output=True, text=True, check=True)
    seconds, total = out.stdout.split()
    assert int(total) == int(expected.sum(dtype=np.int64)), "frames read back differ from those written"
    return float(seconds)


def main() -> None:
    args = parse_args(__doc__ or "")
    n = 10 if args.quick else 49
    cfg = build_config(
        "a small house decorated for Christmas",
        preset="standard",
        overrides={"scene": {"video": {"options": {"fault_probability": 0.0}}}},
    )
    model = make_video_model(cfg.scene.video_source)
    from wonderverse.camera import move_path

    path = move_path(initial_pose(model), np.radians(-30), 0.0, 2.0, -1.2, n)
    model.generate("warm-up", path[:2], 0, None)
    t = time.perf_counter()
    video = model.generate("bench", path, 0, None)
    render_s = time.perf_counter() - t
    rows = [{"what": "procedural render 480x320", "frames": n, "seconds": render_s, "rate": n / render_s}]

    with tempfile.TemporaryDirectory() as tmp:
        store = SceneStore.open_or_create(Path(tmp) / "w")
        t = time.perf_counter()
        at = ATTEMPT.at(seg="s000", attempt=0)  # where a segment's frames go, as generate_segments writes them
        with store.staged(at, cache_key("bench", 1, {})) as g:
            write_array(g, at.frames, video.frames)
        write_s = time.perf_counter() - t
        mb = video.frames.nbytes / 1e6
        rows.append({"what": "frames -> store (staged commit)", "frames": n, "seconds": write_s, "rate": mb / write_s})
        read_s = _read_seconds(Path(tmp) / "w", at.frames, video.frames)
        rows.append({"what": "store -> frames (another process)", "frames": n, "seconds": read_s, "rate": mb / read_s})

        scene = Path(tmp) / "scene"
        small = build_config("a small house decorated for Christmas", preset="preview")
        execute(scene, small)
        t = time.perf_counter()
        results = execute(scene, small)
        rerun_s = time.perf_counter() - t
        assert all(r.status == "cached" for r in results), results
        rows.append({"what": "cached re-run (all steps)", "frames": 0, "seconds": rerun_s, "rate": float("nan")})

    report(
        "render",
        rows,
        {
            "render_fps": round(n / render_s, 2),
            "store_write_mb_s": round(mb / write_s, 1),
            "store_read_mb_s": round(mb / read_s, 1),
            "cached_rerun_s": round(rerun_s, 3),
        },
    )


if __name__ == "__main__":
    main()
