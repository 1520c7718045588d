"""The scene report: one self-contained HTML page a person reads to see what a run did.

`ReportContent` holds what the page shows (plain values and PNG bytes; it knows nothing of the store);
`render_html` turns it into one HTML document with inline CSS, every image inlined as a base64 data URI,
no scripts and no external resources, so the file can be mailed, archived or opened offline. The only
things it points to are files beside it: the links of the file table and the scene's videos, which play
in the page (`<video src="novel.mp4">`, relative) while their stills are inlined like every image. All
text is escaped (prompts and intents are user input). `curves_plot` and `depth_normal_preview` draw the
two figures the check/trajectory plots of `wonderverse.plots` do not cover; `video_stills` reads frames
of an mp4.
"""

from __future__ import annotations

import base64
import html
import io
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

Value = float | int | str | bool | None


class ReportParams(BaseModel):
    """How much the report shows (sizes in pixels)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    preview_frames: int = Field(3, ge=1, le=16, description="frames per segment in the depth/normal preview")
    preview_thumb_width_px: int = Field(200, ge=32, le=1024, description="width of one preview tile")
    overview_frames: int = Field(24, ge=1, le=256, description="stitched frames in the overview sheet")
    curve_smooth_frac: float = Field(0.02, ge=0, le=0.5, description="moving-average window, share of iterations")
    scene_stills: int = Field(4, ge=1, le=16, description="evenly spaced frames shown of each scene video")
    still_width_px: int = Field(240, ge=32, le=1024, description="width of one still of a scene video")
    mesh_view_width_px: int = Field(480, ge=32, le=2048, description="width of the mesh pictures")
    mesh_supersample: int = Field(2, ge=1, le=4, description="rays per pixel side of the mesh pictures")


# -- content -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Picture:
    """A PNG (or JPEG) image and its caption."""

    data: bytes
    caption: str = ""


@dataclass
class AttemptInfo:
    """One generation attempt of a segment and its check.

    accepted: the check's verdict (None: not checked yet); chosen: the attempt later steps follow;
    fault: the fault the procedural world injected (ground truth, diagnostics only), "" for none, None
    when unknown; metrics: ground-truth figures (e.g. SfM ATE) by name; guide: the guide a guided extension was
    generated from, in words ("71 % of pixels known, from segment s000, attempt 0", or "none: " and why), None
    for an attempt that looked for no guide; guide_coverage: that guide's share of known pixels (0..1)."""

    index: int
    seed: int | None = None
    accepted: bool | None = None
    chosen: bool = False
    reasons: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    flagged_frames: list[int] = field(default_factory=list)
    registered_frac: float | None = None
    sfm_seconds: float | None = None
    fault: str | None = None
    metrics: dict[str, Value] = field(default_factory=dict)
    check_plot: bytes | None = None
    topview: bytes | None = None
    guide: str | None = None
    guide_coverage: float | None = None


# A clip's verdict (as `inspect --json` gives it) in words.
CLIP_VERDICTS = {
    "accepted": "accepted",
    "kept_failing": "kept although it failed its check",
    "recovered": "recovered by the global solve (its check failed)",
    "dropped": "dropped by its check",
    "unchecked": "not checked yet",
    "unread": "not read yet",
}
# What a clip's source is, in words.
CLIP_KINDS = {"video": "video file", "folder": "image folder", "pattern": "images matching a pattern"}
# Where a clip's K came from, in words.
K_SOURCES = {
    "given": "given (--fov-deg or --intrinsics)",
    "estimated": "estimated from the clip",
    "guessed": "guessed",
}


@dataclass(frozen=True)
class ClipInfo:
    """One of the user's clips (video backend `files`; one segment each, in the order given).

    name: the file or folder name; kind: "video", "folder" (of images) or "pattern" (a glob of images);
    folder: where it lives; frames: frames used (None: not read yet); width, height: their size in pixels;
    k_source: "given", "estimated" or "guessed"; fov_deg: horizontal field of view of that K; verdict: a key
    of CLIP_VERDICTS; reasons: the check's, in words."""

    segment: str
    name: str
    kind: str = "video"
    folder: str = ""
    frames: int | None = None
    width: int | None = None
    height: int | None = None
    k_source: str | None = None
    fov_deg: float | None = None
    verdict: str = "unread"
    reasons: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()  # what reading it did to it (subsampled, images left out, resized, assumed)

    @property
    def label(self) -> str:
        """The name as a person reads it: folders end with a slash."""
        return self.name + ("/" if self.kind == "folder" else "")

    @property
    def k_words(self) -> str:
        if self.k_source is None:
            return "–"
        fov = f", {self.fov_deg:.1f}° horizontal field of view" if self.fov_deg is not None else ""
        return K_SOURCES.get(self.k_source, self.k_source) + fov


@dataclass
class SegmentInfo:
    """One planned segment: its plan entry, status in words, attempts, and prior previews; `clip` for a
    segment that is one of the user's clips (no plan entry: nothing was planned or generated)."""

    id: str
    role: str = ""
    move: str = ""
    intent: str = ""
    reference: str = ""
    status: str = ""
    status_ok: bool | None = None  # True accepted, False rejected/dropped, None undecided
    frames: int | None = None
    attempts: list[AttemptInfo] = field(default_factory=list)
    previews: list[Picture] = field(default_factory=list)
    metrics: dict[str, Value] = field(default_factory=dict)
    clip: ClipInfo | None = None


@dataclass(frozen=True)
class StepTiming:
    """A pipeline step: its state in the store and how long its last run took (None: not recorded)."""

    step: str
    status: str
    seconds: float | None = None
    description: str = ""


@dataclass(frozen=True)
class VideoClip:
    """A video beside the report, played in the page: `href` is relative to the report; `stills` a
    contact sheet of a few of its frames (inlined, so the page shows the scene where the video cannot play)."""

    href: str
    title: str
    width: int
    height: int
    frames: int
    seconds: float
    stills: Picture | None = None


@dataclass(frozen=True)
class FileEntry:
    """A file or folder beside the store; `path` is relative to the report."""

    path: str
    size_bytes: int
    is_dir: bool = False
    description: str = ""


@dataclass
class ReportContent:
    """Everything the report shows. Sections with nothing in them say so instead of disappearing.

    facts: short label -> value lines for the summary table (settings, headline figures).
    metrics: group title -> {name: value}, e.g. ground-truth errors or the splats' PSNR.
    curves: training curves, name -> one value per iteration.
    videos, mesh_views, scene_notes: the 3D result (renders of the splats, pictures of the mesh) and one
    line for each thing of it that is missing.
    clips: the user's clips in order (video backend `files`), shown in place of the plan; None for a generated
    scene. priors_note: one line when the scene has no depth or normal prior (shown in the summary and where
    the previews would be).
    state: a fingerprint of what the report was made from, written into the page (see `STATE_META`)."""

    title: str
    prompt: str
    facts: dict[str, Value] = field(default_factory=dict)
    planner: str = ""
    plan_note: str = ""
    segments: list[SegmentInfo] = field(default_factory=list)
    overview: Picture | None = None
    trajectory: Picture | None = None
    videos: list[VideoClip] = field(default_factory=list)
    mesh_views: list[Picture] = field(default_factory=list)
    scene_notes: list[str] = field(default_factory=list)
    planned_paths: Picture | None = None
    timings: list[StepTiming] = field(default_factory=list)
    growth: Picture | None = None
    metrics: dict[str, dict[str, Value]] = field(default_factory=dict)
    curves: dict[str, list[float]] = field(default_factory=dict)
    curves_note: str = ""
    files: list[FileEntry] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    generated: str = ""
    state: str = ""
    clips: list[ClipInfo] | None = None
    priors_note: str = ""


# -- figures -------------------------------------------------------------------------------------


def _moving_average(y: np.ndarray, window: int) -> np.ndarray:
    """Centred-ish running mean ignoring NaNs; the first values average what exists so far."""
    if window <= 1 or len(y) < 3:
        return y
    ok = np.isfinite(y)
    c = np.concatenate([[0.0], np.cumsum(np.where(ok, y, 0.0))])
    n = np.concatenate([[0], np.cumsum(ok)])
    idx = np.arange(1, len(y) + 1)
    lo = np.maximum(0, idx - window)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (c[idx] - c[lo]) / (n[idx] - n[lo])


def curves_figure(curves: Mapping[str, Sequence[float]], smooth_frac: float = 0.02, cols: int = 4) -> Any:
    """Small multiples: one panel per curve against the iteration (raw values faint, running mean solid).

    Returns the matplotlib Figure (Agg-ready, no pyplot)."""
    from matplotlib.figure import Figure

    names = [k for k, v in curves.items() if len(v)]
    if not names:
        raise ValueError("no training curves to plot")
    cols = min(cols, len(names))
    rows = -(-len(names) // cols)
    # Fixed margins instead of constrained layout: with a dozen panels the layout solver took seconds.
    fig = Figure(figsize=(3.2 * cols, 2.3 * rows), dpi=100)
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.6 / (2.3 * rows), top=1 - 0.35 / (2.3 * rows))
    fig.subplots_adjust(hspace=0.55, wspace=0.3)
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax, name in zip(axes, names, strict=False):
        y = np.asarray(curves[name], dtype=np.float64)
        x = np.arange(len(y))
        window = max(1, round(smooth_frac * len(y)))
        ax.plot(x, y, color="tab:blue", alpha=0.3 if window > 1 else 1.0, lw=0.8)
        if window > 1:
            ax.plot(x, _moving_average(y, window), color="tab:blue", lw=1.4)
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)
    for ax in axes[len(names) :]:
        ax.set_visible(False)
    fig.supxlabel("iteration", fontsize=9, y=0.1 / (2.3 * rows))
    return fig


def curves_plot(curves: Mapping[str, Sequence[float]], smooth_frac: float = 0.02) -> bytes:
    """PNG bytes of `curves_figure`."""
    from wonderverse.plots import _png

    return _png(curves_figure(curves, smooth_frac))


def colorize_depth(depth: np.ndarray) -> np.ndarray:
    """(H,W) camera-z depth -> (H,W,3) uint8: inverse depth through the turbo colour map (near = warm),
    stretched between the 2nd and 98th percentile of the image; sky (+inf), holes and depth <= 0 dark grey."""
    from matplotlib import colormaps

    d = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0)
    out = np.full((*d.shape, 3), 40, np.uint8)
    if ok.any():
        inv = 1.0 / d[ok]
        lo, hi = np.percentile(inv, [2, 98])
        t = np.clip((inv - lo) / (hi - lo), 0, 1) if hi > lo else np.full_like(inv, 0.5)
        out[ok] = (colormaps["turbo"](t)[:, :3] * 255).round().astype(np.uint8)
    return out


def colorize_normals(normals: np.ndarray) -> np.ndarray:
    """(H,W,3) camera-space normals in OpenCV axes -> (H,W,3) uint8 as ((x, -y, -z) + 1) / 2, the usual
    normal-map look (facing the camera = blue, up = green); missing (zero/NaN) normals grey."""
    n = np.asarray(normals, dtype=np.float64) * [1.0, -1.0, -1.0]
    ok = np.isfinite(n).all(-1) & (np.linalg.norm(np.nan_to_num(n), axis=-1) > 1e-6)
    out = np.full((*n.shape[:2], 3), 128, np.uint8)
    out[ok] = ((np.clip(n[ok], -1, 1) + 1) * 127.5).round().astype(np.uint8)
    return out


def depth_normal_preview(
    frames: np.ndarray,
    depth: np.ndarray,
    normals: np.ndarray,
    labels: Sequence[str],
    gt_depth: np.ndarray | None = None,
    gt_normals: np.ndarray | None = None,
    thumb_width_px: int = 200,
) -> bytes:
    """PNG bytes of a grid: one row per frame (labelled), columns RGB | depth | normals (| GT depth |
    GT normals when given). frames (N,H,W,3) uint8, depth (N,H,W) camera z, normals (N,H,W,3)."""
    from PIL import Image, ImageDraw

    cols: list[tuple[str, list[np.ndarray]]] = [
        ("frame", [np.asarray(f, np.uint8) for f in frames]),
        ("depth prior", [colorize_depth(d) for d in depth]),
        ("normal prior", [colorize_normals(n) for n in normals]),
    ]
    if gt_depth is not None:
        cols.append(("GT depth", [colorize_depth(d) for d in gt_depth]))
    if gt_normals is not None:
        cols.append(("GT normals", [colorize_normals(n) for n in gt_normals]))
    n = len(frames)
    if n == 0 or any(len(imgs) != n for _, imgs in cols) or len(labels) != n:
        raise ValueError("frames, depth, normals, ground truth and labels must all have the same length > 0")
    h, w = frames.shape[1:3]
    tw, th = thumb_width_px, max(1, round(thumb_width_px * h / w))
    head, side, gap = 18, 70, 4
    sheet = Image.new("RGB", (side + len(cols) * (tw + gap), head + n * (th + gap)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for c, (title, imgs) in enumerate(cols):
        x = side + c * (tw + gap)
        draw.text((x + 2, 3), title, fill=(40, 40, 40))
        for r, img in enumerate(imgs):
            sheet.paste(Image.fromarray(img).resize((tw, th), Image.BILINEAR), (x, head + r * (th + gap)))
    for r, label in enumerate(labels):
        draw.text((4, head + r * (th + gap) + th // 2 - 6), label, fill=(40, 40, 40))
    buf = io.BytesIO()
    sheet.save(buf, format="PNG")
    return buf.getvalue()


def video_stills(path: Path | str, count: int) -> tuple[np.ndarray, list[int], int, float]:
    """`count` evenly spaced frames of a video (first and last included; fewer when it is shorter).

    Returns frames (n,H,W,3) uint8, their indices, the video's frame count and its duration in seconds
    (from the container, as ffmpeg counts them). Decodes once, up to the last frame wanted (ffmpeg from
    imageio-ffmpeg). Raises ValueError for a video with no frame and OSError/RuntimeError when ffmpeg
    cannot read the file."""
    import imageio_ffmpeg

    path = str(path)
    n, seconds = imageio_ffmpeg.count_frames_and_secs(path)
    if n < 1:
        raise ValueError(f"{path} holds no video frame")
    picks = sorted({int(i) for i in np.linspace(0, n - 1, min(count, n)).round()})
    reader = imageio_ffmpeg.read_frames(path)
    try:
        w, h = next(reader)["size"]
        out = []
        for i, buf in enumerate(reader):
            if i in picks:
                out.append(np.frombuffer(buf, np.uint8).reshape(h, w, 3).copy())
            if i >= picks[-1]:
                break
    finally:
        reader.close()
    if len(out) != len(picks):  # the container's frame count promised more than the stream held
        picks = picks[: len(out)]
    if not out:
        raise ValueError(f"{path}: no frame could be decoded")
    return np.stack(out), picks, int(n), float(seconds)


def png_bytes(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H,W,3) uint8 image."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(rgb, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


# -- HTML ----------------------------------------------------------------------------------------

# The fingerprint of the store state a report was made from, as `<meta name=... content=SHA256>` in its
# head (first bytes of the file): a cached re-run compares it and leaves an up-to-date report alone.
STATE_META = "wonderverse-state"

CSS = """
*{box-sizing:border-box}
body{margin:0;background:#f4f5f7;color:#1c2230;font:15px/1.5 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif}
header{background:#1c2a45;color:#fff;padding:22px 32px 14px}
header h1{margin:0 0 4px;font-size:24px;font-weight:600}
header .sub{color:#b9c6de;font-size:13px}
nav{margin-top:12px}nav a{color:#d5e2ff;margin-right:16px;font-size:14px;text-decoration:none}
nav a:hover{text-decoration:underline}
main{max-width:1200px;margin:0 auto;padding:8px 24px 48px}
section{background:#fff;border-radius:8px;box-shadow:0 1px 3px rgba(20,30,50,.1);padding:14px 24px 18px;margin:18px 0}
h2{font-size:19px;margin:6px 0 12px;border-bottom:1px solid #e4e7ec;padding-bottom:6px}
h3{font-size:16px;margin:20px 0 8px}
h4{font-size:14px;margin:14px 0 6px;color:#3b4457}
blockquote.prompt{margin:0 0 14px;padding:10px 16px;background:#f0f4fb;border-left:4px solid #4a6fb5;
 font-size:16px;white-space:pre-wrap;overflow-wrap:anywhere}
table{border-collapse:collapse;width:100%;margin:6px 0 10px;font-size:14px}
th,td{padding:5px 10px;border-bottom:1px solid #e8eaef;text-align:left;vertical-align:top;overflow-wrap:anywhere}
th{background:#f7f8fa;font-weight:600;color:#3b4457}
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
table.kv th{width:220px}
table.clips th,table.clips td.num,table.clips td:first-child{white-space:nowrap}
table.clips td:nth-child(2){min-width:180px}table.clips td:nth-child(5){min-width:170px}
.badge{display:inline-block;padding:1px 9px;border-radius:10px;font-size:12px;font-weight:600;white-space:nowrap}
.ok{background:#dcf2e3;color:#13602f}.bad{background:#fbe1de;color:#9d2418}.muted{background:#eceef2;color:#555d6b}
.chosen{background:#e1e9fb;color:#23479a}
.bar{height:10px;background:#6f8fd0;border-radius:3px;min-width:1px}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(340px,1fr));gap:12px}
figure{margin:8px 0}figure img{max-width:100%;height:auto;border:1px solid #e4e7ec;border-radius:4px;display:block}
figcaption{font-size:13px;color:#5a6272;margin-top:3px}
.note{background:#fff8e1;border:1px solid #f1dfa4;border-radius:6px;padding:8px 14px;margin:10px 0;font-size:14px}
.empty{color:#6b7280;font-style:italic}
ul.reasons{margin:0;padding-left:18px}
p.meta{margin:0 0 8px;color:#4b5363;font-size:14px}
.attempt{display:grid;grid-template-columns:4fr 3fr;gap:12px;align-items:start}
.cols{display:grid;grid-template-columns:repeat(auto-fill,minmax(440px,1fr));gap:0 24px}
video{width:100%;height:auto;display:block;background:#111;border-radius:4px}
footer{text-align:center;color:#8a91a0;font-size:12px;padding:10px}
"""


def esc(text: Any) -> str:
    """HTML-escaped text (quotes too, so it is safe in attributes)."""
    return html.escape("" if text is None else str(text), quote=True)


def fmt(v: Value) -> str:
    """A value in words: yes/no, thousands separators, 4 significant digits, '–' for missing/NaN."""
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int | np.integer):
        return f"{int(v):,}"
    if isinstance(v, float | np.floating):
        v = float(v)
        if not math.isfinite(v):
            return "–" if math.isnan(v) else str(v)
        return f"{v:,.0f}" if abs(v) >= 1e4 else f"{v:.4g}"
    return str(v)


def fmt_seconds(s: float | None) -> str:
    if s is None or not math.isfinite(s):
        return "–"
    if s < 60:
        return f"{s:.1f} s" if s >= 0.1 else f"{s * 1000:.0f} ms"
    m, sec = divmod(round(s), 60)
    return f"{m} min {sec:02d} s" if m < 60 else f"{m // 60} h {m % 60:02d} min"


def fmt_bytes(n: int) -> str:
    """A size in decimal units (1 kB = 1000 B, 1 MB = 1e6 B), as `wonderverse inspect` prints them."""
    size = float(n)
    for unit in ("B", "kB", "MB", "GB"):
        if round(size, 1) < 1000 or unit == "GB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1000
    return f"{n} B"


def image_size(data: bytes) -> tuple[str, int, int]:
    """(mime type, width, height) of PNG or JPEG bytes; ValueError for anything else."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return "image/png", w, h
    if data[:2] == b"\xff\xd8":
        i = 2
        while i + 9 < len(data):
            if data[i] != 0xFF:
                break
            marker, length = data[i + 1], struct.unpack(">H", data[i + 2 : i + 4])[0]
            if marker in (0xC0, 0xC1, 0xC2):
                h, w = struct.unpack(">HH", data[i + 5 : i + 9])
                return "image/jpeg", w, h
            i += 2 + length
    raise ValueError("report images must be PNG or JPEG bytes")


def img_tag(data: bytes, alt: str) -> str:
    """An <img> with the image inlined as a base64 data URI and its intrinsic size."""
    mime, w, h = image_size(data)
    b64 = base64.b64encode(data).decode("ascii")
    return f'<img src="data:{mime};base64,{b64}" width="{w}" height="{h}" alt="{esc(alt)}">'


def _figure(data: bytes | None, caption: str) -> str:
    if not data:
        return ""
    return f"<figure>{img_tag(data, caption)}<figcaption>{esc(caption)}</figcaption></figure>"


def _badge(text: str, kind: str) -> str:
    return f'<span class="badge {kind}">{esc(text)}</span>'


def _kv_table(rows: Mapping[str, Value]) -> str:
    body = "".join(f"<tr><th>{esc(k)}</th><td>{esc(fmt(v))}</td></tr>" for k, v in rows.items())
    return f'<table class="kv">{body}</table>'


def _empty(text: str) -> str:
    return f'<p class="empty">{esc(text)}</p>'


def _verdict(a: AttemptInfo) -> str:
    if a.accepted is None:
        v = _badge("not checked", "muted")
    else:
        v = _badge("accepted", "ok") if a.accepted else _badge("rejected", "bad")
    return v + (" " + _badge("used", "chosen") if a.chosen else "")


def _reasons(a: AttemptInfo) -> str:
    items = [esc(r) for r in a.reasons] + [f"<i>note:</i> {esc(n)}" for n in a.notes]
    if a.flagged_frames:
        items.append(f"flagged frame pairs: {esc(', '.join(str(i) for i in a.flagged_frames))}")
    return '<ul class="reasons">' + "".join(f"<li>{i}</li>" for i in items) + "</ul>" if items else "–"


def _attempts_table(seg: SegmentInfo) -> str:
    metric_names = sorted({k for a in seg.attempts for k in a.metrics})
    generated = seg.clip is None  # a clip is read, not generated: it has no seed and no injected fault
    guided = any(a.guide is not None for a in seg.attempts)  # an extension of a guided flow
    head = ["attempt", "seed", "verdict", "reasons", "guide", "registered", "SfM time", "injected fault (GT)"]
    head += metric_names
    if not generated:
        head = [h for h in head if h not in ("seed", "injected fault (GT)")]
    if not guided:
        head.remove("guide")
    rows = []
    for a in seg.attempts:
        reg = "–" if a.registered_frac is None else f"{100 * a.registered_frac:.0f} %"
        fault = "–" if a.fault is None else (a.fault or "none")
        cells = [
            f'<td class="num">{a.index}</td>',
            f'<td class="num">{esc(fmt(a.seed))}</td>' if generated else "",
            f"<td>{_verdict(a)}</td>",
            f"<td>{_reasons(a)}</td>",
            f'<td class="guide">{esc(a.guide or "–")}</td>' if guided else "",
            f'<td class="num">{esc(reg)}</td>',
            f'<td class="num">{esc(fmt_seconds(a.sfm_seconds))}</td>',
            f"<td>{esc(fault)}</td>" if generated else "",
            *(f'<td class="num">{esc(fmt(a.metrics.get(m)))}</td>' for m in metric_names),
        ]
        rows.append(f'<tr id="{esc(seg.id)}-a{a.index}">{"".join(cells)}</tr>')
    return "<table><tr>" + "".join(f"<th>{esc(h)}</th>" for h in head) + "</tr>" + "".join(rows) + "</table>"


def _segment_html(seg: SegmentInfo) -> str:
    kind = {True: "ok", False: "bad", None: "muted"}[seg.status_ok]
    if seg.clip is not None:
        c = seg.clip
        what = CLIP_KINDS.get(c.kind, c.kind)
        meta = [f"{what} in {c.folder}" if c.folder else what]
        if c.frames is not None:
            meta.append(f"{c.frames} frames" + (f", {c.width}×{c.height} px" if c.width else ""))
        meta.append(f"K {c.k_words}")
        title = f"{esc(seg.id)} · {esc(c.label)}"
    else:
        meta = [f"user's words: {seg.intent}" if seg.intent else "no user's words"]
        if seg.reference:
            meta.insert(0, f"starts from {seg.reference}")
        if seg.frames is not None:
            meta.append(f"{seg.frames} frames")
        title = f"{esc(seg.id)} · {esc(seg.role)} · {esc(seg.move)}"
    parts = [
        f'<h3 id="seg-{esc(seg.id)}">{title} {_badge(seg.status or "unknown", kind)}</h3>',
        f'<p class="meta">{esc(" · ".join(meta))}</p>',
    ]
    if seg.attempts:
        parts.append(_attempts_table(seg))
        for a in seg.attempts:
            label = f"{seg.id} attempt {a.index}"
            figs = _figure(a.check_plot, f"{label}: steps against the thresholds") + _figure(
                a.topview, f"{label}: SfM camera path from above"
            )
            if figs:
                parts.append(f'<div class="attempt">{figs}</div>')
        if not any(a.check_plot or a.topview for a in seg.attempts):
            parts.append(_empty("Not checked yet."))
    else:
        parts.append(_empty("Not generated yet."))
    if seg.metrics:
        parts.append("<h4>Against the ground truth</h4>" + _kv_table(seg.metrics))
    for p in seg.previews:
        parts.append(_figure(p.data, p.caption))
    return "".join(parts)


# A step's state (`flows.inspect.StepStatus`) as the report and `inspect` show it
STEP_STATE_WORDS = {"missing": "not run", "ran_then_failed": "ran, then the run failed"}


def _timings_html(timings: Sequence[StepTiming]) -> str:
    if not timings:
        return _empty("No steps recorded.")
    longest = max((t.seconds or 0.0 for t in timings), default=0.0) or 1.0
    kinds = {"complete": "ok", "ran_then_failed": "ok", "stale": "bad", "failed": "bad", "missing": "muted"}
    rows = []
    for t in timings:
        width = 0.0 if t.seconds is None else 100.0 * t.seconds / longest
        bar = f'<div class="bar" style="width:{width:.1f}%"></div>' if t.seconds is not None else ""
        state = _badge(STEP_STATE_WORDS.get(t.status, t.status), kinds.get(t.status, "muted"))
        rows.append(
            f"<tr><td>{esc(t.step)}</td><td>{state}</td>"
            f'<td class="num">{esc(fmt_seconds(t.seconds))}</td><td style="width:35%">{bar}</td>'
            f"<td>{esc(t.description)}</td></tr>"
        )
    total = sum(t.seconds for t in timings if t.seconds is not None)
    rows.append(f'<tr><th>total</th><th></th><th class="num">{esc(fmt_seconds(total))}</th><th></th><th></th></tr>')
    head = "<tr><th>step</th><th>state</th><th>time</th><th></th><th>what</th></tr>"
    note = ""
    if any(t.seconds is None and t.status != "missing" for t in timings):
        note = _empty("– : the time was not recorded (step run by an older WonderVerse).")
    return f"<table>{head}{''.join(rows)}</table>{note}"


def _plan_html(c: ReportContent) -> str:
    if not c.segments:
        return _empty("The plan step has not run yet.")
    head = "<tr><th>segment</th><th>role</th><th>camera move</th><th>user's words</th><th>starts from</th></tr>"
    rows = "".join(
        f'<tr><td><a href="#seg-{esc(s.id)}">{esc(s.id)}</a></td><td>{esc(s.role)}</td><td>{esc(s.move)}</td>'
        f"<td>{esc(s.intent or '–')}</td><td>{esc(s.reference or '–')}</td></tr>"
        for s in c.segments
    )
    planner = f"<p>Planner: {esc(c.planner or '–')}</p>"
    note = f'<div class="note">{esc(c.plan_note)}</div>' if c.plan_note else ""
    paths = _figure(c.planned_paths.data, c.planned_paths.caption) if c.planned_paths else ""
    return f"{planner}{note}<table>{head}{rows}</table>{paths}"


def _clips_html(c: ReportContent) -> str:
    """The user's clips in order: name, frames used, size, where K came from, the check's verdict."""
    if not c.clips:
        return _empty("No clips given.")
    kinds = {"accepted": "ok", "recovered": "ok", "kept_failing": "bad", "dropped": "bad"}
    head = "<tr><th>segment</th><th>clip</th><th>frames</th><th>size</th><th>K</th><th>check</th></tr>"
    rows = []
    for clip in c.clips:
        where = f'<br><span class="empty">{esc(clip.folder)}</span>' if clip.folder else ""
        size = f"{clip.width}×{clip.height} px" if clip.width else "–"
        reasons = "".join(f"<li>{esc(r)}</li>" for r in clip.reasons)
        verdict = _badge(CLIP_VERDICTS.get(clip.verdict, clip.verdict), kinds.get(clip.verdict, "muted")) + (
            f'<ul class="reasons">{reasons}</ul>' if reasons else ""
        )
        rows.append(
            f'<tr id="clip-{esc(clip.segment)}"><td><a href="#seg-{esc(clip.segment)}">{esc(clip.segment)}</a></td>'
            f'<td>{esc(clip.label)}{where}</td><td class="num">{esc(fmt(clip.frames))}</td>'
            f'<td class="num">{esc(size)}</td><td>{esc(clip.k_words)}</td><td>{verdict}</td></tr>'
        )
    note = (
        "<p>Each clip is one segment, in the order given; nothing was planned or generated, and a clip that "
        "fails its check cannot be regenerated. K is the one each clip's own check used; every output uses the "
        "global solve's (Metrics: intrinsics (K) every output uses).</p>"
    )
    read = "".join(
        f"<li>{esc(clip.segment)} {esc(clip.label)}: {esc('; '.join(clip.notes))}</li>"
        for clip in c.clips
        if clip.notes
    )
    how = f'<h3>How the clips were read</h3><ul class="read-notes">{read}</ul>' if read else ""
    return f'{note}<table class="clips">{head}{"".join(rows)}</table>{how}'


def _metrics_html(metrics: Mapping[str, Mapping[str, Value]]) -> str:
    if not metrics:
        return _empty("No metrics yet: they come with the check, poses, priors and splats steps.")
    blocks = "".join(f"<div><h3>{esc(group)}</h3>{_kv_table(values)}</div>" for group, values in metrics.items())
    return f'<div class="cols">{blocks}</div>'


def _files_html(files: Sequence[FileEntry]) -> str:
    if not files:
        return _empty("No files written beside the store yet.")
    rows = []
    for f in files:
        href = quote(f.path) + ("/" if f.is_dir and not f.path.endswith("/") else "")
        name = f.path + ("/" if f.is_dir and not f.path.endswith("/") else "")
        rows.append(
            f'<tr><td><a href="{esc(href)}">{esc(name)}</a></td><td class="num">{esc(fmt_bytes(f.size_bytes))}</td>'
            f"<td>{esc(f.description)}</td></tr>"
        )
    return "<table><tr><th>file</th><th>size</th><th>what</th></tr>" + "".join(rows) + "</table>"


def _video_html(v: VideoClip) -> str:
    # muted + playsinline: browsers let a muted video play inline without a user gesture; preload=metadata
    # reads only the header until someone presses play
    video = (
        f'<video controls muted loop playsinline preload="metadata" src="{esc(quote(v.href))}" '
        f'width="{v.width}" height="{v.height}"></video>'
    )
    what = f"{v.frames} frames, {fmt_seconds(v.seconds)}, {v.width}×{v.height} px"
    link = f'<a href="{esc(quote(v.href))}">{esc(v.href)}</a>'
    stills = _figure(v.stills.data, v.stills.caption) if v.stills else ""
    return f'<div><h3>{esc(v.title)}</h3>{video}<p class="meta">{link} · {esc(what)}</p>{stills}</div>'


def _scene_html(c: ReportContent) -> str:
    parts = []
    if c.videos:
        parts.append(f'<div class="cols">{"".join(_video_html(v) for v in c.videos)}</div>')
    if c.mesh_views:
        figs = "".join(_figure(p.data, p.caption) for p in c.mesh_views)
        parts.append(f'<h3>Mesh</h3><div class="cols">{figs}</div>')
    parts += [_empty(n) for n in c.scene_notes]
    return "".join(parts) or _empty("Nothing to show yet: the outputs step writes the videos and the mesh.")


def _summary_rows(c: ReportContent) -> dict[str, Value]:
    attempts = [a for s in c.segments for a in s.attempts]
    rows: dict[str, Value] = dict(c.facts)
    if c.priors_note:
        rows["priors"] = f"none — {c.priors_note}"
    if c.clips is not None:
        verdicts = [CLIP_VERDICTS.get(x.verdict, x.verdict) for x in c.clips]
        counts = ", ".join(f"{verdicts.count(v)} {v}" for v in dict.fromkeys(verdicts))
        rows["clips"] = f"{len(c.clips)} ({counts})" if c.clips else 0
    else:
        rows["segments"] = len(c.segments)
    if attempts and c.clips is None:
        rejected = sum(a.accepted is False for a in attempts)
        rows["attempts"] = f"{len(attempts)} ({rejected} rejected by the check)"
    done = [t for t in c.timings if t.status in ("complete", "ran_then_failed")]
    if c.timings:
        rows["steps complete"] = f"{len(done)} of {len(c.timings)}"
        rows["recorded run time"] = fmt_seconds(sum(t.seconds for t in c.timings if t.seconds is not None))
    return rows


def render_html(content: ReportContent, params: ReportParams | None = None) -> str:
    """The report as one HTML document (UTF-8 text; inline CSS, images as data URIs, no scripts; the only
    resources it loads are the videos beside it, by relative paths). Raises ValueError for images that are
    not PNG/JPEG."""
    p = params or ReportParams()
    c = content
    curves = {k: v for k, v in c.curves.items() if len(v)}
    curves_html = (
        _figure(curves_plot(curves, p.curve_smooth_frac), "training curves (faint: per iteration; solid: running mean)")
        if curves
        else _empty("The splats step has not run yet.")
    )
    if c.curves_note:
        curves_html += f'<p class="empty">{esc(c.curves_note)}</p>'
    segments = "".join(_segment_html(s) for s in c.segments) or _empty("No segments yet.")
    if c.priors_note:
        segments = _empty(f"No depth or normal previews: {c.priors_note}") + segments
    sections = [
        ("summary", "Summary", _kv_table(_summary_rows(c))),
        ("scene", "Scene", _scene_html(c)),
        ("clips", "Clips", _clips_html(c)) if c.clips is not None else ("plan", "Plan", _plan_html(c)),
        (
            "video",
            "Stitched video",
            (_figure(c.overview.data, c.overview.caption) if c.overview else _empty("No segment rendered yet."))
            + (_figure(c.trajectory.data, c.trajectory.caption) if c.trajectory else ""),
        ),
        (
            "steps",
            "Steps and timings",
            _timings_html(c.timings) + (_figure(c.growth.data, c.growth.caption) if c.growth else ""),
        ),
        ("segments", "Segments and their attempts" if c.clips is None else "Clips and their checks", segments),
        ("curves", "Training curves", curves_html),
        ("metrics", "Metrics", _metrics_html(c.metrics)),
        ("files", "Files", _files_html(c.files)),
    ]
    nav = "".join(f'<a href="#{sid}">{esc(title)}</a>' for sid, title, _ in sections)
    notes = "".join(f'<div class="note">{esc(n)}</div>' for n in c.notes)
    body = "".join(f'<section id="{sid}"><h2>{esc(title)}</h2>{inner}</section>' for sid, title, inner in sections)
    state = f'<meta name="{STATE_META}" content="{esc(c.state)}">' if c.state else ""
    return (
        "<!DOCTYPE html>\n"
        f'<html lang="en"><head><meta charset="utf-8">{state}'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        # An empty inline icon: without it a browser asks the server (or disk) for /favicon.ico.
        '<link rel="icon" href="data:,">'
        f"<title>{esc(c.title)}</title><style>{CSS}</style></head><body>"
        f'<header><h1>{esc(c.title)}</h1><div class="sub">{esc(c.generated)}</div><nav>{nav}</nav></header>'
        f'<main><blockquote class="prompt">{esc(c.prompt)}</blockquote>{notes}{body}</main>'
        "<footer>Written by WonderVerse. Every image is inside this file; the videos and the linked files are "
        "the ones beside it.</footer>"
        "</body></html>\n"
    )
