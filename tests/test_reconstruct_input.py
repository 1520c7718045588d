"""Awkward and bad input to `wonderverse reconstruct`, as users bring it (issue 39): a phone set whose photos are not
all one shape reconstructs, its landscape shots turned to the portrait shape and named; clips of two shapes, a folder of
one image, a video cut short and a clip of 10 000 frames each end in one `error:` line (exit 2, no scene folder) or
a stated line, and nothing is written outside the scene folder.

Ground truth: the fox capture of ../shared/data (portrait photos; the test turns two of them landscape) and clips the
test writes itself (their frame counts and shapes)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import imageio.v2 as imageio
import imageio_ffmpeg
import numpy as np
import pytest
from conftest import run_cli, tree_digest
from PIL import Image

from wonderverse.store import SceneStore

pytestmark = pytest.mark.e2e  # the CLI in a subprocess


def error_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("error:")]


def test_a_phone_set_with_two_landscape_shots_among_portrait_ones_reconstructs(data_dir: Path, tmp_path: Path):
    """16 photos of the fox capture (portrait), two of them turned landscape: the two are turned back a quarter
    (upside down against the originals) and all 16 are posed with one camera of the portrait size; the run's clip
    line names the two turned."""
    src = sorted((data_dir / "instant_ngp_fox" / "images").glob("*.jpg"))[:16]
    if len(src) < 16:
        pytest.skip("the fox capture has fewer than 16 images here")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    turned = {src[4].stem, src[9].stem}
    for p in src:
        img = Image.open(p).convert("RGB").resize((180, 320))
        (img.rotate(90, expand=True) if p.stem in turned else img).save(mixed / f"{p.stem}.png")
    out = tmp_path / "scene"
    r = run_cli("reconstruct", str(mixed), "--out", str(out), "--until", "poses", "--engine", "local", timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    line = next(ln for ln in r.stderr.splitlines() if ln.startswith("wonderverse: clip mixed/:"))
    names = ", ".join(f"{s}.png" for s in sorted(turned))
    assert f"2 of 16 images turned a quarter counter-clockwise to the 180x320 of the others ({names})" in line
    assert "left out" not in line, line
    info = json.loads(run_cli("inspect", str(out), "--json").stdout)
    assert (info["clips"][0]["frames"], info["clips"][0]["size"]) == (16, [180, 320])
    assert {s["name"]: s["status"] for s in info["steps"]}["poses"] == "complete"
    store = SceneStore.open(out)
    poses = store.array("sfm/poses")
    assert poses.shape == (16, 4, 4)  # one camera path over every photo
    assert np.isfinite(poses).all(), "the turned photos register like the others"
    assert store.array("sfm/K")[0, 2] == pytest.approx(90.0)  # one camera of their size: cx = W / 2


def _write_video(path: Path, n: int, size: tuple[int, int], fps: float, noise: bool = False) -> Path:
    """n frames; `noise`: random pixels, so that the frames, not the file's index, make up most of its bytes."""
    w, h = size
    rng = np.random.default_rng(0)
    with imageio.get_writer(path, fps=fps, codec="libx264", quality=5, macro_block_size=1) as wr:
        for i in range(n):
            f = rng.integers(0, 256, (h, w, 3), dtype=np.uint8) if noise else np.zeros((h, w, 3), np.uint8)
            f[..., 1] = i % 256
            wr.append_data(f)
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("inputs")
    _write_video(d / "long.mp4", 10_000, (48, 32), 250.0)  # 40 s at 250 fps
    whole = _write_video(d / "whole.mp4", 40, (96, 64), 8.0, noise=True)
    fast = d / "fast.mp4"  # moov first, as phones write it: a copy cut short still opens
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-i", str(whole), "-c", "copy"]
    subprocess.run([*cmd, "-movflags", "+faststart", str(fast)], check=True)
    (d / "cut.mp4").write_bytes(fast.read_bytes()[: fast.stat().st_size // 2])
    fast.unlink()
    (d / "one").mkdir()
    imageio.imwrite(d / "one" / "0001.png", np.zeros((64, 96, 3), np.uint8))
    (d / "tall").mkdir()
    for i in range(3):
        imageio.imwrite(d / "tall" / f"{i}.png", np.full((96, 64, 3), 30 * i, np.uint8))
    return d


@pytest.mark.parametrize(
    ("clips", "message"),
    [
        (["one"], "one: only 1 frame; a clip needs at least 2 frames"),
        (["whole.mp4", "tall"], "tall: its frames are 64x96 (2:3) but those of the first clip, whole.mp4, are 96x64"),
    ],
)
def test_refused_input_is_one_error_line_and_writes_nothing(inputs: Path, tmp_path: Path, clips, message):
    before = tree_digest(inputs)
    out = tmp_path / "scene"
    r = run_cli("reconstruct", *(str(inputs / c) for c in clips), "--out", str(out))
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert message in lines[0], lines[0]
    assert not out.exists() and list(tmp_path.iterdir()) == [] and tree_digest(inputs) == before


def test_a_long_clip_and_a_cut_one_are_read_with_what_was_done_stated(inputs: Path, tmp_path: Path):
    """10 000 frames: 49 kept, evenly, and the run says so; a video cut short: the frames before the cut, said. The
    clips' folder is left as it was and the run writes only inside its scene folder."""
    before = tree_digest(inputs)
    out = tmp_path / "scene"
    args = ("reconstruct", str(inputs / "long.mp4"), str(inputs / "cut.mp4"), "--out", str(out))
    r = run_cli(*args, "--until", "generate_segments", "--engine", "local", "--fov-deg", "60")
    assert r.returncode == 0, r.stderr[-3000:]
    said = {ln.split(":")[1].strip(): ln for ln in r.stderr.splitlines() if ln.startswith("wonderverse: clip ")}
    assert "subsampled 10000 -> 49 frames" in said["clip long.mp4"], said
    cut = json.loads(run_cli("inspect", str(out), "--json").stdout)["clips"][1]["frames"]
    assert 2 <= cut < 36 and f"the file ends after {cut} of the 40 frames its header announces" in said["clip cut.mp4"]
    assert SceneStore.open(out).array("segments/s000/attempts/0/frames").shape == (49, 32, 48, 3)
    assert "resized 96x64 -> 48x32, the size of the first clip (long.mp4)" in said["clip cut.mp4"]
    assert tree_digest(inputs) == before and [p.name for p in tmp_path.iterdir()] == ["scene"]
