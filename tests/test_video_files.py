"""User clips as segments (wonderverse.video.files): videos, GIFs, image folders, globs; resizing, K, errors.

Every synthetic clip encodes its source frame index in the green channel (20 * i for frame i, or 8 * i for
long clips), so which frames came back, and in which order, is read off the pixels.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from pydantic import ValidationError

from wonderverse.errors import WonderError
from wonderverse.video.base import Video
from wonderverse.video.files import (
    ClipParams,
    FilesVideo,
    _target_size,
    _Thinner,
    group_sources,
    read_clip,
)


def frame(i: int, w: int = 160, h: int = 96, level: int = 20) -> np.ndarray:
    """(h,w,3) uint8: green = level * i everywhere, a white block in the top-left quarter (shows orientation)."""
    f = np.zeros((h, w, 3), np.uint8)
    f[..., 1] = level * i
    f[: h // 2, : w // 2, 0] = 255
    return f


def index_of(f: np.ndarray, level: int = 20) -> int:
    """The source frame index encoded in a frame's green channel (lossy codecs shift it by a few levels)."""
    h, w = f.shape[:2]
    return round(float(f[h // 2 :, w // 2 :, 1].mean()) / level)


def write_mp4(path: Path, n: int, fps: float = 10.0, w: int = 160, h: int = 96, level: int = 20) -> Path:
    with imageio.get_writer(path, fps=fps, codec="libx264", quality=10, macro_block_size=1) as wr:
        for i in range(n):
            wr.append_data(frame(i, w, h, level))
    return path


def write_pngs(folder: Path, names: list[str], sizes: list[tuple[int, int]] | None = None) -> Path:
    """names[i] gets frame i (so the true order is the order of `names`); sizes[i] = (w, h)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        w, h = sizes[i] if sizes else (64, 48)
        Image.fromarray(frame(i, w, h)).save(folder / name)
    return folder


# ---------------------------------------------------------------------------------------------- videos


def test_mp4_frames_order_fps_and_guessed_k(tmp_path: Path) -> None:
    clip = read_clip(write_mp4(tmp_path / "a.mp4", 6, fps=10.0))
    assert clip.frames.shape == (6, 96, 160, 3) and clip.frames.dtype == np.uint8
    assert [index_of(f) for f in clip.frames] == list(range(6))
    assert clip.fps == pytest.approx(10.0)
    np.testing.assert_allclose(clip.times_s, np.arange(6) / 10.0)
    assert clip.source.endswith("a.mp4") and clip.name == "a.mp4"
    # 60 deg horizontal FOV guess: fx = (W/2) / tan(30 deg); centred principal point, square pixels.
    fx = 80.0 / np.tan(np.radians(30.0))
    np.testing.assert_allclose(clip.K, [[fx, 0, 80.0], [0, fx, 48.0], [0, 0, 1]])
    assert clip.K.dtype == np.float64
    assert clip.k_is_guess
    assert any("guessed a 60 deg" in n for n in clip.notes)


def test_mp4_downscaled_to_even_size_with_k_from_known_fov(tmp_path: Path) -> None:
    path = write_mp4(tmp_path / "big.mp4", 3, w=322, h=182)
    clip = read_clip(path, ClipParams(max_side_px=100, fov_deg=90.0))
    # 182 * 100 / 322 = 56.5 -> nearest even 56; the longer side is exactly the cap.
    assert clip.frames.shape == (3, 56, 100, 3)
    assert not clip.k_is_guess
    # 90 deg FOV: fx = W/2 at any size; fy follows the (slightly rounded) vertical scale.
    np.testing.assert_allclose(clip.K, [[50.0, 0, 50.0], [0, 161.0 * 56 / 182, 28.0], [0, 0, 1]])
    assert "resized 322x182 -> 100x56" in clip.notes
    assert not any("guessed" in n for n in clip.notes)
    # The white block is still the top-left quarter after scaling.
    assert clip.frames[0, :20, :40, 0].mean() > 240 and clip.frames[0, 36:, 60:, 0].mean() < 15


def test_odd_size_made_even_never_upscaled(tmp_path: Path) -> None:
    # libx264 (yuv420p) cannot store odd sizes, a GIF can.
    imageio.mimsave(tmp_path / "odd.gif", [frame(i, 75, 41) for i in range(3)], duration=100, loop=0)
    clip = read_clip(tmp_path / "odd.gif", ClipParams(max_side_px=4000))
    # Even sizes never above the source's: 75x41 -> 74x40, principal point still centred.
    assert clip.frames.shape == (3, 40, 74, 3)
    assert "resized 75x41 -> 74x40" in clip.notes
    np.testing.assert_allclose(clip.K[:2, 2], [37.0, 20.0])


def test_mp4_subsampled_evenly_and_noted(tmp_path: Path) -> None:
    path = write_mp4(tmp_path / "long.mp4", 30, level=8)
    clip = read_clip(path, ClipParams(max_frames=7))
    got = [index_of(f, level=8) for f in clip.frames]
    ideal = np.linspace(0, 29, 7)
    assert len(got) == 7 and got[0] == 0 and got == sorted(got)
    # Even to within the step of the bounded-memory thinning (2 frames here).
    assert np.abs(np.array(got) - ideal).max() <= 2.5
    assert "subsampled 30 -> 7 frames" in clip.notes
    np.testing.assert_allclose(clip.times_s, np.array(got) / 10.0, atol=1e-9)


def test_mp4_time_window_and_stride(tmp_path: Path) -> None:
    path = write_mp4(tmp_path / "t.mp4", 12, fps=10.0, level=20)
    clip = read_clip(path, ClipParams(start_s=0.3, end_s=0.9, frame_stride=2))
    got = [index_of(f) for f in clip.frames]
    assert got[0] == 3 and np.all(np.diff(got) == 2) and got[-1] in (7, 9)
    np.testing.assert_allclose(clip.times_s, np.array(got) / 10.0, atol=1e-6)
    assert clip.fps == pytest.approx(5.0)
    assert any(n.startswith("frame stride 2") for n in clip.notes)


def test_rotated_phone_video_comes_out_upright(tmp_path: Path) -> None:
    from imageio_ffmpeg import get_ffmpeg_exe

    src = write_mp4(tmp_path / "land.mp4", 3)
    rot = tmp_path / "portrait.mp4"
    r = subprocess.run(
        [
            get_ffmpeg_exe(),
            "-y",
            "-loglevel",
            "error",
            "-display_rotation",
            "90",
            "-i",
            str(src),
            "-c",
            "copy",
            str(rot),
        ],
        capture_output=True,
    )
    if r.returncode != 0:
        pytest.skip(f"this ffmpeg cannot tag a rotation: {r.stderr.decode()[-200:]}")
    clip = read_clip(rot)
    # 90 deg counter-clockwise display rotation: 160x96 landscape -> 96x160 portrait, top-left block -> bottom-left.
    assert clip.frames.shape == (3, 160, 96, 3)
    f = clip.frames[0, :, :, 0].astype(float)
    assert f[-70:, :40].mean() > 240 and f[:70, :].mean() < 15


# ---------------------------------------------------------------------------------------------- GIFs


def test_gif_frames_fps_and_rgb(tmp_path: Path) -> None:
    frames = [frame(i, 64, 48) for i in range(5)]
    # GIF delays are whole centiseconds: 250 ms per frame = 4 fps exactly.
    imageio.mimsave(tmp_path / "g.gif", frames, duration=250, loop=0)
    clip = read_clip(tmp_path / "g.gif")
    assert clip.frames.shape == (5, 48, 64, 3)
    assert [index_of(f) for f in clip.frames] == list(range(5))
    assert clip.fps == pytest.approx(4.0)
    np.testing.assert_allclose(clip.times_s, np.arange(5) * 0.25)


# ---------------------------------------------------------------------------------------------- images


def test_folder_natural_order_ignores_other_files(tmp_path: Path) -> None:
    names = ["frame1.png", "frame2.png", "frame3.jpg", "frame10.png", "frame11.webp", "frame100.png"]
    folder = write_pngs(tmp_path / "seq", names)
    (folder / "notes.txt").write_text("not an image")
    clip = read_clip(folder)
    assert [index_of(f) for f in clip.frames] == list(range(6))
    assert clip.fps == pytest.approx(8.0) and any("assumed 8 fps" in n for n in clip.notes)


def test_glob_list_and_shell_expanded_arguments(tmp_path: Path) -> None:
    names = ["b_2.png", "b_10.png", "b_33.png"]
    folder = write_pngs(tmp_path / "g", names)
    write_pngs(tmp_path / "g_other", ["b_1.png"])
    by_glob = read_clip(str(folder / "b_*.png"))
    assert [index_of(f) for f in by_glob.frames] == [0, 1, 2]
    by_list = read_clip([folder / "b_33.png", folder / "b_2.png"])  # a list keeps the order given
    assert [index_of(f) for f in by_list.frames] == [2, 0]
    video = write_mp4(tmp_path / "v.mp4", 2)
    args = [str(folder / n) for n in names] + [str(video), str(tmp_path / "g_other")]
    grouped = group_sources(args)
    assert grouped == [[folder / n for n in names], str(video), str(tmp_path / "g_other")]


def test_folder_of_mixed_sizes_same_shape_resized_with_note(tmp_path: Path) -> None:
    folder = write_pngs(tmp_path / "m", ["a1.png", "a2.png", "a3.png"], sizes=[(64, 48), (128, 96), (64, 48)])
    clip = read_clip(folder)
    assert clip.frames.shape == (3, 48, 64, 3)
    assert [index_of(f) for f in clip.frames] == [0, 1, 2]
    assert "1 images of other sizes resized to the first frame's 64x48" in clip.notes


def test_folder_of_another_shape_refused_naming_the_file(tmp_path: Path) -> None:
    folder = write_pngs(tmp_path / "m", ["a1.png", "a2.png"], sizes=[(64, 48), (64, 64)])
    with pytest.raises(WonderError, match=r"a2\.png: image is 64x64 but .*a1\.png is 64x48"):
        read_clip(folder)


def test_grayscale_rgba_and_16bit_images_become_rgb(tmp_path: Path) -> None:
    folder = tmp_path / "modes"
    folder.mkdir()
    gray = np.full((48, 64), 77, np.uint8)
    Image.fromarray(gray, mode="L").save(folder / "f1.png")
    rgba = np.zeros((48, 64, 4), np.uint8)
    rgba[...] = (10, 200, 30, 0)  # fully transparent: the colour is kept, the alpha dropped
    Image.fromarray(rgba, mode="RGBA").save(folder / "f2.png")
    g16 = np.full((48, 64), 50000, np.uint16)
    Image.fromarray(g16).save(folder / "f3.png")
    clip = read_clip(folder)
    assert clip.frames.shape == (3, 48, 64, 3)
    assert np.all(clip.frames[0] == 77)
    assert np.all(clip.frames[1] == (10, 200, 30))
    assert np.all(clip.frames[2] == round(50000 / 257))


# ---------------------------------------------------------------------------------------------- errors


def test_errors_are_one_line_and_name_the_file(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    corrupt = tmp_path / "corrupt.mp4"
    corrupt.write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    bad_gif = tmp_path / "bad.gif"
    bad_gif.write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    empty = tmp_path / "empty"
    empty.mkdir()
    one = write_pngs(tmp_path / "one", ["only.png"])
    broken = write_pngs(tmp_path / "broken", ["x1.png", "x2.png"])
    (broken / "x2.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    imageio.mimsave(tmp_path / "still.gif", [frame(0, 32, 32)], duration=100)
    short = write_mp4(tmp_path / "short.mp4", 10, fps=10.0)
    cases = [
        (corrupt, {}, r"corrupt\.mp4: cannot read video \(.+\)"),
        (bad_gif, {}, r"bad\.gif: cannot read GIF"),
        (empty, {}, r"empty: folder has no images"),
        (one, {}, r"one: only 1 frame; a clip needs at least 2 frames"),
        (one / "only.png", {}, r"only\.png: a single image; a clip needs at least 2 frames"),
        (broken, {}, r"x2\.png: cannot read image"),
        (tmp_path / "still.gif", {}, r"still\.gif: only 1 frame"),
        (tmp_path / "missing.mov", {}, r"missing\.mov: no such file or folder"),
        (str(tmp_path / "*.jpeg"), {}, r"\*\.jpeg: no files match"),
        (short, {"start_s": 5.0}, r"short\.mp4: no frames between 5 s and the end; the video is 1 s long"),
        (short, {"start_s": 0.5, "end_s": 0.55}, r"short\.mp4: only 1 frame between 0\.5 s and 0\.55 s"),
    ]
    for src, kw, pattern in cases:
        with pytest.raises(WonderError, match=pattern) as info:
            read_clip(src, ClipParams(**kw))
        assert "\n" not in str(info.value), str(info.value)


def test_params_validated() -> None:
    with pytest.raises(ValidationError):
        ClipParams(start_s=2.0, end_s=1.0)
    with pytest.raises(ValidationError):
        ClipParams(max_frames=1)
    with pytest.raises(ValidationError):
        ClipParams(unknown=3)  # type: ignore[call-arg]


# ---------------------------------------------------------------------------------------------- FilesVideo


def test_files_video_segments_and_no_regeneration(tmp_path: Path) -> None:
    a = write_mp4(tmp_path / "a.mp4", 4, w=64, h=48)  # a scene's clips have one shape (see below)
    b = write_pngs(tmp_path / "b", ["1.png", "2.png", "3.png"])
    model = FilesVideo([a, b], ClipParams(fov_deg=70.0))
    assert len(model) == 2 and [c.name for c in model.clips] == ["a.mp4", "b"]
    seg = model.segment(1)
    assert isinstance(seg, Video) and seg.gt is None
    assert seg.frames.shape == (3, 48, 64, 3)
    np.testing.assert_allclose(seg.K[0, 0], 32.0 / np.tan(np.radians(35.0)))
    assert not seg.k_is_guess  # the field of view was given
    assert FilesVideo([a]).segment(0).k_is_guess
    with pytest.raises(IndexError):
        model.segment(2)
    with pytest.raises(WonderError, match="cannot be regenerated"):
        model.generate("a prompt", np.tile(np.eye(4), (4, 1, 1)), 0, None)


def test_files_video_skips_or_raises_on_unreadable(tmp_path: Path) -> None:
    good = write_mp4(tmp_path / "good.mp4", 3)
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video at all")
    with pytest.raises(WonderError, match=r"bad\.mp4"):
        FilesVideo([good, bad])
    model = FilesVideo([bad, good], skip_unreadable=True)
    assert len(model) == 1 and model.clips[0].name == "good.mp4"
    assert model.skipped[0][0].endswith("bad.mp4") and "cannot read video" in model.skipped[0][1]
    with pytest.raises(WonderError, match="none of the 1 clips"):
        FilesVideo([bad], skip_unreadable=True)


# ---------------------------------------------------------------------------------------------- properties


@settings(max_examples=200, deadline=None)
@given(st.integers(2, 5000), st.integers(2, 5000), st.one_of(st.none(), st.integers(16, 2000)))
def test_target_size_even_bounded_and_keeps_aspect(w: int, h: int, max_side: int | None) -> None:
    tw, th = _target_size(w, h, max_side)
    assert tw % 2 == 0 and th % 2 == 0 and tw >= 2 and th >= 2
    if max_side is not None:
        assert max(tw, th) <= max_side
    if max_side is None or max(w, h) <= max_side:
        assert abs(tw - w) <= 1 and abs(th - h) <= 1  # never scaled, only made even
    else:
        s = max_side / max(w, h)
        assert abs(tw - w * s) <= 2 and abs(th - h * s) <= 2


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 3000), st.integers(1, 5), st.integers(2, 60))
def test_thinner_keeps_bounded_evenly_spaced_subset(n: int, stride: int, max_frames: int) -> None:
    thin = _Thinner(stride, max_frames)
    for i in range(n):
        if thin.wants(i):
            thin.add(i, np.empty(0))
    idx = np.array([i for i, _ in thin.items])
    assert idx[0] == 0 and len(idx) <= 4 * max_frames
    assert np.all(np.diff(idx) == thin.step) and thin.step % stride == 0
    # Nothing after the last kept frame is further away than one step: the subset covers the whole stream.
    assert n - 1 - idx[-1] < thin.step


# ---------------------------------------------------------------------------------------------- real data


def _real(data_dir: Path, rel: str) -> Path:
    p = data_dir / rel
    if not p.exists():
        pytest.skip(f"shared test data not found: {p}")
    return p


def test_real_realestate10k_mp4_and_cameractrl_gif(data_dir: Path) -> None:
    # SOURCE.md: 16 frames, 384x256, 8 fps for both the RealEstate10K mp4s and the CameraCtrl GIFs.
    mp4 = read_clip(
        _real(data_dir, "cameractrl_re10k/reference_videos/0bf152ef84195293.mp4"), ClipParams(max_side_px=None)
    )
    assert mp4.frames.shape == (16, 256, 384, 3) and mp4.fps == pytest.approx(8.0)
    assert mp4.frames.std() > 10  # real picture content, not a blank decode
    # Consecutive frames of a walkthrough are similar, far-apart ones less so: the order is the video's.
    d = [np.abs(mp4.frames[0].astype(int) - mp4.frames[k].astype(int)).mean() for k in (1, 15)]
    assert d[0] < d[1]
    gif = read_clip(_real(data_dir, "cameractrl_re10k/generated_gifs/sunflowers_3b9420585a1e66fc.gif"))
    assert gif.frames.shape == (16, 256, 384, 3) and gif.frames.std() > 10


def test_real_cogvideox_clip_default_params(data_dir: Path) -> None:
    # SOURCE.md: 49 frames at 720x480, 8 fps; defaults keep 49 frames and scale the longer side to 480.
    clip = read_clip(_real(data_dir, "cogvideox_samples/cogvideox2b_gallery_1.mp4"))
    assert clip.frames.shape == (49, 320, 480, 3)
    assert clip.fps == pytest.approx(8.0)
    assert "resized 720x480 -> 480x320" in clip.notes and clip.k_is_guess
    np.testing.assert_allclose(clip.K[:2, 2], [240.0, 160.0])


# ---------------------------------------------------------------------------------------------- shapes and bad input


def test_a_few_images_of_another_shape_are_left_out_and_named(tmp_path: Path) -> None:
    """A square crop among 4:3 shots: the 4:3 frames are kept (one camera, one shape), the square one is left out
    with a note naming it and what to do; the frames kept are the main shape's, in order. (A portrait shot among
    landscape ones is turned instead: tests/test_mixed_shapes.py.)"""
    sizes = [(64, 48)] * 2 + [(48, 48)] + [(64, 48)] * 2
    folder = write_pngs(tmp_path / "m", [f"a{i}.png" for i in range(5)], sizes=sizes)
    clip = read_clip(folder)
    assert clip.frames.shape == (4, 48, 64, 3)
    assert [index_of(f) for f in clip.frames] == [0, 1, 3, 4]
    assert "1 of 5 images left out: another shape (48x48) than the 64x48 of the others (a2.png)" in clip.notes[1]
    assert "crop them to 4:3 to use them" in clip.notes[1]


def test_exif_rotated_photos_are_one_shape(tmp_path: Path) -> None:
    """A phone photo stored landscape with an EXIF quarter turn is upright portrait, like the others: nothing is left
    out, and it comes out turned (its white top-left block where the others have theirs)."""
    folder = write_pngs(tmp_path / "p", ["a0.png", "a1.png"], sizes=[(48, 64), (48, 64)])
    stored = np.ascontiguousarray(np.rot90(frame(2, 48, 64), k=1))  # 64x48 pixels, turned a quarter left
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 CW to display"
    Image.fromarray(stored).save(folder / "a2.jpg", exif=exif, quality=95)
    clip = read_clip(folder)
    assert clip.frames.shape == (3, 64, 48, 3) and not any("left out" in n for n in clip.notes), clip.notes
    assert clip.frames[2][:16, :12, 0].mean() > 200 and clip.frames[2][-16:, -12:, 0].mean() < 50


def test_clips_of_another_shape_refused_same_shape_resized_with_k(tmp_path: Path) -> None:
    wide = write_mp4(tmp_path / "wide.mp4", 3, w=160, h=96)
    small = write_mp4(tmp_path / "small.mp4", 3, w=80, h=48)
    tall = write_pngs(tmp_path / "tall", ["a.png", "b.png"], sizes=[(48, 64), (48, 64)])
    with pytest.raises(WonderError, match=r"^tall: its frames are 48x64 \(3:4\) but those of the first clip, "):
        FilesVideo([wide, tall], ClipParams(fov_deg=60.0))
    model = FilesVideo([wide, small], ClipParams(fov_deg=60.0))
    first, second = model.clips
    assert second.frames.shape == first.frames.shape == (3, 96, 160, 3)
    np.testing.assert_allclose(second.K, first.K)  # the same field of view at the same size
    assert "resized 80x48 -> 160x96, the size of the first clip (wide.mp4)" in second.notes


def test_a_truncated_video_says_how_much_of_it_is_used(tmp_path: Path) -> None:
    import imageio_ffmpeg

    whole = write_mp4(tmp_path / "whole.mp4", 40, level=6)
    fast = tmp_path / "fast.mp4"  # moov first, as phones and the web write it: a cut copy still opens
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-i", str(whole), "-c", "copy"]
    subprocess.run([*cmd, "-movflags", "+faststart", str(fast)], check=True)
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(fast.read_bytes()[: fast.stat().st_size // 2])
    clip = read_clip(cut, ClipParams(max_frames=None))
    n = len(clip.frames)
    assert 2 <= n < 36 and any(
        f"the file ends after {n} of the 40 frames its header announces" in x for x in clip.notes
    )
    assert not any("ends after" in x for x in read_clip(whole).notes)
    (tmp_path / "cut_head.mp4").write_bytes(whole.read_bytes()[:1000])  # no index at all: refused in one line
    with pytest.raises(WonderError, match=r"cut_head\.mp4: cannot read video"):
        read_clip(tmp_path / "cut_head.mp4")


def test_other_files_of_a_folder_are_named(tmp_path: Path) -> None:
    folder = write_pngs(tmp_path / "f", ["a.png", "b.jpg"])
    (folder / "c.heic").write_bytes(b"not read")
    (folder / ".DS_Store").write_bytes(b"")
    clip = read_clip(folder)
    assert len(clip.frames) == 2
    assert "1 other files left out (.heic): a folder clip reads images only" in " ".join(clip.notes)


def test_a_real_phone_set_with_two_landscape_shots_turns_them_to_portrait(data_dir: Path, tmp_path: Path) -> None:
    """From the fox capture (portrait 1080x1920 photos): twelve of them, two turned landscape. All twelve are read,
    the two turned a quarter counter-clockwise (so upside down against the originals here), and the note names
    them; with the turn written as EXIF orientation instead, all twelve are read upright (as the photos before
    they were turned), nothing said."""
    src = sorted(_real(data_dir, "instant_ngp_fox/images").glob("*.jpg"))[:12]
    plain, mixed, tagged = tmp_path / "plain", tmp_path / "mixed", tmp_path / "tagged"
    for d in (plain, mixed, tagged):
        d.mkdir()
    for i, p in enumerate(src):
        img = Image.open(p).convert("RGB").resize((135, 240))
        img.save(plain / f"{p.stem}.png")
        turned = i in (4, 9)
        (img.rotate(90, expand=True) if turned else img).save(mixed / f"{p.stem}.png")
        exif = Image.Exif()
        if turned:
            exif[0x0112] = 8  # stored turned clockwise, tagged "turn 90 degrees counter-clockwise to display"
        (img.rotate(-90, expand=True) if turned else img).save(tagged / f"{p.stem}.jpg", exif=exif, quality=95)
    clip, reference = read_clip(mixed), read_clip(plain)
    assert clip.frames.shape == (12, 240, 134, 3)  # 135 px wide, made even
    said = next(n for n in clip.notes if "turned" in n)
    assert said.startswith("2 of 12 images turned a quarter counter-clockwise to the 135x240 of the others")
    assert f"({src[4].stem}.png, {src[9].stem}.png)" in said and not any("left out" in n for n in clip.notes)
    for i in range(12):  # the same pixels, the two turned ones half a turn from where they were
        want = np.rot90(reference.frames[i], 2) if i in (4, 9) else reference.frames[i]
        np.testing.assert_array_equal(clip.frames[i], want)
    upright = read_clip(tagged)
    assert len(upright.frames) == 12 and not any("left out" in n or "turned" in n for n in upright.notes)
    for i in (4, 9):  # JPEG-compressed, else the same pixels
        assert np.abs(upright.frames[i].astype(float) - reference.frames[i]).mean() < 4.0
