"""Fit the project's NIQE pristine model from real camera images (the project's real-data folder, `--data`).

As estimatemodelparam.m: per image, 96x96 blocks whose mean local sigma is >= 0.75 x the image's sharpest block
are kept; the mean and covariance of their 36 features (rows with NaN dropped) form the model. Writes
wonderverse/data/niqe_pristine.npz (mean (36,), cov (36,36) float64 and provenance metadata).

Sources (all real captures; see each folder's SOURCE.md): instant_ngp_fox/images (50 hand-held photos, 1080x1920),
viewcrafter_re10k_bedroom/images (25 frames of a real indoor clip, 1280x720) and cameractrl_re10k/reference_videos
(7 real RealEstate10K clips, 384x256, every 5th frame). The AI-generated clips (cogvideox_samples, cameractrl
generated_gifs) are not used.

Usage: python scripts/fit_niqe.py [--data DIR] [--out wonderverse/data/niqe_pristine.npz]

`--data` is the folder holding those sources; by default `../shared/data` beside the repository, the folder the
tests read real data from.
"""

from __future__ import annotations

import argparse
import datetime
import json
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from wonderverse.quality.niqe_metric import SHARPNESS_FRACTION, image_features

VIDEO_FRAME_STEP = 5
ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data"


def real_images(data: Path) -> list[tuple[str, np.ndarray]]:
    """(source name, (H,W,3) uint8) of every real-camera image used for the pristine model."""
    out: list[tuple[str, np.ndarray]] = []
    for folder in ("instant_ngp_fox/images", "viewcrafter_re10k_bedroom/images"):
        for p in sorted((data / folder).glob("*")):
            if p.suffix.lower() in {".jpg", ".jpeg", ".png"}:
                out.append((f"{folder}/{p.name}", np.asarray(iio.imread(p))[..., :3]))
    for p in sorted((data / "cameractrl_re10k/reference_videos").glob("*.mp4")):
        frames = iio.imread(p)
        for i in range(0, len(frames), VIDEO_FRAME_STEP):
            out.append((f"cameractrl_re10k/reference_videos/{p.name}#{i}", frames[i][..., :3]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data", type=Path, default=DEFAULT_DATA, help="folder of the real sources (default: ../shared/data)"
    )
    ap.add_argument("--out", type=Path, default=ROOT / "wonderverse/data/niqe_pristine.npz")
    args = ap.parse_args()
    t0 = time.perf_counter()
    images = real_images(args.data)
    if not images:
        raise SystemExit(f"no real images found under {args.data}")
    kept, per_source = [], {}
    for name, img in images:
        feats, sharpness = image_features(img)
        sel = feats[sharpness >= SHARPNESS_FRACTION * sharpness.max()]
        kept.append(sel)
        src = name.split("/")[0]
        per_source[src] = per_source.get(src, 0) + len(sel)
    rows = np.concatenate(kept)
    rows = rows[np.isfinite(rows).all(1)]
    meta = {
        "sources": sorted(per_source),
        "blocks_per_source": per_source,
        "n_images": len(images),
        "n_blocks": len(rows),
        "sharpness_fraction": SHARPNESS_FRACTION,
        "video_frame_step": VIDEO_FRAME_STEP,
        "date": datetime.date.today().isoformat(),
        "script": "scripts/fit_niqe.py",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        args.out, mean=rows.mean(0), cov=np.cov(rows, rowvar=False), metadata=np.array(json.dumps(meta))
    )
    print(json.dumps(meta, indent=1), f"\nwrote {args.out} in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
