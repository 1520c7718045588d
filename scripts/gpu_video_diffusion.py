"""Once-on-CUDA check of the diffusers video backend with tiny random pipelines.

Builds tiny CogVideoX (and Wan, when ftfy is installed) text-to-video and image-to-video pipelines
(tests/tiny_diffusers.py), saves them, loads them through `DiffusionVideo`'s real loading code and runs
T2V then I2V (from the T2V's last frame) in float16, bfloat16 and bfloat16 with model CPU offload.
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

from tiny_diffusers import save_tiny_pipelines  # noqa: E402

from wonderverse.errors import WonderError  # noqa: E402
from wonderverse.video.diffusion import DiffusionParams, DiffusionVideo  # noqa: E402

PROMPT = "aerial shot, soft lighting, realistic, high-quality, displaying a mountain village by a lake."


def run_one(family: str, folders: dict[str, Path], dtype: str, device: str, offload: str, args: Any) -> dict[str, Any]:
    """T2V then I2V through DiffusionVideo; shapes, seconds, finiteness and determinism of one setting."""
    params = DiffusionParams(
        family=family,
        t2v_model=str(folders["t2v"]),
        i2v_model=str(folders["i2v"]),
        dtype=dtype,
        device=device,
        offload=offload,
        steps=args.steps,
    )
    row: dict[str, Any] = {"family": family, "dtype": dtype, "offload": offload, "device": device}
    path = np.tile(np.eye(4), (args.frames, 1, 1))
    try:
        model = DiffusionVideo(args.width, args.height, args.frames, 60.0, params)
        t0 = time.perf_counter()
        model.pipeline("t2v"), model.pipeline("i2v")
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
            pipeline_dtype=str(model.pipeline("t2v").transformer.dtype).removeprefix("torch."),
            finite=True,  # DiffusionVideo raises on non-finite output
            same_seed_identical=bool(np.array_equal(t2v.frames, again.frames)),
            t2v_mean=round(float(t2v.frames.mean()), 2),
            ok=t2v.frames.shape == (args.frames, args.height, args.width, 3) and i2v.frames.shape == t2v.frames.shape,
        )
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

    families = ("cogvideox", "wan") if importlib.util.find_spec("ftfy") else ("cogvideox",)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.tiny_dir or Path(tmp)
        have = all((root / f"{f}-{m}" / "model_index.json").is_file() for f in families for m in ("t2v", "i2v"))
        folders = (
            {f: {m: root / f"{f}-{m}" for m in ("t2v", "i2v")} for f in families}
            if have
            else save_tiny_pipelines(root, families)
        )
        settings = (
            [("float16", "none"), ("bfloat16", "none"), ("bfloat16", "model")]
            if args.device == "cuda"
            else [("float32", "none")]
        )
        rows = [run_one(f, folders[f], d, args.device, o, args) for f in families for d, o in settings]

    cols = ["family", "dtype", "offload", "load_s", "t2v_s", "i2v_s", "t2v_shape", "finite", "same_seed_identical"]
    cols.append("ok")
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r.get(c, "-")) for c in cols) + (f"  ERROR: {r['error']}" if "error" in r else ""))
    summary = {
        "ok": all(r["ok"] for r in rows),
        "torch": torch.__version__,
        "cuda": torch.cuda.is_available(),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "skipped": [] if "wan" in families else ["wan (ftfy not installed)"],
        "runs": rows,
    }
    print(json.dumps(summary))
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
