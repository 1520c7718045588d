"""Writing frames for people to look at: mp4 videos and contact sheets."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw


def write_mp4(frames: np.ndarray, path: Path, fps: float) -> Path:
    """H.264 mp4 of (N,H,W,3) uint8 frames (ffmpeg from imageio-ffmpeg), as browsers and players take it:
    yuv420p (4:2:0, which H.264's common profiles and every browser decode; sizes padded to even for it) and
    `+faststart` (the moov atom before the media data, so a page can start playing before the whole file
    has arrived)."""
    import imageio.v2 as imageio

    if frames.ndim != 4 or frames.shape[0] == 0:
        raise ValueError(f"need a non-empty (N,H,W,3) frame stack, got shape {frames.shape}")
    h, w = frames.shape[1:3]
    pad = ((0, 0), (0, h % 2), (0, w % 2), (0, 0))
    frames = np.pad(frames, pad, mode="edge") if h % 2 or w % 2 else frames
    path = Path(path)
    with imageio.get_writer(
        path,
        fps=fps,
        codec="libx264",
        quality=8,
        macro_block_size=1,
        pixelformat="yuv420p",
        output_params=["-movflags", "+faststart"],
    ) as wr:
        for f in frames:
            wr.append_data(f)
    return path


def contact_sheet(frames: np.ndarray, labels: list[str], cols: int = 8, thumb_width: int = 160) -> bytes:
    """PNG bytes of a grid of thumbnails, each captioned with its label."""
    n = len(frames)
    if n == 0:
        raise ValueError("contact sheet of zero frames")
    h, w = frames.shape[1:3]
    tw, th = thumb_width, max(1, round(thumb_width * h / w))
    cols = min(cols, n)
    rows = -(-n // cols)
    cap = 14
    sheet = Image.new("RGB", (cols * tw, rows * (th + cap)), (24, 24, 24))
    draw = ImageDraw.Draw(sheet)
    for i, (f, label) in enumerate(zip(frames, labels, strict=True)):
        x, y = (i % cols) * tw, (i // cols) * (th + cap)
        sheet.paste(Image.fromarray(f).resize((tw, th), Image.BILINEAR), (x, y))
        draw.text((x + 2, y + th + 1), label, fill=(230, 230, 230))
    buf = io.BytesIO()
    sheet.save(buf, format="PNG")
    return buf.getvalue()
