"""Once-on-CUDA check of the diffusers video backend with tiny random pipelines.

Builds tiny CogVideoX (and Wan and Wan VACE, when ftfy is installed) pipelines (tests/tiny_diffusers.py), saves
them, loads them through `DiffusionVideo`'s real loading code and runs T2V then I2V (from the T2V's last frame) in
float16, bfloat16 and bfloat16 with model CPU offload. The guided family (wan_vace) renders T2V and I2V with its one
VACE pipeline, then a guided segment: the T2V frames with their right half unknown, from the T2V's last frame; it
reports whether other guide frames change the output and whether the same seed repeats it.
Prints a table; the last line is one JSON object. Exit code 1 when any run failed.

    python scripts/gpu_video_diffusion.py               # on the GPU machine
    python scripts/gpu_video_diffusion.py --device cpu  # the same on CPU (float32, no offload)

Imports: numpy, torch, diffusers, transformers, tokenizers, pydantic (no open3d/zarr/pycolmap/prefect).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from tiny_diffusers import FAMILY_MODES, save_tiny_pipelines  # noqa: E402

from wonderverse.errors import WonderError  # noqa: E402
from wonderverse.video.base import Guide  # noqa: E402
from wonderverse.video.diffusion import DiffusionParams, DiffusionVideo  # noqa: E402

PROMPT = "aerial shot, soft lighting, realistic, high-quality, displaying a mountain village by a lake."


def right_half_unknown(frames: np.ndarray) -> Guide:
    """A guide that knows the left half of `frames` (T,H,W,3) uint8 and leaves the right half to the model."""
    mask = np.zeros(frames.shape[:3], bool)
    mask[:, :, frames.shape[2] // 2 :] = True
    known = np.where(mask[..., None], 0, frames).astype(np.uint8)
    return Guide(frames=known, mask=mask, depth=np.where(mask, np.inf, 1.0).astype(np.float32), source="test")


def run_one(family: str, folders: dict[str, Path], dtype: str, device: str, offload: str, args: Any) -> dict[str, Any]:
    """T2V then I2V (and a guided segment for a guided family) through DiffusionVideo; shapes, seconds, finiteness
    and determinism of one setting."""
    params = DiffusionParams(
        family=family,
        **{f"{mode}_model": str(folder) for mode, folder in folders.items()},
        dtype=dtype,
        device=device,
        offload=offload,
        steps=args.steps,
    )
    row: dict[str, Any] = {"family": family, "dtype": dtype, "offload": offload, "device": device}
    path = np.tile(np.eye(4), (args.frames, 1, 1))
    try:
        import torch

        if device == "cuda":
            torch.cuda.reset_peak_memory_stats()
        model = DiffusionVideo(args.width, args.height, args.frames, 60.0, params)
        t0 = time.perf_counter()
        pipes = [model.pipeline(mode) for mode in folders]
        row["load_s"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        t2v = model.generate(PROMPT, path, 7, None)
        row["t2v_s"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        i2v = model.generate(PROMPT + " around left,", path, 8, t2v.frames[-1])
        row["i2v_s"] = round(time.perf_counter() - t0, 3)
        again = model.generate(PROMPT, path, 7, None)
        row.update(
            t2v_shape=list(t2v.frames.shape),
            i2v_shape=list(i2v.frames.shape),
            frames_dtype=str(t2v.frames.dtype),
            pipeline_dtype=str(pipes[0].transformer.dtype).removeprefix("torch."),
            finite=True,  # DiffusionVideo raises on non-finite output
            same_seed_identical=bool(np.array_equal(t2v.frames, again.frames)),
            t2v_mean=round(float(t2v.frames.mean()), 2),
            takes_guide=model.takes_guide,
        )
        ok = t2v.frames.shape == (args.frames, args.height, args.width, 3) and i2v.frames.shape == t2v.frames.shape
        if model.takes_guide:
            guide = right_half_unknown(t2v.frames)
            t0 = time.perf_counter()
            guided = model.generate(PROMPT + " around left,", path, 9, t2v.frames[-1], guide)
            row["guided_s"] = round(time.perf_counter() - t0, 3)
            other = right_half_unknown(255 - t2v.frames)
            changed = model.generate(PROMPT + " around left,", path, 9, t2v.frames[-1], other)
            repeat = model.generate(PROMPT + " around left,", path, 9, t2v.frames[-1], guide)
            row.update(
                guided_shape=list(guided.frames.shape),
                guide_changes_output=bool(not np.array_equal(guided.frames, changed.frames)),
                guided_same_seed_identical=bool(np.array_equal(guided.frames, repeat.frames)),
            )
            ok = ok and guided.frames.shape == t2v.frames.shape and row["guide_changes_output"]
        if device == "cuda":  # the process's peak: pipelines of earlier runs stay loaded (the backend's cache)
            row["peak_mem_mb"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
        row["ok"] = ok
    except WonderError as e:
        row.update(ok=False, finite=False if "non-finite" in str(e) else None, error=str(e))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=["cuda", "cpu"], default="cuda")
    ap.add_argument("--tiny-dir", type=Path, help="reuse (or write) the tiny pipelines here; default: a temp dir")
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--steps", type=int, default=2)
    args = ap.parse_args(argv)

    import torch

    # the Wan pipelines (VACE included) call ftfy unguarded
    families = ("cogvideox", "wan", "wan_vace") if importlib.util.find_spec("ftfy") else ("cogvideox",)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.tiny_dir or Path(tmp)
        folders = {f: {m: root / f"{f}-{m}" for m in FAMILY_MODES[f]} for f in families}
        missing = tuple(f for f in families if not all((d / "model_index.json").is_file() for d in folders[f].values()))
        if missing:
            folders.update(save_tiny_pipelines(root, missing))
        settings = (
            [("float16", "none"), ("bfloat16", "none"), ("bfloat16", "model")]
            if args.device == "cuda"
            else [("float32", "none")]
        )
        rows = [run_one(f, folders[f], d, args.device, o, args) for f in families for d, o in settings]

    cols = ["family", "dtype", "offload", "load_s", "t2v_s", "i2v_s", "guided_s", "t2v_shape", "finite"]
    cols += ["same_seed_identical", "guided_same_seed_identical", "guide_changes_output", "peak_mem_mb", "ok"]
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r.get(c, "-")) for c in cols) + (f"  ERROR: {r['error']}" if "error" in r else ""))
    summary = {
        "ok": all(r["ok"] for r in rows),
        "torch": torch.__version__,
        "cuda": torch.cuda.is_available(),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "skipped": [] if "wan" in families else ["wan, wan_vace (ftfy not installed)"],
        "runs": rows,
    }
    print(json.dumps(summary))
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
