"""Videos as browsers and players take them: H.264, yuv420p, and faststart (the moov atom before the media data),
read from the file's own atoms and from ffmpeg's description of the stream (imageio-ffmpeg's bundled binary)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from wonderverse.media import write_mp4


def top_level_atoms(path: Path) -> list[tuple[str, int]]:
    """(type, byte offset) of every top-level ISO-BMFF box: 32-bit size, 4-char type; size 1 = 64-bit size
    follows, 0 = to the end of the file."""
    data = path.read_bytes()
    out, at = [], 0
    while at + 8 <= len(data):
        size, kind = int.from_bytes(data[at : at + 4], "big"), data[at + 4 : at + 8].decode("latin-1")
        if size == 1:
            size = int.from_bytes(data[at + 8 : at + 16], "big")
        elif size == 0:
            size = len(data) - at
        assert size >= 8, f"broken box {kind!r} at {at}"
        out.append((kind, at))
        at += size
    assert at == len(data)
    return out


def ffmpeg_video_stream(path: Path) -> str:
    """ffmpeg's one-line description of the file's video stream (`ffmpeg -i` prints it and exits 1)."""
    import imageio_ffmpeg

    r = subprocess.run(
        [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-i", str(path)], capture_output=True, text=True
    )
    lines = [ln for ln in r.stderr.splitlines() if "Video:" in ln]
    assert len(lines) == 1, r.stderr
    return lines[0]


def assert_web_video(path: Path) -> None:
    """H.264 in yuv420p with the moov atom before mdat."""
    atoms = dict((kind, at) for kind, at in reversed(top_level_atoms(path)))  # first occurrence of each
    assert atoms["ftyp"] == 0 and atoms["moov"] < atoms["mdat"], top_level_atoms(path)
    stream = ffmpeg_video_stream(path)
    assert "Video: h264" in stream and "yuv420p" in stream, stream


def test_write_mp4_is_h264_yuv420p_with_faststart(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (12, 31, 45, 3), dtype=np.uint8)  # odd sizes: padded to even for 4:2:0
    path = write_mp4(frames, tmp_path / "v.mp4", fps=12.0)
    assert_web_video(path)
    back = iio.imread(path)
    assert back.shape == (12, 32, 46, 3)
    # a smooth picture survives the encoding (random noise does not, at any sane bitrate)
    smooth = np.broadcast_to(np.linspace(0, 255, 46, dtype=np.uint8)[None, None, :, None], (6, 32, 46, 3)).copy()
    again = iio.imread(write_mp4(smooth, tmp_path / "s.mp4", fps=6.0))
    assert np.abs(again.astype(int) - smooth).mean() < 4


def test_the_atom_reader_sees_a_file_without_faststart(tmp_path: Path) -> None:
    # the check must be able to fail: ffmpeg's default mp4 puts moov after mdat
    import imageio.v2 as imageio

    path = tmp_path / "late.mp4"
    with imageio.get_writer(path, fps=5, codec="libx264", macro_block_size=1) as wr:
        for _ in range(5):
            wr.append_data(np.zeros((16, 16, 3), np.uint8))
    kinds = [k for k, _ in top_level_atoms(path)]
    assert kinds.index("mdat") < kinds.index("moov")
