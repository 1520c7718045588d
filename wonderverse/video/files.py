"""The user's own clips as video segments: video files, GIFs, image folders or globs -> `Clip` / `Video`.

Every clip comes out as (T,H,W,3) uint8 RGB at an even size no longer than `max_side_px`, at most
`max_frames` frames picked evenly over the chosen time window, with a pinhole K in pixels (pixel
centres at +0.5, cx = W/2). An image folder's photos are turned upright per their EXIF orientation; those
whose shape is the main shape transposed (a landscape shot among portrait ones) are turned a quarter to it,
those of another shape left out (`_main_shape`). Everything done to the input is written in `Clip.notes` so
the user sees it. Anything unreadable raises `WonderError` with one line naming the file and the problem.
"""

from __future__ import annotations

import glob
import logging
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from wonderverse.camera import intrinsics
from wonderverse.errors import WonderError
from wonderverse.video.base import Guide, Video

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff"})
GIF_SUFFIXES = frozenset({".gif"})
# Read with ffmpeg; any other suffix is tried with ffmpeg too (it sniffs the container).
VIDEO_SUFFIXES = frozenset({".mp4", ".mov", ".m4v", ".webm", ".avi", ".mkv"})
GLOB_CHARS = frozenset("*?[")
TRUNCATED_SHARE = 0.1  # a video missing more than this share of the frames its header announces is noted
EXIF_ORIENTATION = 0x0112  # the EXIF tag a phone records its rotation in (5-8: turned a quarter)
# Longest tail of a decoder's message kept in a one-line error.
REASON_MAX_CHARS = 160

ClipSource = str | Path | Sequence[str | Path]
# Pixel aspect (fy/fx) of 16:9 footage resized to 3:2 frames without cropping: (16/9) / (3/2).
RESIZED_16_9_TO_3_2 = 32.0 / 27.0


class ClipParams(BaseModel):
    """How a user clip is turned into a segment."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_frames: int | None = Field(
        49, ge=2, le=10_000, description="frames kept at most, picked evenly over the clip; None keeps all"
    )
    frame_stride: int = Field(1, ge=1, le=1000, description="keep every n-th frame before the max_frames cap")
    max_side_px: int | None = Field(
        480, ge=16, le=8192, description="longer side after downscaling (never upscaled); None keeps the size"
    )
    fov_deg: float | None = Field(
        None, gt=5, lt=170, description="horizontal field of view of the camera when known; None = unknown"
    )
    guess_fov_deg: float = Field(60.0, gt=5, lt=170, description="horizontal field of view assumed when unknown")
    intrinsics: tuple[float, float, float, float] | None = Field(
        None,
        description="the camera's K when known: fx, fy, cx, cy in pixels of the source frames (before any resizing; "
        "pixel centres at +0.5), instead of fov_deg and pixel_aspect; held through the global solve as a given "
        "field of view is (steps.poses.refine_intrinsics)",
    )
    pixel_aspect: float | Literal["auto"] = Field(
        "auto",
        description="fy/fx of the frames' pixels (1: square). auto: 32/27 for a video or GIF of 3:2 frames (no "
        "video camera records 3:2; datasets and video models resize 16:9 footage to it, e.g. RealEstate10K at "
        "384x256, CogVideoX at 720x480), else 1",
    )
    start_s: float | None = Field(None, ge=0, description="first second of the clip to use")
    end_s: float | None = Field(None, gt=0, description="last second of the clip to use")
    image_fps: float = Field(8.0, gt=0, le=1000, description="frame rate assumed for image folders (they have none)")
    # Frames of other sizes in an image folder are resized only when the shape is this close to the first frame's;
    # stretching a frame of another shape would silently bend the geometry the pipeline reconstructs.
    max_aspect_mismatch: float = Field(0.01, ge=0, le=0.5, description="relative aspect-ratio difference tolerated")

    @model_validator(mode="after")
    def _window_is_ordered(self) -> ClipParams:
        if isinstance(self.pixel_aspect, float) and not 0.25 <= self.pixel_aspect <= 4.0:
            raise ValueError(f"pixel_aspect must be between 0.25 and 4 (fy/fx), got {self.pixel_aspect}")
        if self.start_s is not None and self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"end_s ({self.end_s}) must be after start_s ({self.start_s})")
        if self.intrinsics is not None and self.fov_deg is not None:
            raise ValueError("give either intrinsics or fov_deg, not both")
        return self

    @field_validator("intrinsics")
    @classmethod
    def _positive(cls, v: tuple[float, float, float, float] | None) -> tuple[float, float, float, float] | None:
        if v is not None and not all(math.isfinite(x) and x > 0 for x in v):
            raise ValueError("must be four positive numbers fx, fy, cx, cy (pixels)")
        return v


@dataclass
class Clip:
    """One user clip, ready to be a segment.

    frames: (T,H,W,3) uint8 RGB, T >= 2, H and W even.
    fps: frame rate of the returned frames (the source rate divided by the mean step between kept frames).
    source: the path (or first image path of an image sequence) it was read from.
    K: (3,3) float64 pinhole intrinsics in pixels of the returned frames, pixel centres at +0.5.
    k_is_guess: True when K comes from `guess_fov_deg`, not from a known K or field of view.
    times_s: (T,) float64 time of each returned frame in seconds from the start of the source.
    notes: what was done to the input, in words (resizing, subsampling, guesses).
    """

    frames: np.ndarray
    fps: float
    source: str
    K: np.ndarray
    k_is_guess: bool
    times_s: np.ndarray
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        """Short name for messages: the file or folder name."""
        return Path(self.source).name


# ---------------------------------------------------------------------------------------------- helpers


def _natural_key(path: Path) -> list[int | str]:
    """Sort key putting frame2 before frame10: digit runs compare as numbers."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", str(path).lower())]


def _short_reason(err: BaseException) -> str:
    """One line out of a decoder's (possibly multi-line, ffmpeg-log) message: its last meaningful line."""
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip() and not ln.startswith("===")]
    reason = lines[-1] if lines else type(err).__name__
    # ffmpeg prefixes its verdict with the input path ("/x/a.mp4: Invalid data ..."); the caller names the file.
    reason = re.sub(r"^.*?\.\w{2,5}: ", "", reason)
    return reason[:REASON_MAX_CHARS]


def _even(x: float, cap: int) -> int:
    """Nearest even integer to x, at least 2, at most cap (rounded down to even)."""
    return max(2, min(round(x / 2.0) * 2, cap - cap % 2))


def _target_size(width: int, height: int, max_side_px: int | None) -> tuple[int, int]:
    """Even (width, height) keeping the aspect ratio, longer side <= max_side_px; never upscaled."""
    scale = 1.0 if max_side_px is None else min(1.0, max_side_px / max(width, height))
    cap_w = width if scale == 1.0 else max_side_px
    cap_h = height if scale == 1.0 else max_side_px
    return _even(width * scale, int(cap_w)), _even(height * scale, int(cap_h))


def _to_rgb(img) -> np.ndarray:  # img: PIL.Image.Image
    """(H,W,3) uint8 RGB from any PIL mode: grey is replicated, alpha dropped, 16-bit scaled to 8."""
    if img.mode.startswith("I") or img.mode == "F":
        a = np.asarray(img, dtype=np.float64)
        a = a / 257.0 if a.max(initial=0.0) > 255 else a  # 16-bit data (the usual case for I;16 PNGs)
        g = np.clip(np.round(a), 0, 255).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=2)
    return np.asarray(img.convert("RGB"), dtype=np.uint8)


def _resize(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """frame (H,W,3) uint8 resized to size = (width, height) with an antialiased Lanczos filter."""
    from PIL import Image

    if frame.shape[1] == size[0] and frame.shape[0] == size[1]:
        return frame
    return np.asarray(Image.fromarray(frame).resize(size, Image.Resampling.LANCZOS), dtype=np.uint8)


def _pick_evenly(n: int, max_frames: int | None) -> np.ndarray:
    """Indices into n items: all of them, or max_frames spread evenly from the first to the last."""
    if max_frames is None or n <= max_frames:
        return np.arange(n)
    return np.round(np.linspace(0, n - 1, max_frames)).astype(np.int64)


class _Thinner:
    """Keeps an even subset of a stream of unknown length in bounded memory.

    Frames whose index is a multiple of `step` are kept; when more than `cap` are held, every other one
    is dropped and `step` doubles, so what is held stays evenly spaced over what has been seen.
    """

    def __init__(self, stride: int, max_frames: int | None) -> None:
        self.step = stride
        self.cap = None if max_frames is None else 4 * max_frames
        self.items: list[tuple[int, np.ndarray]] = []
        self.seen = 0

    def wants(self, i: int) -> bool:
        return i % self.step == 0

    def add(self, i: int, frame: np.ndarray) -> None:
        self.items.append((i, frame))
        if self.cap is not None and len(self.items) > self.cap:
            self.items = self.items[::2]
            self.step *= 2


# ---------------------------------------------------------------------------------------------- sources


def _expand(source: ClipSource) -> tuple[str, Path | list[Path]]:
    """(display name, a single file path or an ordered list of image files) for one clip source."""
    if not isinstance(source, str | Path):
        files = [Path(p) for p in source]
        if not files:
            raise WonderError("empty list of images for a clip")
        missing = [p for p in files if not p.is_file()]
        if missing:
            raise WonderError(f"{missing[0]}: no such file")
        return str(files[0]), files
    text = str(source)
    path = Path(source).expanduser()
    if path.is_dir():
        files = sorted(
            (p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key
        )
        if not files:
            kinds = ", ".join(sorted(s.lstrip(".") for s in IMAGE_SUFFIXES))
            raise WonderError(f"{path}: folder has no images ({kinds})")
        return str(path), files
    if path.is_file():
        return str(path), path
    if GLOB_CHARS & set(text):
        matches = sorted((Path(p) for p in glob.glob(str(path)) if Path(p).is_file()), key=_natural_key)
        if not matches:
            raise WonderError(f"{text}: no files match this pattern")
        images = [p for p in matches if p.suffix.lower() in IMAGE_SUFFIXES]
        if len(images) != len(matches):
            other = next(p for p in matches if p.suffix.lower() not in IMAGE_SUFFIXES)
            raise WonderError(f"{text}: a pattern must match only images; it matches {other.name}")
        return text, images
    raise WonderError(f"{path}: no such file or folder")


def _other_files(name: str, images: list[Path]) -> list[str]:
    """A note naming the files of a folder clip that are not images it reads (HEIC photos, videos, sidecar files;
    hidden files aside), [] when there are none or the clip is not a folder."""
    folder = Path(name)
    if not folder.is_dir():
        return []
    used = {p.name for p in images}
    other = sorted(p for p in folder.iterdir() if p.is_file() and p.name not in used and not p.name.startswith("."))
    if not other:
        return []
    kinds = ", ".join(sorted({p.suffix.lower() or "no suffix" for p in other}))
    readable = ", ".join(sorted(s.lstrip(".") for s in IMAGE_SUFFIXES))
    return [f"{len(other)} other files left out ({kinds}): a folder clip reads images only ({readable})"]


def _window_indices(times: np.ndarray, params: ClipParams) -> np.ndarray:
    """Indices of the frames (at times `times`, seconds) inside [start_s, end_s]."""
    lo = params.start_s if params.start_s is not None else -np.inf
    hi = params.end_s if params.end_s is not None else np.inf
    # Half a microsecond of slack so a frame exactly at a bound is kept despite float rounding of i / fps.
    return np.flatnonzero((times >= lo - 5e-7) & (times <= hi + 5e-7))


def _window_text(params: ClipParams) -> str:
    start = f"{params.start_s:g} s" if params.start_s is not None else "the start"
    end = f"{params.end_s:g} s" if params.end_s is not None else "the end"
    return f"between {start} and {end}"


def _read_image(path: Path) -> np.ndarray:
    """(H,W,3) uint8 RGB of one image file, turned upright per its EXIF orientation (phone photos)."""
    from PIL import Image, ImageOps

    try:
        with Image.open(path) as img:
            img.load()
            return _to_rgb(ImageOps.exif_transpose(img))
    except Exception as e:  # decoders raise many types (OSError, SyntaxError, ValueError, ...); all mean "unreadable"
        raise WonderError(f"{path}: cannot read image ({_short_reason(e)})") from e


@dataclass
class _Raw:
    """Frames as picked from the source, before the final resize to the target size."""

    frames: list[np.ndarray]
    source_indices: np.ndarray  # index of each frame in the source
    times_s: np.ndarray
    source_fps: float
    source_size: tuple[int, int]  # (width, height) of the source frames
    window_frames: int  # frames inside the time window (before stride and the max_frames cap)
    notes: list[str]
    kind: Literal["images", "gif", "video"]


def _upright_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file as `_read_image` returns it (EXIF orientation applied), from its header."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            w, h = img.size
            turned = img.getexif().get(EXIF_ORIENTATION) in (5, 6, 7, 8)  # a quarter turn: width and height swap
    except Exception as e:  # decoders raise many types; all mean "unreadable"
        raise WonderError(f"{path}: cannot read image ({_short_reason(e)})") from e
    return (h, w) if turned else (w, h)


def _same_shape(a: tuple[int, int], b: tuple[int, int], tolerance: float) -> bool:
    """Whether sizes (w, h) a and b have one shape: aspect ratios within `tolerance` (relative) of b's."""
    return abs(a[0] / a[1] - b[0] / b[1]) <= tolerance * b[0] / b[1]


def _transposed(size: tuple[int, int]) -> tuple[int, int]:
    return size[1], size[0]


@dataclass
class _Shapes:
    """Which images of a folder clip are used, and how (`_main_shape`)."""

    kept: np.ndarray  # indices into the files, in order: the main shape's and the turned ones
    turned: frozenset[int]  # indices into the files of images turned a quarter to the main shape
    notes: list[str]


def _shape_groups(sizes: list[tuple[int, int]], tolerance: float) -> list[tuple[tuple[int, int], list[int]]]:
    """The images' sizes (w, h) grouped by shape: (the shape's first size, positions in `sizes`), first seen first."""
    groups: list[tuple[tuple[int, int], list[int]]] = []
    for k, size in enumerate(sizes):
        group = next((g for g in groups if _same_shape(size, g[0], tolerance)), None)
        if group is None:
            groups.append((size, [k]))
        else:
            group[1].append(k)
    return groups


def _main_shape(files: list[Path], window: np.ndarray, params: ClipParams) -> _Shapes:
    """The images of `window` one camera can take: those of the main shape, and those of the main shape transposed
    (aspect within `max_aspect_mismatch` of it), to be turned a quarter. The main shape is the one keeping the
    most images (ties: the one most images have as they are, then the first image's). Notes name the images
    turned and those left out.

    One camera needs one shape: a frame of another shape cannot be resized to it without stretching, and SfM,
    the priors, the splats and every export hold one camera of one size. A landscape shot among portrait ones
    is the same sensor turned a quarter about its optical axis, so turned back to portrait it is a frame of
    that one camera: with square pixels and the principal point in the centre, its K is the others' (the
    pose takes the quarter roll)."""
    tol = params.max_aspect_mismatch
    sizes = [_upright_size(files[i]) for i in window]
    groups = _shape_groups(sizes, tol)

    def turnable(g: tuple[tuple[int, int], list[int]]) -> list[int]:
        """Positions of the images whose shape is g's transposed (a square shape has none)."""
        if _same_shape(g[0], _transposed(g[0]), tol):
            return []
        return [k for o in groups if o is not g and _same_shape(_transposed(o[0]), g[0], tol) for k in o[1]]

    main = max(groups, key=lambda g: (len(g[1]) + len(turnable(g)), len(g[1])))  # max keeps the first of equals
    turn = sorted(turnable(main))
    keep = sorted(main[1] + turn)
    w, h = main[0]
    notes = []
    if turn:
        notes.append(
            f"{len(turn)} of {len(window)} images turned a quarter counter-clockwise to the {w}x{h} of the others "
            f"({_names(files, window, turn)}): they are {_sizes(sizes, turn)}, the others' shape transposed, "
            "so the same camera turned on its side (one camera, one K)"
        )
    other = [k for k in range(len(window)) if k not in set(keep)]
    if other:
        notes.append(
            f"{len(other)} of {len(window)} images left out: another shape ({_sizes(sizes, other)}) than the {w}x{h} "
            f"of the others ({_names(files, window, other)}); one camera needs one shape (crop them to "
            f"{_ratio(w, h)} to use them)"
        )
    return _Shapes(window[keep], frozenset(int(window[k]) for k in turn), notes)


def _names(files: list[Path], window: np.ndarray, positions: list[int]) -> str:
    """'a.png, b.png' for the images at `positions` of `window`, the first five."""
    return ", ".join(files[window[k]].name for k in positions[:5]) + (", …" if len(positions) > 5 else "")


def _sizes(sizes: list[tuple[int, int]], positions: list[int]) -> str:
    """'320x180, 300x170': the distinct sizes at `positions`."""
    return ", ".join(dict.fromkeys(f"{sizes[k][0]}x{sizes[k][1]}" for k in positions))


def _read_chosen(
    files: list[Path], usable: np.ndarray, turned: frozenset[int], params: ClipParams
) -> tuple[np.ndarray, list[np.ndarray]]:
    """(the indices into `files` picked from `usable` by the stride and the max_frames cap, their frames), images
    in `turned` turned a quarter counter-clockwise."""
    strided = usable[:: params.frame_stride]
    chosen = strided[_pick_evenly(len(strided), params.max_frames)]
    frames = [_read_image(files[i]) for i in chosen]
    frames = [np.ascontiguousarray(np.rot90(f)) if i in turned else f for i, f in zip(chosen, frames, strict=True)]
    return chosen, frames


def _read_images(name: str, files: list[Path], params: ClipParams) -> _Raw:
    fps = params.image_fps
    notes = [f"{len(files)} images; frame rate unknown, assumed {fps:g} fps"]
    window = _window_indices(np.arange(len(files)) / fps, params)
    if len(window) == 0:
        raise WonderError(f"{name}: no frames {_window_text(params)} ({len(files)} images at an assumed {fps:g} fps)")
    usable = window
    chosen, frames = _read_chosen(files, usable, frozenset(), params)
    w0, h0 = frames[0].shape[1], frames[0].shape[0]
    if any(not _same_shape((f.shape[1], f.shape[0]), (w0, h0), params.max_aspect_mismatch) for f in frames):
        # images of several shapes (a landscape shot among portrait ones): the main shape's, picked again
        shapes = _main_shape(files, window, params)
        if len(shapes.kept) >= 2:
            notes.extend(shapes.notes)
            usable = shapes.kept
            chosen, frames = _read_chosen(files, usable, shapes.turned, params)
            w0, h0 = frames[0].shape[1], frames[0].shape[0]
    odd = [(files[i], f.shape[1], f.shape[0]) for i, f in zip(chosen, frames, strict=True) if f.shape[:2] != (h0, w0)]
    for f, w, h in odd:
        if abs(w / h - w0 / h0) > params.max_aspect_mismatch * w0 / h0:
            raise WonderError(
                f"{f}: image is {w}x{h} but the clip's first frame {files[chosen[0]].name} is {w0}x{h0};"
                " another shape cannot be resized without stretching (crop the images to one shape)"
            )
    if odd:
        notes.append(f"{len(odd)} images of other sizes resized to the first frame's {w0}x{h0}")
    size = (frames[0].shape[1], frames[0].shape[0])
    return _Raw(frames, chosen, chosen / fps, fps, size, len(usable), notes, kind="images")


def _gif_frames(path: Path) -> Iterator[tuple[float, Any]]:
    """(start time in seconds, the PIL image positioned on that frame) for each frame of an animated GIF;
    convert a frame before asking for the next one."""
    from PIL import Image, ImageSequence

    with Image.open(path) as img:
        t = 0.0
        for frame in ImageSequence.Iterator(img):
            yield t, frame
            # Browsers treat a missing or zero delay as 0.1 s; so do we.
            t += (frame.info.get("duration") or 100) / 1000.0


def _read_gif(path: Path, params: ClipParams) -> _Raw:
    thin = _Thinner(params.frame_stride, params.max_frames)
    times: list[float] = []
    n_window = 0
    try:
        for t, frame in _gif_frames(path):
            times.append(t)
            if not (params.start_s is None or t >= params.start_s - 5e-7):
                continue
            if params.end_s is not None and t > params.end_s + 5e-7:
                break
            if thin.wants(n_window):
                thin.add(len(times) - 1, _to_rgb(frame))
            n_window += 1
    except WonderError:
        raise
    except Exception as e:  # PIL raises OSError, EOFError, SyntaxError, ... for broken GIFs
        raise WonderError(f"{path}: cannot read GIF ({_short_reason(e)})") from e
    if not thin.items:
        raise WonderError(f"{path}: no frames {_window_text(params)} ({len(times)} frames)")
    idx = np.array([i for i, _ in thin.items])
    keep = _pick_evenly(len(idx), params.max_frames)
    frames = [thin.items[k][1] for k in keep]
    steps = np.diff(times) if len(times) > 1 else np.array([0.1])
    fps = 1.0 / float(np.mean(steps)) if np.mean(steps) > 0 else 10.0
    all_times = np.asarray(times)
    size = (frames[0].shape[1], frames[0].shape[0])
    return _Raw(frames, idx[keep], all_times[idx[keep]], fps, size, n_window, [], kind="gif")


class _DropScaleWarning(logging.Filter):
    """imageio-ffmpeg warns whenever the frames read differ in size from the source; we scale on purpose."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("The frame size for reading")


_SCALE_FILTER = _DropScaleWarning()


def _quiet_imageio_ffmpeg() -> None:
    logger = logging.getLogger("imageio_ffmpeg")
    if _SCALE_FILTER not in logger.filters:
        logger.addFilter(_SCALE_FILTER)


def _probe_video(path: Path) -> dict:
    """ffmpeg's header for a video file: fps, size (after any rotation metadata is applied), duration."""
    import imageio_ffmpeg

    _quiet_imageio_ffmpeg()
    gen = imageio_ffmpeg.read_frames(str(path))
    try:
        return next(gen)
    finally:
        gen.close()


def _read_video(path: Path, params: ClipParams) -> _Raw:
    import imageio_ffmpeg

    notes: list[str] = []
    try:
        meta = _probe_video(path)
    except Exception as e:  # ffmpeg failures surface as OSError/RuntimeError, odd headers as IndexError/ValueError
        raise WonderError(f"{path}: cannot read video ({_short_reason(e)})") from e
    width, height = meta["size"]
    fps = float(meta.get("fps") or 0.0)
    if fps <= 0:
        fps = params.image_fps
        notes.append(f"frame rate unknown, assumed {fps:g} fps")
    # ffmpeg seeks to start_s and stops at end_s itself (no decoding of what is outside the window),
    # and scales while decoding, so a long 4K phone video never crosses the pipe at full size.
    start = params.start_s or 0.0
    inp: list[str] = []
    if params.start_s is not None:
        inp += ["-ss", f"{params.start_s:.6f}"]
    if params.end_s is not None:
        inp += ["-t", f"{params.end_s - start:.6f}"]
    target = _target_size(width, height, params.max_side_px)
    out = ["-vf", f"scale={target[0]}:{target[1]}:flags=lanczos"] if target != (width, height) else []
    thin = _Thinner(params.frame_stride, params.max_frames)
    n_window = 0
    try:
        gen = imageio_ffmpeg.read_frames(str(path), input_params=inp, output_params=out)
        try:
            meta_out = next(gen)
            w_out, h_out = meta_out["size"]
            for i, buf in enumerate(gen):
                if thin.wants(i):
                    thin.add(i, np.frombuffer(buf, dtype=np.uint8).reshape(h_out, w_out, 3).copy())
                n_window = i + 1
        finally:
            gen.close()
    except Exception as e:
        raise WonderError(f"{path}: cannot read video ({_short_reason(e)})") from e
    if not thin.items:
        dur = meta.get("duration")
        length = f"; the video is {dur:g} s long" if isinstance(dur, int | float) and math.isfinite(dur) else ""
        raise WonderError(f"{path}: no frames {_window_text(params)}{length}")
    short = _ends_early(meta, fps, n_window, params)
    if short:
        notes.append(short)
    idx = np.array([i for i, _ in thin.items])
    keep = _pick_evenly(len(idx), params.max_frames)
    frames = [thin.items[k][1] for k in keep]
    return _Raw(frames, idx[keep], start + idx[keep] / fps, fps, (width, height), n_window, notes, kind="video")


def _ends_early(meta: dict, fps: float, decoded: int, params: ClipParams) -> str:
    """A note when a whole video decoded to fewer frames than its header announces (duration x fps): a truncated
    file (a copy cut short) whose frames before the cut are used; "" otherwise, or when a time window was asked."""
    duration = meta.get("duration")
    if params.start_s is not None or params.end_s is not None or not isinstance(duration, int | float):
        return ""
    expected = round(float(duration) * fps) if math.isfinite(duration) and duration > 0 else 0
    if expected - decoded < max(2, TRUNCATED_SHARE * expected):
        return ""
    return (
        f"the file ends after {decoded} of the {expected} frames its header announces ({decoded / fps:.1f} of "
        f"{duration:g} s; truncated?): those {decoded} are used"
    )


# ---------------------------------------------------------------------------------------------- public


def read_clip(source: ClipSource, params: ClipParams | None = None) -> Clip:
    """One clip from a video file (mp4/mov/webm/avi/mkv, any container ffmpeg reads), an animated GIF, a folder
    of images (natural order: frame2 before frame10), a glob pattern of images, or a list of image files.

    Returns frames (T,H,W,3) uint8 RGB with even H, W (longer side <= max_side_px, never upscaled), T >= 2
    (at most max_frames, picked evenly after the time window and the stride), K (3,3) float64 pixels for those
    frames (pixel centres at +0.5), from `intrinsics` (the camera's own K), `fov_deg` (cx = W/2) or else from
    `guess_fov_deg` (k_is_guess=True).
    Image folders whose frames differ in size are resized to the first frame's size when the shape (aspect
    ratio) matches within `max_aspect_mismatch`, with a note. In a folder of several shapes, images of the main
    shape transposed (landscape shots among portrait ones) are turned a quarter counter-clockwise and kept (the
    same camera on its side), images of any other shape are left out, each with a note naming them; a folder
    with no two images one camera can take raises, since stretching would bend the geometry.
    Raises WonderError (one line naming the file) for a missing path, an empty folder, an unreadable or corrupt
    file, and a clip with fewer than 2 frames.
    """
    params = params or ClipParams()
    name, what = _expand(source)
    if isinstance(what, list):
        raw = _read_images(name, what, params)
        raw.notes.extend(_other_files(name, what))
    elif what.suffix.lower() in IMAGE_SUFFIXES:
        raise WonderError(f"{what}: a single image; a clip needs at least 2 frames (pass a folder or a video)")
    elif what.suffix.lower() in GIF_SUFFIXES:
        raw = _read_gif(what, params)
    else:
        raw = _read_video(what, params)
    return _finish(name, raw, params)


def _finish(name: str, raw: _Raw, params: ClipParams) -> Clip:
    """Resize to the target size, build K and the notes, and refuse clips of fewer than 2 frames."""
    if len(raw.frames) < 2:
        where = "" if params.start_s is None and params.end_s is None else f" {_window_text(params)}"
        raise WonderError(f"{name}: only 1 frame{where}; a clip needs at least 2 frames to reconstruct from")
    notes = list(raw.notes)
    src_w, src_h = raw.source_size
    target = _target_size(src_w, src_h, params.max_side_px)

    frames = np.stack([_resize(f, target) for f in raw.frames])
    if target != (src_w, src_h):
        notes.append(f"resized {src_w}x{src_h} -> {target[0]}x{target[1]}")

    n_strided = -(-raw.window_frames // params.frame_stride)
    if params.frame_stride > 1:
        notes.append(f"frame stride {params.frame_stride}: {raw.window_frames} -> {n_strided} frames")
    if len(frames) < n_strided:
        notes.append(f"subsampled {n_strided} -> {len(frames)} frames")
    if params.start_s is not None or params.end_s is not None:
        notes.append(f"frames {_window_text(params)}")

    if params.intrinsics is not None:  # the camera's own K, in the source frames' pixels
        fx, fy, cx, cy = params.intrinsics
        if not (cx < src_w and cy < src_h):
            raise WonderError(f"{name}: the principal point ({cx:g}, {cy:g}) lies outside its {src_w}x{src_h} frames")
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    else:
        fov = params.fov_deg if params.fov_deg is not None else params.guess_fov_deg
        if params.fov_deg is None:
            notes.append(f"intrinsics unknown: guessed a {fov:g} deg horizontal field of view")
        aspect = pixel_aspect(raw.kind, src_w, src_h, params.pixel_aspect)
        if aspect != 1.0:
            how = "set" if params.pixel_aspect != "auto" else "assumed for 3:2 video (16:9 footage resized)"
            notes.append(f"pixels not square: fy/fx = {aspect:.4g} {how}")
        K = intrinsics(src_w, src_h, fov)
        K[1, 1] *= aspect
    # K of the source frame, scaled to the returned size (the aspect may change by under a pixel when rounding
    # to even sizes, so fx and fy scale separately and stay exact).
    sx, sy = target[0] / src_w, target[1] / src_h
    K = np.diag([sx, sy, 1.0]) @ K

    span = int(raw.source_indices[-1] - raw.source_indices[0])
    fps = raw.source_fps * (len(frames) - 1) / span if span > 0 else raw.source_fps
    return Clip(
        frames=frames,
        fps=float(fps),
        source=name,
        K=K,
        k_is_guess=params.fov_deg is None and params.intrinsics is None,
        times_s=np.asarray(raw.times_s, dtype=np.float64),
        notes=notes,
    )


def pixel_aspect(kind: str, width: int, height: int, setting: float | Literal["auto"]) -> float:
    """fy/fx of a clip's source pixels: the setting, or for "auto" `RESIZED_16_9_TO_3_2` when a video or GIF
    (`kind`) has 3:2 frames (width:height within 1 %), else 1. A still camera does shoot 3:2, so image folders
    stay square. Measured on the seven RealEstate10K clips at 384x256 (pose files: fx 182-195 px, fy/fx
    32/27): holding 32/27 took the guessed-K check from 0.17-2.55 % ATE to 0.08-0.93 % (`wonderverse.sfm`)."""
    if setting != "auto":
        return float(setting)
    if kind in ("video", "gif") and abs(width / height - 1.5) <= 0.01 * 1.5:
        return RESIZED_16_9_TO_3_2
    return 1.0


def _ratio(w: int, h: int) -> str:
    """'4:3' for 4032x3024."""
    d = math.gcd(w, h)
    return f"{w // d}:{h // d}"


def _to_size(clip: Clip, first: Clip, params: ClipParams) -> Clip:
    """`clip` at the frame size of the scene's first clip: the stitched video, the global solve (one camera), the
    priors, the splats and every export hold one size. A clip of the same shape (aspect within
    `max_aspect_mismatch`) is resized, its K scaled with it, and says so; another shape raises WonderError naming
    both clips (stretching would bend the geometry)."""
    h, w = clip.frames.shape[1:3]
    h0, w0 = first.frames.shape[1:3]
    if (w, h) == (w0, h0):
        return clip
    if not _same_shape((w, h), (w0, h0), params.max_aspect_mismatch):
        raise WonderError(
            f"{clip.name}: its frames are {w}x{h} ({_ratio(w, h)}) but those of the first clip, {first.name}, are "
            f"{w0}x{h0} ({_ratio(w0, h0)}); a scene's clips need one shape (one camera): crop them to one shape, "
            "or reconstruct them apart"
        )
    frames = np.stack([_resize(f, (w0, h0)) for f in clip.frames])
    K = np.diag([w0 / w, h0 / h, 1.0]) @ clip.K
    notes = [*clip.notes, f"resized {w}x{h} -> {w0}x{h0}, the size of the first clip ({first.name})"]
    return Clip(frames, clip.fps, clip.source, K, clip.k_is_guess, clip.times_s, notes)


def group_sources(args: Sequence[str | Path]) -> list[ClipSource]:
    """Clip sources from command-line arguments: runs of consecutive image files (what a shell makes of
    `frames/*.png`) become one image-sequence clip; every other argument is a clip of its own."""
    out: list[ClipSource] = []
    run: list[Path] = []
    for a in args:
        p = Path(a)
        if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file():
            run.append(p)
            continue
        if run:
            out.append(run if len(run) > 1 else run[0])
            run = []
        out.append(a)
    if run:
        out.append(run if len(run) > 1 else run[0])
    return out


class FilesVideo:
    """The user's clips as a video model: segment i is clip i. Clips are read (and checked) when constructed.

    skip_unreadable: drop clips that cannot be read (listed in `skipped` as (source, reason)) instead of
    raising; raises anyway when no clip is left.
    """

    def __init__(
        self, sources: Sequence[ClipSource], params: ClipParams | None = None, skip_unreadable: bool = False
    ) -> None:
        self.params = params or ClipParams()
        self.skipped: list[tuple[str, str]] = []
        self._clips: list[Clip] = []
        if not sources:
            raise WonderError("no clips given")
        for s in sources:
            try:
                self._clips.append(read_clip(s, self.params))
            except WonderError as e:
                if not skip_unreadable:
                    raise
                self.skipped.append((str(s if isinstance(s, str | Path) else s[0]), str(e)))
        if not self._clips:
            raise WonderError(f"none of the {len(sources)} clips could be read: {self.skipped[0][1]}")
        self._clips = [_to_size(c, self._clips[0], self.params) for c in self._clips]

    @property
    def clips(self) -> list[Clip]:
        """The clips read, in the order given (skipped ones left out)."""
        return list(self._clips)

    takes_guide = False  # a user's clip is read, never generated: no guide can shape it

    def __len__(self) -> int:
        return len(self._clips)

    def segment(self, i: int) -> Video:
        """Clip i as a Video: its frames and K (a guess unless fov_deg was given); no ground truth."""
        if not 0 <= i < len(self._clips):
            raise IndexError(f"segment {i} of {len(self._clips)} clips")
        c = self._clips[i]
        return Video(frames=c.frames, K=c.K.copy(), gt=None, k_is_guess=c.k_is_guess)

    def generate(
        self, prompt: str, path: np.ndarray, seed: int, reference: np.ndarray | None, guide: Guide | None = None
    ) -> Video:
        """Always raises: a user's clip is what it is and cannot be generated again (use `segment`), guided or not
        (`takes_guide` is False: clips take no guide)."""
        raise WonderError(
            "clips given by the user cannot be regenerated; a clip that fails its check is dropped or kept"
        )
